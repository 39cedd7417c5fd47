"""End to end: `opacityhull capture` of builtin:tiny on the simulated rig (real drivers,
emulators over ptys, Mitsuba cameras) in a subprocess, interrupted with Ctrl-C and then
killed outright mid-run, resumed to the end; `session verify` passes with exactly the
planned number of images per phase and nothing duplicated. A Ctrl-C sent while Mitsuba
renders an exposure stops the capture after that render, resumably, just the same."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from opacityhull.session import read_manifest

pytestmark = pytest.mark.slow

# builtin:diffuse at 0.4x the default camera resolution (80x60) keeps the renders cheap
RIG = "sim:builtin:diffuse?scale=0.4"
PLAN = "builtin:tiny"


def _cli(*args) -> list[str]:
    return [sys.executable, "-m", "opacityhull.cli", *args]


def _listed(out: Path) -> int:
    return sum(1 for _ in read_manifest(out / "manifest.jsonl")) if (out / "manifest.jsonl").is_file() else 0


def _default_sigint() -> None:
    # a suite started in the background by a non-interactive shell inherits SIGINT
    # ignored, and Python then installs no KeyboardInterrupt handler in the child
    signal.signal(signal.SIGINT, signal.SIG_DFL)


# the CLI with the renderer's and the signal deferral's debug lines on stderr: a line
# "opacityhull.sim.render: mi.render: ..." is written inside the deferral, as the render starts
_TRACED_CLI = (
    "import logging, sys\n"
    "h = logging.StreamHandler(sys.stderr)\n"
    "h.setFormatter(logging.Formatter('%(name)s: %(message)s'))\n"
    "for name in ('opacityhull.sim.render', 'opacityhull.interrupts'):\n"
    "    logging.getLogger(name).setLevel(logging.DEBUG)\n"
    "    logging.getLogger(name).addHandler(h)\n"
    "sys.argv[0] = 'opacityhull'\n"
    "from opacityhull.cli import main\n"
    "main()\n"
)


def _start(out: Path, *extra, rig: str = RIG, plan: str = PLAN, traced: bool = False) -> subprocess.Popen:
    args = ("capture", "--rig", rig, "--plan", plan, "--out", str(out), "--json", *extra)
    return subprocess.Popen(
        [sys.executable, "-c", _TRACED_CLI, *args] if traced else _cli(*args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        preexec_fn=_default_sigint,
    )


def _finish(p: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """``p.communicate(timeout)``; a child still running after it has its threads' stacks
    printed (SIGUSR1: the CLI's faulthandler) into the failure, then is killed."""
    try:
        return p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGUSR1)
        try:
            _, err = p.communicate(timeout=20)
        except subprocess.TimeoutExpired as e:
            err = e.stderr or b""
        p.kill()
        p.communicate()
        text = err.decode(errors="replace") if isinstance(err, bytes) else (err or "")
        raise AssertionError(
            f"capture still running {timeout} s after its signal; its threads:\n{text[-8000:]}"
        ) from None


def _signal_after(proc: subprocess.Popen, out: Path, n_images: int, sig, deadline_s: float = 240.0) -> None:
    """Send ``sig`` once ``n_images`` are listed (polling the manifest the process appends to)."""
    t_end = time.monotonic() + deadline_s
    while _listed(out) < n_images:
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr is not None else ""
            raise AssertionError(f"capture ended before {n_images} images: {err[-2000:]}")
        if time.monotonic() > t_end:
            proc.kill()
            raise AssertionError(f"capture did not reach {n_images} images within {deadline_s} s")
        time.sleep(0.05)
    proc.send_signal(sig)


def test_capture_interrupt_kill_resume_verify(tmp_path):
    dry = subprocess.run(
        _cli("capture", "--rig", RIG, "--plan", PLAN, "--dry-run", "--json"),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert dry.returncode == 0, dry.stderr
    planned = json.loads(dry.stdout)["planned_per_phase"]
    total = sum(planned.values())
    # 3 cameras x 4 table angles (12 views): calibration 3 cameras x 8 board angles, matting
    # 5 shots per view, lightfield 1, reflectance 2 (the plan's lights)
    assert planned == {"calibration": 24, "matting": 60, "lightfield": 12, "reflectance": 24}
    assert total == 120
    rng = random.Random(20240611)
    k1 = rng.randrange(5, total // 3)
    k2 = rng.randrange(total // 3 + 5, 2 * total // 3)
    out = tmp_path / "session"

    # 1. Ctrl-C: exit 130, the JSON summary says incomplete, the rig was left safe
    p = _start(out)
    _signal_after(p, out, k1, signal.SIGINT)
    stdout, stderr = _finish(p, 120)
    assert p.returncode == 130, stderr[-2000:]
    summary = json.loads(stdout)  # --json: stdout holds exactly one JSON object, even after Ctrl-C
    assert summary["complete"] is False and k1 <= summary["images"] < total
    n1 = _listed(out)

    # 2. resume, then SIGKILL mid-run (no clean-up at all)
    p = _start(out, "--resume")
    _signal_after(p, out, k2, signal.SIGKILL)
    _finish(p, 120)
    assert p.returncode == -signal.SIGKILL
    n2 = _listed(out)
    assert n1 < n2 < total

    # 3. resume to the end, 4. verify
    _resume_to_end_and_verify(out, planned, n2)


def _resume_to_end_and_verify(out: Path, planned: dict[str, int], n_before: int, **start) -> None:
    """Resume the session in ``out`` (``n_before`` images listed) to the end, then check
    with `session verify` every file and hash, the exact counts per phase (``planned``)
    and that nothing is listed twice. ``start``: :func:`_start`'s rig and plan."""
    total = sum(planned.values())
    p = _start(out, "--resume", **start)
    stdout, stderr = _finish(p, 300)
    assert p.returncode == 0, stderr[-3000:]
    res = json.loads(stdout)
    assert res["complete"] and res["images"] == total and res["taken"] == total - n_before

    v = subprocess.run(_cli("session", "verify", str(out), "--json"), capture_output=True, text=True, timeout=120)
    assert v.returncode == 0, v.stdout + v.stderr
    rep = json.loads(v.stdout)
    assert rep["ok"] and rep["complete"]
    assert rep["per_phase"] == planned
    assert rep["missing"] == rep["corrupt"] == rep["unlisted"] == []
    ids = [r.id for r in read_manifest(out / "manifest.jsonl")]
    assert len(ids) == len(set(ids)) == total
    # the simulated rig wrote ground truth for the captured views
    assert (out / "groundtruth").is_dir()
    runs = [json.loads(x) for x in (out / "runs.jsonl").read_text().splitlines()]
    assert len(runs) >= 2 and runs[-1]["complete"]  # a SIGKILLed run cannot log itself


def test_ctrl_c_during_a_render_stops_at_the_exposure_and_resumes(tmp_path):
    """SIGINT while Mitsuba renders an exposure (the child says so on stderr, from inside
    the signal deferral, as the render starts): the render finishes, the signal is
    delivered after it, the capture exits 130 keeping the image before, and resumes."""
    plan = Path(__file__).with_name("interrupt_plan.toml")
    rig = "sim:builtin:diffuse"  # 200x150: a render outlasts the parent's reaction to its line
    out = tmp_path / "session"
    p = _start(out, rig=rig, plan=str(plan), traced=True)
    assert p.stderr is not None
    seen: list[str] = []
    armed = False
    # once the first image is listed, stop inside the next image render (an spp above the
    # 1-spp aov pass each view also takes)
    watchdog = threading.Timer(120, p.kill)  # a child that never gets there must not hang the suite
    watchdog.start()
    try:
        while True:
            line = p.stderr.readline()
            if not line:
                p.wait(30)
                raise AssertionError(f"capture ended (exit {p.returncode}) before a 2nd image: {''.join(seen)[-2000:]}")
            seen.append(line)
            if not line.startswith("opacityhull.sim.render: mi.render: "):
                continue
            if armed and int(line.split("mi.render: ", 1)[1].split()[0]) > 1:
                break
            armed = _listed(out) >= 1
    finally:
        watchdog.cancel()
    t_sig = time.monotonic()
    p.send_signal(signal.SIGINT)
    stdout, stderr = _finish(p, 60)
    latency_s = time.monotonic() - t_sig
    stderr = "".join(seen) + stderr
    assert p.returncode == 130, stderr[-2000:]
    assert "opacityhull.interrupts: mi.render: SIGINT arrived during it, delivered now" in stderr, stderr[-2000:]
    assert latency_s < 30, latency_s
    summary = json.loads(stdout)
    n1 = _listed(out)
    assert summary["complete"] is False and summary["images"] == n1 and 1 <= n1 < 3
    _resume_to_end_and_verify(out, {"lightfield": 3}, n1, rig=rig, plan=str(plan))
