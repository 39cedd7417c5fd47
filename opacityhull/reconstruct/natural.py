"""Reflectance fields from natural illumination (Matusik, Loper & Pfister 2004).

The object is a linear "black box" between the illumination shown on a display and the
camera, ``B = T L`` ("Light Transport Model" in Pfister's talk): ``L`` is the display
image (the *illumination domain*, ``H_d × W_d`` display pixels), ``B`` the photograph,
and row ``T_i`` of the transport matrix is pixel i's reflectance function over the
display. Each row is approximated by K axis-aligned box kernels,

    T_i ≈ Σ_k w_{k,i} R_{k,i},

estimated independently per pixel from N displayed natural images ``L_j`` and their
photographs ``b_{i,j}`` by non-negative least squares

    argmin_w ‖A_i w − B_i‖²  subject to  w ≥ 0,      A_i[j, k] = R_{k,i} • L_j,

with the kernels found by hierarchical subdivision: start with one kernel covering the
whole display; at every step try, for *every* current kernel, a split into two equal
halves across x and across y, re-solve the NNLS for each of those 2m candidate kernel
sets, and keep the one candidate with the lowest error. Stop after K kernels (K − 1
splits) or when the error is below a threshold (``rel_tol``). Relighting under a new
display image is ``b_i = Σ_k w_{k,i} (R_{k,i} • L)``.

Implementation choices (and why):

* Kernels are box *means*, not sums (``A[j, k]`` is the mean of ``L_j`` over the box):
  the same model up to a column scale (NNLS is invariant to positive column scaling), but
  the weights become "fraction of the box's light reaching the pixel", O(1) for every
  kernel size, so they survive float16 storage and the NNLS is better conditioned.
* Every input image has a summed-area table (SAT), laid out ``(H_d+1, W_d+1, N, C)`` so
  that one kernel's column over all N images is four contiguous reads.
* The NNLS is Lawson–Hanson on the normal equations (``G = AᵀA``, ``h = Aᵀb``), a
  numba kernel with a Cholesky solve of the passive set per step. A column whose
  Cholesky pivot vanishes (identical images, a box that is black in every image, N < K)
  is linearly dependent on the passive set and is excluded, so rank-deficient systems
  stay finite; the fitted ``A @ w`` is unique even when ``w`` is not. A candidate split
  only changes one kernel into two, so its Gram matrix is the current one with one row
  and column replaced and one appended (2·N·m dot products), and the solve is warm
  started from the current weights split in proportion to the halves' areas (the same
  prediction), which makes most candidate solves one or two Cholesky steps.
* Colour: the kernels are shared by the channels (one reflectance function support per
  pixel, as in the paper's figures) and the weights are per channel; the split error is
  the sum over channels of the per-channel NNLS residuals.
* Progressive refinement (:class:`NaturalEstimator`): images can be added in batches;
  each refinement re-solves the weights of the current kernels with all images so far and
  continues the subdivision from them, with a kernel budget of ``min(K, N)`` — more
  kernels than images is never fitted. The one-shot :func:`estimate_natural` treats
  N < K as an input error.
* Ties: a candidate replaces the best so far only if it lowers the error by more than
  ``1e-12 · ‖b‖²``, and a pixel stops splitting when no candidate lowers the error by
  more than that, so the fast kernel and the SciPy reference make the same choices
  where the floating-point error of the two solvers would otherwise decide.

On-disk layout (:func:`save_field`, NPZ, ``format = "opacityhull.natural/1"``)::

    format        str                       "opacityhull.natural/1"
    domain_hw     int64 (2,)                display pixels (H_d, W_d) of the illumination domain
    pixels_shape  int64 (k,)                shape of the pixel grid (e.g. (H, W)); prod = P
    boxes         uint16 (P, K, 4)          (x0, y0, x1, y1), half-open display pixels;
                                            unused slots are (0, 0, 0, 0)
    weights       float16|float32 (P, K, C) per-channel weight of each box mean (0 if unused)
    n_kernels     uint8 (P,)                kernels used per pixel (≤ K)
    residual      float32 (P,)              ‖A w − b‖² / max(‖b‖², tiny) at the end
    n_images      int64 ()                  N used in the estimate
    meta          str                       JSON provenance (view id, display, K, rel_tol, …)
    pixel_index   int32 (P,)   optional     for a field of some pixels of an image: the
                                            row-major index of each pixel in ``image_hw``
    image_hw      int64 (2,)   optional     (H, W) of that image

so a pixel costs ``8 K + K C · (2|4) + 5`` bytes (K = 25, RGB, float16: 355 B). The
capture phase will write one file per view and display as
``MODEL/natural/<view_id>/<display>.npz`` next to ``reflectance/<view_id>.exr``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit, prange

from ..errors import FormatError, InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = [
    "NaturalConfig",
    "NaturalField",
    "NaturalEstimator",
    "summed_area_tables",
    "box_means",
    "nnls",
    "nnls_reference",
    "estimate_natural",
    "estimate_natural_reference",
    "relight_natural",
    "relight_natural_reference",
    "save_field",
    "field_path",
    "transport_matrix",
    "load_field",
    "scatter_pixels",
    "display_directions",
    "envmap_display_image",
    "relight_view_natural",
    "load_view_fields",
    "display_hit_mask",
    "FORMAT",
]

FORMAT = "opacityhull.natural/1"
#: relative improvement below which a split is "no better" (see module docstring)
TIE_REL = 1e-12
#: a Cholesky pivot below this fraction of the column's own norm² means "dependent column"
PIVOT_REL = 1e-10
MAX_KERNELS = 255


@dataclass(frozen=True, kw_only=True)
class NaturalConfig:
    """Options of the estimation.

    Parameters
    ----------
    n_kernels : int
        K, box kernels per pixel (the paper's default 25), 1 ≤ K ≤ 255.
    rel_tol : float
        A pixel stops splitting once ``‖A w − b‖² ≤ rel_tol · ‖b‖²`` (the seed's "until
        the error of the estimation is below a certain threshold"); 0 = always K kernels.
    weights_dtype : {"float32", "float16"}
        Storage type of the weights in :func:`save_field`.
    """

    n_kernels: int = 25
    rel_tol: float = 1e-8
    weights_dtype: str = "float32"

    def __post_init__(self):
        if not (1 <= int(self.n_kernels) <= MAX_KERNELS):
            raise InputError(f"n_kernels={self.n_kernels}: expected 1 … {MAX_KERNELS}")
        if not (math.isfinite(self.rel_tol) and self.rel_tol >= 0):
            raise InputError(f"rel_tol={self.rel_tol}: expected a finite number ≥ 0")
        if self.weights_dtype not in ("float32", "float16"):
            raise InputError(f"weights_dtype={self.weights_dtype!r}: expected 'float32' or 'float16'")


@dataclass(frozen=True)
class NaturalField:
    """Box-kernel reflectance functions of P pixels over one display domain.

    Attributes
    ----------
    boxes : uint16 (P, K, 4)
        (x0, y0, x1, y1), half-open, in display pixels; unused slots are zeros.
    weights : float32 (P, K, C)
        Weight of each box *mean* per channel.
    n_kernels : uint8 (P,)
    residual : float32 (P,)
        Relative squared residual of the fit.
    domain_hw : (int, int)
    pixels_shape : tuple
        Shape of the pixel grid, ``prod(pixels_shape) == P``.
    n_images : int
    meta : dict
        Free JSON-able provenance (view id, display, options), stored as ``meta``.
    """

    boxes: np.ndarray
    weights: np.ndarray
    n_kernels: np.ndarray
    residual: np.ndarray
    domain_hw: tuple
    pixels_shape: tuple
    n_images: int
    meta: dict = dataclasses.field(default_factory=dict, compare=False)
    pixel_index: np.ndarray | None = dataclasses.field(default=None, compare=False)
    image_hw: tuple | None = None

    @property
    def n_pixels(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def channels(self) -> int:
        return int(self.weights.shape[2])

    def bytes_per_pixel(self, weights_dtype: str = "float32") -> float:
        """Stored bytes per pixel in the NPZ layout (uncompressed)."""
        K, C = self.boxes.shape[1], self.weights.shape[2]
        return 4 * 2 * K + K * C * np.dtype(weights_dtype).itemsize + 1 + 4


# --------------------------------------------------------------------------- inputs


def _as_nhwc(name: str, images) -> np.ndarray:
    a = np.asarray(images)
    if a.ndim == 3:
        a = a[..., None]
    if a.ndim != 4 or a.shape[0] < 1 or a.shape[1] < 1 or a.shape[2] < 1 or a.shape[3] < 1:
        raise ShapeError(f"{name} has shape {a.shape}, expected (N, H_d, W_d[, C]) with N, H_d, W_d ≥ 1")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ShapeError(f"{name} has dtype {a.dtype}, expected a real number type")
    return a


def _check_finite(name: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(f"{name}: {int(bad.sum())} non-finite values, first at index {first}")


def summed_area_tables(images) -> np.ndarray:
    """Summed-area tables of N images, laid out for per-kernel column reads.

    Parameters
    ----------
    images : array (N, H_d, W_d) or (N, H_d, W_d, C)
        Display radiance (any consistent linear unit).

    Returns
    -------
    sat : float64 (H_d + 1, W_d + 1, N, C)
        ``sat[y, x, j, c] = Σ_{y' < y, x' < x} images[j, y', x', c]``; row and column 0 are
        zero, so the sum over the half-open box [x0, x1) × [y0, y1) is
        ``sat[y1, x1] − sat[y0, x1] − sat[y1, x0] + sat[y0, x0]``.
    """
    a = _as_nhwc("images", images).astype(np.float64)
    _check_finite("images", a)
    N, H, W, C = a.shape
    sat = np.zeros((H + 1, W + 1, N, C))
    np.cumsum(np.cumsum(a.transpose(1, 2, 0, 3), axis=0), axis=1, out=sat[1:, 1:])
    return sat


def box_means(sat: np.ndarray, boxes) -> np.ndarray:
    """Mean of every image over each box, from summed-area tables (four lookups).

    Parameters
    ----------
    sat : float64 (H_d + 1, W_d + 1, N, C)
    boxes : int (M, 4)
        (x0, y0, x1, y1), half-open; empty boxes give 0.

    Returns
    -------
    means : float64 (N, M, C)
    """
    b = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    x0, y0, x1, y1 = b.T
    s = sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]  # (M, N, C)
    area = ((x1 - x0) * (y1 - y0)).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(area[:, None, None] > 0, s / np.maximum(area, 1)[:, None, None], 0.0)
    return m.transpose(1, 0, 2)


# --------------------------------------------------------------------------- numba kernels


@njit(cache=True)
def nnls_gram(G, h, bb, m, x, passive, excluded, s, Lw, idx):  # pragma: no cover - compiled
    """Lawson–Hanson on the normal equations of an m-column problem, warm started
    from the feasible x (entries > 0 form the initial passive set). Returns the
    squared residual bb − 2 xᵀh + xᵀGx (clamped at 0). x is updated in place."""
    for j in range(m):
        passive[j] = x[j] > 0.0
        excluded[j] = False
    max_outer = 3 * m + 3
    just_added = -1
    for _outer in range(max_outer):
        # ---- inner loop: least squares on the passive set, kept feasible
        for _inner in range(m + 2):
            n = 0
            for j in range(m):
                if passive[j]:
                    idx[n] = j
                    n += 1
            if n == 0:
                break
            # Cholesky of G[P, P]; a vanishing pivot marks a dependent column
            bad = -1
            for a in range(n):
                ia = idx[a]
                for c in range(a + 1):
                    ic = idx[c]
                    v = G[ia, ic]
                    for t in range(c):
                        v -= Lw[a, t] * Lw[c, t]
                    if c == a:
                        if v <= PIVOT_REL * G[ia, ia] or v <= 0.0:
                            bad = a
                            break
                        Lw[a, a] = math.sqrt(v)
                    else:
                        Lw[a, c] = v / Lw[c, c]
                if bad >= 0:
                    break
            if bad >= 0:
                j = idx[bad]
                passive[j] = False
                excluded[j] = True
                x[j] = 0.0
                continue
            # forward / back substitution
            for a in range(n):
                v = h[idx[a]]
                for t in range(a):
                    v -= Lw[a, t] * s[t]
                s[a] = v / Lw[a, a]
            for a in range(n - 1, -1, -1):
                v = s[a]
                for t in range(a + 1, n):
                    v -= Lw[t, a] * s[t]
                s[a] = v / Lw[a, a]
            feasible = True
            for a in range(n):
                if not (s[a] > 0.0):
                    feasible = False
                    break
            if feasible:
                for a in range(n):
                    x[idx[a]] = s[a]
                break
            # step towards s until the first passive weight hits zero
            alpha = 1.0
            amin = -1
            for a in range(n):
                if not (s[a] > 0.0):
                    xa = x[idx[a]]
                    d = xa - s[a]
                    r = xa / d if d > 0.0 else 0.0
                    if r < alpha or amin < 0:
                        alpha = min(r, alpha)
                        amin = a
            for a in range(n):
                j = idx[a]
                x[j] = x[j] + alpha * (s[a] - x[j])
                if a == amin or not (x[j] > 0.0):
                    x[j] = 0.0
                    passive[j] = False
            if just_added >= 0 and not passive[just_added]:
                # the column just added could not enter: numerically dependent
                excluded[just_added] = True
                just_added = -1
        just_added = -1
        # ---- outer: most positive gradient among the active constraints
        best = -1
        bestw = 0.0
        for j in range(m):
            if passive[j] or excluded[j]:
                continue
            w = h[j]
            for t in range(m):
                if x[t] != 0.0:
                    w -= G[j, t] * x[t]
            tol = 1e-10 * math.sqrt(max(G[j, j], 0.0) * max(bb, 0.0))
            if w > tol and w > bestw:
                bestw = w
                best = j
        if best < 0:
            break
        passive[best] = True
        just_added = best
    r = bb
    for j in range(m):
        if x[j] != 0.0:
            r -= 2.0 * x[j] * h[j]
            for t in range(m):
                if x[t] != 0.0:
                    r += x[j] * G[j, t] * x[t]
    return max(r, 0.0)


@njit(cache=True)
def box_col(sat, x0, y0, x1, y1, out):  # pragma: no cover - compiled
    N = sat.shape[2]
    C = sat.shape[3]
    inv = 1.0 / ((x1 - x0) * (y1 - y0))
    for j in range(N):
        for c in range(C):
            out[j, c] = (sat[y1, x1, j, c] - sat[y0, x1, j, c] - sat[y1, x0, j, c] + sat[y0, x0, j, c]) * inv


@njit(cache=True)
def dot_cols(a, b, c):  # pragma: no cover - compiled
    v = 0.0
    for j in range(a.shape[0]):
        v += a[j, c] * b[j, c]
    return v


@njit(cache=True)
def prep_candidate(
    sat, boxes, cols, b, k, o, m, cL, cR, valid, frac, dL, dR, dLL, dRR, dLR, hL, hR
):  # pragma: no cover - compiled
    """Columns of kernel k's two halves for cut o and their dots with the m columns and b."""
    X0, Y0, X1, Y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
    lo, hi = (X0, X1) if o == 0 else (Y0, Y1)  # the extent cut o halves (0: x, 1: y)
    if hi - lo < 2:
        valid[k, o] = False
        return
    mid = lo + (hi - lo) // 2
    lx1, ly1 = (mid, Y1) if o == 0 else (X1, mid)  # the first half ends at mid
    rx0, ry0 = (mid, Y0) if o == 0 else (X0, mid)  # the second starts there
    box_col(sat, X0, Y0, lx1, ly1, cL[k, o])
    box_col(sat, rx0, ry0, X1, Y1, cR[k, o])
    frac[k, o] = (mid - lo) / (hi - lo)
    valid[k, o] = True
    C = cols.shape[2]
    for c in range(C):
        for t in range(m):
            if t != k:
                dL[k, o, c, t] = dot_cols(cL[k, o], cols[t], c)
                dR[k, o, c, t] = dot_cols(cR[k, o], cols[t], c)
        dLL[k, o, c] = dot_cols(cL[k, o], cL[k, o], c)
        dRR[k, o, c] = dot_cols(cR[k, o], cR[k, o], c)
        dLR[k, o, c] = dot_cols(cL[k, o], cR[k, o], c)
        hL[k, o, c] = dot_cols(cL[k, o], b, c)
        hR[k, o, c] = dot_cols(cR[k, o], b, c)


@njit(cache=True)
def fit_pixel(sat, b, K, rel_tol, boxes, m0, w_out):  # pragma: no cover - compiled
    """Subdivide one pixel's kernels from its m0 current boxes up to K.
    boxes (K, 4) int64 in/out; w_out (K, C) out. Returns (m, squared residual sum, bb).

    Every candidate's half-box columns and their dot products are cached across
    iterations: a split changes one kernel and adds one, so per iteration only the dots
    with those two columns are new (O(m·N) instead of O(m²·N))."""
    N = sat.shape[2]
    C = sat.shape[3]
    Km = K + 1
    cols = np.zeros((Km, N, C))
    G = np.zeros((C, Km, Km))
    h = np.zeros((C, Km))
    x = np.zeros((C, Km))
    bbc = np.zeros(C)
    # candidate cache: kernel k, orientation o (0: cut across x, 1: across y)
    cL = np.zeros((Km, 2, N, C))
    cR = np.zeros((Km, 2, N, C))
    valid = np.zeros((Km, 2), np.bool_)
    frac = np.zeros((Km, 2))
    dL = np.zeros((Km, 2, C, Km))
    dR = np.zeros((Km, 2, C, Km))
    dLL = np.zeros((Km, 2, C))
    dRR = np.zeros((Km, 2, C))
    dLR = np.zeros((Km, 2, C))
    hL = np.zeros((Km, 2, C))
    hR = np.zeros((Km, 2, C))
    # work
    Gc = np.zeros((Km, Km))
    hc = np.zeros(Km)
    xc = np.zeros(Km)
    xbest = np.zeros((C, Km))
    xcand = np.zeros((C, Km))
    passive = np.zeros(Km, np.bool_)
    excluded = np.zeros(Km, np.bool_)
    s = np.zeros(Km)
    Lw = np.zeros((Km, Km))
    idx = np.zeros(Km, np.int64)
    bb = 0.0
    for c in range(C):
        v = 0.0
        for j in range(N):
            v += b[j, c] * b[j, c]
        bbc[c] = v
        bb += v
    m = m0
    if m < 1:
        boxes[0, 0] = 0
        boxes[0, 1] = 0
        boxes[0, 2] = sat.shape[1] - 1
        boxes[0, 3] = sat.shape[0] - 1
        m = 1
    for k in range(m):
        box_col(sat, boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3], cols[k])
    for c in range(C):
        for k in range(m):
            h[c, k] = dot_cols(cols[k], b, c)
            for t in range(k + 1):
                v = dot_cols(cols[k], cols[t], c)
                G[c, k, t] = v
                G[c, t, k] = v
    err = 0.0
    for c in range(C):
        err += nnls_gram(G[c], h[c], bbc[c], m, x[c], passive, excluded, s, Lw, idx)
    tie = TIE_REL * bb
    if m < K and err > rel_tol * bb and err > tie:
        for k in range(m):
            for o in range(2):
                prep_candidate(sat, boxes, cols, b, k, o, m, cL, cR, valid, frac, dL, dR, dLL, dRR, dLR, hL, hR)
    while m < K and err > rel_tol * bb and err > tie:
        best_err = err - tie
        best_k = -1
        best_o = -1
        for k in range(m):
            for o in range(2):
                if not valid[k, o]:
                    continue
                fL = frac[k, o]
                tot = 0.0
                for c in range(C):
                    # candidate Gram: column k -> left half, column m -> right half
                    for r in range(m):
                        for t in range(m):
                            Gc[r, t] = G[c, r, t]
                        hc[r] = h[c, r]
                        xc[r] = x[c, r]
                    for t in range(m):
                        if t != k:
                            Gc[k, t] = dL[k, o, c, t]
                            Gc[t, k] = dL[k, o, c, t]
                            Gc[m, t] = dR[k, o, c, t]
                            Gc[t, m] = dR[k, o, c, t]
                    Gc[k, k] = dLL[k, o, c]
                    Gc[m, m] = dRR[k, o, c]
                    Gc[k, m] = dLR[k, o, c]
                    Gc[m, k] = dLR[k, o, c]
                    hc[k] = hL[k, o, c]
                    hc[m] = hR[k, o, c]
                    wk = x[c, k]
                    xc[k] = wk * fL
                    xc[m] = wk * (1.0 - fL)
                    tot += nnls_gram(Gc, hc, bbc[c], m + 1, xc, passive, excluded, s, Lw, idx)
                    for r in range(m + 1):
                        xcand[c, r] = xc[r]
                    if tot >= best_err:
                        break  # the other channels can only add error
                if tot < best_err:
                    best_err = tot
                    best_k = k
                    best_o = o
                    for c in range(C):
                        for r in range(m + 1):
                            xbest[c, r] = xcand[c, r]
        if best_k < 0:
            break
        # apply the best split: kernel k becomes the low half, kernel m the high half
        k = best_k
        o = best_o
        # box k keeps the first half of its extent along axis o, new box m takes the second
        lo, hi = boxes[k, o], boxes[k, o + 2]
        mid = lo + (hi - lo) // 2
        boxes[m, :] = boxes[k, :]
        boxes[k, o + 2] = mid
        boxes[m, o] = mid
        for j in range(N):
            for c in range(C):
                cols[k, j, c] = cL[k, o, j, c]
                cols[m, j, c] = cR[k, o, j, c]
        for c in range(C):
            for t in range(m):
                if t != k:
                    G[c, k, t] = dL[k, o, c, t]
                    G[c, t, k] = dL[k, o, c, t]
                    G[c, m, t] = dR[k, o, c, t]
                    G[c, t, m] = dR[k, o, c, t]
            G[c, k, k] = dLL[k, o, c]
            G[c, m, m] = dRR[k, o, c]
            G[c, k, m] = dLR[k, o, c]
            G[c, m, k] = dLR[k, o, c]
            h[c, k] = hL[k, o, c]
            h[c, m] = hR[k, o, c]
            for r in range(m + 1):
                x[c, r] = xbest[c, r]
        knew = m
        m += 1
        err = best_err
        if m < K and err > rel_tol * bb and err > tie:
            # the cached candidates of unchanged kernels need dots with the two new columns
            for q in range(m):
                if q in (k, knew):
                    continue
                for oo in range(2):
                    if not valid[q, oo]:
                        continue
                    for c in range(C):
                        dL[q, oo, c, k] = dot_cols(cL[q, oo], cols[k], c)
                        dR[q, oo, c, k] = dot_cols(cR[q, oo], cols[k], c)
                        dL[q, oo, c, knew] = dot_cols(cL[q, oo], cols[knew], c)
                        dR[q, oo, c, knew] = dot_cols(cR[q, oo], cols[knew], c)
            for oo in range(2):
                prep_candidate(sat, boxes, cols, b, k, oo, m, cL, cR, valid, frac, dL, dR, dLL, dRR, dLR, hL, hR)
                prep_candidate(sat, boxes, cols, b, knew, oo, m, cL, cR, valid, frac, dL, dR, dLL, dRR, dLR, hL, hR)
    for c in range(C):
        for k in range(m):
            w_out[k, c] = x[c, k]
    return m, err, bb


@njit(cache=True, parallel=True)
def fit_batch(sat, obs, K, rel_tol, boxes, m0, w_out, n_out, res_out):  # pragma: no cover - compiled
    P = obs.shape[0]
    for p in prange(P):
        m, err, bb = fit_pixel(sat, obs[p], K, rel_tol, boxes[p], m0[p], w_out[p])
        n_out[p] = m
        res_out[p] = err / bb if bb > 0.0 else 0.0


@njit(cache=True, parallel=True)
def relight_batch(sat, boxes, weights, n_used, out):  # pragma: no cover - compiled
    P = boxes.shape[0]
    C = out.shape[1]
    for p in prange(P):
        for c in range(C):
            out[p, c] = 0.0
        for k in range(n_used[p]):
            x0 = np.int64(boxes[p, k, 0])
            y0 = np.int64(boxes[p, k, 1])
            x1 = np.int64(boxes[p, k, 2])
            y1 = np.int64(boxes[p, k, 3])
            area = (x1 - x0) * (y1 - y0)
            if area <= 0:
                continue
            inv = 1.0 / area
            for c in range(C):
                cs = c if sat.shape[2] > 1 else 0
                mean = (sat[y1, x1, cs] - sat[y0, x1, cs] - sat[y1, x0, cs] + sat[y0, x0, cs]) * inv
                out[p, c] += weights[p, k, c] * mean


@njit(cache=True)
def nnls_single(G, h, bb, x):  # pragma: no cover - compiled
    m = G.shape[0]
    passive = np.zeros(m, np.bool_)
    excluded = np.zeros(m, np.bool_)
    s = np.zeros(m)
    Lw = np.zeros((m, m))
    idx = np.zeros(m, np.int64)
    return nnls_gram(G, h, bb, m, x, passive, excluded, s, Lw, idx)


_KERNELS = {"fit_batch": fit_batch, "relight_batch": relight_batch, "nnls_single": nnls_single, "fit_pixel": fit_pixel}


def _kernels():
    return _KERNELS


# --------------------------------------------------------------------------- NNLS


def nnls(A, b) -> tuple[np.ndarray, float]:
    """Non-negative least squares ``argmin_{x ≥ 0} ‖A x − b‖`` by the fast kernel.

    Lawson–Hanson on the normal equations (the kernel the estimator uses per candidate).

    Parameters
    ----------
    A : (N, m) float
    b : (N,) float

    Returns
    -------
    x : float64 (m,)
    rnorm : float
        ‖A x − b‖ (computed directly from A, not from the normal equations).
    """
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    if A.ndim != 2 or A.shape[0] != b.shape[0] or A.shape[1] < 1:
        raise ShapeError(f"nnls: A has shape {A.shape} and b {b.shape}, expected (N, m) and (N,)")
    _check_finite("nnls A", A)
    _check_finite("nnls b", b)
    x = np.zeros(A.shape[1])
    _kernels()["nnls_single"](A.T @ A, A.T @ b, float(b @ b), x)
    return x, float(np.linalg.norm(A @ x - b))


def nnls_reference(A, b) -> tuple[np.ndarray, float]:
    """``scipy.optimize.nnls`` (the reference the fast kernel is tested against)."""
    from scipy.optimize import nnls as sp_nnls

    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    x, _ = sp_nnls(A, b)
    return x, float(np.linalg.norm(A @ x - b))


# --------------------------------------------------------------------------- estimation


def _prepare(images, observations):
    """Validate and flatten: observations are (N, *pixels, C) with a channel axis, or
    (N, P) for mono; the images have 1 channel (shared by all of C) or C."""
    L = _as_nhwc("natural images", images)
    _check_finite("natural images", L)
    obs = np.asarray(observations)
    if obs.ndim < 2 or not np.issubdtype(obs.dtype, np.number) or np.issubdtype(obs.dtype, np.complexfloating):
        raise ShapeError(
            f"observations have shape {obs.shape} and dtype {obs.dtype}, expected real (N, *pixels, C) or (N, P)"
        )
    N = L.shape[0]
    if obs.shape[0] != N:
        raise ShapeError(f"observations have {obs.shape[0]} images, natural images {N}: they must match")
    if obs.ndim == 2:
        obs = obs[..., None]
    C, C_img = obs.shape[-1], L.shape[3]
    if C_img not in (1, C):
        raise ShapeError(f"natural images have {C_img} channels, observations {C} (last axis): expected 1 or {C}")
    pixels_shape = tuple(int(v) for v in obs.shape[1:-1])
    o = obs.reshape(N, -1, C).astype(np.float64)
    _check_finite("observations", o)
    return L, o.transpose(1, 0, 2).copy(), pixels_shape, C


def _check_domain(H: int, W: int) -> None:
    if max(H, W) > 65535:
        raise InputError(f"display domain {W}x{H} too large for uint16 box corners (max 65535 px per axis)")


def _broadcast_sat(sat: np.ndarray, C: int) -> np.ndarray:
    if sat.shape[3] == C:
        return sat
    return np.ascontiguousarray(np.broadcast_to(sat, sat.shape[:3] + (C,)))


def _fit(sat, obs, K, rel_tol, boxes, m0):
    """Run the subdivision kernel; ``boxes`` (P, ≥K, 4) int64 and ``m0`` are the
    starting kernels and are updated in place."""
    P, N, C = obs.shape
    w = np.zeros((P, K, C))
    n = np.zeros(P, np.int64)
    res = np.zeros(P)
    if P:
        _kernels()["fit_batch"](sat, obs, int(K), float(rel_tol), boxes, m0, w, n, res)
    return w, n, res


def _make_field(boxes, w, n, res, domain_hw, pixels_shape, N) -> NaturalField:
    P, K = boxes.shape[:2]
    used = np.arange(K)[None, :] < n[:, None]
    b = np.where(used[..., None], boxes, 0).astype(np.uint16)
    ww = np.where(used[..., None], w, 0.0).astype(np.float32)
    return NaturalField(
        boxes=b,
        weights=ww,
        n_kernels=n.astype(np.uint8),
        residual=res.astype(np.float32),
        domain_hw=tuple(int(v) for v in domain_hw),
        pixels_shape=tuple(pixels_shape),
        n_images=int(N),
    )


def estimate_natural(images, observations, *, config: NaturalConfig = NaturalConfig()) -> NaturalField:
    """Estimate every pixel's box-kernel reflectance function from natural images.

    Parameters
    ----------
    images : array (N, H_d, W_d[, C])
        The displayed illumination images, linear display radiance.
    observations : array (N, *pixels, C) or (N, P)
        The photographs (linear), one per image; ``pixels`` is any grid shape and the
        last axis is always the channel axis (2-D input means mono). Images with one
        channel light every observed channel (a grey display seen in colour).
    config : NaturalConfig

    Returns
    -------
    NaturalField

    Raises
    ------
    InputError
        N < K (fewer images than kernels: underdetermined), non-finite inputs, shape mismatch.
    """
    L, obs, pixels_shape, C = _prepare(images, observations)
    N, H, W = L.shape[:3]
    K = int(config.n_kernels)
    if N < K:
        raise InputError(
            f"natural estimation with n_kernels={K} needs at least {K} images, got N={N}: add images or lower n_kernels"
        )
    _check_domain(H, W)
    sat = _broadcast_sat(summed_area_tables(L), C)
    P = obs.shape[0]
    boxes = np.zeros((P, K, 4), np.int64)
    m0 = np.zeros(P, np.int64)
    w, n, res = _fit(sat, obs, K, config.rel_tol, boxes, m0)
    return _make_field(boxes, w, n, res, (H, W), pixels_shape, N)


class NaturalEstimator:
    """Progressive refinement: add natural images in batches, refine after each.

    Each :meth:`refine` re-solves the weights of the current kernels with every image so
    far and continues the subdivision from them, with a budget of ``min(K, N)`` kernels.
    """

    def __init__(self, *, config: NaturalConfig = NaturalConfig()):
        self.config = config
        self._images: list[np.ndarray] = []
        self._obs: list[np.ndarray] = []
        self._boxes = None
        self._n = None
        self.field: NaturalField | None = None

    @property
    def n_images(self) -> int:
        return sum(a.shape[0] for a in self._images)

    def add(self, images, observations) -> None:
        """Queue N' more (image, photograph) pairs; shapes as in :func:`estimate_natural`."""
        L, obs, pixels_shape, C = _prepare(images, observations)
        if self._images:
            L0 = self._images[0]
            if (
                L.shape[1:] != L0.shape[1:]
                or obs.shape[0] != self._obs[0].shape[0]
                or obs.shape[2] != self._obs[0].shape[2]
            ):
                raise ShapeError(
                    f"batch with images {L.shape[1:]} and {obs.shape[0]} pixels × {obs.shape[2]} "
                    f"channels does not match the first batch ({L0.shape[1:]}, "
                    f"{self._obs[0].shape[0]} × {self._obs[0].shape[2]})"
                )
        self._pixels_shape = pixels_shape
        self._images.append(L)
        self._obs.append(obs)

    def refine(self) -> NaturalField:
        """Refine the kernels with all images so far and return the current field."""
        if not self._images:
            raise InputError("NaturalEstimator.refine: no images added")
        L = np.concatenate(self._images, axis=0)
        obs = np.concatenate(self._obs, axis=1)
        N, H, W = L.shape[:3]
        _check_domain(H, W)
        P, _, C = obs.shape
        K = int(self.config.n_kernels)
        budget = min(K, N)
        if self._boxes is None:
            self._boxes = np.zeros((P, K, 4), np.int64)
            self._n = np.zeros(P, np.int64)
        sat = _broadcast_sat(summed_area_tables(L), C)
        w, n, res = _fit(sat, obs, budget, self.config.rel_tol, self._boxes, self._n)
        self._n = n
        wk = np.zeros((P, K, C))
        wk[:, :budget] = w
        self.field = _make_field(self._boxes, wk, n, res, (H, W), self._pixels_shape, N)
        return self.field


# --------------------------------------------------------------------------- relighting


def _check_field_image(field: NaturalField, image) -> np.ndarray:
    L = np.asarray(image)
    if L.ndim == 2:
        L = L[..., None]
    if L.ndim != 3 or tuple(L.shape[:2]) != tuple(field.domain_hw) or L.shape[2] not in (1, field.channels):
        raise ShapeError(
            f"illumination image has shape {L.shape}, expected {tuple(field.domain_hw)} "
            f"× 1 or {field.channels} channels (the field's display domain)"
        )
    L = L.astype(np.float64)
    _check_finite("illumination image", L)
    return L


def relight_natural(field: NaturalField, image) -> np.ndarray:
    """Relight under a new display image: ``b_i = Σ_k w_{k,i} (R_{k,i} • L)`` via one SAT.

    Parameters
    ----------
    field : NaturalField
    image : array (H_d, W_d[, C])
        New illumination on the display domain (same units as the estimation images).

    Returns
    -------
    float32 (*pixels_shape, C)
    """
    L = _check_field_image(field, image)
    sat = summed_area_tables(L[None])[:, :, 0, :]  # (H+1, W+1, C)
    out = np.zeros((field.n_pixels, field.channels))
    n = field.n_kernels.astype(np.int64)
    _kernels()["relight_batch"](np.ascontiguousarray(sat), field.boxes, field.weights.astype(np.float64), n, out)
    return out.reshape(field.pixels_shape + (field.channels,)).astype(np.float32)


def relight_natural_reference(field: NaturalField, image) -> np.ndarray:
    """Slow reference of :func:`relight_natural`: each box summed directly, no SAT."""
    L = _check_field_image(field, image)
    C = field.channels
    out = np.zeros((field.n_pixels, C))
    for p in range(field.n_pixels):
        for k in range(int(field.n_kernels[p])):
            x0, y0, x1, y1 = (int(v) for v in field.boxes[p, k])
            if x1 > x0 and y1 > y0:
                mean = L[y0:y1, x0:x1].reshape(-1, L.shape[2]).mean(axis=0)
                out[p] += field.weights[p, k].astype(np.float64) * np.broadcast_to(mean, (C,))
    return out.reshape(field.pixels_shape + (C,)).astype(np.float32)


def transport_matrix(field: NaturalField) -> np.ndarray:
    """The dense transport ``T`` (P, C, H_d·W_d) the kernels represent (small fields only)."""
    H, W = field.domain_hw
    T = np.zeros((field.n_pixels, field.channels, H, W))
    for p in range(field.n_pixels):
        for k in range(int(field.n_kernels[p])):
            x0, y0, x1, y1 = (int(v) for v in field.boxes[p, k])
            a = (x1 - x0) * (y1 - y0)
            if a > 0:
                T[p, :, y0:y1, x0:x1] += field.weights[p, k, :, None, None] / a
    return T.reshape(field.n_pixels, field.channels, H * W)


# --------------------------------------------------------------------------- reference


def estimate_natural_reference(
    images, observations, *, config: NaturalConfig = NaturalConfig(), columns: str = "direct"
) -> NaturalField:
    """Slow, obviously-correct reference of :func:`estimate_natural`.

    The same subdivision rule, with ``scipy.optimize.nnls`` solving every candidate from
    scratch on the explicit matrix ``A`` and box means taken either directly from the
    images (``columns="direct"``: the oracle) or from the SATs (``"sat"``: the
    "SciPy per pixel" baseline of ``benchmarks/natural.py``).
    """
    from scipy.optimize import nnls as sp_nnls

    L, obs, pixels_shape, C = _prepare(images, observations)
    N, H, W = L.shape[:3]
    K = int(config.n_kernels)
    if N < K:
        raise InputError(f"natural estimation with n_kernels={K} needs at least {K} images, got N={N}")
    Lf = np.broadcast_to(L.astype(np.float64), (N, H, W, C))
    sat = _broadcast_sat(summed_area_tables(L), C) if columns == "sat" else None

    def col(box):
        x0, y0, x1, y1 = box
        if sat is not None:
            return box_means(sat, [box])[:, 0, :]
        return Lf[:, y0:y1, x0:x1, :].mean(axis=(1, 2))

    def solve(cols, b):
        A = np.stack(cols, axis=1)  # (N, m, C)
        err, ws = 0.0, []
        for c in range(C):
            w, r = sp_nnls(A[:, :, c], b[:, c])
            ws.append(w)
            err += float(np.sum((A[:, :, c] @ w - b[:, c]) ** 2))
        return err, np.stack(ws, axis=1)

    P = obs.shape[0]
    boxes = np.zeros((P, K, 4), np.int64)
    weights = np.zeros((P, K, C))
    n_used = np.zeros(P, np.int64)
    res = np.zeros(P)
    for p in range(P):
        b = obs[p]
        bb = float(np.sum(b * b))
        tie = TIE_REL * bb
        bx = [(0, 0, W, H)]
        cols = [col(bx[0])]
        err, w = solve(cols, b)
        while len(bx) < K and err > config.rel_tol * bb and err > tie:
            best = (err - tie, None, None, None)
            for k, (x0, y0, x1, y1) in enumerate(bx):
                for o in range(2):
                    if o == 0 and x1 - x0 >= 2:
                        mid = x0 + (x1 - x0) // 2
                        lo, hi = (x0, y0, mid, y1), (mid, y0, x1, y1)
                    elif o == 1 and y1 - y0 >= 2:
                        mid = y0 + (y1 - y0) // 2
                        lo, hi = (x0, y0, x1, mid), (x0, mid, x1, y1)
                    else:
                        continue
                    cand = bx[:k] + [lo] + bx[k + 1 :] + [hi]
                    ccols = cols[:k] + [col(lo)] + cols[k + 1 :] + [col(hi)]
                    e, wc = solve(ccols, b)
                    if e < best[0]:
                        best = (e, cand, ccols, wc)
            if best[1] is None:
                break
            err, bx, cols, w = best
        m = len(bx)
        boxes[p, :m] = bx
        weights[p, :m] = w
        n_used[p] = m
        res[p] = err / bb if bb > 0 else 0.0
    return _make_field(boxes, weights, n_used, res, (H, W), pixels_shape, N)


# --------------------------------------------------------------------------- storage


def field_path(model_root, view_id: str, display: str) -> Path:
    """Where the capture phase will store a view's field for one display:
    ``MODEL/natural/<view_id>/<display>.npz``."""
    return Path(model_root) / "natural" / str(view_id) / f"{display}.npz"


def save_field(path, field: NaturalField, *, weights_dtype: str = "float32") -> Path:
    """Write a field as NPZ in the layout of the module docstring (atomically)."""
    from ..imageio import atomic_path

    path = Path(path)
    if weights_dtype not in ("float32", "float16"):
        raise InputError(f"weights_dtype={weights_dtype!r}: expected 'float32' or 'float16'")
    w = field.weights
    if weights_dtype == "float16":
        big = np.abs(w) > 65504
        if big.any():
            log.warning("%s: %d weights beyond float16 range clamped to ±65504", path, int(big.sum()))
        w = np.clip(w, -65504, 65504)
    arrays: dict[str, np.ndarray] = dict(
        format=np.array(FORMAT),
        domain_hw=np.array(field.domain_hw, np.int64),
        pixels_shape=np.array(field.pixels_shape, np.int64),
        boxes=field.boxes.astype(np.uint16),
        weights=w.astype(weights_dtype),
        n_kernels=field.n_kernels.astype(np.uint8),
        residual=field.residual.astype(np.float32),
        n_images=np.array(field.n_images, np.int64),
        meta=np.array(json.dumps(field.meta, sort_keys=True)),
    )
    if field.pixel_index is not None:
        arrays["pixel_index"] = np.asarray(field.pixel_index, np.int32)
        arrays["image_hw"] = np.array(field.image_hw, np.int64)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        # numpy's stub binds **kwds to the allow_pickle parameter's type
        np.savez_compressed(f, **arrays)  # pyright: ignore[reportArgumentType]
        f.flush()
        import os

        os.fsync(f.fileno())
    return path


def load_field(path) -> NaturalField:
    """Read a field written by :func:`save_field`; corrupt or foreign files raise FormatError."""
    import zipfile

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise FormatError(f"natural field {path}: file not found") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise FormatError(f"natural field {path}: not a readable NPZ ({e})") from None
    need = ("format", "domain_hw", "pixels_shape", "boxes", "weights", "n_kernels", "residual", "n_images")
    missing = [k for k in need if k not in d]
    if missing:
        raise FormatError(f"natural field {path}: missing arrays {missing}")
    if str(d["format"]) != FORMAT:
        raise FormatError(f"natural field {path}: format {str(d['format'])!r}, expected {FORMAT!r}")
    boxes, w, n = d["boxes"], d["weights"], d["n_kernels"]
    H, W = (int(v) for v in d["domain_hw"])
    pshape = tuple(int(v) for v in d["pixels_shape"])
    P = int(np.prod(pshape)) if pshape else 1
    if boxes.dtype != np.uint16 or boxes.ndim != 3 or boxes.shape[0] != P or boxes.shape[2] != 4:
        raise FormatError(f"natural field {path}: boxes {boxes.dtype} {boxes.shape}, expected uint16 ({P}, K, 4)")
    if w.ndim != 3 or w.shape[:2] != boxes.shape[:2] or w.dtype not in (np.float16, np.float32):
        raise FormatError(
            f"natural field {path}: weights {w.dtype} {w.shape}, expected float16/32 {boxes.shape[:2]} × C"
        )
    if n.shape != (P,) or int(n.max(initial=0)) > boxes.shape[1]:
        raise FormatError(
            f"natural field {path}: n_kernels shape {n.shape} or max {int(n.max(initial=0))} "
            f"inconsistent with K={boxes.shape[1]}"
        )
    b = boxes.astype(np.int64)
    used = np.arange(boxes.shape[1])[None, :] < n[:, None]
    ok = (b[..., 0] <= b[..., 2]) & (b[..., 1] <= b[..., 3]) & (b[..., 2] <= W) & (b[..., 3] <= H)
    if not ok[used].all():
        raise FormatError(f"natural field {path}: {int((~ok & used).sum())} boxes outside the {W}x{H} domain")
    if not np.isfinite(w).all():
        raise FormatError(f"natural field {path}: non-finite weights")
    try:
        meta = json.loads(str(d["meta"])) if "meta" in d else {}
    except ValueError:
        raise FormatError(f"natural field {path}: meta is not JSON") from None
    idx, ihw = None, None
    if "pixel_index" in d:
        idx = d["pixel_index"].astype(np.int64)
        ihw = tuple(int(v) for v in d.get("image_hw", np.zeros(0)))
        if len(ihw) != 2 or idx.shape != (P,) or (P and (idx.min() < 0 or idx.max() >= ihw[0] * ihw[1])):
            raise FormatError(
                f"natural field {path}: pixel_index {idx.shape} / image_hw {ihw} inconsistent with {P} pixels"
            )
    return NaturalField(
        boxes=boxes,
        weights=w.astype(np.float32),
        n_kernels=n.astype(np.uint8),
        residual=d["residual"].astype(np.float32),
        domain_hw=(H, W),
        pixels_shape=pshape,
        n_images=int(d["n_images"]),
        meta=meta,
        pixel_index=idx,
        image_hw=ihw,
    )


def scatter_pixels(field: NaturalField, values) -> np.ndarray:
    """Per-pixel values (P, C) of a field with ``pixel_index`` into its image,
    float32 (H, W, C), zero elsewhere."""
    if field.pixel_index is None or field.image_hw is None:
        raise InputError("scatter_pixels: the field has no pixel_index/image_hw (it covers a whole pixel grid)")
    v = np.asarray(values).reshape(field.n_pixels, -1)
    H, W = field.image_hw
    out = np.zeros((H * W, v.shape[1]), np.float32)
    out[np.asarray(field.pixel_index, np.int64)] = v
    return out.reshape(H, W, v.shape[1])


# --------------------------------------------------------------------------- environment maps


def display_directions(display, table_deg: float, *, centre_m=(0.0, 0.0, 0.0), supersample: int = 1) -> np.ndarray:
    """Unit directions (H_d, W_d, s², 3) in the *object* frame at ``table_deg`` from
    ``centre_m`` (object frame) to ``supersample²`` points of every display pixel.

    Pixel (x, y) has column x from the panel's left and row y from its top edge (the
    pattern's layout, :meth:`DisplaySpec.frame`). A display fixed in the rig turns
    against the object by ``-table_deg``; one on the turntable does not.
    """
    from ..camera import object_from_rig

    W_d, H_d = (int(v) for v in display.resolution)
    w, h = display.size_m
    s = max(int(supersample), 1)
    off = (np.arange(s) + 0.5) / s
    xs = ((np.arange(W_d)[:, None] + off[None, :]) / W_d - 0.5) * w  # (W_d, s)
    ys = (0.5 - (np.arange(H_d)[:, None] + off[None, :]) / H_d) * h  # (H_d, s)
    X = np.broadcast_to(xs[None, :, None, :], (H_d, W_d, s, s))
    Y = np.broadcast_to(ys[:, None, :, None], (H_d, W_d, s, s))
    local = np.stack([X, Y, np.zeros_like(X), np.ones_like(X)], axis=-1).reshape(H_d, W_d, s * s, 4)
    F = display.frame()
    P = local @ F.T  # rig frame at table angle 0
    # a display that turns with the object: the rig frame at 0 is the object frame
    obj = P[..., :3] if display.rotates_with_table else (P @ object_from_rig(table_deg).T)[..., :3]
    d = obj - np.asarray(centre_m, np.float64)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def envmap_display_image(
    envmap, display, table_deg: float, *, centre_m=(0.0, 0.0, 0.0), supersample: int = 3
) -> np.ndarray:
    """The image a display would show so that it sends the object what ``envmap`` sends
    from the display's solid angle: float64 (H_d, W_d, 3), in the envmap's radiance units.

    The kernels' illumination is display *radiance* (a box mean of it), and a display
    showing radiance E(d) along the direction d at which the object sees each of its
    pixels delivers the same light as the environment over that solid angle (both are
    radiance; the solid-angle weighting is the transport's, learnt by the estimate). The
    environment is averaged over ``supersample²`` directions per display pixel.
    Distant-light approximation: every point of the object sees a display pixel along
    the same direction (from ``centre_m``).
    """
    d = display_directions(display, table_deg, centre_m=centre_m, supersample=supersample)
    H_d, W_d, S, _ = d.shape
    rad = np.asarray(envmap.lookup(d.reshape(-1, 3)), np.float64).reshape(H_d, W_d, S, -1)
    return rad.mean(axis=2)[..., :3]


def relight_view_natural(
    fields: dict, envmap, geometry, table_deg: float, *, centre_m=(0.0, 0.0, 0.0), supersample: int = 3
) -> np.ndarray | None:
    """The display-domain part of one relit view under an environment map: the sum over
    illumination domains of :func:`relight_natural` under :func:`envmap_display_image`.

    Parameters
    ----------
    fields : {display name: NaturalField} of one view (fields with ``pixel_index``).
    envmap : :class:`~opacityhull.envmap.EnvironmentMap`, object frame.
    geometry : RigGeometry (the displays).
    table_deg : the view's table angle.

    Returns
    -------
    float32 (H, W, 3) premultiplied radiance to add to the light-array part, or None
    when ``fields`` is empty.
    """
    out = None
    for name, f in sorted(fields.items()):
        L = envmap_display_image(envmap, geometry.display(name), table_deg, centre_m=centre_m, supersample=supersample)
        vals = relight_natural(f, L)
        img = (
            scatter_pixels(f, vals)[..., :3]
            if f.pixel_index is not None
            else vals.reshape(tuple(f.pixels_shape) + (-1,))[..., :3]
        )
        out = img.astype(np.float32) if out is None else out + img
    return out


def load_view_fields(model_root, view_id: str) -> dict:
    """``{display: NaturalField}`` of ``MODEL/natural/<view_id>/*.npz`` (empty if none)."""
    d = Path(model_root) / "natural" / str(view_id)
    if not d.is_dir():
        return {}
    return {p.stem: load_field(p) for p in sorted(d.glob("*.npz"))}


def display_hit_mask(display, table_deg: float, directions, *, centre_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Which of ``directions`` (..., 3), object frame at ``table_deg``, from ``centre_m``
    meet the display's rectangle: bool (...). The complement of
    :func:`display_directions` — used to restrict an environment map to the solid angle
    a display covers (the part of the lighting its field can reproduce)."""
    from ..camera import object_from_rig

    F = display.frame()
    if not display.rotates_with_table:
        F = object_from_rig(table_deg) @ F
    Finv = np.linalg.inv(F)
    d = np.asarray(directions, np.float64)
    o = Finv[:3, :3] @ np.asarray(centre_m, np.float64) + Finv[:3, 3]
    v = d @ Finv[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / v[..., 2]
    x = o[0] + t * v[..., 0]
    y = o[1] + t * v[..., 1]
    w, h = display.size_m
    return np.isfinite(t) & (t > 0) & (np.abs(x) <= w / 2) & (np.abs(y) <= h / 2)
