"""Camera model shared by every stage, and its conversions.

Conventions (DESIGN.md, fixed):

* OpenCV pinhole with OpenCV's 5-coefficient distortion ``(k1, k2, p1, p2, k3)``.
* Camera frame: x right, y down, z forward. The centre of the top-left pixel is
  ``(0, 0)``.
* Extrinsics are stored as ``world_from_cam`` (4×4, camera-to-world).
* World frame of the rig: origin at the centre of the turntable top, +Y up along the
  table axis. The *object frame* is the rig frame at table angle 0; a table angle
  ``a`` rotates the object by ``+a`` degrees about +Y (right-handed: +Z towards +X).
  See :func:`rig_from_object`.

Conversions live here and only here:

* COLMAP text (``cameras.txt``/``images.txt``) and binary (``*.bin`` through pycolmap,
  winning over text as in COLMAP): COLMAP puts the centre of the top-left pixel at
  (0.5, 0.5), so ``cx_colmap = cx + 0.5``; it stores ``cam_from_world``.
* OpenCV ``FileStorage`` YAML.
* Mitsuba's ``perspective`` sensor: x left, y up, z forward, so
  ``to_world = world_from_cam @ diag(-1, -1, 1, 1)``; the principal point offset is
  a fraction of the film size with the sign flipped by the same mirror.
* nerfstudio ``transforms.json`` frames (OpenGL camera: x right, y up, z backward).
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from collections.abc import Iterator, Sequence

import numpy as np

from .errors import FormatError, InputError, ShapeError, check_shape

__all__ = [
    "Camera",
    "rot_y",
    "rig_from_object",
    "object_from_rig",
    "look_at_world_from_cam",
    "write_colmap_text",
    "read_colmap_text",
    "read_colmap_binary",
    "read_colmap_model",
    "colmap_model_kind",
    "colmap_intrinsics",
    "write_opencv_yaml",
    "read_opencv_yaml",
    "mitsuba_sensor_params",
    "camera_from_mitsuba_params",
    "nerfstudio_transform_matrix",
    "camera_from_nerfstudio",
    "coincident_views",
]

_MITSUBA_FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])
_OPENGL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


# --------------------------------------------------------------------------- frames


def rot_y(angle_rad: float) -> np.ndarray:
    """3×3 right-handed rotation about +Y by ``angle_rad`` (+Z turns towards +X)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rig_from_object(table_deg: float) -> np.ndarray:
    """4×4 transform taking object-frame points to the rig frame at table angle ``table_deg``."""
    T = np.eye(4)
    T[:3, :3] = rot_y(math.radians(table_deg))
    return T


def object_from_rig(table_deg: float) -> np.ndarray:
    """Inverse of :func:`rig_from_object`."""
    T = np.eye(4)
    T[:3, :3] = rot_y(math.radians(table_deg)).T
    return T


def look_at_world_from_cam(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV-convention ``world_from_cam`` for a camera at ``eye`` looking at ``target``.

    Image "up" (−y of the camera) is as close to ``up`` as possible. Raises
    :class:`InputError` when ``eye == target``; a view straight along ``up`` picks a
    deterministic perpendicular instead of failing.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    n = np.linalg.norm(z)
    if not np.isfinite(n) or n < 1e-12:
        raise InputError(f"look-at eye {eye.tolist()} coincides with target {target.tolist()}")
    z /= n
    x = np.cross(z, up)  # camera x = right = forward x up, so that image up (-y) follows `up`
    if np.linalg.norm(x) < 1e-9:  # looking along the up axis: image up follows world +Z instead
        alt = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(z, alt)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def _check_rigid(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    check_shape(name, T, (4, 4))
    if not np.all(np.isfinite(T)):
        raise InputError(f"{name} contains NaN or Inf")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError(f"{name} is not a rigid transform (rotation part not orthonormal, det=+1)")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"{name} last row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    return T


# --------------------------------------------------------------------------- camera


@dataclass(frozen=True)
class Camera:
    """A calibrated camera: intrinsics ``K``, distortion, image size and pose.

    Parameters
    ----------
    K : (3, 3) array
        Pinhole intrinsics, OpenCV pixel convention (top-left pixel centre at 0, 0).
        Skew must be zero (COLMAP has no skew).
    dist : (5,) array
        OpenCV distortion ``(k1, k2, p1, p2, k3)``.
    width, height : int
        Image size in pixels.
    world_from_cam : (4, 4) array
        Camera-to-world rigid transform, camera frame x right, y down, z forward.
    name : str
        Free-form identifier (``cam0``, a view id, ...).
    """

    K: np.ndarray
    width: int
    height: int
    world_from_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    name: str = ""

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        check_shape("K", K, (3, 3))
        if abs(K[0, 1]) > 1e-9:
            raise InputError(f"camera {self.name!r}: K has skew {K[0, 1]}; resample to a skew-free K")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"camera {self.name!r}: focal lengths must be > 0, got {K[0, 0]}, {K[1, 1]}")
        dist = np.zeros(5)
        d = np.asarray(self.dist, dtype=np.float64).ravel()
        if d.size > 5:
            raise ShapeError(f"camera {self.name!r}: dist has {d.size} coefficients, expected at most 5")
        dist[: d.size] = d
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"camera {self.name!r}: image size {self.width}x{self.height} must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "world_from_cam", _check_rigid("world_from_cam", self.world_from_cam))

    # -- simple accessors
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return (self.width, self.height)

    @property
    def cam_from_world(self) -> np.ndarray:
        T = np.eye(4)
        R = self.world_from_cam[:3, :3]
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ self.world_from_cam[:3, 3]
        return T

    @property
    def centre_world(self) -> np.ndarray:
        """Camera centre in world coordinates, shape (3,)."""
        return self.world_from_cam[:3, 3].copy()

    @property
    def forward_world(self) -> np.ndarray:
        """Unit optical axis (+z of the camera) in world coordinates."""
        return self.world_from_cam[:3, 2].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def with_pose(self, world_from_cam) -> Camera:
        return replace(self, world_from_cam=np.asarray(world_from_cam, dtype=np.float64))

    def with_name(self, name: str) -> Camera:
        return replace(self, name=name)

    def scaled(self, factor: float) -> Camera:
        """The same camera at ``factor`` times the resolution (pixel centres kept consistent)."""
        w = int(round(self.width * factor))
        h = int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return replace(self, K=K, width=w, height=h)

    # -- projection
    def world_to_cam(self, points_world) -> np.ndarray:
        """Transform (N, 3) world points into the camera frame."""
        P = np.asarray(points_world, dtype=np.float64)
        check_shape("points_world", P, (None, 3))
        T = self.cam_from_world
        return P @ T[:3, :3].T + T[:3, 3]

    def distort_normalized(self, xy) -> np.ndarray:
        """Apply the OpenCV distortion model to normalised coordinates, (N, 2) → (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        if not self.has_distortion:
            return xy.copy()
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def undistort_normalized(self, xy_distorted, iterations: int = 20) -> np.ndarray:
        """Invert :meth:`distort_normalized` by fixed-point iteration (as OpenCV does)."""
        xyd = np.asarray(xy_distorted, dtype=np.float64)
        if not self.has_distortion:
            return xyd.copy()
        k1, k2, p1, p2, k3 = self.dist
        x, y = xyd[:, 0].copy(), xyd[:, 1].copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (xyd[:, 0] - dx) / radial
            y = (xyd[:, 1] - dy) / radial
        return np.stack([x, y], axis=1)

    def project(self, points_world) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to pixels.

        Parameters
        ----------
        points_world : (N, 3) array, metres.

        Returns
        -------
        uv : (N, 2) float64 pixel coordinates (OpenCV convention). Points at or behind
            the camera (z <= 0) get NaN.
        z : (N,) depth along the optical axis in metres.
        """
        Pc = self.world_to_cam(points_world)
        z = Pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = Pc[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        xy = self.distort_normalized(xy)
        uv = np.empty_like(xy)
        uv[:, 0] = self.fx * xy[:, 0] + self.cx
        uv[:, 1] = self.fy * xy[:, 1] + self.cy
        return uv, z

    def unproject(self, uv, z) -> np.ndarray:
        """Inverse of :meth:`project`: pixels (N, 2) and depths z (N,) → world points (N, 3)."""
        uv = np.asarray(uv, dtype=np.float64)
        check_shape("uv", uv, (None, 2))
        z = np.broadcast_to(np.asarray(z, dtype=np.float64), (uv.shape[0],))
        xyd = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        xy = self.undistort_normalized(xyd)
        Pc = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
        R, t = self.world_from_cam[:3, :3], self.world_from_cam[:3, 3]
        return Pc @ R.T + t

    def pixel_rays(self, uv=None) -> tuple[np.ndarray, np.ndarray]:
        """Unit world-space ray directions through pixel centres.

        Parameters
        ----------
        uv : (N, 2) array, optional
            Pixels to cast through. Default: every pixel, returned as (H, W, 3).

        Returns
        -------
        origin : (3,) camera centre in world coordinates.
        directions : (N, 3) or (H, W, 3) unit vectors.
        """
        if uv is None:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
            pts = np.stack([u.ravel(), v.ravel()], axis=1)
            shape = (self.height, self.width, 3)
        else:
            pts = np.asarray(uv, dtype=np.float64)
            check_shape("uv", pts, (None, 2))
            shape = (pts.shape[0], 3)
        xyd = np.stack([(pts[:, 0] - self.cx) / self.fx, (pts[:, 1] - self.cy) / self.fy], axis=1)
        xy = self.undistort_normalized(xyd)
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        d = d @ self.world_from_cam[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self.centre_world, d.reshape(shape)

    def supersampled_rays(self, ss: int) -> tuple[np.ndarray, np.ndarray]:
        """Rays of ``ss x ss`` stratified samples per pixel.

        Returns
        -------
        origin : (3,) camera centre in world coordinates.
        directions : (H*W*ss*ss, 3) unit vectors, pixel-major (the ss² samples of a pixel are
            contiguous; sample (i, j) of pixel (u, v) sits at (u + offs[j], v + offs[i])).
        """
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        uu, vv = np.broadcast_arrays(
            u[..., None, None] + offs[None, None, None, :], v[..., None, None] + offs[None, None, :, None]
        )
        return self.pixel_rays(np.stack([uu.reshape(-1), vv.reshape(-1)], axis=1))

    def in_image(self, uv, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (pixel centres 0..W-1, with ``margin``)."""
        uv = np.asarray(uv)
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= -0.5 - margin)
                & (uv[:, 0] <= self.width - 0.5 + margin)
                & (uv[:, 1] >= -0.5 - margin)
                & (uv[:, 1] <= self.height - 0.5 + margin)
            )

    def projection_matrix(self) -> np.ndarray:
        """3×4 ``K [R | t]`` (ignores distortion)."""
        return self.K @ self.cam_from_world[:3, :]


# --------------------------------------------------------------------------- atomic text


#: :func:`coincident_views`: camera centres closer than this fraction of their median
#: distance to the centres' centroid, and optical frames within this angle, count as one
#: viewpoint. The Middlebury temple ring photographs its first viewpoint twice (views 1
#: and 11: identical poses, the photographs 41.5 dB apart); a turntable's 0 deg and 360 deg
#: stops would be the same.
COINCIDENT_CENTRE_REL = 5e-3
COINCIDENT_ANGLE_DEG = 0.5


def coincident_views(
    cameras: Sequence[Camera],
    *,
    centre_tol_rel: float = COINCIDENT_CENTRE_REL,
    angle_tol_deg: float = COINCIDENT_ANGLE_DEG,
) -> list[tuple[int, ...]]:
    """Groups of views that photograph the same viewpoint.

    Two views are coincident when their camera centres are closer than
    ``centre_tol_rel`` × the median distance of all centres to their centroid and the
    rotation between their camera frames is below ``angle_tol_deg``; groups are the
    connected components of that relation (so a chain of near-duplicates is one group).
    Leave-one-out holds a group out together: a view whose twin stays in the model is
    not a novel view.

    Parameters
    ----------
    cameras : V cameras.
    centre_tol_rel : float > 0, relative centre tolerance.
    angle_tol_deg : float > 0, degrees.

    Returns
    -------
    list of tuples of view indices, ascending, each of 2 or more views; views with no
    twin are in none.
    """
    if not (math.isfinite(centre_tol_rel) and centre_tol_rel > 0):
        raise InputError(f"coincident_views: centre_tol_rel must be > 0, got {centre_tol_rel}")
    if not (math.isfinite(angle_tol_deg) and angle_tol_deg > 0):
        raise InputError(f"coincident_views: angle_tol_deg must be > 0, got {angle_tol_deg}")
    cams = list(cameras)
    V = len(cams)
    if V < 2:
        return []
    c = np.array([cam.centre_world for cam in cams])
    R = np.array([cam.world_from_cam[:3, :3] for cam in cams])
    spread = float(np.median(np.linalg.norm(c - c.mean(axis=0), axis=1)))
    # all views at one centre (a pure rotation set): only equal centres coincide
    tol_c = centre_tol_rel * spread if spread > 0 else 0.0
    cos_tol = math.cos(math.radians(angle_tol_deg))
    parent = list(range(V))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
    # angle of R_a^T R_b: trace = 1 + 2 cos(theta)
    tr = np.einsum("aji,bji->ab", R, R)
    for a, b in zip(*np.nonzero(np.triu((d <= tol_c) & ((tr - 1.0) / 2.0 >= cos_tol), k=1)), strict=True):
        ra, rb = root(int(a)), root(int(b))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for v in range(V):
        groups.setdefault(root(v), []).append(v)
    return sorted(tuple(g) for g in groups.values() if len(g) > 1)


def _atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# --------------------------------------------------------------------------- COLMAP text


def _colmap_model_and_params(cam: Camera) -> tuple[str, list[float]]:
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5
    k1, k2, p1, p2, k3 = cam.dist
    if not cam.has_distortion:
        return "PINHOLE", [fx, fy, cx, cy]
    if k3 == 0:
        return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]


def _rotmat_to_qwxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def _qwxyz_to_rotmat(q) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w]).as_matrix()


class _ColmapModelError(ValueError):
    """Internal: a COLMAP camera model or parameter list this module cannot map."""


#: COLMAP camera models with an exact OpenCV 5-term equivalent, and their parameter names.
COLMAP_MODELS_SUPPORTED = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


def colmap_intrinsics(model: str, params) -> tuple[np.ndarray, np.ndarray]:
    """``(K, dist)`` in the OpenCV convention of a COLMAP camera ``model`` and its ``params``.

    Only models with an exact OpenCV 5-term equivalent are mapped (the keys of
    :data:`COLMAP_MODELS_SUPPORTED`; FULL_OPENCV only with k4 = k5 = k6 = 0): fisheye,
    FOV, thin-prism, division and spherical models have no such equivalent and raise
    ``ValueError`` naming the model (undistort them with COLMAP's ``image_undistorter``
    first). The principal point moves by −0.5 px (COLMAP's top-left pixel centre is
    at 0.5, 0.5).
    """
    p = [float(x) for x in params]
    names = COLMAP_MODELS_SUPPORTED.get(model)
    if names is None:
        raise _ColmapModelError(
            f"camera model {model} not supported (use SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or "
            "FULL_OPENCV; undistort other models with COLMAP's image_undistorter first)"
        )
    if len(p) != len(names):
        raise _ColmapModelError(
            f"wrong number of parameters for {model}: {len(p)}, expected {len(names)} ({', '.join(names)})"
        )
    if not all(math.isfinite(x) for x in p):
        raise _ColmapModelError(f"camera parameters of {model} are not finite: {p}")
    v = dict(zip(names, p, strict=True))
    dist = np.zeros(5)
    fx = fy = v.get("f", 0.0)
    fx, fy = v.get("fx", fx), v.get("fy", fy)
    if model == "SIMPLE_RADIAL":
        dist[0] = v["k"]
    elif model == "RADIAL":
        dist[:2] = (v["k1"], v["k2"])
    elif model == "OPENCV":
        dist[:4] = (v["k1"], v["k2"], v["p1"], v["p2"])
    elif model == "FULL_OPENCV":
        if v["k4"] or v["k5"] or v["k6"]:
            raise _ColmapModelError("FULL_OPENCV with k4..k6 != 0 is not supported (rational model)")
        dist[:] = (v["k1"], v["k2"], v["p1"], v["p2"], v["k3"])
    K = np.array([[fx, 0, v["cx"] - 0.5], [0, fy, v["cy"] - 0.5], [0, 0, 1]])
    return K, dist


def _checked_qwxyz_to_rotmat(q, t=(0.0, 0.0, 0.0), *, where: str, tol: float = 1e-3) -> np.ndarray:
    """Rotation of a COLMAP quaternion, refusing what COLMAP would silently turn into
    garbage: a non-finite pose, a zero quaternion (scipy would raise a bare ValueError)
    and one whose length is off 1 by more than ``tol`` (a wrong column order or a
    corrupt file rather than rounding). Near-unit quaternions are normalised."""
    q = np.asarray(q, dtype=np.float64)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(np.asarray(t, dtype=np.float64)))):
        raise FormatError(f"{where}: pose is not finite (quaternion {q.tolist()}, translation {list(t)})")
    n = float(np.linalg.norm(q))
    if n < 1e-12:
        raise FormatError(f"{where}: rotation quaternion (QW, QX, QY, QZ) is zero; expected unit length")
    if abs(n - 1.0) > tol:
        raise FormatError(
            f"{where}: rotation quaternion {q.tolist()} has length {n:.6g}, expected 1 "
            f"(within {tol:g}); is the column order QW QX QY QZ?"
        )
    return _qwxyz_to_rotmat(q / n)


def colmap_reconstruction(
    cameras: Sequence[Camera],
    names: Sequence[str] | None = None,
    *,
    share_intrinsics: Sequence[int] | None = None,
    points3d=None,
):
    """The views as a ``pycolmap.Reconstruction`` (COLMAP's own model, written as text
    or binary by its ``write_text`` / ``write_binary``): one COLMAP camera per
    ``share_intrinsics`` group (default one per image), each in a trivial rig, one image
    per camera in a trivial frame with its ``cam_from_world`` pose, and ``points3d``
    ((M, 3), optional) as points without tracks (grey, error -1: not measured)."""
    import pycolmap

    names = list(names) if names is not None else [c.name for c in cameras]
    if len(names) != len(cameras):
        raise InputError(f"{len(names)} names for {len(cameras)} cameras")
    groups = list(share_intrinsics) if share_intrinsics is not None else list(range(len(cameras)))
    rec = pycolmap.Reconstruction()
    written: dict[int, int] = {}
    for cam, g in zip(cameras, groups, strict=True):
        if g in written:
            continue
        model, params = _colmap_model_and_params(cam)
        cid = len(written) + 1
        written[g] = cid
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model=model, width=int(cam.width), height=int(cam.height), params=params, camera_id=cid)
        )
    for i, (cam, g, name) in enumerate(zip(cameras, groups, names, strict=True), start=1):
        if any(c.isspace() for c in name):
            raise InputError(f"COLMAP image names cannot contain spaces: {name!r}")
        T = cam.cam_from_world
        w, x, y, z = _rotmat_to_qwxyz(T[:3, :3])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), np.asarray(T[:3, 3], np.float64))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=str(name), camera_id=written[g], image_id=i), pose)
    if points3d is not None:
        grey = np.array([128, 128, 128], np.uint8)
        for p in np.asarray(points3d, dtype=np.float64).reshape(-1, 3):
            rec.add_point3D(p, pycolmap.Track(), grey)
    return rec


def write_colmap_text(
    directory,
    cameras: Sequence[Camera],
    names: Sequence[str] | None = None,
    *,
    share_intrinsics: Sequence[int] | None = None,
    points3d=None,
) -> None:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``: the
    layout COLMAP 3 and 4 both read), written by pycolmap (:func:`colmap_reconstruction`).

    Parameters
    ----------
    directory : path
        Output folder (created). Any ``*.bin`` model files there are removed, since
        COLMAP reads ``.bin`` before ``.txt``.
    cameras : sequence of Camera
        One per image.
    names : sequence of str, optional
        Image names (relative paths); default ``cam.name``.
    share_intrinsics : sequence of int, optional
        For each image, the index of its COLMAP camera; images with the same index
        share intrinsics (e.g. one physical camera over many table angles). Default:
        one COLMAP camera per image.
    points3d : (M, 3) array, optional
        Sparse points written to ``points3D.txt`` (no tracks).
    """
    import shutil
    import tempfile

    rec = colmap_reconstruction(cameras, names, share_intrinsics=share_intrinsics, points3d=points3d)
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for b in ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin"):
        (d / b).unlink(missing_ok=True)
    # written beside, then each file renamed into place: a crash leaves whole files
    tmp = Path(tempfile.mkdtemp(prefix=".colmap-", dir=d))
    try:
        rec.write_text(str(tmp))
        for extra in ("rigs.txt", "frames.txt"):
            # COLMAP 4's trivial rigs and frames repeat the poses; without them the model
            # is COLMAP 3's layout (which COLMAP 4 reads too) and images.txt is the pose
            (tmp / extra).unlink(missing_ok=True)
            (d / extra).unlink(missing_ok=True)
        for f in sorted(tmp.iterdir()):
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(f, d / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def read_colmap_text(directory) -> list[tuple[str, Camera]]:
    """Read a COLMAP text model (``cameras.txt`` and ``images.txt``; ``points3D.txt`` may
    be absent) through ``pycolmap.Reconstruction.read_text`` into
    ``[(image_name, Camera), ...]`` (sorted by image id).

    Supports the SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and
    FULL_OPENCV camera models (FULL_OPENCV only with k4 = k5 = k6 = 0). Errors name
    the file and line (and the image).
    """
    d = Path(directory)
    cams_path, imgs_path = d / "cameras.txt", d / "images.txt"
    for p in (cams_path, imgs_path):
        if not p.is_file():
            raise FormatError(f"COLMAP text model: {p} not found (expected cameras.txt and images.txt in {d})")
    import pycolmap

    rec = pycolmap.Reconstruction()
    with _colmap_text_folder(d) as src:
        try:
            rec.read_text(str(src))
        except Exception as e:  # noqa: BLE001  pycolmap maps C++ errors to several types (ValueError, IndexError, ...): any is a bad file
            raise FormatError(_colmap_text_error(d, e)) from None
    return _views_of(rec, d, text=True)


@contextmanager
def _colmap_text_folder(d: Path) -> Iterator[Path]:
    """``d``, or when it has no ``points3D.txt`` (pycolmap needs one; camera-only models
    such as a session's ``cameras/`` may lack it) a temporary folder linking its two
    files beside an empty one."""
    import shutil
    import tempfile

    if (d / "points3D.txt").is_file():
        yield d
        return
    tmp = Path(tempfile.mkdtemp(prefix="opacityhull-colmap-"))
    try:
        for n in ("cameras.txt", "images.txt", "rigs.txt", "frames.txt"):
            if (d / n).is_file():
                (tmp / n).symlink_to((d / n).resolve())
        (tmp / "points3D.txt").write_text("")
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, words) of the data lines of a COLMAP text file: comments and
    blank lines skipped; in ``images.txt`` only the pose lines (every other data line
    is a POINTS2D line, possibly empty)."""
    images = path.name == "images.txt"
    expect_points = False
    for n, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        s = line.strip()
        if s.startswith("#"):
            continue
        if images and expect_points:
            expect_points = False
            continue
        if not s:
            continue
        expect_points = images
        yield n, s.split()


def _line_of(path: Path, first_word: int) -> int | None:
    """The line of ``path`` whose data line starts with id ``first_word``."""
    for n, words in _data_lines(path):
        if words[0] == str(first_word):
            return n
    return None


def _colmap_text_error(d: Path, e: Exception) -> str:
    """What pycolmap could not read in the text model at ``d``, with file and line:
    pycolmap's messages name neither."""
    for path, what in ((d / "cameras.txt", "camera"), (d / "images.txt", "image")):
        for n, words in _data_lines(path):
            try:
                ids = [int(words[0])] + ([int(words[2]), int(words[3])] if what == "camera" else [int(words[8])])
                nums = [float(v) for v in (words[4:] if what == "camera" else words[1:8])]
            except (ValueError, IndexError):
                return f"{path}:{n}: cannot parse the {what} line {' '.join(words)[:80]!r}"
            del ids
            if what == "camera" and words[1] not in COLMAP_MODELS_SUPPORTED:
                return f"{path}:{n}: camera model {words[1]} not supported ({str(e).strip()[:120]})"
            if not all(math.isfinite(v) for v in nums):
                name = " ".join(words[9:]) if what == "image" else words[1]
                return f"{path}:{n}: {what} {name!r}: pose is not finite ({' '.join(words[:8])})"
    cams = {w[0] for _, w in _data_lines(d / "cameras.txt")}
    for n, words in _data_lines(d / "images.txt"):
        if len(words) > 8 and words[8] not in cams:
            name = " ".join(words[9:])
            return f"{d / 'images.txt'}:{n}: image {name!r} refers to camera {words[8]}, not in cameras.txt"
    return f"{d}: cannot read the COLMAP text model ({str(e).strip()})"


def _views_of(rec, d: Path, *, text: bool) -> list[tuple[str, Camera]]:
    """``[(image_name, Camera)]`` of a read ``pycolmap.Reconstruction`` (registered images,
    by image id), its camera models mapped by :func:`colmap_intrinsics` and its poses
    checked (:func:`_checked_qwxyz_to_rotmat`); errors name ``cameras.txt``/``.bin`` and
    ``images.txt``/``.bin`` with the line (text) or the id (binary)."""
    cams_file, imgs_file = (d / "cameras.txt", d / "images.txt") if text else (d / "cameras.bin", d / "images.bin")
    intr: dict[int, tuple[np.ndarray, np.ndarray, int, int]] = {}
    for cid, c in rec.cameras.items():
        try:
            K, dist = colmap_intrinsics(c.model.name, np.asarray(c.params))
        except _ColmapModelError as e:
            where = f"{cams_file}:{_line_of(cams_file, cid)}" if text else f"{cams_file}: camera {cid}"
            raise FormatError(f"{where}: {e}") from None
        intr[cid] = (K, dist, int(c.width), int(c.height))
    out: list[tuple[str, Camera]] = []
    for iid in sorted(rec.images):
        img = rec.images[iid]
        if not img.has_pose:
            continue
        cfw = img.cam_from_world()
        x, y, z, w = (float(v) for v in np.asarray(cfw.rotation.quat))
        t = [float(v) for v in np.asarray(cfw.translation)]
        where = (
            f"{imgs_file}:{_line_of(imgs_file, iid)}: image {img.name!r}"
            if text
            else f"{imgs_file}: image {img.name!r} (id {iid})"
        )
        R = _checked_qwxyz_to_rotmat([w, x, y, z], t, where=where)
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ np.asarray(t)
        K, dist, wd, ht = intr[img.camera_id]
        out.append((img.name, Camera(K=K, dist=dist, width=wd, height=ht, world_from_cam=T, name=img.name)))
    return out


COLMAP_BINARY_FILES = ("cameras.bin", "images.bin")


def colmap_model_kind(directory) -> str:
    """``"binary"`` when ``directory`` holds ``cameras.bin`` or ``images.bin`` (COLMAP
    reads ``.bin`` before ``.txt``), else ``"text"``."""
    d = Path(directory)
    return "binary" if any((d / b).is_file() for b in COLMAP_BINARY_FILES) else "text"


def read_colmap_binary(directory) -> list[tuple[str, Camera]]:
    """Read a binary COLMAP model through ``pycolmap.Reconstruction`` into
    ``[(image_name, Camera), ...]`` (registered images only, sorted by image id).

    Camera models are mapped by :func:`colmap_intrinsics`. pycolmap keeps quaternions as
    stored (a zero one becomes the identity rotation), so each is checked here: zero,
    non-unit or non-finite poses raise :class:`FormatError` naming ``images.bin`` and
    the image.
    """
    d = Path(directory)
    try:
        import pycolmap
    except ImportError:  # pragma: no cover - pycolmap is a dependency
        raise FormatError(
            f"{d}: a binary COLMAP model needs pycolmap (pip install pycolmap), "
            "or convert it with `colmap model_converter --output_type TXT`"
        ) from None
    try:
        rec = pycolmap.Reconstruction(str(d))
    except Exception as e:  # noqa: BLE001  pycolmap maps C++ errors to several types (ValueError, RuntimeError, ...): any is a bad model
        raise FormatError(
            f"{d}: cannot read the binary COLMAP model ({str(e).strip()}); expected cameras.bin, "
            "images.bin and points3D.bin (COLMAP 4 also rigs.bin, frames.bin)"
        ) from None
    return _views_of(rec, d, text=False)


def read_colmap_model(directory) -> list[tuple[str, Camera]]:
    """Read a COLMAP model, binary (via pycolmap) when ``.bin`` files are present (they win
    over ``.txt``, as in COLMAP), else text (:func:`read_colmap_text`)."""
    if colmap_model_kind(directory) == "binary":
        return read_colmap_binary(directory)
    return read_colmap_text(directory)


# --------------------------------------------------------------------------- OpenCV YAML


def write_opencv_yaml(path, cam: Camera, *, extra: dict | None = None) -> None:
    """Write a camera as OpenCV FileStorage YAML (``camera_matrix``,
    ``distortion_coefficients``, ``image_width``, ``image_height``, ``world_from_cam``).

    ``extra`` maps names to numbers or arrays written alongside (e.g. ``reproj_rms_px``).
    The write is atomic.
    """
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp{os.getpid()}_{path.name}")
    if not str(tmp).endswith((".yaml", ".yml")):
        tmp = tmp.with_suffix(".yaml")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("camera_name", cam.name or path.stem)
        fs.write("image_width", int(cam.width))
        fs.write("image_height", int(cam.height))
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", cam.dist.reshape(1, 5))
        fs.write("world_from_cam", cam.world_from_cam)
        for k, v in (extra or {}).items():
            if isinstance(v, (int, float, np.floating, np.integer)):
                fs.write(k, float(v))
            elif isinstance(v, str):
                fs.write(k, v)
            else:
                fs.write(k, np.asarray(v, dtype=np.float64))
    finally:
        fs.release()
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_opencv_yaml(path) -> Camera:
    """Read a camera written by :func:`write_opencv_yaml` (or any OpenCV calibration
    YAML with ``camera_matrix``, ``distortion_coefficients``, ``image_width``,
    ``image_height``; the pose defaults to identity)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"camera file {path} not found")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise FormatError(f"{path}: not a readable OpenCV YAML/XML file")

        def mat(key, required=True):
            node = fs.getNode(key)
            if node.empty():
                if required:
                    raise FormatError(f"{path}: missing key {key!r}")
                return None
            return node.mat()

        K = mat("camera_matrix")
        dist = mat("distortion_coefficients", required=False)
        T = mat("world_from_cam", required=False)
        w = fs.getNode("image_width").real()
        h = fs.getNode("image_height").real()
        name_node = fs.getNode("camera_name")
        name = name_node.string() if not name_node.empty() else path.stem
    finally:
        fs.release()
    if K is None or K.shape != (3, 3):
        raise FormatError(f"{path}: camera_matrix must be 3x3")
    return Camera(
        K=K,
        dist=np.zeros(5) if dist is None else dist.ravel()[:5],
        width=int(w),
        height=int(h),
        world_from_cam=np.eye(4) if T is None else T,
        name=name,
    )


# --------------------------------------------------------------------------- Mitsuba


def mitsuba_sensor_params(cam: Camera) -> dict:
    """Parameters of a Mitsuba ``perspective`` sensor equivalent to ``cam``.

    Returns a plain dict (``fov``, ``fov_axis``, ``principal_point_offset_x``/``_y``,
    ``to_world`` as a nested 4×4 list, ``width``, ``height``); ``sim`` wraps it into a
    Mitsuba dict. Mitsuba has no distortion and no separate fx/fy, so a camera with
    distortion or non-square pixels raises :class:`InputError` — render undistorted
    and distort afterwards.
    """
    if cam.has_distortion:
        raise InputError(f"camera {cam.name!r} has distortion; Mitsuba's perspective sensor has none")
    if abs(cam.fx - cam.fy) > 1e-6 * cam.fx:
        raise InputError(f"camera {cam.name!r}: fx={cam.fx} != fy={cam.fy}; Mitsuba needs square pixels")
    fov_y = math.degrees(2.0 * math.atan(cam.height / (2.0 * cam.fy)))
    # Mitsuba's film x/y run opposite to its camera x/y (mirror), hence the minus signs;
    # +0.5 converts OpenCV's pixel-centre convention to continuous film coordinates.
    ppx = -(cam.cx + 0.5 - cam.width / 2.0) / cam.width
    ppy = -(cam.cy + 0.5 - cam.height / 2.0) / cam.height
    return {
        "fov": fov_y,
        "fov_axis": "y",
        "principal_point_offset_x": ppx,
        "principal_point_offset_y": ppy,
        "to_world": (cam.world_from_cam @ _MITSUBA_FLIP).tolist(),
        "width": cam.width,
        "height": cam.height,
    }


def camera_from_mitsuba_params(p: dict, name: str = "") -> Camera:
    """Inverse of :func:`mitsuba_sensor_params`."""
    w, h = int(p["width"]), int(p["height"])
    if p.get("fov_axis", "x") != "y":
        raise InputError("only fov_axis='y' sensors are supported")
    fy = h / (2.0 * math.tan(math.radians(p["fov"]) / 2.0))
    cx = -p.get("principal_point_offset_x", 0.0) * w + w / 2.0 - 0.5
    cy = -p.get("principal_point_offset_y", 0.0) * h + h / 2.0 - 0.5
    K = np.array([[fy, 0, cx], [0, fy, cy], [0, 0, 1]])
    T = np.asarray(p["to_world"], dtype=np.float64) @ _MITSUBA_FLIP
    return Camera(K=K, width=w, height=h, world_from_cam=T, name=name)


# --------------------------------------------------------------------------- nerfstudio


def nerfstudio_transform_matrix(cam: Camera) -> list[list[float]]:
    """``transform_matrix`` of a nerfstudio frame (OpenGL camera-to-world)."""
    return (cam.world_from_cam @ _OPENGL_FLIP).tolist()


def nerfstudio_intrinsics(cam: Camera) -> dict:
    """Per-frame intrinsics keys of nerfstudio's ``transforms.json`` (``OPENCV`` model).

    nerfstudio uses the same pixel-centre convention as COLMAP (+0.5).
    """
    k1, k2, p1, p2, k3 = cam.dist
    return {
        "camera_model": "OPENCV",
        "fl_x": cam.fx,
        "fl_y": cam.fy,
        "cx": cam.cx + 0.5,
        "cy": cam.cy + 0.5,
        "w": cam.width,
        "h": cam.height,
        "k1": k1,
        "k2": k2,
        "k3": k3,
        "p1": p1,
        "p2": p2,
    }


def camera_from_nerfstudio(
    transform_matrix,
    *,
    fl_x: float,
    fl_y: float,
    cx: float,
    cy: float,
    w: int,
    h: int,
    k1: float = 0.0,
    k2: float = 0.0,
    k3: float = 0.0,
    p1: float = 0.0,
    p2: float = 0.0,
    name: str = "",
    rigid_tol: float = 1e-4,
) -> Camera:
    """Inverse of :func:`nerfstudio_transform_matrix` and :func:`nerfstudio_intrinsics`.

    Parameters
    ----------
    transform_matrix : (4, 4) or (3, 4) array
        nerfstudio camera-to-world, OpenGL camera (x right, y up, z backward).
    fl_x, fl_y, cx, cy : float
        Pixels; the principal point in nerfstudio's (= COLMAP's) convention, top-left
        pixel centre at (0.5, 0.5).
    w, h : int
        Image size in pixels.
    k1, k2, k3, p1, p2 : float
        nerfstudio ``OPENCV`` distortion (OpenCV's ``k1 k2 p1 p2 k3``).
    rigid_tol : float
        JSON files often carry 6–8 significant digits, so the rotation may be off
        orthonormal by ~1e-7: within ``rigid_tol`` it is re-orthonormalised (nearest
        rotation, SVD); beyond, or with a reflection or scale, :class:`InputError`.
    """
    M = np.asarray(transform_matrix, dtype=np.float64)
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4):
        raise InputError(f"transform_matrix has shape {M.shape}, expected 4x4 (or 3x4)")
    if not np.all(np.isfinite(M)):
        raise InputError("transform_matrix contains NaN or Inf")
    if not np.allclose(M[3], [0, 0, 0, 1], atol=1e-9):
        raise InputError(f"transform_matrix last row is {M[3].tolist()}, expected [0, 0, 0, 1]")
    R = M[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > rigid_tol or det <= 0:
        raise InputError(
            f"transform_matrix is not rigid (max |RᵀR − I| = {err:.3g}, det = {det:.6g}; expected a "
            f"rotation within {rigid_tol:g} and det +1: no scale, shear or mirror)"
        )
    U, _, Vt = np.linalg.svd(R)
    M = M.copy()
    M[:3, :3] = U @ Vt
    K = np.array([[fl_x, 0.0, cx - 0.5], [0.0, fl_y, cy - 0.5], [0.0, 0.0, 1.0]])
    # _OPENGL_FLIP is its own inverse
    return Camera(
        K=K,
        width=int(w),
        height=int(h),
        world_from_cam=M @ _OPENGL_FLIP,
        dist=np.array([k1, k2, p1, p2, k3]),
        name=name,
    )
