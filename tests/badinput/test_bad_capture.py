"""``capture`` stopped by SIGTERM / SIGHUP (a scheduler, systemd, a closed terminal)
gets what Ctrl-C gets: ``rig.safe()``, the lock removed, exit 143 / 129, resumable. And
a session cannot be resumed with another simulated scene."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def _manifest_ids(out: Path) -> list[str]:
    p = out / "manifest.jsonl"
    return [json.loads(x)["id"] for x in p.read_text().splitlines() if x.strip()] if p.is_file() else []


def _child(out: Path, *args, hold: str | None = None):
    env = dict(os.environ, PYTHONPATH=str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if hold:
        env["OPACITYHULL_TEST_HOLD_AT"] = hold
    # default dispositions: a suite started in the background inherits SIGINT/SIGHUP ignored
    return subprocess.Popen(
        [sys.executable, str(HERE / "capture_child.py"), str(out), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: [signal.signal(s, signal.SIG_DFL) for s in (signal.SIGHUP, signal.SIGTERM)],
    )


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_leave_the_rig_safe_and_the_session_resumable(tmp_path, sig, code):
    from opacityhull.acquire.verify import verify_session

    out = tmp_path / "s"
    mark = tmp_path / "signal-sent"
    proc = _child(out, hold=f"5:{mark}")
    for line in proc.stdout:
        if line.startswith("img ") and int(line.split()[1]) >= 5:
            total = int(line.split()[2])
            proc.send_signal(sig)
            mark.touch()  # the child waits at image 5 until the signal is on its way
            break
    rest, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    state = [x for x in rest.splitlines() if x.startswith("state ")][0]
    assert "lights={0: 0, 1: 0, 2: 0, 3: 0}" in state and "shown=False" in state, state
    assert "moving=False" in state and "feed_hold_sent=True" in state, state
    assert "terminated by SIG" in err
    assert not (out / ".capture.lock").exists()
    listed = len(_manifest_ids(out))
    assert 5 <= listed < total
    assert verify_session(out)["ok"]
    proc = _child(out, "--resume")
    rest, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    res = json.loads([x for x in rest.splitlines() if x.startswith("done ")][0][5:])
    assert res["complete"] and res["taken"] == total - listed
    ids = _manifest_ids(out)
    assert len(ids) == len(set(ids)) == total


def test_resume_with_another_simulated_scene_is_refused(tmp_path):
    """The issue: `--resume` of a diffuse session with sim:builtin:glass gave one session of
    40 cup and 80 glass images. The geometry and plan match; the scene does not."""
    sys.path.insert(0, str(HERE.parent / "acquire"))
    from rigkit import LabRig, tiny_plan

    from opacityhull.acquire.runner import run_capture
    from opacityhull.errors import ConfigError

    from badkit import tree_digest

    out = tmp_path / "s"
    rig = LabRig()
    rig.open()
    try:
        n = {"k": 0}

        def stop_early(done, total):
            n["k"] = done
            if done == 4:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            run_capture(rig, tiny_plan(), out, progress=stop_early, rig_source="sim:builtin:diffuse")
        before = tree_digest(out)
        with pytest.raises(ConfigError, match=r"rig_source = 'sim:builtin:diffuse'.*same --rig"):
            run_capture(rig, tiny_plan(), out, resume=True, rig_source="sim:builtin:glass")
        assert tree_digest(out) == before
        assert not (out / ".capture.lock").exists()
        res = run_capture(rig, tiny_plan(), out, resume=True, rig_source="sim:builtin:diffuse")
        assert res.complete
    finally:
        rig.close()


def test_an_ignored_sighup_stays_ignored():
    """`nohup opacityhull capture ...` ignores SIGHUP on purpose: the capture must not
    turn it into a stop."""
    from opacityhull.acquire.runner import terminate_as_interrupt

    old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with terminate_as_interrupt():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, signal.SIG_IGN)
            os.kill(os.getpid(), signal.SIGHUP)  # ignored: nothing is raised
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, old)
