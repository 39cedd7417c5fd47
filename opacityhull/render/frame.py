"""What both shading drivers of :func:`~opacityhull.render.renderer.render_image` share:
the frame they return (:class:`RenderResult`), the splat records of a frame
(:func:`setup_splats`), the EWA coverage (:func:`coverage_full`, :func:`coverage_from`,
:func:`normalise`), the surfels' areas, a distorted camera's pinhole canvas and remap,
and the stage timings. The per-surfel driver is ``renderer.render_image``; the per-pixel
one is :func:`opacityhull.render.deferred.render_deferred`."""

from __future__ import annotations

import math
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..imageio import ALPHA_CUTOFF, straight_from_premul
from ..model import Surfels
from . import kernels as K
from .background import composite_over, resolve_background
from .config import RenderConfig

__all__ = [
    "ALPHA_MIN",
    "RenderResult",
    "coverage_full",
    "coverage_from",
    "normalise",
    "setup_splats",
    "surfel_areas",
]

ALPHA_MIN = ALPHA_CUTOFF  # the project's one straight-colour cut-off (imageio)
"""Below this alpha a pixel's straight colour is reported as 0 (premultiplied colour / α
is meaningless there)."""


@dataclass
class RenderResult:
    """A rendered frame.

    Attributes
    ----------
    rgba : (H, W, 4) float32, straight alpha (colour 0 where α < ALPHA_MIN).
    depth : (H, W) float32, weighted mean z (metres along the optical axis) of the blended
        fragments; +inf where nothing was drawn.
    weight : (H, W) float32, Σ of the EWA kernel weights (0 where nothing was drawn).
    coverage : (H, W) float32 in [0, 1], geometric coverage of each pixel's filter footprint
        by the splatted surface (1 everywhere drawn when ``config.edge_coverage`` is off).
    camera : the camera rendered.
    config : the options used.
    stats : counts (surfels, splats drawn, ...) and timings in ms.
    """

    rgba: np.ndarray
    depth: np.ndarray
    weight: np.ndarray
    coverage: np.ndarray
    camera: Camera
    config: RenderConfig = field(default_factory=RenderConfig)
    stats: dict = field(default_factory=dict)

    @property
    def premul(self) -> np.ndarray:
        """(H, W, 4) premultiplied RGBA."""
        out = self.rgba.copy()
        out[..., :3] *= out[..., 3:4]
        return out

    @property
    def alpha(self) -> np.ndarray:
        return self.rgba[..., 3]

    def over(self, background=None) -> np.ndarray:
        """Composite over a background: None (``config.background``, else black), a
        colour (number or RGB triple), an (H, W, 3|4) image, or an :class:`~opacityhull.envmap.EnvironmentMap`
        (looked up along this camera's pixel rays). Returns (H, W, 3) float32 linear."""
        bg = self.config.background if background is None else background
        return composite_over(self.rgba, resolve_background(bg, self.camera))


def _pinhole_for(camera: Camera) -> tuple[Camera, np.ndarray | None]:
    """A distortion-free camera covering ``camera``'s field of view, and the remap grid
    (H, W, 2) from the distorted image to it (None when there is no distortion)."""
    if not camera.has_distortion:
        return camera, None
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    xyd = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    xy = camera.undistort_normalized(xyd)
    pu = camera.fx * xy[:, 0] + camera.cx
    pv = camera.fy * xy[:, 1] + camera.cy
    # a canvas covering every undistorted pixel, at most twice the image each way
    lo_u = max(np.floor(np.nanmin(pu)) - 1, -camera.width / 2)
    hi_u = min(np.ceil(np.nanmax(pu)) + 1, 1.5 * camera.width)
    lo_v = max(np.floor(np.nanmin(pv)) - 1, -camera.height / 2)
    hi_v = min(np.ceil(np.nanmax(pv)) + 1, 1.5 * camera.height)
    lo_u, lo_v = min(lo_u, 0.0), min(lo_v, 0.0)
    hi_u, hi_v = max(hi_u, camera.width - 1.0), max(hi_v, camera.height - 1.0)
    Kp = camera.K.copy()
    Kp[0, 2] -= lo_u
    Kp[1, 2] -= lo_v
    pin = Camera(
        K=Kp,
        width=int(hi_u - lo_u) + 1,
        height=int(hi_v - lo_v) + 1,
        world_from_cam=camera.world_from_cam,
        name=camera.name,
    )
    grid = np.stack([pu - lo_u, pv - lo_v], axis=1).reshape(camera.height, camera.width, 2).astype(np.float32)
    return pin, grid


def _remap(img: np.ndarray, grid: np.ndarray, *, nearest: bool = False, border=0.0) -> np.ndarray:
    import cv2

    return cv2.remap(
        img,
        grid[..., 0],
        grid[..., 1],
        cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border,
    )


def _remap_buffers(premul, wsum, cov, depth, grid):
    """The rendered buffers resampled through the distortion ``grid``; depth by nearest
    neighbour (blending depths across a silhouette would invent surfaces), inf outside."""
    return (
        _remap(premul, grid),
        _remap(np.ascontiguousarray(wsum), grid),
        _remap(cov, grid),
        _remap(depth, grid, nearest=True, border=float("inf")),
    )


def _stage_end(progress, done: int) -> float:
    """The ``perf_counter`` time a render stage ended, after reporting ``done`` of the 3 stages to ``progress``."""
    t = time.perf_counter()
    if progress:
        progress(done, 3)
    return t


def _stage_ms(t0: float, **ends: float) -> dict:
    """Milliseconds per stage from the ``perf_counter`` time each stage ended (in order), and the total."""
    ms, prev = {}, t0
    for stage, t in ends.items():
        ms[stage], prev = 1e3 * (t - prev), t
    ms["total"] = 1e3 * (prev - t0)
    return ms


def _view_stats(camera, config, threads, exclude_views, pv, valid, draw) -> dict:
    """The stats entries both shading modes report alike."""
    return {
        "splats_setup": int(valid.sum()),
        "splats_drawn": int(draw.size),
        "width": camera.width,
        "height": camera.height,
        "k": int(config.k),
        "threads": threads,
        "excluded_views": [int(v) for v in exclude_views],
        "nonfinite_texels": pv.nonfinite_texels,
    }


def setup_splats(
    surfels, positions, areas, cam_row, W, H, config: RenderConfig, threads, splat, valid, cov6=None
) -> None:
    """Splat records of ``surfels`` centred at ``positions`` (the hull's, or the shading
    depth's displaced ones) for the frame ``cam_row`` (W×H), in parallel; ``cov6``:
    anisotropic radius tensors (:func:`render_image`)."""
    K.parallel_for(
        K.splat_setup,
        len(surfels),
        (
            positions,
            surfels.normals,
            surfels.radii,
            areas,
            cam_row,
            W,
            H,
            float(config.sigma_radius),
            float(config.filter),
            float(config.cutoff_sigma),
            float(config.epsilon_z),
            bool(config.backface_cull),
            K.NO_COV if cov6 is None else cov6,
            splat,
            valid,
        ),
        threads=threads,
    )


def coverage_full(config: RenderConfig) -> float:
    """The area-weighted kernel sum Σw·A that counts as full coverage: inside a surface
    Σw·A ≈ the Gaussian's mass within the cutoff, ``1 − exp(−c²/2)``, times
    ``coverage_threshold``."""
    return config.coverage_threshold * (1.0 - math.exp(-0.5 * config.cutoff_sigma**2))


def coverage_from(area_sum: np.ndarray, wsum: np.ndarray, config: RenderConfig) -> np.ndarray:
    """Pixel coverage in [0, 1] from the area-weighted kernel sum Σw·A: Σw·A over
    :func:`coverage_full`, clipped to [0, 1] (0 where nothing was drawn). NumPy reference
    of the coverage part of :func:`~opacityhull.render.kernels.resolve`."""
    if not config.edge_coverage:
        return (wsum > 0).astype(np.float32)
    cov = np.clip(area_sum / coverage_full(config), 0.0, 1.0).astype(np.float32)
    return np.where(wsum > 0, cov, np.float32(0.0)).astype(np.float32)


def normalise(
    acc: np.ndarray, wsum: np.ndarray, zsum: np.ndarray, coverage: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """EWA normalisation (NumPy reference of :func:`~opacityhull.render.kernels.resolve`):
    premultiplied RGBA Σw·c / Σw (times ``coverage`` when given) → straight RGBA; depth
    Σw·z / Σw (inf where Σw = 0) — the depth is not scaled by the coverage."""
    has = wsum > 0
    inv = np.where(has, 1.0 / np.where(has, wsum, 1.0), 0.0).astype(np.float32)
    depth = np.where(has, zsum * inv, np.inf).astype(np.float32)
    if coverage is not None:
        inv = inv * coverage
    premul = acc * inv[..., None]
    return straight_from_premul(premul), depth


_AREA_CACHE: dict = {}


def surfel_areas(surfels: Surfels, *, neighbours: int = 12) -> np.ndarray:
    """(N,) float32 surface area represented by each surfel (m²), for edge coverage.

    From the k nearest neighbours (SciPy KDTree): the j-th neighbour at distance r_j
    means about j surfels per π r_j², so A ≈ mean over j of π r_j² / j; the estimate is
    then averaged over each surfel's neighbourhood, which removes the banding a regular
    lattice gives single-k estimates. Cached per Surfels object (a model is opened once,
    rendered many times).
    """

    key = id(surfels)
    hit = _AREA_CACHE.get(key)
    if hit is not None and hit[0]() is surfels and hit[1].shape[0] == len(surfels):
        return hit[1]
    from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

    N = len(surfels)
    P = np.asarray(surfels.positions, dtype=np.float64)
    fin = np.all(np.isfinite(P), axis=1)
    areas = np.zeros(N, np.float32)
    n_ok = int(fin.sum())
    if n_ok >= 2:
        k = min(neighbours, n_ok - 1)
        tree = KDTree(P[fin])
        d, nb = tree.query(P[fin], k=k + 1)
        j = np.arange(1, k + 1)
        a = np.pi * np.mean(d[:, 1:] ** 2 / j, axis=1)
        a = np.mean(a[nb], axis=1)
        areas[fin] = a
    elif n_ok == 1:
        r = np.asarray(surfels.radii, np.float64)[fin]
        areas[fin] = np.pi * r**2
    ref = weakref.ref(surfels, lambda _r, key=key: _AREA_CACHE.pop(key, None))
    _AREA_CACHE[key] = (ref, areas)
    return areas


def seed_surfel_areas(surfels, areas) -> None:
    """Hand :func:`surfel_areas` (so ``render_image``) these areas for ``surfels``
    instead of its k-nearest-neighbour estimate: an LOD cut's summed subtree areas (the
    estimate costs more than the render of a cut: 120 ms for 15 k nodes), or the full
    model's areas for the splat part of a hybrid frame. The entry lives as long as
    ``surfels``."""
    key = id(surfels)
    ref = weakref.ref(surfels, lambda _r, key=key: _AREA_CACHE.pop(key, None))
    _AREA_CACHE[key] = (ref, np.ascontiguousarray(areas, dtype=np.float32))
