"""`opacityhull rig bringup` on the emulated rig with the simulator's cameras (Mitsuba at
4 spp, two 200x150 cameras): every step passes; the walk resumes; an injected fault
(`--fault`, the specs of `rig emulate`) fails the right step, naming the device and what
to check, and skips the steps that need that device."""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from opacityhull.acquire.plan import load_plan
from opacityhull.rigs.bringup import BringupOptions, board_rotation_deg, open_for_bringup, run_bringup
from opacityhull.rigs.config import parse_rig_config
from opacityhull.tomlio import toml_dumps
from opacityhull.sim.simrig import DEFAULT_RIG_TOML, bringup_sim_rig

ROOT = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-m", "opacityhull.cli"]
KEEP = ("cam4", "cam5")  # the two highest cameras see the board on its wedge at 0 and 90 deg


def two_camera_rig() -> dict:
    raw = tomllib.loads(DEFAULT_RIG_TOML.read_text())
    raw = copy.deepcopy(raw)
    raw["geometry"]["cameras"] = [c for c in raw["geometry"]["cameras"] if c["name"] in KEEP]
    raw["devices"]["cameras"] = [c for c in raw["devices"]["cameras"] if c["name"] in KEEP]
    return raw


@pytest.fixture(scope="module")
def rig_toml(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("bringup") / "rig.toml"
    p.write_text(toml_dumps(two_camera_rig()))
    return p


@settings(max_examples=50, deadline=None)
@given(
    turn=st.floats(-170, 170),
    swing=st.floats(-3, 3),
    axis=st.tuples(st.floats(-1, 1), st.floats(0.3, 1), st.floats(-1, 1)),
    board=st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-3, 3)),
)
def test_twist_about_the_table_axis_ignores_tilt_errors(turn, swing, axis, board):
    n = np.array(axis) / np.linalg.norm(axis)
    R_a = Rotation.from_rotvec(board).as_matrix()
    other = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
    other /= np.linalg.norm(other)
    R_turn = Rotation.from_rotvec(math.radians(turn) * n).as_matrix()
    R_swing = Rotation.from_rotvec(math.radians(swing) * other).as_matrix()
    R_b = R_swing @ R_turn @ R_a
    assert board_rotation_deg(R_a, R_turn @ R_a) == pytest.approx(abs(turn), abs=1e-4)
    # a tilt about another axis changes the whole angle but barely the twist
    assert board_rotation_deg(R_a, R_b, n) == pytest.approx(abs(turn), abs=0.01 + abs(swing) * 0.05)


def run(config: Path, state: Path, *extra, timeout=600):
    return subprocess.run(
        [*CLI, "rig", "bringup", "--config", str(config), "--state", str(state), "--json", *extra],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout,
    )


def test_every_step_passes_on_the_emulated_rig_and_the_walk_resumes(rig_toml, tmp_path):
    state = tmp_path / "state.json"
    r = run(rig_toml, state)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    steps = {s["step"]: s for s in out["steps"]}
    assert out["ok"] and all(s["verdict"] == "pass" for s in out["steps"])
    assert set(steps) == {
        "answers:turntable",
        "answers:light_array.rotation",
        "answers:light_array",
        "answers:backdrops",
        "answers:cam4",
        "answers:cam5",
        "turntable",
        *(f"lamp:{i}" for i in range(4)),
        "display:bottom",
        "display:back",
        "exposure:cam4",
        "exposure:cam5",
    }
    assert abs(steps["turntable"]["measurement"]["board turned (deg)"] - 90.0) <= 1.0
    assert steps["display:back"]["measurement"]["contrast"] > 100  # a display emits no light when black
    assert all(steps[f"lamp:{i}"]["measurement"]["rise"] > 0.001 for i in range(4))
    # each step says what it checks, the measurement and the verdict, on stderr too
    assert "[PASS] turntable: the board turns with the table by 90 ± 1° — board turned (deg) = " in r.stderr
    # resumed: the passed steps are not run again (no device moves, no photograph)
    r2 = run(rig_toml, state)
    assert r2.returncode == 0, r2.stderr
    again = {s["step"]: s for s in json.loads(r2.stdout)["steps"]}
    assert all(s["earlier"] for k, s in again.items() if not k.startswith("answers:"))
    assert "(passed earlier)" in r2.stderr


@pytest.mark.parametrize(
    "fault, failed, says, skipped",
    [
        ("turntable:silent", "answers:turntable", "silent — is it powered", ["turntable"]),
        ("backdrops:babble:4000", "answers:backdrops", "garbled — check the baud rate", ["display:bottom"]),
        ("light_array:silent", "answers:light_array", "light_array", ["lamp:0", "lamp:3"]),
    ],
)
def test_an_injected_fault_fails_the_right_step(rig_toml, tmp_path, fault, failed, says, skipped):
    cfg = parse_rig_config(tomllib.loads(rig_toml.read_text()), source=str(rig_toml))
    dev, _, spec = fault.partition(":")
    plan = load_plan("builtin:demo")
    assert plan.calibration is not None
    opts = BringupOptions(charuco=plan.calibration.charuco, lamp_exposure_s=2.0)
    with open_for_bringup(cfg, faults={dev: [spec]}, simulated=bringup_sim_rig) as (rig, failed_ports):
        results = {r.step: r for r in run_bringup(rig, options=opts, failed_ports=failed_ports)}
    bad = [k for k, r in results.items() if r.verdict == "fail"]
    assert failed in bad, {k: r.verdict for k, r in results.items()}
    assert dev in results[failed].what_to_check and says in results[failed].what_to_check
    for k in skipped:
        assert results[k].verdict == "skip" and f"needs {dev}" in results[k].what_to_check
    # the other devices' steps still pass
    others = [k for k, r in results.items() if r.verdict == "pass"]
    assert "exposure:cam5" in others or dev == "light_array"


def test_cli_fault_exits_3_naming_the_step(rig_toml, tmp_path):
    r = run(rig_toml, tmp_path / "s.json", "--fault", "turntable:silent", "--restart")
    assert r.returncode == 3
    assert "bring-up failed: answers:turntable: turntable:" in " ".join(r.stderr.split())


def test_simulated_cameras_need_the_injected_simulator(rig_toml):
    # rigs/ cannot build simulated cameras itself (it imports nothing above rigs/): the
    # caller passes the simulator in, and without it the walk refuses before any port opens
    from opacityhull.errors import ConfigError

    cfg = parse_rig_config(tomllib.loads(rig_toml.read_text()), source=str(rig_toml))
    with pytest.raises(ConfigError, match="simulated cameras"), open_for_bringup(cfg):
        pass
