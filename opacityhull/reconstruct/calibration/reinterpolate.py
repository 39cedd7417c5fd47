"""Step 1b of the calibration (``CalibrationConfig.interpolate="aruco-calib"``): the
ChArUco corners found again through a first camera estimate, as ``opacityhull calibrate``
does (OpenCV's ``calibrate_camera_charuco`` sample).

OpenCV's ``CharucoDetector`` without a camera places each corner from the homography of
its neighbouring markers, and ``cornerSubPix`` stops at 0.1 px
(``cornerRefinementMinAccuracy``): where it starts shows in the result. Here each camera
is first calibrated from the decoded markers' corners alone (step 2's
:func:`fit_intrinsics`, so the principal point and aspect ratio are held where one
board plane cannot constrain them), then every view's corners are projected through
that camera and refined again (:func:`opacityhull.charuco.reinterpolate_board`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from ...camera import Camera
from ...charuco import BoardDetection, CharucoSpec, reinterpolate_board
from .config import CalibrationConfig
from .detect import CharucoObservation, marker_observation, observation_from, screen_observation
from .intrinsics import fit_intrinsics

__all__ = ["reinterpolate_views"]

log = logging.getLogger(__name__)


def reinterpolate_views(
    detections: Sequence[tuple[CharucoObservation, BoardDetection]],
    *,
    gray_of: Callable[[str], np.ndarray],
    image_sizes: Mapping[int, tuple[int, int]],
    charuco: CharucoSpec,
    nominal: Sequence[Camera] | None,
    config: CalibrationConfig,
) -> tuple[list[CharucoObservation], list[str]]:
    """Every view's ChArUco corners re-found through its camera's marker-corner calibration.

    Parameters
    ----------
    detections : sequence of (CharucoObservation, BoardDetection)
        One per view, as :func:`opacityhull.charuco.detect_board` found it.
    gray_of : callable view id → (H, W) uint8 array
        The image the detection searched (called once per view with markers).
    image_sizes : mapping camera index → (width, height)
    charuco : CharucoSpec
    nominal : sequence of Camera, optional
        Initial ``K`` (and held principal point / aspect ratio) of each camera.
    config : CalibrationConfig

    Returns
    -------
    observations : list of CharucoObservation
        Same views and order as ``detections``; a camera whose markers cannot calibrate
        it (fewer than three usable views) keeps its first-pass corners.
    notes : list of str
        One line per camera: what the corners were re-found through, or why not.
    """
    out = [obs for obs, _ in detections]
    notes: list[str] = []
    for c in sorted(image_sizes):
        name = nominal[c].name if nominal is not None and nominal[c].name else f"cam{c}"
        mine = [k for k, (obs, _) in enumerate(detections) if obs.camera == c]
        markers = [
            marker_observation(detections[k][1], charuco=charuco, camera=c, table_deg=detections[k][0].table_deg)
            for k in mine
        ]
        usable = [m for m in markers if screen_observation(m, charuco=charuco, config=config) is None]
        if len(usable) < 3:
            notes.append(f"{name}: {len(usable)} view(s) with usable marker corners; first-pass corners kept")
            continue
        fit = fit_intrinsics(
            usable, size=image_sizes[c], K0=None if nominal is None else nominal[c].K, config=config, name=name
        )
        if fit.K is None or fit.dist is None:
            notes.append(f"{name}: marker corners left {fit.n_views} view(s) after screening; first-pass corners kept")
            continue
        for k in mine:
            obs, det = detections[k]
            if len(det.marker_ids) == 0:
                continue
            again = reinterpolate_board(gray_of(obs.view), det, charuco=charuco, K=fit.K, dist=fit.dist)
            out[k] = observation_from(again, camera=c, table_deg=obs.table_deg)
        notes.append(
            f"{name}: corners re-found through the camera calibrated from {fit.n_views} views' marker corners "
            f"(fx {fit.K[0, 0]:.1f} px, held {', '.join(fit.fixed) or 'nothing'})"
        )
        log.debug(notes[-1])
    return out, notes
