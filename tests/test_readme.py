"""Every example in README.md runs, verbatim (#33): a doctest-like runner over the fenced
``sh`` blocks. The commands run in order, in one scratch folder where ``examples/`` and
``tests/`` of this repository are linked in (the README's relative paths), with this
interpreter's ``opacityhull`` first on PATH; a line ending in ``&`` starts in the
background and is stopped when the run ends.

Each command is one of three kinds, decided by the tables below (nothing is left out
silently: a command in no table is slow, and every skip names its reason):

* :data:`FAST` — runs in ``make test`` (CI), in ``test_fast_readme_examples``;
* slow (the rest) — runs with the fast ones in ``test_every_readme_example``, marked
  ``readme_slow``: ``make test`` deselects it, ``make bench`` (``make readme``) runs it;
* :data:`SKIP` — not run, with the reason (placeholders for the reader's own files, a
  server that runs until Ctrl-C, the make targets that run this very file, lines whose
  inputs other work of #33 adds).
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"

#: Command prefixes that run in CI: each takes seconds, and needs only what the fast
#: commands before it made.
FAST = (
    "opacityhull sim scenes",
    "opacityhull sim explain",
    "opacityhull sim render",
    "opacityhull rig emulate",
    "opacityhull rig check",
    "opacityhull capture --rig examples/rig-emulated.toml --plan builtin:paper --dry-run",
    "opacityhull import colmap --model tests/data/real/",
    "F=tests/data/real/matting-flowers; opacityhull matte",
    "opacityhull calibrate tests/data/real/calibration/",
)

#: Command prefixes not run, each with its reason.
SKIP = {
    "make demo": "the make target itself (it installs into .venv); `opacityhull demo` is what it runs, tested in tests/view",
    "make test": "the make target that runs this file",
    "opacityhull view out/m --port": "serves until Ctrl-C; `view out/m --out out/web` below writes the same bundle",
    "opacityhull import colmap --model sparse/0": "placeholder for the reader's own COLMAP model (the dino import runs)",
    "opacityhull import nerfstudio --transforms data/transforms.json": "placeholder for the reader's own transforms.json",
}
SKIP_CONTAINS: dict[str, str] = {}


@dataclass(frozen=True)
class Example:
    line: int  # 1-based line of README.md where the command starts
    text: str  # the command as written, continuation lines joined
    background: bool

    @property
    def kind(self) -> str:
        return "skip" if self.skip_reason else ("fast" if self.text.startswith(FAST) else "slow")

    @property
    def skip_reason(self) -> str | None:
        for prefix, why in SKIP.items():
            if self.text.startswith(prefix):
                return why
        for part, why in SKIP_CONTAINS.items():
            if part in self.text:
                return why
        return None


def readme_examples(text: str) -> list[Example]:
    """The commands of every fenced ``sh`` block of ``text``, in order."""
    out: list[Example] = []
    in_sh = False
    pending: list[str] = []
    start = 0
    for n, raw in enumerate(text.splitlines(), start=1):
        if raw.startswith("```"):
            in_sh = raw.strip() == "```sh" if not in_sh else False
            continue
        if not in_sh:
            continue
        if not pending:
            start = n
        pending.append(raw)
        if raw.rstrip().endswith("\\"):
            continue
        joined = " ".join(p.rstrip().removesuffix("\\").strip() for p in pending)
        pending = []
        code = _strip_comment(joined).strip()
        if not code:
            continue
        out.append(Example(start, code.removesuffix("&").strip(), code.endswith("&")))
    return out


def _strip_comment(line: str) -> str:
    """``line`` without its trailing ``# comment`` (a ``#`` that starts a shell word)."""
    i = 0
    quote = None
    while i < len(line):
        c = line[i]
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i]
        i += 1
    return line


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("readme")
    for name in ("examples", "tests"):
        (d / name).symlink_to(REPO / name)
    (d / "out").mkdir()
    return d


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = f"{REPO}{os.pathsep}{env.get('PYTHONPATH', '')}".rstrip(os.pathsep)
    env.setdefault("NUMBA_NUM_THREADS", "1")
    env["OPACITYHULL_NO_HINT"] = "1"
    return env


def _wait_for_config(ex: Example, cwd: Path, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """A background emulator is up when the rig TOML it writes (``--write-config``) exists."""
    words = shlex.split(ex.text)
    path = cwd / words[words.index("--write-config") + 1] if "--write-config" in words else None
    t0 = time.monotonic()
    while path is not None and not path.is_file():
        if proc.poll() is not None:
            raise AssertionError(f"README.md:{ex.line}: `{ex.text}` exited early ({proc.returncode})")
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"README.md:{ex.line}: `{ex.text}` wrote no {path} in {timeout_s:.0f} s")
        time.sleep(0.1)


#: Command prefixes that need an X display (what the reader's desktop session gives): run
#: under a private Xvfb when DISPLAY is not set, skipped (saying so) without Xvfb.
NEEDS_DISPLAY = ("opacityhull rig monitors",)


def run_examples(examples: list[Example], cwd: Path, *, timeout_s: float) -> None:
    import contextlib
    import shutil

    env = _env()
    background: list[subprocess.Popen] = []
    with contextlib.ExitStack() as stack:
        if not env.get("DISPLAY") and shutil.which("Xvfb") and any(e.text.startswith(NEEDS_DISPLAY) for e in examples):
            from opacityhull.rigs.testing import xvfb

            env["DISPLAY"], _ = stack.enter_context(xvfb(((640, 480),)))
        _run_examples(examples, cwd, env, background, timeout_s=timeout_s)


def _run_examples(examples: list[Example], cwd: Path, env: dict, background: list, *, timeout_s: float) -> None:
    try:
        for ex in examples:
            if ex.text.startswith(NEEDS_DISPLAY) and not env.get("DISPLAY"):
                print(f"README.md:{ex.line}: skipped (no DISPLAY and no Xvfb to start one): {ex.text}")
                continue
            if ex.background:
                proc = subprocess.Popen(
                    ["bash", "-c", ex.text], cwd=cwd, env=env, start_new_session=True,
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                )  # fmt: skip
                background.append(proc)
                _wait_for_config(ex, cwd, proc)
                continue
            r = subprocess.run(
                ["bash", "-c", ex.text], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s
            )
            assert r.returncode == 0, f"README.md:{ex.line}: `{ex.text}` exited {r.returncode}\n{r.stderr[-3000:]}"
    finally:
        for proc in background:  # only the emulators this run started, by their process group
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)


def test_readme_examples_are_all_classified():
    """The README has examples of every kind, each skipped one names its reason, and the
    short path and the tour are among them."""
    examples = readme_examples(README.read_text())
    kinds = {k: [e for e in examples if e.kind == k] for k in ("fast", "slow", "skip")}
    assert all(kinds.values()), {k: len(v) for k, v in kinds.items()}
    assert examples[0].text.startswith("make demo")  # the shortest path comes first
    texts = [e.text for e in examples]
    assert any(t.startswith("opacityhull render out/dino-m --orbit") for t in texts)
    assert not any("orbit/frame.png" in t or "/tmp/" in t for t in texts)
    for e in kinds["skip"]:
        print(f"README.md:{e.line}: skipped ({e.skip_reason}): {e.text}")


def test_readme_parser_joins_lines_and_strips_comments():
    text = "x\n```sh\na --b c \\\n    --d '#e'  # note\n\n# only a comment\nf g &  # in the background\n```\n```\nnot sh\n```\n"
    ex = readme_examples(text)
    assert [(e.line, e.text, e.background) for e in ex] == [(3, "a --b c --d '#e'", False), (7, "f g", True)]


def test_fast_readme_examples(workdir):
    examples = [e for e in readme_examples(README.read_text()) if e.kind == "fast"]
    run_examples(examples, workdir, timeout_s=600)


@pytest.mark.readme_slow
@pytest.mark.timeout(7200)
def test_every_readme_example(tmp_path):
    for name in ("examples", "tests"):
        (tmp_path / name).symlink_to(REPO / name)
    (tmp_path / "out").mkdir()
    examples = [e for e in readme_examples(README.read_text()) if e.kind != "skip"]
    run_examples(examples, tmp_path, timeout_s=3600)
