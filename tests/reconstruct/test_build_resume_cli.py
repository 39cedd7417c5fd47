"""``opacityhull build`` killed by SIGTERM once its matting step is finished, then
``build --resume``: every step the killed build had finished (its manifest, read after
the process is gone) is reported reused, the rest ran, and the model equals an
uninterrupted build. No timing: the kill lands wherever it lands after matting."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import rcsynth
from opacityhull.model import OpacityHullModel

CLI = Path(sys.executable).with_name("opacityhull")


def test_sigterm_after_matting_then_resume(tmp_path):
    session = tmp_path / "session"
    rcsynth.make_session(session, kind="sphere", n_angles=4, reflectance=False, seed=13)
    out = tmp_path / "model"
    args = [str(CLI), "build", str(session), "--out", str(out), "--hull-res", "40", "--no-pictures"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    man = out / "build" / "manifest.json"
    deadline = time.monotonic() + 300  # a hang guard, not a measurement
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                if "matting" in json.loads(man.read_text())["steps"]:
                    break
            except (OSError, ValueError, KeyError):
                pass
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    finished = set(json.loads(man.read_text())["steps"])
    assert {"cameras", "matting"} <= finished
    if proc.returncode != 0:
        assert proc.returncode in (-signal.SIGTERM, 128 + signal.SIGTERM)
        # killed before its write step finished: no model.toml claims a finished model
        assert (out / "model.toml").exists() == ("write" in finished)

    res = subprocess.run([*args, "--resume", "--json"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    steps = json.loads(res.stdout)["steps"]
    for name, status in steps.items():
        assert status == ("reused" if name in finished else "ran"), (name, status, finished)
    assert steps["matting"] == "reused"

    from opacityhull.reconstruct.build import BuildConfig, build_model

    ref = tmp_path / "ref"
    build_model(session, ref, config=BuildConfig(hull_res=40, pictures=False))
    a, b = OpacityHullModel.open(out), OpacityHullModel.open(ref)
    np.testing.assert_array_equal(a.surfels.positions, b.surfels.positions)
    for i in range(len(a.views)):
        np.testing.assert_array_equal(a.load_view_rgba(i), b.load_view_rgba(i))
