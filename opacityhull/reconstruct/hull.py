"""Visual hull: silhouettes from alpha mattes, carved into a voxel grid.

The visual hull is the largest object consistent with the silhouettes: a voxel is
removed when its centre projects, in some view, onto an image pixel outside that view's
silhouette. Two rules keep the carve conservative:

* a voxel whose centre projects outside an image, or lies behind (or on the plane of)
  a camera, is *not carved by that view* — that camera says nothing about it (this also
  makes a camera whose centre is inside the bounding volume harmless);
* silhouettes are dilated by the calibration reprojection RMS (rounded up to whole
  pixels) before carving, so a calibration error of that size never cuts the object.

Pixel lookup: a projected centre ``(u, v)`` falls in pixel ``(floor(u + 0.5),
floor(v + 0.5))`` (OpenCV convention: pixel centres at integers).

Three carvers with identical results (the tests check bit-for-bit equality):

* :func:`carve_octree` — the fast one. Cells of ``root_cell``³ voxels are refined
  coarse-to-fine. For a cell and a view, the 8 extreme voxel *centres* of the cell are
  projected; their bounding rectangle of pixels contains the pixel of every voxel centre
  in the cell (pinhole projection maps the convex hull of the centres into the convex hull
  of the projected corners). A per-view summed-area table counts silhouette pixels in the
  rectangle (pixels outside the image count as silhouette: not carved there): none → the
  whole cell is removed; all → this view can never carve inside the cell and is dropped
  from the cell's active views; otherwise the cell is split. A cell with no active view
  left is kept whole. At one voxel the rectangle is one pixel, so the leaf test *is* the
  centre test of dense carving: the octree hull equals the centre-sampled dense hull, not
  a voxel fatter.
* :func:`carve_dense` — every voxel centre against every view (numba, parallel over
  x-slices, early exit on the first carving view): the reference the issue quotes.
* :func:`carve_reference` — the same test in plain NumPy through
  :meth:`Camera.project`, for small grids only (the slow oracle).

Lens distortion: the carvers take pinhole cameras. Silhouettes of distorted cameras are
first resampled to the undistorted pinhole image (:func:`undistort_silhouette`, dilated
by one pixel to stay conservative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, cast, overload

import numpy as np
from numba import njit, prange

from ..camera import Camera
from ..errors import InputError, ShapeError

__all__ = [
    "HullGrid",
    "EmptyHullError",
    "silhouette_from_alpha",
    "undistort_silhouette",
    "projection_matrices",
    "hull_bounds",
    "carve_octree",
    "carve_dense",
    "carve_reference",
    "point_in_hull",
    "view_rejections",
    "carve_robust",
    "enclosed_holes",
    "OctreeStats",
]


class EmptyHullError(InputError):
    """The silhouettes are inconsistent or empty: the visual hull has no voxel."""


@dataclass(frozen=True)
class HullGrid:
    """A regular voxel grid in the object frame.

    Attributes
    ----------
    lo : (3,) float64, metres: the low corner of voxel (0, 0, 0); its centre is
        ``lo + 0.5 * voxel_m``.
    voxel_m : edge length of a voxel, metres.
    shape : (nx, ny, nz); arrays over the grid are indexed ``[ix, iy, iz]``.
    """

    lo: np.ndarray
    voxel_m: float
    shape: tuple[int, int, int]

    def __post_init__(self):
        lo = np.asarray(self.lo, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(lo)):
            raise InputError(f"hull grid origin {lo.tolist()} is not finite")
        if not (self.voxel_m > 0 and math.isfinite(self.voxel_m)):
            raise InputError(f"hull voxel size must be > 0, got {self.voxel_m}")
        shape = tuple(int(s) for s in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise InputError(f"hull grid shape must be 3 positive ints, got {self.shape}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "voxel_m", float(self.voxel_m))
        object.__setattr__(self, "shape", shape)

    @classmethod
    def from_bounds(cls, lo, hi, resolution: int) -> HullGrid:
        """The grid with ``resolution`` voxels along the longest side of box ``[lo, hi]``
        (the other sides rounded up, the box centred)."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        ext = hi - lo
        if not np.all(ext > 0):
            raise InputError(f"hull bounds lo={lo.tolist()} hi={hi.tolist()} are empty")
        if int(resolution) < 1:
            raise InputError(f"hull resolution must be >= 1, got {resolution}")
        h = float(ext.max()) / int(resolution)
        shape = np.maximum(1, np.ceil(ext / h - 1e-9).astype(int))
        centre = 0.5 * (lo + hi)
        nx, ny, nz = (int(s) for s in shape)
        return cls(centre - 0.5 * shape * h, h, (nx, ny, nz))

    @property
    def hi(self) -> np.ndarray:
        return self.lo + np.asarray(self.shape) * self.voxel_m

    def centres(self, index) -> np.ndarray:
        """World positions (N, 3) of voxel centres for integer indices (N, 3)."""
        return self.lo + (np.asarray(index, dtype=np.float64) + 0.5) * self.voxel_m

    def all_centres(self) -> np.ndarray:
        """(nx, ny, nz, 3) voxel centres."""
        axes = [self.lo[i] + (np.arange(self.shape[i]) + 0.5) * self.voxel_m for i in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


# --------------------------------------------------------------------------- silhouettes


def silhouette_from_alpha(alpha, *, threshold: float = 0.5, dilate_px: float = 0.0) -> np.ndarray:
    """Binary silhouette ``alpha > threshold``, dilated by a disc of ``ceil(dilate_px)``
    pixels. NaN alpha counts as background. Returns (H, W) bool."""
    import cv2

    a = np.asarray(alpha, dtype=np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise ShapeError(f"alpha has shape {np.shape(alpha)}, expected (H, W)")
    if not (0.0 <= threshold < 1.0):
        raise InputError(f"alpha threshold must be in [0, 1), got {threshold}")
    sil = np.nan_to_num(a, nan=0.0) > threshold
    r = int(math.ceil(max(0.0, float(dilate_px)) - 1e-9))
    if r > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        sil = cv2.dilate(sil.astype(np.uint8), k).astype(bool)
    return sil


def undistort_silhouette(silhouette, camera: Camera) -> tuple[np.ndarray, Camera]:
    """Resample a distorted camera's silhouette to the pinhole camera with the same K.

    Returns the (H, W) bool silhouette (dilated by 1 px so resampling never shrinks it)
    and the camera without distortion. Cameras without distortion pass through.
    """
    import cv2

    sil = np.asarray(silhouette, dtype=bool)
    if not camera.has_distortion:
        return sil, camera
    H, W = camera.height, camera.width
    mapx, mapy = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, (W, H), cv2.CV_32FC1)
    # pixels of the pinhole image whose source lies outside the distorted image are
    # unknown: mark them silhouette (not carved), as for pixels outside an image
    out = cv2.remap(sil.astype(np.uint8), mapx, mapy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=1)
    out = cv2.dilate(out, np.ones((3, 3), np.uint8))
    return out.astype(bool), Camera(
        K=camera.K, width=W, height=H, world_from_cam=camera.world_from_cam, name=camera.name
    )


def projection_matrices(cameras) -> np.ndarray:
    """(V, 3, 4) float64 ``K [R | t]`` per camera (pinhole; distortion must be removed)."""
    Ps = []
    for c in cameras:
        if c.has_distortion:
            raise InputError(
                f"camera {c.name!r} has lens distortion; undistort its silhouette first (hull.undistort_silhouette)"
            )
        Ps.append(c.projection_matrix())
    return np.ascontiguousarray(np.array(Ps, dtype=np.float64).reshape(-1, 3, 4))


def _stack_silhouettes(silhouettes, cameras):
    if len(silhouettes) != len(cameras):
        raise InputError(f"{len(silhouettes)} silhouettes for {len(cameras)} cameras")
    if len(cameras) == 0:
        raise InputError("visual hull needs at least one view")
    Hm = max(c.height for c in cameras)
    Wm = max(c.width for c in cameras)
    stack = np.zeros((len(cameras), Hm, Wm), np.uint8)
    sizes = np.zeros((len(cameras), 2), np.int64)
    for i, (s, c) in enumerate(zip(silhouettes, cameras, strict=True)):
        s = np.asarray(s)
        if s.shape != (c.height, c.width):
            raise ShapeError(f"silhouette {i} ({c.name}) has shape {s.shape}, expected {(c.height, c.width)}")
        stack[i, : c.height, : c.width] = s.astype(bool)
        sizes[i] = (c.width, c.height)
    return stack, sizes


# --------------------------------------------------------------------------- bounds


def _robust_extent(sil: np.ndarray, min_component_frac: float):
    """(rows, cols) index arrays spanned by the silhouette's connected components of at
    least ``min_component_frac`` of the largest one's area (isolated matting specks left
    out), or all pixels when the fraction is 0."""
    import cv2

    if min_component_frac <= 0:
        return np.nonzero(sil.any(axis=1))[0], np.nonzero(sil.any(axis=0))[0]
    n, _, stats, _ = cv2.connectedComponentsWithStats(sil.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(0, int), np.zeros(0, int)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.nonzero(areas >= min_component_frac * areas.max())[0] + 1
    x0 = stats[keep, cv2.CC_STAT_LEFT].min()
    y0 = stats[keep, cv2.CC_STAT_TOP].min()
    x1 = (stats[keep, cv2.CC_STAT_LEFT] + stats[keep, cv2.CC_STAT_WIDTH]).max() - 1
    y1 = (stats[keep, cv2.CC_STAT_TOP] + stats[keep, cv2.CC_STAT_HEIGHT]).max() - 1
    return np.array([y0, y1]), np.array([x0, x1])


def hull_bounds(
    silhouettes, cameras, *, margin_px: float = 1.0, fallback=None, min_component_frac: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box containing the visual hull, by linear programming.

    Every point of the hull that is in front of camera v projects inside the bounding
    rectangle of v's silhouette (grown by ``margin_px``), i.e. satisfies four linear
    inequalities. Sides of a rectangle touching the image border give no constraint (the
    object may continue outside). The box is ``min/max x, y, z`` over the polytope, six
    LPs (``scipy.optimize.linprog``). A view whose camera centre falls inside the box (its
    constraints only hold in front of it) is dropped and the box recomputed.

    Parameters
    ----------
    silhouettes : list of (H, W) bool, cameras : list of pinhole Camera.
    fallback : (lo, hi) or None — a box intersected with the constraints (e.g. the rig
        volume above the turntable); needed when the constraints alone are unbounded.
    min_component_frac : rectangles span only the connected components with at least
        this fraction of the largest component's area, so isolated matting specks do not
        inflate the box (0 = every pixel). The carve itself still uses every pixel.

    Raises
    ------
    EmptyHullError : a silhouette is empty or the constraints are infeasible.
    InputError : the box is unbounded and no ``fallback`` was given.
    """
    from scipy.optimize import linprog

    rows = []
    empty = []
    for i, (s, c) in enumerate(zip(silhouettes, cameras, strict=True)):
        s = np.asarray(s, dtype=bool)
        ys, xs = _robust_extent(s, min_component_frac)
        if xs.size == 0:
            empty.append(c.name or str(i))
            continue
        P = c.projection_matrix()
        u0, u1 = xs[0] - 0.5 - margin_px, xs[-1] + 0.5 + margin_px
        v0, v1 = ys[0] - 0.5 - margin_px, ys[-1] + 0.5 + margin_px
        cons = []
        # each row a with a . [p, 1] >= 0
        if xs[0] > 0:
            cons.append(P[0] - u0 * P[2])
        if xs[-1] < c.width - 1:
            cons.append(u1 * P[2] - P[0])
        if ys[0] > 0:
            cons.append(P[1] - v0 * P[2])
        if ys[-1] < c.height - 1:
            cons.append(v1 * P[2] - P[1])
        rows.append((i, c.centre_world, cons))
    if empty:
        raise EmptyHullError(
            f"empty silhouette in view(s) {', '.join(empty[:10])}{' ...' if len(empty) > 10 else ''}: "
            "the visual hull is empty; exclude those views (BuildConfig.exclude_views / --exclude-view) "
            "or lower the alpha threshold"
        )
    active = {i for i, _, _ in rows}
    fb_lo = fb_hi = None
    if fallback is not None:
        fb_lo, fb_hi = (np.asarray(x, dtype=np.float64) for x in fallback)
    for _ in range(len(rows) + 1):
        A, b = [], []
        for i, _, cons in rows:
            if i not in active:
                continue
            for a in cons:
                n = np.linalg.norm(a[:3])
                if n > 0:
                    A.append(-a[:3] / n)
                    b.append(a[3] / n)
        bounds = [(None, None)] * 3 if fb_lo is None or fb_hi is None else list(zip(fb_lo, fb_hi, strict=True))
        lo, hi = np.empty(3), np.empty(3)
        for ax in range(3):
            for sign, out in ((1.0, lo), (-1.0, hi)):
                cvec = np.zeros(3)
                cvec[ax] = sign
                res = linprog(
                    cvec,
                    A_ub=np.array(A).reshape(-1, 3) if A else None,
                    b_ub=np.array(b) if b else None,
                    bounds=bounds,
                    method="highs",
                )
                if res.status == 2:
                    raise EmptyHullError(
                        "the silhouettes' bounding rectangles do not intersect in space: "
                        "the cameras or the silhouettes are inconsistent (wrong calibration?)"
                    )
                if res.status == 3:
                    raise InputError(
                        f"the visual hull is unbounded along {'xyz'[ax]} (silhouettes touch the image borders "
                        "in every view on one side); give explicit bounds (BuildConfig.bounds_m / --bounds)"
                    )
                if res.status != 0:
                    raise InputError(f"bounding-box LP failed: {res.message}")
                out[ax] = res.x[ax]
        # a box corner or face can pass through a camera centre (its wedge's apex), so
        # test with a small tolerance; dropping a view only makes the box larger
        tol = 1e-6 * float(np.max(hi - lo)) + 1e-12
        inside = [i for i, C, _ in rows if i in active and np.all(C >= lo - tol) and np.all(C <= hi + tol)]
        if not inside:
            return lo, hi
        active -= set(inside)
    return lo, hi  # pragma: no cover


# --------------------------------------------------------------------------- kernels


@njit(cache=True, inline="always")
def _proj(P, v, x, y, z):
    """Homogeneous projection of (x, y, z) by view v; one canonical evaluation order so
    every kernel rounds identically."""
    a = ((P[v, 0, 0] * x + P[v, 0, 1] * y) + P[v, 0, 2] * z) + P[v, 0, 3]
    b = ((P[v, 1, 0] * x + P[v, 1, 1] * y) + P[v, 1, 2] * z) + P[v, 1, 3]
    w = ((P[v, 2, 0] * x + P[v, 2, 1] * y) + P[v, 2, 2] * z) + P[v, 2, 3]
    return a, b, w


@njit(cache=True, inline="always")
def _centre_pixel(P, sizes, v, x, y, z):
    """``(seen, column, row)``: the pixel view v sees the point in (nearest centre), and
    whether the point is in front of the camera and inside the image at all."""
    a, b, w = _proj(P, v, x, y, z)
    if not (w > 0.0):
        return False, 0, 0
    u = a / w
    t = b / w
    fu = math.floor(u + 0.5)
    fv = math.floor(t + 0.5)
    if not (fu >= 0.0 and fu < sizes[v, 0] and fv >= 0.0 and fv < sizes[v, 1]):
        return False, 0, 0
    return True, int(fu), int(fv)


@njit(cache=True, inline="always")
def _centre_carves(P, sil, sizes, v, x, y, z):
    """True when view v carves the point (in front, inside the image, not silhouette)."""
    seen, iu, iv = _centre_pixel(P, sizes, v, x, y, z)
    return seen and sil[v, iv, iu] == 0


@njit(cache=True, parallel=True, nogil=True)
def _dense_kernel(P, sil, sizes, lo, h, nx, ny, nz, tol, occ):
    V = P.shape[0]
    for ix in prange(nx):
        x = lo[0] + (ix + 0.5) * h
        last = 0
        for iy in range(ny):
            y = lo[1] + (iy + 0.5) * h
            for iz in range(nz):
                z = lo[2] + (iz + 0.5) * h
                keep = 1
                rej = 0
                # start with the view that carved the previous voxel: neighbours are
                # usually carved by the same view, so most voxels exit after one test
                for j in range(V):
                    v = last + j
                    if v >= V:
                        v -= V
                    if _centre_carves(P, sil, sizes, v, x, y, z):
                        rej += 1
                        if rej > tol:
                            keep = 0
                            last = v
                            break
                occ[ix, iy, iz] = keep


def _check_tolerance(tolerance, n_views: int) -> int:
    t = int(tolerance) if isinstance(tolerance, (int, np.integer)) else -1
    if t < 0 or t != tolerance:
        raise InputError(
            f"carve tolerance must be an integer >= 0 (views allowed to reject a kept voxel), got {tolerance!r}"
        )
    if n_views and t >= n_views:
        raise InputError(
            f"carve tolerance {t} would let every one of the {n_views} views reject a voxel and "
            f"keep it; expected 0 <= tolerance < {n_views}"
        )
    return t


def carve_dense(silhouettes, cameras, grid: HullGrid, *, tolerance: int = 0) -> np.ndarray:
    """Centre-sampled dense carve (numba). Returns (nx, ny, nz) bool occupancy.

    ``tolerance``: a voxel survives when at most this many views reject it (robust
    carving under imperfect masks; 0 is the classical visual hull)."""
    sil, sizes = _stack_silhouettes(silhouettes, cameras)
    tol = _check_tolerance(tolerance, len(cameras))
    P = projection_matrices(cameras)
    occ = np.empty(grid.shape, np.uint8)
    _dense_kernel(P, sil, sizes, grid.lo, grid.voxel_m, *grid.shape, tol, occ)
    return occ.view(bool)


def carve_reference(silhouettes, cameras, grid: HullGrid, *, tolerance: int = 0) -> np.ndarray:
    """Slow NumPy oracle of the centre test through :meth:`Camera.project` (small grids):
    a voxel is kept when at most ``tolerance`` views carve its centre."""
    if len(silhouettes) != len(cameras):
        raise InputError(f"{len(silhouettes)} silhouettes for {len(cameras)} cameras")
    tol = _check_tolerance(tolerance, len(cameras))
    pts = grid.all_centres().reshape(-1, 3)
    rejections = np.zeros(pts.shape[0], np.int64)
    for s, c in zip(silhouettes, cameras, strict=True):
        if c.has_distortion:
            raise InputError(f"camera {c.name!r} has lens distortion; undistort its silhouette first")
        s = np.asarray(s, dtype=bool)
        # the same arithmetic as the kernels (P = K [R|t], evaluated in that order)
        P = c.projection_matrix()
        a = ((P[0, 0] * pts[:, 0] + P[0, 1] * pts[:, 1]) + P[0, 2] * pts[:, 2]) + P[0, 3]
        b = ((P[1, 0] * pts[:, 0] + P[1, 1] * pts[:, 1]) + P[1, 2] * pts[:, 2]) + P[1, 3]
        w = ((P[2, 0] * pts[:, 0] + P[2, 1] * pts[:, 1]) + P[2, 2] * pts[:, 2]) + P[2, 3]
        front = w > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            fu = np.floor(a / w + 0.5)
            fv = np.floor(b / w + 0.5)
        inside = front & (fu >= 0) & (fu < c.width) & (fv >= 0) & (fv < c.height)
        carved = np.zeros(pts.shape[0], bool)
        carved[inside] = ~s[fv[inside].astype(int), fu[inside].astype(int)]
        rejections += carved
    return (rejections <= tol).reshape(grid.shape)


@njit(cache=True, parallel=True, nogil=True)
def _sat_kernel(sil, sat):
    V, H, W = sil.shape
    for v in prange(V):
        for y in range(H):
            run = 0
            for x in range(W):
                run += sil[v, y, x]
                sat[v, y + 1, x + 1] = sat[v, y, x + 1] + run


def _summed_area(sil: np.ndarray) -> np.ndarray:
    """(V, H+1, W+1) int32 summed-area tables of silhouette pixels (numba, per view)."""
    V, H, W = sil.shape
    sat = np.empty((V, H + 1, W + 1), np.int32)
    sat[:, 0, :] = 0
    sat[:, :, 0] = 0
    _sat_kernel(sil, sat)
    return sat


@njit(cache=True, nogil=True)
def _cell_view_test(P, sat, sizes, v, x0, y0, z0, x1, y1, z1):
    """Classify a box of voxel centres [x0, x1]×[y0, y1]×[z0, z1] against view v.

    Returns 0 = carve the whole box, 1 = the view never carves inside the box (drop it),
    2 = undecided (split).
    """
    W = sizes[v, 0]
    H = sizes[v, 1]
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    n_front = 0
    n_back = 0
    for c in range(8):
        x = x1 if (c & 1) else x0
        y = y1 if (c & 2) else y0
        z = z1 if (c & 4) else z0
        a, b, w = _proj(P, v, x, y, z)
        if w > 0.0:
            n_front += 1
            u = a / w
            t = b / w
            umin = min(umin, u)
            umax = max(umax, u)
            vmin = min(vmin, t)
            vmax = max(vmax, t)
        else:
            n_back += 1
    if n_back == 8:
        return 1  # entirely behind the camera: never carved by it
    if n_back > 0:
        return 2  # straddles the camera plane: cannot bound the projection
    iu0 = math.floor(umin + 0.5)
    iu1 = math.floor(umax + 0.5)
    iv0 = math.floor(vmin + 0.5)
    iv1 = math.floor(vmax + 0.5)
    # huge rectangles (cells near the camera plane) are never decidable cheaply
    if iu1 - iu0 > 1e7 or iv1 - iv0 > 1e7:
        return 2
    area = (iu1 - iu0 + 1.0) * (iv1 - iv0 + 1.0)
    cu0 = max(iu0, 0.0)
    cu1 = min(iu1, W - 1.0)
    cv0 = max(iv0, 0.0)
    cv1 = min(iv1, H - 1.0)
    if cu0 > cu1 or cv0 > cv1:
        return 1  # entirely outside the image: not carved there
    a0 = int(cu0)
    a1 = int(cu1) + 1
    b0 = int(cv0)
    b1 = int(cv1) + 1
    inside_img = (a1 - a0) * (b1 - b0)
    count = sat[v, b1, a1] - sat[v, b0, a1] - sat[v, b1, a0] + sat[v, b0, a0]
    outside_img = area - inside_img
    inside = count + outside_img  # out-of-image pixels count as silhouette
    if inside <= 0:
        return 0
    if inside >= area:
        return 1
    return 2


@njit(cache=True, parallel=True, nogil=True)
def _octree_kernel(P, sat, sizes, lo, h, nx, ny, nz, root, tol, occ, stats):
    """Coarse-to-fine carving over root cells of ``root`` voxels (a power of two)."""
    V = P.shape[0]
    rx = (nx + root - 1) // root
    ry = (ny + root - 1) // root
    rz = (nz + root - 1) // root
    nroots = rx * ry * rz
    depth = 0
    s = root
    while s > 1:
        s //= 2
        depth += 1
    cap = 7 * depth + 8
    for r in prange(nroots):
        rix = r // (ry * rz)
        riy = (r // rz) % ry
        riz = r % rz
        st_pos = np.empty((cap, 3), np.int64)
        st_size = np.empty(cap, np.int64)
        st_nact = np.empty(cap, np.int64)
        st_act = np.empty((cap, V), np.int32)
        st_rej = np.empty(cap, np.int64)
        act = np.empty(V, np.int32)
        top = 0
        st_pos[0, 0] = rix * root
        st_pos[0, 1] = riy * root
        st_pos[0, 2] = riz * root
        st_size[0] = root
        st_nact[0] = V
        st_rej[0] = 0
        for v in range(V):
            st_act[0, v] = v
        top = 1
        n_tests = 0
        n_cells = 0
        while top > 0:
            top -= 1
            i0 = st_pos[top, 0]
            j0 = st_pos[top, 1]
            k0 = st_pos[top, 2]
            sz = st_size[top]
            nact = st_nact[top]
            rej = st_rej[top]
            i1 = min(i0 + sz, nx)
            j1 = min(j0 + sz, ny)
            k1 = min(k0 + sz, nz)
            if i0 >= nx or j0 >= ny or k0 >= nz:
                continue
            n_cells += 1
            # extreme voxel centres of the (clipped) cell
            x0 = lo[0] + (i0 + 0.5) * h
            y0 = lo[1] + (j0 + 0.5) * h
            z0 = lo[2] + (k0 + 0.5) * h
            x1 = lo[0] + (i1 - 1 + 0.5) * h
            y1 = lo[1] + (j1 - 1 + 0.5) * h
            z1 = lo[2] + (k1 - 1 + 0.5) * h
            carved = False
            keep_n = 0
            for q in range(nact):
                v = st_act[top, q]
                n_tests += 1
                res = _cell_view_test(P, sat, sizes, v, x0, y0, z0, x1, y1, z1)
                if res == 0:
                    # this view rejects every voxel of the cell; it is spent (no need to
                    # test it again below), and the cell goes once more than `tol` do
                    rej += 1
                    if rej > tol:
                        carved = True
                        break
                    continue
                if res == 2:
                    act[keep_n] = v
                    keep_n += 1
            if carved:
                continue  # occupancy starts at 0
            if keep_n == 0:
                for i in range(i0, i1):
                    for j in range(j0, j1):
                        for k in range(k0, k1):
                            occ[i, j, k] = 1
                continue
            # a single voxel always decides (its rectangle is one pixel), so sz > 1 here
            half = sz // 2
            for c in range(8):
                ci = i0 + (half if (c & 1) else 0)
                cj = j0 + (half if (c & 2) else 0)
                ck = k0 + (half if (c & 4) else 0)
                if ci >= nx or cj >= ny or ck >= nz:
                    continue
                st_pos[top, 0] = ci
                st_pos[top, 1] = cj
                st_pos[top, 2] = ck
                st_size[top] = half
                st_nact[top] = keep_n
                st_rej[top] = rej
                for q in range(keep_n):
                    st_act[top, q] = act[q]
                top += 1
        stats[r, 0] = n_cells
        stats[r, 1] = n_tests


@dataclass(frozen=True)
class OctreeStats:
    """Work done by :func:`carve_octree`: cells visited and cell-view tests."""

    cells: int
    tests: int
    root_cell: int


def enclosed_holes(silhouette) -> np.ndarray:
    """The silhouette with its enclosed holes filled: background regions not connected
    to the image border (8-connected foreground encloses them). A hole in one view only
    is the typical matting failure (a shadow as dark as the backdrop); a real
    see-through gap shows in several neighbouring views."""
    from scipy import ndimage

    filled = ndimage.binary_fill_holes(np.asarray(silhouette, dtype=bool))
    assert filled is not None  # it returns None only when given output=
    return filled


def backdrop_holes(silhouette, luminance, *, ring_px: int = 15, margin: float = 0.04) -> np.ndarray:
    """The silhouette with its enclosed holes filled, except holes that show the backdrop.

    A see-through gap shows the same backdrop as the frame around the object (or a
    darker one: the object shades it); a shadow on the object still reflects light and
    is brighter than the backdrop, though dark enough to fall below the mask's
    threshold. A hole (an 8-connected background region not touching the border) is kept
    open when its median ``luminance`` is at most the backdrop's median plus ``margin``
    × (object median − backdrop median); the backdrop is the ring of ``ring_px`` pixels
    around the filled silhouette. Measured on the Middlebury rings (display values
    0–255): the temple's colonnade gaps have medians 1–23 against backdrops of 8–29,
    the dino's shadow holes 22–45 against 4–16.

    Parameters
    ----------
    silhouette : (H, W) bool.
    luminance : (H, W) float, any monotonic brightness of the photograph.
    ring_px : width of the backdrop ring (px).
    margin : tolerance as a fraction of the object–backdrop contrast.

    Returns
    -------
    (H, W) bool: the "strong" silhouette for :func:`carve_robust` — rejections outside
    it are trusted.
    """
    import cv2
    from scipy import ndimage

    sil = np.asarray(silhouette, dtype=bool)
    lum = np.asarray(luminance, dtype=np.float32)
    if lum.shape != sil.shape:
        raise InputError(f"backdrop_holes: luminance {lum.shape} must match the silhouette {sil.shape}")
    filled = enclosed_holes(sil)
    holes = filled & ~sil
    if not holes.any():
        return filled
    k = np.ones((2 * ring_px + 1, 2 * ring_px + 1), np.uint8)
    ring = (cv2.dilate(filled.astype(np.uint8), k) > 0) & ~filled
    obj = sil & np.isfinite(lum)
    ring &= np.isfinite(lum)
    if not ring.any() or not obj.any():
        return filled
    bg = float(np.median(lum[ring]))
    fg = float(np.median(lum[obj]))
    limit = bg + margin * max(fg - bg, 0.0)
    lab, n = cast("tuple[np.ndarray, int]", ndimage.label(holes, structure=np.ones((3, 3), bool)))
    if n == 0:
        return filled
    vals = np.nan_to_num(lum[lab > 0], nan=np.inf)
    med = np.asarray(ndimage.median(vals, labels=lab[lab > 0], index=np.arange(1, n + 1)), dtype=np.float64)
    open_ids = np.flatnonzero(med <= limit) + 1
    if open_ids.size == 0:
        return filled
    return filled & ~np.isin(lab, open_ids)


def bright_extensions(
    silhouette,
    luminance,
    *,
    reach_px: int,
    open_px: int = 3,
    margin: float = 0.2,
    ring_px: int = 15,
    median_px: int = 5,
) -> np.ndarray:
    """Thick bright extensions of a silhouette: object parts a threshold lost at the
    outline (a shadowed plate that sticks out past it), not the thin glow around it.

    Pixels within ``reach_px`` of the filled silhouette (:func:`enclosed_holes`) whose
    ``median_px`` median-filtered ``luminance`` is above the backdrop's median plus
    ``margin`` × (object median − backdrop median), in the components that touch the
    silhouette (8-connected), opened by a disc of ``open_px``: the lens and display glow
    that lifts a band of a few pixels around every outline is thinner than the disc and
    goes; a protrusion wider than it stays. The backdrop is the ring of ``ring_px``
    pixels beyond the reach. An unknown (NaN) luminance is never bright.

    Parameters
    ----------
    silhouette : (H, W) bool.
    luminance : (H, W) float, any monotonic brightness of the photograph.
    reach_px : how far beyond the outline to look (px), >= 0; 0 finds nothing.
    open_px : the opening's disc radius (px), >= 0 (the glow's width).
    margin : the brightness limit between backdrop (0) and object (1).
    ring_px, median_px : the backdrop ring's width and the median filter's size (odd).

    Returns
    -------
    (H, W) bool, disjoint from the filled silhouette: pixels a tolerant carve should
    doubt (:func:`carve_robust`'s strong silhouettes).
    """
    import cv2
    from scipy import ndimage

    sil = np.asarray(silhouette, dtype=bool)
    lum = np.asarray(luminance, dtype=np.float32)
    if sil.ndim != 2:
        raise ShapeError(f"bright_extensions: silhouette has shape {sil.shape}, expected (H, W)")
    if lum.shape != sil.shape:
        raise InputError(f"bright_extensions: luminance {lum.shape} must match the silhouette {sil.shape}")
    if int(reach_px) < 0 or int(open_px) < 0 or int(ring_px) < 1 or int(median_px) < 1 or int(median_px) % 2 == 0:
        raise InputError(
            f"bright_extensions: reach_px {reach_px} and open_px {open_px} must be >= 0, ring_px {ring_px} >= 1, "
            f"median_px {median_px} odd and >= 1"
        )
    none = np.zeros_like(sil)
    filled = enclosed_holes(sil)
    r = int(reach_px)
    if r == 0 or not filled.any():
        return none
    lum = np.where(np.isfinite(lum), lum, -np.inf).astype(np.float32)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    reach = cv2.dilate(filled.astype(np.uint8), disc) > 0
    k = np.ones((2 * ring_px + 1, 2 * ring_px + 1), np.uint8)
    ring = (cv2.dilate(reach.astype(np.uint8), k) > 0) & ~reach & np.isfinite(lum)
    obj = sil & np.isfinite(lum)
    if not ring.any() or not obj.any():
        return none
    bg = float(np.median(lum[ring]))
    fg = float(np.median(lum[obj]))
    limit = bg + float(margin) * max(fg - bg, 0.0)
    # cv2's median filter takes float32 only up to a 5-px window; -inf sorts below all
    sm = ndimage.median_filter(lum, size=int(median_px), mode="nearest") if median_px > 1 else lum
    cand = (sm > limit) & reach & ~filled
    lab, _ = cast("tuple[np.ndarray, int]", ndimage.label(cand | filled, structure=np.ones((3, 3), bool)))
    ids = np.unique(lab[filled])
    grown = np.isin(lab, ids[ids > 0]) & cand
    if open_px > 0:
        d = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(open_px) + 1, 2 * int(open_px) + 1))
        grown = cv2.morphologyEx(grown.astype(np.uint8), cv2.MORPH_OPEN, d) > 0
    return grown & ~filled


def carve_robust(
    silhouettes,
    cameras,
    grid: HullGrid,
    *,
    tolerance: int = 1,
    root_cell: int = 32,
    return_stats: bool = False,
    strong_silhouettes=None,
):
    """Confidence-weighted robust carve: a rejection by a view's outer contour is always
    trusted (the view saw background there), a rejection through an *enclosed hole* of
    its silhouette (:func:`enclosed_holes`) is doubtful, and a voxel is removed by one
    trusted rejection or by more than ``tolerance`` rejections in all. With tolerance 0
    it is the classical hull. Returns the occupancy (and the two carves' summed
    :class:`OctreeStats`) and the filled ("strong") silhouettes for the surfel
    bisection (:func:`.surfels.sample_hull_surfels`). ``strong_silhouettes`` replaces
    the filled silhouettes (e.g. :func:`backdrop_holes`, which keeps see-through gaps
    open); each must contain its silhouette."""
    if strong_silhouettes is None:
        strong = [enclosed_holes(s) for s in silhouettes]
    else:
        if len(strong_silhouettes) != len(silhouettes):
            raise InputError(f"{len(strong_silhouettes)} strong silhouettes for {len(silhouettes)} views")
        strong = [
            np.asarray(t, bool) | np.asarray(s, bool) for t, s in zip(strong_silhouettes, silhouettes, strict=True)
        ]
    a, sa = carve_octree(strong, cameras, grid, root_cell=root_cell, return_stats=True)
    if tolerance == 0:
        b, sb = carve_octree(silhouettes, cameras, grid, root_cell=root_cell, return_stats=True)
    else:
        b, sb = carve_octree(silhouettes, cameras, grid, root_cell=root_cell, return_stats=True, tolerance=tolerance)
    occ = a & b
    st = OctreeStats(sa.cells + sb.cells, sa.tests + sb.tests, root_cell)
    return (occ, st, strong) if return_stats else (occ, strong)


@overload
def carve_octree(
    silhouettes,
    cameras,
    grid: HullGrid,
    *,
    root_cell: int = 32,
    return_stats: Literal[False] = False,
    tolerance: int = 0,
) -> np.ndarray: ...
@overload
def carve_octree(
    silhouettes, cameras, grid: HullGrid, *, root_cell: int = 32, return_stats: Literal[True], tolerance: int = 0
) -> tuple[np.ndarray, OctreeStats]: ...
@overload
def carve_octree(
    silhouettes, cameras, grid: HullGrid, *, root_cell: int = 32, return_stats: bool = False, tolerance: int = 0
) -> np.ndarray | tuple[np.ndarray, OctreeStats]: ...
def carve_octree(
    silhouettes, cameras, grid: HullGrid, *, root_cell: int = 32, return_stats: bool = False, tolerance: int = 0
) -> np.ndarray | tuple[np.ndarray, OctreeStats]:
    """Octree visual-hull carve (numba, parallel over root cells); see the module docstring.

    Parameters
    ----------
    silhouettes : list of (H, W) bool, one per camera (pinhole cameras).
    cameras : list of Camera.
    grid : HullGrid.
    root_cell : edge of the root cells in voxels (a power of two).
    tolerance : a voxel survives when at most this many views reject it (robust carving
        under imperfect masks: a shadow as dark as the backdrop punches a hole into one
        view's mask, which then carves a tunnel through a classical hull). 0 is the
        classical visual hull. A view that rejects a whole cell is counted once and not
        tested again below it, so the result still equals the dense carve with the same
        tolerance, voxel for voxel.

    Returns
    -------
    (nx, ny, nz) bool occupancy, identical to :func:`carve_dense`; with
    ``return_stats`` also an :class:`OctreeStats`.
    """
    if root_cell < 1 or (root_cell & (root_cell - 1)):
        raise InputError(f"root_cell must be a power of two, got {root_cell}")
    sil, sizes = _stack_silhouettes(silhouettes, cameras)
    tol = _check_tolerance(tolerance, len(cameras))
    P = projection_matrices(cameras)
    sat = _summed_area(sil)
    occ = np.zeros(grid.shape, np.uint8)
    nx, ny, nz = grid.shape
    nroots = (-(-nx // root_cell)) * (-(-ny // root_cell)) * (-(-nz // root_cell))
    stats = np.zeros((nroots, 2), np.int64)
    _octree_kernel(P, sat, sizes, grid.lo, grid.voxel_m, nx, ny, nz, int(root_cell), tol, occ, stats)
    occ = occ.view(bool)
    if return_stats:
        return occ, OctreeStats(int(stats[:, 0].sum()), int(stats[:, 1].sum()), int(root_cell))
    return occ


@njit(cache=True, parallel=True, nogil=True)
def _points_kernel(P, sil, sizes, pts, tol, out):
    V = P.shape[0]
    for n in prange(pts.shape[0]):
        keep = True
        rej = 0
        for v in range(V):
            if _centre_carves(P, sil, sizes, v, pts[n, 0], pts[n, 1], pts[n, 2]):
                rej += 1
                if rej > tol:
                    keep = False
                    break
        out[n] = keep


@njit(cache=True, parallel=True, nogil=True)
def _rejections_kernel(P, sil, sizes, pts, out):
    V = P.shape[0]
    for n in prange(pts.shape[0]):
        for v in range(V):
            out[n, v] = _centre_carves(P, sil, sizes, v, pts[n, 0], pts[n, 1], pts[n, 2])


def point_in_hull(points, silhouettes, cameras, *, tolerance: int = 0) -> np.ndarray:
    """Image-based hull membership of arbitrary points (N, 3): the centre test of the
    carvers applied to each point (kept when at most ``tolerance`` views reject it).
    Returns (N,) bool."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    sil, sizes = _stack_silhouettes(silhouettes, cameras)
    tol = _check_tolerance(tolerance, len(cameras))
    P = projection_matrices(cameras)
    out = np.empty(pts.shape[0], np.bool_)
    _points_kernel(P, sil, sizes, pts, tol, out)
    return out


def view_rejections(points, silhouettes, cameras) -> np.ndarray:
    """(N, V) bool: view v's silhouette rejects point n (its centre test carves it).
    With robust carving, the kept points a view rejects are where its mask disagrees
    with the hull (shadow holes, frame edges, misregistration)."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    sil, sizes = _stack_silhouettes(silhouettes, cameras)
    P = projection_matrices(cameras)
    out = np.empty((pts.shape[0], P.shape[0]), np.bool_)
    _rejections_kernel(P, sil, sizes, pts, out)
    return out
