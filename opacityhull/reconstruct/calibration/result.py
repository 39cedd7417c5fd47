"""The calibration's result and its consumers (object-frame cameras of views)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Sequence

import numpy as np

from ...camera import Camera
from ...charuco import CharucoSpec
from ...errors import InputError
from ...riggeometry import RigGeometry, view_id

__all__ = ["CalibrationResult", "view_cameras", "reprojection_rms_px"]


def reprojection_rms_px(residuals_px: np.ndarray) -> float:
    """RMS length of (N, 2) pixel error vectors (NaN for none)."""
    r = np.asarray(residuals_px, dtype=np.float64).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if r.size else float("nan")


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`calibrate_observations`.

    Attributes
    ----------
    rig_cameras : list of Camera
        One per physical camera (index = rig geometry order), ``world_from_cam`` =
        ``rig_from_cam`` (rig frame at table angle 0 = object frame), calibrated ``K``
        and ``dist``.
    reproj_rms_px : list of float
        Reprojection RMS per camera over its used views, through the rig model (px,
        RMS of the 2-D error vector length); NaN for a camera not calibrated.
    per_view_rms_px : dict view id → float
        The same per used view.
    object_from_board : (4, 4) array
        Estimated placement of the board on the table at table angle 0.
    axis_dir_prealign : (C, 3) array
        Table axis direction estimated in each camera's frame from that camera's board
        poses alone, before the rig frame was defined (diagnostic; rows of cameras
        without an estimate are NaN).
    used_views : tuple of str
        View ids that entered the fit.
    dropped_views : dict view id → str
        Views left out, with the reason.
    residuals_px : (M, 2) array
        Predicted − detected corner positions of every used corner (px).
    residual_views : (M,) array of str
        View id of each residual row.
    table_scale : float
        Factor applied to recorded table angles (1 unless ``fit_table_scale``).
    fixed_intrinsics : dict camera → tuple of str
        Intrinsic parameters held fixed per camera (and why, see ``notes``).
    initial_rms_px : list of float
        Per-camera RMS of the rig model before the nlopt refinement.
    seconds : dict stage → s
        Time per stage (``detect`` is filled by :func:`calibrate_session`).
    refine_info : dict
        The nlopt refinement: ``evaluations``, ``runs`` (restarts + 1), ``cost_start``,
        ``cost_end`` (sum of squared pixel errors); empty when ``refine=False``.
    notes : tuple of str
        Decisions worth telling the user (parameters held, outliers dropped).
    charuco : CharucoSpec
        The board used.
    camera_indices : tuple of int
        The cameras that were calibrated. ``rig_cameras[c]`` is always physical camera
        ``c`` (rig geometry order); a camera that took no images in the session is left
        at its nominal pose with NaN RMS and is not listed here.
    uncalibrated : dict camera → str
        Why each camera not in ``camera_indices`` was not calibrated.
    """

    rig_cameras: list[Camera]
    reproj_rms_px: list[float]
    per_view_rms_px: dict[str, float]
    object_from_board: np.ndarray
    axis_dir_prealign: np.ndarray
    used_views: tuple[str, ...]
    dropped_views: dict[str, str]
    residuals_px: np.ndarray
    residual_views: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))
    table_scale: float = 1.0
    fixed_intrinsics: dict[int, tuple[str, ...]] = field(default_factory=dict)
    initial_rms_px: list[float] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    refine_info: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    charuco: CharucoSpec = field(default_factory=CharucoSpec)
    camera_indices: tuple[int, ...] = ()
    uncalibrated: dict[int, str] = field(default_factory=dict)

    def __post_init__(self):
        if not self.camera_indices:
            object.__setattr__(self, "camera_indices", tuple(range(len(self.rig_cameras))))

    def camera(self, index: int) -> Camera:
        """The calibrated rig camera of physical camera ``index`` (InputError when that
        camera was not calibrated)."""
        if int(index) not in self.camera_indices:
            raise InputError(f"camera {index} was not calibrated (calibrated: {list(self.camera_indices)})")
        return self.rig_cameras[int(index)]

    @property
    def calibrated_cameras(self) -> list[Camera]:
        """The calibrated rig cameras, in ``camera_indices`` order."""
        return [self.rig_cameras[c] for c in self.camera_indices]

    @property
    def rms_px(self) -> float:
        """Overall reprojection RMS (px)."""
        return reprojection_rms_px(self.residuals_px)

    def summary(self) -> dict:
        """JSON-ready summary (for ``build --json`` and ``report.json``)."""
        return {
            "reproj_rms_px": float(self.rms_px),
            "reproj_rms_px_per_camera": {
                self.rig_cameras[c].name: float(self.reproj_rms_px[c]) for c in self.camera_indices
            },
            "initial_rms_px_per_camera": {
                self.rig_cameras[c].name: float(self.initial_rms_px[c]) for c in self.camera_indices
            },
            "focal_px": {
                self.rig_cameras[c].name: [self.rig_cameras[c].fx, self.rig_cameras[c].fy] for c in self.camera_indices
            },
            "used_views": len(self.used_views),
            "dropped_views": dict(self.dropped_views),
            "table_scale": float(self.table_scale),
            "board_centre_m": (
                self.object_from_board[:3, :3] @ np.array([*np.array(self.charuco.size_m) / 2, 0.0])
                + self.object_from_board[:3, 3]
            ).tolist(),
            "board_tilt_deg": float(math.degrees(math.acos(np.clip(-self.object_from_board[1, 2], -1, 1)))),
            "fixed_intrinsics": {
                self.camera(c).name: list(v) for c, v in self.fixed_intrinsics.items() if c in self.camera_indices
            },
            "uncalibrated": {self.rig_cameras[c].name: why for c, why in self.uncalibrated.items()},
            "seconds": dict(self.seconds),
            "notes": list(self.notes),
        }


def view_cameras(result: CalibrationResult, views: Sequence[tuple[int, float]]) -> list[Camera]:
    """Object-frame cameras of views ``(camera, table_deg)``, named by view id.

    The pose comes from the rig model: ``object_from_rig(s·a) · rig_from_cam(c)`` with
    the calibrated table-angle scale ``s``.
    """
    out = []
    for c, a in views:
        c = int(c)
        if c not in result.camera_indices:
            raise InputError(
                f"view ({c}, {a}): camera {c} was not calibrated (calibrated: {list(result.camera_indices)})"
            )
        cam = RigGeometry.view_camera(result.camera(c), float(a) * result.table_scale)
        out.append(cam.with_name(view_id(c, a)))
    return out
