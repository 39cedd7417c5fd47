"""ChArUco corners found again through a camera (``--interpolate aruco-calib``, OpenCV's
``calibrate_camera_charuco`` pipeline) on ray-cast boards with exact ground truth, and the
ArUco marker corners a first calibration starts from."""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.camera import Camera
from opacityhull.charuco import CharucoSpec, detect_board, marker_points, reinterpolate_board
from opacityhull.reconstruct.calibration.evaluate import render_charuco_view
from opacityhull.se3 import rigid, rodrigues

SPEC = CharucoSpec(squares_x=5, squares_y=7, square_m=0.04, marker_m=0.02, dictionary="DICT_6X6_250")
K = np.array([[460.0, 0.0, 318.0], [0.0, 460.0, 242.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.09, 0.0, 0.0, 0.0])  # a webcam's barrel distortion


def _view(rx_deg: float, ry_deg: float, seed: int):
    w, h = SPEC.size_m
    R = rodrigues(np.radians([rx_deg, ry_deg, 3.0]))
    cam_from_board = rigid(R, np.array([0.0, 0.0, 0.36]) - R @ np.array([w / 2, h / 2, 0.0]))
    cam = Camera(K=K, dist=DIST, width=640, height=480, world_from_cam=np.eye(4))
    img = render_charuco_view(
        cam, world_from_board=cam_from_board, charuco=SPEC, noise_sigma=0.01, rng=np.random.default_rng(seed)
    )
    gray = np.clip(np.asarray(img, dtype=np.float64).reshape(480, 640, -1)[..., 0] * 255 + 0.5, 0, 255)
    return gray.astype(np.uint8), cam_from_board


def _truth(cam_from_board: np.ndarray, obj: np.ndarray) -> np.ndarray:
    import cv2

    rv = cv2.Rodrigues(cam_from_board[:3, :3])[0]
    uv, _ = cv2.projectPoints(obj, rv, cam_from_board[:3, 3], K, DIST)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize(("rx", "ry", "seed"), [(25.0, -10.0, 1), (-15.0, 30.0, 2)])
def test_reinterpolated_corners_match_truth(rx, ry, seed):
    """Through the true camera, the same corners are found and lie on the true projections
    to 0.1 px RMS (cornerSubPix stops at 0.1 px); the marker corners a first calibration
    uses reproject to within 1 px (they are the polygon's unrefined corners)."""
    gray, cam_from_board = _view(rx, ry, seed)
    det = detect_board(gray, charuco=SPEC)
    assert len(det) >= 20 and len(det.marker_ids) >= 14
    again = reinterpolate_board(gray, det, charuco=SPEC, K=K, dist=DIST)
    assert set(again.ids) == set(det.ids)
    for d in (det, again):
        err = d.image_points - _truth(cam_from_board, d.object_points)
        assert float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) <= 0.1, err
    obj, img = marker_points(det, SPEC)
    assert obj.shape == (4 * len(det.marker_ids), 3) and img.shape == (len(obj), 2)
    merr = np.linalg.norm(img - _truth(cam_from_board, obj), axis=1)
    assert float(np.median(merr)) <= 1.0, merr


def test_reinterpolate_follows_the_variant():
    """An inverted, mirrored print is found again in its own variant, with the corners in
    the flipped image as ``detect_board`` gives them."""
    gray, _ = _view(20.0, 15.0, 3)
    shown = np.ascontiguousarray(255 - gray[:, ::-1])
    det = detect_board(shown, charuco=SPEC, try_mirrored=True)
    assert det.inverted and det.mirrored and len(det) >= 20
    ref = detect_board(gray, charuco=SPEC)
    again = reinterpolate_board(shown, det, charuco=SPEC, K=K, dist=DIST)
    ia, ir = {int(i): k for k, i in enumerate(again.ids)}, {int(i): k for k, i in enumerate(ref.ids)}
    common = sorted(set(ia) & set(ir))
    assert len(common) >= 20
    d = again.image_points[[ia[i] for i in common]] - ref.image_points[[ir[i] for i in common]]
    assert float(np.abs(d).max()) <= 0.15, d
