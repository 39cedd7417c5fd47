"""Analytic opacity hulls with exact ground truth, for tests and benchmarks.

A textured sphere seen by a turntable rig: every photograph, and every novel view, is
computed by ray-sphere intersection with s×s supersampling, so the expected image of
any camera is known exactly. Surfels lie on the sphere (Fibonacci lattice), with
outward normals, radii covering the surface, and visibility from the exact depth test
(a point of a sphere is seen from C iff (C − p)·n > 0). The sphere is its own visual
hull, so what the renderer adds — ULR blending across views, EWA resampling — is all
that the comparison measures.

Appearance: a smooth colour texture (longitude/latitude sines) lit by a fixed
directional light, plus an optional Blinn–Phong highlight that makes the radiance
view-dependent; with ``fuzzy=True`` the surface is semi-transparent, α(p) ∈ [0.2, 0.9],
which the opacity light field carries as alpha.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..model import Surfels, ViewInfo, write_model
from ..riggeometry import RigGeometry, view_id

__all__ = [
    "AnalyticSphere",
    "SyntheticModel",
    "make_sphere_model",
    "write_sphere_model",
    "fibonacci_sphere",
    "rig_dict",
]


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit vectors (golden-angle spiral)."""
    if n < 1:
        raise InputError(f"fibonacci_sphere: n = {n}, expected >= 1")
    i = np.arange(n) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)


@dataclass(frozen=True)
class AnalyticSphere:
    """The scene: a sphere with an analytic opacity light field."""

    centre: tuple = (0.0, 0.1, 0.0)
    radius: float = 0.08
    fuzzy: bool = False
    specular: float = 0.25
    shininess: float = 20.0
    light_dir: tuple = (0.4, 0.8, 0.45)
    texture_freq: float = 1.0

    def _local(self, p):
        q = (np.asarray(p, np.float64) - np.asarray(self.centre)) / self.radius
        lon = np.arctan2(q[..., 0], q[..., 2])
        lat = np.arcsin(np.clip(q[..., 1], -1, 1))
        return q, lon, lat

    def albedo(self, p) -> np.ndarray:
        _, lon, lat = self._local(p)
        f = self.texture_freq
        a = np.stack(
            [
                0.5 + 0.35 * np.sin(5 * f * lon) * np.cos(4 * f * lat),
                0.5 + 0.35 * np.sin(3 * f * lon + 1.0) * np.sin(5 * f * lat),
                0.5 + 0.35 * np.cos(4 * f * lon - 3 * f * lat),
            ],
            axis=-1,
        )
        return np.clip(a, 0.05, 0.95)

    def alpha(self, p) -> np.ndarray:
        if not self.fuzzy:
            return np.ones(np.shape(p)[:-1])
        _, lon, lat = self._local(p)
        return 0.55 + 0.35 * np.sin(4 * lon + 2 * lat)

    def radiance(self, p, view_from) -> np.ndarray:
        """Straight colour at surface points ``p`` seen from points ``view_from``."""
        q, _, _ = self._local(p)
        n = q / np.linalg.norm(q, axis=-1, keepdims=True)
        L = np.asarray(self.light_dir, np.float64)
        L = L / np.linalg.norm(L)
        c = self.albedo(p) * (0.35 + 0.65 * np.clip(n @ L, 0, None))[..., None]
        if self.specular:
            V = np.asarray(view_from, np.float64) - np.asarray(p, np.float64)
            V = V / np.linalg.norm(V, axis=-1, keepdims=True)
            Hh = V + L
            Hh = Hh / np.linalg.norm(Hh, axis=-1, keepdims=True)
            c = c + self.specular * np.clip(np.sum(n * Hh, axis=-1), 0, None)[..., None] ** self.shininess
        return c

    def hit(self, origin, dirs):
        """Front intersection distance along unit ``dirs`` (…, 3) from ``origin`` (3,); nan on a miss."""
        oc = np.asarray(origin, np.float64) - np.asarray(self.centre)
        b = dirs @ oc
        c = oc @ oc - self.radius**2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        return np.where((disc >= 0) & (t > 0), t, np.nan)

    def render(self, camera: Camera, *, supersample: int = 3) -> np.ndarray:
        """Exact (supersampled) straight RGBA (H, W, 4) of the scene seen by ``camera``."""
        s = int(supersample)
        H, W = camera.height, camera.width
        offs = (np.arange(s) + 0.5) / s - 0.5
        ox, oy = np.meshgrid(offs, offs)
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        uu = (u[..., None] + ox.ravel()).reshape(-1)
        vv = (v[..., None] + oy.ravel()).reshape(-1)
        o, d = camera.pixel_rays(np.stack([uu, vv], axis=1))
        t = self.hit(o, d)
        ok = np.isfinite(t)
        p = o + d[ok] * t[ok, None]
        a = np.zeros(len(t))
        col = np.zeros((len(t), 3))
        a[ok] = self.alpha(p)
        col[ok] = self.radiance(p, np.broadcast_to(o, p.shape)) * a[ok, None]
        a = a.reshape(H, W, s * s).mean(axis=2)
        col = col.reshape(H, W, s * s, 3).mean(axis=2)
        out = np.zeros((H, W, 4), np.float32)
        has = a > 0
        out[..., :3] = np.where(has[..., None], col / np.where(has, a, 1)[..., None], 0)
        out[..., 3] = a
        return out


def rig_dict(
    *, elevations_deg=(5.0, 35.0, 65.0), distance_m=0.5, target=(0.0, 0.1, 0.0), width=96, height=72, fov_y_deg=30.0
) -> dict:
    """A rig geometry table (riggeometry schema) with one camera per elevation."""
    return {
        "target_m": list(map(float, target)),
        "cameras": [
            {
                "name": f"cam{i}",
                "width": int(width),
                "height": int(height),
                "distance_m": float(distance_m),
                "elevation_deg": float(e),
                "azimuth_deg": 0.0,
                "fov_y_deg": float(fov_y_deg),
            }
            for i, e in enumerate(elevations_deg)
        ],
    }


@dataclass
class SyntheticModel:
    """An analytic model in memory: what :func:`opacityhull.model.write_model` takes, plus the scene."""

    scene: AnalyticSphere
    views: list
    surfels: Surfels
    view_rgba: list
    rig: dict
    provenance: dict = field(default_factory=dict)

    @property
    def cameras(self) -> list:
        return [v.camera for v in self.views]

    def views_premul(self) -> list:
        out = []
        for a in self.view_rgba:
            b = a.copy()
            b[..., :3] *= b[..., 3:4]
            out.append(b)
        return out


def make_sphere_model(
    n_surfels: int = 20000,
    *,
    width: int = 96,
    height: int = 72,
    table_step_deg: float = 30.0,
    elevations_deg: Sequence[float] = (5.0, 35.0, 65.0),
    distance_m: float = 0.5,
    fov_y_deg: float = 30.0,
    fuzzy: bool = False,
    specular: float = 0.25,
    supersample: int = 3,
    radius_factor: float = 0.8,
    texture_freq: float = 1.0,
    distortion: Sequence[float] | None = None,
) -> SyntheticModel:
    """Analytic sphere model: turntable views (every ``table_step_deg``, one camera per
    elevation), exact photographs, Fibonacci surfels with radius
    ``radius_factor · √(area per surfel)`` (0.62 would just cover a hexagonal lattice)."""
    scene = AnalyticSphere(fuzzy=fuzzy, specular=specular, texture_freq=texture_freq)
    rig = rig_dict(
        elevations_deg=elevations_deg,
        distance_m=distance_m,
        target=scene.centre,
        width=width,
        height=height,
        fov_y_deg=fov_y_deg,
    )
    geo = RigGeometry.from_dict(rig)
    rig_cams = geo.nominal_cameras()
    if distortion is not None:
        rig_cams = [
            Camera(
                K=c.K,
                width=c.width,
                height=c.height,
                world_from_cam=c.world_from_cam,
                dist=np.asarray(distortion, float),
                name=c.name,
            )
            for c in rig_cams
        ]
    views = []
    n_steps = int(round(360.0 / table_step_deg))
    for t in range(n_steps):
        a = t * table_step_deg
        for ci, rc in enumerate(rig_cams):
            vid = view_id(ci, a)
            views.append(ViewInfo(len(views), vid, ci, float(a), RigGeometry.view_camera(rc, a, name=vid)))
    imgs = [scene.render(v.camera, supersample=supersample) for v in views]
    dirs = fibonacci_sphere(n_surfels)
    pos = np.asarray(scene.centre) + scene.radius * dirs
    area = 4 * math.pi * scene.radius**2 / n_surfels
    radii = np.full(n_surfels, radius_factor * math.sqrt(area))
    vis = np.zeros((n_surfels, len(views)), bool)
    for v in views:
        cam = v.camera
        facing = ((cam.centre_world - pos) * dirs).sum(axis=1) > 0
        uv, z = cam.project(pos)
        vis[:, v.index] = facing & (z > 0) & cam.in_image(uv)
    surfels = Surfels.from_bool(pos, dirs, radii, vis)
    prov = {
        "synthetic": "analytic sphere",
        "n_surfels": n_surfels,
        "fuzzy": fuzzy,
        "specular": specular,
        "supersample": supersample,
    }
    return SyntheticModel(scene, views, surfels, imgs, rig, prov)


def write_sphere_model(root, **kwargs) -> tuple[Path, SyntheticModel]:
    """Write :func:`make_sphere_model` as a model folder; returns (path, the in-memory model)."""
    m = make_sphere_model(**kwargs)
    path = write_model(
        root, views=m.views, surfels=m.surfels, view_rgba=m.view_rgba, rig=m.rig, provenance=m.provenance
    )
    return path, m
