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

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numba import njit, prange

from ..errors import InputError, ShapeError
from ..imageio import straight_from_premul  # the one conversion (re-exported for build)

log = logging.getLogger(__name__)

#: how :func:`correct_photometric_drift` maps each backdrop shot onto its object shot
DriftMode = Literal["none", "gain", "affine", "field"]
_DRIFT_MODES = ("none", "gain", "affine", "field")

__all__ = [
    "straight_from_premul",
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
    "backdrop_from_displays",
    "DriftMode",
    "DriftOptions",
    "DriftReport",
    "ShotDrift",
    "correct_photometric_drift",
    "object_support",
    "shift_image",
    "estimate_backdrop_flow",
    "warp_image",
]

#: some observation of the pixel was at or above the saturation level (dropped)
FLAG_SATURATED = np.uint8(1)
#: some observation of the pixel was NaN or Inf (dropped)
FLAG_INVALID = np.uint8(2)
#: the backdrops were too alike here (alpha_std > max_alpha_std): value filled from neighbours
FLAG_UNKNOWN = np.uint8(4)
#: every observation of some channel was dropped: that channel of F' is a lower bound
FLAG_CHANNEL_LOST = np.uint8(8)


@dataclass(frozen=True, kw_only=True)
class DriftOptions:
    """Tuning of :func:`correct_photometric_drift`.

    Parameters
    ----------
    rounds : int
        Alternations matte → backdrop mask → fit. Round 0 fits over every valid pixel
        (robust weights only); later rounds exclude the object found by the previous
        matte. On the flowers set the backdrop statistic is the same with 2, 3 or 4
        rounds; the fractional share of the frame is 10.9 / 10.4 / 10.5 %.
    field_sigma_rel : float
        ``mode="field"``: standard deviation of the Gaussian window of the gain field, as
        a fraction of ``max(H, W)`` (0.003 = 2.9 px at 960 px): small enough to follow
        the changed shading of cloth folds, large enough to average JPEG noise. (0.004
        before the flow: once the flow has taken a fold's motion, the finer field takes
        its shading; flowers band 99.00 % at 0.004, 99.04 % at 0.003, 99.05 % at 0.0025.)
    field_sigma_min_px : float
        Lower bound of that standard deviation in pixels: on small images a window of a
        pixel or two would fit every backdrop pixel exactly and force alpha to 0 on
        any faint structure outside the object mask.
    object_seed, object_low : float
        The object excluded from the fit: connected regions of ``alpha > object_low``
        that contain a pixel with ``alpha > object_seed`` (hysteresis, so specks of
        spurious alpha in the backdrop are not excluded and do get corrected).
    object_margin_rel : float
        The object mask is dilated by this fraction of ``max(H, W)`` (blur, halo).
    register : bool
        Estimate a sub-pixel translation of each backdrop shot against its object shot
        (Lucas-Kanade on backdrop pixels only).
    apply_shift_px : float
        Resample the backdrop by the estimated translation when its length is at least
        this (pixels). Below it the shift is only reported: resampling blurs the
        backdrop's texture by up to half a pixel, which costs more than a small shift.
    tukey_c : float
        Tukey biweight constant, in robust standard deviations of the relative residual.
    flow : bool
        Non-rigid registration (:func:`estimate_backdrop_flow`): in the last round, a
        dense displacement field of each backdrop shot onto its object shot, estimated
        on the backdrop pixels only (the object and its margin excluded, the field
        filled there from its surroundings), and the backdrop resampled by it before the
        gain field is fitted. It follows a cloth fold that moved between the shots,
        which no gain field can: on the flowers set the band at alpha < 0.05 goes from
        98.90 % (field alone) to 99.04 % (the leaf tip in it caps it at 99.10 %; see
        ``benchmarks/out/matting_real.md``). Needs ``rounds >= 2``.
    flow_sigma_px : float
        Standard deviation (pixels) of the Gaussian window of the flow's local
        least-squares fit: a fold moves over a pixel or two, so the window is that small.
    flow_max_px : float
        Displacements are clipped to this length (pixels).
    flow_iters : int
        Gauss-Newton iterations of the flow (each re-samples the backdrop).
    flow_prior : float
        Weight of the flow's pull towards 0, in units of the residual's noise variance
        (:func:`estimate_backdrop_flow`).
    """

    rounds: int = 3
    field_sigma_rel: float = 0.003
    field_sigma_min_px: float = 2.5
    object_seed: float = 0.9
    object_low: float = 0.1
    object_margin_rel: float = 0.004
    register: bool = True
    apply_shift_px: float = 0.5
    tukey_c: float = 4.685
    flow: bool = True
    flow_sigma_px: float = 1.0
    flow_max_px: float = 2.0
    flow_iters: int = 4
    flow_prior: float = 1.0

    def __post_init__(self):
        if not (isinstance(self.rounds, int) and self.rounds >= 1):
            raise InputError(f"drift rounds must be an integer >= 1, got {self.rounds!r}")
        if not (0 < self.field_sigma_rel < 1):
            raise InputError(f"drift field_sigma_rel must be in (0, 1), got {self.field_sigma_rel}")
        if not (self.field_sigma_min_px > 0 and math.isfinite(self.field_sigma_min_px)):
            raise InputError(f"drift field_sigma_min_px must be > 0, got {self.field_sigma_min_px}")
        if not (0 <= self.object_low < self.object_seed <= 1):
            raise InputError(
                f"drift needs 0 <= object_low < object_seed <= 1, got object_low="
                f"{self.object_low}, object_seed={self.object_seed}"
            )
        if not (0 <= self.object_margin_rel < 1):
            raise InputError(f"drift object_margin_rel must be in [0, 1), got {self.object_margin_rel}")
        if not (self.apply_shift_px >= 0):
            raise InputError(f"drift apply_shift_px must be >= 0, got {self.apply_shift_px}")
        if not (self.tukey_c > 0):
            raise InputError(f"drift tukey_c must be > 0, got {self.tukey_c}")
        if not (self.flow_sigma_px > 0 and math.isfinite(self.flow_sigma_px)):
            raise InputError(f"drift flow_sigma_px must be > 0, got {self.flow_sigma_px}")
        if not (self.flow_max_px > 0 and math.isfinite(self.flow_max_px)):
            raise InputError(f"drift flow_max_px must be > 0, got {self.flow_max_px}")
        if not (isinstance(self.flow_iters, int) and self.flow_iters >= 1):
            raise InputError(f"drift flow_iters must be an integer >= 1, got {self.flow_iters!r}")
        if not (self.flow_prior > 0 and math.isfinite(self.flow_prior)):
            raise InputError(f"drift flow_prior must be > 0, got {self.flow_prior}")


@dataclass(frozen=True, kw_only=True)
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
    drift : {"none", "gain", "affine", "field"}
        Photometric drift correction of the backdrops before the solve
        (:func:`correct_photometric_drift`). "none" (default) for calibrated captures
        (the simulator, HDR merges with fixed exposure); "field" for real photographs
        whose exposure, white balance or lighting changed between the backdrop and the
        object shots (on the flowers set it is the only mode that reaches 99 % clean
        backdrop, with the flow of ``DriftOptions``; see
        ``tests/reconstruct/test_matting_real.py``).
    drift_options : DriftOptions
        Tuning of the drift correction (ignored when ``drift="none"``).
    """

    max_alpha_std: float = 0.05
    noise_sigma: float | None = None
    noise_floor_rel: float = 1e-3
    fill: bool = True
    drift: DriftMode = "none"
    drift_options: DriftOptions = field(default_factory=lambda: DriftOptions())

    def __post_init__(self):
        if isinstance(self.drift_options, dict):  # round trip through asdict (build config)
            object.__setattr__(self, "drift_options", DriftOptions(**self.drift_options))
        if self.drift not in _DRIFT_MODES:
            raise InputError(f"matting drift must be one of {', '.join(_DRIFT_MODES)}, got {self.drift!r}")
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
    drift: DriftReport | None = None

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
                flags[n] = _classify_dropped(C, B, csat, bsat, n, sw[j : j + 3], fg)
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
    _confidence_kernel(
        np.ascontiguousarray(S, dtype=np.float64), sigma_eff, float(options.max_alpha_std), flags, astd, conf
    )
    alpha = np.asarray(alpha, dtype=np.float32).reshape(H, W)  # no copy when already float32
    fg = np.asarray(fg, dtype=np.float32).reshape(H, W, 3)
    flags = flags.reshape(H, W)
    unknown = (flags & FLAG_UNKNOWN) != 0
    if options.fill and np.any(unknown):
        vals = np.concatenate([alpha[..., None], fg], axis=-1).astype(np.float64)
        filled = _fill_clean(vals, (~unknown).astype(np.float64))
        alpha = np.clip(filled[..., 0], 0.0, 1.0).astype(np.float32)
        fg = np.maximum(filled[..., 1:], 0.0).astype(np.float32)
    return MatteResult(
        alpha=alpha,
        fg_premul=fg,
        alpha_std=astd.reshape(H, W),
        confidence=conf.reshape(H, W),
        flags=flags,
        noise_sigma=sigma_eff,
    )


def solve_matte(
    observations, backdrops, *, c_saturation=None, b_saturation=None, options: MattingOptions = MattingOptions()
) -> MatteResult:
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
    B, drift = _drift_corrected(C, B, cs, bs, options)
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
    return _with_drift(_finish(alpha, fg, S, res2, dof, flags, Br, H, W, options), drift)


def _weights_and_flags(C, B, cs, bs):
    finite = np.isfinite(C) & np.isfinite(B)
    sat = (C >= cs[:, None, None]) | (B >= bs[:, None, None])
    w = (finite & ~sat).astype(np.float64)
    flags = np.where(np.any(~finite, axis=(0, 2)), FLAG_INVALID, 0) | np.where(
        np.any(sat & finite, axis=(0, 2)), FLAG_SATURATED, 0
    )
    return w, flags.astype(np.uint8)


def _flat_system(observations, backdrops, c_saturation, b_saturation, options: MattingOptions):
    """What both NumPy solvers start from: the drift-corrected observations and
    backdrops as (K, H*W, 3) float64, their (K, H*W, 3) sample weights (0 = dropped),
    the (H*W,) uint8 flags, the image size (H, W) and the drift fit."""
    C, B, cs, bs = _prepare(observations, backdrops, c_saturation, b_saturation)
    B, drift = _drift_corrected(C, B, cs, bs, options)
    K, H, W, _ = C.shape
    C = C.reshape(K, H * W, 3).astype(np.float64)
    B = B.reshape(K, H * W, 3).astype(np.float64)
    w, flags = _weights_and_flags(C, B, cs, bs)
    return C, B, w, flags, (H, W), drift


def solve_matte_numpy(
    observations, backdrops, *, c_saturation=None, b_saturation=None, options: MattingOptions = MattingOptions()
) -> MatteResult:
    """The closed form of :func:`solve_matte`, vectorised in NumPy (float64)."""
    C, B, w, flags, (H, W), drift = _flat_system(observations, backdrops, c_saturation, b_saturation, options)
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
    return _with_drift(_finish(a, np.maximum(f, 0.0), S, res2, dof, flags, B.astype(np.float32), H, W, options), drift)


def solve_matte_reference(
    observations, backdrops, *, c_saturation=None, b_saturation=None, options: MattingOptions = MattingOptions()
) -> MatteResult:
    """Slow oracle: every pixel's 3K×4 system ``[I3 | -B_k] [F'; alpha] = C_k - B_k``
    solved with ``numpy.linalg.lstsq`` (dropped rows removed; alpha clamped to [0, 1]
    then ``F'`` re-solved with alpha fixed). Use on small images only."""
    Cr, Br, w, flags, (H, W), drift = _flat_system(observations, backdrops, c_saturation, b_saturation, options)
    K, N, _ = Cr.shape
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
        x = np.zeros(len(cols)) if A2.shape[0] == 0 else np.linalg.lstsq(A2, d, rcond=None)[0]
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
    return _with_drift(_finish(alpha, fg, S, res2, dof, flags, Br.astype(np.float32), H, W, options), drift)


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
    with the upsampled coarser one, ``x = w x + (1 - w) up(x_coarse)``. Parameters and
    result as :func:`fill_from_neighbours`.
    """
    v, w = _fill_inputs(values, weights)
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
                up = (1 - fy) * ((1 - fx) * coarse[y0, x0, c] + fx * coarse[y0, x1, c]) + fy * (
                    (1 - fx) * coarse[y1, x0, c] + fx * coarse[y1, x1, c]
                )
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
    return _fill_clean(*_fill_inputs(values, weights))


def _fill_inputs(values, weights) -> tuple[np.ndarray, np.ndarray]:
    """Shared input cleaning of the push-pull fill (not part of the algorithm the oracle checks):
    contiguous float64 (H, W, C) values, zero where the weight is 0 or the value is not finite,
    and (H, W) weights clipped to [0, 1] with NaN as 0."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 2:
        v = v[..., None]
    w = np.clip(np.nan_to_num(np.asarray(weights, dtype=np.float64), nan=0.0), 0.0, 1.0)
    if w.shape != v.shape[:2]:
        raise ShapeError(f"weights have shape {w.shape}, expected {v.shape[:2]}")
    v = np.ascontiguousarray(np.where(w[..., None] > 0, np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0), 0.0))
    return v, w


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


def backdrop_from_displays(
    camera, table_deg: float, geometry, patterns: dict, *, supersample: int = 3, off_radiance: float = 0.0
) -> np.ndarray:
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
    o, d = camera.supersampled_rays(s)
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


# --------------------------------------------------------------------------- photometric drift


@dataclass
class ShotDrift:
    """What :func:`correct_photometric_drift` found for one (object, backdrop) pair.

    Attributes
    ----------
    gain : (3,) per-channel ratio of the corrected to the original backdrop, mean over
        the backdrop pixels the fit used (1 = no drift). The exposure change is its mean,
        the white-balance change its ratio between channels.
    gain_p5, gain_p95 : (3,) 5th / 95th percentile over those pixels of the per-pixel
        gain (``mode="field"``: how much the drift varies across the frame; otherwise
        equal to ``gain`` up to offsets).
    matrix, offset : ``mode="affine"``: the fitted ``C = matrix @ B + offset`` (3×3, 3).
    shift_px : (dx, dy) translation of the backdrop shot's content relative to the object
        shot (the backdrop pixel ``(x + dx, y + dy)`` matches object pixel ``(x, y)``), or
        None when registration was off or failed.
    shift_applied : whether the backdrop was resampled by ``shift_px``.
    ncc : correlation coefficient of backdrop and object shot (grey, backdrop pixels)
        after the registration (None if not run).
    residual_before, residual_after : robust standard deviation (1.4826 · MAD) of the
        relative residual ``|C - B| / |B|`` over the backdrop pixels, before and after.
    fit_fraction : fraction of the frame used as backdrop by the last round.
    flow_px_p50, flow_px_p99 : median and 99th percentile of the length (pixels) of the
        non-rigid registration's displacement over the backdrop pixels, or None when
        it was off (``DriftOptions.flow``).
    """

    gain: tuple
    gain_p5: tuple
    gain_p95: tuple
    matrix: list | None
    offset: tuple | None
    shift_px: tuple | None
    shift_applied: bool
    ncc: float | None
    residual_before: float
    residual_after: float
    fit_fraction: float
    flow_px_p50: float | None = None
    flow_px_p99: float | None = None

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class DriftReport:
    """Output of :func:`correct_photometric_drift`: the mode, one :class:`ShotDrift` per
    pair, and notes (fallbacks taken)."""

    mode: str
    shots: list
    notes: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"mode": self.mode, "shots": [s.to_dict() for s in self.shots], "notes": list(self.notes)}


def _drift_corrected(C, B, cs, bs, options: MattingOptions):
    if options.drift == "none":
        return B, None
    Bc, report = _correct(C, B, cs, bs, options.drift, options.drift_options, replace(options, drift="none"))
    return Bc, report


def _with_drift(result: MatteResult, drift) -> MatteResult:
    result.drift = drift
    return result


def object_support(alpha, *, seed: float = 0.9, low: float = 0.1, margin_px: int = 0) -> np.ndarray:
    """Pixels that belong to (or lie next to) the object in a matte: connected regions
    (8-neighbourhood) of ``alpha > low`` that contain at least one ``alpha > seed``
    pixel, dilated by ``margin_px`` (square).

    Parameters
    ----------
    alpha : (H, W) float in [0, 1].

    Returns
    -------
    (H, W) bool.
    """
    import cv2

    a = np.nan_to_num(np.asarray(alpha, dtype=np.float32), nan=1.0)
    if a.ndim != 2:
        raise ShapeError(f"alpha has shape {a.shape}, expected (H, W)")
    n, lab_cv = cv2.connectedComponents((a > low).astype(np.uint8), connectivity=8)
    lab = np.asarray(lab_cv, np.int64)  # cv2's stubs type the labels as MatLike
    keep = np.zeros(n, bool)
    keep[np.unique(lab[a > seed])] = True
    keep[0] = False
    obj = keep[lab]
    if margin_px > 0 and obj.any():
        k = 2 * int(margin_px) + 1
        obj = cv2.dilate(obj.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    return obj


def _tukey(r, w, c):
    """Tukey biweights of residuals ``r`` (>= 0) scaled by their robust spread over w > 0."""
    sel = r[w > 0]
    s = 1.4826 * float(np.median(sel)) if sel.size else 0.0
    t = c * max(s, 1e-9)
    u = np.minimum(r / t, 1.0)
    return (1.0 - u * u) ** 2


def _rel_residual(c, pred, b):
    """|C - pred| / (|B| + floor) per pixel; (H, W, 3) inputs."""
    nb = np.sqrt(np.einsum("...c,...c->...", b, b))
    flat = nb.reshape(-1)
    floor = 1e-3 * max(float(np.percentile(flat[:: max(1, flat.size // 20_000)], 99)), 1e-12)
    e = c - pred
    return np.sqrt(np.einsum("...c,...c->...", e, e)) / (nb + floor)


def _fit_gain(c, b, w, iters, tc):
    """Per-channel gain ``C = g B`` (IRLS, Tukey). Returns prediction and per-pixel gain."""
    rw = np.ones(w.shape)
    g = np.ones(3)
    for _ in range(iters):
        ww = (w * rw)[..., None]
        den = (ww * b * b).sum((0, 1))
        g = np.where(den > 0, (ww * b * c).sum((0, 1)) / np.where(den > 0, den, 1.0), 1.0)
        rw = _tukey(_rel_residual(c, g * b, b), w, tc)
    return g * b, np.broadcast_to(g, b.shape), None


def _fit_affine(c, b, w, iters, tc):
    """``C = M B + o`` (3×3 + offset, IRLS, Tukey)."""
    H, W, _ = b.shape
    A = np.concatenate([b.reshape(-1, 3), np.ones((H * W, 1))], axis=1)
    cf = c.reshape(-1, 3)
    rw = np.ones(H * W)
    X = np.vstack([np.eye(3), np.zeros((1, 3))])
    wf = w.reshape(-1)
    for _ in range(iters):
        ww = wf * rw
        sel = ww > 0
        if sel.sum() < 8:
            break
        sw = np.sqrt(ww[sel])[:, None]
        X = np.linalg.lstsq(A[sel] * sw, cf[sel] * sw, rcond=None)[0]
        pred = (A @ X).reshape(H, W, 3)
        rw = _tukey(_rel_residual(c, pred, b), w, tc).reshape(-1)
    pred = (A @ X).reshape(H, W, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        gpix = np.where(b > 0, pred / np.where(b > 0, b, 1.0), 1.0)
    return pred, gpix, X


def _fit_poly_gain(c, b, w, iters, tc, deg=2, step=2):
    """Per-channel gain that is a polynomial of degree ``deg`` in (x, y): the robust
    first round of ``mode="field"``, before the object is known (a local field would
    absorb the object; a smooth polynomial cannot). Fitted on every ``step``-th row and
    column (6 unknowns per channel need far fewer pixels) by weighted normal equations,
    well conditioned on [-1, 1]²; evaluated on the full grid."""
    H, W, _ = b.shape
    terms = [(i, j) for i in range(deg + 1) for j in range(deg + 1 - i)]

    def basis(yy, xx):
        u = (xx.reshape(-1) + 0.5) / W * 2 - 1
        v = (yy.reshape(-1) + 0.5) / H * 2 - 1
        return np.stack([u**i * v**j for i, j in terms], axis=1)

    ys, xs = np.arange(0, H, step), np.arange(0, W, step)
    Phi = basis(*np.meshgrid(ys, xs, indexing="ij"))
    cs, bs_, ws = c[::step, ::step], b[::step, ::step], w[::step, ::step]
    wf = ws.reshape(-1)
    bf, cf = bs_.reshape(-1, 3), cs.reshape(-1, 3)
    rw = np.ones(wf.size)
    X = np.zeros((Phi.shape[1], 3))
    X[0] = 1.0  # the constant term is the first basis function
    for _ in range(iters):
        ww = wf * rw
        if np.count_nonzero(ww) < 4 * Phi.shape[1]:
            break
        for ch in range(3):
            A = Phi * bf[:, ch : ch + 1]
            Aw = A * ww[:, None]
            M = Aw.T @ A
            rhs = Aw.T @ cf[:, ch]
            try:
                X[:, ch] = np.linalg.solve(M, rhs)
            except np.linalg.LinAlgError:  # e.g. a channel that is 0 in every backdrop pixel
                X[:, ch] = np.linalg.lstsq(M, rhs, rcond=None)[0]
        pred = ((Phi @ X) * bf).reshape(cs.shape)
        rw = _tukey(_rel_residual(cs, pred, bs_), ws, tc).reshape(-1)
    # on the full grid the basis is separable: g_c = V A_c U^T with A_c[j, i] = X[(i, j), c]
    U = np.stack([((np.arange(W) + 0.5) / W * 2 - 1) ** i for i in range(deg + 1)], axis=1)
    V = np.stack([((np.arange(H) + 0.5) / H * 2 - 1) ** j for j in range(deg + 1)], axis=1)
    gpix = np.empty((H, W, 3))
    for ch in range(3):
        A = np.zeros((deg + 1, deg + 1))
        for t, (i, j) in enumerate(terms):
            A[j, i] = X[t, ch]
        gpix[..., ch] = V @ A @ U.T
    return gpix * b, gpix, None


def _fit_field(c, b, w, iters, tc, sigma_px):
    """Per-channel gain field by normalised convolution: ``g = G*(w B C) / G*(w B²)`` with
    a Gaussian window G, IRLS-reweighted; where the window holds too little backdrop
    (behind the object) the field is filled from its neighbours (push-pull). For wide
    windows the sums are area-decimated by ``f = sigma // 3`` before blurring and the
    field is upsampled bilinearly (the field is smooth at that scale; 4x less work at
    full-size photographs)."""
    import cv2

    H, W = w.shape
    f = max(1, int(sigma_px // 3))
    small = (max(1, W // f), max(1, H // f))

    def down(x):
        return x if f == 1 else cv2.resize(x, small, interpolation=cv2.INTER_AREA)

    rw = np.ones(w.shape)
    g = np.ones(b.shape)
    s = sigma_px / f
    for _ in range(iters):
        ww = w * rw
        wbc, wbb = ww[..., None] * b * c, ww[..., None] * b * b
        den = cv2.GaussianBlur(down(wbb), (0, 0), s)
        num = cv2.GaussianBlur(down(wbc), (0, 0), s)
        cover = cv2.GaussianBlur(down(ww), (0, 0), s)
        # a weak prior towards the global gain keeps g finite where B ~ 0
        g0 = wbc.sum((0, 1)) / np.maximum(wbb.sum((0, 1)), 1e-30)
        sel = cover > 1e-6
        eps = 1e-3 * np.maximum(np.median(den[sel], axis=0) if sel.any() else 1e-12, 1e-30)
        gl = (num + eps * g0) / (den + eps)
        conf = np.clip(cover / 0.3, 0.0, 1.0)
        gl = fill_from_neighbours(np.where(conf[..., None] > 0, gl, 0.0), conf)
        g = gl if f == 1 else cv2.resize(gl, (W, H), interpolation=cv2.INTER_LINEAR)
        rw = _tukey(_rel_residual(c, g * b, b), w, tc)
    return g * b, g, None


def _estimate_shift(c, b, w, *, iters: int = 12, max_shift_px: float = 4.0, max_points: int = 60_000):
    """Sub-pixel translation of backdrop ``b`` onto object shot ``c`` over mask ``w``
    (Lucas-Kanade / Gauss-Newton with a per-channel gain and offset re-fitted every
    iteration, so photometric drift does not bias it). ``b`` is sampled with a cubic
    B-spline at up to ``max_points`` evenly spread backdrop pixels. Returns
    ((dx, dy), ncc) with ncc the correlation coefficient (grey) after alignment, or
    (None, None) when it does not converge within ``max_shift_px``.

    (OpenCV's masked ECC was tried first: on synthetic data with a known shift its mask
    handling biased the estimate by 0.07-0.25 px; warpAffine-based resampling stalls
    up to 0.04 px off, as it quantises positions to 1/32 px.)
    """
    from scipy import ndimage

    H, W = w.shape
    sel = w > 0
    border = int(math.ceil(max_shift_px)) + 2
    sel[:border] = sel[-border:] = False
    sel[:, :border] = sel[:, -border:] = False
    ys, xs = np.nonzero(sel)
    if ys.size < 100:
        return None, None
    stride = max(1, ys.size // max_points)
    ys, xs = ys[::stride].astype(np.float64), xs[::stride].astype(np.float64)
    cs = c[ys.astype(int), xs.astype(int)].astype(np.float64)
    b64 = b.astype(np.float64)
    coef = [ndimage.spline_filter(b64[..., ch], order=3, mode="nearest") for ch in range(3)]
    gy_img, gx_img = np.gradient(b64, axis=(0, 1))

    def sample(d):
        yy, xx = ys + d[1], xs + d[0]
        bv = np.stack(
            [ndimage.map_coordinates(coef[ch], [yy, xx], order=3, mode="nearest", prefilter=False) for ch in range(3)],
            -1,
        )
        return bv, yy, xx

    d = np.zeros(2)
    for _ in range(iters):
        bv, yy, xx = sample(d)
        # the Jacobian only steers the iteration (the fixed point is set by bv): linear
        # interpolation of the gradient images is enough
        gxv = np.stack(
            [ndimage.map_coordinates(gx_img[..., ch], [yy, xx], order=1, mode="nearest") for ch in range(3)], -1
        )
        gyv = np.stack(
            [ndimage.map_coordinates(gy_img[..., ch], [yy, xx], order=1, mode="nearest") for ch in range(3)], -1
        )
        # photometry given the shift: per channel c = g b + o
        mb, mc = bv.mean(0), cs.mean(0)
        vb = ((bv - mb) ** 2).sum(0)
        g = np.where(vb > 0, ((bv - mb) * (cs - mc)).sum(0) / np.where(vb > 0, vb, 1.0), 1.0)
        r = cs - g * bv - (mc - g * mb)
        jx, jy = g * gxv, g * gyv
        A = np.array([[(jx * jx).sum(), (jx * jy).sum()], [(jx * jy).sum(), (jy * jy).sum()]])
        rhs = np.array([(jx * r).sum(), (jy * r).sum()])
        try:
            step = np.linalg.solve(A, rhs)
        except np.linalg.LinAlgError:  # no texture in the backdrop pixels
            return None, None
        d = d + step
        if not np.all(np.isfinite(d)) or np.hypot(*d) > max_shift_px:
            log.warning("drift registration did not converge (|shift| > %.1f px)", max_shift_px)
            return None, None
        if np.hypot(*step) < 1e-3:
            break
    bg, cg = sample(d)[0].mean(-1), cs.mean(-1)
    ncc = float(np.corrcoef(bg, cg)[0, 1]) if bg.std() > 0 and cg.std() > 0 else None
    return (float(d[0]), float(d[1])), ncc


def shift_image(image, shift_px) -> np.ndarray:
    """Resample ``image`` (H, W[, C]) so that output pixel ``(x, y)`` is input pixel
    ``(x + dx, y + dy)``: cubic B-spline (``scipy.ndimage.shift``), edges replicated.
    float32. (OpenCV's warpAffine quantises positions to 1/32 px, which makes a
    sub-pixel Gauss-Newton stall up to 0.04 px off.)"""
    from scipy import ndimage

    a = np.asarray(image, dtype=np.float32)
    sh = (-float(shift_px[1]), -float(shift_px[0])) + (0.0,) * (a.ndim - 2)
    return ndimage.shift(a, sh, order=3, mode="nearest").astype(np.float32)


@njit(cache=True, inline="always")
def _keys(t):
    """Keys' cubic convolution weights (a = -0.5, Catmull-Rom) of the taps at offsets -1..2."""
    t2 = t * t
    t3 = t2 * t
    return (
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    )


@njit(parallel=True, cache=True)
def _warp_kernel(a, flow, out):
    H, W, C = a.shape
    for y in prange(H):
        for x in range(W):
            sx = x + flow[y, x, 0]
            sy = y + flow[y, x, 1]
            x0 = math.floor(sx)
            y0 = math.floor(sy)
            wx = _keys(sx - x0)
            wy = _keys(sy - y0)
            for c in range(C):
                acc = 0.0
                for j in range(4):
                    yy = min(max(y0 - 1 + j, 0), H - 1)
                    row = 0.0
                    for i in range(4):
                        xx = min(max(x0 - 1 + i, 0), W - 1)
                        row += wx[i] * a[yy, xx, c]
                    acc += wy[j] * row
                out[y, x, c] = acc


def warp_image(image, flow_px) -> np.ndarray:
    """Resample ``image`` (H, W[, C]) so that output pixel ``(x, y)`` is input pixel
    ``(x + fx, y + fy)`` with ``(fx, fy) = flow_px[y, x]`` (the convention of
    :func:`shift_image`, per pixel): Keys' cubic convolution (Catmull-Rom; exact on
    quadratics), edges replicated, numba. float32. (``cv2.remap`` quantises positions
    to 1/32 px, which stalls the flow's Gauss-Newton up to 0.03 px short.)"""
    a = np.asarray(image, dtype=np.float32)
    f = np.ascontiguousarray(flow_px, dtype=np.float64)
    H, W = a.shape[:2]
    if f.shape != (H, W, 2):
        raise ShapeError(f"flow has shape {f.shape}, expected {(H, W, 2)}")
    a3 = np.ascontiguousarray(a.reshape(H, W, -1))
    out = np.empty_like(a3)
    _warp_kernel(a3, f, out)
    return out.reshape(a.shape)


def estimate_backdrop_flow(
    observation,
    backdrop,
    weights,
    *,
    sigma_px: float = 1.0,
    max_px: float = 2.0,
    iters: int = 6,
    prior: float = 1.0,
) -> np.ndarray:
    """Dense displacement of a backdrop shot onto its object shot, on backdrop pixels:
    the non-rigid registration of :func:`correct_photometric_drift` (``DriftOptions.flow``).

    Lucas-Kanade with a Gaussian window per pixel, iterated (Gauss-Newton, the backdrop
    re-sampled each time), over all three channels, each scaled by the backdrop's
    median level on ``weights`` so a dark channel counts as much as a bright one. Each
    update solves ``(A + lambda n I) d = b`` with the window's structure tensor ``A``,
    its weight ``n`` and ``lambda`` = ``prior`` times the noise variance of the
    starting residual (robust, from its pixel-scale part; Tikhonov): where the backdrop has no texture above the noise the flow stays near 0,
    and along a fold (1-D structure) only the displacement across it is found — the
    component that matters. Lengths are clipped to ``max_px``; where the window holds
    too little backdrop (behind the object) the field is filled from its surroundings
    (push-pull).

    Parameters
    ----------
    observation, backdrop : (H, W, 3) float
        The object shot and its backdrop shot, photometrically matched already (the
        flow explains the remaining difference by motion only).
    weights : (H, W) float
        > 0 on backdrop pixels (object absent), 0 elsewhere.

    Returns
    -------
    (H, W, 2) float32 ``(fx, fy)`` in pixels: ``warp_image(backdrop, flow)`` matches
    ``observation`` on the backdrop pixels.
    """
    import cv2

    c = np.asarray(observation, dtype=np.float32)
    b = np.asarray(backdrop, dtype=np.float32)
    w = (np.asarray(weights) > 0).astype(np.float32)
    H, W = w.shape
    if c.shape != (H, W, 3) or b.shape != (H, W, 3):
        raise ShapeError(f"observation {c.shape} and backdrop {b.shape} must be (H, W, 3) with weights {w.shape}")
    flow = np.zeros((H, W, 2), np.float32)
    sel = w > 0
    if sel.sum() < 16:
        return flow
    level = np.maximum(np.median(b[sel], axis=0), 1e-6).astype(np.float32)
    c, b = c / level, b / level
    # the noise of the residual from its pixel-scale part (residual minus the mean of
    # its 4 neighbours: var = 1.25 sigma^2 for white noise), which a smooth motion
    # barely reaches, so a frame that moved everywhere does not read as noise
    r = c - b
    hp = r - 0.25 * (np.roll(r, 1, 0) + np.roll(r, -1, 0) + np.roll(r, 1, 1) + np.roll(r, -1, 1))
    inner = sel.copy()
    inner[[0, -1]] = False
    inner[:, [0, -1]] = False
    h = hp[inner] if inner.any() else hp[sel]
    mad = np.median(np.abs(h - np.median(h, axis=0)), axis=0)
    # floored at 0.1 % of the level per channel, so noise-free data is held too
    lam = max(float(np.sum((1.4826 * mad) ** 2 / 1.25)), 3e-6) * prior

    def blur(x):
        return cv2.GaussianBlur(x, (0, 0), sigma_px)

    n = blur(w)
    for _ in range(iters):
        bw = warp_image(b, flow)
        ix = cv2.Sobel(bw, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        iy = cv2.Sobel(bw, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        r = (c - bw) * w[..., None]
        axx = blur((w[..., None] * ix * ix).sum(-1)) + lam * n
        axy = blur((w[..., None] * ix * iy).sum(-1))
        ayy = blur((w[..., None] * iy * iy).sum(-1)) + lam * n
        # the prior holds the whole flow, not the step, towards 0: (A + lam) d = b - lam f
        bx = blur((ix * r).sum(-1)) - lam * n * flow[..., 0]
        by = blur((iy * r).sum(-1)) - lam * n * flow[..., 1]
        det = axx * ayy - axy * axy
        ok = det > 1e-20
        det = np.where(ok, det, 1.0)
        d = np.stack(
            [np.where(ok, (ayy * bx - axy * by) / det, 0.0), np.where(ok, (axx * by - axy * bx) / det, 0.0)], -1
        )
        flow = flow + d.astype(np.float32)
        length = np.hypot(flow[..., 0], flow[..., 1])
        flow *= np.minimum(1.0, max_px / np.maximum(length, 1e-12))[..., None]
    conf = np.clip(n / 0.3, 0.0, 1.0)
    return fill_from_neighbours(np.where(conf[..., None] > 0, flow, 0.0), conf).astype(np.float32)


def correct_photometric_drift(
    observations,
    backdrops,
    *,
    mode: DriftMode = "field",
    options: DriftOptions = DriftOptions(),
    matting: MattingOptions = MattingOptions(),
    c_saturation=None,
    b_saturation=None,
):
    """Map each backdrop shot onto the photometry (and position) of its object shot.

    Real two-backdrop shots drift: the camera re-meters exposure and white balance
    between the backdrop and the object shot, displays warm up, daylight changes, a
    cloth settles. Left alone, a drift of a few percent becomes alpha of the same order
    over the whole backdrop (``alpha ~ (1 - g) B·ΔB / |ΔB|²``). The transform of shot k
    is fitted on pixels where the object is absent, alternating with the matte:

    1. round 0: a robust (Tukey IRLS) fit over every valid pixel — the object is a
       minority of the frame, so the weights reject it; ``mode="field"`` uses a
       quadratic-in-(x, y) gain here, which cannot absorb the object;
    2. matte with the corrected backdrops, object support = hysteresis regions of alpha
       (:func:`object_support`), dilated; fit again on the rest;
    3. after round 0, a sub-pixel translation per shot on the backdrop pixels
       (Lucas-Kanade with per-channel gain and offset; reported, and applied when longer
       than ``options.apply_shift_px``);
    4. in the last round (``options.flow``), a dense non-rigid registration of each
       backdrop shot onto its object shot on the backdrop pixels
       (:func:`estimate_backdrop_flow`), for cloth folds that moved between the shots;
       the backdrop is resampled by it before the last fit.

    Modes: ``"gain"`` per-channel gain ``C = g ∘ B``; ``"affine"`` ``C = M B + o`` (3×3 +
    offset); ``"field"`` a per-channel gain field that varies smoothly over the frame
    (Gaussian window ``field_sigma_rel · max(H, W)``, filled behind the object from its
    surroundings). Measured on the flowers set (tests/reconstruct/test_matting_real.py):
    of its pure-backdrop band 53 % is at alpha < 0.05 uncorrected, 64 % with "gain", 69 %
    with "affine" — the drift varies over the frame (lighting changed the fold shading)
    — and 99.04 % with "field" (99.95 % without the leaf tip that reaches into the band;
    98.90 % without the non-rigid registration, ``DriftOptions.flow``).

    Parameters
    ----------
    observations, backdrops : (K, H, W, 3) float
        Linear radiance; K >= 2 as for :func:`solve_matte`.
    mode : {"none", "gain", "affine", "field"}
    options : DriftOptions
    matting : MattingOptions used for the intermediate mattes (its ``drift`` is ignored).
    c_saturation, b_saturation : as for :func:`solve_matte`: such samples are not fitted.

    Returns
    -------
    corrected : (K, H, W, 3) float32
        The backdrops to pass to :func:`solve_matte` (``drift="none"``).
    report : DriftReport
    """
    C, B, cs, bs = _prepare(observations, backdrops, c_saturation, b_saturation)
    if mode not in _DRIFT_MODES:
        raise InputError(f"drift mode must be one of {', '.join(_DRIFT_MODES)}, got {mode!r}")
    return _correct(C, B, cs, bs, mode, options, replace(matting, drift="none"))


def _correct(C, B, cs, bs, mode, opts: DriftOptions, matting: MattingOptions):
    K, H, W, _ = C.shape
    notes = []
    valid = np.all(np.isfinite(C) & np.isfinite(B), axis=-1)
    valid &= np.all(C < cs[:, None, None, None], axis=-1) & np.all(B < bs[:, None, None, None], axis=-1)
    C64 = np.where(np.isfinite(C), C, 0.0).astype(np.float64)
    Bsrc = np.where(np.isfinite(B), B, 0.0).astype(np.float64)
    ident = [dict(g=np.ones((H, W, 3)), X=None) for _ in range(K)]
    shifts = [None] * K
    nccs = [None] * K
    applied = [False] * K
    flows: list[tuple[float, float] | None] = [None] * K
    if mode == "none":
        Bc = B.copy()
        fits = ident
        masks = [valid[k] for k in range(K)]
    else:
        Bc = B.copy()
        fits = list(ident)
        masks = [valid[k] for k in range(K)]
        size = max(H, W)
        margin = int(round(opts.object_margin_rel * size))
        sigma = max(opts.field_sigma_rel * size, opts.field_sigma_min_px)
        obj = np.zeros((H, W), bool)
        for rnd in range(opts.rounds):
            for k in range(K):
                w = (valid[k] & ~obj).astype(np.float64)
                if w.sum() < max(64, 1e-3 * H * W):
                    notes.append(
                        f"shot {k}: round {rnd}: only {int(w.sum())} backdrop pixels; kept the previous correction"
                    )
                    continue
                masks[k] = w > 0
                if rnd == 1 and opts.register:
                    shifts[k], nccs[k] = _estimate_shift(C64[k], Bsrc[k], w)
                    if shifts[k] is not None and math.hypot(*shifts[k]) >= opts.apply_shift_px:
                        Bsrc[k] = shift_image(Bsrc[k], shifts[k])
                        applied[k] = True
                if rnd >= 1 and rnd == opts.rounds - 1 and opts.flow:
                    # the backdrop (as registered so far) under the previous round's gain
                    # is matched photometrically by the fine field, so what is left on
                    # backdrop pixels is motion and noise. (A wider reference field would
                    # let the flow see all of a moved fold, but on the flowers set the
                    # fold's shading changed too, and the flow then reads shading as
                    # motion: 4x wider, 345 band pixels left instead of 89.)
                    f = estimate_backdrop_flow(
                        C64[k],
                        np.asarray(fits[k]["g"]) * Bsrc[k],
                        w,
                        sigma_px=opts.flow_sigma_px,
                        max_px=opts.flow_max_px,
                        iters=opts.flow_iters,
                        prior=opts.flow_prior,
                    )
                    Bsrc[k] = warp_image(Bsrc[k], f).astype(np.float64)
                    length = np.hypot(f[..., 0], f[..., 1])[w > 0]
                    flows[k] = (float(np.median(length)), float(np.percentile(length, 99)))
                if mode == "gain":
                    pred, g, X = _fit_gain(C64[k], Bsrc[k], w, 6, opts.tukey_c)
                elif mode == "affine":
                    pred, g, X = _fit_affine(C64[k], Bsrc[k], w, 6, opts.tukey_c)
                elif rnd == 0:
                    pred, g, X = _fit_poly_gain(C64[k], Bsrc[k], w, 6, opts.tukey_c)
                else:
                    pred, g, X = _fit_field(C64[k], Bsrc[k], w, 3, opts.tukey_c, sigma)
                fits[k] = dict(g=g, X=X)
                # keep what the sensor could not measure as it was: dropped samples stay dropped
                Bc[k] = np.where(np.isfinite(B[k]), pred, B[k]).astype(np.float32)
            if rnd + 1 < opts.rounds:
                alpha = solve_matte(C, Bc, c_saturation=cs, b_saturation=bs, options=matting).alpha
                obj = object_support(alpha, seed=opts.object_seed, low=opts.object_low, margin_px=margin)
    shots = []
    for k in range(K):
        m = masks[k]
        g = np.asarray(fits[k]["g"])
        if m.any():
            b_m = Bsrc[k][m]
            gm = np.where(b_m.sum(0) > 0, Bc[k][m].astype(np.float64).sum(0) / np.maximum(b_m.sum(0), 1e-30), 1.0)
            gp = np.broadcast_to(g, (H, W, 3))[m]
            p5, p95 = np.percentile(gp, 5, axis=0), np.percentile(gp, 95, axis=0)
            rb = _rel_residual(C64[k], np.where(np.isfinite(B[k]), B[k], 0.0), Bsrc[k])[m]
            ra = _rel_residual(C64[k], Bc[k].astype(np.float64), Bsrc[k])[m]
            res_b, res_a = 1.4826 * float(np.median(rb)), 1.4826 * float(np.median(ra))
        else:
            gm = p5 = p95 = np.ones(3)
            res_b = res_a = float("nan")
        X = fits[k]["X"]
        fl = flows[k]
        shots.append(
            ShotDrift(
                gain=tuple(float(x) for x in gm),
                gain_p5=tuple(float(x) for x in p5),
                gain_p95=tuple(float(x) for x in p95),
                matrix=None if X is None else X[:3].T.tolist(),
                offset=None if X is None else tuple(float(x) for x in X[3]),
                shift_px=shifts[k],
                shift_applied=applied[k],
                ncc=nccs[k],
                residual_before=res_b,
                residual_after=res_a,
                fit_fraction=float(m.mean()),
                flow_px_p50=None if fl is None else fl[0],
                flow_px_p99=None if fl is None else fl[1],
            )
        )
        log.info("drift shot %d: gain %s, shift %s (applied %s)", k, np.round(gm, 4), shifts[k], applied[k])
    return Bc, DriftReport(mode=mode, shots=shots, notes=notes)
