"""Rigid transforms (SE(3)) and rotations (SO(3)) as plain NumPy arrays.

The one place for the small rotation and pose helpers: 4×4 homogeneous rigid
transforms ``T = [[R, t], [0, 1]]`` named ``a_from_b`` (``x_a = T @ x_b``), 3×3
rotation matrices and OpenCV rotation vectors (axis × angle in radians, as
``cv2.Rodrigues``). Frame conventions of the rig (``rot_y``, ``rig_from_object``) live
in :mod:`opacityhull.camera`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "rodrigues",
    "rvec_from_matrix",
    "rigid",
    "invert_rigid",
    "project_to_so3",
    "mean_pose",
    "axis_rotation",
    "rotation_angle_deg",
    "wrap_deg",
]


def rodrigues(rvec: ArrayLike) -> np.ndarray:
    """(3, 3) rotation matrix of the rotation vector ``rvec`` (3,) (radians; ``cv2.Rodrigues``)."""
    import cv2

    return np.asarray(cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0])


def rvec_from_matrix(R: ArrayLike) -> np.ndarray:
    """(3,) rotation vector (radians) of the (3, 3) rotation matrix ``R``; inverse of :func:`rodrigues`.

    OpenCV's conversion: a rotation by less than about 1e-5 rad (sin θ < 1e-5) comes back
    as the zero vector (measured: 1e-5 rad about +Z → 0), which is below anything the
    calibration resolves.
    """
    import cv2

    return np.asarray(cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0]).ravel()


def rigid(R: ArrayLike, t: ArrayLike) -> np.ndarray:
    """(4, 4) rigid transform from a (3, 3) rotation ``R`` and a (3,) translation ``t``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform: ``[[Rᵀ, −Rᵀt], [0, 1]]`` (exact, no general solve)."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def project_to_so3(M: ArrayLike) -> np.ndarray:
    """The rotation matrix nearest to the (3, 3) matrix ``M`` in the Frobenius norm
    (SVD, with the sign fixed so that the determinant is +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def mean_pose(Ts: Sequence[np.ndarray], weights: ArrayLike | None = None) -> np.ndarray:
    """Chordal mean of (4, 4) rigid transforms (rotation: SVD projection of the weighted
    sum of rotation matrices; translation: weighted mean). ``weights`` (N,), default equal."""
    w = np.ones(len(Ts)) if weights is None else np.asarray(weights, dtype=np.float64)
    R_sum = np.zeros((3, 3))
    t_sum = np.zeros(3)
    for wi, T in zip(w, Ts, strict=True):
        R_sum += wi * T[:3, :3]
        t_sum += wi * T[:3, 3]
    return rigid(project_to_so3(R_sum), t_sum / w.sum())


def axis_rotation(d: ArrayLike, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about the unit vector ``d`` (3,) (right-handed)."""
    return rodrigues(np.asarray(d, dtype=np.float64) * angle_rad)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a (3, 3) rotation matrix in degrees (0..180), accurate near 0 and 180
    (``atan2`` of the skew part's norm and the trace, not ``acos`` of the trace)."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return math.degrees(math.atan2(s, c))


def wrap_deg(a: ArrayLike) -> np.ndarray:
    """Angles in degrees wrapped to [-180, 180)."""
    return (np.asarray(a, dtype=np.float64) + 180.0) % 360.0 - 180.0
