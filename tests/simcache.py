"""Shared, memoised captures and builds on the simulated rig, for tests.

Capturing a session on the Mitsuba-simulated rig takes minutes; several test modules
(reconstruction e2e, renderer leave-one-out, relighting) need the same kind of session.
This module captures each (scene, plan, scale) once per test run and builds each
(capture, build options) once, whoever asks first; later callers get the same folders.

API (stable — other stages' tests depend on it)::

    import simcache                        # tests/ is on sys.path (tests/conftest.py)

    session_dir = simcache.captured(scene, plan_path, scale)              -> Path
    model_dir = simcache.built(scene, plan_path, scale, **build_config)   -> Path
    simcache.report(model_dir)             -> dict (model_dir/report.json)
    simcache.CI_PLAN, simcache.CI_SCALE    the shared CI plan (3 cameras x 6 table
                                           angles, matting with object-absent shots,
                                           lightfield, one light) and its scale

* ``scene``: a built-in scene name (``"diffuse"``, ``"glossy"``, ``"fuzzy"``, ...) or
  any ``sim:`` spec body such as ``"builtin:diffuse@/path/rig.toml"``; the capture runs
  on ``sim:<scene>?scale=<scale>``.
* ``plan_path``: a plan TOML path or ``"builtin:tiny|demo|paper"``. The plan's *text*
  is part of the cache key, so two files with the same content share a capture.
* ``scale``: multiplies the simulated cameras' resolution (1.0 = 200x150).
* ``build_config``: keyword arguments of
  :class:`opacityhull.reconstruct.build.BuildConfig` (e.g. ``hull_res=96,
  cameras="groundtruth", alpha_threshold=0.05``). Every build runs with
  ``ground_truth=True`` (simulated sessions have ``groundtruth/``), so
  ``report(model_dir)["metrics"]`` has alpha MAE, hull IoU, ... Equal keyword sets
  share a model.

The returned folders are read-only by convention: a test that modifies a session or a
model must copy it first (``shutil.copytree``).

The capture runs the real CLI (``python -m opacityhull.cli capture ... --json``) in a
subprocess; the build runs in-process (``build_model``). A failure is remembered for
the rest of the run (the next caller gets the same error at once instead of paying for
the capture again).

Where things live: ``<pytest basetemp>/simcache/<key>/`` (set up by the session fixture
in tests/conftest.py; under pytest-xdist the workers share the parent directory and
take a file lock per key, so a capture still happens once). Outside pytest the root is
a fresh temporary directory. Setting ``OPACITYHULL_SIMCACHE=/some/dir`` keeps captures
and builds across runs (a developer convenience: the key covers the scene, plan text,
scale and build options, *not* the code — clear the directory after changing the
simulator, acquire or reconstruct).

Timings of what was actually captured or built in this run: :func:`log`.

Captures ahead of need: a test module's ``prebuild()`` (tests/background.py) calls
:func:`prefetch` for the captures its fixtures will ask for; when the session begins,
tests/conftest.py starts :func:`start_prefetch`, one background process that captures
them in turn (at a lower priority, on the cores the foreground leaves idle), and moves
those modules to the end of the run. The fixtures call :func:`captured` as before: the
per-key file lock makes them wait for a capture in progress, and a finished one is
reused; a prefetch that failed leaves nothing behind, so the fixture captures again
and reports the error itself.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "captured",
    "built",
    "report",
    "configure",
    "root",
    "log",
    "prefetch",
    "start_prefetch",
    "CI_PLAN",
    "CI_SCALE",
]

CI_PLAN = Path(__file__).parent / "e2e" / "data" / "sim_ci.toml"
CI_SCALE = 1.0

_ROOT: Path | None = None
_MEMO: dict[str, Path] = {}
_FAILED: dict[str, str] = {}
_LOG: list[dict] = []
_PREFETCH: list[tuple[str, str, float]] = []


def configure(path) -> Path:
    """Set the cache root (the conftest fixture does this); ``OPACITYHULL_SIMCACHE``
    overrides it. Returns the root in use."""
    global _ROOT
    env = os.environ.get("OPACITYHULL_SIMCACHE")
    _ROOT = Path(env) if env else Path(path)
    _ROOT.mkdir(parents=True, exist_ok=True)
    return _ROOT


def root() -> Path:
    """The cache root (a temporary directory when nothing was configured)."""
    if _ROOT is None:
        configure(os.environ.get("OPACITYHULL_SIMCACHE") or tempfile.mkdtemp(prefix="simcache_"))
    return _ROOT  # type: ignore[return-value]


def log() -> list[dict]:
    """What this process captured or built: ``[{"what", "key", "seconds"}]``."""
    return list(_LOG)


def _plan_text(plan_path) -> str:
    s = str(plan_path)
    if s.startswith("builtin:"):
        import opacityhull.acquire.plan as plan_mod

        return (Path(plan_mod.__file__).with_name("plans") / f"{s.split(':', 1)[1]}.toml").read_text()
    p = Path(plan_path)
    if not p.is_file():
        raise FileNotFoundError(f"simcache: plan {p} not found")
    return p.read_text()


def _slug(text: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in text).strip("-")[:40]


def _rig_spec(scene: str, scale: float) -> str:
    body = scene if (":" in scene or "@" in scene) else f"builtin:{scene}"
    sep = "&" if "?" in body else "?"
    return f"sim:{body}{sep}scale={float(scale):g}"


def _capture_key(scene: str, plan_path, scale: float) -> str:
    h = hashlib.sha256(f"{scene}\n{float(scale)!r}\n{_plan_text(plan_path)}".encode()).hexdigest()[:12]
    stem = Path(str(plan_path).split(":")[-1]).stem
    return f"{_slug(scene)}_{_slug(stem)}_s{float(scale):g}_{h}"


@contextmanager
def _locked(key: str):
    lock = root() / f".{key}.lock"
    with open(lock, "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            # held by another worker or by the prefetch job: that job now has the
            # foreground's share of the cores
            import background

            with background.hurried():
                fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _remember_failure(key: str, fn):
    if key in _FAILED:
        raise AssertionError(f"simcache: {_FAILED[key]} (failed earlier in this run)")
    try:
        return fn()
    except BaseException as e:  # noqa: BLE001 - re-raised; remembered so others do not retry
        _FAILED[key] = f"{type(e).__name__}: {str(e)[-1500:]}"
        raise


def captured(scene: str, plan_path, scale: float = CI_SCALE) -> Path:
    """The session folder of ``scene`` captured with ``plan_path`` at ``scale`` (once
    per run; see the module docstring)."""
    key = _capture_key(scene, plan_path, scale)
    if key in _MEMO:
        return _MEMO[key]

    def run() -> Path:
        base = root() / key
        sess = base / "session"
        with _locked(key):
            if not (base / "capture.done").is_file():
                part = base / "session.partial"
                shutil.rmtree(part, ignore_errors=True)
                shutil.rmtree(sess, ignore_errors=True)
                base.mkdir(parents=True, exist_ok=True)
                env = dict(os.environ, COLUMNS="400")  # rich wraps messages at the terminal width
                t = time.perf_counter()
                p = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "opacityhull.cli",
                        "capture",
                        "--rig",
                        _rig_spec(scene, scale),
                        "--plan",
                        str(plan_path),
                        "--out",
                        str(part),
                        "--json",
                    ],
                    capture_output=True,
                    text=True,
                    timeout=3000,
                    env=env,
                )
                if p.returncode != 0:
                    raise AssertionError(
                        f"capture of {_rig_spec(scene, scale)} with {plan_path} failed "
                        f"(exit {p.returncode}): {p.stderr[-2000:]}"
                    )
                part.rename(sess)
                secs = time.perf_counter() - t
                (base / "capture.done").write_text(json.dumps({"seconds": secs, "summary": p.stdout.strip()}))
                _LOG.append({"what": "capture", "key": key, "seconds": secs})
        return sess

    sess = _remember_failure(key, run)
    _MEMO[key] = sess
    return sess


def built(scene: str, plan_path, scale: float = CI_SCALE, **build_config) -> Path:
    """The model folder built from :func:`captured` ``(scene, plan_path, scale)`` with
    ``BuildConfig(**build_config)`` and ``ground_truth=True`` (once per run)."""
    from opacityhull.reconstruct.build import BuildConfig, build_model

    cfg = BuildConfig(**build_config)  # validates the keywords before any capture
    ckey = _capture_key(scene, plan_path, scale)
    bhash = hashlib.sha256(repr(sorted(build_config.items())).encode()).hexdigest()[:12]
    key = f"{ckey}/model_{bhash}"
    if key in _MEMO:
        return _MEMO[key]

    def run() -> Path:
        sess = captured(scene, plan_path, scale)
        base = root() / ckey
        model = base / f"model_{bhash}"
        with _locked(f"{ckey}_model_{bhash}"):
            if not (base / f"model_{bhash}.done").is_file():
                part = base / f"model_{bhash}.partial"
                shutil.rmtree(part, ignore_errors=True)
                shutil.rmtree(model, ignore_errors=True)
                t = time.perf_counter()
                build_model(sess, part, config=cfg, ground_truth=True)
                part.rename(model)
                # report.json names the folder it was written in: point it at the final one
                rp = model / "report.json"
                rep = json.loads(rp.read_text())
                rep["model_dir"] = str(model)
                rp.write_text(json.dumps(rep, indent=2) + "\n")
                secs = time.perf_counter() - t
                (base / f"model_{bhash}.done").write_text(
                    json.dumps({"seconds": secs, "build_config": repr(sorted(build_config.items()))})
                )
                _LOG.append({"what": "build", "key": key, "seconds": secs})
        return model

    model = _remember_failure(key, run)
    _MEMO[key] = model
    return model


def prefetch(scene: str, plan_path, scale: float = CI_SCALE) -> None:
    """Ask for :func:`captured` ``(scene, plan_path, scale)`` ahead of need (from a test
    module's ``prebuild()``; :func:`start_prefetch` captures what was asked, in order)."""
    # the job runs in its own folder: a relative plan path would not resolve there
    plan = str(plan_path) if str(plan_path).startswith("builtin:") else str(Path(plan_path).resolve())
    spec = (scene, plan, float(scale))
    if spec not in _PREFETCH:
        _PREFETCH.append(spec)


def start_prefetch() -> None:
    """Start one background job (tests/background.py) capturing every :func:`prefetch`
    ed session that is not captured yet, in the order asked."""
    import background

    todo = [s for s in _PREFETCH if not (root() / _capture_key(*s) / "capture.done").is_file()]
    if todo:
        # the capture's own threads: no numba thread limit
        background.start(
            "simcache_prefetch", [sys.executable, __file__, str(root()), json.dumps(todo)], numba_threads=None
        )


def report(model_dir) -> dict:
    """``report.json`` of a model built by :func:`built` (metrics, seconds, notes...)."""
    return json.loads((Path(model_dir) / "report.json").read_text())


if __name__ == "__main__":  # the job of start_prefetch(): ROOT '[[scene, plan, scale], ...]'
    configure(sys.argv[1])
    # stopped (background.stop_all, or the parent's death): the capture in progress too
    import signal

    signal.signal(signal.SIGTERM, lambda *_: os.killpg(0, signal.SIGKILL))
    for _scene, _plan, _scale in json.loads(sys.argv[2]):
        try:
            captured(_scene, _plan, _scale)
            print(f"prefetched {_scene} {_plan} {_scale:g}", flush=True)
        except Exception as e:  # noqa: BLE001 - the fixture that needs it captures again and fails there
            print(f"prefetch of {_scene} {_plan} {_scale:g} failed: {e}", flush=True)
