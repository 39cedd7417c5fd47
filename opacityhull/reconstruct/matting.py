"""Multi-background (triangulation) matting: alpha and premultiplied foreground from K
photographs of the object in front of K known backdrops.

Model (Smith & Blinn 1996, "Blue Screen Matting", generalised to K backdrops as in
Matusik et al. 2002)::

    C_k = F' + (1 - alpha) B_k              k = 1..K, per colour channel

with ``F'`` the premultiplied foreground (``alpha F``) and ``B_k`` the backdrop seen at
that pixel without the object. Each pixel gives 3K equations in 4 unknowns
``(F'_r, F'_g, F'_b, alpha)``. Eliminating ``F'`` from the normal equations leaves one
scalar equation: with per-channel (weighted) means ``B̄_c``, ``C̄_c`` over the K shots,

    S = sum_kc (B_kc - B̄_c)^2                (Schur complement of the normal matrix)
    P = sum_kc (B_kc - B̄_c)(C_kc - C̄_c)
    1 - alpha = P / S,     F'_c = C̄_c - (1 - alpha) B̄_c.

``S`` is the whole story of conditioning: the least-squares alpha has standard deviation
``sigma / sqrt(S)`` for observation noise ``sigma`` (PITFALLS: the solve degenerates where
the backdrops are alike at a pixel, not where the foreground equals a backdrop). So the
per-pixel confidence is the predicted alpha standard deviation ``alpha_std = sigma /
sqrt(S)``, with ``sigma`` estimated robustly from the fit residuals over the image (floored
so that noise-free data still flags identical backdrops). Pixels whose ``alpha_std``
exceeds ``max_alpha_std`` are *unknown* and filled from confident neighbours by push-pull
interpolation (never NaN). Observations that are saturated or non-finite get weight 0
(per channel) and their pixels are flagged.

Where the backdrops ``B_k`` come from (the caller decides, see :mod:`.build`):

1. **Object-absent captures (default, implemented here and in the runner).** The plan
   photographs every backdrop pattern once more with the object removed, from every view
   (``matting`` records with ``object_present = False``). These are exact: they include
   the display's angular falloff, the camera's blur and the light reflected by the panels.
2. **Pattern through the calibrated display geometry** (:func:`backdrop_from_displays`):
   when a plan has no object-absent shots, each pixel's ray is intersected with the
   displays (``DisplaySpec.corners_rig``; the bottom display turns with the table, so in
   the object frame it is fixed while the back display turns by ``-table_deg``) and the
   uploaded pattern is looked up, times the display's ``max_radiance`` (a linear
   radiometric model without falloff or blur). It is an approximation: use it only when
   the object-absent captures are missing.

Kernels: :func:`solve_matte` (numba, one pass per pixel, parallel over pixels) is the
fast path; :func:`solve_matte_numpy` is the same closed form vectorised in NumPy; and
:func:`solve_matte_reference` solves every pixel's 3K×4 system with
``numpy.linalg.lstsq`` — the slow, obviously correct oracle the tests compare with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..errors import InputError, ShapeError

__all__ = [
    "MattingOptions",
    "MatteResult",
    "FLAG_SATURATED",
    "FLAG_INVALID",
    "FLAG_UNKNOWN",
    "FLAG_CHANNEL_LOST",
    "solve_matte",
    "solve_matte_numpy",
    "solve_matte_reference",
    "fill_from_neighbours",
    "fill_from_neighbours_reference",
    "straight_from_premul",
    "backdrop_from_displays",
]

#: some observation of the pixel was at or above the saturation level (dropped)
FLAG_SATURATED = np.uint8(1)
#: some observation of the pixel was NaN or Inf (dropped)
FLAG_INVALID = np.uint8(2)
#: the backdrops were too alike here (alpha_std > max_alpha_std): value filled from neighbours
FLAG_UNKNOWN = np.uint8(4)
#: every observation of some channel was dropped: that channel of F' is a lower bound
FLAG_CHANNEL_LOST = np.uint8(8)


@dataclass(frozen=True)
class MattingOptions:
    """Options of :func:`solve_matte`.

    Parameters
    ----------
    max_alpha_std : float
        A pixel whose predicted alpha standard deviation ``sigma / sqrt(S)`` exceeds this
        is unknown and filled from its neighbours.
    noise_sigma : float or None
        Observation noise (radiance units). None: estimated from the fit residuals
        (median over pixels of ``residual^2 / (n_obs - 4)``).
    noise_floor_rel : float
        Lower bound of ``sigma`` as a fraction of the backdrops' 99th-percentile level, so
        that noise-free images still flag pixels with (nearly) identical backdrops.
    fill : bool
        Fill unknown pixels from confident neighbours (push-pull). If False they keep the
        clamped least-squares value (or 0 where S = 0).
    """

    max_alpha_std: float = 0.05
    noise_sigma: float | None = None
    noise_floor_rel: float = 1e-3
    fill: bool = True

    def __post_init__(self):
        if not (self.max_alpha_std > 0 and math.isfinite(self.max_alpha_std)):
            raise InputError(f"matting max_alpha_std must be > 0, got {self.max_alpha_std}")
        if self.noise_sigma is not None and not (self.noise_sigma >= 0):
            raise InputError(f"matting noise_sigma must be >= 0 or None, got {self.noise_sigma}")
        if not self.noise_floor_rel >= 0:
            raise InputError(f"matting noise_floor_rel must be >= 0, got {self.noise_floor_rel}")


@dataclass
class MatteResult:
    """Output of :func:`solve_matte`.

    Attributes
    ----------
    alpha : (H, W) float32 in [0, 1].
    fg_premul : (H, W, 3) float32 >= 0, premultiplied foreground ``alpha F``.
    alpha_std : (H, W) float32, predicted standard deviation of alpha (capped at 1).
    confidence : (H, W) float32 in [0, 1]: ``1 - alpha_std / max_alpha_std`` clipped.
    flags : (H, W) uint8, bits FLAG_SATURATED | FLAG_INVALID | FLAG_UNKNOWN | FLAG_CHANNEL_LOST.
    noise_sigma : the observation noise used (estimated or given).
    """

    alpha: np.ndarray
    fg_premul: np.ndarray
    alpha_std: np.ndarray
    confidence: np.ndarray
    flags: np.ndarray
    noise_sigma: float

    @property
    def unknown(self) -> np.ndarray:
        return (self.flags & FLAG_UNKNOWN) != 0

    @property
    def saturated(self) -> np.ndarray:
        return (self.flags & FLAG_SATURATED) != 0

    @property
    def invalid(self) -> np.ndarray:
        return (self.flags & FLAG_INVALID) != 0


# --------------------------------------------------------------------------- inputs


def _prepare(observations, backdrops, c_saturation, b_saturation):
    C = np.asarray(observations)
    B = np.asarray(backdrops)
    if C.ndim != 4 or C.shape[-1] != 3:
        raise ShapeError(f"observations have shape {C.shape}, expected (K, H, W, 3)")
    if B.shape != C.shape:
        raise ShapeError(f"backdrops have shape {B.shape}, expected {C.shape} (one per observation)")
    K = C.shape[0]
    if K < 2:
        raise InputError(f"triangulation matting needs at least 2 backdrops per pixel, got K={K}")
    C = np.ascontiguousarray(C, dtype=np.float32)
    B = np.ascontiguousarray(B, dtype=np.float32)

    def level(x, name):
        if x is None:
            return np.full(K, np.inf, np.float32)
        a = np.broadcast_to(np.asarray(x, dtype=np.float32), (K,)).copy()
        if np.any(np.isnan(a)) or np.any(a <= 0):
            raise InputError(f"{name} must be > 0 (per observation), got {a.tolist()}")
        return a

    return C, B, level(c_saturation, "c_saturation"), level(b_saturation, "b_saturation")


# --------------------------------------------------------------------------- numba kernel


_BLOCK = 3 * 256  # flat (pixel, channel) elements per work item; accumulators stay in L1


@njit(cache=True, parallel=True, nogil=True, fastmath={"contract"})
def _matte_kernel(C, B, csat, bsat, alpha, fg, S_out, res2, dof, flags):
    """C, B: (K, N, 3) float32. Outputs per pixel n: alpha, fg (N, 3), S, residual^2,
    degrees of freedom and flags (saturated=1, invalid=2, channel lost=8).

    Work is split into blocks of flat (pixel, channel) elements so that the inner loop
    over an observation's contiguous values vectorises; per element it accumulates raw
    moments (w, b, c, bb, bc, cc) in float64, from which the centred moments follow. K is
    small and values are O(1..1e4), so the cancellation error (~1e-16 relative) is far
    below any usable backdrop spread.
    """
    K = C.shape[0]
    N = C.shape[1]
    Cf = C.reshape(K, N * 3)
    Bf = B.reshape(K, N * 3)
    M = N * 3
    nblocks = (M + _BLOCK - 1) // _BLOCK
    for bi in prange(nblocks):
        m0 = bi * _BLOCK
        m1 = min(M, m0 + _BLOCK)
        m = m1 - m0
        sw = np.zeros(_BLOCK)
        sb = np.zeros(_BLOCK)
        sc = np.zeros(_BLOCK)
        sbb = np.zeros(_BLOCK)
        sbc = np.zeros(_BLOCK)
        scc = np.zeros(_BLOCK)
        for k in range(K):
            cs = np.float64(csat[k])
            bs = np.float64(bsat[k])
            ck = Cf[k, m0:m1]
            bk = Bf[k, m0:m1]
            for j in range(m):
                cv = np.float64(ck[j])
                bv = np.float64(bk[j])
                # `x < level` is False for NaN and +Inf; the lower bounds catch -Inf.
                ok = (cv < cs) & (bv < bs) & (cv > -np.inf) & (bv > -np.inf)
                w = 1.0 if ok else 0.0
                cv = cv if ok else 0.0
                bv = bv if ok else 0.0
                sw[j] += w
                sb[j] += bv
                sc[j] += cv
                sbb[j] += bv * bv
                sbc[j] += bv * cv
                scc[j] += cv * cv
        # centred moments and means per element (a vectorisable loop)
        for j in range(m):
            inv = 1.0 / sw[j] if sw[j] > 0 else 0.0
            mb = sb[j] * inv
            mc = sc[j] * inv
            sbb[j] -= sb[j] * mb
            sbc[j] -= sb[j] * mc
            scc[j] -= sc[j] * mc
            sb[j] = mb
            sc[j] = mc
        full = 3.0 * K
        for q in range(m // 3):
            j = 3 * q
            n = m0 // 3 + q
            Sbb = sbb[j] + sbb[j + 1] + sbb[j + 2]
            Sbc = sbc[j] + sbc[j + 1] + sbc[j + 2]
            Scc = scc[j] + scc[j + 1] + scc[j + 2]
            if Sbb < 0.0:
                Sbb = 0.0
            a = 1.0 - Sbc / Sbb if Sbb > 0.0 else 0.0
            if a < 0.0:
                a = 0.0
            elif a > 1.0:
                a = 1.0
            beta = 1.0 - a
            # F' is unconstrained given alpha, so clamping alpha and recomputing F' is
            # the constrained least-squares optimum; its residual follows from moments.
            r2 = Scc - 2.0 * beta * Sbc + beta * beta * Sbb
            res2[n] = r2 if r2 > 0.0 else 0.0
            alpha[n] = a
            S_out[n] = Sbb
            nobs = sw[j] + sw[j + 1] + sw[j + 2]
            dof[n] = nobs - 4.0
            f0 = sc[j] - beta * sb[j]
            f1 = sc[j + 1] - beta * sb[j + 1]
            f2 = sc[j + 2] - beta * sb[j + 2]
            fg[n, 0] = f0 if f0 > 0.0 else 0.0
            fg[n, 1] = f1 if f1 > 0.0 else 0.0
            fg[n, 2] = f2 if f2 > 0.0 else 0.0
            if nobs < full:
                flags[n] = _classify_dropped(C, B, csat, bsat, n, sw[j:j + 3], fg)
            else:
                flags[n] = 0


@njit(cache=True, nogil=True)
def _classify_dropped(C, B, csat, bsat, n, sw, fg):
    """Rare path of :func:`_matte_kernel`: why were observations of pixel n dropped, and
    the lower bound of F' for channels that lost every observation."""
    K = C.shape[0]
    fl = 0
    for c in range(3):
        for k in range(K):
            cv = C[k, n, c]
            bv = B[k, n, c]
            if not (math.isfinite(cv) and math.isfinite(bv)):
                fl |= 2
            elif cv >= csat[k] or bv >= bsat[k]:
                fl |= 1
        if sw[c] == 0:
            # every observation of the channel dropped: F' is only known to be at
            # least the largest finite (clipped) observation
            fl |= 8
            f = 0.0
            for k in range(K):
                cv = C[k, n, c]
                if math.isfinite(cv) and cv > f:
                    f = cv
            fg[n, c] = f
    return fl


@njit(cache=True, nogil=True)
def _confidence_kernel(S, sigma, max_std, flags, astd, conf):
    for n in range(S.shape[0]):
        sd = sigma / math.sqrt(S[n]) if S[n] > 0 else np.inf
        if not (sd <= max_std):
            flags[n] |= 4
        sd = sd if sd < 1.0 else 1.0
        astd[n] = sd
        c = 1.0 - sd / max_std
        conf[n] = c if c > 0.0 else 0.0


def _finish(alpha, fg, S, res2, dof, flags, B, H, W, options: MattingOptions) -> MatteResult:
    """Noise estimate, confidence, unknown marking and filling (shared by all solvers)."""
    N = H * W
    if options.noise_sigma is not None:
        sigma = float(options.noise_sigma)
    else:
        stride = max(1, N // 50_000)  # a subsample is plenty for a median
        r, d, s_ = res2[::stride], dof[::stride], S[::stride]
        ok = (d > 0) & (s_ > 0) & np.isfinite(r)
        sel = r[ok] / d[ok]
        sigma = float(np.sqrt(np.median(sel))) if sel.size else 0.0
    Bs = np.asarray(B).reshape(-1)[:: max(1, B.size // 30_000)]
    Bs = Bs[np.isfinite(Bs)]
    scale = float(np.percentile(np.abs(Bs), 99)) if Bs.size else 0.0
    sigma_eff = max(sigma, options.noise_floor_rel * scale, 1e-12)
    flags = np.ascontiguousarray(flags, dtype=np.uint8).copy()
    astd = np.empty(N, np.float32)
    conf = np.empty(N, np.float32)
    _confidence_kernel(np.ascontiguousarray(S, dtype=np.float64), sigma_eff, float(options.max_alpha_std),
                       flags, astd, conf)
    alpha = np.asarray(alpha, dtype=np.float32).reshape(H, W)  # no copy when already float32
    fg = np.asarray(fg, dtype=np.float32).reshape(H, W, 3)
    flags = flags.reshape(H, W)
    unknown = (flags & FLAG_UNKNOWN) != 0
    if options.fill and np.any(unknown):
        vals = np.concatenate([alpha[..., None], fg], axis=-1).astype(np.float64)
        filled = _fill_clean(vals, (~unknown).astype(np.float64))
        alpha = np.clip(filled[..., 0], 0.0, 1.0).astype(np.float32)
        fg = np.maximum(filled[..., 1:], 0.0).astype(np.float32)
    return MatteResult(alpha=alpha, fg_premul=fg, alpha_std=astd.reshape(H, W), confidence=conf.reshape(H, W),
                       flags=flags, noise_sigma=sigma_eff)


def solve_matte(observations, backdrops, *, c_saturation=None, b_saturation=None,
                options: MattingOptions = MattingOptions()) -> MatteResult:
    """Alpha and premultiplied foreground from K (object, backdrop) image pairs.

    Parameters
    ----------
    observations : (K, H, W, 3) float
        Radiance of the object in front of backdrop k.
    backdrops : (K, H, W, 3) float
        Radiance of backdrop k alone (same view, object absent), see the module docstring
        for where these come from.
    c_saturation, b_saturation : float or (K,) array, optional
        Values at or above which an observation / backdrop is clipped (radiance units,
        i.e. ``white_level / (gain * exposure_s)`` for a raw capture); such samples get
        weight 0. Default: no clipping (HDR merges).
    options : MattingOptions

    Returns
    -------
    MatteResult
        ``alpha`` (H, W) in [0, 1], ``fg_premul`` (H, W, 3) >= 0, ``alpha_std``,
        ``confidence``, ``flags``; no NaN anywhere.
    """
    C, B, cs, bs = _prepare(observations, backdrops, c_saturation, b_saturation)
    K, H, W, _ = C.shape
    N = H * W
    Cr = C.reshape(K, N, 3)
    Br = B.reshape(K, N, 3)
    # float32 outputs (S, which decides confidence, stays float64): less write traffic
    alpha = np.empty(N, np.float32)
    fg = np.empty((N, 3), np.float32)
    S = np.empty(N, np.float64)
    res2 = np.empty(N, np.float32)
    dof = np.empty(N, np.float32)
    flags = np.empty(N, np.uint8)
    _matte_kernel(Cr, Br, cs, bs, alpha, fg, S, res2, dof, flags)
    return _finish(alpha, fg, S, res2, dof, flags, Br, H, W, options)


def _weights_and_flags(C, B, cs, bs):
    finite = np.isfinite(C) & np.isfinite(B)
    sat = (C >= cs[:, None, None]) | (B >= bs[:, None, None])
    w = (finite & ~sat).astype(np.float64)
    flags = np.where(np.any(~finite, axis=(0, 2)), FLAG_INVALID, 0) | np.where(
        np.any(sat & finite, axis=(0, 2)), FLAG_SATURATED, 0)
    return w, flags.astype(np.uint8)


def solve_matte_numpy(observations, backdrops, *, c_saturation=None, b_saturation=None,
                      options: MattingOptions = MattingOptions()) -> MatteResult:
    """The closed form of :func:`solve_matte`, vectorised in NumPy (float64)."""
    C, B, cs, bs = _prepare(observations, backdrops, c_saturation, b_saturation)
    K, H, W, _ = C.shape
    N = H * W
    C = C.reshape(K, N, 3).astype(np.float64)
    B = B.reshape(K, N, 3).astype(np.float64)
    w, flags = _weights_and_flags(C, B, cs, bs)
    C0 = np.where(w > 0, C, 0.0)
    B0 = np.where(w > 0, B, 0.0)
    sw = w.sum(axis=0)  # (N, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        mb = np.where(sw > 0, (w * B0).sum(0) / sw, 0.0)
        mc = np.where(sw > 0, (w * C0).sum(0) / sw, 0.0)
    db = (B0 - mb) * w
    dc = (C0 - mc) * w
    S = (db * db).sum(axis=(0, 2))
    P = (db * dc).sum(axis=(0, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(S > 0, 1.0 - P / np.where(S > 0, S, 1.0), 0.0)
    a = np.clip(a, 0.0, 1.0)
    beta = 1.0 - a
    f = mc - beta[:, None] * mb
    e = (C0 - f - beta[None, :, None] * B0) * w
    res2 = (e * e).sum(axis=(0, 2))
    lost = np.any(sw == 0, axis=1)
    if np.any(lost):
        cmax = np.max(np.where(np.isfinite(C), C, 0.0), axis=0)
        cmax = np.maximum(cmax, 0.0)
        f = np.where(sw == 0, cmax, f)
        flags = flags | np.where(lost, FLAG_CHANNEL_LOST, 0).astype(np.uint8)
    dof = sw.sum(axis=1) - 4.0
    return _finish(a, np.maximum(f, 0.0), S, res2, dof, flags, B.astype(np.float32), H, W, options)


def solve_matte_reference(observations, backdrops, *, c_saturation=None, b_saturation=None,
                          options: MattingOptions = MattingOptions()) -> MatteResult:
    """Slow oracle: every pixel's 3K×4 system ``[I3 | -B_k] [F'; alpha] = C_k - B_k``
    solved with ``numpy.linalg.lstsq`` (dropped rows removed; alpha clamped to [0, 1]
    then ``F'`` re-solved with alpha fixed). Use on small images only."""
    C, B, cs, bs = _prepare(observations, backdrops, c_saturation, b_saturation)
    K, H, W, _ = C.shape
    N = H * W
    Cr = C.reshape(K, N, 3).astype(np.float64)
    Br = B.reshape(K, N, 3).astype(np.float64)
    w, flags = _weights_and_flags(Cr, Br, cs, bs)
    alpha = np.zeros(N)
    fg = np.zeros((N, 3))
    S = np.zeros(N)
    res2 = np.zeros(N)
    dof = np.zeros(N)
    for n in range(N):
        rows, rhs, chans = [], [], []
        for k in range(K):
            for c in range(3):
                if w[k, n, c] == 0:
                    continue
                r = np.zeros(4)
                r[c] = 1.0
                r[3] = -Br[k, n, c]
                rows.append(r)
                rhs.append(Cr[k, n, c] - Br[k, n, c])
                chans.append(c)
        A = np.array(rows).reshape(-1, 4)
        d = np.array(rhs)
        chans = np.array(chans, dtype=int)
        present = [c for c in range(3) if np.any(chans == c)]
        cols = present + [3]
        A2 = A[:, cols]
        if A2.shape[0] == 0:
            x = np.zeros(len(cols))
        else:
            x = np.linalg.lstsq(A2, d, rcond=None)[0]
        # S = the alpha-alpha entry of the Schur complement of A2^T A2
        if A2.shape[0] > 0:
            M = A2.T @ A2
            m = len(present)
            Mff, Mfa, Maa = M[:m, :m], M[:m, m], M[m, m]
            S[n] = Maa - Mfa @ np.linalg.solve(Mff, Mfa) if m else Maa
        a = x[-1]
        if not (S[n] > 0):
            a = 0.0
        a = min(max(a, 0.0), 1.0)
        f = np.zeros(3)
        for c in present:
            sel = chans == c
            # with alpha fixed the optimum F'_c is the mean of C - (1 - alpha) B
            f[c] = np.mean((d[sel] + Br[:, n, c][w[:, n, c] > 0]) - (1 - a) * Br[:, n, c][w[:, n, c] > 0])
        e = d - (A[:, :3] @ f + A[:, 3] * a) if len(d) else np.zeros(0)
        res2[n] = float(e @ e)
        dof[n] = len(d) - 4.0
        for c in range(3):
            if c not in present:
                flags[n] |= FLAG_CHANNEL_LOST
                vals = Cr[:, n, c]
                vals = vals[np.isfinite(vals)]
                f[c] = max(vals.max(), 0.0) if vals.size else 0.0
        alpha[n] = a
        fg[n] = np.maximum(f, 0.0)
    return _finish(alpha, fg, S, res2, dof, flags, Br.astype(np.float32), H, W, options)


# --------------------------------------------------------------------------- filling


def _down2(x: np.ndarray) -> np.ndarray:
    """2×2 box sum with zero padding for odd sizes; (H, W, ...) → (ceil(H/2), ceil(W/2), ...)."""
    H, W = x.shape[:2]
    if H % 2 or W % 2:
        pad = [(0, H % 2), (0, W % 2)] + [(0, 0)] * (x.ndim - 2)
        x = np.pad(x, pad)
    return x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2]


def _up2(x: np.ndarray, H: int, W: int) -> np.ndarray:
    """Bilinear upsampling by 2 (pixel-centre aligned), cropped to (H, W)."""
    h, w = x.shape[:2]
    ys = (np.arange(H) + 0.5) / 2.0 - 0.5
    xs = (np.arange(W) + 0.5) / 2.0 - 0.5
    y0 = np.clip(np.floor(ys).astype(int), 0, h - 1)
    x0 = np.clip(np.floor(xs).astype(int), 0, w - 1)
    y1 = np.clip(y0 + 1, 0, h - 1)
    x1 = np.clip(x0 + 1, 0, w - 1)
    fy = np.clip(ys - y0, 0.0, 1.0)
    fx = np.clip(xs - x0, 0.0, 1.0)
    extra = (None,) * (x.ndim - 2)
    fy = fy[(slice(None), None) + extra]
    fx = fx[(None, slice(None)) + extra]
    top = x[y0][:, x0] * (1 - fx) + x[y0][:, x1] * fx
    bot = x[y1][:, x0] * (1 - fx) + x[y1][:, x1] * fx
    return top * (1 - fy) + bot * fy


def fill_from_neighbours_reference(values, weights) -> np.ndarray:
    """NumPy oracle of :func:`fill_from_neighbours` (same algorithm, float64).

    Fill low-weight pixels from their confident neighbours (push-pull, Gortler et al.
    1996): a weighted image pyramid is pushed down to 1 pixel, then each level is blended
    with the upsampled coarser one, ``x = w x + (1 - w) up(x_coarse)``.

    Parameters
    ----------
    values : (H, W, C) float
    weights : (H, W) float in [0, 1]; 1 = known, 0 = unknown.

    Returns
    -------
    (H, W, C) float64 with pixels of weight 1 unchanged and no NaN. If no pixel has
    weight > 0 the result is zeros.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 2:
        v = v[..., None]
    w = np.clip(np.nan_to_num(np.asarray(weights, dtype=np.float64), nan=0.0), 0.0, 1.0)
    if w.shape != v.shape[:2]:
        raise ShapeError(f"weights have shape {w.shape}, expected {v.shape[:2]}")
    v = np.where(w[..., None] > 0, np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    levels = [(v, w)]
    while max(levels[-1][1].shape) > 1:
        lv, lw = levels[-1]
        sw = _down2(lw)
        sv = _down2(lv * lw[..., None])
        with np.errstate(invalid="ignore", divide="ignore"):
            mv = np.where(sw[..., None] > 0, sv / np.where(sw > 0, sw, 1.0)[..., None], 0.0)
        levels.append((mv, np.minimum(sw, 1.0)))
    x = levels[-1][0]
    for lv, lw in reversed(levels[:-1]):
        up = _up2(x, lv.shape[0], lv.shape[1])
        x = lw[..., None] * lv + (1.0 - lw[..., None]) * up
    return x


@njit(cache=True, nogil=True)
def _push_level(v, w, out_v, out_w):
    """One push step: 2×2 weighted means (zero weight outside), weights clamped to 1."""
    h, wd, nc = v.shape
    H2, W2 = out_w.shape
    for i in range(H2):
        for j in range(W2):
            sw = 0.0
            for c in range(nc):
                out_v[i, j, c] = 0.0
            for di in range(2):
                y = 2 * i + di
                if y >= h:
                    continue
                for dj in range(2):
                    x = 2 * j + dj
                    if x >= wd:
                        continue
                    ww = w[y, x]
                    if ww > 0:
                        sw += ww
                        for c in range(nc):
                            out_v[i, j, c] += ww * v[y, x, c]
            if sw > 0:
                for c in range(nc):
                    out_v[i, j, c] /= sw
            out_w[i, j] = sw if sw < 1.0 else 1.0


@njit(cache=True, inline="always")
def _upsample_taps(i, n_coarse):
    """Bilinear taps of fine index ``i`` on a grid half as fine with ``n_coarse`` cells:
    (lower index, upper index, weight of the upper), edges clamped."""
    s = (i + 0.5) / 2.0 - 0.5
    i0 = int(math.floor(s))
    f = s - i0
    i1 = i0 + 1
    if i0 < 0:
        i0 = 0
        f = 0.0
    if i1 > n_coarse - 1:
        i1 = n_coarse - 1
    if i0 > n_coarse - 1:
        i0 = n_coarse - 1
    return i0, i1, f


@njit(cache=True, nogil=True)
def _pull_level(v, w, coarse):
    """One pull step in place: v = w v + (1 - w) bilinear_up(coarse)."""
    h, wd, nc = v.shape
    hc, wc = coarse.shape[0], coarse.shape[1]
    for i in range(h):
        y0, y1, fy = _upsample_taps(i, hc)
        for j in range(wd):
            ww = w[i, j]
            if ww >= 1.0:
                continue
            x0, x1, fx = _upsample_taps(j, wc)
            for c in range(nc):
                up = ((1 - fy) * ((1 - fx) * coarse[y0, x0, c] + fx * coarse[y0, x1, c])
                      + fy * ((1 - fx) * coarse[y1, x0, c] + fx * coarse[y1, x1, c]))
                v[i, j, c] = ww * v[i, j, c] + (1.0 - ww) * up


def fill_from_neighbours(values, weights) -> np.ndarray:
    """Fill low-weight pixels from their confident neighbours (push-pull, Gortler et al.
    1996): a weighted image pyramid is pushed down to 1 pixel, then each level is blended
    with the bilinearly upsampled coarser one, ``x = w x + (1 - w) up(x_coarse)``.

    Parameters
    ----------
    values : (H, W, C) float
    weights : (H, W) float in [0, 1]; 1 = known, 0 = unknown.

    Returns
    -------
    (H, W, C) float64 with pixels of weight 1 unchanged and no NaN. If no pixel has
    weight > 0 the result is zeros. Numba; :func:`fill_from_neighbours_reference` is the
    NumPy oracle.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 2:
        v = v[..., None]
    w = np.clip(np.nan_to_num(np.asarray(weights, dtype=np.float64), nan=0.0), 0.0, 1.0)
    if w.shape != v.shape[:2]:
        raise ShapeError(f"weights have shape {w.shape}, expected {v.shape[:2]}")
    v = np.ascontiguousarray(np.where(w[..., None] > 0, np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0), 0.0))
    return _fill_clean(v, w)


def _fill_clean(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Push-pull on finite, contiguous float64 (H, W, C) values and (H, W) weights in [0, 1]."""
    levels = [(v, w)]
    while max(levels[-1][1].shape) > 1:
        lv, lw = levels[-1]
        h2, w2 = (lw.shape[0] + 1) // 2, (lw.shape[1] + 1) // 2
        nv = np.empty((h2, w2, lv.shape[2]))
        nw = np.empty((h2, w2))
        _push_level(lv, lw, nv, nw)
        levels.append((nv, nw))
    x = levels[-1][0]
    for lv, lw in reversed(levels[:-1]):
        _pull_level(lv, lw, x)
        x = lv
    return x


# --------------------------------------------------------------------------- helpers


def straight_from_premul(premul, alpha, *, eps: float = 1e-3) -> np.ndarray:
    """Straight colour ``F = F' / alpha`` where ``alpha > eps``, else 0. (H, W, 3) float32."""
    a = np.asarray(alpha, dtype=np.float32)[..., None]
    p = np.asarray(premul, dtype=np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        F = np.where(a > eps, p / np.maximum(a, eps), 0.0)
    return np.nan_to_num(F, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def backdrop_from_displays(camera, table_deg: float, geometry, patterns: dict, *, supersample: int = 3,
                           off_radiance: float = 0.0) -> np.ndarray:
    """Predict the backdrop a view sees from the shown patterns and the display geometry.

    The fallback source of backdrops when a plan has no object-absent captures (see the
    module docstring). Each pixel is supersampled ``supersample``² times; every sample
    ray is intersected with every display rectangle, the nearest hit looks up the pattern
    texel (nearest texel, as a plasma panel shows it) and emits
    ``max_radiance * drive`` (linear drive values in [0, 1]) if the ray meets the panel's
    front (a panel seen from behind is dark). Rays that miss every display see
    ``off_radiance``.

    Parameters
    ----------
    camera : Camera in the object frame (the view camera).
    table_deg : table angle of the view (the back display is fixed in the rig frame, so it
        turns by ``-table_deg`` in the object frame; the bottom display turns with the
        table and is fixed in the object frame).
    geometry : RigGeometry.
    patterns : {display name: (rows, cols, 3) drive values in [0, 1]}; displays not in
        the dict are dark.

    Returns
    -------
    (H, W, 3) float32 radiance.
    """
    from ..camera import object_from_rig

    s = int(supersample)
    if s < 1:
        raise InputError(f"supersample must be >= 1, got {supersample}")
    H, W = camera.height, camera.width
    offs = (np.arange(s) + 0.5) / s - 0.5
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    # sample (i, j) of a pixel sits at (u + offs[j], v + offs[i])
    uu, vv = np.broadcast_arrays(u[..., None, None] + offs[None, None, None, :],
                                 v[..., None, None] + offs[None, None, :, None])
    uu, vv = uu.reshape(-1), vv.reshape(-1)
    o, d = camera.pixel_rays(np.stack([uu, vv], axis=1))
    best_t = np.full(d.shape[0], np.inf)
    out = np.full((d.shape[0], 3), float(off_radiance))
    obj_from_rig = object_from_rig(table_deg)
    for disp in geometry.displays:
        if disp.name not in patterns:
            continue
        pat = np.asarray(patterns[disp.name], dtype=np.float64)
        if pat.ndim == 2:
            pat = pat[..., None].repeat(3, axis=2)
        # corners in the object frame: the bottom panel turns with the object (fixed in
        # the object frame); a fixed panel turns by -table_deg relative to the object.
        corners_rig = disp.corners_rig(table_deg) if disp.rotates_with_table else disp.corners_rig(0.0)
        P = corners_rig @ obj_from_rig[:3, :3].T
        tl, tr, br, bl = P
        ex, ey = tr - tl, bl - tl
        n = np.cross(ex, ey)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((tl - o) @ n) / denom
        hit = np.isfinite(t) & (t > 0) & (t < best_t)
        X = o + t[:, None] * d
        rel = X - tl
        a = rel @ ex / (ex @ ex)
        b = rel @ ey / (ey @ ey)
        hit &= (a >= 0) & (a < 1) & (b >= 0) & (b < 1)
        rows, cols = pat.shape[:2]
        ci = np.clip((a[hit] * cols).astype(int), 0, cols - 1)
        ri = np.clip((b[hit] * rows).astype(int), 0, rows - 1)
        # a panel emits from its front only; seen from behind it is dark (and occludes)
        front = denom[hit] > 0  # n = right x down = -normal: a front hit has d . normal < 0
        out[hit] = np.where(front[:, None], disp.max_radiance * pat[ri, ci], 0.0)
        best_t[hit] = t[hit]
    return out.reshape(H, W, s * s, 3).mean(axis=2).astype(np.float32)
