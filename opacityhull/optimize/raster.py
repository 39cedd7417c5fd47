"""Differentiable EWA surfel rasterizer on the CPU (forward and analytic backward).

Each surfel is an oriented elliptical Gaussian disc (a 2DGS-like surfel): the degenerate
3-D Gaussian of covariance ``R diag(su², sv², 0) Rᵀ`` whose tangent axes are the first two
columns of the rotation ``R`` of its quaternion. It is projected with the local affine
approximation of the perspective projection at its centre (Zwicker et al. 2001, the EWA
splatting of the source notes; Kerbl et al. 2023): the screen covariance is
``J W Σ Wᵀ Jᵀ + lowpass·I``, the last term being EWA's screen-space resampling filter,
which keeps edge-on and zero-scale discs finite. Surfels behind ``near_m`` or whose
``cutoff_sigma`` ellipse covers no pixel centre are culled; the rest are binned into
square tiles, each tile's list in view-depth order (ties by surfel index, so results are
deterministic), and composited front to back with
``alpha_i = min(0.99, opacity_i · exp(-½ dᵀ Σ'⁻¹ d))``; fragments with
``alpha < alpha_min`` or outside the cutoff ellipse are skipped, and a pixel stops once its
transmittance falls below ``transmittance_min`` (after the fragment that took it there).

The backward pass walks each pixel's fragments back to front, recovering the
transmittance before each fragment from the final one, and chains the gradients through
the compositing, the 2-D Gaussian, the conic, the projection (``J`` and the world-to-camera
rotation ``W``), the covariance from quaternion and scales, and the colour.

Layout of the work: a per-surfel set-up (``prange`` over surfels), one global depth sort,
a deterministic counting fill of the tile lists (a fixed number of chunks, whatever the
thread count), then ``prange`` over groups of tiles for the per-pixel passes. A tile's
pixels are touched only by the splats' own cutoff ellipses (row by row), not the whole
tile. The backward pass writes each (tile, surfel) entry's partial gradient into its own
slot and the slots are summed per surfel in entry order: no races, and the same bytes
whatever the thread count. The NumPy twin is :mod:`opacityhull.optimize.raster_reference`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from ..errors import InputError, ShapeError

__all__ = [
    "RasterCamera",
    "SplatParams",
    "RasterConfig",
    "RasterOutput",
    "SplatGrads",
    "rasterize",
    "rasterize_backward",
    "ALPHA_MAX",
]

ALPHA_MAX = 0.99
"""The per-fragment opacity clamp (keeps ``1 - alpha`` invertible in the backward pass)."""

_FILL_CHUNKS = 16  # fixed, so the tile lists do not depend on the thread count
_TILE_GROUPS = 64  # tiles are dealt round-robin to this many groups: balanced static split


@dataclass(frozen=True, kw_only=True)
class RasterCamera:
    """A pinhole camera for the rasterizer.

    Attributes
    ----------
    K : (3, 3) float64 pixel intrinsics, OpenCV convention (pixel centres at integer
        coordinates, last row ``0 0 1``).
    cam_from_world : (3, 4) float64 ``[R | t]``, metres.
    width, height : image size in pixels.
    """

    K: np.ndarray
    cam_from_world: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, np.float64)
        M = np.asarray(self.cam_from_world, np.float64)
        if K.shape != (3, 3):
            raise ShapeError(f"RasterCamera.K has shape {K.shape}, expected (3, 3)")
        if M.shape != (3, 4):
            raise ShapeError(f"RasterCamera.cam_from_world has shape {M.shape}, expected (3, 4)")
        if int(self.width) < 1 or int(self.height) < 1:
            raise InputError(f"RasterCamera size {self.width}x{self.height}: expected both >= 1")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_from_world", M)


@dataclass(frozen=True, kw_only=True)
class SplatParams:
    """N oriented elliptical Gaussian discs (2DGS-like surfels).

    Attributes
    ----------
    means : (N, 3) float32 world metres.
    quats : (N, 4) float32 (w, x, y, z), normalised inside (a zero quaternion is the
        identity); the disc spans the rotated local x and y axes, its normal is local z.
    log_scales : (N, 2) float32 log of the standard deviation along the two tangent axes,
        metres.
    opacity_logits : (N,) float32, opacity = sigmoid(logit).
    colors : (N, 3) float32 linear RGB for this view.
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    colors: np.ndarray

    def __post_init__(self) -> None:
        n = np.shape(self.means)[0] if np.ndim(self.means) == 2 else -1
        for name, tail in (
            ("means", (3,)),
            ("quats", (4,)),
            ("log_scales", (2,)),
            ("opacity_logits", ()),
            ("colors", (3,)),
        ):
            a = getattr(self, name)
            if np.shape(a) != (n, *tail):
                raise ShapeError(f"SplatParams.{name} has shape {np.shape(a)}, expected {(max(n, 0), *tail)}")

    @property
    def n(self) -> int:
        return int(np.shape(self.means)[0])


@dataclass(frozen=True, kw_only=True)
class RasterConfig:
    """Options of :func:`rasterize` (see the module docstring for their meaning).

    ``lowpass_px2`` is EWA's screen-space filter variance (px², must be > 0: it keeps
    edge-on discs invertible); ``cutoff_sigma`` bounds each splat at that Mahalanobis
    radius; ``tile_px`` is the side of the square bins.
    """

    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lowpass_px2: float = 0.3
    cutoff_sigma: float = 3.0
    near_m: float = 0.01
    alpha_min: float = 1 / 255
    transmittance_min: float = 1e-4
    tile_px: int = 16

    def __post_init__(self) -> None:
        if not self.lowpass_px2 > 0:
            raise InputError(f"RasterConfig.lowpass_px2 = {self.lowpass_px2}: expected > 0")
        if not self.cutoff_sigma > 0:
            raise InputError(f"RasterConfig.cutoff_sigma = {self.cutoff_sigma}: expected > 0")
        if not self.near_m > 0:
            raise InputError(f"RasterConfig.near_m = {self.near_m}: expected > 0")
        if not 1 <= int(self.tile_px) <= 256:
            raise InputError(f"RasterConfig.tile_px = {self.tile_px}: expected 1..256")
        if len(self.background) != 3:
            raise InputError(f"RasterConfig.background = {self.background}: expected 3 values")


@dataclass(frozen=True, kw_only=True, eq=False)
class _RasterContext:
    """What the backward pass needs from the forward pass (opaque to callers)."""

    n: int
    width: int
    height: int
    config: RasterConfig
    mu: np.ndarray  # (N, 2) f64 projected centre, px
    conic: np.ndarray  # (N, 3) f64 inverse screen covariance (A, B, C)
    ext: np.ndarray  # (N, 2) f64 half extent of the cutoff ellipse, px
    opac: np.ndarray  # (N,) f64 sigmoid(logit)
    depth: np.ndarray  # (N,) f64 view depth
    colors: np.ndarray  # (N, 3) f64
    tile_off: np.ndarray  # (n_tiles + 1,) int64
    ent_sid: np.ndarray  # (E,) int32 surfel of each entry, per tile in depth order
    t_final: np.ndarray  # (H, W) f64
    last: np.ndarray  # (H, W) int64 entry index of the last fragment composited, -1 none
    n_tx: int


@dataclass(frozen=True, kw_only=True, eq=False)
class RasterOutput:
    """The rendered view.

    Attributes
    ----------
    image : (H, W, 3) float32 linear RGB composited over ``config.background``.
    alpha : (H, W) float32 ``1 - final transmittance``.
    depth : (H, W) float32 alpha-weighted view depth ``Σ alpha_i T_i z_i`` (metres; divide
        by ``alpha`` for the mean depth of the covered part).
    n_fragments : number of (surfel, pixel) fragments composited.
    n_entries : number of (surfel, tile) entries in the tile lists.
    visible : (N,) bool, surfels that passed culling (in front of ``near_m``, ellipse on a
        pixel centre).
    ctx : state for :func:`rasterize_backward`.
    """

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    n_fragments: int
    n_entries: int
    visible: np.ndarray
    ctx: _RasterContext = field(repr=False)


@dataclass(frozen=True, kw_only=True, eq=False)
class SplatGrads:
    """Gradients of a scalar loss with respect to :class:`SplatParams` (same shapes,
    float32), plus ``means2d_abs`` (N,) float32 = |dL/d(projected 2-D centre)| in
    loss per pixel (the densification statistic) and ``visible`` (N,) bool."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    colors: np.ndarray
    means2d_abs: np.ndarray
    visible: np.ndarray


# ---------------------------------------------------------------------------- kernels


@njit(cache=True, error_model="numpy")
def _frame(quat, log_scale):
    """Unit quaternion → the disc's two scaled tangent axes (world) and their parts."""
    qw, qx, qy, qz = float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3])
    nq = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    nq = max(nq, 1e-12)
    w, x, y, z = qw / nq, qx / nq, qy / nq, qz / nq
    c0 = np.empty(3)
    c1 = np.empty(3)
    c0[0] = 1.0 - 2.0 * (y * y + z * z)
    c0[1] = 2.0 * (x * y + w * z)
    c0[2] = 2.0 * (x * z - w * y)
    c1[0] = 2.0 * (x * y - w * z)
    c1[1] = 1.0 - 2.0 * (x * x + z * z)
    c1[2] = 2.0 * (y * z + w * x)
    su = math.exp(float(log_scale[0]))
    sv = math.exp(float(log_scale[1]))
    return w, x, y, z, nq, c0, c1, su, sv


@njit(cache=True, parallel=True, error_model="numpy")
def _preprocess(means, quats, log_scales, logits, colors, K, M, width, height, lowpass, cutoff, near, tile):
    n = means.shape[0]
    mu = np.zeros((n, 2))
    conic = np.zeros((n, 3))
    ext = np.zeros((n, 2))
    opac = np.zeros(n)
    depth = np.zeros(n)
    col = np.zeros((n, 3))
    rect = np.zeros((n, 4), np.int64)
    valid = np.zeros(n, np.bool_)
    n_tx = (width + tile - 1) // tile
    n_ty = (height + tile - 1) // tile
    for i in prange(n):
        for c in range(3):
            col[i, c] = colors[i, c]
        lg = float(logits[i])
        opac[i] = 1.0 / (1.0 + math.exp(-lg))
        m0, m1, m2 = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        t0 = M[0, 0] * m0 + M[0, 1] * m1 + M[0, 2] * m2 + M[0, 3]
        t1 = M[1, 0] * m0 + M[1, 1] * m1 + M[1, 2] * m2 + M[1, 3]
        t2 = M[2, 0] * m0 + M[2, 1] * m1 + M[2, 2] * m2 + M[2, 3]
        depth[i] = t2
        if not t2 >= near:
            continue
        w, x, y, z, nq, c0, c1, su, sv = _frame(quats[i], log_scales[i])
        iz = 1.0 / t2
        ja0 = 0.0
        ja1 = 0.0
        jb0 = 0.0
        jb1 = 0.0
        for r in range(2):
            u = K[r, 0] * t0 + K[r, 1] * t1
            mu[i, r] = u * iz + K[r, 2]
            J0 = K[r, 0] * iz
            J1 = K[r, 1] * iz
            J2 = -u * iz * iz
            # camera-frame axes W c · s, then their images J (W c s)
            ta = 0.0
            tb = 0.0
            for k in range(3):
                wa = M[k, 0] * c0[0] + M[k, 1] * c0[1] + M[k, 2] * c0[2]
                wb = M[k, 0] * c1[0] + M[k, 1] * c1[1] + M[k, 2] * c1[2]
                Jk = J0 if k == 0 else (J1 if k == 1 else J2)
                ta += Jk * wa
                tb += Jk * wb
            if r == 0:
                ja0 = ta * su
                jb0 = tb * sv
            else:
                ja1 = ta * su
                jb1 = tb * sv
        a = ja0 * ja0 + jb0 * jb0 + lowpass
        b = ja0 * ja1 + jb0 * jb1
        c = ja1 * ja1 + jb1 * jb1 + lowpass
        det = a * c - b * b
        if not (det > 0 and math.isfinite(det) and math.isfinite(mu[i, 0]) and math.isfinite(mu[i, 1])):
            continue
        conic[i, 0] = c / det
        conic[i, 1] = -b / det
        conic[i, 2] = a / det
        hx = cutoff * math.sqrt(a)
        hy = cutoff * math.sqrt(c)
        ext[i, 0] = hx
        ext[i, 1] = hy
        # pixel centres inside the ellipse's box, clamped before the integer conversion
        x0 = math.ceil(min(max(mu[i, 0] - hx, -1.0), width + 1.0))
        x1 = math.floor(min(max(mu[i, 0] + hx, -1.0), width + 1.0))
        y0 = math.ceil(min(max(mu[i, 1] - hy, -1.0), height + 1.0))
        y1 = math.floor(min(max(mu[i, 1] + hy, -1.0), height + 1.0))
        x0 = max(x0, 0)
        y0 = max(y0, 0)
        x1 = min(x1, width - 1)
        y1 = min(y1, height - 1)
        if x0 > x1 or y0 > y1:
            continue
        rect[i, 0] = min(int(x0) // tile, n_tx - 1)
        rect[i, 1] = min(int(y0) // tile, n_ty - 1)
        rect[i, 2] = min(int(x1) // tile, n_tx - 1) + 1
        rect[i, 3] = min(int(y1) // tile, n_ty - 1) + 1
        valid[i] = True
    return mu, conic, ext, opac, depth, col, rect, valid


@njit(cache=True, parallel=True, error_model="numpy")
def _count_entries(order, rect, n_tx, n_tiles, chunks):
    m = order.shape[0]
    counts = np.zeros((chunks, n_tiles), np.int64)
    for c in prange(chunks):
        for j in range(c * m // chunks, (c + 1) * m // chunks):
            s = order[j]
            for ty in range(rect[s, 1], rect[s, 3]):
                for tx in range(rect[s, 0], rect[s, 2]):
                    counts[c, ty * n_tx + tx] += 1
    return counts


@njit(cache=True, parallel=True, error_model="numpy")
def _fill_entries(order, rect, n_tx, start, n_entries):
    chunks = start.shape[0]
    m = order.shape[0]
    ent = np.empty(n_entries, np.int32)
    for c in prange(chunks):
        pos = start[c].copy()
        for j in range(c * m // chunks, (c + 1) * m // chunks):
            s = order[j]
            for ty in range(rect[s, 1], rect[s, 3]):
                for tx in range(rect[s, 0], rect[s, 2]):
                    t = ty * n_tx + tx
                    ent[pos[t]] = s
                    pos[t] += 1
    return ent


@njit(cache=True, inline="always", error_model="numpy")
def _row_span(A, B, C, dy, cut2, xc0, xa, xb):
    """Pixel-centre x range [x0, x1] of one row of the cutoff ellipse inside the tile's
    columns [xa, xb), widened by a hair: the exact ``q <= cut2`` test is applied per pixel."""
    disc = B * B * dy * dy - A * (C * dy * dy - cut2)
    if disc < 0.0:
        disc = 0.0
    r = math.sqrt(disc) / A
    xc = xc0 - B * dy / A
    lo = min(max(xc - r - 1e-6, xa - 1.0), xb + 1.0)
    hi = min(max(xc + r + 1e-6, xa - 1.0), xb + 1.0)
    return max(xa, math.ceil(lo)), min(xb - 1, math.floor(hi))


@njit(cache=True, parallel=True, error_model="numpy")
def _forward(tile_off, ent, mu, conic, ext, opac, depth, col, width, height, tile, n_tx, cut2, amin, tmin, bg):
    n_tiles = tile_off.shape[0] - 1
    rgb = np.zeros((height, width, 3))
    dep = np.zeros((height, width))
    T = np.ones((height, width))
    last = np.full((height, width), -1, np.int64)
    nfrag = np.zeros(_TILE_GROUPS, np.int64)
    for g in prange(_TILE_GROUPS):
        for t in range(g, n_tiles, _TILE_GROUPS):
            ty = t // n_tx
            tx = t - ty * n_tx
            xa = tx * tile
            ya = ty * tile
            xb = min(xa + tile, width)
            yb = min(ya + tile, height)
            live = (xb - xa) * (yb - ya)
            nf = 0
            for k in range(tile_off[t], tile_off[t + 1]):
                s = ent[k]
                m0 = mu[s, 0]
                m1 = mu[s, 1]
                A = conic[s, 0]
                B = conic[s, 1]
                C = conic[s, 2]
                o = opac[s]
                ylo = max(ya, math.ceil(max(m1 - ext[s, 1] - 1e-6, ya - 1.0)))
                yhi = min(yb - 1, math.floor(min(m1 + ext[s, 1] + 1e-6, yb + 1.0)))
                for y in range(ylo, yhi + 1):
                    dy = y - m1
                    x0, x1 = _row_span(A, B, C, dy, cut2, m0, xa, xb)
                    for x in range(x0, x1 + 1):
                        Tp = T[y, x]
                        if Tp < tmin:
                            continue
                        dx = x - m0
                        q = A * dx * dx + 2.0 * B * dx * dy + C * dy * dy
                        if q > cut2:
                            continue
                        a = min(ALPHA_MAX, o * math.exp(-0.5 * q))
                        if a < amin:
                            continue
                        w = a * Tp
                        rgb[y, x, 0] += w * col[s, 0]
                        rgb[y, x, 1] += w * col[s, 1]
                        rgb[y, x, 2] += w * col[s, 2]
                        dep[y, x] += w * depth[s]
                        Tn = Tp * (1.0 - a)
                        T[y, x] = Tn
                        last[y, x] = k
                        nf += 1
                        if Tn < tmin:
                            live -= 1
                if live == 0:
                    break
            nfrag[g] += nf
    image = np.empty((height, width, 3), np.float32)
    alpha = np.empty((height, width), np.float32)
    dep32 = np.empty((height, width), np.float32)
    for y in prange(height):
        for x in range(width):
            for c in range(3):
                image[y, x, c] = rgb[y, x, c] + T[y, x] * bg[c]
            alpha[y, x] = 1.0 - T[y, x]
            dep32[y, x] = dep[y, x]
    return image, alpha, dep32, T, last, nfrag.sum()


@njit(cache=True, parallel=True, error_model="numpy")
def _backward(
    tile_off, ent, mu, conic, ext, opac, col, width, height, tile, n_tx, cut2, amin, t_final, last, bg, dimg, dalpha
):
    """Per entry: dL/d(mu0, mu1, A, B, C, opacity, r, g, b), into its own slot."""
    n_tiles = tile_off.shape[0] - 1
    slots = np.zeros((ent.shape[0], 9))
    T = t_final.copy()
    Bacc = np.empty((height, width, 3))
    for g in prange(_TILE_GROUPS):
        for t in range(g, n_tiles, _TILE_GROUPS):
            ty = t // n_tx
            tx = t - ty * n_tx
            xa = tx * tile
            ya = ty * tile
            xb = min(xa + tile, width)
            yb = min(ya + tile, height)
            kend = -1
            for y in range(ya, yb):
                for x in range(xa, xb):
                    kend = max(kend, last[y, x])
                    for c in range(3):
                        Bacc[y, x, c] = bg[c]
            for k in range(kend, tile_off[t] - 1, -1):
                s = ent[k]
                m0 = mu[s, 0]
                m1 = mu[s, 1]
                A = conic[s, 0]
                B = conic[s, 1]
                C = conic[s, 2]
                o = opac[s]
                c0 = col[s, 0]
                c1 = col[s, 1]
                c2 = col[s, 2]
                g_m0 = 0.0
                g_m1 = 0.0
                g_A = 0.0
                g_B = 0.0
                g_C = 0.0
                g_o = 0.0
                g_c0 = 0.0
                g_c1 = 0.0
                g_c2 = 0.0
                ylo = max(ya, math.ceil(max(m1 - ext[s, 1] - 1e-6, ya - 1.0)))
                yhi = min(yb - 1, math.floor(min(m1 + ext[s, 1] + 1e-6, yb + 1.0)))
                for y in range(ylo, yhi + 1):
                    dy = y - m1
                    x0, x1 = _row_span(A, B, C, dy, cut2, m0, xa, xb)
                    for x in range(x0, x1 + 1):
                        if k > last[y, x]:
                            continue
                        dx = x - m0
                        q = A * dx * dx + 2.0 * B * dx * dy + C * dy * dy
                        if q > cut2:
                            continue
                        gs = math.exp(-0.5 * q)
                        a0 = o * gs
                        a = min(ALPHA_MAX, a0)
                        if a < amin:
                            continue
                        om = 1.0 - a
                        Tb = T[y, x] / om
                        w = a * Tb
                        d0 = dimg[y, x, 0]
                        d1 = dimg[y, x, 1]
                        d2 = dimg[y, x, 2]
                        g_c0 += w * d0
                        g_c1 += w * d1
                        g_c2 += w * d2
                        b0 = Bacc[y, x, 0]
                        b1 = Bacc[y, x, 1]
                        b2 = Bacc[y, x, 2]
                        dLa = (
                            Tb * ((c0 - b0) * d0 + (c1 - b1) * d1 + (c2 - b2) * d2) + dalpha[y, x] * t_final[y, x] / om
                        )
                        Bacc[y, x, 0] = a * c0 + om * b0
                        Bacc[y, x, 1] = a * c1 + om * b1
                        Bacc[y, x, 2] = a * c2 + om * b2
                        T[y, x] = Tb
                        if a0 < ALPHA_MAX:
                            g_o += dLa * gs
                            dLq = -0.5 * gs * o * dLa
                            g_A += dLq * dx * dx
                            g_B += dLq * 2.0 * dx * dy
                            g_C += dLq * dy * dy
                            g_m0 -= dLq * 2.0 * (A * dx + B * dy)
                            g_m1 -= dLq * 2.0 * (B * dx + C * dy)
                slots[k, 0] = g_m0
                slots[k, 1] = g_m1
                slots[k, 2] = g_A
                slots[k, 3] = g_B
                slots[k, 4] = g_C
                slots[k, 5] = g_o
                slots[k, 6] = g_c0
                slots[k, 7] = g_c1
                slots[k, 8] = g_c2
    return slots


@njit(cache=True, error_model="numpy")
def _reduce_slots(ent, slots, n):
    # serial, in entry order: a fixed summation order, so the same bytes every run
    G = np.zeros((n, 9))
    for e in range(ent.shape[0]):
        s = ent[e]
        for j in range(9):
            G[s, j] += slots[e, j]
    return G


@njit(cache=True, parallel=True, error_model="numpy")
def _backward_params(G, valid, means, quats, log_scales, opac, conic, K, M, lowpass):
    n = means.shape[0]
    g_means = np.zeros((n, 3), np.float32)
    g_quats = np.zeros((n, 4), np.float32)
    g_ls = np.zeros((n, 2), np.float32)
    g_lg = np.zeros(n, np.float32)
    g_col = np.zeros((n, 3), np.float32)
    g_mu_abs = np.zeros(n, np.float32)
    for i in prange(n):
        if not valid[i]:
            continue
        o = opac[i]
        g_lg[i] = G[i, 5] * o * (1.0 - o)
        for c in range(3):
            g_col[i, c] = G[i, 6 + c]
        gm0 = G[i, 0]
        gm1 = G[i, 1]
        g_mu_abs[i] = math.sqrt(gm0 * gm0 + gm1 * gm1)
        # conic (A, B, C) = inverse of Σ2 = [[a, b], [b, c]]:  dL/dΣ2 = -Q Gm Q
        A = conic[i, 0]
        B = conic[i, 1]
        C = conic[i, 2]
        gA = G[i, 2]
        gB = 0.5 * G[i, 3]
        gC = G[i, 4]
        # P = Gm Q, with Gm = [[gA, gB], [gB, gC]], Q = [[A, B], [B, C]]
        p00 = gA * A + gB * B
        p01 = gA * B + gB * C
        p10 = gB * A + gC * B
        p11 = gB * B + gC * C
        da = -(A * p00 + B * p10)
        db = -2.0 * (A * p01 + B * p11)
        dc = -(B * p01 + C * p11)
        m0, m1, m2 = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        t = np.empty(3)
        for r in range(3):
            t[r] = M[r, 0] * m0 + M[r, 1] * m1 + M[r, 2] * m2 + M[r, 3]
        w, x, y, z, nq, c0, c1, su, sv = _frame(quats[i], log_scales[i])
        iz = 1.0 / t[2]
        J = np.empty((2, 3))
        u = np.empty(2)
        for r in range(2):
            u[r] = K[r, 0] * t[0] + K[r, 1] * t[1]
            J[r, 0] = K[r, 0] * iz
            J[r, 1] = K[r, 1] * iz
            J[r, 2] = -u[r] * iz * iz
        Ta = np.empty(3)  # W c0 su, camera frame
        Tb = np.empty(3)
        for k in range(3):
            Ta[k] = (M[k, 0] * c0[0] + M[k, 1] * c0[1] + M[k, 2] * c0[2]) * su
            Tb[k] = (M[k, 0] * c1[0] + M[k, 1] * c1[1] + M[k, 2] * c1[2]) * sv
        ja = np.empty(2)
        jb = np.empty(2)
        for r in range(2):
            ja[r] = J[r, 0] * Ta[0] + J[r, 1] * Ta[1] + J[r, 2] * Ta[2]
            jb[r] = J[r, 0] * Tb[0] + J[r, 1] * Tb[1] + J[r, 2] * Tb[2]
        # Σ2 = ja jaᵀ + jb jbᵀ + lowpass I
        gja0 = 2.0 * ja[0] * da + ja[1] * db
        gja1 = 2.0 * ja[1] * dc + ja[0] * db
        gjb0 = 2.0 * jb[0] * da + jb[1] * db
        gjb1 = 2.0 * jb[1] * dc + jb[0] * db
        gTa = np.empty(3)
        gTb = np.empty(3)
        gJ = np.empty((2, 3))
        for k in range(3):
            gTa[k] = J[0, k] * gja0 + J[1, k] * gja1
            gTb[k] = J[0, k] * gjb0 + J[1, k] * gjb1
            gJ[0, k] = gja0 * Ta[k] + gjb0 * Tb[k]
            gJ[1, k] = gja1 * Ta[k] + gjb1 * Tb[k]
        g_ls[i, 0] = Ta[0] * gTa[0] + Ta[1] * gTa[1] + Ta[2] * gTa[2]
        g_ls[i, 1] = Tb[0] * gTb[0] + Tb[1] * gTb[1] + Tb[2] * gTb[2]
        # world-frame gradients of the unit tangent columns: su Wᵀ gTa, sv Wᵀ gTb
        gc0 = np.empty(3)
        gc1 = np.empty(3)
        for k in range(3):
            gc0[k] = su * (M[0, k] * gTa[0] + M[1, k] * gTa[1] + M[2, k] * gTa[2])
            gc1[k] = sv * (M[0, k] * gTb[0] + M[1, k] * gTb[1] + M[2, k] * gTb[2])
        # d col0 / d(w, x, y, z) and d col1 / d(w, x, y, z) of the unit quaternion
        gw = gc0[1] * 2 * z - gc0[2] * 2 * y - gc1[0] * 2 * z + gc1[2] * 2 * x
        gx = gc0[1] * 2 * y + gc0[2] * 2 * z + gc1[0] * 2 * y - gc1[1] * 4 * x + gc1[2] * 2 * w
        gy = -gc0[0] * 4 * y + gc0[1] * 2 * x - gc0[2] * 2 * w + gc1[0] * 2 * x + gc1[2] * 2 * z
        gz = -gc0[0] * 4 * z + gc0[1] * 2 * w + gc0[2] * 2 * x - gc1[0] * 2 * w - gc1[1] * 4 * z + gc1[2] * 2 * y
        dot = w * gw + x * gx + y * gy + z * gz
        g_quats[i, 0] = (gw - w * dot) / nq
        g_quats[i, 1] = (gx - x * dot) / nq
        g_quats[i, 2] = (gy - y * dot) / nq
        g_quats[i, 3] = (gz - z * dot) / nq
        # camera-frame centre: through mu (its Jacobian is J) and through J itself
        iz2 = iz * iz
        gt0 = J[0, 0] * gm0 + J[1, 0] * gm1
        gt1 = J[0, 1] * gm0 + J[1, 1] * gm1
        gt2 = J[0, 2] * gm0 + J[1, 2] * gm1
        for r in range(2):
            gt0 -= gJ[r, 2] * K[r, 0] * iz2
            gt1 -= gJ[r, 2] * K[r, 1] * iz2
            gt2 += -gJ[r, 0] * K[r, 0] * iz2 - gJ[r, 1] * K[r, 1] * iz2 + gJ[r, 2] * 2.0 * u[r] * iz2 * iz
        for k in range(3):
            g_means[i, k] = M[0, k] * gt0 + M[1, k] * gt1 + M[2, k] * gt2
    return g_means, g_quats, g_ls, g_lg, g_col, g_mu_abs


# ------------------------------------------------------------------------- drivers


def _depth_order(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Indices of the valid surfels by (float32 view depth, index): a unique key, so any
    sort gives the same order."""
    idx = np.flatnonzero(valid)
    key = (depth[idx].astype(np.float32).view(np.uint32).astype(np.uint64) << np.uint64(32)) | idx.astype(np.uint64)
    return idx[np.argsort(key)]


def rasterize(params: SplatParams, cam: RasterCamera, *, config: RasterConfig = RasterConfig()) -> RasterOutput:
    """Render the surfels ``params`` seen by ``cam`` (see the module docstring).

    Returns
    -------
    RasterOutput with ``image`` (H, W, 3) float32, ``alpha`` (H, W) float32, ``depth``
    (H, W) float32 (alpha-weighted, metres), ``n_fragments``, ``visible`` and the context
    :func:`rasterize_backward` needs.
    """
    W, H, tile = int(cam.width), int(cam.height), int(config.tile_px)
    mu, conic, ext, opac, depth, col, rect, valid = _preprocess(
        np.ascontiguousarray(params.means),
        np.ascontiguousarray(params.quats),
        np.ascontiguousarray(params.log_scales),
        np.ascontiguousarray(params.opacity_logits),
        np.ascontiguousarray(params.colors),
        cam.K,
        cam.cam_from_world,
        W,
        H,
        float(config.lowpass_px2),
        float(config.cutoff_sigma),
        float(config.near_m),
        tile,
    )
    n_tx = (W + tile - 1) // tile
    n_tiles = n_tx * ((H + tile - 1) // tile)
    order = _depth_order(depth, valid)
    counts = _count_entries(order, rect, n_tx, n_tiles, _FILL_CHUNKS)
    per_tile = counts.sum(axis=0)
    tile_off = np.zeros(n_tiles + 1, np.int64)
    np.cumsum(per_tile, out=tile_off[1:])
    start = tile_off[:-1][None, :] + np.cumsum(counts, axis=0) - counts
    ent = _fill_entries(order, rect, n_tx, np.ascontiguousarray(start), int(tile_off[-1]))
    bg = np.asarray(config.background, np.float64)
    cut2 = float(config.cutoff_sigma) ** 2
    image, alpha, dep, T, last, nfrag = _forward(
        tile_off,
        ent,
        mu,
        conic,
        ext,
        opac,
        depth,
        col,
        W,
        H,
        tile,
        n_tx,
        cut2,
        float(config.alpha_min),
        float(config.transmittance_min),
        bg,
    )
    ctx = _RasterContext(
        n=params.n,
        width=W,
        height=H,
        config=config,
        mu=mu,
        conic=conic,
        ext=ext,
        opac=opac,
        depth=depth,
        colors=col,
        tile_off=tile_off,
        ent_sid=ent,
        t_final=T,
        last=last,
        n_tx=n_tx,
    )
    return RasterOutput(
        image=image, alpha=alpha, depth=dep, n_fragments=int(nfrag), n_entries=int(ent.shape[0]), visible=valid, ctx=ctx
    )


def rasterize_backward(
    out: RasterOutput,
    params: SplatParams,
    cam: RasterCamera,
    *,
    dL_dimage: np.ndarray,
    dL_dalpha: np.ndarray | None,
    config: RasterConfig = RasterConfig(),
) -> SplatGrads:
    """Gradients of a scalar loss L through :func:`rasterize`.

    Parameters
    ----------
    out : the forward pass's output for the same ``params``, ``cam`` and ``config``.
    dL_dimage : (H, W, 3) dL/d``out.image``.
    dL_dalpha : (H, W) dL/d``out.alpha``, or None (zero).
    """
    ctx = out.ctx
    W, H = ctx.width, ctx.height
    if params.n != ctx.n or (int(cam.width), int(cam.height)) != (W, H) or config != ctx.config:
        raise InputError("rasterize_backward: params, camera or config differ from the forward pass's")
    dimg = np.ascontiguousarray(dL_dimage, np.float64)
    if dimg.shape != (H, W, 3):
        raise ShapeError(f"dL_dimage has shape {dimg.shape}, expected {(H, W, 3)}")
    dal = np.zeros((H, W)) if dL_dalpha is None else np.ascontiguousarray(dL_dalpha, np.float64)
    if dal.shape != (H, W):
        raise ShapeError(f"dL_dalpha has shape {dal.shape}, expected {(H, W)}")
    bg = np.asarray(config.background, np.float64)
    slots = _backward(
        ctx.tile_off,
        ctx.ent_sid,
        ctx.mu,
        ctx.conic,
        ctx.ext,
        ctx.opac,
        ctx.colors,
        W,
        H,
        int(config.tile_px),
        ctx.n_tx,
        float(config.cutoff_sigma) ** 2,
        float(config.alpha_min),
        ctx.t_final,
        ctx.last,
        bg,
        dimg,
        dal,
    )
    G = _reduce_slots(ctx.ent_sid, slots, ctx.n)
    gm, gq, gs, gl, gc, gabs = _backward_params(
        G,
        out.visible,
        np.ascontiguousarray(params.means),
        np.ascontiguousarray(params.quats),
        np.ascontiguousarray(params.log_scales),
        ctx.opac,
        ctx.conic,
        cam.K,
        cam.cam_from_world,
        float(config.lowpass_px2),
    )
    return SplatGrads(
        means=gm, quats=gq, log_scales=gs, opacity_logits=gl, colors=gc, means2d_abs=gabs, visible=out.visible.copy()
    )
