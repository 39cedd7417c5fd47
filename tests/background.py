"""Slow, self-contained preparations run in background processes, started when the test
run begins, so that they use the core the rest of the suite leaves idle.

Most of the suite is single-threaded Python: a fresh clone's ``make test`` on the 2-core
machine kept 1.4 cores busy on average (27 min 25 s user + system time in 19 min 58 s,
install and lint included). A test module whose fixtures spend minutes on deterministic
work that needs nothing from the test (the real rings' fitted builds of
tests/e2e/test_real_sets_split.py; simulated captures, through
:func:`simcache.prefetch`) defines ``prebuild()``, which hands that work to
:func:`start`; tests/conftest.py calls every selected module's ``prebuild()`` when the
session starts and moves those modules to the end of the run, by when their products
are ready. The fixture calls ``prebuild()`` again (idempotent: a job already started is
not started twice) and :func:`wait` s for it, so a module run alone, or under
pytest-xdist (whose workers do not prebuild), starts its jobs on demand and gets the
same products.

API::

    import background                      # tests/ is on sys.path (tests/conftest.py)

    job_dir = background.start(key, argv)  -> Path   (argv runs with cwd job_dir)
    background.wait(key, timeout_s=...)    # raises AssertionError with the job's log tail
    background.stop_all()                  # terminate what still runs (session end)
    background.log()                       -> [{"key", "seconds", "returncode"}]

Each job runs ``argv`` in its own process group, at a lower priority (``nice`` 10: the
tests in the foreground keep their speed, the job takes what they leave; :func:`hurried`
restores it while the foreground waits) and with one numba thread unless asked (two
jobs fill two cores when nothing else runs). The products do not depend on either (the
fit's kernels give the same bytes whatever the thread count, see
opacityhull/optimize/raster.py). Output goes to ``<root>/<key>.log``, the products to
``<root>/<key>/``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["configure", "root", "start", "wait", "hurried", "stop_all", "log"]

#: the background jobs' scheduling priority (``os.nice`` increment)
NICE = 10


@dataclass
class _Job:
    proc: subprocess.Popen
    log_path: Path
    t_start: float
    seconds: float | None = None


_ROOT: Path | None = None
_JOBS: dict[str, _Job] = {}


def configure(path) -> Path:
    """Set the folder the jobs write into (the conftest fixture does this)."""
    global _ROOT
    _ROOT = Path(path)
    _ROOT.mkdir(parents=True, exist_ok=True)
    return _ROOT


def root() -> Path:
    """The jobs' folder (a temporary directory when nothing was configured)."""
    if _ROOT is None:
        configure(tempfile.mkdtemp(prefix="background_"))
    return _ROOT  # type: ignore[return-value]


def _libc():
    try:
        import ctypes

        return ctypes.CDLL(None)
    except OSError:
        return None


# loaded here, not in the child: between fork and exec only calls that take no lock
# another thread of pytest might hold at the fork (an import would) are safe
_LIBC = _libc()
_PR_SET_PDEATHSIG = 1


def _lower_priority() -> None:
    os.nice(NICE)
    # a pytest killed outright (SIGTERM/SIGKILL skips its fixtures' teardown) takes its
    # jobs with it: Linux's PR_SET_PDEATHSIG; elsewhere they run to their end
    if _LIBC is not None and hasattr(_LIBC, "prctl"):
        _LIBC.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM))


def start(key: str, argv: list[str], *, numba_threads: int | None = 1) -> Path:
    """Start ``argv`` as background job ``key`` (once per process: a second call with
    the same key returns at once), with ``numba_threads`` numba threads (None: as this
    process). Returns the job's folder (its working directory)."""
    job_dir = root() / key
    if key in _JOBS:
        return job_dir
    job_dir.mkdir(parents=True, exist_ok=True)
    log_path = root() / f"{key}.log"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if numba_threads is not None:
        env["NUMBA_NUM_THREADS"] = str(numba_threads)
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(
            argv,
            cwd=job_dir,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: hurried() and stop_all() reach its children
            preexec_fn=_lower_priority,
        )
    _JOBS[key] = _Job(proc, log_path, time.perf_counter())
    return job_dir


def wait(key: str, *, timeout_s: float) -> None:
    """Wait for job ``key`` to finish; an AssertionError naming its exit code and the
    tail of its log when it failed or did not finish within ``timeout_s``."""
    job = _JOBS.get(key)
    if job is None:
        raise AssertionError(f"background job {key!r} was never started")
    try:
        with hurried():
            rc = job.proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(OSError):
            os.killpg(job.proc.pid, signal.SIGKILL)
        job.proc.wait()
        rc = None
    if job.seconds is None:
        job.seconds = time.perf_counter() - job.t_start
    if rc != 0:
        tail = job.log_path.read_text(errors="replace")[-3000:]
        what = f"exit {rc}" if rc is not None else f"not finished after {timeout_s:g} s"
        raise AssertionError(f"background job {key!r} failed ({what}); {job.log_path}:\n{tail}")


@contextlib.contextmanager
def hurried():
    """While the foreground idles (waiting for a job's product): every running job, with
    its children, at normal priority where allowed (lowering a nice value needs root;
    otherwise they keep it, and have the cores to themselves anyway); back to their own
    after, for the jobs still running."""
    was = {}
    for key, job in _JOBS.items():
        if job.proc.poll() is None:
            with contextlib.suppress(OSError):
                was[key] = os.getpriority(os.PRIO_PROCESS, job.proc.pid)
                os.setpriority(os.PRIO_PGRP, job.proc.pid, 0)
    try:
        yield
    finally:
        for key, nice in was.items():
            if _JOBS[key].proc.poll() is None:
                with contextlib.suppress(OSError):
                    os.setpriority(os.PRIO_PGRP, _JOBS[key].proc.pid, nice)


def stop_all() -> None:
    """Terminate the jobs still running (a run stopped early, or a module that failed
    before it waited)."""
    for job in _JOBS.values():
        if job.proc.poll() is None:
            with contextlib.suppress(OSError):
                os.killpg(job.proc.pid, signal.SIGTERM)
            try:
                job.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(OSError):
                    os.killpg(job.proc.pid, signal.SIGKILL)
                job.proc.wait()


def log() -> list[dict]:
    """The jobs of this process: ``[{"key", "seconds", "returncode"}]`` (seconds from
    the start to the first :func:`wait` that saw it finish; None while running)."""
    return [{"key": k, "seconds": j.seconds, "returncode": j.proc.poll()} for k, j in _JOBS.items()]
