"""Options and the error of the rig calibration (:mod:`opacityhull.reconstruct.calibration`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Callable
from typing import Literal

from ...errors import ConfigError, InputError

__all__ = ["CalibrationError", "CalibrationConfig", "ProgressCallback", "Interpolation"]

ProgressCallback = Callable[[int, int], None]

#: How ChArUco corners are placed before sub-pixel refinement; the names of
#: ``opacityhull calibrate --interpolate`` (see :mod:`opacityhull.calibrate.inputs`).
Interpolation = Literal["homography", "aruco-calib"]


class CalibrationError(InputError):
    """The captures cannot calibrate the rig (e.g. a camera with fewer than three usable
    views). The message names the camera, how many views were usable and why the others
    were dropped."""


@dataclass(frozen=True, kw_only=True)
class CalibrationConfig:
    """Options of :func:`calibrate_observations` / :func:`calibrate_session`.

    Parameters
    ----------
    min_corners : int
        Views with fewer detected ChArUco corners are dropped.
    min_spread_squares : float
        Views whose corners' minor-axis standard deviation on the board is below this
        many squares are dropped as collinear.
    min_image_spread_px : float
        Views whose corners' minor-axis standard deviation in the image is below this
        (board seen edge-on) are dropped.
    max_view_rms_px : float
        After the per-camera ``calibrateCamera``, views with a reprojection RMS above
        ``max(max_view_rms_px, 3 × median)`` are dropped as misdetections and the camera
        is calibrated again.
    refine : bool
        Run the joint nlopt refinement of the rig model (else the initial rig model from
        step 3 is returned, still predicting every view from the model).
    fix_k3, fix_k2, fix_tangential : bool or None
        Hold these distortion coefficients at 0. ``fix_k2=None``: automatic (held when
        the corners cover less than ``min_k2_coverage`` of the image half-diagonal).
    fix_principal_point, fix_aspect_ratio : bool or None
        Hold the principal point / ``fx/fy`` at the nominal values. ``None``: automatic,
        held when the board normals seen by the camera span less than
        ``min_plane_spread_deg`` (a single plane constrains only two intrinsics).
    min_plane_spread_deg, min_k2_coverage : float
        Thresholds of the automatic choices above.
    min_fov_free_principal_point_deg : float
        Even with varied board normals, the principal point is held at nominal for
        cameras whose diagonal field of view is narrower than this: under a narrow
        perspective a shifted principal point is nearly the same as a rotated camera.
        Measured on the simulated rig (24° vertical FOV, board on a 35° wedge, 8 table
        angles): freeing it gave principal points 1–46 px off and rotations 0.27–7.8°
        off; holding it gave 0.07–0.20° and 0.07–0.16 px reprojection over the working
        volume.
    select_distortion : bool
        Choose the distortion model per camera by BIC among the nested models none ⊂ k1
        ⊂ k1k2 ⊂ k1k2p1p2 (⊂ +k3) allowed by the ``fix_*`` options; else use the
        largest allowed model.
    fit_board_tilt : bool
        Estimate the board's tilt relative to the table axis (2 DoF).
    fit_table_scale : bool
        Estimate a common scale of the table angles (an encoder steps-per-degree error).
        A constant table-angle offset is not observable (it is the board yaw gauge).
    skip_unusable_cameras : bool
        Leave a camera with fewer than three usable views uncalibrated (nominal, listed
        in ``CalibrationResult.uncalibrated``) instead of raising
        :class:`CalibrationError` — for a build that can drop that camera's views.
    max_iter : int
        Maximum objective evaluations of each nlopt run.
    restarts : int
        The refinement re-whitens its variables and restarts up to this many times
        while the cost still drops by more than 1e-9 relative.
    tonemap_percentile : float
        Percentile of the luminance mapped to white for detection.
    detect_upscale : tuple of int
        Resolution factors the detector tries (see :func:`detect_charuco`).
    detect_max_upscaled_px : int
        Upscaled images stay below this size on their long side.
    interpolate : {"aruco-calib", "homography"}
        How :func:`calibrate_session` places the ChArUco corners before ``cornerSubPix``.
        ``homography``: OpenCV's ``CharucoDetector`` without a camera (each corner from
        its neighbouring markers' homography), one pass. ``aruco-calib``: as
        ``opacityhull calibrate`` (OpenCV's ``calibrate_camera_charuco`` sample): each
        camera first calibrated from the decoded markers' corners (step 2's
        :func:`fit_intrinsics`, with its held intrinsics), every view's corners found
        again through that camera (:func:`opacityhull.charuco.reinterpolate_board`),
        then the calibration solved from those corners. ``homography`` is the default
        here (unlike the ``calibrate`` command) because the simulated rig is not better
        with ``aruco-calib`` (benchmarks/turntable_interpolation.py): the corners land as
        close or closer to the true projections, and the RMS drops (tiny plan 0.176 ->
        0.158 px, demo 0.153 -> 0.141 px), but with 3-7 views per camera the lower
        residual lets BIC choose a spurious distortion (demo cam0: k1 = 0.49 on a
        pinhole) and the working volume reprojects worse (tiny 0.20 -> 0.77 px, demo
        0.16 -> 0.80 px, rotation 0.20 -> 0.35 deg); at twice the resolution rotation is
        equal and the volume better (0.14 -> 0.11 px) but position and focal worse
        (5.9 -> 8.1 mm, 0.44 -> 0.74 %).
    """

    min_corners: int = 8
    min_spread_squares: float = 0.3
    min_image_spread_px: float = 2.0
    max_view_rms_px: float = 2.0
    refine: bool = True
    fix_k3: bool = True
    fix_k2: bool | None = None
    fix_tangential: bool = False
    fix_principal_point: bool | None = None
    fix_aspect_ratio: bool | None = None
    min_plane_spread_deg: float = 10.0
    min_fov_free_principal_point_deg: float = 40.0
    min_k2_coverage: float = 0.6
    select_distortion: bool = True
    fit_board_tilt: bool = True
    fit_table_scale: bool = False
    skip_unusable_cameras: bool = False
    max_iter: int = 400
    restarts: int = 3
    tonemap_percentile: float = 99.5
    detect_upscale: tuple[int, ...] = (1, 2, 3)
    detect_max_upscaled_px: int = 2048
    interpolate: Interpolation = "homography"

    def __post_init__(self):
        if int(self.min_corners) < 4:
            raise ConfigError(f"CalibrationConfig.min_corners={self.min_corners}: need at least 4 corners per view")
        for name in (
            "min_spread_squares",
            "min_image_spread_px",
            "max_view_rms_px",
            "min_plane_spread_deg",
            "min_k2_coverage",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"CalibrationConfig.{name}={v!r}: expected a finite number >= 0")
        if int(self.max_iter) < 1 or int(self.restarts) < 0:
            raise ConfigError(
                f"CalibrationConfig: max_iter={self.max_iter} must be >= 1, restarts={self.restarts} >= 0"
            )
        if not self.detect_upscale or any(int(f) < 1 for f in self.detect_upscale):
            raise ConfigError(f"CalibrationConfig.detect_upscale={self.detect_upscale!r}: expected factors >= 1")
        if self.interpolate not in ("aruco-calib", "homography"):
            raise ConfigError(
                f"CalibrationConfig.interpolate={self.interpolate!r}: expected 'aruco-calib' or 'homography'"
            )
        if not 50.0 <= float(self.tonemap_percentile) <= 100.0:
            raise ConfigError(f"CalibrationConfig.tonemap_percentile={self.tonemap_percentile}: expected 50..100")
