"""``capture`` stopped by SIGTERM / SIGHUP (a scheduler, systemd, a closed terminal)
gets what Ctrl-C gets: ``rig.safe()``, the lock removed, exit 143 / 129, resumable. And
a session cannot be resumed with another simulated scene."""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import pytest
from helpers import python_child, with_pythonpath
from rigkit import assert_left_safe, assert_resumed_to_the_end

HERE = Path(__file__).resolve().parent


def _manifest_ids(out: Path) -> list[str]:
    p = out / "manifest.jsonl"
    return [json.loads(x)["id"] for x in p.read_text().splitlines() if x.strip()] if p.is_file() else []


def _child(out: Path, *args, hold: str | None = None):
    env = with_pythonpath(HERE)
    if hold:
        env["OPACITYHULL_TEST_HOLD_AT"] = hold
    return python_child(HERE / "capture_child.py", str(out), *args, env=env, preexec_fn=_default_dispositions)


def _default_dispositions() -> None:
    """A suite started in the background inherits SIGINT/SIGHUP ignored: the child gets
    the default dispositions back."""
    for s in (signal.SIGHUP, signal.SIGTERM):
        signal.signal(s, signal.SIG_DFL)


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
    assert_left_safe([x for x in rest.splitlines() if x.startswith("state ")][0])
    assert "terminated by SIG" in err
    assert not (out / ".capture.lock").exists()
    listed = len(_manifest_ids(out))
    assert 5 <= listed < total
    assert verify_session(out)["ok"]
    assert_resumed_to_the_end(_child(out, "--resume"), out, listed=listed, total=total, timeout_s=120)


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
