"""tests/background.py, the background jobs that slow modules' ``prebuild()`` starts
with the run (and tests/simcache.py's prefetch through it)."""

from __future__ import annotations

import os
import sys
import time

import pytest

import background


@pytest.fixture
def jobs(tmp_path, monkeypatch):
    """A fresh job table in ``tmp_path`` (the session's jobs are left alone)."""
    monkeypatch.setattr(background, "_JOBS", {})
    monkeypatch.setattr(background, "_ROOT", None)
    background.configure(tmp_path)
    yield background
    background.stop_all()


def test_a_job_runs_once_in_its_folder_at_a_lower_priority(jobs):
    code = "import os, pathlib; pathlib.Path('out.txt').write_text(f\"{os.nice(0)} {os.environ['NUMBA_NUM_THREADS']}\")"
    d = jobs.start("ok", [sys.executable, "-c", code])
    assert jobs.start("ok", [sys.executable, "-c", "raise SystemExit(3)"]) == d  # started once
    jobs.wait("ok", timeout_s=60)
    nice, threads = (d / "out.txt").read_text().split()
    assert int(nice) >= min(os.nice(0) + jobs.NICE, 19) or os.geteuid() == 0  # root may have raised it back
    assert threads == "1"
    (row,) = jobs.log()
    assert row["key"] == "ok" and row["returncode"] == 0 and row["seconds"] > 0


def test_a_failed_job_fails_the_waiting_test_with_its_log(jobs):
    jobs.start("bad", [sys.executable, "-c", "print('what went wrong'); raise SystemExit(3)"])
    with pytest.raises(AssertionError, match=r"(?s)'bad' failed \(exit 3\).*what went wrong"):
        jobs.wait("bad", timeout_s=60)
    with pytest.raises(AssertionError, match="never started"):
        jobs.wait("other", timeout_s=1)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting for its reaper does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _child_pid(job_dir, timeout_s: float = 30) -> int:
    t = time.perf_counter()
    while not (job_dir / "child.pid").is_file() or not (job_dir / "child.pid").read_text():
        assert time.perf_counter() - t < timeout_s
        time.sleep(0.05)
    return int((job_dir / "child.pid").read_text())


# a job with a child of its own (as the prefetch job's capture subprocess), both asleep
SLEEPER = (
    "import pathlib, subprocess, sys, time; "
    "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']); "
    "pathlib.Path('child.pid').write_text(str(p.pid)); time.sleep(60)"
)


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_a_job_past_its_time_and_a_running_one_are_stopped_with_their_children(jobs):
    d = jobs.start("slow", [sys.executable, "-c", SLEEPER])
    child = _child_pid(d)
    with pytest.raises(AssertionError, match="not finished after 0.5 s"):
        jobs.wait("slow", timeout_s=0.5)
    assert not _alive(child)
    d = jobs.start("left", [sys.executable, "-c", SLEEPER])
    child = _child_pid(d)
    jobs.stop_all()
    assert jobs.log()[1]["returncode"] is not None
    t = time.perf_counter()
    while _alive(child) and time.perf_counter() - t < 10:
        time.sleep(0.05)  # SIGTERM reached it; its exit may take a moment
    assert not _alive(child)


def test_jobs_run_at_normal_priority_only_while_the_foreground_waits(jobs):
    d = jobs.start("sleeper", [sys.executable, "-c", SLEEPER])
    child = _child_pid(d)
    pid = jobs._JOBS["sleeper"].proc.pid

    def nice() -> tuple[int, int]:
        return os.getpriority(os.PRIO_PROCESS, pid), os.getpriority(os.PRIO_PROCESS, child)

    low = min(os.getpriority(os.PRIO_PROCESS, 0) + jobs.NICE, 19)
    assert nice() == (low, low)
    with jobs.hurried():
        # lowering a nice value needs root; without it the job keeps its own
        assert nice() == ((0, 0) if os.geteuid() == 0 else (low, low))
    assert nice() == (low, low)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_job_ends_with_the_process_that_started_it(tmp_path):
    """A pytest killed outright runs no teardown: its jobs must not outlive it."""
    code = (
        "import sys, time; sys.path.insert(0, sys.argv[1]); import background; "
        "background.configure(sys.argv[2]); "
        "background.start('orphan', [sys.executable, '-c', 'import time; time.sleep(60)']); "
        "print(background._JOBS['orphan'].proc.pid, flush=True); time.sleep(60)"
    )
    import subprocess

    p = subprocess.Popen(
        [sys.executable, "-c", code, os.path.dirname(background.__file__), str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert p.stdout is not None
    job = int(p.stdout.readline())
    assert _alive(job)
    p.kill()
    p.wait()
    t = time.perf_counter()
    while _alive(job) and time.perf_counter() - t < 10:
        time.sleep(0.05)
    assert not _alive(job)
