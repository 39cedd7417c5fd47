"""Photo-consistent refinement of hull surfels: geometry beyond the visual hull.

The visual hull is the largest shape consistent with the silhouettes; where the object
has concavities no silhouette sees, the hull surface lies outside the true surface, the
source views' colours at a hull point disagree and blended renderings ghost. The true
surface lies *inside* the hull, so each surfel searches inward along its (outward) hull
normal for the depth at which the views agree:

1. **views** — among the views the surfel is visible in (minus ``exclude_views``, e.g. a
   held-out view), the ``n_views`` most fronto-parallel (largest ``n · (c − p)/|c − p|``);
   the first is the reference.
2. **cost volume** — candidates ``p − d n`` for ``d = 0, s, 2s, … ≤ d_max`` with ``s`` =
   ``depth_step_px`` reference-pixel footprints (``z_ref / f_ref``). At each candidate a
   ``patch_size²`` grid on the tangent plane (spacing ``patch_step_px`` footprints) is
   projected into every chosen view and sampled bilinearly from the grey images; the score
   is the mean normalised cross-correlation of the reference patch with the others (NCC
   is robust to the exposure and shading differences between views). Variances get
   ``texture_std²`` added, so an untextured patch scores ≈ 0 everywhere instead of
   amplifying noise. A candidate whose centre leaves the silhouette (α ≤
   ``alpha_threshold``) of a chosen view is outside the hull: it and everything deeper are
   invalid (the search never passes through a thin part to the far side).
3. **decision** — best candidate, refined to sub-step by a parabola through its
   neighbours; it is *confident* when its NCC ≥ ``min_ncc`` and the cost ratio
   ``(1 − best) / (1 − second)`` against the best candidate at least two steps away is
   ≤ ``peak_ratio`` (a distinct peak). Unconfident surfels keep depth 0 (the hull), and so
   do rim surfels: those within ``rim_px`` of the silhouette boundary of their reference
   view, where even the most frontal view sees the surface grazing (there the hull is
   exact).
4. **regularisation** — each surfel takes the median depth of the confident (and rim)
   surfels among its ``neighbours`` nearest (``scipy.spatial.KDTree``), provided at least
   ``min_support`` of them are; otherwise depth 0. This removes isolated wrong matches and
   fills small gaps. Then ``smooth_iters`` passes of the k-neighbour mean taper the steps
   left between moved and unmoved surfels: the renderer's ε-z-buffer shows a depth step
   as a seam of partial coverage (measured: 2 → 20 passes, +0.2 dB LOO on templeSR).
5. **clamp** — the refined points are tested against the silhouettes of *every* view
   (:func:`.hull.point_in_hull`, α > ``alpha_threshold``); a point outside has its depth
   halved until it is inside (or 0). A surfel therefore never leaves the hull.
6. **outlines** (``keep_coverage``) — the photographs' silhouettes are exact, and so is the
   hull's outline in every captured view; moving a contour surfel inward shrinks it. Each
   view's surfel coverage (disc z-buffer) is compared with the hull's; moved surfels whose
   hull position falls on a pixel that lost coverage, or that no view sees any more, go
   back onto the hull and are held there while the depths are smoothed again (up to
   ``coverage_rounds`` times). Radii grow to ``radius_factor`` × the distance to the
   ``radius_neighbours``-th neighbour, since moved surfels spread apart.

Normals are kept from the hull (``normals="hull"``) or re-estimated by PCA of the
refined neighbours, oriented like the hull normal (``normals="pca"``).

Defaults were chosen by leave-one-out on templeSR/dinoSR at hull-res 256
(``benchmarks/photo_refine.py``): a shallow search (``d_max_px = 12``) beat 24 and 40
(deeper matches are more often wrong, and each wrong one is a seam); ``n_best = 2`` and a
7×7 patch changed LOO by < 0.05 dB. The figures are in ``benchmarks/out/photo_refine.md``.

:func:`cost_volume` is the numba kernel (parallel over surfels); :func:`cost_volume_reference`
is the same arithmetic in plain NumPy (a loop over surfels), for the tests.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
from numba import njit, prange

from ..errors import ConfigError, InputError, ShapeError
from .hull import point_in_hull, projection_matrices

__all__ = ["PhotoConfig", "refine_surfels", "select_views", "cost_volume", "cost_volume_reference", "tangent_frames"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class PhotoConfig:
    """Options of :func:`refine_surfels` (pixel quantities are reference-view footprints
    ``z_ref / f_ref`` at the hull point, so the defaults hold at any scale).

    n_views : views scored per surfel, the reference included (≥ 2).
    n_best : score = mean NCC of the ``n_best`` best-matching other views (0 = all of them):
        robust to views occluded at the candidate depth.
    patch_size : odd side of the tangent-plane patch, in samples.
    patch_step_px : patch sample spacing.
    depth_step_px : spacing of the depth candidates.
    d_max_px : deepest candidate below the hull surface (also bounded by the silhouettes).
    texture_std : added to the patch standard deviations (linear radiance units): patches
        with less contrast than this give NCC ≈ 0 and are left on the hull.
    min_ncc : minimum mean NCC of a confident depth.
    peak_ratio : maximum ``(1 − best)/(1 − second)``; smaller = stricter.
    rim_px : surfels this close to the reference view's silhouette boundary stay on the hull.
    rim_cos : if > 0, so do surfels within ``rim_px`` of the silhouette boundary of any view
        that sees them grazing (``|n · ray| <= rim_cos``).
    alpha_threshold : silhouette = α > this (the build's threshold).
    neighbours : k of the neighbourhood median (1 = no regularisation).
    min_support : fraction of the k neighbours that must be confident.
    smooth_iters : passes of a k-neighbour mean over the median-filtered depths.
    normals : ``"hull"`` keeps the input normals, ``"pca"`` re-estimates them.
    radius_neighbours, radius_factor : a surfel's radius becomes at least ``radius_factor``
        × the distance to its ``radius_neighbours``-th nearest refined neighbour (0 disables).
    keep_coverage : put surfels back on the hull wherever moving them would uncover pixels
        the hull's surfels covered in some view (the photographs' outlines are exact), then
        smooth again with them held, up to ``coverage_rounds`` times.
    """

    n_views: int = 5
    n_best: int = 0
    patch_size: int = 5
    patch_step_px: float = 1.0
    depth_step_px: float = 1.0
    d_max_px: float = 12.0
    texture_std: float = 0.01
    min_ncc: float = 0.5
    peak_ratio: float = 0.9
    rim_px: float = 1.5
    rim_cos: float = 0.0
    alpha_threshold: float = 0.5
    neighbours: int = 16
    min_support: float = 0.25
    smooth_iters: int = 20
    normals: Literal["hull", "pca"] = "hull"
    radius_neighbours: int = 6
    radius_factor: float = 1.0
    keep_coverage: bool = True
    coverage_rounds: int = 3

    def __post_init__(self):
        if int(self.n_views) < 2:
            raise ConfigError(f"PhotoConfig.n_views must be >= 2 (a reference and one more), got {self.n_views}")
        if int(self.n_best) < 0:
            raise ConfigError(f"PhotoConfig.n_best must be >= 0 (0 = all views), got {self.n_best}")
        if int(self.patch_size) < 1 or int(self.patch_size) % 2 == 0:
            raise ConfigError(f"PhotoConfig.patch_size must be odd and >= 1, got {self.patch_size}")
        for key in ("patch_step_px", "depth_step_px"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"PhotoConfig.{key} must be > 0, got {v}")
        if not (math.isfinite(self.d_max_px) and self.d_max_px >= 0):
            raise ConfigError(f"PhotoConfig.d_max_px must be >= 0, got {self.d_max_px}")
        if not (self.texture_std > 0):
            raise ConfigError(f"PhotoConfig.texture_std must be > 0, got {self.texture_std}")
        if not (-1.0 <= self.min_ncc <= 1.0):
            raise ConfigError(f"PhotoConfig.min_ncc must be in [-1, 1], got {self.min_ncc}")
        if not (0.0 < self.peak_ratio <= 1.0):
            raise ConfigError(f"PhotoConfig.peak_ratio must be in (0, 1], got {self.peak_ratio}")
        if not (0.0 <= self.rim_cos <= 1.0):
            raise ConfigError(f"PhotoConfig.rim_cos must be in [0, 1], got {self.rim_cos}")
        if not (self.rim_px >= 0):
            raise ConfigError(f"PhotoConfig.rim_px must be >= 0, got {self.rim_px}")
        if int(self.neighbours) < 1:
            raise ConfigError(f"PhotoConfig.neighbours must be >= 1, got {self.neighbours}")
        if not (0.0 <= self.min_support <= 1.0):
            raise ConfigError(f"PhotoConfig.min_support must be in [0, 1], got {self.min_support}")
        if self.normals not in ("hull", "pca"):
            raise ConfigError(f"PhotoConfig.normals must be 'hull' or 'pca', got {self.normals!r}")

    @property
    def n_depths(self) -> int:
        return int(math.floor(self.d_max_px / self.depth_step_px + 1e-9)) + 1


# --------------------------------------------------------------------------- inputs


def _stack(name, arrays, cameras, channels):
    V = len(cameras)
    if len(arrays) != V:
        raise InputError(f"{len(arrays)} {name} for {V} cameras")
    Hm = max(c.height for c in cameras)
    Wm = max(c.width for c in cameras)
    out = np.zeros((V, Hm, Wm), np.float32)
    for i, (a, c) in enumerate(zip(arrays, cameras)):
        a = np.asarray(a, dtype=np.float32)
        if channels == 3 and a.ndim == 3 and a.shape[2] in (3, 4):
            a = a[..., :3].mean(axis=2)
        elif channels == 1 and a.ndim == 3 and a.shape[2] == 1:
            a = a[..., 0]
        if a.shape != (c.height, c.width):
            raise ShapeError(
                f"{name}[{i}] ({c.name}) has shape {np.shape(arrays[i])}, expected "
                f"({c.height}, {c.width}{', 3' if channels == 3 else ''})"
            )
        out[i, : c.height, : c.width] = a
    return out


def tangent_frames(normals) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) orthogonal to each unit normal (and to each other)."""
    n = np.asarray(normals, dtype=np.float64)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, helper)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-300)
    t2 = np.cross(n, t1)
    return t1, t2


def select_views(
    positions, normals, visibility, cameras, *, n_views: int, exclude_views: Sequence[int] = ()
) -> np.ndarray:
    """(N, n_views) int64 view indices per surfel, most fronto-parallel first, −1 padded.

    Only views with the visibility bit set and not in ``exclude_views`` are chosen."""
    pos = np.asarray(positions, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    vis = np.asarray(visibility, dtype=bool).copy()
    V = len(cameras)
    for v in exclude_views:
        if not 0 <= int(v) < V:
            raise InputError(f"exclude_views: view {v} out of range [0, {V})")
        vis[:, int(v)] = False
    C = np.array([c.centre_world for c in cameras], dtype=np.float64).reshape(V, 3)
    d = C[None, :, :] - pos[:, None, :]
    d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-300)
    cos = np.einsum("nvk,nk->nv", d, nrm)
    cos = np.where(vis, cos, -np.inf)
    m = min(int(n_views), V)
    order = np.argsort(-cos, axis=1, kind="stable")[:, :m]
    ok = np.take_along_axis(vis, order, axis=1)
    out = np.full((pos.shape[0], int(n_views)), -1, np.int64)
    out[:, :m] = np.where(ok, order, -1)
    return out


# --------------------------------------------------------------------------- kernel


@njit(cache=True, inline="always")
def _bilinear(img, v, W, H, u, t):
    """Bilinear sample of img[v] at pixel (u, t), pixel centres at integers; NaN off the image."""
    if not (u >= 0.0 and t >= 0.0 and u <= W - 1.0 and t <= H - 1.0):
        return np.nan
    x0 = min(int(math.floor(u)), W - 2) if W > 1 else 0
    y0 = min(int(math.floor(t)), H - 2) if H > 1 else 0
    fx = u - x0
    fy = t - y0
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    a = img[v, y0, x0] * (1.0 - fx) + img[v, y0, x1] * fx
    b = img[v, y1, x0] * (1.0 - fx) + img[v, y1, x1] * fx
    return a * (1.0 - fy) + b * fy


@njit(cache=True, inline="always")
def _project(P, v, x, y, z):
    a = P[v, 0, 0] * x + P[v, 0, 1] * y + P[v, 0, 2] * z + P[v, 0, 3]
    b = P[v, 1, 0] * x + P[v, 1, 1] * y + P[v, 1, 2] * z + P[v, 1, 3]
    w = P[v, 2, 0] * x + P[v, 2, 1] * y + P[v, 2, 2] * z + P[v, 2, 3]
    if not (w > 0.0):
        return np.nan, np.nan
    return a / w, b / w


@njit(cache=True, nogil=True)
def _surfel_costs(
    n, P, grey, alpha, sizes, pos, nrm, t1, t2, views, step, spacing, D, K, eps2, athr, n_best, out, buf, nccs
):
    m = 0
    for j in range(views.shape[1]):
        if views[n, j] >= 0:
            m += 1
    for d in range(D):
        out[n, d] = np.nan
    if m < 2:
        return
    half = (K - 1) // 2
    KK = K * K
    for d in range(D):
        depth = d * step[n]
        cx = pos[n, 0] - depth * nrm[n, 0]
        cy = pos[n, 1] - depth * nrm[n, 1]
        cz = pos[n, 2] - depth * nrm[n, 2]
        if d > 0:
            inside = True
            for j in range(m):
                v = views[n, j]
                u, t = _project(P, v, cx, cy, cz)
                a = _bilinear(alpha, v, sizes[v, 0], sizes[v, 1], u, t)
                if not (a > athr):
                    inside = False
                    break
            if not inside:
                break  # outside the hull: this and every deeper candidate stay NaN
        for j in range(m):
            v = views[n, j]
            k = 0
            for a in range(-half, half + 1):
                for b in range(-half, half + 1):
                    sa = a * spacing[n]
                    sb = b * spacing[n]
                    x = cx + sa * t1[n, 0] + sb * t2[n, 0]
                    y = cy + sa * t1[n, 1] + sb * t2[n, 1]
                    z = cz + sa * t1[n, 2] + sb * t2[n, 2]
                    u, t = _project(P, v, x, y, z)
                    buf[j, k] = _bilinear(grey, v, sizes[v, 0], sizes[v, 1], u, t)
                    k += 1
        # reference statistics
        ok0 = True
        mu0 = 0.0
        for k in range(KK):
            if not math.isfinite(buf[0, k]):
                ok0 = False
            mu0 += buf[0, k]
        if not ok0:
            continue
        mu0 /= KK
        var0 = 0.0
        for k in range(KK):
            var0 += (buf[0, k] - mu0) * (buf[0, k] - mu0)
        var0 /= KK
        cnt = 0
        for j in range(1, m):
            okj = True
            mu = 0.0
            for k in range(KK):
                if not math.isfinite(buf[j, k]):
                    okj = False
                mu += buf[j, k]
            if not okj:
                continue
            mu /= KK
            var = 0.0
            cov = 0.0
            for k in range(KK):
                var += (buf[j, k] - mu) * (buf[j, k] - mu)
                cov += (buf[j, k] - mu) * (buf[0, k] - mu0)
            var /= KK
            cov /= KK
            nccs[cnt] = cov / math.sqrt((var0 + eps2) * (var + eps2))
            cnt += 1
        if cnt > 0:
            out[n, d] = _mean_best(nccs, cnt, n_best)


@njit(cache=True, inline="always")
def _mean_best(x, cnt, n_best):
    """Mean of the n_best largest of x[:cnt] (all when n_best <= 0 or >= cnt): views that do
    not see the candidate (occluded at that depth) score low and are left out."""
    k = cnt if (n_best <= 0 or n_best >= cnt) else n_best
    for i in range(1, cnt):  # insertion sort, descending (cnt is a handful)
        v = x[i]
        j = i - 1
        while j >= 0 and x[j] < v:
            x[j + 1] = x[j]
            j -= 1
        x[j + 1] = v
    t = 0.0
    for i in range(k):
        t += x[i]
    return t / k


@njit(cache=True, parallel=True, nogil=True)
def _cost_kernel(P, grey, alpha, sizes, pos, nrm, t1, t2, views, step, spacing, D, K, eps2, athr, n_best, out):
    N = pos.shape[0]
    nchunk = 64
    per = (N + nchunk - 1) // nchunk
    for c in prange(nchunk):
        buf = np.empty((views.shape[1], K * K), np.float64)
        nccs = np.empty(views.shape[1], np.float64)
        for n in range(c * per, min(N, (c + 1) * per)):
            _surfel_costs(
                n,
                P,
                grey,
                alpha,
                sizes,
                pos,
                nrm,
                t1,
                t2,
                views,
                step,
                spacing,
                D,
                K,
                eps2,
                athr,
                n_best,
                out,
                buf,
                nccs,
            )


def _kernel_inputs(positions, normals, cameras, grey, alpha, views, step_m, spacing_m):
    pos = np.ascontiguousarray(np.asarray(positions, dtype=np.float64))
    nrm = np.ascontiguousarray(np.asarray(normals, dtype=np.float64))
    t1, t2 = tangent_frames(nrm)
    P = projection_matrices(cameras)
    sizes = np.array([(c.width, c.height) for c in cameras], dtype=np.int64).reshape(-1, 2)
    return (
        P,
        np.ascontiguousarray(grey, dtype=np.float32),
        np.ascontiguousarray(alpha, dtype=np.float32),
        sizes,
        pos,
        nrm,
        np.ascontiguousarray(t1),
        np.ascontiguousarray(t2),
        np.ascontiguousarray(views, dtype=np.int64),
        np.ascontiguousarray(step_m, dtype=np.float64),
        np.ascontiguousarray(spacing_m, dtype=np.float64),
    )


def cost_volume(
    positions,
    normals,
    cameras,
    grey,
    alpha,
    views,
    step_m,
    spacing_m,
    *,
    n_depths: int,
    patch_size: int,
    texture_std: float,
    alpha_threshold: float,
    n_best: int = 0,
) -> np.ndarray:
    """Mean NCC (N, n_depths) of each surfel's candidates ``p − d·step_m·n`` (numba).

    Parameters
    ----------
    positions, normals : (N, 3) hull points (metres) and unit outward normals.
    cameras : V pinhole cameras (object frame).
    grey, alpha : (V, Hmax, Wmax) float32 grey images and mattes (views padded).
    views : (N, m) view indices per surfel (reference first), −1 = none.
    step_m, spacing_m : (N,) depth step and patch spacing in metres.
    n_best : average only the ``n_best`` best-matching views' NCC (0 = all).

    Returns
    -------
    (N, n_depths) float64 mean NCC in [−1, 1]; NaN where the candidate is invalid (fewer than
    two views, off an image, non-finite pixels, or at/below a silhouette exit).
    """
    args = _kernel_inputs(positions, normals, cameras, grey, alpha, views, step_m, spacing_m)
    out = np.empty((args[4].shape[0], int(n_depths)), np.float64)
    if out.size:
        _cost_kernel(
            *args, int(n_depths), int(patch_size), float(texture_std) ** 2, float(alpha_threshold), int(n_best), out
        )
    return out


def cost_volume_reference(
    positions,
    normals,
    cameras,
    grey,
    alpha,
    views,
    step_m,
    spacing_m,
    *,
    n_depths: int,
    patch_size: int,
    texture_std: float,
    alpha_threshold: float,
    n_best: int = 0,
) -> np.ndarray:
    """NumPy oracle of :func:`cost_volume` (loop over surfels and depths; vectorised over
    the patch; small inputs only)."""
    P, grey, alpha, sizes, pos, nrm, t1, t2, views, step, spacing = _kernel_inputs(
        positions, normals, cameras, grey, alpha, views, step_m, spacing_m
    )
    K = int(patch_size)
    half = (K - 1) // 2
    ab = np.array([(a, b) for a in range(-half, half + 1) for b in range(-half, half + 1)], dtype=np.float64)
    eps2 = float(texture_std) ** 2

    def sample(img, v, pts):
        h = np.c_[pts, np.ones(len(pts))] @ P[v].T
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(h[:, 2] > 0, h[:, 0] / h[:, 2], np.nan)
            t = np.where(h[:, 2] > 0, h[:, 1] / h[:, 2], np.nan)
        W, H = sizes[v]
        inside = (u >= 0) & (t >= 0) & (u <= W - 1) & (t <= H - 1)
        u0 = np.where(inside, u, 0.0)
        t0 = np.where(inside, t, 0.0)
        x0 = np.minimum(np.floor(u0).astype(int), max(W - 2, 0))
        y0 = np.minimum(np.floor(t0).astype(int), max(H - 2, 0))
        fx, fy = u0 - x0, t0 - y0
        x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
        im = img[v].astype(np.float64)
        val = (im[y0, x0] * (1 - fx) + im[y0, x1] * fx) * (1 - fy) + (im[y1, x0] * (1 - fx) + im[y1, x1] * fx) * fy
        return np.where(inside, val, np.nan)

    out = np.full((pos.shape[0], int(n_depths)), np.nan)
    for n in range(pos.shape[0]):
        vs = [int(v) for v in views[n] if v >= 0]
        if len(vs) < 2:
            continue
        for d in range(int(n_depths)):
            c = pos[n] - d * step[n] * nrm[n]
            if d > 0 and not all(sample(alpha, v, c[None])[0] > alpha_threshold for v in vs):
                break
            pts = c + spacing[n] * (ab[:, :1] * t1[n] + ab[:, 1:] * t2[n])
            patches = [sample(grey, v, pts) for v in vs]
            p0 = patches[0]
            if not np.all(np.isfinite(p0)):
                continue
            scores = []
            for p in patches[1:]:
                if not np.all(np.isfinite(p)):
                    continue
                cov = np.mean((p - p.mean()) * (p0 - p0.mean()))
                scores.append(cov / math.sqrt((p0.var() + eps2) * (p.var() + eps2)))
            if scores:
                scores = sorted(scores, reverse=True)
                k = len(scores) if (n_best <= 0 or n_best >= len(scores)) else n_best
                out[n, d] = float(np.mean(scores[:k]))
    return out


# --------------------------------------------------------------------------- decision


def best_depths(scores: np.ndarray, *, min_ncc: float, peak_ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of an (N, D) NCC volume: sub-step best index (float), its NCC and whether it is
    confident (NCC ≥ ``min_ncc`` and ``(1 − best)/(1 − second) ≤ peak_ratio``, the second
    being the best candidate at least two steps away). Rows without a finite entry give
    index 0, NCC NaN, not confident."""
    N, D = scores.shape
    s = np.where(np.isfinite(scores), scores, -np.inf)
    j = np.argmax(s, axis=1)
    best = s[np.arange(N), j]
    far = s.copy()
    idx = np.arange(D)[None, :]
    far[np.abs(idx - j[:, None]) <= 1] = -np.inf
    second = far.max(axis=1) if D else np.full(N, -np.inf)
    # parabola through the neighbours (only where both exist)
    jm, jp = np.clip(j - 1, 0, D - 1), np.clip(j + 1, 0, D - 1)
    sm, sp = s[np.arange(N), jm], s[np.arange(N), jp]
    ok = (j > 0) & (j < D - 1) & np.isfinite(sm) & np.isfinite(sp)
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = sm - 2 * best + sp
        off = np.where(ok & (denom < 0), 0.5 * (sm - sp) / denom, 0.0)
    sub = j + np.clip(off, -0.5, 0.5)
    finite = np.isfinite(best)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.isfinite(second), (1.0 - best) / np.maximum(1.0 - second, 1e-12), 0.0)
    conf = finite & (best >= min_ncc) & (ratio <= peak_ratio)
    sub = np.where(finite, sub, 0.0)
    return sub, np.where(finite, best, np.nan), conf


def _rim(positions, normals, views, cameras, sils, rim_px, rim_cos):
    """Surfels on a silhouette rim: within ``rim_px`` of the silhouette boundary of their
    reference view, or (``rim_cos > 0``) of any view that sees them grazing
    (``|n · ray| <= rim_cos``) — the contour generators that make each view's outline."""
    from scipy.ndimage import distance_transform_edt

    out = np.zeros(positions.shape[0], bool)
    if rim_px <= 0 or positions.shape[0] == 0:
        return out
    ref = views[:, 0]
    for v, cam in enumerate(cameras):
        sel = np.flatnonzero(ref == v) if rim_cos <= 0 else np.arange(positions.shape[0])
        if not sel.size:
            continue
        s = sils[v, : cam.height, : cam.width]
        # distance of silhouette pixels to the nearest non-silhouette pixel (the boundary)
        edt = distance_transform_edt(np.pad(s, 1, constant_values=False))
        assert isinstance(edt, np.ndarray)  # distances only: no indices or out= requested
        inner = edt[1:-1, 1:-1]
        uv, z = cam.project(positions[sel])
        x = np.floor(uv[:, 0] + 0.5)
        y = np.floor(uv[:, 1] + 0.5)
        good = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x < cam.width) & (y < cam.height)
        dist = np.full(sel.size, np.inf)
        dist[good] = inner[y[good].astype(int), x[good].astype(int)]
        near = dist <= rim_px
        if rim_cos > 0:
            ray = positions[sel] - cam.centre_world
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-300)
            graze = np.abs(np.einsum("nk,nk->n", ray, normals[sel])) <= rim_cos
            out[sel] |= near & (graze | (ref[sel] == v))
        else:
            out[sel] |= near
    return out


def _clamp_into_hull(pos, nrm, depth, sils, cameras, clamped):
    """Refined points ``pos − depth·n``, with the depth of any point outside some view's
    silhouette halved until it is inside (then 0). Updates ``depth`` and ``clamped`` in place."""
    new = pos - depth[:, None] * nrm
    for it in range(7):
        moved = np.flatnonzero(depth > 0)
        if not moved.size:
            break
        bad = moved[~point_in_hull(new[moved], sils, cameras)]
        if not bad.size:
            break
        clamped[bad] = True
        depth[bad] = 0.0 if it == 6 else 0.5 * depth[bad]
        new[bad] = pos[bad] - depth[bad, None] * nrm[bad]
    return new


def _grown_radii(points, radii, k, factor):
    """Radii grown to ``factor`` × the distance to the k-th nearest neighbour: moved surfels
    spread apart where the surface is deeper than the hull, and the discs must still meet."""
    from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

    n = points.shape[0]
    if k < 1 or factor <= 0 or n < 2:
        return radii.copy()
    kk = min(int(k), n - 1)
    d, _ = KDTree(points).query(points, k=kk + 1)
    return np.maximum(radii, factor * d[:, -1])


def _restore_coverage(cov_h, pos, nrm, new, new_n, new_r, depth, cameras, *, iterations=3, grow_px=1, min_views=1):
    """Surfels to put back on the hull so that every view's surfel coverage (the rendered
    outline) stays what the hull's was: moving a contour surfel inward shrinks the outline
    the photographs' silhouettes made. Returns an (N,) bool mask."""
    from scipy.ndimage import binary_dilation

    from .visibility import surfel_visibility

    restored = np.zeros(pos.shape[0], bool)
    cur = new.copy()
    cur_n = new_n.copy()
    st = np.ones((2 * grow_px + 1, 2 * grow_px + 1), bool)
    for _ in range(iterations):
        vis, zb = surfel_visibility(cur, cur_n, new_r, cameras, return_depth=True)
        lost = cov_h & ~np.isfinite(zb)
        # a moved surfel no view sees any more would be drawn by nobody (a hole)
        add = (depth > 0) & ~restored & (vis.sum(axis=1) < min_views)
        if not lost.any() and not add.any():
            break
        cand = np.flatnonzero((depth > 0) & ~restored & ~add)
        for v, cam in enumerate(cameras):
            lv = lost[v, : cam.height, : cam.width]
            if not lv.any():
                continue
            lv = binary_dilation(lv, structure=st)
            uv, _ = cam.project(pos[cand])
            x = np.floor(uv[:, 0] + 0.5)
            y = np.floor(uv[:, 1] + 0.5)
            good = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x < cam.width) & (y < cam.height)
            hit = np.zeros(cand.size, bool)
            hit[good] = lv[y[good].astype(int), x[good].astype(int)]
            add[cand[hit]] = True
        if not add.any():
            break
        restored |= add
        cur[add] = pos[add]
        cur_n[add] = nrm[add]
    return restored


def _pca_normals(points, hull_normals, k):
    from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

    n = points.shape[0]
    if n < 3:
        return hull_normals.copy()
    k = min(max(int(k), 3), n)
    _, nb = KDTree(points).query(points, k=k)
    q = points[nb] - points[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q)
    w, vec = np.linalg.eigh(cov)
    nn = vec[:, :, 0]
    dot = np.einsum("ni,ni->n", nn, hull_normals)
    nn = nn * np.where(dot < 0, -1.0, 1.0)[:, None]
    bad = ~np.all(np.isfinite(nn), axis=1) | (w[:, 1] <= 0)
    nn[bad] = hull_normals[bad]
    return nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300)


def refine_surfels(
    positions,
    normals,
    radii,
    visibility,
    cameras,
    images,
    alphas,
    *,
    config: PhotoConfig = PhotoConfig(),
    exclude_views: Sequence[int] = (),
):
    """Move hull surfels inward to their photo-consistent depth (see the module docstring).

    Parameters
    ----------
    positions : (N, 3) surfel centres on the visual hull, metres, object frame.
    normals : (N, 3) unit outward hull normals.
    radii : (N,) surfel radii, metres (the smallest radii returned).
    visibility : (N, V) bool visibility vectors (e.g. ``Surfels.visible_bool()``).
    cameras : V pinhole :class:`~opacityhull.camera.Camera` (object frame, no distortion).
    images : V linear RGB (H, W, 3) float images (a (V, H, W, 3) array or a list); RGBA is
        accepted and its alpha ignored. Non-finite pixels invalidate the patches that touch them.
    alphas : V (H, W) mattes in [0, 1]; the silhouettes are ``α > config.alpha_threshold``.
    config : :class:`PhotoConfig`.
    exclude_views : view indices never used (a held-out view in leave-one-out).

    Returns
    -------
    positions : (N, 3) float64 refined centres (inside the hull of the silhouettes).
    normals : (N, 3) float64 unit normals (the input ones, or PCA with ``normals="pca"``).
    radii : (N,) float64 radii, grown where the refined surfels spread apart.
    stats : dict — ``depth_m`` (N,) inward displacement, ``confident`` (N,) bool, ``ncc``
        (N,) best NCC (NaN without two views), and counts/means/seconds.
    """
    t0 = time.perf_counter()
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ShapeError(f"positions have shape {pos.shape}, expected (N, 3)")
    N = pos.shape[0]
    nrm = np.asarray(normals, dtype=np.float64)
    if nrm.shape != pos.shape:
        raise ShapeError(f"normals have shape {nrm.shape}, expected {pos.shape}")
    rad = np.asarray(radii, dtype=np.float64).reshape(-1)
    if rad.shape != (N,):
        raise ShapeError(f"radii have shape {rad.shape}, expected ({N},)")
    V = len(cameras)
    vis = np.asarray(visibility, dtype=bool)
    if vis.shape != (N, V):
        raise ShapeError(f"visibility has shape {vis.shape}, expected ({N}, {V}) for {V} cameras")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(nrm))):
        raise InputError("refine_surfels: surfel positions or normals contain NaN/Inf")
    lens = np.linalg.norm(nrm, axis=1)
    if N and not np.all(np.abs(lens - 1) < 1e-3):
        raise InputError(
            f"refine_surfels: normals must be unit length (found lengths in [{lens.min():.3g}, {lens.max():.3g}])"
        )
    grey = _stack("images", list(images), cameras, 3)
    alpha = _stack("alphas", list(alphas), cameras, 1)
    np.nan_to_num(alpha, copy=False, nan=0.0)  # in place: a second (V, H, W) stack is the peak at many views
    sils = alpha > config.alpha_threshold

    views = select_views(pos, nrm, vis, cameras, n_views=config.n_views, exclude_views=exclude_views)
    ref = views[:, 0] if N else np.zeros(0, np.int64)
    has_ref = ref >= 0
    foot = np.full(N, np.nan)
    if N:
        for v, cam in enumerate(cameras):
            sel = np.flatnonzero(ref == v)
            if sel.size:
                z = cam.world_to_cam(pos[sel])[:, 2]
                foot[sel] = np.maximum(z, 0.0) / min(cam.fx, cam.fy)
    foot = np.where(has_ref & np.isfinite(foot) & (foot > 0), foot, 0.0)
    step = foot * config.depth_step_px
    spacing = foot * config.patch_step_px
    D = config.n_depths
    scores = cost_volume(
        pos,
        nrm,
        cameras,
        grey,
        alpha,
        views,
        step,
        spacing,
        n_depths=D,
        patch_size=config.patch_size,
        texture_std=config.texture_std,
        alpha_threshold=config.alpha_threshold,
        n_best=config.n_best,
    )
    t_cost = time.perf_counter() - t0
    sub, best, conf = best_depths(scores, min_ncc=config.min_ncc, peak_ratio=config.peak_ratio)
    conf &= foot > 0
    depth_raw = np.where(conf, sub * step, 0.0)
    rim = _rim(pos, nrm, views, cameras, sils, config.rim_px, config.rim_cos) & has_ref
    conf_raw = conf.copy()
    depth_raw[rim] = 0.0
    anchor = conf | rim

    depth = depth_raw.copy()
    k = min(int(config.neighbours), N)
    nb = None
    if k > 1:
        from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

        _, nb = KDTree(pos).query(pos, k=k)
        nd = np.where(anchor[nb], depth_raw[nb], np.nan)
        support = anchor[nb].mean(axis=1)
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(nd, axis=1)
        depth = np.where((support >= config.min_support) & np.isfinite(med), med, 0.0)
        depth[rim] = 0.0
    fixed = rim.copy()  # surfels held on the hull
    restored = np.zeros(N, bool)
    clamped = np.zeros(N, bool)
    sil_list = list(sils)
    target = depth.copy()
    cov_h = None
    for rnd in range(int(config.coverage_rounds) if config.keep_coverage else 1):
        depth = np.where(fixed, 0.0, target)
        if nb is not None:
            # the median keeps steps between neighbours; averaging tapers them (also towards
            # surfels held on the hull), since the renderer's ε-z-buffer shows a step as a
            # seam of partial coverage
            for _ in range(int(config.smooth_iters)):
                depth = depth[nb].mean(axis=1)
                depth[fixed] = 0.0
        new = _clamp_into_hull(pos, nrm, depth, sil_list, cameras, clamped)
        out_n = nrm.copy()
        if config.normals == "pca":
            out_n = _pca_normals(new, nrm, config.neighbours)
            out_n[fixed] = nrm[fixed]
        out_r = rad.copy()
        if not np.any(depth > 0):
            break
        out_r = _grown_radii(new, rad, config.radius_neighbours, config.radius_factor)
        if not config.keep_coverage:
            break
        if cov_h is None:
            from .visibility import surfel_visibility

            cov_h = np.isfinite(surfel_visibility(pos, nrm, rad, cameras, return_depth=True)[1])
        back = _restore_coverage(cov_h, pos, nrm, new, out_n, out_r, depth, cameras)
        if not back.any():
            break
        restored |= back
        fixed |= back
        new[back] = pos[back]
        out_n[back] = nrm[back]
        depth[back] = 0.0
        out_r = _grown_radii(new, rad, config.radius_neighbours, config.radius_factor)
    secs = time.perf_counter() - t0
    moved_mask = depth > 0
    stats = {
        "depth_m": depth,
        "confident": conf_raw,
        "rim": rim,
        "ncc": best,
        "n_surfels": int(N),
        "n_confident": int(conf_raw.sum()),
        "n_rim": int(rim.sum()),
        "n_moved": int(moved_mask.sum()),
        "n_clamped": int(clamped.sum()),
        "n_restored_for_coverage": int(restored.sum()),
        "mean_depth_moved_m": float(depth[moved_mask].mean()) if moved_mask.any() else 0.0,
        "median_footprint_m": float(np.median(foot[foot > 0])) if np.any(foot > 0) else 0.0,
        "n_depths": int(D),
        "seconds_cost_volume": float(t_cost),
        "seconds": float(secs),
    }
    log.info(
        "photo refinement: %d/%d surfels confident, %d moved (mean %.3g m), %.2f s",
        stats["n_confident"],
        N,
        stats["n_moved"],
        stats["mean_depth_moved_m"],
        secs,
    )
    return new, out_n, out_r, stats
