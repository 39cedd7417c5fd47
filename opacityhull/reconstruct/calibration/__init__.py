"""Calibration of the rig from ChArUco captures on the turntable.

Pipeline (each step a pure function over arrays, in its own module;
:func:`calibrate_session` is the runner, in :mod:`.calibrate`):

1. **Detection** (:mod:`.detect`, :func:`detect_charuco`, :func:`screen_observation`):
   linear images tone-mapped to 8 bit and searched with OpenCV 5's ``CharucoDetector``;
   views with too few or (nearly) collinear corners are dropped with the reason. With
   ``CalibrationConfig.interpolate="aruco-calib"`` (:mod:`.reinterpolate`) the corners
   are found again through a first calibration from the marker corners, as
   ``opacityhull calibrate`` does (off by default: not better on the simulated rig).
2. **Intrinsics per camera** (:mod:`.intrinsics`): ``cv2.calibrateCamera`` over that
   camera's usable views, holding what a single board plane cannot constrain (principal
   point, aspect ratio, ``k2``), the distortion model chosen by BIC, misdetections
   dropped.
3. **Turntable axis** (:mod:`.axis`, :func:`estimate_turntable_axis`) per camera from
   its board poses, which defines the rig frame; then one board placement on the table
   for all cameras (:mod:`.board`; the board's nominal yaw and height fix the gauge).
4. **Joint refinement** (:mod:`.refine`) with nlopt L-BFGS, whitened by the Gauss–Newton
   Hessian: per-camera intrinsics and ``cam_from_rig``, the board placement, optionally
   a table-angle scale. Every view (c, a) is predicted as ``cam_from_rig(c) ·
   rig_from_object(s·a) · object_from_board`` — a view never gets its own pose.

The result (:mod:`.result`, :class:`CalibrationResult`) holds the rig cameras
(``world_from_cam = rig_from_cam``), per-camera and per-view reprojection RMS, the board
placement and the dropped views with reasons; :func:`view_cameras` turns it into
object-frame cameras of views. :mod:`.evaluate` compares it with ground truth
(:func:`pose_errors`) and holds :func:`render_charuco_view`, an independent ray-cast
renderer of the board through a known (distorted) camera, the exact ground truth of the
tests and the benchmark. Rotation and pose helpers are the shared :mod:`opacityhull.se3`.
"""

from __future__ import annotations

from ...se3 import rodrigues as _rodrigues  # noqa: F401  (benchmarks/calibration.py imports it)
from ...se3 import rotation_angle_deg
from .axis import estimate_turntable_axis
from .calibrate import calibrate_observations, calibrate_session
from .config import CalibrationConfig, CalibrationError, Interpolation, ProgressCallback
from .detect import CharucoObservation, detect_charuco, screen_observation, tonemap_for_detection
from .evaluate import pose_errors, render_charuco_view
from .reinterpolate import reinterpolate_views
from .result import CalibrationResult, view_cameras

__all__ = [
    "CalibrationError",
    "CalibrationConfig",
    "CharucoObservation",
    "CalibrationResult",
    "ProgressCallback",
    "Interpolation",
    "reinterpolate_views",
    "tonemap_for_detection",
    "detect_charuco",
    "screen_observation",
    "estimate_turntable_axis",
    "calibrate_observations",
    "calibrate_session",
    "view_cameras",
    "pose_errors",
    "render_charuco_view",
    "rotation_angle_deg",
]
