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

Layout of the work (numba, ``prange`` wherever the work splits): per surfel, only the view
depth and the tile of the projected centre; one sort of the surfels in front of the near
plane by (float32 view depth, index), and a counting sort of that order by centre tile;
the records (covariance, conic, tile rectangle) computed straight into that (centre tile,
depth) order, so that a tile's entries read memory forwards;
one key per (surfel, tile) = tile << 32 | depth rank, sorted, gives every tile's list in
depth order; then ``prange`` over tiles dealt round-robin to 64 groups (a balanced static
split) for the per-pixel passes. A splat visits only the pixels of its cutoff ellipse's
bounding box inside the tile (an exact per-row span of the ellipse measured ~10 % slower:
its square root per row cost more than the pixels it saves). The backward pass writes each (tile,
surfel) entry's partial gradient into its own slot, slots laid out surfel by surfel, and
the per-surfel pass sums them in a fixed order: no races, and the same bytes whatever the
thread count, the tile size or the surfels' memory order. Input in random memory order
costs cache misses (``spatial_order`` gives a Morton order). The NumPy twin is
:mod:`opacityhull.optimize.raster_reference`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from ..camera import Camera
from ..errors import InputError, ShapeError

__all__ = [
    "RasterCamera",
    "SplatParams",
    "RasterConfig",
    "RasterOutput",
    "SplatGrads",
    "rasterize",
    "rasterize_backward",
    "spatial_order",
    "ALPHA_MAX",
]

ALPHA_MAX = 0.99
"""The per-fragment opacity clamp (keeps ``1 - alpha`` invertible in the backward pass)."""

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

    @classmethod
    def from_camera(cls, camera: Camera, *, ignore_distortion: bool = False) -> RasterCamera:
        """The rasterizer's pinhole for a project :class:`~opacityhull.camera.Camera`.

        The rasterizer projects without lens distortion; a camera with non-zero distortion
        is refused (``InputError`` naming it and the coefficients) unless
        ``ignore_distortion`` (then the pinhole part is used as it is)."""
        if not ignore_distortion and np.any(np.asarray(camera.dist) != 0):
            raise InputError(
                f"camera {camera.name!r} has lens distortion {np.asarray(camera.dist).tolist()}: "
                "the rasterizer needs undistorted views (or ignore_distortion=True)"
            )
        return cls(
            K=np.asarray(camera.K, np.float64),
            cam_from_world=np.asarray(camera.cam_from_world, np.float64)[:3, :],
            width=int(camera.width),
            height=int(camera.height),
        )


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
    recs: np.ndarray  # (M, 16) f64 the visible surfels' records by (centre tile, depth) (layout: R_* below)
    order: np.ndarray  # (M,) int64 surfel of each record
    tile_off: np.ndarray  # (n_tiles + 1,) int64
    ent: np.ndarray  # (E,) int32 record of each entry, per tile in depth order
    rank_off: np.ndarray  # (M + 1,) int64 a record's gradient slots
    ent_slot: np.ndarray  # (E,) int64 gradient slot of each entry (grouped by record)
    t_final: np.ndarray  # (H, W) f64
    last: np.ndarray  # (H, W) int32 entry index of the last fragment composited, -1 none
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
    timings_s : wall seconds per stage (``sort``, ``setup``, ``bin``, ``composite``).
    """

    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    n_fragments: int
    n_entries: int
    visible: np.ndarray
    ctx: _RasterContext = field(repr=False)
    timings_s: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True, eq=False)
class SplatGrads:
    """Gradients of a scalar loss with respect to :class:`SplatParams` (same shapes,
    float32), plus ``means2d_abs`` (N,) float32 = |dL/d(projected 2-D centre)| in
    loss per pixel (the densification statistic), ``visible`` (N,) bool and
    ``timings_s`` (wall seconds per stage: ``composite``, ``params``)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    colors: np.ndarray
    means2d_abs: np.ndarray
    visible: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------- kernels

# A visible surfel's record (one row of 16 float64, two cache lines), in depth order so
# that a tile's entries read memory forwards: projected centre (px), conic (A, B, C) of
# q = A dx² + 2B dx dy + C dy², opacity, colour, view depth, half height of the cutoff
# ellipse, and its half width.
R_M0, R_M1, R_A, R_B, R_C, R_O, R_R, R_G, R_BL, R_Z, R_HY, R_HX = range(12)
_REC = 16


@njit(cache=True, inline="always", error_model="numpy")
def _frame(quat, log_scale):
    """Normalised quaternion (w, x, y, z), its norm, the two unit tangent axes (world) and
    the two standard deviations."""
    qw, qx, qy, qz = float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3])
    nq = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
    w, x, y, z = qw / nq, qx / nq, qy / nq, qz / nq
    a0 = 1.0 - 2.0 * (y * y + z * z)
    a1 = 2.0 * (x * y + w * z)
    a2 = 2.0 * (x * z - w * y)
    b0 = 2.0 * (x * y - w * z)
    b1 = 1.0 - 2.0 * (x * x + z * z)
    b2 = 2.0 * (y * z + w * x)
    return w, x, y, z, nq, a0, a1, a2, b0, b1, b2, math.exp(float(log_scale[0])), math.exp(float(log_scale[1]))


@njit(cache=True, inline="always", error_model="numpy")
def _project(mean, quat, log_scale, K, M, lowpass):
    """Camera-frame centre, projected centre and screen covariance (a, b, c) of one surfel,
    with the intermediate values the backward pass reuses."""
    m0, m1, m2 = float(mean[0]), float(mean[1]), float(mean[2])
    t0 = M[0, 0] * m0 + M[0, 1] * m1 + M[0, 2] * m2 + M[0, 3]
    t1 = M[1, 0] * m0 + M[1, 1] * m1 + M[1, 2] * m2 + M[1, 3]
    t2 = M[2, 0] * m0 + M[2, 1] * m1 + M[2, 2] * m2 + M[2, 3]
    w, x, y, z, nq, a0, a1, a2, b0, b1, b2, su, sv = _frame(quat, log_scale)
    # camera-frame scaled tangent axes Ta = W a su, Tb = W b sv
    Ta0 = (M[0, 0] * a0 + M[0, 1] * a1 + M[0, 2] * a2) * su
    Ta1 = (M[1, 0] * a0 + M[1, 1] * a1 + M[1, 2] * a2) * su
    Ta2 = (M[2, 0] * a0 + M[2, 1] * a1 + M[2, 2] * a2) * su
    Tb0 = (M[0, 0] * b0 + M[0, 1] * b1 + M[0, 2] * b2) * sv
    Tb1 = (M[1, 0] * b0 + M[1, 1] * b1 + M[1, 2] * b2) * sv
    Tb2 = (M[2, 0] * b0 + M[2, 1] * b1 + M[2, 2] * b2) * sv
    iz = 1.0 / t2
    u0 = K[0, 0] * t0 + K[0, 1] * t1
    u1 = K[1, 0] * t0 + K[1, 1] * t1
    # J = d(pixel)/d(camera point) at the centre; rows (K_r0/z, K_r1/z, -u_r/z²)
    J00, J01, J02 = K[0, 0] * iz, K[0, 1] * iz, -u0 * iz * iz
    J10, J11, J12 = K[1, 0] * iz, K[1, 1] * iz, -u1 * iz * iz
    ja0 = J00 * Ta0 + J01 * Ta1 + J02 * Ta2
    ja1 = J10 * Ta0 + J11 * Ta1 + J12 * Ta2
    jb0 = J00 * Tb0 + J01 * Tb1 + J02 * Tb2
    jb1 = J10 * Tb0 + J11 * Tb1 + J12 * Tb2
    ca = ja0 * ja0 + jb0 * jb0 + lowpass
    cb = ja0 * ja1 + jb0 * jb1
    cc = ja1 * ja1 + jb1 * jb1 + lowpass
    return t0, t1, t2, u0 * iz + K[0, 2], u1 * iz + K[1, 2], ca, cb, cc


@njit(cache=True, parallel=True, error_model="numpy")
def _centres(means, K, M, width, height, near, tile):
    """Per surfel: view depth, the tile of its (clamped) projected centre, and whether it
    is in front of the near plane — all the two sorts need, before the covariance."""
    n = means.shape[0]
    depth = np.empty(n)
    ctile = np.empty(n, np.int64)
    front = np.empty(n, np.bool_)
    n_tx = (width + tile - 1) // tile
    for i in prange(n):
        m0, m1, m2 = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        t0 = M[0, 0] * m0 + M[0, 1] * m1 + M[0, 2] * m2 + M[0, 3]
        t1 = M[1, 0] * m0 + M[1, 1] * m1 + M[1, 2] * m2 + M[1, 3]
        t2 = M[2, 0] * m0 + M[2, 1] * m1 + M[2, 2] * m2 + M[2, 3]
        depth[i] = t2
        front[i] = t2 >= near
        mx = (K[0, 0] * t0 + K[0, 1] * t1) / t2 + K[0, 2]
        my = (K[1, 0] * t0 + K[1, 1] * t1) / t2 + K[1, 2]
        if not (math.isfinite(mx) and math.isfinite(my)):
            mx = 0.0
            my = 0.0
        ctile[i] = (int(min(max(my, 0.0), height - 1.0)) // tile) * n_tx + int(min(max(mx, 0.0), width - 1.0)) // tile
    return depth, ctile, front


@njit(cache=True, parallel=True, error_model="numpy")
def _setup_records(
    order, means, quats, log_scales, logits, colors, K, M, width, height, lowpass, cutoff, tile, visible
):
    """The records of the surfels in front of the near plane, in record order: screen
    covariance, conic, tile rectangle. Surfels whose cutoff ellipse covers no pixel centre
    get no tiles (and stay not ``visible``)."""
    m = order.shape[0]
    recs = np.empty((m, _REC))
    rects = np.zeros((m, 4), np.int64)
    ntile = np.zeros(m, np.int64)
    n_tx = (width + tile - 1) // tile
    n_ty = (height + tile - 1) // tile
    for r in prange(m):
        i = order[r]
        t0, t1, t2, mx, my, ca, cb, cc = _project(means[i], quats[i], log_scales[i], K, M, lowpass)
        recs[r, R_Z] = t2
        det = ca * cc - cb * cb
        if not (det > 0 and math.isfinite(det) and math.isfinite(mx) and math.isfinite(my)):
            continue
        A = cc / det
        B = -cb / det
        C = ca / det
        hx = cutoff * math.sqrt(ca)
        hy = cutoff * math.sqrt(cc)
        # pixel centres inside the ellipse's box, clamped before the integer conversion
        x0 = max(math.ceil(min(max(mx - hx, -1.0), width + 1.0)), 0)
        x1 = min(math.floor(min(max(mx + hx, -1.0), width + 1.0)), width - 1)
        y0 = max(math.ceil(min(max(my - hy, -1.0), height + 1.0)), 0)
        y1 = min(math.floor(min(max(my + hy, -1.0), height + 1.0)), height - 1)
        if x0 > x1 or y0 > y1:
            continue
        recs[r, R_M0] = mx
        recs[r, R_M1] = my
        recs[r, R_A] = A
        recs[r, R_B] = B
        recs[r, R_C] = C
        recs[r, R_O] = 1.0 / (1.0 + math.exp(-float(logits[i])))
        recs[r, R_R] = colors[i, 0]
        recs[r, R_G] = colors[i, 1]
        recs[r, R_BL] = colors[i, 2]
        recs[r, R_HY] = hy
        recs[r, R_HX] = hx
        rects[r, 0] = min(x0 // tile, n_tx - 1)
        rects[r, 1] = min(y0 // tile, n_ty - 1)
        rects[r, 2] = min(x1 // tile, n_tx - 1) + 1
        rects[r, 3] = min(y1 // tile, n_ty - 1) + 1
        ntile[r] = (rects[r, 2] - rects[r, 0]) * (rects[r, 3] - rects[r, 1])
        visible[i] = True
    return recs, rects, ntile


@njit(cache=True, error_model="numpy")
def _tile_major(order_d, ctile, n_tiles):
    """Records ordered by (centre tile, depth, index): a stable counting sort of the depth
    order by centre tile. Returns the record order and each record's depth rank."""
    m = order_d.shape[0]
    start = np.zeros(n_tiles + 1, np.int64)
    for j in range(m):
        start[ctile[order_d[j]] + 1] += 1
    for t in range(n_tiles):
        start[t + 1] += start[t]
    order = np.empty(m, np.int64)
    rank_d = np.empty(m, np.int64)
    rec_of_rank = np.empty(m, np.int64)
    for j in range(m):
        s = order_d[j]
        r = start[ctile[s]]
        start[ctile[s]] += 1
        order[r] = s
        rank_d[r] = j
        rec_of_rank[j] = r
    return order, rank_d, rec_of_rank


@njit(cache=True, parallel=True, error_model="numpy")
def _entry_keys(rects, rank_d, rank_off, n_tx):
    """One key per (record, tile): tile << 32 | depth rank, written record by record (so
    position = gradient slot). Sorted, the keys are the tile lists in depth order."""
    m = rects.shape[0]
    keys = np.empty(rank_off[m], np.uint64)
    for r in prange(m):
        i = rank_off[r]
        for ty in range(rects[r, 1], rects[r, 3]):
            for tx in range(rects[r, 0], rects[r, 2]):
                keys[i] = (np.uint64(ty * n_tx + tx) << np.uint64(32)) | np.uint64(rank_d[r])
                i += 1
    return keys


@njit(cache=True, parallel=True, error_model="numpy")
def _decode_entries(keys, rec_of_rank, rects, rank_off, n_tx, n_tiles):
    """Sorted keys → each entry's record and gradient slot, and the tiles' offsets."""
    e = keys.shape[0]
    ent = np.empty(e, np.int32)
    slot = np.empty(e, np.int64)
    tile_off = np.empty(n_tiles + 1, np.int64)
    lo32 = np.uint64(0xFFFFFFFF)
    for k in prange(e):
        t = np.int64(keys[k] >> np.uint64(32))
        r = rec_of_rank[np.int64(keys[k] & lo32)]
        ty = t // n_tx
        tx = t - ty * n_tx
        ent[k] = r
        slot[k] = rank_off[r] + (ty - rects[r, 1]) * (rects[r, 2] - rects[r, 0]) + (tx - rects[r, 0])
        # the first entry of each tile writes the offsets of the tiles up to it
        tp = -1 if k == 0 else np.int64(keys[k - 1] >> np.uint64(32))
        if tp != t:
            for u in range(tp + 1, t + 1):
                tile_off[u] = k
    t_last = -1 if e == 0 else np.int64(keys[e - 1] >> np.uint64(32))
    for u in range(t_last + 1, n_tiles + 1):
        tile_off[u] = e
    return ent, slot, tile_off


@njit(cache=True, inline="always", error_model="numpy")
def _row_range(m1, hy, ya, yb):
    """Pixel centres [lo, hi] within ``hy`` of ``m1`` inside [ya, yb), widened by a hair:
    the exact ``q <= cut²`` test is made per pixel."""
    lo = max(ya, math.ceil(max(m1 - hy - 1e-6, ya - 1.0)))
    hi = min(yb - 1, math.floor(min(m1 + hy + 1e-6, yb + 1.0)))
    return lo, hi


@njit(cache=True, inline="always", error_model="numpy")
def _tile_box(t, n_tx, tile, width, height):
    """Pixel box [xa, xb) x [ya, yb) of tile ``t`` (row-major, ``n_tx`` tiles a row),
    clipped to the frame: the forward and backward passes walk the same tiles."""
    ty = t // n_tx
    tx = t - ty * n_tx
    xa = tx * tile
    ya = ty * tile
    return xa, ya, min(xa + tile, width), min(ya + tile, height)


@njit(cache=True, parallel=True, error_model="numpy")
def _forward(tile_off, ent, recs, width, height, tile, n_tx, cut2, amin, tmin, bg):
    n_tiles = tile_off.shape[0] - 1
    rgb = np.zeros((height, width, 3))
    dep = np.zeros((height, width))
    T = np.ones((height, width))
    last = np.full((height, width), -1, np.int32)
    nfrag = np.zeros(_TILE_GROUPS, np.int64)
    rowlive = np.empty((_TILE_GROUPS, tile), np.int64)  # live pixels per row of the tile
    for g in prange(_TILE_GROUPS):
        for t in range(g, n_tiles, _TILE_GROUPS):
            xa, ya, xb, yb = _tile_box(t, n_tx, tile, width, height)
            live = (xb - xa) * (yb - ya)
            for y in range(ya, yb):
                rowlive[g, y - ya] = xb - xa
            nf = 0
            for k in range(tile_off[t], tile_off[t + 1]):
                j = ent[k]
                m0 = recs[j, R_M0]
                m1 = recs[j, R_M1]
                A = recs[j, R_A]
                B2 = 2.0 * recs[j, R_B]
                C = recs[j, R_C]
                o = recs[j, R_O]
                cr = recs[j, R_R]
                cg = recs[j, R_G]
                cbl = recs[j, R_BL]
                z = recs[j, R_Z]
                y0, y1 = _row_range(m1, recs[j, R_HY], ya, yb)
                x0, x1 = _row_range(m0, recs[j, R_HX], xa, xb)
                for y in range(y0, y1 + 1):
                    if rowlive[g, y - ya] == 0:
                        continue
                    dy = y - m1
                    bq = B2 * dy
                    cq = C * dy * dy
                    for x in range(x0, x1 + 1):
                        Tp = T[y, x]
                        if Tp < tmin:
                            continue
                        dx = x - m0
                        q = (A * dx + bq) * dx + cq
                        if q > cut2:
                            continue
                        a = min(ALPHA_MAX, o * math.exp(-0.5 * q))
                        if a < amin:
                            continue
                        w = a * Tp
                        rgb[y, x, 0] += w * cr
                        rgb[y, x, 1] += w * cg
                        rgb[y, x, 2] += w * cbl
                        dep[y, x] += w * z
                        Tn = Tp - w
                        T[y, x] = Tn
                        last[y, x] = k
                        nf += 1
                        if Tn < tmin:
                            live -= 1
                            rowlive[g, y - ya] -= 1
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
def _backward(tile_off, ent, ent_slot, recs, width, height, tile, n_tx, cut2, amin, t_final, last, bg, dimg, dalpha):
    """Per entry: dL/d(mu0, mu1, A, B, C, opacity, r, g, b), into its own slot (float32:
    a tile's partial sum is accumulated in float64 and rounded once)."""
    n_tiles = tile_off.shape[0] - 1
    slots = np.empty((ent.shape[0], 9), np.float32)
    T = t_final.copy()
    Bacc = np.empty((height, width, 3))
    rowlast = np.empty((_TILE_GROUPS, tile), np.int64)  # last entry composited per row of the tile
    for g in prange(_TILE_GROUPS):
        for t in range(g, n_tiles, _TILE_GROUPS):
            xa, ya, xb, yb = _tile_box(t, n_tx, tile, width, height)
            kend = -1
            for y in range(ya, yb):
                rl = -1
                for x in range(xa, xb):
                    rl = max(rl, last[y, x])
                    for c in range(3):
                        Bacc[y, x, c] = bg[c]
                rowlast[g, y - ya] = rl
                kend = max(kend, rl)
            for k in range(max(kend + 1, tile_off[t]), tile_off[t + 1]):
                e = ent_slot[k]
                for c in range(9):
                    slots[e, c] = 0.0
            for k in range(kend, tile_off[t] - 1, -1):
                j = ent[k]
                m0 = recs[j, R_M0]
                m1 = recs[j, R_M1]
                A = recs[j, R_A]
                B = recs[j, R_B]
                B2 = 2.0 * B
                C = recs[j, R_C]
                o = recs[j, R_O]
                c0 = recs[j, R_R]
                c1 = recs[j, R_G]
                c2 = recs[j, R_BL]
                g_m0 = 0.0
                g_m1 = 0.0
                g_A = 0.0
                g_B = 0.0
                g_C = 0.0
                g_o = 0.0
                g_c0 = 0.0
                g_c1 = 0.0
                g_c2 = 0.0
                y0, y1 = _row_range(m1, recs[j, R_HY], ya, yb)
                x0, x1 = _row_range(m0, recs[j, R_HX], xa, xb)
                for y in range(y0, y1 + 1):
                    if k > rowlast[g, y - ya]:
                        continue
                    dy = y - m1
                    bq = B2 * dy
                    cq = C * dy * dy
                    for x in range(x0, x1 + 1):
                        if k > last[y, x]:
                            continue
                        dx = x - m0
                        q = (A * dx + bq) * dx + cq
                        if q > cut2:
                            continue
                        gs = math.exp(-0.5 * q)
                        a0 = o * gs
                        a = min(ALPHA_MAX, a0)
                        if a < amin:
                            continue
                        inv_om = 1.0 / (1.0 - a)
                        om = 1.0 - a
                        Tb = T[y, x] * inv_om
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
                            Tb * ((c0 - b0) * d0 + (c1 - b1) * d1 + (c2 - b2) * d2)
                            + dalpha[y, x] * t_final[y, x] * inv_om
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
                e = ent_slot[k]
                slots[e, 0] = g_m0
                slots[e, 1] = g_m1
                slots[e, 2] = g_A
                slots[e, 3] = g_B
                slots[e, 4] = g_C
                slots[e, 5] = g_o
                slots[e, 6] = g_c0
                slots[e, 7] = g_c1
                slots[e, 8] = g_c2
    return slots


@njit(cache=True, parallel=True, error_model="numpy")
def _backward_params(slots, rank_off, order, recs, means, quats, log_scales, K, M, lowpass):
    """Sum each record's entry slots in a fixed order, then chain to the parameters."""
    n = means.shape[0]
    g_means = np.zeros((n, 3), np.float32)
    g_quats = np.zeros((n, 4), np.float32)
    g_ls = np.zeros((n, 2), np.float32)
    g_lg = np.zeros(n, np.float32)
    g_col = np.zeros((n, 3), np.float32)
    g_mu_abs = np.zeros(n, np.float32)
    for j in prange(order.shape[0]):
        if rank_off[j + 1] == rank_off[j]:
            continue  # culled off-frame: no tiles, no record
        gm0 = 0.0
        gm1 = 0.0
        gA = 0.0
        gB = 0.0
        gC = 0.0
        go = 0.0
        gr = 0.0
        gg = 0.0
        gb = 0.0
        for k in range(rank_off[j], rank_off[j + 1]):
            gm0 += slots[k, 0]
            gm1 += slots[k, 1]
            gA += slots[k, 2]
            gB += slots[k, 3]
            gC += slots[k, 4]
            go += slots[k, 5]
            gr += slots[k, 6]
            gg += slots[k, 7]
            gb += slots[k, 8]
        i = order[j]
        o = recs[j, R_O]
        g_lg[i] = go * o * (1.0 - o)
        g_col[i, 0] = gr
        g_col[i, 1] = gg
        g_col[i, 2] = gb
        g_mu_abs[i] = math.sqrt(gm0 * gm0 + gm1 * gm1)
        # conic Q = [[A, B], [B, C]] = Σ2⁻¹ and dL/dΣ2 = -Q Gm Q with Gm = [[gA, gB/2], [gB/2, gC]]
        A = recs[j, R_A]
        B = recs[j, R_B]
        C = recs[j, R_C]
        hB = 0.5 * gB
        p00 = gA * A + hB * B
        p01 = gA * B + hB * C
        p10 = hB * A + gC * B
        p11 = hB * B + gC * C
        da = -(A * p00 + B * p10)
        db = -2.0 * (A * p01 + B * p11)
        dc = -(B * p01 + C * p11)
        # recompute the projection's intermediates (cheaper than storing them)
        m0, m1, m2 = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        t0 = M[0, 0] * m0 + M[0, 1] * m1 + M[0, 2] * m2 + M[0, 3]
        t1 = M[1, 0] * m0 + M[1, 1] * m1 + M[1, 2] * m2 + M[1, 3]
        t2 = M[2, 0] * m0 + M[2, 1] * m1 + M[2, 2] * m2 + M[2, 3]
        w, x, y, z, nq, a0, a1, a2, b0, b1, b2, su, sv = _frame(quats[i], log_scales[i])
        Ta0 = (M[0, 0] * a0 + M[0, 1] * a1 + M[0, 2] * a2) * su
        Ta1 = (M[1, 0] * a0 + M[1, 1] * a1 + M[1, 2] * a2) * su
        Ta2 = (M[2, 0] * a0 + M[2, 1] * a1 + M[2, 2] * a2) * su
        Tb0 = (M[0, 0] * b0 + M[0, 1] * b1 + M[0, 2] * b2) * sv
        Tb1 = (M[1, 0] * b0 + M[1, 1] * b1 + M[1, 2] * b2) * sv
        Tb2 = (M[2, 0] * b0 + M[2, 1] * b1 + M[2, 2] * b2) * sv
        iz = 1.0 / t2
        iz2 = iz * iz
        u0 = K[0, 0] * t0 + K[0, 1] * t1
        u1 = K[1, 0] * t0 + K[1, 1] * t1
        J00, J01, J02 = K[0, 0] * iz, K[0, 1] * iz, -u0 * iz2
        J10, J11, J12 = K[1, 0] * iz, K[1, 1] * iz, -u1 * iz2
        ja0 = J00 * Ta0 + J01 * Ta1 + J02 * Ta2
        ja1 = J10 * Ta0 + J11 * Ta1 + J12 * Ta2
        jb0 = J00 * Tb0 + J01 * Tb1 + J02 * Tb2
        jb1 = J10 * Tb0 + J11 * Tb1 + J12 * Tb2
        # Σ2 = ja jaᵀ + jb jbᵀ + lowpass I
        gja0 = 2.0 * ja0 * da + ja1 * db
        gja1 = 2.0 * ja1 * dc + ja0 * db
        gjb0 = 2.0 * jb0 * da + jb1 * db
        gjb1 = 2.0 * jb1 * dc + jb0 * db
        # ja = J Ta: dL/dTa = Jᵀ dL/dja, dL/dJ = dL/dja Taᵀ + dL/djb Tbᵀ
        gTa0 = J00 * gja0 + J10 * gja1
        gTa1 = J01 * gja0 + J11 * gja1
        gTa2 = J02 * gja0 + J12 * gja1
        gTb0 = J00 * gjb0 + J10 * gjb1
        gTb1 = J01 * gjb0 + J11 * gjb1
        gTb2 = J02 * gjb0 + J12 * gjb1
        gJ00 = gja0 * Ta0 + gjb0 * Tb0
        gJ01 = gja0 * Ta1 + gjb0 * Tb1
        gJ02 = gja0 * Ta2 + gjb0 * Tb2
        gJ10 = gja1 * Ta0 + gjb1 * Tb0
        gJ11 = gja1 * Ta1 + gjb1 * Tb1
        gJ12 = gja1 * Ta2 + gjb1 * Tb2
        # Ta = W a su: d/dlog su = Ta · dL/dTa
        g_ls[i, 0] = Ta0 * gTa0 + Ta1 * gTa1 + Ta2 * gTa2
        g_ls[i, 1] = Tb0 * gTb0 + Tb1 * gTb1 + Tb2 * gTb2
        # world-frame gradients of the unit tangent axes: su Wᵀ dL/dTa, sv Wᵀ dL/dTb
        ga0 = su * (M[0, 0] * gTa0 + M[1, 0] * gTa1 + M[2, 0] * gTa2)
        ga1 = su * (M[0, 1] * gTa0 + M[1, 1] * gTa1 + M[2, 1] * gTa2)
        ga2 = su * (M[0, 2] * gTa0 + M[1, 2] * gTa1 + M[2, 2] * gTa2)
        gb0 = sv * (M[0, 0] * gTb0 + M[1, 0] * gTb1 + M[2, 0] * gTb2)
        gb1 = sv * (M[0, 1] * gTb0 + M[1, 1] * gTb1 + M[2, 1] * gTb2)
        gb2 = sv * (M[0, 2] * gTb0 + M[1, 2] * gTb1 + M[2, 2] * gTb2)
        # the axes as functions of the unit quaternion (the first two columns of R)
        gw = 2.0 * (ga1 * z - ga2 * y - gb0 * z + gb2 * x)
        gx = 2.0 * (ga1 * y + ga2 * z + gb0 * y - 2.0 * gb1 * x + gb2 * w)
        gy = 2.0 * (-2.0 * ga0 * y + ga1 * x - ga2 * w + gb0 * x + gb2 * z)
        gz = 2.0 * (-2.0 * ga0 * z + ga1 * w + ga2 * x - gb0 * w - 2.0 * gb1 * z + gb2 * y)
        # through the normalisation q / |q|
        dot = w * gw + x * gx + y * gy + z * gz
        g_quats[i, 0] = (gw - w * dot) / nq
        g_quats[i, 1] = (gx - x * dot) / nq
        g_quats[i, 2] = (gy - y * dot) / nq
        g_quats[i, 3] = (gz - z * dot) / nq
        # camera-frame centre: through the projected centre (its Jacobian is J) and through J
        gt0 = J00 * gm0 + J10 * gm1 - (gJ02 * K[0, 0] + gJ12 * K[1, 0]) * iz2
        gt1 = J01 * gm0 + J11 * gm1 - (gJ02 * K[0, 1] + gJ12 * K[1, 1]) * iz2
        gt2 = J02 * gm0 + J12 * gm1
        gt2 += -(gJ00 * K[0, 0] + gJ01 * K[0, 1] + gJ10 * K[1, 0] + gJ11 * K[1, 1]) * iz2
        gt2 += 2.0 * (gJ02 * u0 + gJ12 * u1) * iz2 * iz
        for c in range(3):
            g_means[i, c] = M[0, c] * gt0 + M[1, c] * gt1 + M[2, c] * gt2
    return g_means, g_quats, g_ls, g_lg, g_col, g_mu_abs


# ------------------------------------------------------------------------- drivers


def _depth_order(depth: np.ndarray, front: np.ndarray) -> np.ndarray:
    """Indices of the surfels in front of the near plane by (float32 view depth, index): a
    unique key (depth ≥ near_m > 0, so the float bits sort as the numbers), so any sort
    gives the same order."""
    idx = np.flatnonzero(front)
    key = (depth[idx].astype(np.float32).view(np.uint32).astype(np.uint64) << np.uint64(32)) | idx.astype(np.uint64)
    key.sort()
    return (key & np.uint64(0xFFFFFFFF)).astype(np.int64)


def spatial_order(means: np.ndarray, *, bits: int = 10) -> np.ndarray:
    """A permutation (N,) int64 that puts surfels in Morton (Z-curve) order of their
    positions quantised to ``2**bits`` cells per axis of their bounding box.

    The rasterizer's per-tile passes read the surfel records in (tile, depth) order; when
    the surfels are spatially coherent in memory those reads stream, when they are in
    random order each one is a cache miss (measured in ``benchmarks/optimize_raster.py``).
    A fitting loop that appends clones at densification should reorder with this now and
    then (apply the permutation to every per-surfel array, optimizer state included).
    """
    p = np.asarray(means, np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError(f"spatial_order: means has shape {p.shape}, expected (N, 3)")
    if len(p) == 0:
        return np.zeros(0, np.int64)
    lo = p.min(axis=0)
    span = np.maximum(p.max(axis=0) - lo, 1e-30)
    q = np.clip(((p - lo) / span * (2**bits - 1)).round(), 0, 2**bits - 1).astype(np.uint64)
    code = np.zeros(len(p), np.uint64)
    for b in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + axis)
    return np.argsort(code, kind="stable")


def rasterize(params: SplatParams, cam: RasterCamera, *, config: RasterConfig = RasterConfig()) -> RasterOutput:
    """Render the surfels ``params`` seen by ``cam`` (see the module docstring).

    Returns
    -------
    RasterOutput with ``image`` (H, W, 3) float32, ``alpha`` (H, W) float32, ``depth``
    (H, W) float32 (alpha-weighted, metres), ``n_fragments``, ``visible`` and the context
    :func:`rasterize_backward` needs.
    """
    W, H, tile = int(cam.width), int(cam.height), int(config.tile_px)
    if params.n >= 2**31:
        raise InputError(f"rasterize: {params.n} surfels, at most 2**31 - 1")
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        bad = int(np.count_nonzero(np.isnan(getattr(params, name))))
        if bad:
            # a diverged optimizer: name it here rather than return a NaN image
            raise InputError(f"rasterize: SplatParams.{name} has {bad} NaN values")
    clock = [time.perf_counter()]

    def lap() -> float:
        clock.append(time.perf_counter())
        return clock[-1] - clock[-2]

    timings: dict[str, float] = {}
    means = np.ascontiguousarray(params.means)
    depth, ctile, front = _centres(means, cam.K, cam.cam_from_world, W, H, float(config.near_m), tile)
    n_tx = (W + tile - 1) // tile
    n_tiles = n_tx * ((H + tile - 1) // tile)
    order_d = _depth_order(depth, front)
    order, rank_d, rec_of_rank = _tile_major(order_d, ctile, n_tiles)
    timings["sort"] = lap()
    valid = np.zeros(params.n, np.bool_)
    recs, rects, ntile = _setup_records(
        order,
        means,
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
        tile,
        valid,
    )
    timings["setup"] = lap()
    rank_off = np.zeros(len(order) + 1, np.int64)
    np.cumsum(ntile, out=rank_off[1:])
    if rank_off[-1] >= 2**31:
        raise InputError(f"rasterize: {rank_off[-1]} tile entries, at most 2**31 - 1 (surfels too large on screen?)")
    keys = _entry_keys(rects, rank_d, rank_off, n_tx)
    keys.sort()
    ent, ent_slot, tile_off = _decode_entries(keys, rec_of_rank, rects, rank_off, n_tx, n_tiles)
    timings["bin"] = lap()
    image, alpha, dep, T, last, nfrag = _forward(
        tile_off,
        ent,
        recs,
        W,
        H,
        tile,
        n_tx,
        float(config.cutoff_sigma) ** 2,
        float(config.alpha_min),
        float(config.transmittance_min),
        np.asarray(config.background, np.float64),
    )
    timings["composite"] = lap()
    ctx = _RasterContext(
        n=params.n,
        width=W,
        height=H,
        config=config,
        recs=recs,
        order=order,
        tile_off=tile_off,
        ent=ent,
        rank_off=rank_off,
        ent_slot=ent_slot,
        t_final=T,
        last=last,
        n_tx=n_tx,
    )
    return RasterOutput(
        image=image,
        alpha=alpha,
        depth=dep,
        n_fragments=int(nfrag),
        n_entries=int(ent.shape[0]),
        visible=valid,
        ctx=ctx,
        timings_s=timings,
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

    Returns
    -------
    SplatGrads (float32; zero for surfels that were culled).
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
    t0 = time.perf_counter()
    slots = _backward(
        ctx.tile_off,
        ctx.ent,
        ctx.ent_slot,
        ctx.recs,
        W,
        H,
        int(config.tile_px),
        ctx.n_tx,
        float(config.cutoff_sigma) ** 2,
        float(config.alpha_min),
        ctx.t_final,
        ctx.last,
        np.asarray(config.background, np.float64),
        dimg,
        dal,
    )
    t1 = time.perf_counter()
    gm, gq, gs, gl, gc, gabs = _backward_params(
        slots,
        ctx.rank_off,
        ctx.order,
        ctx.recs,
        np.ascontiguousarray(params.means),
        np.ascontiguousarray(params.quats),
        np.ascontiguousarray(params.log_scales),
        cam.K,
        cam.cam_from_world,
        float(config.lowpass_px2),
    )
    timings = {"composite": t1 - t0, "params": time.perf_counter() - t1}
    return SplatGrads(
        means=gm,
        quats=gq,
        log_scales=gs,
        opacity_logits=gl,
        colors=gc,
        means2d_abs=gabs,
        visible=out.visible.copy(),
        timings_s=timings,
    )
