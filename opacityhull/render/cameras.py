"""Cameras for rendering: a captured view's camera, look-at cameras, orbits, resizing,
and the parsers of the CLI's ``--view``, ``--look-at`` and ``--orbit`` options."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..camera import Camera, look_at_world_from_cam, object_from_rig, rig_from_object
from ..errors import InputError

__all__ = [
    "resize_camera",
    "look_at_camera",
    "captured_view_camera",
    "scene_target",
    "orbit_cameras",
    "parse_view_spec",
    "parse_look_at",
    "mean_fov_y_deg",
]


def resize_camera(cam: Camera, width: int | None = None, height: int | None = None) -> Camera:
    """``cam`` at another resolution with the same vertical field of view and the
    principal point at the same relative position (square pixels are kept square; a
    different aspect ratio widens or narrows the horizontal field of view)."""
    w = int(width) if width else None
    h = int(height) if height else None
    if w is None and h is None:
        return cam
    if w is not None and w <= 0 or h is not None and h <= 0:
        raise InputError(f"--width/--height must be positive, got {width}x{height}")
    if h is None:
        assert w is not None  # both None returned above
        h = max(1, int(round(cam.height * w / cam.width)))
    if w is None:
        w = max(1, int(round(cam.width * h / cam.height)))
    sy = h / cam.height
    K = cam.K.copy()
    K[1, 1] = cam.fy * sy
    K[0, 0] = cam.fx * sy
    K[0, 2] = (cam.cx + 0.5) / cam.width * w - 0.5
    K[1, 2] = (cam.cy + 0.5) / cam.height * h - 0.5
    return Camera(K=K, width=w, height=h, world_from_cam=cam.world_from_cam, dist=cam.dist, name=cam.name)


def look_at_camera(eye, target, *, fov_y_deg: float, width: int, height: int, name: str = "look_at") -> Camera:
    """A pinhole camera at ``eye`` looking at ``target`` with image up ≈ +Y."""
    if not (0 < fov_y_deg < 180):
        raise InputError(f"field of view {fov_y_deg} deg: expected 0 < fov < 180")
    f = height / (2.0 * math.tan(math.radians(fov_y_deg) / 2.0))
    K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
    return Camera(
        K=K, width=int(width), height=int(height), world_from_cam=look_at_world_from_cam(eye, target), name=name
    )


def mean_fov_y_deg(cameras: Sequence[Camera]) -> float:
    return float(np.mean([math.degrees(2 * math.atan(c.height / (2 * c.fy))) for c in cameras]))


def captured_view_camera(views, camera_index: int, table_deg: float) -> Camera:
    """The object-frame camera of view (camera_index, table_deg).

    ``views`` are the model's :class:`~opacityhull.model.ViewInfo`. A captured view is
    returned as is; another table angle of a captured physical camera is derived by
    turning the table (the camera is fixed in the rig frame): ``object_from_rig(a') ·
    rig_from_object(a) · world_from_cam``.
    """
    same = [v for v in views if v.camera_index == camera_index]
    if not same:
        cams = sorted({v.camera_index for v in views})
        raise InputError(f"--view {camera_index},{table_deg}: no captured camera {camera_index} (cameras: {cams})")
    for v in same:
        if abs(((v.table_deg - table_deg) + 180.0) % 360.0 - 180.0) < 1e-6:
            return v.camera
    v = same[0]
    T = object_from_rig(table_deg) @ rig_from_object(v.table_deg) @ v.camera.world_from_cam
    return v.camera.with_pose(T).with_name(f"c{camera_index}_t{table_deg % 360.0:07.3f}")


def scene_target(cameras: Sequence[Camera], fallback=None) -> np.ndarray:
    """The point closest (least squares) to all optical axes — where the rig aims.
    Falls back to ``fallback`` (e.g. the surfel centroid) when the axes are parallel."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        d = c.forward_world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.centre_world
    if np.linalg.cond(A) > 1e8:
        if fallback is None:
            raise InputError("cannot find where the cameras aim (optical axes parallel); give --look-at")
        return np.asarray(fallback, dtype=np.float64)
    return np.linalg.solve(A, b)


def orbit_cameras(
    cameras: Sequence[Camera],
    n: int,
    *,
    width: int | None = None,
    height: int | None = None,
    target=None,
    elevation_deg: float | None = None,
    distance_m: float | None = None,
    fov_y_deg: float | None = None,
) -> list[Camera]:
    """``n`` cameras on a circle about the vertical (+Y) axis through the target, at the
    captured cameras' mean elevation and distance (unless given), starting at the first
    captured camera's azimuth, looking at the target.

    Intrinsics follow the first captured camera (its vertical field of view unless
    ``fov_y_deg``), resized to ``width`` × ``height``.
    """
    if n < 1:
        raise InputError(f"--orbit {n}: expected at least 1 frame")
    t = scene_target(cameras) if target is None else np.asarray(target, dtype=np.float64)
    offs = np.stack([c.centre_world - t for c in cameras])
    dist = np.linalg.norm(offs, axis=1)
    el = np.degrees(np.arcsin(np.clip(offs[:, 1] / np.maximum(dist, 1e-12), -1, 1)))
    e = float(np.mean(el)) if elevation_deg is None else float(elevation_deg)
    r = float(np.mean(dist)) if distance_m is None else float(distance_m)
    if not r > 0:
        raise InputError(f"orbit distance {r} m: expected > 0")
    az0 = math.degrees(math.atan2(offs[0, 0], offs[0, 2]))
    ref = cameras[0]
    fov = mean_fov_y_deg([ref]) if fov_y_deg is None else float(fov_y_deg)
    w = int(width) if width else ref.width
    h = int(height) if height else (ref.height if not width else max(1, round(ref.height * w / ref.width)))
    out = []
    for i in range(n):
        az = math.radians(az0 + 360.0 * i / n)
        er = math.radians(e)
        eye = t + r * np.array([math.cos(er) * math.sin(az), math.sin(er), math.cos(er) * math.cos(az)])
        out.append(look_at_camera(eye, t, fov_y_deg=fov, width=w, height=h, name=f"orbit_{i:03d}"))
    return out


def parse_view_spec(spec: str) -> tuple[int, float]:
    """``"CAM,TABLE_DEG"`` → (camera index, table angle in degrees)."""
    parts = [p.strip() for p in str(spec).split(",")]
    try:
        if len(parts) != 2:
            raise ValueError
        c, a = int(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(f"--view {spec!r}: expected CAM,TABLE_DEG, e.g. 0,30") from None
    if c < 0 or not math.isfinite(a):
        raise InputError(f"--view {spec!r}: camera index must be >= 0 and the angle finite")
    return c, a


def parse_look_at(spec: str) -> tuple[np.ndarray, np.ndarray, float | None]:
    """``"EX,EY,EZ,TX,TY,TZ[,FOV]"`` (metres, degrees) → (eye, target, fov or None)."""
    try:
        vals = [float(p) for p in str(spec).split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (6, 7) or not all(math.isfinite(v) for v in vals):
        raise InputError(f"--look-at {spec!r}: expected EX,EY,EZ,TX,TY,TZ[,FOV_DEG] (metres, degrees)")
    eye, target = np.array(vals[:3]), np.array(vals[3:6])
    if np.linalg.norm(eye - target) < 1e-9:
        raise InputError(f"--look-at {spec!r}: eye and target coincide")
    return eye, target, (vals[6] if len(vals) == 7 else None)
