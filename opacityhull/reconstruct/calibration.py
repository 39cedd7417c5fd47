"""Calibration of the rig from ChArUco captures on the turntable.

Pipeline (each step a pure function over arrays; :func:`calibrate_session` is the runner):

1. **Detection** (:func:`detect_charuco`): linear float images are tone-mapped to 8 bit
   (luminance / high percentile, sRGB encoding) and searched with OpenCV 5's
   ``CharucoDetector.detectBoard`` → ``board.matchImagePoints``. Views with too few
   corners, or whose corners are (nearly) collinear on the board or in the image, are
   dropped with the reason recorded (collinear corners make ``cv2.calibrateCamera``
   assert).
2. **Intrinsics per camera** (``cv2.calibrateCamera`` over that camera's usable views).
   A board lying flat on a turntable shows every camera *one plane* only — turning the
   board inside its own plane adds no information about ``K`` — and one plane
   constrains just two intrinsic parameters (Zhang 2000; Sturm & Maybank 1999): with
   ``fx, fy, cx, cy`` all free the problem is degenerate (measured: fy off by 40 %,
   cx by 30 px at 0.1 px noise). So by default (``fix_principal_point=None``,
   ``fix_aspect_ratio=None``) the principal point and the aspect ratio are held at the
   nominal values whenever the board normals seen by a camera span less than
   ``min_plane_spread_deg``; a board tilted on a wedge (normals precessing as the
   table turns) frees them. ``k2`` is likewise held at 0 when the corners never reach
   ``min_k2_coverage`` of the image half-diagonal (an r⁴ term fitted on the centre
   alone extrapolates wildly towards the corners).
3. **Turntable axis** (per camera, from the ``calibrateCamera`` board poses): every
   relative motion between two table angles is a rotation about the axis; its
   direction is the common fixed vector of the relative rotations (sign: rotation by
   ``+Δa``), a point on it solves ``(I − Q) o = t_j − Q t_i`` in least squares. The rig
   frame follows: +Y = axis, origin = axis ∩ board top plane shifted down by the board
   height, azimuth from the board's x axis at table angle 0 (the gauge fixed by
   :meth:`opacityhull.charuco.CharucoSpec.object_from_board`).
4. **Joint refinement** with nlopt (``LD_LBFGS`` on the sum of squared reprojection
   errors, analytic gradient from ``cv2.projectPoints``' Jacobian, variables whitened
   by the Gauss–Newton Hessian at the start so L-BFGS takes Newton-like steps):
   per-camera intrinsics (those not held), per-camera ``cam_from_rig`` (6 DoF), the
   board's placement on the table (centre x, z and two tilts; yaw and height are the
   gauge) and optionally a table-angle scale. Every observation (c, a) is predicted as
   ``cam_from_rig(c) · rig_from_object(s·a) · object_from_board`` — a view never gets
   its own pose.

The result (:class:`CalibrationResult`) holds the rig cameras (``world_from_cam =
rig_from_cam``), per-camera and per-view reprojection RMS, the board placement and the
dropped views with reasons. :func:`view_cameras` turns it into object-frame cameras of
views; :func:`pose_errors` compares it with ground truth. :func:`render_charuco_view`
is an independent ray-cast renderer of the board through a known (distorted) camera,
used by tests and the benchmark as exact ground truth.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from ..camera import Camera, rig_from_object, rot_y
from ..charuco import CharucoSpec
from ..errors import ConfigError, InputError, ShapeError
from ..riggeometry import RigGeometry, view_id

__all__ = [
    "CalibrationError",
    "CalibrationConfig",
    "CharucoObservation",
    "CalibrationResult",
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

ProgressCallback = Callable[[int, int], None]


class CalibrationError(InputError):
    """The captures cannot calibrate the rig (e.g. a camera with fewer than three usable
    views). The message names the camera, how many views were usable and why the others
    were dropped."""


# --------------------------------------------------------------------------- config


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

    def __post_init__(self):
        if int(self.min_corners) < 4:
            raise ConfigError(f"CalibrationConfig.min_corners={self.min_corners}: need at least 4 corners per view")
        for name in ("min_spread_squares", "min_image_spread_px", "max_view_rms_px", "min_plane_spread_deg",
                     "min_k2_coverage"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"CalibrationConfig.{name}={v!r}: expected a finite number >= 0")
        if int(self.max_iter) < 1 or int(self.restarts) < 0:
            raise ConfigError(f"CalibrationConfig: max_iter={self.max_iter} must be >= 1, restarts={self.restarts} >= 0")
        if not self.detect_upscale or any(int(f) < 1 for f in self.detect_upscale):
            raise ConfigError(f"CalibrationConfig.detect_upscale={self.detect_upscale!r}: expected factors >= 1")
        if not 50.0 <= float(self.tonemap_percentile) <= 100.0:
            raise ConfigError(f"CalibrationConfig.tonemap_percentile={self.tonemap_percentile}: expected 50..100")


# --------------------------------------------------------------------------- observations


@dataclass(frozen=True)
class CharucoObservation:
    """Detected ChArUco corners of one view (camera ``camera`` at ``table_deg``).

    Attributes
    ----------
    camera : int
        Physical camera index.
    table_deg : float
        Turntable angle in degrees.
    ids : (N,) int array
        ChArUco corner ids.
    image_points : (N, 2) float array
        Corner positions in pixels (OpenCV convention: top-left pixel centre = (0, 0)).
    object_points : (N, 3) float array
        The same corners in the board frame, metres (z = 0).
    """

    camera: int
    table_deg: float
    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray

    def __post_init__(self):
        ids = np.asarray(self.ids, dtype=np.int32).ravel()
        ip = np.asarray(self.image_points, dtype=np.float64).reshape(-1, 2)
        op = np.asarray(self.object_points, dtype=np.float64).reshape(-1, 3)
        if not (ids.shape[0] == ip.shape[0] == op.shape[0]):
            raise ShapeError(
                f"observation {self.view}: {ids.shape[0]} ids, {ip.shape[0]} image points and "
                f"{op.shape[0]} object points; expected the same count"
            )
        object.__setattr__(self, "camera", int(self.camera))
        object.__setattr__(self, "table_deg", float(self.table_deg))
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "image_points", ip)
        object.__setattr__(self, "object_points", op)

    @property
    def view(self) -> str:
        return view_id(self.camera, self.table_deg)

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def tonemap_for_detection(image, *, percentile: float = 99.5) -> np.ndarray:
    """Linear float image → 8-bit sRGB-encoded luminance for the marker detector.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
        Linear values (C = 1..4; the first three channels are Rec.709 RGB, a fourth
        channel (alpha) is ignored). NaN counts as black, +Inf as white.
    percentile : float
        Luminance percentile mapped to white (robust against specular highlights).

    Returns
    -------
    (H, W) uint8 array.
    """
    from ..imageio import srgb_encode

    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 3:
        if a.shape[2] >= 3:
            lum = 0.2126 * a[..., 0] + 0.7152 * a[..., 1] + 0.0722 * a[..., 2]
        elif a.shape[2] in (1, 2):
            lum = a[..., 0]
        else:
            raise ShapeError(f"image has shape {a.shape}, expected (H, W) or (H, W, 1..4)")
    elif a.ndim == 2:
        lum = a
    else:
        raise ShapeError(f"image has shape {a.shape}, expected (H, W) or (H, W, 1..4)")
    finite = np.isfinite(lum)
    scale = float(np.percentile(lum[finite], percentile)) if finite.any() else 0.0
    if not scale > 0:
        scale = float(lum[finite].max()) if finite.any() else 0.0
    if not scale > 0:  # nothing positive and finite: only +Inf shows
        return np.where(np.isposinf(lum), 255, 0).astype(np.uint8)
    v = np.where(finite, lum / scale, np.where(np.isposinf(lum), 1.0, 0.0))
    return np.round(srgb_encode(v) * 255.0).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def _detector(spec: CharucoSpec):
    import cv2

    board = spec.board()
    return board, cv2.aruco.CharucoDetector(board)


def detect_charuco(image, *, charuco: CharucoSpec, camera: int = 0, table_deg: float = 0.0,
                   percentile: float = 99.5, upscale: Sequence[int] = (1, 2, 3),
                   max_upscaled_px: int = 2048) -> CharucoObservation:
    """Detect the ChArUco corners of ``charuco`` in one image.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
        Linear float image (or already 8-bit: uint8 images are used as they are).
    charuco : CharucoSpec
        The board.
    camera, table_deg : the view the image belongs to (copied into the result).
    percentile : tone-mapping white point, see :func:`tonemap_for_detection`.
    upscale : sequence of int
        Resolution factors tried in turn (bicubic) until every corner of the board is
        found; the factor finding the most corners wins. Markers of a few pixels per bit
        (small boards, low-resolution cameras, grazing views) are found only on an
        upscaled image. Factors whose image would exceed ``max_upscaled_px`` on its long
        side are skipped.

    Returns
    -------
    CharucoObservation
        Corner positions in the original image's pixels; possibly zero corners.
    """
    import cv2

    a = np.asarray(image)
    if a.dtype == np.uint8:
        gray = a if a.ndim == 2 else (a[..., :3].mean(axis=2).round().astype(np.uint8) if a.shape[2] >= 3 else a[..., 0])
    else:
        gray = tonemap_for_detection(a, percentile=percentile)
    gray = np.ascontiguousarray(gray)
    board, det = _detector(charuco)
    n_total = (charuco.squares_x - 1) * (charuco.squares_y - 1)
    best = (None, None, 1)
    for f in upscale:
        f = int(f)
        if f < 1 or (f > 1 and max(gray.shape) * f > max_upscaled_px):
            continue
        g = gray if f == 1 else cv2.resize(gray, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
        corners, ids, _, _ = det.detectBoard(g)
        n = 0 if ids is None or corners is None else len(ids)
        if n > (0 if best[1] is None else len(best[1])):
            best = (corners, ids, f)
        if n >= n_total:
            break
    corners, ids, f = best
    if ids is None or len(ids) == 0:
        return CharucoObservation(camera, table_deg, np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros((0, 3)))
    obj, img = board.matchImagePoints(corners, ids)
    # cv2.resize maps pixel centres as x_up = (x + 0.5) f − 0.5.
    img = (np.asarray(img, dtype=np.float64).reshape(-1, 2) + 0.5) / f - 0.5
    return CharucoObservation(camera, table_deg, ids.ravel(), img, np.asarray(obj).reshape(-1, 3))


def _minor_std(points2: np.ndarray) -> float:
    """Standard deviation along the minor principal axis of a 2-D point set."""
    if points2.shape[0] < 2:
        return 0.0
    c = np.cov(points2.T)
    return float(math.sqrt(max(np.linalg.eigvalsh(c)[0], 0.0)))


def screen_observation(obs: CharucoObservation, *, charuco: CharucoSpec,
                       config: CalibrationConfig = CalibrationConfig()) -> str | None:
    """Why ``obs`` cannot be used for calibration, or None when it can.

    Checks the corner count, finiteness, collinearity on the board (minor-axis spread
    of the object points, in squares) and in the image (board seen edge-on).
    """
    n = len(obs)
    if n == 0:
        return "no ChArUco corners detected"
    if n < config.min_corners:
        return f"only {n} corners detected (min_corners={config.min_corners})"
    if not (np.all(np.isfinite(obs.image_points)) and np.all(np.isfinite(obs.object_points))):
        return "non-finite corner coordinates"
    spread = _minor_std(obs.object_points[:, :2]) / charuco.square_m
    if spread < config.min_spread_squares:
        return (f"corners (nearly) collinear on the board: minor-axis spread {spread:.3f} squares "
                f"< min_spread_squares={config.min_spread_squares}")
    ispread = _minor_std(obs.image_points)
    if ispread < config.min_image_spread_px:
        return (f"corners (nearly) collinear in the image (board seen edge-on): minor-axis spread "
                f"{ispread:.2f} px < min_image_spread_px={config.min_image_spread_px}")
    return None


# --------------------------------------------------------------------------- small geometry


def _rodrigues(rvec) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def _rvec(R) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _rt(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _project_to_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _mean_pose(Ts: Sequence[np.ndarray], weights=None) -> np.ndarray:
    """Chordal mean of rigid transforms (rotation: SVD projection of the weighted sum)."""
    w = np.ones(len(Ts)) if weights is None else np.asarray(weights, dtype=np.float64)
    R = _project_to_so3(sum(wi * T[:3, :3] for wi, T in zip(w, Ts)))
    t = sum(wi * T[:3, 3] for wi, T in zip(w, Ts)) / w.sum()
    return _rt(R, t)


def _axis_rotation(d: np.ndarray, angle_rad: float) -> np.ndarray:
    """3×3 rotation by ``angle_rad`` about the unit vector ``d`` (right-handed)."""
    import cv2

    return cv2.Rodrigues((np.asarray(d, dtype=np.float64) * angle_rad).reshape(3, 1))[0]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a 3×3 rotation matrix in degrees (0..180)."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return math.degrees(math.atan2(s, c))


def _wrap_deg(a):
    return (np.asarray(a, dtype=np.float64) + 180.0) % 360.0 - 180.0


# --------------------------------------------------------------------------- axis


def estimate_turntable_axis(table_deg: Sequence[float], cam_from_board: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
            dlt = math.radians(float(_wrap_deg(a[j] - a[i])))
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
    for ai, T in zip(a, Ts):
        Rb = _axis_rotation(d, -math.radians(ai))
        Mb = _rt(Rb, o - Rb @ o)
        back.append(Mb @ T)
    return d, o, _mean_pose(back)


def _rig_from_axis(d, o, cam_from_board0, spec: CharucoSpec) -> np.ndarray:
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
    return _rt(np.column_stack([ex, d, ez]), origin)


# --------------------------------------------------------------------------- board placement (gauge)

_R0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # board x→+X, y→+Z, z→−Y


def _board_pose(spec: CharucoSpec, tilt_x: float, tilt_z: float, cx: float, cz: float) -> np.ndarray:
    """``object_from_board`` in the gauge: yaw = spec.yaw_deg, centre height = spec.height_m."""
    R = rot_y(math.radians(spec.yaw_deg)) @ _rodrigues([tilt_x, 0.0, tilt_z]) @ spec.tilt_rotation() @ _R0
    w, h = spec.size_m
    centre = np.array([cx, spec.height_m, cz])
    return _rt(R, centre - R @ np.array([w / 2, h / 2, 0.0]))


def _board_params(spec: CharucoSpec, object_from_board: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_board_pose` (projects onto the gauge)."""
    R = object_from_board[:3, :3]
    Rt = rot_y(math.radians(spec.yaw_deg)).T @ R @ (spec.tilt_rotation() @ _R0).T
    rv = _rvec(Rt)
    w, h = spec.size_m
    centre = object_from_board[:3, 3] + R @ np.array([w / 2, h / 2, 0.0])
    return np.array([rv[0], rv[2], centre[0], centre[2]])


# --------------------------------------------------------------------------- rig model


@dataclass
class _CamBlock:
    index: int
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    cam_from_rig: np.ndarray
    free: tuple[str, ...]          # free intrinsics: f | fx, fy; cx, cy; k1, k2, p1, p2, k3
    aspect: float                  # fx / fy when "f" is the parameter
    obj: np.ndarray                # (N, 3) board points of all its views
    img: np.ndarray                # (N, 2)
    angle: np.ndarray              # (N,) table degrees per point
    view_of_point: np.ndarray      # (N,) index into views
    views: list[str]
    offset: int = 0                # start of its parameters in x

    @property
    def n_params(self) -> int:
        return len(self.free) + 6


class _RigModel:
    """Parameter packing, residuals and Jacobian of the turntable rig model."""

    def __init__(self, blocks: list[_CamBlock], spec: CharucoSpec, board: np.ndarray, *,
                 fit_tilt: bool, fit_scale: bool, scale: float = 1.0):
        self.blocks = blocks
        self.spec = spec
        self.fit_tilt = fit_tilt
        self.fit_scale = fit_scale
        off = 0
        for b in blocks:
            b.offset = off
            off += b.n_params
        self.board_offset = off
        self.board_names = (["tilt_x", "tilt_z"] if fit_tilt else []) + ["centre_x", "centre_z"]
        off += len(self.board_names)
        self.scale_offset = off if fit_scale else None
        self.n = off + (1 if fit_scale else 0)
        self.board0 = np.asarray(board, dtype=np.float64)  # (tilt_x, tilt_z, cx, cz)
        self.scale0 = scale

    # ---- packing
    def pack(self) -> np.ndarray:
        x = np.zeros(self.n)
        for b in self.blocks:
            vals = {"f": b.K[1, 1], "fx": b.K[0, 0], "fy": b.K[1, 1], "cx": b.K[0, 2], "cy": b.K[1, 2],
                    "k1": b.dist[0], "k2": b.dist[1], "p1": b.dist[2], "p2": b.dist[3], "k3": b.dist[4]}
            for i, nm in enumerate(b.free):
                x[b.offset + i] = vals[nm]
            k = b.offset + len(b.free)
            x[k:k + 3] = _rvec(b.cam_from_rig[:3, :3])
            x[k + 3:k + 6] = b.cam_from_rig[:3, 3]
        bp = self.board0 if self.fit_tilt else self.board0[2:]
        x[self.board_offset:self.board_offset + len(bp)] = bp
        if self.fit_scale:
            x[self.scale_offset] = self.scale0
        return x

    def camera_params(self, b: _CamBlock, x: np.ndarray):
        K = b.K.copy()
        dist = b.dist.copy()
        p = dict(zip(b.free, x[b.offset:b.offset + len(b.free)]))
        if "f" in p:
            K[1, 1] = p["f"]
            K[0, 0] = p["f"] * b.aspect
        for nm, (r, c) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            if nm in p:
                K[r, c] = p[nm]
        for i, nm in enumerate(("k1", "k2", "p1", "p2", "k3")):
            if nm in p:
                dist[i] = p[nm]
        k = b.offset + len(b.free)
        return K, dist, x[k:k + 3].copy(), x[k + 3:k + 6].copy()

    def board_params(self, x: np.ndarray) -> np.ndarray:
        v = x[self.board_offset:self.board_offset + len(self.board_names)]
        return v.copy() if self.fit_tilt else np.concatenate([self.board0[:2], v])

    def scale(self, x: np.ndarray) -> float:
        return float(x[self.scale_offset]) if self.fit_scale else self.scale0

    def object_from_board(self, x: np.ndarray) -> np.ndarray:
        return _board_pose(self.spec, *self.board_params(x))

    def _rig_points(self, b: _CamBlock, bp: np.ndarray, s: float) -> np.ndarray:
        T = _board_pose(self.spec, *bp)
        P = b.obj @ T[:3, :3].T + T[:3, 3]
        th = np.radians(s * b.angle)
        c, sn = np.cos(th), np.sin(th)
        return np.stack([c * P[:, 0] + sn * P[:, 2], P[:, 1], -sn * P[:, 0] + c * P[:, 2]], axis=1)

    # ---- residuals
    def residuals(self, x: np.ndarray) -> list[np.ndarray]:
        """Per camera block, (N, 2) predicted − observed pixels."""
        import cv2

        bp, s = self.board_params(x), self.scale(x)
        out = []
        for b in self.blocks:
            K, dist, rv, tv = self.camera_params(b, x)
            X = self._rig_points(b, bp, s)
            uv, _ = cv2.projectPoints(X, rv, tv, K, dist)
            out.append(uv.reshape(-1, 2) - b.img)
        return out

    def cost_grad_hessian(self, x: np.ndarray, *, want_hessian: bool):
        """Cost Σr², gradient 2Jᵀr and (optionally) Gauss–Newton Hessian 2JᵀJ."""
        import cv2

        bp, s = self.board_params(x), self.scale(x)
        # d(rig points)/d(board & scale params) by central differences (5 cheap evaluations).
        ext_idx = list(range(self.board_offset, self.n))
        cost = 0.0
        g = np.zeros(self.n)
        H = np.zeros((self.n, self.n)) if want_hessian else None
        for b in self.blocks:
            K, dist, rv, tv = self.camera_params(b, x)
            X = self._rig_points(b, bp, s)
            uv, J = cv2.projectPoints(X, rv, tv, K, dist)
            r = (uv.reshape(-1, 2) - b.img).ravel()
            cost += float(r @ r)
            N = X.shape[0]
            cols = []
            for nm in b.free:
                if nm == "f":
                    cols.append(J[:, 6] * b.aspect + J[:, 7])
                else:
                    cols.append(J[:, {"fx": 6, "fy": 7, "cx": 8, "cy": 9, "k1": 10, "k2": 11,
                                      "p1": 12, "p2": 13, "k3": 14}[nm]])
            Jc = np.column_stack(cols + [J[:, 0:6]]) if cols else J[:, 0:6]
            # extra (board/scale) columns: dUV/dXcam · R · dXrig/dθ
            R = _rodrigues(rv)
            Jt = J[:, 3:6].reshape(N, 2, 3)
            dX = self._rig_point_derivs(b, bp, s)  # (N, 3, m)
            Je = np.einsum("nij,jk,nkm->nim", Jt, R, dX).reshape(2 * N, -1)
            sl = slice(b.offset, b.offset + b.n_params)
            g[sl] += 2.0 * Jc.T @ r
            g[ext_idx] += 2.0 * Je.T @ r
            if want_hessian:
                H[sl, sl] += 2.0 * Jc.T @ Jc
                cross = 2.0 * Jc.T @ Je
                H[sl, ext_idx] += cross
                H[ext_idx, sl] += cross.T
                H[np.ix_(ext_idx, ext_idx)] += 2.0 * Je.T @ Je
        return cost, g, H

    def _rig_point_derivs(self, b: _CamBlock, bp: np.ndarray, s: float) -> np.ndarray:
        m = len(self.board_names) + (1 if self.fit_scale else 0)
        out = np.empty((b.obj.shape[0], 3, m))
        h = 1e-6
        names = list(range(4)) if self.fit_tilt else [2, 3]
        for k, idx in enumerate(names):
            e = np.zeros(4)
            e[idx] = h
            out[:, :, k] = (self._rig_points(b, bp + e, s) - self._rig_points(b, bp - e, s)) / (2 * h)
        if self.fit_scale:
            out[:, :, m - 1] = (self._rig_points(b, bp, s + h) - self._rig_points(b, bp, s - h)) / (2 * h)
        return out


def _refine_nlopt(model: _RigModel, x0: np.ndarray, *, max_iter: int, restarts: int) -> tuple[np.ndarray, dict]:
    """Minimise Σ r² with nlopt L-BFGS in variables whitened by the Gauss–Newton Hessian."""
    import nlopt
    from scipy.linalg import solve_triangular

    x_best = x0.copy()
    f_best = model.cost_grad_hessian(x0, want_hessian=False)[0]
    info = {"evaluations": 0, "runs": 0, "cost_start": f_best}
    for _ in range(restarts + 1):
        _, _, H = model.cost_grad_hessian(x_best, want_hessian=True)
        d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        Hs = H / np.outer(d, d) + 1e-9 * np.eye(model.n)  # Jacobi scaling, then a tiny ridge
        L = np.linalg.cholesky(Hs)
        # x = x_ref + D⁻¹ L⁻ᵀ δ  ⇒  the Hessian in δ is the identity at x_ref.
        x_ref = x_best.copy()

        def to_x(delta):
            return x_ref + solve_triangular(L.T, delta, lower=False) / d

        state = {"f": f_best, "x": x_best.copy()}

        def objective(delta, grad):
            x = to_x(delta)
            f, gx, _ = model.cost_grad_hessian(x, want_hessian=False)
            info["evaluations"] += 1
            if not math.isfinite(f):
                f = 1e300
                gx = np.zeros_like(gx)
            if grad.size:
                grad[:] = solve_triangular(L, gx / d, lower=True)
            if f < state["f"]:
                state["f"], state["x"] = f, x
            return f

        opt = nlopt.opt(nlopt.LD_LBFGS, model.n)
        opt.set_min_objective(objective)
        opt.set_maxeval(int(max_iter))
        opt.set_ftol_rel(1e-13)
        opt.set_xtol_rel(1e-12)
        opt.set_vector_storage(min(model.n, 30))
        try:
            opt.optimize(np.zeros(model.n))
        except (nlopt.RoundoffLimited, RuntimeError, ValueError):
            pass  # L-BFGS hit the floating-point floor; the best point seen is kept
        info["runs"] += 1
        improved = (f_best - state["f"]) > 1e-9 * max(f_best, 1e-300)
        if state["f"] < f_best:
            f_best, x_best = state["f"], state["x"]
        if not improved:
            break
    info["cost_end"] = f_best
    return x_best, info


# --------------------------------------------------------------------------- result


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
        r = self.residuals_px
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if r.size else float("nan")

    def summary(self) -> dict:
        """JSON-ready summary (for ``build --json`` and ``report.json``)."""
        return {
            "reproj_rms_px": float(self.rms_px),
            "reproj_rms_px_per_camera": {self.rig_cameras[c].name: float(self.reproj_rms_px[c])
                                         for c in self.camera_indices},
            "initial_rms_px_per_camera": {self.rig_cameras[c].name: float(self.initial_rms_px[c])
                                          for c in self.camera_indices},
            "focal_px": {self.rig_cameras[c].name: [self.rig_cameras[c].fx, self.rig_cameras[c].fy]
                         for c in self.camera_indices},
            "used_views": len(self.used_views),
            "dropped_views": dict(self.dropped_views),
            "table_scale": float(self.table_scale),
            "board_centre_m": (self.object_from_board[:3, :3] @ np.array([*np.array(self.charuco.size_m) / 2, 0.0])
                               + self.object_from_board[:3, 3]).tolist(),
            "board_tilt_deg": float(math.degrees(math.acos(np.clip(-self.object_from_board[1, 2], -1, 1)))),
            "fixed_intrinsics": {self.camera(c).name: list(v) for c, v in self.fixed_intrinsics.items()
                                 if c in self.camera_indices},
            "uncalibrated": {self.rig_cameras[c].name: why for c, why in self.uncalibrated.items()},
            "seconds": dict(self.seconds),
            "notes": list(self.notes),
        }


# --------------------------------------------------------------------------- main entry


def _plane_spread_deg(normals: list[np.ndarray]) -> float:
    N = np.array(normals)
    m = N.mean(axis=0)
    m /= np.linalg.norm(m)
    return float(np.degrees(np.arccos(np.clip(N @ m, -1, 1))).max() * 2.0)


def calibrate_observations(
    observations: Sequence[CharucoObservation],
    *,
    image_sizes: Mapping[int, tuple[int, int]] | Sequence[tuple[int, int]],
    charuco: CharucoSpec,
    nominal: Sequence[Camera] | None = None,
    config: CalibrationConfig = CalibrationConfig(),
    dropped: Mapping[str, str] | None = None,
) -> CalibrationResult:
    """Calibrate the rig (intrinsics, distortion, rig poses, board placement) from
    ChArUco detections.

    Parameters
    ----------
    observations : sequence of CharucoObservation
        Detections, one per view (camera, table angle); at most one per view.
    image_sizes : mapping or sequence camera index → (width, height)
        Every camera listed here must be calibrated.
    charuco : CharucoSpec
        The board and its nominal placement (fixes the gauge about the table axis).
    nominal : sequence of Camera, optional
        Nominal rig cameras (initial ``K``; names). Default: principal point at the
        image centre, focal length from OpenCV's homography initialisation.
    config : CalibrationConfig
    dropped : mapping view id → reason, optional
        Views already dropped upstream (e.g. unreadable images); copied into the result.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        A camera has fewer than three usable views, or its views do not span two
        distinct table angles.
    """
    import cv2

    t_start = time.perf_counter()
    sizes = dict(image_sizes) if isinstance(image_sizes, Mapping) else dict(enumerate(image_sizes))
    if not sizes:
        raise InputError("calibrate_observations: image_sizes is empty (no cameras to calibrate)")
    cams = sorted(int(c) for c in sizes)
    if nominal is not None and len(nominal) < max(cams) + 1:
        raise InputError(f"nominal has {len(nominal)} cameras, image_sizes names camera {max(cams)}")
    names = {c: (nominal[c].name if nominal is not None and nominal[c].name else f"cam{c}") for c in cams}
    dropped_views: dict[str, str] = dict(dropped or {})
    notes: list[str] = []
    by_cam: dict[int, list[CharucoObservation]] = {c: [] for c in cams}
    seen: set[str] = set()
    for obs in observations:
        if obs.view in seen:
            raise InputError(f"two observations of view {obs.view}; expected one per (camera, table angle)")
        seen.add(obs.view)
        if obs.camera not in by_cam:
            raise InputError(f"observation {obs.view}: camera {obs.camera} is not in image_sizes (cameras {cams})")
        reason = screen_observation(obs, charuco=charuco, config=config)
        if reason is None:
            w, h = sizes[obs.camera]
            ip = obs.image_points
            if np.any(ip < -0.5) or np.any(ip[:, 0] > w - 0.5) or np.any(ip[:, 1] > h - 0.5):
                reason = f"corners outside the {w}x{h} image"
        if reason is None:
            by_cam[obs.camera].append(obs)
        else:
            dropped_views[obs.view] = reason

    def _too_few(c, usable):
        mine = {v: r for v, r in dropped_views.items() if v.startswith(f"c{c}_t")}
        why = "; ".join(f"{v}: {r}" for v, r in sorted(mine.items())) or "no calibration views captured"
        return CalibrationError(
            f"camera {c} ({names[c]}): only {usable} usable calibration view(s), need at least 3 "
            f"({len(mine)} dropped — {why})"
        )

    uncalibrated: dict[int, str] = {}

    def _unusable(c, usable):
        err = _too_few(c, usable)
        if not config.skip_unusable_cameras:
            raise err
        uncalibrated[c] = str(err)
        notes.append(f"{names[c]}: not calibrated (skip_unusable_cameras): {err}")

    for c in list(cams):
        if len(by_cam[c]) < 3:
            _unusable(c, len(by_cam[c]))
    cams = [c for c in cams if c not in uncalibrated]
    if not cams:
        raise CalibrationError("no camera has three usable calibration views: "
                               + " | ".join(uncalibrated[c] for c in sorted(uncalibrated)))

    # ---- step 2: intrinsics per camera
    K_init: dict[int, np.ndarray] = {}
    dist_init: dict[int, np.ndarray] = {}
    poses: dict[int, list[tuple[CharucoObservation, np.ndarray]]] = {}
    fixed: dict[int, tuple[str, ...]] = {}
    for c in cams:
        w, h = sizes[c]
        views = sorted(by_cam[c], key=lambda o: o.table_deg)
        objs = [o.object_points.astype(np.float32) for o in views]
        imgs = [o.image_points.astype(np.float32) for o in views]
        if nominal is not None:
            K0 = nominal[c].K.copy()
        else:
            K0 = cv2.initCameraMatrix2D(objs, imgs, (w, h), aspectRatio=1.0)
            K0[0, 2], K0[1, 2] = (w - 1) / 2.0, (h - 1) / 2.0
        normals = []
        for o in views:
            ok, rv, _ = cv2.solvePnP(o.object_points, o.image_points, K0, None, flags=cv2.SOLVEPNP_IPPE)
            if ok:
                normals.append(_rodrigues(rv)[:, 2])
        spread = _plane_spread_deg(normals) if normals else 0.0
        single_plane = spread < config.min_plane_spread_deg
        fov_diag_deg = 2.0 * math.degrees(math.atan(0.5 * math.hypot(w, h) / float(K0[0, 0])))
        narrow = fov_diag_deg < config.min_fov_free_principal_point_deg
        fix_pp = (single_plane or narrow) if config.fix_principal_point is None else bool(config.fix_principal_point)
        if narrow and not single_plane and config.fix_principal_point is None:
            notes.append(f"{names[c]}: diagonal field of view {fov_diag_deg:.1f} deg (< "
                         f"{config.min_fov_free_principal_point_deg}): principal point held at nominal")
        fix_ar = single_plane if config.fix_aspect_ratio is None else bool(config.fix_aspect_ratio)
        if single_plane and (config.fix_principal_point is None or config.fix_aspect_ratio is None):
            notes.append(f"{names[c]}: board normals span {spread:.1f} deg (< {config.min_plane_spread_deg}): "
                         "one plane constrains only two intrinsics; principal point and aspect ratio held at nominal")
        allpts = np.concatenate([o.image_points for o in views])
        r_cov = float(np.max(np.hypot(allpts[:, 0] - K0[0, 2], allpts[:, 1] - K0[1, 2]))) / (0.5 * math.hypot(w, h))
        fix_k2 = (r_cov < config.min_k2_coverage) if config.fix_k2 is None else bool(config.fix_k2)
        if config.fix_k2 is None and fix_k2:
            notes.append(f"{names[c]}: corners reach {r_cov:.2f} of the image half-diagonal "
                         f"(< {config.min_k2_coverage}); k2 held at 0")
        flags = cv2.CALIB_USE_INTRINSIC_GUESS
        held = []
        if fix_pp:
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
            held += ["cx", "cy"]
        if fix_ar:
            flags |= cv2.CALIB_FIX_ASPECT_RATIO
            held += ["fx/fy"]
        # Nested distortion models, smallest first, up to what the config allows.
        chain = [("none", ()), ("k1", ("k1",))]
        if not fix_k2:
            chain.append(("k1k2", ("k1", "k2")))
        if not config.fix_tangential:
            chain.append((chain[-1][0] + "p", chain[-1][1] + ("p1", "p2")))
        if not config.fix_k3 and not fix_k2:
            chain.append((chain[-1][0] + "k3", chain[-1][1] + ("k3",)))
        n_intr = (1 if fix_ar else 2) + (0 if fix_pp else 2)

        def dist_flags(free_dist):
            f = flags
            for nm, fl in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
                if nm not in free_dist:
                    f |= fl
            if "p1" not in free_dist:
                f |= cv2.CALIB_ZERO_TANGENT_DIST
            return f

        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)

        def fit(views_, free_dist):
            objs_ = [o.object_points.astype(np.float32) for o in views_]
            imgs_ = [o.image_points.astype(np.float32) for o in views_]
            out = cv2.calibrateCameraExtended(objs_, imgs_, (w, h), K0.copy(), np.zeros(5),
                                              flags=dist_flags(free_dist), criteria=crit)
            rms_, K_, dist_, rv_, tv_, _, _, pv_ = out
            return rms_, K_, dist_, rv_, tv_, np.asarray(pv_).ravel()

        # Misdetections first, with the largest model (a wrong view must not choose it).
        rms, K, dist, rvecs, tvecs, per_view = fit(views, chain[-1][1])
        lim = max(config.max_view_rms_px, 3.0 * float(np.median(per_view)))
        bad = [i for i, e in enumerate(per_view) if e > lim]
        if bad:
            for i in bad:
                dropped_views[views[i].view] = (f"reprojection RMS {per_view[i]:.2f} px after calibrating "
                                                f"{names[c]} alone (> {lim:.2f} px): misdetection")
            views = [v for i, v in enumerate(views) if i not in bad]
            notes.append(f"{names[c]}: dropped {len(bad)} outlier view(s)")
            if len(views) < 3:
                _unusable(c, len(views))
                continue
        if config.select_distortion and len(chain) > 1:
            # BIC over the nested models: a coefficient must pay for itself. Spurious
            # distortion trades off against the focal length (measured: k1 = -0.35 and a
            # 6 % focal error on a distortion-free 24 deg camera).
            n_res = 2 * sum(len(o) for o in views)
            scored = []
            for name, free_dist in chain:
                r_ = fit(views, free_dist)
                ssr = max(r_[0] ** 2 * n_res / 2.0, 1e-300)
                k = n_intr + len(free_dist) + 6 * len(views)
                scored.append((n_res * math.log(ssr / n_res) + k * math.log(n_res), name, free_dist, r_))
            _, model_name, free_dist, (rms, K, dist, rvecs, tvecs, per_view) = min(scored, key=lambda t: t[0])
            notes.append(f"{names[c]}: distortion model '{model_name}' chosen by BIC ("
                         + ", ".join(f"{nm} {b:.1f}" for b, nm, _, _ in scored) + ")")
        else:
            free_dist = chain[-1][1]
            if bad:
                rms, K, dist, rvecs, tvecs, per_view = fit(views, free_dist)
        held += [nm for nm in ("k1", "k2", "p1", "p2", "k3") if nm not in free_dist]
        fixed[c] = tuple(held)
        K_init[c] = K
        dist_init[c] = np.asarray(dist, dtype=np.float64).ravel()[:5]
        poses[c] = [(o, _rt(_rodrigues(rv), np.asarray(tv).ravel())) for o, rv, tv in zip(views, rvecs, tvecs)]
    cams = [c for c in cams if c not in uncalibrated]
    if not cams:
        raise CalibrationError("no camera has three usable calibration views: "
                               + " | ".join(uncalibrated[c] for c in sorted(uncalibrated)))
    t_intr = time.perf_counter()

    # ---- step 3: axis and rig frame per camera, then one board placement for all
    axis_dirs = np.full((max(cams) + 1, 3), np.nan)
    rig_est: dict[int, np.ndarray] = {}
    board_est = []
    for c in cams:
        angles = [o.table_deg for o, _ in poses[c]]
        Ts = [T for _, T in poses[c]]
        try:
            d, o, B0 = estimate_turntable_axis(angles, Ts)
        except CalibrationError as e:
            raise CalibrationError(f"camera {c} ({names[c]}): {e}") from None
        axis_dirs[c] = d
        cam_from_rig = _rig_from_axis(d, o, B0, charuco)
        rig_est[c] = cam_from_rig
        board_est.append((_inv(cam_from_rig) @ B0, len(Ts)))
    obj_from_board = _mean_pose([T for T, _ in board_est], [n for _, n in board_est])
    bparams = _board_params(charuco, obj_from_board)
    if not config.fit_board_tilt:
        bparams[:2] = 0.0
    obj_from_board = _board_pose(charuco, *bparams)
    board_from_object = _inv(obj_from_board)
    blocks = []
    for c in cams:
        # cam_from_rig consistent with the common board: mean over views of
        # cam_from_board(c, a) · board_from_object · object_from_rig(a)
        cands = [T @ board_from_object @ _inv(rig_from_object(o.table_deg)) for o, T in poses[c]]
        cam_from_rig = _mean_pose(cands)
        views = [o for o, _ in poses[c]]
        free = []
        if "fx/fy" in fixed[c]:
            free.append("f")
        else:
            free += ["fx", "fy"]
        if "cx" not in fixed[c]:
            free += ["cx", "cy"]
        free += [nm for nm in ("k1", "k2", "p1", "p2", "k3") if nm not in fixed[c]]
        K = K_init[c]
        blocks.append(_CamBlock(
            index=c, size=sizes[c], K=K.copy(), dist=dist_init[c].copy(), cam_from_rig=cam_from_rig,
            free=tuple(free), aspect=float(K[0, 0] / K[1, 1]),
            obj=np.concatenate([o.object_points for o in views]),
            img=np.concatenate([o.image_points for o in views]),
            angle=np.concatenate([np.full(len(o), o.table_deg) for o in views]),
            view_of_point=np.concatenate([np.full(len(o), i) for i, o in enumerate(views)]),
            views=[o.view for o in views],
        ))
    model = _RigModel(blocks, charuco, bparams, fit_tilt=config.fit_board_tilt, fit_scale=config.fit_table_scale)
    x0 = model.pack()
    t_axis = time.perf_counter()

    def rms_per_cam(x):
        return [float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) for r in model.residuals(x)]

    initial_rms = rms_per_cam(x0)
    # ---- step 4: joint refinement
    x = x0
    info: dict = {}
    if config.refine:
        x, info = _refine_nlopt(model, x0, max_iter=config.max_iter, restarts=config.restarts)
    t_refine = time.perf_counter()

    res = model.residuals(x)
    n_cams = len(nominal) if nominal is not None else max(cams) + 1
    rig_cams: list[Camera | None] = [None] * n_cams
    rms_final, rms_init = [float("nan")] * n_cams, [float("nan")] * n_cams
    per_view: dict[str, float] = {}
    rows, row_views = [], []
    for b, r, r_end, r_start in zip(blocks, res, rms_per_cam(x), initial_rms):
        K, dist, rv, tv = model.camera_params(b, x)
        cam_from_rig = _rt(_rodrigues(rv), tv)
        rig_cams[b.index] = Camera(K=K, dist=dist, width=b.size[0], height=b.size[1],
                                   world_from_cam=_inv(cam_from_rig), name=names[b.index])
        rms_final[b.index], rms_init[b.index] = r_end, r_start
        for i, v in enumerate(b.views):
            rv_ = r[b.view_of_point == i]
            per_view[v] = float(np.sqrt(np.mean(np.sum(rv_ * rv_, axis=1))))
        rows.append(r)
        row_views.append(np.array(b.views, dtype=object)[b.view_of_point])
    missing = [c for c in range(n_cams) if rig_cams[c] is None]
    if missing and nominal is None:
        raise InputError(f"calibrate_observations: cameras {missing} were not calibrated (not in image_sizes, "
                         "or skipped); give `nominal` (the whole rig) to keep them as designed")
    for c in missing:  # cameras not calibrated: kept nominal, marked, never used for views
        rig_cams[c] = nominal[c]
        uncalibrated.setdefault(c, "no images in the session: left nominal")
    return CalibrationResult(
        rig_cameras=rig_cams,
        reproj_rms_px=rms_final,
        per_view_rms_px=per_view,
        object_from_board=model.object_from_board(x),
        axis_dir_prealign=axis_dirs,
        used_views=tuple(v for b in blocks for v in b.views),
        dropped_views=dropped_views,
        residuals_px=np.concatenate(rows),
        residual_views=np.concatenate(row_views).astype(str),
        table_scale=model.scale(x),
        fixed_intrinsics=fixed,
        initial_rms_px=rms_init,
        seconds={"intrinsics": t_intr - t_start, "axis": t_axis - t_intr, "refine": t_refine - t_axis},
        refine_info=dict(info),
        notes=tuple(notes),
        charuco=charuco,
        camera_indices=tuple(cams),
        uncalibrated=dict(sorted(uncalibrated.items())),
    )


def calibrate_session(session, *, config: CalibrationConfig = CalibrationConfig(),
                      progress: ProgressCallback | None = None) -> CalibrationResult:
    """Calibrate the rig from the ``calibration`` phase of a session.

    Parameters
    ----------
    session : opacityhull.session.Session
        Its calibration records (one shot per (camera, table angle), board on the table,
        linear EXR, HDR merges preferred), ``session.geometry`` (nominal rig: initial
        guess and camera names) and ``session.meta["charuco"]`` (the board; default
        :class:`CharucoSpec` when absent). Every camera with images in the session (any
        phase) is calibrated; cameras without any image are left out
        (``result.camera_indices``).
    config : CalibrationConfig
    progress : callable(done, total), optional
        Called after each image is searched for corners.

    Returns
    -------
    CalibrationResult
        ``seconds["detect"]`` holds the detection time.

    Raises
    ------
    CalibrationError
        No calibration phase, or a camera with fewer than three usable views.
    """
    from ..errors import FormatError

    geometry: RigGeometry = session.geometry
    nominal = geometry.nominal_cameras()
    spec_d = session.meta.get("charuco")
    spec = CharucoSpec.from_dict(spec_d, where=f"{session.root / 'session.toml'}:charuco") if spec_d else CharucoSpec()
    recs = session.select(phase="calibration", kind=None)
    if not recs:
        raise CalibrationError(f"{session.root}: the session has no 'calibration' phase records "
                               "(capture the ChArUco board first, or provide calibration/<camera>.yaml)")
    shots: dict[str, object] = {}
    for r in recs:
        shots.setdefault(r.shot, r)
    t0 = time.perf_counter()
    observations: list[CharucoObservation] = []
    dropped: dict[str, str] = {}
    # Calibrate every camera the session used (in any phase): a camera the plan left out
    # entirely needs no calibration; one with images but no usable board views is an error.
    used = sorted({r.camera for r in session.records})
    sizes = {i: (nominal[i].width, nominal[i].height) for i in used if 0 <= i < len(nominal)}
    by_view: dict[str, str] = {}
    seen_size: dict[int, tuple[int, int]] = {}
    total = len(shots)
    for k, (shot, r) in enumerate(sorted(shots.items())):
        if progress is not None:
            progress(k, total)
        vid = view_id(r.camera, r.table_deg)
        if not 0 <= r.camera < len(nominal):
            raise FormatError(f"{session.root}: calibration shot {shot} names camera {r.camera}; "
                              f"the rig has {len(nominal)} cameras")
        if vid in by_view:
            dropped.setdefault(vid, f"several calibration shots of this view ({by_view[vid]}, {shot}); used the first")
            continue
        by_view[vid] = shot
        try:
            img = session.load_radiance(shot)
        except (FormatError, OSError) as e:
            dropped[vid] = f"image unreadable: {e}"
            continue
        h, w = img.shape[:2]
        if r.camera in seen_size and seen_size[r.camera] != (w, h):
            dropped[vid] = (f"image is {w}x{h}, the camera's other calibration images are "
                            f"{seen_size[r.camera][0]}x{seen_size[r.camera][1]}")
            continue
        seen_size[r.camera] = sizes[r.camera] = (w, h)
        observations.append(detect_charuco(img, charuco=spec, camera=r.camera, table_deg=r.table_deg,
                                           percentile=config.tonemap_percentile, upscale=config.detect_upscale,
                                           max_upscaled_px=config.detect_max_upscaled_px))
    if progress is not None:
        progress(total, total)
    t_detect = time.perf_counter() - t0
    # Nominal intrinsics scaled to the image size actually captured.
    nom = list(nominal)
    for i in sizes:
        w, h = sizes[i]
        c = nominal[i]
        nom[i] = c if (w, h) == (c.width, c.height) else c.scaled(w / c.width)
    result = calibrate_observations(observations, image_sizes=sizes, charuco=spec, nominal=nom, config=config,
                                    dropped=dropped)
    return replace(result, seconds={"detect": t_detect, **result.seconds})


# --------------------------------------------------------------------------- consumers


def view_cameras(result: CalibrationResult, views: Sequence[tuple[int, float]]) -> list[Camera]:
    """Object-frame cameras of views ``(camera, table_deg)``, named by view id.

    The pose comes from the rig model: ``object_from_rig(s·a) · rig_from_cam(c)`` with
    the calibrated table-angle scale ``s``.
    """
    out = []
    for c, a in views:
        c = int(c)
        if c not in result.camera_indices:
            raise InputError(f"view ({c}, {a}): camera {c} was not calibrated "
                             f"(calibrated: {list(result.camera_indices)})")
        cam = RigGeometry.view_camera(result.camera(c), float(a) * result.table_scale)
        out.append(cam.with_name(view_id(c, a)))
    return out


def pose_errors(result: CalibrationResult | Sequence[Camera], true_rig_cameras: Sequence[Camera], *,
                align_gauge: bool = False, volume_m: float | None = 0.2) -> dict:
    """Errors of calibrated rig cameras against ground truth.

    Parameters
    ----------
    result : CalibrationResult or list of Camera (rig frame)
    true_rig_cameras : list of Camera
        True ``rig_from_cam`` and intrinsics (e.g. the simulator's
        ``groundtruth/calibration/<name>.yaml`` read with ``camera.read_opencv_yaml``),
        one per rig camera; only the calibrated ones (``result.camera_indices``) are
        compared.
    align_gauge : bool
        First remove the rig frame's gauge freedom — a rotation about +Y and a shift
        along +Y, which calibration fixes from the board's nominal yaw and height: the
        yaw from the camera orientations, then (with ``volume_m``) yaw and shift that
        minimise the working volume's reprojection differences (nlopt BOBYQA), else the
        shift from the camera heights. The fitted gauge is reported.
    volume_m : float or None
        Side of the working volume (a cube standing on the table centre) whose points
        (a 5×5×5 grid) are projected with the estimated and the true camera:
        ``volume_reproj_px`` is the RMS pixel distance per camera — what silhouettes
        and hulls see. The focal length and the camera distance are poorly separated by
        a flat board (their errors largely cancel in this number).

    Returns
    -------
    dict with ``cameras`` (indices compared: the calibrated ones), per-camera lists
    ``rotation_deg``, ``position_mm``, ``focal_pct`` (mean of fx, fy),
    ``principal_point_px``, ``volume_reproj_px``, their maxima ``max_*``, and
    ``gauge_yaw_deg``, ``gauge_dy_mm`` (0 unless ``align_gauge``).
    """
    true = list(true_rig_cameras)
    if isinstance(result, CalibrationResult):
        if len(true) != len(result.rig_cameras):
            raise InputError(f"pose_errors: {len(result.rig_cameras)} rig cameras vs {len(true)} true cameras")
        idx = list(result.camera_indices)
        est = [result.rig_cameras[c] for c in idx]
        true = [true[c] for c in idx]
    else:
        est = list(result)
        idx = list(range(len(est)))
        if len(est) != len(true):
            raise InputError(f"pose_errors: {len(est)} calibrated cameras vs {len(true)} true cameras")
    X = None
    if volume_m:
        g = (np.arange(5) / 4.0 - 0.5) * float(volume_m)
        X = np.stack(np.meshgrid(g, g + 0.5 * float(volume_m), g, indexing="ij"), axis=-1).reshape(-1, 3)
    G = np.eye(4)
    yaw = dy = 0.0
    if align_gauge:
        # true ≈ G·est with G = rot_y(ψ) + (0, dy, 0). ψ first from the camera axes
        # (orientations are accurate; positions are not, along each optical axis).
        Re = np.concatenate([c.world_from_cam[:3, :3].T for c in est])
        Rt = np.concatenate([c.world_from_cam[:3, :3].T for c in true])
        psi = math.atan2(np.sum(Re[:, 2] * Rt[:, 0] - Re[:, 0] * Rt[:, 2]),
                         np.sum(Re[:, 0] * Rt[:, 0] + Re[:, 2] * Rt[:, 2]))
        dy = float(np.mean([t.centre_world[1] - e.centre_world[1] for e, t in zip(est, true)]))
        if X is not None:
            # Then (ψ, dy) minimising the working volume's reprojection differences.
            import nlopt

            uv_true = [t.project(X)[0] for t in true]

            def f(p, grad):
                Gp = _rt(rot_y(p[0]), [0.0, p[1], 0.0])
                tot = 0.0
                for e, ut in zip(est, uv_true):
                    d = e.with_pose(Gp @ e.world_from_cam).project(X)[0] - ut
                    tot += float(np.nansum(d * d))
                return tot

            opt = nlopt.opt(nlopt.LN_BOBYQA, 2)
            opt.set_min_objective(f)
            opt.set_initial_step([math.radians(0.5), 0.005])
            opt.set_xtol_abs([1e-9, 1e-9])
            opt.set_maxeval(400)
            try:
                psi, dy = (float(v) for v in opt.optimize([psi, dy]))
            except nlopt.RoundoffLimited:
                pass
        G = _rt(rot_y(psi), [0.0, dy, 0.0])
        yaw = math.degrees(psi)
    rot, pos, foc, pp, vol = [], [], [], [], []
    for e, t in zip(est, true):
        Te = G @ e.world_from_cam
        if volume_m:
            uv_e, _ = e.with_pose(Te).project(X)
            uv_t, _ = t.project(X)
            vol.append(float(np.sqrt(np.nanmean(np.sum((uv_e - uv_t) ** 2, axis=1)))))
        rot.append(rotation_angle_deg(Te[:3, :3].T @ t.world_from_cam[:3, :3]))
        pos.append(float(np.linalg.norm(Te[:3, 3] - t.world_from_cam[:3, 3]) * 1000.0))
        foc.append(float(100.0 * abs((e.fx + e.fy) - (t.fx + t.fy)) / (t.fx + t.fy)))
        pp.append(float(math.hypot(e.cx - t.cx, e.cy - t.cy)))
    return {
        "cameras": idx,
        "rotation_deg": rot,
        "position_mm": pos,
        "focal_pct": foc,
        "principal_point_px": pp,
        "max_rotation_deg": max(rot),
        "max_position_mm": max(pos),
        "max_focal_pct": max(foc),
        "max_principal_point_px": max(pp),
        "volume_reproj_px": vol,
        "max_volume_reproj_px": max(vol) if vol else float("nan"),
        "gauge_yaw_deg": yaw,
        "gauge_dy_mm": dy * 1000.0,
    }


# --------------------------------------------------------------------------- synthetic views


def _lattice_offsets(n: int) -> np.ndarray:
    """(n, 2) sub-pixel offsets in (-0.5, 0.5): a rank-1 (Fibonacci-like) lattice, so that
    x and y each take n distinct values — an axis-aligned edge is resolved to 1/n px
    instead of the 1/√n of a regular grid."""
    phi = (math.sqrt(5.0) - 1.0) / 2.0
    g = min((c for c in range(1, max(n, 2)) if math.gcd(c, n) == 1), key=lambda c: abs(c / n - phi))
    k = np.arange(n)
    return np.stack([(k + 0.5) / n - 0.5, ((k * g) % n + 0.5) / n - 0.5], axis=1)


@functools.lru_cache(maxsize=4)
def _sample_rays(K_bytes: bytes, dist_bytes: bytes, W: int, H: int, n: int) -> np.ndarray:
    """Undistorted normalised coordinates (n, H·W, 1, 2) float32 of n samples in every
    pixel (cached: undistortion is the costly part and the same for every board pose)."""
    cam = Camera(K=np.frombuffer(K_bytes).reshape(3, 3), dist=np.frombuffer(dist_bytes), width=W, height=H)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.empty((n, H * W, 1, 2), np.float32)
    for k, (dx, dy) in enumerate(_lattice_offsets(n)):
        xyd = np.stack([(u.ravel() + dx - cam.cx) / cam.fx, (v.ravel() + dy - cam.cy) / cam.fy], axis=1)
        out[k, :, 0, :] = cam.undistort_normalized(xyd, iterations=30)
    out.setflags(write=False)
    return out


def render_charuco_view(
    camera: Camera,
    *,
    world_from_board: np.ndarray,
    charuco: CharucoSpec,
    samples: int = 9,
    px_per_square: int = 96,
    margin_squares: float = 0.5,
    albedo: tuple[float, float] = (0.04, 0.85),
    background: float = 0.2,
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Ray-cast the ChArUco board through a known camera: exact ground truth for tests.

    Independent of the calibration code: each of ``samples`` samples per pixel is
    undistorted with the camera's model, cast as a ray, intersected with the board plane
    and looks up the OpenCV board image (``CharucoSpec.image``, bilinear) surrounded by a
    white paper margin; everything else is a uniform table of reflectance
    ``background``.

    Parameters
    ----------
    camera : Camera
        Intrinsics, distortion, size and ``world_from_cam``.
    world_from_board : (4, 4) array
        Board pose in the same world frame (board frame as OpenCV defines it).
    charuco : CharucoSpec
    samples : int
        Samples per pixel (box filter over a rank-1 lattice).
    px_per_square : int
        Resolution of the board texture.
    margin_squares : float
        White margin around the printed squares.
    albedo : (black, white) linear reflectances of the print.
    background : linear reflectance of the table.
    noise_sigma : float
        Standard deviation of additive Gaussian noise (linear units).
    rng : numpy Generator, required when ``noise_sigma > 0``.

    Returns
    -------
    (H, W, 3) float32 linear image.
    """
    import cv2

    if noise_sigma > 0 and rng is None:
        raise InputError("render_charuco_view: noise_sigma > 0 needs an explicit rng (numpy Generator)")
    n = int(samples)
    if n < 1:
        raise InputError(f"render_charuco_view: samples={samples} must be >= 1")
    tex = charuco.image(px_per_square).astype(np.float32) / 255.0
    tex = albedo[0] + (albedo[1] - albedo[0]) * tex
    m = int(round(margin_squares * px_per_square))
    tex = cv2.copyMakeBorder(tex, m, m, m, m, cv2.BORDER_CONSTANT, value=float(albedo[1]))
    board_from_cam = _inv(np.asarray(world_from_board, dtype=np.float64)) @ camera.world_from_cam
    R, o = board_from_cam[:3, :3], board_from_cam[:3, 3]
    W, H = camera.width, camera.height
    if o[2] >= 0:  # camera on the back side of (or in) the board plane: the print is invisible
        img = np.full((H, W), float(background))
    else:
        # A ray r = (x, y, 1) meets the board plane z = 0 at
        #   X = (o_x R_2 − o_z R_0)·r / R_2·r,  Y = (o_y R_2 − o_z R_1)·r / R_2·r,
        # in front of the camera iff R_2·r > 0: a homography from undistorted normalised
        # coordinates to board metres, then to texture pixels (pixel i covers
        # [i, i+1)·square/pps, centre at i + 0.5; plus the margin).
        Hb = np.stack([o[0] * R[2] - o[2] * R[0], o[1] * R[2] - o[2] * R[1], R[2]])
        sc = px_per_square / charuco.square_m
        A = np.array([[sc, 0.0, m - 0.5], [0.0, sc, m - 0.5], [0.0, 0.0, 1.0]])
        Hm = A @ Hb
        rays = _sample_rays(camera.K.tobytes(), camera.dist.tobytes(), W, H, n)
        acc = np.zeros((H, W), np.float32)
        for k in range(n):
            xy = rays[k]
            maps = cv2.perspectiveTransform(xy, Hm).reshape(H, W, 2)
            w = (Hm[2, 0] * xy[:, 0, 0] + Hm[2, 1] * xy[:, 0, 1] + Hm[2, 2]).reshape(H, W)
            maps[w <= 0] = -1e4
            acc += cv2.remap(tex, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=float(background))
        img = acc / n
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.repeat(img[:, :, None], 3, axis=2).astype(np.float32)
