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
(``cost_volume(..., oracle=True)``: one signature, one argument conversion) is the same
arithmetic in plain NumPy (a loop over surfels), for the tests.

**Memory.** :func:`refine_surfels` streams the photographs: the surfels are scored in
batches of one reference view (split further when their views exceed the budget), each
batch on the few views it uses, loaded into ``PhotoConfig.max_views_in_memory`` slots of
grey image and matte (the view needed again furthest ahead makes room), the same kernel
run on the remapped view indices, so the cost volume is bit for bit the full-stack one.
The silhouettes are held bit-packed and the hull test takes them a batch of views at a
time; a list of deferred photographs (the build's) is read view by view. Its memory is
O(max_views_in_memory·H·W) for the pixels + O(V·H·W/8) for the packed silhouettes +
O(N·(V + n_depths)) per surfel (visibility and scores), not O(V·H·W) floats. The outline
restoration (``keep_coverage``, not the build's shading mode) still renders (V, H, W) depth
buffers through :func:`.visibility.surfel_visibility`.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass
from typing import Literal
from collections.abc import Sequence

import numpy as np
from numba import njit, prange

from ..errors import ConfigError, InputError, ShapeError
from .hull import point_in_hull, projection_matrices

__all__ = ["PhotoConfig", "refine_surfels", "select_views", "cost_volume", "cost_volume_reference", "tangent_frames"]

log = logging.getLogger(__name__)

#: working memory of :func:`select_views` (its surfels are taken in chunks of this size)
SELECT_CHUNK_BYTES = 32 << 20


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
    max_views_in_memory : the memory budget, in views (≥ ``n_views``): the cost volume holds
        at most this many views' grey image and matte (8 bytes a pixel a view, e.g. 32 views
        = 20 MB at 320×240, 360 MB at 1360×1032), the hull test at most 8× as many
        silhouettes (1 byte a pixel). It bounds memory, not the result, which is bit for bit
        the same at any budget; a smaller one only reads photographs again more often.
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
    max_views_in_memory: int = 32

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
        if int(self.max_views_in_memory) < int(self.n_views):
            raise ConfigError(
                f"PhotoConfig.max_views_in_memory must be >= n_views = {self.n_views} (one surfel's "
                f"views are scored together), got {self.max_views_in_memory}"
            )

    @property
    def n_depths(self) -> int:
        return int(math.floor(self.d_max_px / self.depth_step_px + 1e-9)) + 1


# --------------------------------------------------------------------------- inputs


def _plane(name, i, a, cam, channels) -> np.ndarray:
    """View ``i``'s (H, W) float32 plane: the channel mean of an RGB(A) image
    (``channels=3``) or a matte (``channels=1``). Reads ``a`` (a deferred photograph is
    loaded here)."""
    a = np.asarray(a, dtype=np.float32)
    shape = a.shape
    if channels == 3 and a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[..., :3].mean(axis=2)
    elif channels == 1 and a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.shape != (cam.height, cam.width):
        raise ShapeError(
            f"{name}[{i}] ({cam.name}) has shape {shape}, expected "
            f"({cam.height}, {cam.width}{', 3' if channels == 3 else ''})"
        )
    return a


def _stack(name, arrays, cameras, channels):
    """(V, Hmax, Wmax) float32 planes of every view, zero-padded (the full-stack inputs of
    :func:`cost_volume`; :func:`refine_surfels` streams instead)."""
    V = len(cameras)
    if len(arrays) != V:
        raise InputError(f"{len(arrays)} {name} for {V} cameras")
    Hm = max(c.height for c in cameras)
    Wm = max(c.width for c in cameras)
    out = np.zeros((V, Hm, Wm), np.float32)
    for i, (a, c) in enumerate(zip(arrays, cameras, strict=True)):
        out[i, : c.height, : c.width] = _plane(name, i, a, c, channels)
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
    m = min(int(n_views), V)
    out = np.full((pos.shape[0], int(n_views)), -1, np.int64)
    # in row chunks: the (n, V, 3) directions are 24 B a surfel a view, 1 GB for 10⁵
    # surfels and 432 views at once (row by row, the same numbers)
    rows = max(1, SELECT_CHUNK_BYTES // (64 * max(V, 1)))
    for r0 in range(0, pos.shape[0], rows):
        r1 = min(r0 + rows, pos.shape[0])
        d = C[None, :, :] - pos[r0:r1, None, :]
        d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-300)
        cos = np.einsum("nvk,nk->nv", d, nrm[r0:r1])
        del d
        cos = np.where(vis[r0:r1], cos, -np.inf)
        order = np.argsort(-cos, axis=1, kind="stable")[:, :m]
        ok = np.take_along_axis(vis[r0:r1], order, axis=1)
        out[r0:r1, :m] = np.where(ok, order, -1)
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
    oracle: bool = False,
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
    oracle : compute with the kernel's NumPy twin instead (:func:`cost_volume_reference`).

    Returns
    -------
    (N, n_depths) float64 mean NCC in [−1, 1]; NaN where the candidate is invalid (fewer than
    two views, off an image, non-finite pixels, or at/below a silhouette exit).
    """
    args = _kernel_inputs(positions, normals, cameras, grey, alpha, views, step_m, spacing_m)
    out = np.empty((args[4].shape[0], int(n_depths)), np.float64)
    if out.size:
        (_cost_reference if oracle else _cost_kernel)(
            *args, int(n_depths), int(patch_size), float(texture_std) ** 2, float(alpha_threshold), int(n_best), out
        )
    return out


cost_volume_reference = functools.partial(cost_volume, oracle=True)
"""NumPy oracle of :func:`cost_volume`: the same arguments, the same arithmetic written as a
loop over surfels and depths, vectorised over the patch (small inputs only)."""


def _cost_reference(P, grey, alpha, sizes, pos, nrm, t1, t2, views, step, spacing, D, K, eps2, athr, n_best, out):
    """NumPy twin of :func:`_cost_kernel` (the same arguments; writes ``out``)."""
    half = (K - 1) // 2
    ab = np.array([(a, b) for a in range(-half, half + 1) for b in range(-half, half + 1)], dtype=np.float64)

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

    out[:] = np.nan
    for n in range(pos.shape[0]):
        vs = [int(v) for v in views[n] if v >= 0]
        if len(vs) < 2:
            continue
        for d in range(D):
            c = pos[n] - d * step[n] * nrm[n]
            if d > 0 and not all(sample(alpha, v, c[None])[0] > athr for v in vs):
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


# --------------------------------------------------------------------------- streaming


def _cost_batches(views, cap: int) -> list[np.ndarray]:
    """Surfel index batches of the streamed cost volume: the surfels with two or more
    views, grouped by reference view in view order (neighbouring references share most of
    their views, so a view stays loaded across consecutive batches), a group split
    further, in order, wherever the union of its surfels' views would exceed ``cap``."""
    m = (views >= 0).sum(axis=1)
    active = np.flatnonzero(m >= 2)
    if not active.size:
        return []
    order = active[np.argsort(views[active, 0], kind="stable")]
    refs = views[order, 0]
    cuts = np.flatnonzero(np.diff(refs)) + 1
    out = []
    for grp in np.split(order, cuts):
        vv = views[grp]
        if np.unique(vv[vv >= 0]).size <= cap:
            out.append(grp)
            continue
        # surfels with the same view set side by side, so that a split cuts few of them apart
        key = np.sort(np.where(vv >= 0, vv, np.iinfo(np.int64).max), axis=1)
        grp = grp[np.lexsort(key.T[::-1])]
        cur: set[int] = set()
        start = 0
        for k, n in enumerate(grp):
            row = {int(v) for v in views[n] if v >= 0}
            if len(cur | row) > cap:
                out.append(grp[start:k])
                start, cur = k, set()
            cur |= row
        out.append(grp[start:])
    return out


def _streamed_cost_volume(
    pos, nrm, cameras, images, alphas, views, step, spacing, *, config: PhotoConfig, cap: int
) -> tuple[np.ndarray, dict]:
    """:func:`cost_volume` over the full stacks, computed with at most ``cap`` views'
    grey image and matte in memory.

    The surfels are scored in :func:`_cost_batches`; a batch's views are loaded into a
    fixed set of ``min(cap, views used)`` slots (a view already there is kept; the one to
    make room for is the view needed again furthest in the future, Belady's rule, so with
    enough slots every photograph is read once), the batch's view indices, projection
    matrices and sizes remapped to the slots, and the same kernel run on it: each surfel
    sees the same pixels through the same arithmetic, so the volume is bit for bit the
    full-stack one. Memory: O(min(cap, V)·Hmax·Wmax) (8 bytes a pixel) + O(N·n_depths).
    Returns the (N, n_depths) volume and counts (``n_view_loads``, ``n_cost_batches``,
    ``views_in_memory``)."""
    N, D = pos.shape[0], int(config.n_depths)
    scores = np.full((N, D), np.nan)
    batches = _cost_batches(views, cap)
    counts = {"n_view_loads": 0, "n_cost_batches": len(batches), "views_in_memory": 0}
    if not batches:
        return scores, counts
    uses: dict[int, list[int]] = {}
    needs = []
    for b, sel in enumerate(batches):
        vv = views[sel]
        need = np.unique(vv[vv >= 0])
        needs.append(need)
        for v in need:
            uses.setdefault(int(v), []).append(b)
    S = min(int(cap), len(uses))
    Hm = max(c.height for c in cameras)
    Wm = max(c.width for c in cameras)
    grey = np.zeros((S, Hm, Wm), np.float32)
    alpha = np.zeros((S, Hm, Wm), np.float32)
    held = np.full(S, -1, np.int64)  # the view in each slot
    slot_of: dict[int, int] = {}
    P_all = projection_matrices(cameras)
    size_all = np.array([(c.width, c.height) for c in cameras], dtype=np.int64).reshape(-1, 2)
    t1, t2 = tangent_frames(nrm)
    K, eps2 = int(config.patch_size), float(config.texture_std) ** 2

    def next_use(v, b):
        u = uses[v]
        k = int(np.searchsorted(u, b, side="left"))
        return u[k] if k < len(u) else math.inf

    for b, sel in enumerate(batches):
        need = [int(v) for v in needs[b]]
        keep = set(need)
        for v in need:
            if v in slot_of:
                continue
            free = np.flatnonzero(held < 0)
            if free.size:
                s = int(free[0])
            else:
                # evict the held view (not needed by this batch) used again furthest ahead
                # (there is one: a batch needs at most cap views and v is not held yet)
                cand = [int(x) for x in held if int(x) not in keep]
                victim = max(cand, key=lambda x: next_use(x, b))
                s = slot_of.pop(victim)
            cam = cameras[v]
            h, w = cam.height, cam.width
            grey[s, :h, :w] = _plane("images", v, images[v], cam, 3)
            alpha[s, :h, :w] = _plane("alphas", v, alphas[v], cam, 1)
            # in place: NaN matte = outside (a copy of the plane would be a second one alive)
            np.nan_to_num(alpha[s, :h, :w], copy=False, nan=0.0)
            held[s] = v
            slot_of[v] = s
            counts["n_view_loads"] += 1
        lut = np.full(len(cameras), -1, np.int64)
        occupied = np.flatnonzero(held >= 0)
        lut[held[occupied]] = occupied
        vb = views[sel]
        vl = np.ascontiguousarray(np.where(vb >= 0, lut[np.maximum(vb, 0)], -1))
        # an empty slot's camera is never indexed (no surfel's view maps to it)
        src = np.where(held >= 0, held, 0)
        out = np.empty((sel.size, D), np.float64)
        _cost_kernel(
            np.ascontiguousarray(P_all[src]),
            grey,
            alpha,
            np.ascontiguousarray(size_all[src]),
            np.ascontiguousarray(pos[sel]),
            np.ascontiguousarray(nrm[sel]),
            np.ascontiguousarray(t1[sel]),
            np.ascontiguousarray(t2[sel]),
            vl,
            np.ascontiguousarray(step[sel]),
            np.ascontiguousarray(spacing[sel]),
            D,
            K,
            eps2,
            float(config.alpha_threshold),
            int(config.n_best),
            out,
        )
        scores[sel] = out
    counts["views_in_memory"] = int(S)
    return scores, counts


class _PackedSilhouettes(Sequence):
    """Per-view (H, W) bool masks held bit-packed along rows (H·W/8 bytes a view);
    ``sils[i]`` unpacks view ``i`` alone and a slice is another such sequence. (The
    layout of :class:`.build.PackedMasks`, kept here so that the refinement does not
    import the build.)"""

    def __init__(self, bits=None):
        self._bits: list = [] if bits is None else bits

    def append(self, mask) -> None:
        m = np.asarray(mask, bool)
        self._bits.append((np.packbits(m, axis=1), m.shape[1]))

    def __len__(self) -> int:
        return len(self._bits)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return _PackedSilhouettes(self._bits[i])
        bits, w = self._bits[i]
        return np.unpackbits(bits, axis=1, count=w).view(bool)


def _silhouettes(alphas, cameras, threshold: float) -> _PackedSilhouettes:
    """Every view's silhouette ``α > threshold`` (NaN = outside), read one matte at a time
    and held bit-packed."""
    out = _PackedSilhouettes()
    for i, cam in enumerate(cameras):
        out.append(_plane("alphas", i, alphas[i], cam, 1) > threshold)
    return out


def _in_hull(points, sils, cameras, *, batch: int) -> np.ndarray:
    """:func:`.hull.point_in_hull` (tolerance 0) with at most ``batch`` views' silhouettes
    unpacked at a time: a point is inside iff no view rejects it, so the batches' answers
    are ANDed (only points still inside are tested against the next batch)."""
    cams = list(cameras)
    ok = np.ones(points.shape[0], bool)
    b = max(1, int(batch))
    for b0 in range(0, len(cams), b):
        idx = np.flatnonzero(ok)
        if not idx.size:
            break
        ok[idx] = point_in_hull(points[idx], sils[b0 : b0 + b], cams[b0 : b0 + b])
    return ok


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
        s = np.asarray(sils[v], dtype=bool)
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


def _clamp_into_hull(pos, nrm, depth, sils, cameras, clamped, *, batch: int):
    """Refined points ``pos − depth·n``, with the depth of any point outside some view's
    silhouette halved until it is inside (then 0). Updates ``depth`` and ``clamped`` in place.
    ``sils`` is a sequence of (H, W) masks (bit-packed); ``batch`` views are tested at a time."""
    new = pos - depth[:, None] * nrm
    for it in range(7):
        moved = np.flatnonzero(depth > 0)
        if not moved.size:
            break
        bad = moved[~_in_hull(new[moved], sils, cameras, batch=batch)]
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


def stable_knn(points, k: int, *, rel_tol: float = 1e-4, extra: int = 32) -> np.ndarray:
    """(N, k) indices of each point's k nearest points (itself first), ties broken by index.

    Hull surfels lie on grid lines, so many of a surfel's neighbours are exactly
    equidistant; ``KDTree.query`` then picks among them by the tree's layout, and a 1e-10 m
    change of the positions (a 1e-9 change of the cameras) picked others — measured on the
    tiny plan's build: the neighbourhood medians moved the refined depth of 42 % of the
    surfels by up to 3.4 mm. Here distances within ``rel_tol`` × the median nearest-
    neighbour spacing count as equal (a bucket of 0.3 µm at the tiny plan's 2.8 mm spacing,
    2000× the perturbation), and the candidates (``k + extra``, wider than a grid's tie
    group) are ordered by (bucket, index)."""
    from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

    n = len(points)
    kk = min(n, int(k) + int(extra))
    d, idx = KDTree(points).query(points, k=kk)
    d, idx = np.atleast_2d(d), np.atleast_2d(idx)
    if n < 2:
        return idx[:, :k]
    spacing = float(np.median(d[:, 1])) if d.shape[1] > 1 else 0.0
    q = np.round(d / max(rel_tol * spacing, 1e-300))
    order = np.lexsort((idx, q), axis=-1)
    return np.take_along_axis(idx, order, axis=1)[:, :k]


def _pca_normals(points, hull_normals, k):
    n = points.shape[0]
    if n < 3:
        return hull_normals.copy()
    k = min(max(int(k), 3), n)
    nb = stable_knn(points, k)
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
    images : V linear RGB (H, W, 3) float images (a (V, H, W, 3) array, a list, or any
        sequence of array-likes read on access, e.g. deferred photographs); RGBA is accepted
        and its alpha ignored. Non-finite pixels invalidate the patches that touch them.
        A view is read when a batch of surfels first needs it, and again only if the memory
        budget evicted it meanwhile (``stats["n_view_loads"]``); views no surfel scores
        are never read.
    alphas : V (H, W) mattes in [0, 1]; the silhouettes are ``α > config.alpha_threshold``.
        Each is read twice: once for the silhouettes and once (or as often as its image)
        for the cost volume.
    config : :class:`PhotoConfig`.
    exclude_views : view indices never used (a held-out view in leave-one-out).

    Returns
    -------
    positions : (N, 3) float64 refined centres (inside the hull of the silhouettes).
    normals : (N, 3) float64 unit normals (the input ones, or PCA with ``normals="pca"``).
    radii : (N,) float64 radii, grown where the refined surfels spread apart.
    stats : dict — ``depth_m`` (N,) inward displacement, ``confident`` (N,) bool, ``ncc``
        (N,) best NCC (NaN without two views), and counts/means/seconds, among them
        ``n_view_loads`` (photographs read), ``n_cost_batches`` and ``views_in_memory``
        (slots of grey and matte held, ≤ ``config.max_views_in_memory``).

    Notes
    -----
    Memory is O(``max_views_in_memory``·Hmax·Wmax) (8 bytes a pixel) + O(V·H·W/8) (packed
    silhouettes) + O(N·(V + n_depths)), independent of V in the pixels (see the module
    docstring); with ``keep_coverage`` the outline check adds (V, H, W) depth buffers.
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
    # indexed, never materialised: a list of deferred photographs stays deferred
    images = images if hasattr(images, "__getitem__") and hasattr(images, "__len__") else list(images)
    alphas = alphas if hasattr(alphas, "__getitem__") and hasattr(alphas, "__len__") else list(alphas)
    for name, arrays in (("images", images), ("alphas", alphas)):
        if len(arrays) != V:
            raise InputError(f"{len(arrays)} {name} for {V} cameras")
    cameras = list(cameras)
    sils = _silhouettes(alphas, cameras, config.alpha_threshold)

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
    cap = int(config.max_views_in_memory)
    scores, counts = _streamed_cost_volume(
        pos, nrm, cameras, images, alphas, views, step, spacing, config=config, cap=cap
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
        nb = stable_knn(pos, k)
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
    target = depth.copy()
    cov_h = None
    for _rnd in range(int(config.coverage_rounds) if config.keep_coverage else 1):
        depth = np.where(fixed, 0.0, target)
        if nb is not None:
            # the median keeps steps between neighbours; averaging tapers them (also towards
            # surfels held on the hull), since the renderer's ε-z-buffer shows a step as a
            # seam of partial coverage
            for _ in range(int(config.smooth_iters)):
                depth = depth[nb].mean(axis=1)
                depth[fixed] = 0.0
        # the hull test's silhouettes are 1 byte a pixel against the cost volume's 8
        new = _clamp_into_hull(pos, nrm, depth, sils, cameras, clamped, batch=8 * cap)
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
        **counts,
        "seconds_cost_volume": float(t_cost),
        "seconds": float(secs),
    }
    log.info(
        "photo refinement: %d/%d surfels confident, %d moved (mean %.3g m), %.2f s; "
        "%d photograph reads for %d views in %d batches, %d views in memory",
        stats["n_confident"],
        N,
        stats["n_moved"],
        stats["mean_depth_moved_m"],
        secs,
        counts["n_view_loads"],
        V,
        counts["n_cost_batches"],
        counts["views_in_memory"],
    )
    return new, out_n, out_r, stats
