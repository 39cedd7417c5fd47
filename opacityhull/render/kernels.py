"""Fast numba kernels of the renderer. Each has a slow NumPy twin in
:mod:`opacityhull.render.reference`; the tests compare them.

The kernels are serial ``@njit(cache=True, nogil=True, error_model="numpy")`` functions over an index range
(surfels ``i0:i1``, or every ``stride``-th band from ``b0``); :func:`parallel_for` runs
them on a thread pool. Measured here: numba ``parallel=True`` kernels took ~4× longer to
compile (≈90 s vs ≈24 s cold for this module on the shared 2-core machine) and their
OpenMP workers spin-wait, which collapsed throughput when the cores were oversubscribed;
plain threads releasing the GIL give the same parallelism without either cost.

Kernels
-------
* :func:`bounding_sphere` / :func:`block_bounds` — bounding spheres of the surfel
  cloud or of a block of consecutive surfels, for the lower bounds that let the ULR
  search stop early (exactly).
* :func:`ulr_kernel` (:func:`ulr_select` / :func:`ulr_shade`) — Unstructured-Lumigraph
  weights per surfel (k nearest *allowed* views by angle, Buehler 2001) or the blended
  premultiplied RGBA (bilinear fetch from the chosen views).
* :func:`splat_setup` — EWA resampling kernel per surfel (Zwicker 2001): screen centre,
  conic of ``M = J V Jᵀ + H``, normalisation ``|J| / (2π √|M|)``, bounding box, depth plane.
* :func:`bin_splats` / :func:`rasterize` — band-parallel
  two-pass ε-z-buffer splatting (depth pass, then accumulation) over the splat records
  listed per band of rows, returning the unnormalised accumulators;
  :func:`splat_bands` bins and runs it (or the deferred geometry pass, which draws the
  same fragments through the same helpers) over interleaved bands on threads.

Packed camera rows (``float64[21]``): ``R`` (cam_from_world rotation, row-major, 0–8),
``t`` (9–11), ``fx, fy, cx, cy`` (12–15), OpenCV distortion ``k1, k2, p1, p2, k3``
(16–20).

Splat records (``float32[SPLAT_FIELDS]``, one per surfel; see the ``S_*`` columns):
screen centre x, y (px), depth z (m), conic A, B, C of M⁻¹ (q = A dx² + 2B dx dy + C dy²),
kernel normalisation W, depth gradients dz/dx, dz/dy (m/px), depth clamp (m), ε (m),
inclusive pixel bounding box x0, x1, y0, y1 (exact small integers as floats), the
blended premultiplied RGBA written by :func:`ulr_shade`, and the surface area the surfel
stands for (m², for edge coverage). One 80-byte record per splat keeps each of the
rasteriser's reads to one or two cache lines, in increasing address order within a band —
scattered reads of separate arrays made it latency-bound (measured 2–3× slower).
"""

from __future__ import annotations

import math
import threading
from typing import NamedTuple

import numpy as np
from numba import njit

from .config import KMAX, default_threads  # KMAX: largest supported k

S_ONEHOT = 1e-14
"""``1 − cos θ`` below which a view's ray is taken to coincide with the desired ray
(θ ≲ 1.4e-7 rad). The ULR weight of a coinciding view diverges; the normalised limit is
one-hot, which is what the kernel returns. Off this threshold the weights already
differ from one-hot by O(θ²), so the switch is continuous to float precision."""

M_FLOOR = 1e-6
"""px² added to the resampling covariance so that an edge-on splat with no
prefilter (``filter=0``) still has an invertible conic."""

NO_COV = np.zeros((0, 6), np.float64)
"""The empty ``cov6`` of :func:`splat_setup`: isotropic discs."""

# splat record columns
S_X, S_Y, S_Z, S_A, S_B, S_C, S_W, S_DZX, S_DZY, S_ZDEV, S_ZEPS = range(11)
S_BX0, S_BX1, S_BY0, S_BY1 = range(11, 15)
S_RGBA = 15
S_AREA = 19
SPLAT_FIELDS = 20

ZDEV_FOOTPRINTS = 4.0
"""Fragment depths follow the splat's tangent plane but are clamped to ± this many
footprint radii of the centre depth (guards near-edge-on splats, whose plane
extrapolates far over the prefiltered footprint)."""


# --------------------------------------------------------------------------- helpers


@njit(cache=True, inline="always", error_model="numpy")
def _project(cams, c, x, y, z):
    """World point → (u, v, depth) through packed camera row ``c`` of ``cams``; u = v = nan
    behind it. (Indexing ``cams[c, j]`` rather than taking the row ``cams[c]``: a row slice
    is a new array object with reference counting, which made the ULR search ~1.5× slower.)"""
    X = cams[c, 0] * x + cams[c, 1] * y + cams[c, 2] * z + cams[c, 9]
    Y = cams[c, 3] * x + cams[c, 4] * y + cams[c, 5] * z + cams[c, 10]
    Z = cams[c, 6] * x + cams[c, 7] * y + cams[c, 8] * z + cams[c, 11]
    if not Z > 0.0:
        return np.nan, np.nan, Z
    iz = 1.0 / Z  # the winners' projections are ~20 % of shading (measured by ablation)
    xn = X * iz
    yn = Y * iz
    k1 = cams[c, 16]
    k2 = cams[c, 17]
    p1 = cams[c, 18]
    p2 = cams[c, 19]
    k3 = cams[c, 20]
    if k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0:
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        xn = xd
        yn = yd
    return cams[c, 12] * xn + cams[c, 14], cams[c, 13] * yn + cams[c, 15], Z


@njit(cache=True, inline="always", error_model="numpy")
def _before(s_a, r_a, s_b, r_b):
    """Strict order of candidates: smaller angle first, ties by the view's tie rank
    (its position when views are sorted by centre coordinates, so that the order of
    views in the model does not matter)."""
    return s_a < s_b or (s_a == s_b and r_a < r_b)


@njit(cache=True, inline="always", error_model="numpy")
def _weights(best_s, m, k, w):
    """ULR weights of a sorted candidate list (m ≥ 1) into ``w[:m]``.

    * coinciding ray(s) (s ≤ S_ONEHOT): one-hot (uniform among coinciding views);
    * k = 1 or m = 1: the nearest view alone;
    * m ≥ k: r_i = (s_k − s_i)/s_i for the k−1 nearest, the k-th is the threshold;
    * 2 ≤ m < k: threshold at θ = 180° (s = 2), i.e. r_i = (1 + cos θ_i)/(1 − cos θ_i)
      over all m, so the weights stay continuous in the desired view;
    * all penalties tie (Σr = 0): uniform over the m candidates.
    """
    for i in range(m):
        w[i] = 0.0
    if best_s[0] <= S_ONEHOT:
        c = 0
        for i in range(m):
            if best_s[i] <= S_ONEHOT:
                c += 1
        for i in range(c):
            w[i] = 1.0 / c
        return
    if k == 1 or m == 1:
        w[0] = 1.0
        return
    if m >= k:
        thr = best_s[k - 1]
        n = k - 1
    else:
        thr = 2.0
        n = m
    tot = 0.0
    for i in range(n):
        r = (thr - best_s[i]) / best_s[i]
        if r < 0.0:
            r = 0.0
        w[i] = r
        tot += r
    if tot > 0.0 and math.isfinite(tot):
        for i in range(n):
            w[i] /= tot
    else:
        for i in range(m):
            w[i] = 1.0 / m


@njit(cache=True, inline="always", error_model="numpy")
def _bilinear(texels, off, W, H, u, y):
    """Bilinear sample (4 values) of a premultiplied RGBA view at pixel (u, y) (pixel
    centres at integers, edge texels repeated over the half-pixel border). The weights
    and sums are float32 like the texels (measured ~10 % faster shading than float64;
    relative error ~1e-7)."""
    fx = math.floor(u)
    fy = math.floor(y)
    ax = np.float32(u - fx)
    ay = np.float32(y - fy)
    x0 = int(fx)
    y0 = int(fy)
    x1 = min(max(x0 + 1, 0), W - 1)
    y1 = min(max(y0 + 1, 0), H - 1)
    x0 = min(max(x0, 0), W - 1)
    y0 = min(max(y0, 0), H - 1)
    one = np.float32(1.0)
    w00 = (one - ax) * (one - ay)
    w01 = ax * (one - ay)
    w10 = (one - ax) * ay
    w11 = ax * ay
    i00 = off + y0 * W + x0
    i01 = off + y0 * W + x1
    i10 = off + y1 * W + x0
    i11 = off + y1 * W + x1
    c0 = w00 * texels[i00, 0] + w01 * texels[i01, 0] + w10 * texels[i10, 0] + w11 * texels[i11, 0]
    c1 = w00 * texels[i00, 1] + w01 * texels[i01, 1] + w10 * texels[i10, 1] + w11 * texels[i11, 1]
    c2 = w00 * texels[i00, 2] + w01 * texels[i01, 2] + w10 * texels[i10, 2] + w11 * texels[i11, 2]
    c3 = w00 * texels[i00, 3] + w01 * texels[i01, 3] + w10 * texels[i10, 3] + w11 * texels[i11, 3]
    return c0, c1, c2, c3


CHUNK = 1024
"""Surfels per task of :func:`parallel_for`."""


@njit(cache=True, nogil=True, error_model="numpy")
def bounding_sphere(positions):
    """Centre (bounding-box centre) and radius of the finite ``positions`` (N, 3)."""
    n = positions.shape[0]
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(n):
        ok = True
        for c in range(3):
            if not math.isfinite(positions[i, c]):
                ok = False
        if not ok:
            continue
        for c in range(3):
            p = positions[i, c]
            if p < lo[c]:
                lo[c] = p
            if p > hi[c]:
                hi[c] = p
    centre = np.zeros(3)
    if not (lo[0] <= hi[0] and lo[1] <= hi[1] and lo[2] <= hi[2]):
        return centre, 0.0
    for c in range(3):
        centre[c] = 0.5 * (lo[c] + hi[c])
    r2 = 0.0
    for i in range(n):
        a = positions[i, 0] - centre[0]
        b = positions[i, 1] - centre[1]
        d = positions[i, 2] - centre[2]
        v = a * a + b * b + d * d
        if v > r2 and math.isfinite(v):
            r2 = v
    return centre, math.sqrt(r2)


ULR_BLOCK = 512
"""Surfels per block of the ULR search: consecutive (Morton-sorted) surfels are close
together, so per-block bounds are much tighter than per-frame ones."""


@njit(cache=True, nogil=True, error_model="numpy")
def block_bounds(positions, i0, i1, desired_centre, view_centres, order, s_lb):
    """Scan order and lower bounds of s = 1 − cos θ (see
    :func:`opacityhull.render.views.scan_order`, the same bound) valid for surfels
    ``i0:i1``, computed from their bounding sphere. Writes ``order`` and ``s_lb`` (V,)."""
    lo0 = np.inf
    lo1 = np.inf
    lo2 = np.inf
    hi0 = -np.inf
    hi1 = -np.inf
    hi2 = -np.inf
    for i in range(i0, i1):
        x = positions[i, 0]
        y = positions[i, 1]
        z = positions[i, 2]
        if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
            lo0 = min(lo0, x)
            hi0 = max(hi0, x)
            lo1 = min(lo1, y)
            hi1 = max(hi1, y)
            lo2 = min(lo2, z)
            hi2 = max(hi2, z)
    V = view_centres.shape[0]
    if not lo0 <= hi0:
        for v in range(V):
            order[v] = v
            s_lb[v] = 0.0
        return
    o0 = 0.5 * (lo0 + hi0)
    o1 = 0.5 * (lo1 + hi1)
    o2 = 0.5 * (lo2 + hi2)
    rho = 0.5 * math.sqrt((hi0 - lo0) ** 2 + (hi1 - lo1) ** 2 + (hi2 - lo2) ** 2)
    a0 = desired_centre[0] - o0
    a1 = desired_centre[1] - o1
    a2 = desired_centre[2] - o2
    da = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    raw = np.empty(V)
    if not da > 0.0:
        for v in range(V):
            raw[v] = 0.0
    else:
        sc = math.asin(min(1.0, rho / da)) if da > rho else math.pi
        for v in range(V):
            b0 = view_centres[v, 0] - o0
            b1 = view_centres[v, 1] - o1
            b2 = view_centres[v, 2] - o2
            db = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
            if not db > 0.0:
                raw[v] = 0.0
                continue
            c = (a0 * b0 + a1 * b1 + a2 * b2) / (da * db)
            th = math.acos(min(1.0, max(-1.0, c)))
            sv = math.asin(min(1.0, rho / db)) if db > rho else math.pi
            lb = min(max(th - sc - sv - 1e-7, 0.0), math.pi)
            raw[v] = max(1.0 - math.cos(lb) - 1e-12, 0.0)
    idx = np.argsort(raw, kind="mergesort")
    for j in range(V):
        order[j] = idx[j]
        s_lb[j] = raw[idx[j]]


@njit(cache=True, nogil=True, error_model="numpy")
def ulr_kernel(
    positions,
    visibility,
    drawable,
    allowed,
    desired_centre,
    view_centres,
    view_cams,
    view_sizes,
    view_offsets,
    texels,
    order,
    s_lb,
    tie_rank,
    k,
    shade,
    out_rgba,
    rgba_col,
    ok,
    out_idx,
    out_w,
    out_uv,
    out_count,
    block,
    i0,
    i1,
):
    """ULR blending of surfels ``i0:i1``: the weights (``shade=False``) or the blended
    RGBA (``shade=True``). One kernel for both, so it compiles once.

    Per surfel p: the k nearest allowed views by the angle θ between the rays from p to
    the desired centre and to the view centre; a view must see p (visibility bit), not
    be excluded, and project p inside its image. Candidates are ordered by
    ``s = 1 − cos θ``, computed as ``|d − d_v|² / 2`` for unit rays d, d_v (no
    cancellation near θ = 0), ties broken by ``tie_rank``. The scan visits views in
    order of a lower bound of s and stops once the bound exceeds the current k-th best
    (exact). Fast path: choose by angle alone, then project the winners; only when a
    winner falls outside its image (rare: visibility bits come from in-image
    projections) is the search repeated with the image test on every candidate — both
    give the same list. Weights: :func:`_weights`. A surfel on the desired centre is not
    drawn.

    Parameters
    ----------
    positions : (N, 3) float32. visibility : (N, ceil(V/8)) uint8 packed bits.
    drawable : (N,) bool, surfels to process (the rest get ok = False / count = 0).
    allowed : (V,) uint8, 0 for excluded views. desired_centre : (3,) float64.
    view_centres : (V, 3) float64. view_cams : (V, 21) float64 packed cameras.
    view_sizes : (V, 2) int64 (width, height). view_offsets, texels : packed premultiplied
        RGBA (see :class:`~opacityhull.render.views.PreparedViews`).
    order, s_lb : (V,) scan order and its non-decreasing lower bounds of s = 1 − cos θ,
        valid for every surfel; used as given when ``block == 0``. With ``block > 0``
        they are recomputed (:func:`block_bounds`) for every ``block`` consecutive
        surfels, which is exact too and much tighter when the surfels are sorted.
    tie_rank : (V,) int64. k : int in [1, KMAX].

    Outputs (shade=True)
    --------------------
    out_rgba[i, rgba_col:rgba_col+4] : Σ w_j · bilinear(view_j, uv_j), premultiplied (an
    (N, 4) array with rgba_col = 0, or the splat records with rgba_col = S_RGBA).
    ok[i] : False where the surfel is not drawable or no allowed view sees it.

    Outputs (shade=False)
    ---------------------
    out_idx (N, k) int32 (−1 unused), out_w (N, k) float32, out_uv (N, k, 2) float32 pixel
    positions in the chosen views, out_count (N,) int32 candidates found (0 = not drawn).
    """
    best_s = np.empty(KMAX)
    best_v = np.empty(KMAX, np.int64)
    best_u = np.empty(KMAX)
    best_y = np.empty(KMAX)
    w = np.empty(KMAX)
    V = view_centres.shape[0]
    dcx = desired_centre[0]
    dcy = desired_centre[1]
    dcz = desired_centre[2]
    if block > 0:
        order = np.empty(V, np.int64)
        s_lb = np.empty(V)
    for i in range(i0, i1):
        if block > 0 and (i - i0) % block == 0:
            block_bounds(positions, i, min(i1, i + block), desired_centre, view_centres, order, s_lb)
        if shade:
            ok[i] = False
        else:
            out_count[i] = 0
            for j in range(k):
                out_idx[i, j] = -1
                out_w[i, j] = 0.0
                out_uv[i, j, 0] = np.nan
                out_uv[i, j, 1] = np.nan
        if not drawable[i]:
            continue
        # the k nearest allowed views (see the docstring); written out here rather than
        # called: as a separate function (inlined by numba or not) the search measured
        # 10–50 % slower
        px = np.float64(positions[i, 0])
        py = np.float64(positions[i, 1])
        pz = np.float64(positions[i, 2])
        dx = dcx - px
        dy = dcy - py
        dz = dcz - pz
        nd = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not nd > 0.0:
            continue  # the surfel sits on the desired centre
        inv = 1.0 / nd
        dx *= inv
        dy *= inv
        dz *= inv
        m = 0
        for strict in range(2):
            m = 0
            for j in range(V):
                if m == k and s_lb[j] > best_s[k - 1]:
                    break  # every later view is provably farther (sorted lower bounds)
                v = order[j]
                if allowed[v] == 0 or (visibility[i, v >> 3] >> (v & 7)) & 1 == 0:
                    continue
                ex = view_centres[v, 0] - px
                ey = view_centres[v, 1] - py
                ez = view_centres[v, 2] - pz
                ne = math.sqrt(ex * ex + ey * ey + ez * ez)
                if not ne > 0.0:
                    continue
                inv = 1.0 / ne
                ex = ex * inv - dx
                ey = ey * inv - dy
                ez = ez * inv - dz
                s = 0.5 * (ex * ex + ey * ey + ez * ez)  # 1 − cos θ without cancellation
                rv = tie_rank[v]
                if m == k and not _before(s, rv, best_s[k - 1], tie_rank[best_v[k - 1]]):
                    continue
                u = 0.0
                yy = 0.0
                if strict == 1:
                    u, yy, zc = _project(view_cams, v, px, py, pz)
                    if not (u >= -0.5 and u <= view_sizes[v, 0] - 0.5 and yy >= -0.5 and yy <= view_sizes[v, 1] - 0.5):
                        continue
                pos = m if m < k else k - 1  # insertion, dropping the last when full
                while pos > 0 and _before(s, rv, best_s[pos - 1], tie_rank[best_v[pos - 1]]):
                    if pos < k:
                        best_s[pos] = best_s[pos - 1]
                        best_v[pos] = best_v[pos - 1]
                        best_u[pos] = best_u[pos - 1]
                        best_y[pos] = best_y[pos - 1]
                    pos -= 1
                best_s[pos] = s
                best_v[pos] = v
                best_u[pos] = u
                best_y[pos] = yy
                if m < k:
                    m += 1
            if strict == 1:
                break
            # fast path: chosen by angle alone; project the winners, and only when one
            # falls outside its image search again with the image test on every candidate
            inside = True
            for j in range(m):
                v = best_v[j]
                u, yy, zc = _project(view_cams, v, px, py, pz)
                best_u[j] = u
                best_y[j] = yy
                if not (u >= -0.5 and u <= view_sizes[v, 0] - 0.5 and yy >= -0.5 and yy <= view_sizes[v, 1] - 0.5):
                    inside = False
            if inside:
                break
        if m <= 0:
            continue
        _weights(best_s, m, k, w)
        if not shade:
            out_count[i] = m
            for j in range(m):
                out_idx[i, j] = best_v[j]
                out_w[i, j] = w[j]
                out_uv[i, j, 0] = best_u[j]
                out_uv[i, j, 1] = best_y[j]
            continue
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        for j in range(m):
            if w[j] > 0.0:
                v = best_v[j]
                c0, c1, c2, c3 = _bilinear(
                    texels, view_offsets[v], view_sizes[v, 0], view_sizes[v, 1], best_u[j], best_y[j]
                )
                a0 += w[j] * c0
                a1 += w[j] * c1
                a2 += w[j] * c2
                a3 += w[j] * c3
        out_rgba[i, rgba_col] = a0
        out_rgba[i, rgba_col + 1] = a1
        out_rgba[i, rgba_col + 2] = a2
        out_rgba[i, rgba_col + 3] = a3
        ok[i] = True


_NO_I32 = np.zeros((0, 1), np.int32)
_NO_F32_2 = np.zeros((0, 1), np.float32)
_NO_F32_3 = np.zeros((0, 1, 2), np.float32)
_NO_I32_1 = np.zeros(0, np.int32)
_NO_BOOL = np.zeros(0, np.bool_)
_NO_TEX = np.zeros((0, 4), np.float32)
_NO_OFF = np.zeros(0, np.int64)


class UlrHead(NamedTuple):
    """The arguments :func:`ulr_select` and :func:`ulr_shade` share (see :func:`ulr_kernel`):
    the points and their visibility, which are drawn, and the views."""

    positions: np.ndarray
    visibility: np.ndarray
    drawable: np.ndarray
    allowed: np.ndarray
    desired_centre: np.ndarray
    view_centres: np.ndarray
    view_cams: np.ndarray
    view_sizes: np.ndarray


def ulr_select(head: UlrHead, order, s_lb, tie_rank, k, out_idx, out_w, out_uv, out_count, i0, i1, block=ULR_BLOCK):
    """ULR weights of surfels ``i0:i1`` (see :func:`ulr_kernel`, ``shade=False``)."""
    no_shade = (_NO_OFF, _NO_TEX, order, s_lb, tie_rank, k, False, _NO_F32_2, 0, _NO_BOOL)
    ulr_kernel(*head, *no_shade, out_idx, out_w, out_uv, out_count, block, i0, i1)


def ulr_shade(
    head: UlrHead, view_offsets, texels, order, s_lb, tie_rank, k, out_rgba, rgba_col, ok, i0, i1, block=ULR_BLOCK
):
    """ULR-blended premultiplied RGBA of surfels ``i0:i1`` (see :func:`ulr_kernel`, ``shade=True``)."""
    shade = (view_offsets, texels, order, s_lb, tie_rank, k, True, out_rgba, rgba_col, ok)
    ulr_kernel(*head, *shade, _NO_I32, _NO_F32_2, _NO_F32_3, _NO_I32_1, block, i0, i1)


@njit(cache=True, nogil=True, error_model="numpy")
def bilinear_fetch(texels, offset, width, height, uv, out):
    """Bilinear samples of one packed premultiplied view at (N, 2) pixel positions into out (N, 4)."""
    for i in range(uv.shape[0]):
        c0, c1, c2, c3 = _bilinear(texels, offset, width, height, uv[i, 0], uv[i, 1])
        out[i, 0] = c0
        out[i, 1] = c1
        out[i, 2] = c2
        out[i, 3] = c3


@njit(cache=True, nogil=True, error_model="numpy")
def splat_setup(
    positions,
    normals,
    radii,
    areas,
    cam,
    width,
    height,
    sigma_radius,
    filter_var,
    cutoff,
    eps_z,
    cull_backfaces,
    cov6,
    out_splat,
    valid,
    i0,
    i1,
):
    """EWA resampling kernel of every surfel in the desired (pinhole) camera.

    The surfel's tangent disc carries an isotropic Gaussian ``V = (sigma_radius·r)² I``.
    With ``P`` the 2×3 derivative of the pinhole projection at the surfel's camera-frame
    position and ``T`` any orthonormal tangent basis, ``J = P T`` and, because V is
    isotropic, ``J V Jᵀ = σ² P (I − n nᵀ) Pᵀ`` — no tangent frame needed. The
    resampling kernel is ``M = J V Jᵀ + H`` with ``H = filter_var·I`` (px²). A pixel at
    offset d gets weight ``|J| / (2π √|M|) · exp(−½ dᵀ M⁻¹ d)`` within ``dᵀM⁻¹d ≤
    cutoff²``. Depth over the splat follows the tangent plane (linearised at the
    centre). With the footprint radius ``f = cutoff·√λmax(M)·z/f̄`` (metres: the cutoff
    ellipse's major semi-axis back-projected to the surfel's depth, ≈ r when magnified,
    the prefilter's reach when minified), depths are clamped to ``±ZDEV_FOOTPRINTS·f``
    and the ε-z tolerance is ``eps_z·f``: scaling ε with r alone discarded most
    same-surface fragments of minified splats (measured: interior coverage 0.5).
    ``areas`` (m² of surface per surfel) is copied for the coverage channel.

    Anisotropic splats (statistical nodes, :mod:`opacityhull.render.spg`): with ``cov6``
    (N, 6) — a radius tensor ``R²`` (xx, xy, xz, yy, yz, zz, m², object frame; a disc is
    ``r² (I − n nᵀ)``) — the kernel is ``σ² P R² Pᵀ + H`` instead (``radii`` then only
    gate validity); the empty :data:`NO_COV` keeps the isotropic disc.

    Processes surfels ``i0:i1``: writes ``valid[i]`` (False when behind the camera,
    facing away, degenerate, or without a pixel centre inside its cutoff ellipse) and the
    geometry columns of ``out_splat`` (N, SPLAT_FIELDS) float32, including the inclusive
    pixel ranges x0..x1, y0..y1 of the cutoff ellipse's bounding box clipped to the image.
    """
    fx = cam[12]
    fy = cam[13]
    cx = cam[14]
    cy = cam[15]
    two_pi = 2.0 * math.pi
    # camera centre −Rᵀt: back faces (about half of a closed surface) are culled in the
    # world frame before any projection work
    ccx = -(cam[0] * cam[9] + cam[3] * cam[10] + cam[6] * cam[11])
    ccy = -(cam[1] * cam[9] + cam[4] * cam[10] + cam[7] * cam[11])
    ccz = -(cam[2] * cam[9] + cam[5] * cam[10] + cam[8] * cam[11])
    aniso = cov6.shape[0] > 0
    for i in range(i0, i1):
        valid[i] = False
        px = np.float64(positions[i, 0])
        py = np.float64(positions[i, 1])
        pz = np.float64(positions[i, 2])
        r = np.float64(radii[i])
        if not (r > 0.0 and math.isfinite(r) and math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            continue
        ax = np.float64(normals[i, 0])
        ay = np.float64(normals[i, 1])
        az = np.float64(normals[i, 2])
        nn2 = ax * ax + ay * ay + az * az
        has_normal = nn2 > 1e-24 and math.isfinite(nn2)
        # the sign test needs no unit normal: back faces leave before the square root
        if cull_backfaces and has_normal and ax * (px - ccx) + ay * (py - ccy) + az * (pz - ccz) >= 0.0:
            continue
        nn = math.sqrt(nn2)
        X = cam[0] * px + cam[1] * py + cam[2] * pz + cam[9]
        Y = cam[3] * px + cam[4] * py + cam[5] * pz + cam[10]
        Z = cam[6] * px + cam[7] * py + cam[8] * pz + cam[11]
        if not Z > 1e-9:
            continue
        if has_normal:
            inn = 1.0 / nn
            n0 = (cam[0] * ax + cam[1] * ay + cam[2] * az) * inn
            n1 = (cam[3] * ax + cam[4] * ay + cam[5] * az) * inn
            n2 = (cam[6] * ax + cam[7] * ay + cam[8] * az) * inn
        else:  # no usable normal: a disc facing the camera
            d = -1.0 / math.sqrt(X * X + Y * Y + Z * Z)
            n0 = X * d
            n1 = Y * d
            n2 = Z * d
        ndp = n0 * X + n1 * Y + n2 * Z  # n · (p − camera centre); < 0 when facing the camera
        if cull_backfaces and ndp >= 0.0:
            continue
        iz = 1.0 / Z
        a0 = fx * iz
        a2 = -fx * X * iz * iz
        b1 = fy * iz
        b2 = -fy * Y * iz * iz
        pn0 = a0 * n0 + a2 * n2
        pn1 = b1 * n1 + b2 * n2
        j00 = a0 * a0 + a2 * a2 - pn0 * pn0
        j01 = a2 * b2 - pn0 * pn1
        j11 = b1 * b1 + b2 * b2 - pn1 * pn1
        detjj = j00 * j11 - j01 * j01
        detj = math.sqrt(detjj) if detjj > 0.0 else 0.0
        if aniso:
            # P R² Pᵀ with R² rotated into the camera frame (P = [[a0, 0, a2], [0, b1, b2]])
            s2 = sigma_radius * sigma_radius
            c00, c01, c02 = cov6[i, 0], cov6[i, 1], cov6[i, 2]
            c11, c12, c22 = cov6[i, 3], cov6[i, 4], cov6[i, 5]
            # rows of P·R (R = cam rotation): p0 = a0·R[0] + a2·R[2], p1 = b1·R[1] + b2·R[2]
            p00 = a0 * cam[0] + a2 * cam[6]
            p01 = a0 * cam[1] + a2 * cam[7]
            p02 = a0 * cam[2] + a2 * cam[8]
            p10 = b1 * cam[3] + b2 * cam[6]
            p11 = b1 * cam[4] + b2 * cam[7]
            p12 = b1 * cam[5] + b2 * cam[8]
            q00 = c00 * p00 + c01 * p01 + c02 * p02
            q01 = c01 * p00 + c11 * p01 + c12 * p02
            q02 = c02 * p00 + c12 * p01 + c22 * p02
            q10 = c00 * p10 + c01 * p11 + c02 * p12
            q11 = c01 * p10 + c11 * p11 + c12 * p12
            q12 = c02 * p10 + c12 * p11 + c22 * p12
            g00 = p00 * q00 + p01 * q01 + p02 * q02
            g01 = p10 * q00 + p11 * q01 + p12 * q02
            g11 = p10 * q10 + p11 * q11 + p12 * q12
        else:
            s2 = (sigma_radius * r) ** 2
            g00 = j00
            g01 = j01
            g11 = j11
        m00 = s2 * g00 + filter_var + M_FLOOR
        m01 = s2 * g01
        m11 = s2 * g11 + filter_var + M_FLOOR
        detm = m00 * m11 - m01 * m01
        if not (detm > 0.0 and math.isfinite(detm)):
            continue
        x0 = fx * X * iz + cx
        y0 = fy * Y * iz + cy
        hx = cutoff * math.sqrt(m00)
        hy = cutoff * math.sqrt(m11)
        lo_x = max(x0 - hx, 0.0)
        hi_x = min(x0 + hx, width - 1.0)
        lo_y = max(y0 - hy, 0.0)
        hi_y = min(y0 + hy, height - 1.0)
        if not (lo_x <= hi_x and lo_y <= hi_y):
            continue
        bx0 = int(math.ceil(lo_x))
        bx1 = int(math.floor(hi_x))
        by0 = int(math.ceil(lo_y))
        by1 = int(math.floor(hi_y))
        if bx0 > bx1 or by0 > by1:
            continue
        if abs(ndp) > 1e-12 * Z:
            g = -Z * Z / ndp
            dzx = g * n0 / fx
            dzy = g * n1 / fy
        else:
            dzx = 0.0
            dzy = 0.0
        out_splat[i, S_X] = x0
        out_splat[i, S_Y] = y0
        out_splat[i, S_Z] = Z
        idet = 1.0 / detm
        out_splat[i, S_A] = m11 * idet
        out_splat[i, S_B] = -m01 * idet
        out_splat[i, S_C] = m00 * idet
        out_splat[i, S_W] = detj * math.sqrt(idet) / two_pi
        out_splat[i, S_DZX] = dzx
        out_splat[i, S_DZY] = dzy
        # footprint radius: the cutoff ellipse's major semi-axis back-projected to the
        # surfel's depth (≈ r when magnified, the prefilter's extent when minified)
        lmax = 0.5 * (m00 + m11) + math.sqrt(0.25 * (m00 - m11) ** 2 + m01 * m01)
        foot = cutoff * math.sqrt(lmax) * Z * 2.0 / (fx + fy)
        out_splat[i, S_ZDEV] = ZDEV_FOOTPRINTS * foot
        out_splat[i, S_ZEPS] = eps_z * foot
        out_splat[i, S_BX0] = bx0
        out_splat[i, S_BX1] = bx1
        out_splat[i, S_BY0] = by0
        out_splat[i, S_BY1] = by1
        for c in range(S_RGBA, S_RGBA + 4):
            out_splat[i, c] = 0.0
        out_splat[i, S_AREA] = areas[i]
        valid[i] = True


EXP_LUT_SIZE = 1024


def exp_table(cutoff: float) -> np.ndarray:
    """exp(−q/2) sampled at q = i·cutoff²/EXP_LUT_SIZE, i = 0..EXP_LUT_SIZE+1 (float64),
    linearly interpolated by the rasteriser (relative error < 1e-6 for cutoff ≤ 3)."""
    q = np.arange(EXP_LUT_SIZE + 2) * (cutoff * cutoff / EXP_LUT_SIZE)
    return np.exp(-0.5 * q)


@njit(cache=True, nogil=True, error_model="numpy")
def bin_splats(splat, draw, height, band_h):
    """CSR lists of the splats overlapping each band of ``band_h`` rows, in ``draw`` order.

    Returns counts (n_bands + 1,) int64 offsets and lists (L,) int64 surfel indices.
    The records are read once (their band ranges kept in a compact array for the second
    pass): re-reading the scattered 80-byte records cost as much as the first pass.
    """
    nb = (height + band_h - 1) // band_h
    nd = draw.shape[0]
    counts = np.zeros(nb + 1, np.int64)
    bands = np.empty((nd, 2), np.int32)
    for t in range(nd):
        i = draw[t]
        b0 = int(splat[i, S_BY0]) // band_h
        b1 = int(splat[i, S_BY1]) // band_h
        bands[t, 0] = b0
        bands[t, 1] = b1
        for b in range(b0, b1 + 1):
            counts[b + 1] += 1
    for b in range(nb):
        counts[b + 1] += counts[b]
    lists = np.empty(counts[nb], np.int64)
    fill = counts[:nb].copy()
    for t in range(nd):
        i = draw[t]
        for b in range(bands[t, 0], bands[t, 1] + 1):
            lists[fill[b]] = i
            fill[b] += 1
    return counts, lists


@njit(cache=True, inline="always", error_model="numpy")
def _band_constants(counts, cutoff, lut):
    """Number of bands, cutoff² and the exp table's index scale of a rasteriser call
    (:func:`rasterize`, :func:`~opacityhull.render.deferred.rasterize_geometry`)."""
    c2 = np.float64(cutoff) * np.float64(cutoff)
    return counts.shape[0] - 1, c2, (lut.shape[0] - 2) / c2


@njit(cache=True, inline="always", error_model="numpy")
def _band_rows(b, band_h, height):
    """First and last row of band ``b``."""
    ylo = b * band_h
    return ylo, min(height - 1, ylo + band_h - 1)


@njit(cache=True, inline="always", error_model="numpy")
def _splat_geometry(splat, i, ylo, yhi):
    """Record ``i``'s centre (px), depth (m), conic A, 2B, C, depth gradients, depth
    clamp range, column range and row range within rows ``ylo..yhi`` (inclusive), as the
    rasteriser's two passes both need them."""
    z0 = np.float64(splat[i, S_Z])
    dev = np.float64(splat[i, S_ZDEV])
    return (
        np.float64(splat[i, S_X]),
        np.float64(splat[i, S_Y]),
        z0,
        np.float64(splat[i, S_A]),
        2.0 * np.float64(splat[i, S_B]),
        np.float64(splat[i, S_C]),
        np.float64(splat[i, S_DZX]),
        np.float64(splat[i, S_DZY]),
        z0 - dev,
        z0 + dev,
        int(splat[i, S_BX0]),
        int(splat[i, S_BX1]),
        max(int(splat[i, S_BY0]), ylo),
        min(int(splat[i, S_BY1]), yhi),
    )


@njit(cache=True, inline="always", error_model="numpy")
def _row_terms(y, y0, B2, C, z0, dzy):
    """Row ``y``'s part of a splat's footprint: 2B·dy, C·dy² and the tangent-plane depth
    at the centre column (dy = y − y0), shared by every pixel of the row."""
    dy = y - y0
    return B2 * dy, C * dy * dy, z0 + dzy * dy


@njit(cache=True, inline="always")
def _fragment(A, tt, cdy, dx, zrow, dzx, zlo, zhi):
    """Mahalanobis distance q and clamped tangent-plane depth (float64) of the pixel
    ``dx`` columns off a splat's centre in a row (:func:`_row_terms`): the one
    footprint both rasteriser passes test."""
    return (A * dx + tt) * dx + cdy, min(max(zrow + dzx * dx, zlo), zhi)


@njit(cache=True, inline="always", error_model="numpy")
def _depth_pass(splat, lists, t0, t1, ylo, yhi, c2, zlim):  # pragma: no cover - compiled
    """Pass 1 of the ε-z-buffer over surfels ``lists[t0:t1]`` in rows ``ylo..yhi``:
    ``zlim = min(zlim, z + ε)`` for fragments with ``q ≤ c2``."""
    inf32 = np.float32(np.inf)
    for t in range(t0, t1):
        i = lists[t]
        x0, y0, z0, A, B2, C, dzx, dzy, zlo, zhi, xa, xb, ya, yb = _splat_geometry(splat, i, ylo, yhi)
        eps = np.float64(splat[i, S_ZEPS])
        for y in range(ya, yb + 1):
            tt, cdy, zrow = _row_terms(y, y0, B2, C, z0, dzy)
            for x in range(xa, xb + 1):
                q, z = _fragment(A, tt, cdy, x - x0, zrow, dzx, zlo, zhi)
                zl = np.float32(z + eps) if q <= c2 else inf32
                zlim[y, x] = min(zlim[y, x], zl)


@njit(cache=True, inline="always")
def _ewa_weight(A, tt, cdy, dx, zrow, dzx, zlo, zhi, c2, lut, lut_scale, w0):
    """A splat's Mahalanobis distance q, clamped depth z and (unmasked) weight at one
    pixel of a row: shared by the colour rasteriser and the deferred geometry pass, so
    both draw exactly the same footprint."""
    q, zd = _fragment(A, tt, cdy, dx, zrow, dzx, zlo, zhi)
    z = np.float32(zd)
    f = min(q, c2) * lut_scale
    j = int(f)
    f -= j
    w = w0 * np.float32(lut[j] + f * (lut[j + 1] - lut[j]))
    return q, z, w


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def rasterize(splat, lists, counts, height, width, cutoff, band_h, lut, accum, zlim, b0, stride):
    """Two-pass ε-z-buffer splatting of binned splat records.

    ``splat[lists[counts[b]:counts[b+1]]]`` are the records overlapping band b (rows
    ``b·band_h … b·band_h + band_h − 1``) in surfel order (:func:`bin_splats`); they are
    read in place — copying them into band order first measured slower in total (the
    copy cost more than the rasteriser saved on its reads, which go forward through
    memory within a band). This call processes bands
    ``b0, b0 + stride, …`` into ``accum`` / ``zlim`` (preallocated, zero / +inf); bands own
    their pixels, so threads given different ``b0`` never race, and the accumulation
    order at every pixel is the surfel order (deterministic, equal to the reference's).

    Pass 1: ``zlim = min over fragments of (z + ε)`` for fragments with ``q ≤ cutoff²``.
    Pass 2: fragments with ``q ≤ cutoff²`` and ``z ≤ zlim`` accumulate
    ``w = W·exp(−q/2)`` (``lut`` from :func:`exp_table`, linear interpolation) times
    RGBA, w, w·z and w·area. The inner loops are branch-free (a fragment outside adds 0).

    Outputs
    -------
    accum : (H, W, 7) float32: Σw·r, Σw·g, Σw·b, Σw·a (premultiplied), Σw, Σw·z, Σw·area
        (the coverage: ≈ 1 where the surface covers the pixel's filter footprint).
    zlim : (H, W) float32 front depth + ε (inf where nothing was drawn).
    """
    nb, c2, lut_scale = _band_constants(counts, cutoff, lut)
    zero32 = np.float32(0.0)
    for b in range(b0, nb, stride):
        ylo, yhi = _band_rows(b, band_h, height)
        _depth_pass(splat, lists, counts[b], counts[b + 1], ylo, yhi, c2, zlim)
        for t in range(counts[b], counts[b + 1]):
            i = lists[t]
            x0, y0, z0, A, B2, C, dzx, dzy, zlo, zhi, xa, xb, ya, yb = _splat_geometry(splat, i, ylo, yhi)
            w0 = splat[i, S_W]
            r0 = splat[i, S_RGBA]
            r1 = splat[i, S_RGBA + 1]
            r2 = splat[i, S_RGBA + 2]
            r3 = splat[i, S_RGBA + 3]
            ar = splat[i, S_AREA]
            for y in range(ya, yb + 1):
                tt, cdy, zrow = _row_terms(y, y0, B2, C, z0, dzy)
                for x in range(xa, xb + 1):
                    q, z, w = _ewa_weight(A, tt, cdy, x - x0, zrow, dzx, zlo, zhi, c2, lut, lut_scale, w0)
                    w = w if (q <= c2 and z <= zlim[y, x]) else zero32
                    accum[y, x, 0] += w * r0
                    accum[y, x, 1] += w * r1
                    accum[y, x, 2] += w * r2
                    accum[y, x, 3] += w * r3
                    accum[y, x, 4] += w
                    accum[y, x, 5] += w * z
                    accum[y, x, 6] += w * ar


@njit(cache=True, nogil=True, error_model="numpy")
def resolve(accum, coverage_full, edge_coverage, alpha_min, out_rgba, out_depth, out_weight, out_cov, y0, y1):
    """EWA normalisation of rows ``y0:y1`` of the accumulators (the fast twin of
    :func:`opacityhull.render.renderer.coverage_from` + :func:`~opacityhull.render.renderer.normalise`).

    Per pixel with Σw > 0: coverage ``c = clip(Σw·A / coverage_full, 0, 1)`` (edge
    coverage) or 1; premultiplied RGBA ``Σw·rgba / Σw · c``; alpha clipped to [0, 1];
    straight colour = premultiplied / α where α ≥ ``alpha_min``, else 0; depth
    ``Σw·z / Σw``. Pixels with Σw = 0: RGBA 0, depth +inf, coverage 0.

    accum : (H, W, 7) float32 from :func:`rasterize`. Outputs (H, W, 4), (H, W), (H, W),
    (H, W) float32.
    """
    W = accum.shape[1]
    inv_full = np.float32(1.0 / coverage_full)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    amin = np.float32(alpha_min)
    for y in range(y0, y1):
        for x in range(W):
            ws = accum[y, x, 4]
            out_weight[y, x] = ws
            if not ws > zero:
                out_rgba[y, x, 0] = zero
                out_rgba[y, x, 1] = zero
                out_rgba[y, x, 2] = zero
                out_rgba[y, x, 3] = zero
                out_depth[y, x] = np.inf
                out_cov[y, x] = zero
                continue
            c = min(max(accum[y, x, 6] * inv_full, zero), one) if edge_coverage else one
            out_cov[y, x] = c
            inv = one / ws
            out_depth[y, x] = accum[y, x, 5] * inv
            s = inv * c
            a = min(max(accum[y, x, 3] * s, zero), one)
            out_rgba[y, x, 3] = a
            if a >= amin:
                s = s / a
                out_rgba[y, x, 0] = accum[y, x, 0] * s
                out_rgba[y, x, 1] = accum[y, x, 1] * s
                out_rgba[y, x, 2] = accum[y, x, 2] * s
            else:
                out_rgba[y, x, 0] = zero
                out_rgba[y, x, 1] = zero
                out_rgba[y, x, 2] = zero


# --------------------------------------------------------------------------- threads

_POOL = None


def _pool():
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max_workers=max(2, default_threads()), thread_name_prefix="opacityhull-render")
    return _POOL


def parallel_for(fn, n: int, args: tuple, *, threads: int = 1, chunk: int = CHUNK) -> None:
    """Run ``fn(*args, i0, i1)`` over ``[0, n)`` in chunks on ``threads`` threads
    (``fn`` is a nogil kernel; each chunk writes disjoint outputs)."""
    if threads <= 1 or n <= chunk:
        fn(*args, 0, n)
        return
    step = max(chunk, -(-n // (4 * threads)))  # ~4 tasks per thread for balance
    futs = [_pool().submit(fn, *args, i0, min(n, i0 + step)) for i0 in range(0, n, step)]
    for f in futs:
        f.result()


class Scratch(threading.local):
    """Per-thread work arrays reused from frame to frame.

    The renderer's per-frame buffers (splat records: 80 B per surfel; band lists;
    accumulators) are tens of MB; fresh ones come from ``mmap`` and are page-faulted in
    on first touch each frame (measured: 40 MB fresh + filled 9.5 ms, refilled 4.9 ms).
    Buffers grow by 25 % when too small and are never shrunk; :meth:`clear` frees them.
    Arrays handed out are views into the buffers: valid until the same name is asked for
    again on this thread, so nothing returned to a caller may be one of them.
    """

    def __init__(self):
        self._bufs = {}

    def get(self, name: str, shape, dtype) -> np.ndarray:
        shape = tuple(int(x) for x in shape)
        n = 1
        for x in shape:
            n *= x
        dtype = np.dtype(dtype)
        buf = self._bufs.get(name)
        if buf is None or buf.dtype != dtype or buf.size < n:
            grown = int(1.25 * buf.size) if buf is not None and buf.dtype == dtype else 0
            buf = np.empty(max(n, grown, 1), dtype)
            self._bufs[name] = buf
        return buf[:n].reshape(shape)

    def clear(self) -> None:
        self._bufs.clear()


SCRATCH = Scratch()
"""The renderer's per-thread :class:`Scratch` (``SCRATCH.clear()`` releases the memory)."""


def filled(scratch: Scratch | None, name: str, shape, dtype, value) -> np.ndarray:
    """``np.full(shape, value, dtype)``; with ``scratch``, its buffer ``name`` refilled
    with ``value`` (see :meth:`Scratch.get` for how long it stays valid)."""
    if scratch is None:
        # zeros come from calloc: pages the rasteriser never reaches are never written
        return np.zeros(shape, dtype) if value == 0 else np.full(shape, value, dtype)
    buf = scratch.get(name, shape, dtype)
    buf.fill(value)
    return buf


def splat_bands(raster, splat, draw, height, width, cutoff, band_h, outputs: tuple, *, threads: int = 1) -> None:
    """Bin the drawn splats into bands of ``band_h`` rows (:func:`bin_splats`) and run
    ``raster(splat, lists, counts, height, width, cutoff, band_h, lut, *outputs, b0,
    stride)`` over them (:func:`rasterize`, or
    :func:`~opacityhull.render.deferred.rasterize_geometry`) on ``threads`` threads,
    each taking every ``stride``-th band: interleaved bands balance the load when the
    object fills only part of the frame, and bands own their pixels, so the threads
    never race."""
    counts, lists = bin_splats(splat, draw, height, band_h)
    args = (splat, lists, counts, height, width, cutoff, band_h, exp_table(cutoff), *outputs)
    nb = counts.shape[0] - 1
    if threads <= 1 or nb < 2:
        raster(*args, 0, 1)
        return
    T = min(threads, nb)
    futs = [_pool().submit(raster, *args, t, T) for t in range(T)]
    for f in futs:
        f.result()


def splat_frame(splat, draw, height, width, cutoff, band_h, *, threads: int = 1, scratch: Scratch | None = None):
    """Bin and rasterise the drawn splats. Returns (accum (H, W, 7), zlim); with
    ``scratch`` they live in its buffers."""
    accum = filled(scratch, "accum", (height, width, 7), np.float32, 0.0)
    zlim = filled(scratch, "zlim", (height, width), np.float32, np.inf)
    splat_bands(rasterize, splat, draw, height, width, cutoff, band_h, (accum, zlim), threads=threads)
    return accum, zlim
