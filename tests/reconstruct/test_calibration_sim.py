"""Calibration on real Mitsuba renders of the simulated rig (``sim:builtin:diffuse``),
captured through the real acquisition runner, drivers and emulators, checked against the
simulator's ``groundtruth/calibration``.

The rig's cameras are 200x150 px with a 24 deg field of view at 1 m: a flat board gives
each camera one plane, so the focal length and the camera distance are only weakly
separated (their errors cancel in what silhouettes see: the working volume reprojects
within a fraction of a pixel). The thresholds below are those of that geometry.
"""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from opacityhull.camera import read_opencv_yaml
from opacityhull.reconstruct.calibration import (
    CalibrationConfig,
    CalibrationError,
    calibrate_session,
    pose_errors,
    view_cameras,
)
from opacityhull.reconstruct.exports import export_colmap

pytestmark = pytest.mark.slow

# The simulator's large-marker board (scene builtin:charuco): OpenCV finds it at 200x150.
BOARD = dict(squares_x=6, squares_y=5, square_m=0.05, marker_m=0.038, dictionary="DICT_4X4_50")


@pytest.fixture(scope="module")
def sim_session(tmp_path_factory):
    sim = pytest.importorskip("opacityhull.sim.simrig")
    from opacityhull.acquire.plan import parse_plan
    from opacityhull.acquire.runner import run_capture
    from opacityhull.session import Session

    plan = parse_plan(
        {
            "plan": {"name": "calibration-only", "seed": 3, "cameras": [1, 3, 4, 5]},
            "table": {"steps": 4},
            "exposures": {"default_s": [0.5]},
            "phases": {"calibration": {"count": 8, "charuco": BOARD, "level": 255}},
        }
    )
    out = tmp_path_factory.mktemp("simcal") / "session"
    with sim.open_sim_rig("sim:builtin:diffuse") as rig:
        run_capture(rig, plan, out, fsync=False)
        rig.ground_truth(out, [])
    s = Session.open(out)
    true = [read_opencv_yaml(out / "groundtruth" / "calibration" / f"{c.name}.yaml") for c in s.geometry.cameras]
    return s, true


def test_low_camera_is_reported_not_miscalibrated(sim_session):
    s, _ = sim_session
    # cam1 sits 24 deg above the table: the flat board is too oblique at 200x150.
    with pytest.raises(CalibrationError, match=r"camera 1 \(cam1\): only \d usable calibration view"):
        calibrate_session(s)


def test_mitsuba_captures_calibrate_the_rig(sim_session, tmp_path):
    s, true = sim_session
    res = calibrate_session(s, config=CalibrationConfig(skip_unusable_cameras=True))
    assert res.camera_indices == (3, 4, 5)
    assert set(res.uncalibrated) == {0, 1, 2} and "usable" in res.uncalibrated[1]
    assert s.charuco is not None and res.charuco.square_m == pytest.approx(0.05)
    for c in res.camera_indices:
        assert res.reproj_rms_px[c] < 0.3, res.summary()
    pe = pose_errors(res, true, align_gauge=True)
    assert pe["cameras"] == [3, 4, 5]
    # What the hull sees: the working volume reprojects like through the true cameras.
    assert pe["max_volume_reproj_px"] < 0.5, pe
    assert pe["max_rotation_deg"] < 0.4, pe
    assert pe["max_focal_pct"] < 5.0, pe  # focal/distance degeneracy of one plane at 24 deg FOV
    assert abs(pe["gauge_yaw_deg"]) < 0.2 and abs(pe["gauge_dy_mm"]) < 5.0  # board placed as declared
    # No spurious distortion on Mitsuba's distortion-free pinhole: BIC keeps (almost) none.
    for c in res.camera_indices:
        assert np.abs(res.rig_cameras[c].dist[1:]).max() == 0.0
    # Every view's camera from the rig model, exported and read back by pycolmap.
    views = [(c, a) for c, a in s.views(phase="calibration") if c in res.camera_indices]
    cams = view_cameras(res, views)
    rec = pycolmap.Reconstruction(str(export_colmap(cams, [c.name for c in cams], tmp_path / "sparse")))
    assert rec.num_images() == len(views) and rec.num_cameras() == 3
