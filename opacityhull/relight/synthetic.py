"""An analytic relighting test object: a Lambertian sphere on the rig, written as a
model folder with exact one-light-at-a-time images and an exact relit ground truth.

Used by the tests and ``benchmarks/relight.py`` where no simulated model is needed:
the sphere is convex (no shadows, no interreflection) and lit by ideal directional
lights of the calibrated irradiance, so the only error left in relighting is the
filtering of the environment onto the K captured directions — which is what the
number-of-lights and kernel sweeps measure.

Every pixel is supersampled (``ss × ss`` rays), so alpha is the sphere's coverage
and the one-light images are premultiplied exactly as a camera over a black backdrop
sees them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..model import LightSample, Surfels, ViewInfo, light_key, write_model
from ..riggeometry import RigGeometry, view_id
from ..envmap import EnvironmentMap, latlong_directions, latlong_solid_angles

__all__ = ["SphereScene", "paper_light_rig", "sphere_rig", "write_sphere_model", "sphere_hits", "sphere_groundtruth"]


@dataclass(frozen=True)
class SphereScene:
    """A textured Lambertian sphere (object frame)."""

    centre_m: tuple[float, float, float] = (0.0, 0.1, 0.0)
    radius_m: float = 0.08
    albedo_rgb: tuple[float, float, float] = (0.75, 0.55, 0.35)
    #: albedo is modulated by 1 + texture · cos(3 φ) of the normal's azimuth φ, so that
    #: the relit images are not rotationally symmetric (a table-angle bug shows)
    texture: float = 0.3

    def albedo(self, normals: np.ndarray) -> np.ndarray:
        phi = np.arctan2(normals[..., 0], normals[..., 2])
        m = 1.0 + self.texture * np.cos(3 * phi)
        return m[..., None] * np.asarray(self.albedo_rgb)


def paper_light_rig(
    n_lights: int = 4,
    n_positions: int = 15,
    *,
    elevations_deg: Sequence[float] | None = None,
    distance_m: float = 1.2,
    intensities: Sequence[float] | None = None,
    colours: Sequence[Sequence[float]] | None = None,
) -> tuple[list[dict], list[float]]:
    """Light table entries of an overhead array of ``n_lights`` on an arc and the
    ``n_positions`` array angles (the paper: 4 × 15, 24° apart)."""
    if elevations_deg is None:
        # spread over the upper hemisphere, equal steps between the horizon and the zenith
        elevations_deg = [90.0 * (j + 0.5) / n_lights for j in range(n_lights)]
    lights = []
    for j, el in enumerate(elevations_deg):
        lights.append(
            {
                "id": j,
                "elevation_deg": float(el),
                "azimuth_deg": 0.0 if j % 2 == 0 else 180.0 / max(1, n_positions),  # stagger rings
                "distance_m": distance_m,
                "intensity": float(intensities[j]) if intensities is not None else 1.0,
                "colour": list(colours[j]) if colours is not None else [1.0, 1.0, 1.0],
            }
        )
    positions = [360.0 * p / n_positions for p in range(n_positions)]
    return lights, positions


def sphere_rig(
    *,
    width: int = 48,
    height: int = 40,
    n_lights: int = 4,
    n_positions: int = 15,
    camera_elevations_deg: Sequence[float] = (10.0, 40.0),
    calibrated: bool = True,
    light_elevations_deg: Sequence[float] | None = None,
) -> tuple[dict, list[float]]:
    """Rig table (riggeometry schema) and array angles for the sphere model."""
    intens = colours = None
    if calibrated:
        # lights of unequal output and tint: relighting must divide them out
        intens = [0.8 + 0.15 * j for j in range(n_lights)]
        colours = [[1.0, 0.9 + 0.03 * j, 0.8 + 0.05 * j] for j in range(n_lights)]
    lights, positions = paper_light_rig(
        n_lights, n_positions, elevations_deg=light_elevations_deg, intensities=intens, colours=colours
    )
    cams = [
        {
            "name": f"cam{i}",
            "width": width,
            "height": height,
            "distance_m": 0.6,
            "elevation_deg": float(e),
            "azimuth_deg": 0.0,
            "fov_y_deg": 25.0,
        }
        for i, e in enumerate(camera_elevations_deg)
    ]
    return {"target_m": [0.0, 0.1, 0.0], "cameras": cams, "lights": lights}, positions


def sphere_hits(cam: Camera, scene: SphereScene, *, ss: int = 2):
    """Ray–sphere hits of ``ss × ss`` sub-pixel rays: (H, W, ss², 3) normals (NaN on a
    miss) and (H, W, ss²) hit mask."""
    c = np.asarray(scene.centre_m, float)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    normals, hits = [], []
    for oy in offs:
        for ox in offs:
            v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
            uv = np.stack([u.ravel() + ox, v.ravel() + oy], 1)
            o, d = cam.pixel_rays(uv)
            oc = o - c
            b = d @ oc
            disc = b * b - (oc @ oc - scene.radius_m**2)
            hit = disc > 0
            t = -b - np.sqrt(np.where(hit, disc, 0))
            x = o + t[:, None] * d
            n = (x - c) / scene.radius_m
            n[~hit] = np.nan
            normals.append(n.reshape(cam.height, cam.width, 3))
            hits.append(hit.reshape(cam.height, cam.width))
    return np.stack(normals, 2), np.stack(hits, 2)


def _one_light_images(normals, hits, albedo, dirs, irr) -> np.ndarray:
    """(K, H, W, 3): mean over sub-pixels of ρ/π max(0, n·d_k) E_k (0 on a miss)."""
    n = np.nan_to_num(normals)
    cos = np.clip(np.einsum("hwsc,kc->khws", n, dirs), 0, None) * hits[None]
    return np.einsum("khws,hwsc,kc->khwc", cos, albedo / math.pi, irr).astype(np.float32) / hits.shape[2]


def write_sphere_model(
    root,
    *,
    scene: SphereScene = SphereScene(),
    width: int = 48,
    height: int = 40,
    n_lights: int = 4,
    n_positions: int = 15,
    table_degs: Sequence[float] = (0.0, 90.0, 180.0, 270.0),
    camera_elevations_deg: Sequence[float] = (10.0, 40.0),
    ss: int = 2,
    calibrated: bool = True,
    light_elevations_deg: Sequence[float] | None = None,
    n_surfels: int = 4000,
    drop_light: tuple[int, str] | None = None,
) -> Path:
    """Write the sphere as a model folder (views, surfels, reflectance, rig).

    ``drop_light = (view index, key)`` leaves that one-light image out of that view's
    reflectance file (the missing-data hard case).
    """
    rig, positions = sphere_rig(
        width=width,
        height=height,
        n_lights=n_lights,
        n_positions=n_positions,
        camera_elevations_deg=camera_elevations_deg,
        calibrated=calibrated,
        light_elevations_deg=light_elevations_deg,
    )
    geom = RigGeometry.from_dict(rig)
    rig_cams = geom.nominal_cameras()
    views = []
    for a in table_degs:
        for ci, rc in enumerate(rig_cams):
            vid = view_id(ci, a)
            views.append(ViewInfo(len(views), vid, ci, float(a), geom.view_camera(rc, a, name=vid)))
    samples = [LightSample(light_key(L.id, b), L.id, b) for b in positions for L in geom.lights]
    hits_cache = {}
    rgba = []
    for v in views:
        n, h = sphere_hits(v.camera, scene, ss=ss)
        hits_cache[v.index] = (n, h)
        cov = h.mean(axis=2)
        alb = scene.albedo(np.nan_to_num(n))
        # straight colour under a uniform white sky of radiance 1: ρ (1 + n_y) / 2 would
        # be exact for a hemisphere; any plausible colour will do for the light field
        shade = (alb * ((1 + np.nan_to_num(n[..., 1:2])) / 2) * h[..., None]).sum(2)
        col = np.where(cov[..., None] > 0, shade / np.maximum(h.sum(2), 1)[..., None], 0)
        rgba.append(np.concatenate([col, cov[..., None]], -1).astype(np.float32))
    # surfels: Fibonacci points on the sphere, visible where front-facing
    i = np.arange(n_surfels) + 0.5
    y = 1 - 2 * i / n_surfels
    r = np.sqrt(1 - y * y)
    ph = math.pi * (1 + 5**0.5) * i
    nrm = np.stack([r * np.cos(ph), y, r * np.sin(ph)], 1)
    pos = np.asarray(scene.centre_m) + scene.radius_m * nrm
    vis = np.stack([((v.camera.centre_world - pos) * nrm).sum(1) > 0 for v in views], 1)
    rad = np.full(n_surfels, scene.radius_m * math.sqrt(4.0 / n_surfels) * 1.2)
    surfels = Surfels.from_bool(pos, nrm, rad, vis)

    def images(vi):
        n, h = hits_cache[vi]
        dirs = np.array([geom.light_direction_object(s.light_id, views[vi].table_deg, s.array_deg) for s in samples])
        irr = np.array([geom.light(s.light_id).intensity * np.asarray(geom.light(s.light_id).colour) for s in samples])
        olat = _one_light_images(n, h, scene.albedo(np.nan_to_num(n)), dirs, irr)
        return {s.key: olat[k] for k, s in enumerate(samples)}

    root = Path(root)
    prov = {
        "generator": "opacityhull.relight.synthetic.write_sphere_model",
        "scene": "analytic:lambertian-sphere",
        "light_model": "directional",
        "sphere": {
            "centre_m": list(scene.centre_m),
            "radius_m": scene.radius_m,
            "albedo_rgb": list(scene.albedo_rgb),
            "texture": scene.texture,
        },
    }
    write_model(
        root,
        views=views,
        surfels=surfels,
        view_rgba=rgba,
        rig=rig,
        provenance=prov,
        reflectance={"lights": samples, "images": images},
    )
    if drop_light is not None:
        # the file exists but one sample is stored under another name, as a capture
        # that lost one image would leave it
        from ..imageio import read_exr_layers, write_exr_layers

        vi, key = drop_light
        p = root / "reflectance" / f"{views[vi].id}.exr"
        layers = read_exr_layers(p)
        layers[f"{key}x"] = layers.pop(key)
        write_exr_layers(p, layers)
    return root


def sphere_groundtruth(
    cam: Camera, scene: SphereScene, env: EnvironmentMap, *, ss: int = 2, upper_only: bool = True, chunk: int = 4096
) -> np.ndarray:
    """Exact premultiplied relit image of the sphere under ``env`` (H, W, 3) float32:
    mean over sub-pixel rays of ρ/π Σ_j max(0, n·ω_j) L_j Δω_j over the map's texels
    (the upper hemisphere only when ``upper_only``, matching a table that blocks light
    from below)."""
    n, h = sphere_hits(cam, scene, ss=ss)
    H, W = env.height, env.width
    dirs = latlong_directions(H, W).reshape(-1, 3)
    sa = np.broadcast_to(latlong_solid_angles(H, W)[:, None], (H, W)).reshape(-1)
    power = env.radiance.reshape(-1, 3).astype(np.float64) * sa[:, None]
    if upper_only:
        power = power * (dirs[:, 1] > 0)[:, None]
    keep = np.any(power > 0, axis=1)
    dirs, power = dirs[keep], power[keep]
    nh = n[h]  # only rays that hit the sphere
    irr = np.zeros((nh.shape[0], 3))
    for s in range(0, len(dirs), chunk):
        irr += np.clip(nh @ dirs[s : s + chunk].T, 0, None) @ power[s : s + chunk]
    rad = np.zeros(n.shape)
    rad[h] = scene.albedo(nh) / math.pi * irr
    return (rad.sum(2) / h.shape[2]).astype(np.float32)
