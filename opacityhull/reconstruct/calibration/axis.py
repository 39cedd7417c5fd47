"""Step 3 of the calibration: the turntable axis and the rig frame seen from one camera.

Every relative motion of the board between two table angles is a rotation about the
axis: its direction is the common fixed vector of the relative rotations (sign: rotation
by ``+Δa``), and a point on it solves ``(I − Q) o = t_j − Q t_i`` in least squares. The
rig frame follows: +Y = axis, origin = axis ∩ board top plane shifted down by the board
height, azimuth from the board's x axis at table angle 0 (the gauge fixed by
:meth:`opacityhull.charuco.CharucoSpec.object_from_board`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ...charuco import CharucoSpec
from ...errors import ShapeError
from ...se3 import axis_rotation, mean_pose, rigid, wrap_deg
from .config import CalibrationError

__all__ = ["estimate_turntable_axis", "rig_from_axis"]


def estimate_turntable_axis(
    table_deg: Sequence[float], cam_from_board: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The turntable axis in a camera's frame from board poses at several table angles.

    Parameters
    ----------
    table_deg : (V,) table angles in degrees (at least two distinct ones).
    cam_from_board : V 4×4 board poses in the camera frame (e.g. from ``solvePnP``).

    Returns
    -------
    direction : (3,) unit axis direction; a table angle ``+a`` is a right-handed rotation
        by ``a`` about it (so it is the rig's +Y seen from the camera).
    point : (3,) the point of the axis closest to the mean board position.
    cam_from_board0 : (4, 4) the board pose at table angle 0, averaged over all views
        after rotating each back about the axis.
    """
    a = np.asarray(table_deg, dtype=np.float64)
    Ts = [np.asarray(T, dtype=np.float64) for T in cam_from_board]
    if a.shape[0] != len(Ts):
        raise ShapeError(f"{a.shape[0]} table angles for {len(Ts)} poses")
    M = np.zeros((3, 3))
    vee_sum = np.zeros(3)
    rows, rhs = [], []
    npairs = 0
    for i in range(len(Ts)):
        for j in range(i + 1, len(Ts)):
            dlt = math.radians(float(wrap_deg(a[j] - a[i])))
            if abs(math.sin(dlt / 2.0)) < math.sin(math.radians(0.5)):
                continue  # (nearly) the same angle: no information about the axis
            Q = Ts[j][:3, :3] @ Ts[i][:3, :3].T
            A = Q - np.eye(3)
            M += A.T @ A
            vee = 0.5 * np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
            vee_sum += math.sin(dlt) * vee
            rows.append(np.eye(3) - Q)
            rhs.append(Ts[j][:3, 3] - Q @ Ts[i][:3, 3])
            npairs += 1
    if npairs == 0:
        raise CalibrationError(
            f"turntable axis: the usable views are all at the same table angle ({sorted(set(np.round(a, 3)))}); "
            "need at least two distinct angles"
        )
    w, V = np.linalg.eigh(M)
    d = V[:, 0]
    # Sign: rotations by +Δa about +d. With only ±180° pairs the sense is invisible; the
    # board then decides (it lies face up, its z axis points down the table axis).
    if abs(vee_sum @ d) > 1e-6 * max(1.0, np.linalg.norm(vee_sum)) and np.linalg.norm(vee_sum) > 1e-9:
        if vee_sum @ d < 0:
            d = -d
    else:
        up = -sum(T[:3, 2] for T in Ts)
        if up @ d < 0:
            d = -d
    centre = np.mean([T[:3, 3] for T in Ts], axis=0)
    A = np.vstack(rows + [d[None, :]])
    b = np.concatenate(rhs + [np.array([d @ centre])])
    o = np.linalg.lstsq(A, b, rcond=None)[0]
    back = []
    for ai, T in zip(a, Ts, strict=True):
        Rb = axis_rotation(d, -math.radians(ai))
        Mb = rigid(Rb, o - Rb @ o)
        back.append(Mb @ T)
    return d, o, mean_pose(back)


def rig_from_axis(d, o, cam_from_board0, spec: CharucoSpec) -> np.ndarray:
    """``cam_from_rig`` from the axis (camera frame) and the board at table angle 0."""
    n = cam_from_board0[:3, 2]
    if abs(float(d @ n)) < 1e-6:
        raise CalibrationError("turntable axis lies in the board plane: the board stands upright on the table")
    # The gauge puts the board's centre at height spec.height_m above the table top: the
    # rig origin is the centre's foot on the axis, lowered by that height. (For a flat
    # board this is where the axis meets the board plane; for a board on a wedge it is not.)
    w, h = spec.size_m
    centre = cam_from_board0[:3, :3] @ np.array([w / 2, h / 2, 0.0]) + cam_from_board0[:3, 3]
    origin = o + float((centre - o) @ d) * d - spec.height_m * d
    bx = cam_from_board0[:3, 0]
    v = bx - (bx @ d) * d
    v /= np.linalg.norm(v)
    psi = math.radians(spec.yaw_deg)
    ex = math.cos(psi) * v - math.sin(psi) * np.cross(d, v)
    ez = np.cross(ex, d)
    return rigid(np.column_stack([ex, d, ez]), origin)
