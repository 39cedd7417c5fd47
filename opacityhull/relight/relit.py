"""Relit views: each captured view under new light as a weighted sum of its
one-light-at-a-time images ("Relighting – 1st step" of Pfister's talk).

For view i with one-light images O_k (premultiplied radiance, observed over black
backdrops) and calibrated weights w_k (:mod:`.basis`),

    relit_i = Σ_k w_k ⊙ O_k          (per RGB channel),   alpha_i = matte of view i,

which is a (pixels × K) · (K) product per channel — memory-bound, done by a numba
kernel with a loop-over-lights reference (:func:`relight_stack_reference`). The relit
views (premultiplied RGB + matte alpha) go to the ULR surfel renderer unchanged
("2nd step").

Near-light correction (``near_light=True``, the default): the array's lights are points
at ~1 m, not directions, so a one-light image records irradiance I_k / |p_k − x|² at
the surface point x instead of the calibrated I_k / |p_k|² at the rig origin — the top
of a 15 cm object is ~35 % brighter under an overhead light than its foot. Given the
surface point behind each pixel (the hull's depth in that view), the kernel scales each
sample by |p_k − x|² / |p_k|² (clamped to [1/4, 4] against a wild hull point), turning
it into the response to a directional light of the calibrated irradiance — what an
environment map at infinity delivers. On the simulated cup this halves the relighting
error (grace: 39 % → 20 % with 24 lights). Models whose provenance says their
one-light images were made with ideal directional lights (``light_model =
"directional"``, the analytic test sphere) are not corrected.

Compression: :func:`compress_reflectance` keeps a rank-r truncated SVD of the view's
(3·pixels × K) reflectance matrix ("PCA per view", uncentred: the optimal rank-r
approximation in the Frobenius norm, and linear relighting needs no mean); relighting
then costs r instead of K multiply-adds per pixel and the data shrink by ≈ K / r.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import FormatError, InputError, ShapeError
from ..reflectance_pca import CompressedReflectance, compress_reflectance, compress_reflectance_reference
from .basis import (
    KernelConfig,
    LightSet,
    directional_light_weights,
    integrate_envmap,
    light_set_from_model,
    prepare_envmap,
)
from ..envmap import EnvironmentMap

__all__ = [
    "RelightConfig",
    "relight_stack",
    "relight_stack_reference",
    "CompressedReflectance",
    "compress_reflectance",
    "compress_reflectance_reference",
    "Relighter",
    "view_surface_points",
    "directional_lights",
]


# --------------------------------------------------------------------------- kernels


#: pixels per block of the relighting kernels (one block: one task of the parallel loop)
_BLOCK_PIXELS = 4096


def _kernels():
    """(serial, parallel) compiled kernels. Blocks of 4096 pixels keep the float64
    accumulator in L2 while the K one-light images stream through once; the
    near-light and plain loops are separate so the plain one vectorises."""
    from numba import njit, prange

    @njit(cache=True, fastmath=False)
    def block(stack, weights, points, light_pos, b, out):  # pragma: no cover - compiled
        P = stack.shape[1]
        near = points.shape[0] == P  # a point per pixel: near lights (else directional)
        p0 = b * _BLOCK_PIXELS
        p1 = min(P, p0 + _BLOCK_PIXELS)
        K = stack.shape[0]
        M = weights.shape[0]
        acc = np.zeros((M, p1 - p0, 3))
        f = np.ones(p1 - p0)
        for k in range(K):
            if near:
                lx, ly, lz = light_pos[k, 0], light_pos[k, 1], light_pos[k, 2]
                l2 = lx * lx + ly * ly + lz * lz
                for p in range(p0, p1):
                    x = points[p, 0]
                    if x == x:  # NaN: no surface behind this pixel, factor 1
                        dx = lx - x
                        dy = ly - points[p, 1]
                        dz = lz - points[p, 2]
                        f[p - p0] = min(4.0, max(0.25, (dx * dx + dy * dy + dz * dz) / l2))
            for m in range(M):
                w0, w1, w2 = weights[m, k, 0], weights[m, k, 1], weights[m, k, 2]
                if w0 == 0.0 and w1 == 0.0 and w2 == 0.0:
                    continue
                if near:
                    for p in range(p0, p1):
                        q = p - p0
                        acc[m, q, 0] += w0 * f[q] * stack[k, p, 0]
                        acc[m, q, 1] += w1 * f[q] * stack[k, p, 1]
                        acc[m, q, 2] += w2 * f[q] * stack[k, p, 2]
                else:
                    for p in range(p0, p1):
                        q = p - p0
                        acc[m, q, 0] += w0 * stack[k, p, 0]
                        acc[m, q, 1] += w1 * stack[k, p, 1]
                        acc[m, q, 2] += w2 * stack[k, p, 2]
        for m in range(M):
            for q in range(p1 - p0):
                out[m, p0 + q, 0] = acc[m, q, 0]
                out[m, p0 + q, 1] = acc[m, q, 1]
                out[m, p0 + q, 2] = acc[m, q, 2]

    @njit(cache=True)
    def serial(stack, weights, points, light_pos, out):  # pragma: no cover - compiled
        for b in range((stack.shape[1] + _BLOCK_PIXELS - 1) // _BLOCK_PIXELS):
            block(stack, weights, points, light_pos, b, out)

    @njit(cache=True, parallel=True)
    def parallel(stack, weights, points, light_pos, out):  # pragma: no cover - compiled
        for b in prange((stack.shape[1] + _BLOCK_PIXELS - 1) // _BLOCK_PIXELS):
            block(stack, weights, points, light_pos, b, out)

    return serial, parallel


_KERNELS = None
#: below this many pixel-lights the thread start-up costs more than it saves
PARALLEL_MIN_WORK = 1 << 21


def _get_kernel(work: int):
    global _KERNELS
    if _KERNELS is None:
        _KERNELS = _kernels()
    return _KERNELS[1] if work >= PARALLEL_MIN_WORK else _KERNELS[0]


def _check_stack(stack, weights):
    s = np.asarray(stack)
    if s.ndim != 4 or s.shape[3] != 3:
        raise ShapeError(f"reflectance stack has shape {s.shape}, expected (K, H, W, 3)")
    w = np.asarray(weights, np.float64)
    single = w.ndim == 2
    if single:
        w = w[None]
    if w.ndim != 3 or w.shape[1:] != (s.shape[0], 3):
        raise ShapeError(f"weights have shape {np.shape(weights)}, expected ({s.shape[0]}, 3) or (M, {s.shape[0]}, 3)")
    if not np.all(np.isfinite(w)):
        raise InputError("relighting weights contain NaN or Inf")
    return s, w, single


def relight_stack(stack, weights, *, points=None, light_positions=None) -> np.ndarray:
    """Σ_k weights[k] ⊙ stack[k] per channel (the relit image), numba.

    Parameters
    ----------
    stack : (K, H, W, 3) float32 one-light images (premultiplied radiance).
    weights : (K, 3) or (M, K, 3) float64 calibrated weights (M lightings at once).
    points : (H, W, 3) surface point behind each pixel (object frame, metres; NaN
        where there is none) for the near-light correction, with ``light_positions``
        (K, 3) the lights' positions in the same frame. Both or neither.

    Returns
    -------
    (H, W, 3) float32, or (M, H, W, 3) for (M, K, 3) weights. Accumulates in float64.
    """
    s, w, single = _check_stack(stack, weights)
    K, H, W, _ = s.shape
    flat = np.ascontiguousarray(s, dtype=np.float32).reshape(K, H * W, 3)
    if (points is None) != (light_positions is None):
        raise InputError("near-light correction needs both points and light_positions")
    if points is not None:
        pts = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        if pts.shape[0] != H * W:
            raise ShapeError(f"points have shape {np.shape(points)}, expected ({H}, {W}, 3)")
        lp = np.ascontiguousarray(light_positions, np.float64)
        if lp.shape != (K, 3):
            raise ShapeError(f"light_positions have shape {lp.shape}, expected ({K}, 3)")
    else:
        pts = np.zeros((0, 3))
        lp = np.ones((K, 3))
    out = np.empty((w.shape[0], H * W, 3), np.float32)
    _get_kernel(K * H * W * w.shape[0])(flat, np.ascontiguousarray(w), pts, lp, out)
    out = out.reshape(w.shape[0], H, W, 3)
    return out[0] if single else out


def relight_stack_reference(stack, weights, *, points=None, light_positions=None) -> np.ndarray:
    """Loop-over-lights NumPy version of :func:`relight_stack` (the test oracle)."""
    s, w, single = _check_stack(stack, weights)
    s = np.asarray(s, np.float64)
    out = np.zeros((w.shape[0],) + s.shape[1:])
    for m in range(w.shape[0]):
        for k in range(s.shape[0]):
            img = s[k] * w[m, k]
            if points is not None:
                pts = np.asarray(points, np.float64)
                p = np.asarray(light_positions, np.float64)[k]
                f = np.clip(np.sum((p - pts) ** 2, axis=-1) / np.sum(p**2), 0.25, 4.0)
                f = np.where(np.isnan(f), 1.0, f)
                img = img * f[..., None]
            out[m] += img
    out = out.astype(np.float32)
    return out[0] if single else out


# --------------------------------------------------------------------------- model


@dataclass(frozen=True, kw_only=True)
class RelightConfig:
    """Options of model relighting.

    Attributes
    ----------
    kernel : how lighting is filtered onto the captured lights (:class:`KernelConfig`).
    near_light : scale each one-light sample by |p_k − x|² / |p_k|² using the hull's
        depth (see the module docstring); ignored for models with directional lights.
    pca_rank : relight from a rank-r compression of each view's data (None: exact).
    """

    kernel: KernelConfig = field(default_factory=KernelConfig)
    near_light: bool = True
    pca_rank: int | None = None


def directional_lights(model) -> bool:
    """True when the model says its one-light images were made with ideal directional
    lights (``[provenance] light_model = "directional"``), False otherwise."""
    return str((model.meta.get("provenance", {}) or {}).get("light_model", "")).lower() == "directional"


def view_surface_points(model, i: int, *, disc_scale: float = 1.5) -> np.ndarray:
    """(H, W, 3) object-frame point of the hull surface behind each pixel of view i
    (NaN where no surfel is hit): the pixel's ray cast against the discs of the
    surfels visible in the view (radius × ``disc_scale`` so that neighbouring discs
    overlap), keeping the nearest hit — a point on the surfel's tangent plane, not its
    centre, so the points do not step from surfel to surfel."""
    cam = model.views[i].camera
    s = model.surfels
    vis = s.visible_in(i)
    P = s.positions[vis].astype(np.float64)
    N = s.normals[vis].astype(np.float64)
    r = s.radii[vis].astype(np.float64) * disc_scale
    uv, z = cam.project(P)
    ok = np.isfinite(uv).all(axis=1) & (z > 0)
    P, N, r, uv, z = P[ok], N[ok], r[ok], uv[ok], z[ok]
    o, rays = cam.pixel_rays()
    rad_px = r * max(cam.fx, cam.fy) / z + 1.0  # bound of the disc's footprint
    t_best = np.full((cam.height, cam.width), np.inf)
    pts = np.full((cam.height, cam.width, 3), np.nan)
    _raycast_discs(uv, rad_px, P, N, r, np.asarray(o, np.float64), np.ascontiguousarray(rays), t_best, pts)
    return pts


def _raycast_discs(uv, rad_px, P, N, r, o, rays, t_best, pts):
    from numba import njit

    global _RC
    if _RC is None:

        @njit(cache=True)
        def rc(uv, rad_px, P, N, r, o, rays, t_best, pts):  # pragma: no cover - compiled
            H, W = t_best.shape
            for n in range(uv.shape[0]):
                x0 = max(0, int(math.floor(uv[n, 0] - rad_px[n])))
                x1 = min(W - 1, int(math.ceil(uv[n, 0] + rad_px[n])))
                y0 = max(0, int(math.floor(uv[n, 1] - rad_px[n])))
                y1 = min(H - 1, int(math.ceil(uv[n, 1] + rad_px[n])))
                cx, cy, cz = P[n, 0], P[n, 1], P[n, 2]
                nx, ny, nz = N[n, 0], N[n, 1], N[n, 2]
                num = (cx - o[0]) * nx + (cy - o[1]) * ny + (cz - o[2]) * nz
                r2 = r[n] * r[n]
                for y in range(y0, y1 + 1):
                    for x in range(x0, x1 + 1):
                        dx, dy, dz = rays[y, x, 0], rays[y, x, 1], rays[y, x, 2]
                        den = dx * nx + dy * ny + dz * nz
                        if abs(den) < 1e-6:
                            continue
                        t = num / den
                        if t <= 0.0 or t >= t_best[y, x]:
                            continue
                        hx = o[0] + t * dx - cx
                        hy = o[1] + t * dy - cy
                        hz = o[2] + t * dz - cz
                        if hx * hx + hy * hy + hz * hz <= r2:
                            t_best[y, x] = t
                            pts[y, x, 0] = hx + cx
                            pts[y, x, 1] = hy + cy
                            pts[y, x, 2] = hz + cz

        _RC = rc
    _RC(uv, rad_px, P, N, r, o, rays, t_best, pts)


_RC = None


class Relighter:
    """Relights the captured views of one model.

    Weights depend only on the table angle (all cameras at one table angle share the
    light directions), so they are computed once per (lighting, table angle).
    """

    def __init__(self, model, *, config: RelightConfig = RelightConfig()):
        self.model = model
        self.config = config
        self.lights: LightSet = light_set_from_model(model)
        self._wcache: dict = {}
        self._prepared: dict = {}
        #: whether the near-light correction is applied (config, unless the model's
        #: one-light images come from ideal directional lights)
        self.near_light = bool(config.near_light) and directional_lights(model) is False
        #: per view index: {"rel_error", "compression_ratio", "rank"} of the last PCA relight
        self.pca_stats: dict[int, dict] = {}
        geom = model.geometry
        self._light_pos_rig = np.array(
            [
                geom.light(int(i)).position_rig(float(a))
                for i, a in zip(self.lights.light_ids, self.lights.array_deg, strict=True)
            ]
        )

    @classmethod
    def open(cls, path, *, config: RelightConfig = RelightConfig()) -> Relighter:
        from ..model import OpacityHullModel

        return cls(OpacityHullModel.open(path), config=config)

    # ---- weights
    def light_positions_object(self, table_deg: float) -> np.ndarray:
        from ..camera import object_from_rig

        return self._light_pos_rig @ object_from_rig(table_deg)[:3, :3].T

    def weights(self, table_deg: float, *, envmap: EnvironmentMap | None = None, lights=None) -> np.ndarray:
        """Calibrated (K, 3) weights for views at ``table_deg`` under ``envmap`` or
        ``lights = (directions (M, 3), irradiance (M, 3))`` (object frame), or both
        (summed)."""
        if envmap is None and lights is None:
            raise InputError("relighting needs an environment map (--envmap) or lights (--lights)")
        key = (
            envmap,
            None if lights is None else (np.asarray(lights[0]).tobytes(), np.asarray(lights[1]).tobytes()),
            round(float(table_deg) % 360.0, 9),
        )
        if key not in self._wcache:
            dirs = self.lights.directions_object(table_deg)
            w = np.zeros((len(self.lights), 3))
            if envmap is not None:
                if envmap not in self._prepared:  # texel directions and powers: once per map
                    self._prepared = {envmap: prepare_envmap(envmap, config=self.config.kernel)}
                w += integrate_envmap(None, dirs, config=self.config.kernel, prepared=self._prepared[envmap])
            if lights is not None:
                w += directional_light_weights(dirs, lights[0], lights[1], config=self.config.kernel)
            self._wcache[key] = w / self.lights.output_rgb
        return self._wcache[key]

    # ---- data
    def load_stack(self, i: int) -> np.ndarray:
        """(K, H, W, 3) float32 one-light images of view i in the light set's order."""
        imgs = self.model.load_reflectance(i)
        first = imgs[self.lights.keys[0]]
        stack = np.empty((len(self.lights),) + first.shape, np.float32)
        for k, key in enumerate(self.lights.keys):
            a = imgs[key]
            if a.shape != first.shape:
                raise FormatError(
                    f"{self.model.root}: view {self.model.views[i].id} one-light image {key} has shape "
                    f"{a.shape}, others {first.shape}"
                )
            stack[k] = a
        bad = ~np.isfinite(stack)
        if bad.any():
            k = int(np.argwhere(bad)[0][0])
            raise FormatError(
                f"{self.model.root}: view {self.model.views[i].id} one-light image {self.lights.keys[k]} "
                f"has {int(bad[k].sum())} NaN/Inf values"
            )
        return stack

    def matte(self, i: int) -> np.ndarray:
        """(H, W) float32 alpha of view i."""
        return self.model.load_view_rgba(i)[..., 3]

    # ---- relighting
    def relight_view(
        self, i: int, *, envmap: EnvironmentMap | None = None, lights=None, weights=None, stack=None, alpha=None
    ) -> np.ndarray:
        """(H, W, 4) float32 premultiplied RGBA of view i relit: RGB = Σ_k w_k O_k,
        A = the view's matte; colour where the matte is 0 is zeroed (premultiplied
        colour must vanish with alpha). ``weights`` may be (M, K, 3) → (M, H, W, 4)."""
        v = self.model.views[i]
        w = self.weights(v.table_deg, envmap=envmap, lights=lights) if weights is None else np.asarray(weights)
        s = self.load_stack(i) if stack is None else stack
        a = self.matte(i) if alpha is None else alpha
        if a.shape != s.shape[1:3]:
            raise FormatError(f"{self.model.root}: view {v.id} matte is {a.shape}, one-light images are {s.shape[1:3]}")
        pts = lp = None
        if self.near_light:
            pts = view_surface_points(self.model, i)
            lp = self.light_positions_object(v.table_deg)
        if self.config.pca_rank is not None:
            comp = compress_reflectance(s if pts is None else _near_scaled(s, pts, lp), self.config.pca_rank)
            rgb = comp.relight(w)
            self.pca_stats[i] = {
                "rank": comp.rank,
                "rel_error": comp.rel_error,
                "compression_ratio": comp.compression_ratio,
            }
        else:
            rgb = relight_stack(s, w, points=pts, light_positions=lp)
        rgb = np.where((a > 0)[..., None], rgb, np.float32(0))
        aa = np.broadcast_to(a[..., None], rgb.shape[:-1] + (1,))
        return np.concatenate([rgb, aa], axis=-1).astype(np.float32)

    def relight_views(
        self,
        indices: Sequence[int] | None = None,
        *,
        envmap: EnvironmentMap | None = None,
        lights=None,
        progress: Callable[[int, int], None] | None = None,
    ) -> list[np.ndarray]:
        """Relit premultiplied RGBA of the views ``indices`` (default all), in order."""
        idx = list(range(len(self.model.views))) if indices is None else list(indices)
        out = []
        for n, i in enumerate(idx):
            out.append(self.relight_view(i, envmap=envmap, lights=lights))
            if progress:
                progress(n + 1, len(idx))
        return out


def _near_scaled(stack, points, light_positions):
    """The stack with the near-light factor applied per sample (for PCA)."""
    out = np.empty_like(stack)
    for k in range(stack.shape[0]):
        p = light_positions[k]
        f = np.clip(np.sum((p - points) ** 2, axis=-1) / np.sum(p**2), 0.25, 4.0)
        out[k] = stack[k] * np.where(np.isnan(f), 1.0, f)[..., None]
    return out
