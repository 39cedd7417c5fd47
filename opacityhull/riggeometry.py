"""Rig geometry: where the cameras, lights and displays are. Pure data, no devices.

Read from the ``[geometry]`` part of a rig TOML (the same file for a hardware rig and
the simulated one) and copied verbatim into every session's ``session.toml``, so that
``sim`` (which builds a scene from it), ``acquire`` (which records it), and
``reconstruct``/``relight`` (which read it back from the session) share one
description. Device URLs and DMX channels live in the ``[devices]`` part, parsed by
:mod:`opacityhull.rigs.config`.

Frames (see :mod:`opacityhull.camera`): the rig frame has its origin at the centre of
the turntable top and +Y up along the table axis. Cameras are fixed in the rig frame.
Lights are given at array angle 0 and rotate about +Y with the array. Displays either
rotate with the table (the bottom panel) or are fixed (the back panel).

Schema (all lengths in metres, angles in degrees)::

    [geometry]
    target_m = [0.0, 0.1, 0.0]        # point the cameras aim at

    [[geometry.cameras]]
    name = "cam0"
    width = 320                       # pixels
    height = 240
    distance_m = 1.0                  # from target
    elevation_deg = 0.0               # above the table plane
    azimuth_deg = 0.0                 # about +Y, 0 = looking from +Z
    fov_y_deg = 30.0                  # or focal_px = ...
    gain = 1.0                        # sensor value per (radiance x second)

    [[geometry.lights]]
    id = 0
    elevation_deg = 45.0              # at array angle 0
    azimuth_deg = 0.0
    distance_m = 1.2
    intensity = 1.0                   # calibrated relative output (1 = nominal)
    colour = [1.0, 1.0, 1.0]
    radius_m = 0.025                  # optional: the lamp's emitting sphere (simulator); > 0

    [[geometry.displays]]
    name = "bottom"
    centre_m = [0.0, 0.0, 0.0]
    normal = [0.0, 1.0, 0.0]          # emitting side
    up = [0.0, 0.0, -1.0]             # direction of the panel's pixel row 0
    size_m = [0.6, 0.6]               # width, height
    resolution = [64, 64]             # pattern pixels (width, height)
    rotates_with_table = true
    max_radiance = 1.0                # radiance of a full-white pixel
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Mapping

import numpy as np

from .camera import Camera, look_at_world_from_cam, object_from_rig, rot_y
from .errors import ConfigError

__all__ = [
    "CameraSpec",
    "LightSpec",
    "DisplaySpec",
    "RigGeometry",
    "view_id",
    "parse_view_id",
    "bottom_display",
    "back_display",
]


def bottom_display(size_m: list[float], resolution: list[int], **fields: Any) -> dict[str, Any]:
    """The ``"bottom"`` ``[[geometry.displays]]`` entry: centred at the rig origin, normal
    +y, up -z, turning with the table; ``size_m`` is (width, height) in metres,
    ``resolution`` (columns, rows) in texels; ``fields`` (e.g. ``max_radiance``) are appended."""
    return {
        "name": "bottom",
        "centre_m": [0.0, 0.0, 0.0],
        "normal": [0.0, 1.0, 0.0],
        "up": [0.0, 0.0, -1.0],
        "size_m": size_m,
        "resolution": resolution,
        "rotates_with_table": True,
        **fields,
    }


def back_display(centre_m: list[float], size_m: list[float], resolution: list[int], **fields: Any) -> dict[str, Any]:
    """The ``"back"`` ``[[geometry.displays]]`` entry: centred at ``centre_m`` (rig frame,
    metres), normal +z, up +y; ``fields`` (``rotates_with_table``, ``max_radiance``) as given."""
    return {
        "name": "back",
        "centre_m": centre_m,
        "normal": [0.0, 0.0, 1.0],
        "up": [0.0, 1.0, 0.0],
        "size_m": size_m,
        "resolution": resolution,
        **fields,
    }


def view_id(camera: int, table_deg: float) -> str:
    """Canonical id of "view (c, a)": ``c{c}_t{deg:07.3f}``, e.g. ``c0_t030.000``."""
    return f"c{int(camera)}_t{float(table_deg) % 360.0:07.3f}"


def parse_view_id(vid: str) -> tuple[int, float]:
    """Inverse of :func:`view_id`."""
    try:
        c, t = vid.split("_t")
        return int(c[1:]), float(t)
    except (ValueError, IndexError):
        raise ConfigError(f"{vid!r} is not a view id of the form c<camera>_t<deg>") from None


def _vec(where: str, v, n: int = 3) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected a list of {n} numbers, got {v!r}") from None
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{where}: expected a list of {n} finite numbers, got {v!r}")
    return a


def _num(where: str, d: Mapping, key: str, default=None, *, positive=False, lo=None, hi=None) -> float:
    if key not in d:
        if default is None:
            raise ConfigError(f"{where}: missing key {key!r}")
        return float(default)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{where}.{key}: expected a number, got {v!r}")
    if positive and v <= 0:
        raise ConfigError(f"{where}.{key}: must be > 0, got {v}")
    if lo is not None and v < lo or hi is not None and v > hi:
        raise ConfigError(f"{where}.{key}: must be in [{lo}, {hi}], got {v}")
    return float(v)


def _check_keys(where: str, d: Mapping, allowed: set[str]) -> None:
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


@dataclass(frozen=True)
class CameraSpec:
    name: str
    width: int
    height: int
    distance_m: float
    elevation_deg: float
    azimuth_deg: float
    focal_px: float
    gain: float = 1.0
    cx: float | None = None
    cy: float | None = None

    def nominal_camera(self, target_m: np.ndarray) -> Camera:
        """The camera as designed, pose in the rig frame (``world_from_cam`` = rig_from_cam)."""
        el, az = math.radians(self.elevation_deg), math.radians(self.azimuth_deg)
        offset = self.distance_m * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        eye = np.asarray(target_m) + offset
        T = look_at_world_from_cam(eye, target_m)
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        K = np.array([[self.focal_px, 0, cx], [0, self.focal_px, cy], [0, 0, 1.0]])
        return Camera(K=K, width=self.width, height=self.height, world_from_cam=T, name=self.name)


@dataclass(frozen=True)
class LightSpec:
    id: int
    position_m: np.ndarray  # rig frame, array angle 0
    intensity: float = 1.0
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: radius of the lamp's emitting sphere (a bulb behind a diffuser), metres; ``None``
    #: is an ideal point light (a smooth glass is black under it: no path finds a point)
    radius_m: float | None = None

    def position_rig(self, array_deg: float) -> np.ndarray:
        return rot_y(math.radians(array_deg)) @ self.position_m


@dataclass(frozen=True)
class DisplaySpec:
    name: str
    centre_m: np.ndarray
    normal: np.ndarray
    up: np.ndarray
    size_m: tuple[float, float]
    resolution: tuple[int, int]
    rotates_with_table: bool
    max_radiance: float = 1.0

    def frame(self) -> np.ndarray:
        """4×4 rig_from_panel at table angle 0: panel x = right (pixel columns), y = up
        (towards pixel row 0), z = normal. Panel units are metres, origin at the centre."""
        n = self.normal / np.linalg.norm(self.normal)
        up = self.up - n * float(self.up @ n)
        up /= np.linalg.norm(up)
        right = np.cross(up, n)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, up, n, self.centre_m
        return T

    def corners_rig(self, table_deg: float = 0.0) -> np.ndarray:
        """(4, 3) corners (top-left, top-right, bottom-right, bottom-left as seen from the
        emitting side) in the rig frame at ``table_deg``."""
        w, h = self.size_m
        local = np.array([[-w / 2, h / 2, 0, 1], [w / 2, h / 2, 0, 1], [w / 2, -h / 2, 0, 1], [-w / 2, -h / 2, 0, 1]])
        P = (self.frame() @ local.T).T[:, :3]
        if self.rotates_with_table:
            P = P @ rot_y(math.radians(table_deg)).T
        return P


@dataclass(frozen=True)
class RigGeometry:
    """Cameras, lights and displays of a rig, in the rig frame."""

    target_m: np.ndarray
    cameras: tuple[CameraSpec, ...]
    lights: tuple[LightSpec, ...] = ()
    displays: tuple[DisplaySpec, ...] = ()
    raw: dict = field(default_factory=dict, compare=False)

    # ---- parsing
    @classmethod
    def from_dict(cls, g: Mapping[str, Any], where: str = "geometry") -> RigGeometry:
        if not isinstance(g, Mapping):
            raise ConfigError(f"{where}: expected a table")
        _check_keys(where, g, {"target_m", "cameras", "lights", "displays"})
        target = _vec(f"{where}.target_m", g.get("target_m", [0.0, 0.0, 0.0]))
        cams = []
        names = set()
        raw_cams = g.get("cameras")
        if not raw_cams:
            # the TOML table is [[geometry.cameras]] wherever `where` says the file is
            table = where.rsplit(": ", 1)[-1]
            raise ConfigError(f"{where}.cameras: at least one [[{table}.cameras]] entry is required")
        for i, c in enumerate(raw_cams):
            w = f"{where}.cameras[{i}]"
            _check_keys(
                w,
                c,
                {
                    "name",
                    "width",
                    "height",
                    "distance_m",
                    "elevation_deg",
                    "azimuth_deg",
                    "fov_y_deg",
                    "focal_px",
                    "gain",
                    "cx",
                    "cy",
                },
            )
            name = str(c.get("name", f"cam{i}"))
            if name in names:
                raise ConfigError(f"{w}.name: duplicate camera name {name!r}")
            names.add(name)
            width = int(_num(w, c, "width", positive=True))
            height = int(_num(w, c, "height", positive=True))
            if "focal_px" in c and "fov_y_deg" in c:
                raise ConfigError(f"{w}: give either focal_px or fov_y_deg, not both")
            if "focal_px" in c:
                f = _num(w, c, "focal_px", positive=True)
            else:
                fov = _num(w, c, "fov_y_deg", 30.0, lo=1e-3, hi=179.0)
                f = height / (2.0 * math.tan(math.radians(fov) / 2.0))
            cams.append(
                CameraSpec(
                    name=name,
                    width=width,
                    height=height,
                    distance_m=_num(w, c, "distance_m", positive=True),
                    elevation_deg=_num(w, c, "elevation_deg", 0.0, lo=-90, hi=90),
                    azimuth_deg=_num(w, c, "azimuth_deg", 0.0),
                    focal_px=f,
                    gain=_num(w, c, "gain", 1.0, positive=True),
                    cx=None if "cx" not in c else _num(w, c, "cx"),
                    cy=None if "cy" not in c else _num(w, c, "cy"),
                )
            )
        lights = []
        ids = set()
        for i, L in enumerate(g.get("lights", [])):
            w = f"{where}.lights[{i}]"
            _check_keys(
                w,
                L,
                {"id", "elevation_deg", "azimuth_deg", "distance_m", "position_m", "intensity", "colour", "radius_m"},
            )
            lid = int(_num(w, L, "id", i))
            if lid in ids:
                raise ConfigError(f"{w}.id: duplicate light id {lid}")
            ids.add(lid)
            if "position_m" in L:
                pos = _vec(f"{w}.position_m", L["position_m"])
            else:
                el = math.radians(_num(w, L, "elevation_deg", lo=-90, hi=90))
                az = math.radians(_num(w, L, "azimuth_deg", 0.0))
                r = _num(w, L, "distance_m", positive=True)
                pos = r * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
            if np.linalg.norm(pos) < 1e-9:
                raise ConfigError(f"{w}: light at the origin has no direction")
            cr, cg, cb = (float(x) for x in _vec(f"{w}.colour", L.get("colour", [1.0, 1.0, 1.0])))
            colour = (cr, cg, cb)
            radius = None if "radius_m" not in L else _num(w, L, "radius_m", positive=True)
            if radius is not None and radius >= 0.5 * float(np.linalg.norm(pos)):
                raise ConfigError(
                    f"{w}.radius_m: {radius} m is not a small lamp at {float(np.linalg.norm(pos)):.3g} m from the "
                    "rig origin; expected < half its distance"
                )
            lights.append(
                LightSpec(
                    id=lid,
                    position_m=pos,
                    intensity=_num(w, L, "intensity", 1.0, lo=0.0),
                    colour=colour,
                    radius_m=radius,
                )
            )
        displays = []
        dnames = set()
        for i, d in enumerate(g.get("displays", [])):
            w = f"{where}.displays[{i}]"
            _check_keys(
                w, d, {"name", "centre_m", "normal", "up", "size_m", "resolution", "rotates_with_table", "max_radiance"}
            )
            name = str(d.get("name", f"display{i}"))
            if name in dnames:
                raise ConfigError(f"{w}.name: duplicate display name {name!r}")
            dnames.add(name)
            normal = _vec(f"{w}.normal", d.get("normal"))
            up = _vec(f"{w}.up", d.get("up"))
            if np.linalg.norm(np.cross(normal, up)) < 1e-6:
                raise ConfigError(f"{w}: 'up' must not be parallel to 'normal'")
            size = _vec(f"{w}.size_m", d.get("size_m"), 2)
            res = _vec(f"{w}.resolution", d.get("resolution"), 2)
            if np.any(size <= 0) or np.any(res < 1):
                raise ConfigError(f"{w}: size_m and resolution must be positive")
            displays.append(
                DisplaySpec(
                    name=name,
                    centre_m=_vec(f"{w}.centre_m", d.get("centre_m")),
                    normal=normal / np.linalg.norm(normal),
                    up=up,
                    size_m=(float(size[0]), float(size[1])),
                    resolution=(int(res[0]), int(res[1])),
                    rotates_with_table=bool(d.get("rotates_with_table", False)),
                    max_radiance=_num(w, d, "max_radiance", 1.0, positive=True),
                )
            )
        return cls(target_m=target, cameras=tuple(cams), lights=tuple(lights), displays=tuple(displays), raw=dict(g))

    def to_dict(self) -> dict:
        """The TOML-ready table this geometry was parsed from."""
        return dict(self.raw)

    # ---- queries
    def nominal_cameras(self) -> list[Camera]:
        """Cameras as designed, poses in the rig frame (table angle 0)."""
        return [c.nominal_camera(self.target_m) for c in self.cameras]

    def light(self, light_id: int) -> LightSpec:
        for L in self.lights:
            if L.id == light_id:
                return L
        raise ConfigError(f"light id {light_id} not in the rig (ids: {[L.id for L in self.lights]})")

    def display(self, name: str) -> DisplaySpec:
        for d in self.displays:
            if d.name == name:
                return d
        raise ConfigError(f"display {name!r} not in the rig (names: {[d.name for d in self.displays]})")

    @staticmethod
    def view_camera(rig_camera: Camera, table_deg: float, name: str | None = None) -> Camera:
        """View (c, a): the rig camera's pose expressed in the object frame at table angle a."""
        T = object_from_rig(table_deg) @ rig_camera.world_from_cam
        cam = rig_camera.with_pose(T)
        return cam.with_name(name) if name is not None else cam

    def light_direction_object(self, light_id: int, table_deg: float, array_deg: float) -> np.ndarray:
        """Unit direction from the object-frame origin towards the light."""
        p = self.light(light_id).position_rig(array_deg)
        p = object_from_rig(table_deg)[:3, :3] @ p
        return p / np.linalg.norm(p)

    def light_position_object(self, light_id: int, table_deg: float, array_deg: float) -> np.ndarray:
        p = self.light(light_id).position_rig(array_deg)
        return object_from_rig(table_deg)[:3, :3] @ p
