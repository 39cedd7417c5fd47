"""The board's placement on the table in the calibration's gauge.

The rig frame has two gauge freedoms the captures cannot fix — a rotation about the
table axis and a shift along it — so the board's yaw and centre height are held at the
nominal :class:`~opacityhull.charuco.CharucoSpec` values; what is estimated is its
centre (x, z) on the table and (optionally) two small tilts on top of the nominal wedge.
"""

from __future__ import annotations

import math

import numpy as np

from ...camera import rot_y
from ...charuco import BOARD_R0, CharucoSpec
from ...se3 import rigid, rodrigues, rvec_from_matrix

__all__ = ["board_pose", "board_params"]


def board_pose(spec: CharucoSpec, tilt_x: float, tilt_z: float, cx: float, cz: float) -> np.ndarray:
    """``object_from_board`` (4, 4) in the gauge: yaw = spec.yaw_deg, centre height = spec.height_m.

    ``tilt_x, tilt_z`` are a rotation vector's x and z components (radians) applied on
    top of the nominal wedge; ``cx, cz`` the board centre on the table (metres).
    """
    R = rot_y(math.radians(spec.yaw_deg)) @ rodrigues([tilt_x, 0.0, tilt_z]) @ spec.tilt_rotation() @ BOARD_R0
    w, h = spec.size_m
    centre = np.array([cx, spec.height_m, cz])
    return rigid(R, centre - R @ np.array([w / 2, h / 2, 0.0]))


def board_params(spec: CharucoSpec, object_from_board: np.ndarray) -> np.ndarray:
    """Inverse of :func:`board_pose`: ``(tilt_x, tilt_z, cx, cz)`` of a (4, 4) pose,
    projected onto the gauge (its yaw and height are dropped)."""
    R = object_from_board[:3, :3]
    Rt = rot_y(math.radians(spec.yaw_deg)).T @ R @ (spec.tilt_rotation() @ BOARD_R0).T
    rv = rvec_from_matrix(Rt)
    w, h = spec.size_m
    centre = object_from_board[:3, 3] + R @ np.array([w / 2, h / 2, 0.0])
    return np.array([rv[0], rv[2], centre[0], centre[2]])
