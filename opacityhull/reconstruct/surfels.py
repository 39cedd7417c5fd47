"""Surfels on the visual hull: layered-depth-cube (LDC) sampling, as in Pfister et al.
("Surfels", SIGGRAPH 2000) and the opacity-hull paper.

Rays are cast through the carved voxel grid along each of the three axes, one ray per
voxel column (``oversample``² per column if asked). Along a ray, every change of
occupancy between two consecutive voxel centres brackets a hull-surface crossing; the
crossing is located to sub-voxel precision by **bisection against the silhouettes** —
the image-based point test of :func:`.hull.point_in_hull`, i.e. the exact visual hull
rather than its voxelisation. The bisection only tests views that can change the answer
along the bracket: a view is skipped when the bracket's projection lies entirely within
the silhouette (the silhouette's distance transform at the inside end exceeds the
projected bracket length plus a pixel diagonal), which is exact, not a heuristic.

Each crossing is a surfel with

* **position** — the bisection result (error ≤ voxel / 2^iterations along the ray);
* **normal** — minus the gradient of the occupancy smoothed by a Gaussian, evaluated at
  the surfel: outward, and well defined on flat faces and curved parts alike. The scale
  is the pixel footprint on the object (the occupancy is block-averaged to it first):
  finer than that, the hull's surface is the silhouettes' pixel staircase, not the
  object's shape;
* **radius** — hole-free coverage: samples of axis ``a`` lie on a square grid of
  spacing ``s`` in the plane normal to ``a``; a disc of radius ``r`` with normal ``n``
  projects onto that plane as an ellipse with semi-axes ``r`` and ``r |n_a|``, which
  contains the grid cell's circumcircle (radius ``s / sqrt(2)``) when
  ``r = s / (sqrt(2) |n_a|)``.

The three axes sample the same surface; like the LDC's "3-to-1 reduction" each surfel
is kept only by the axis along which its normal is largest (``|n_a| >= 1/sqrt(3)``, so
radii stay below ``1.23 s``), which keeps the density near one surfel per ``s²`` —
plus, near the seams where two axes are almost equally dominant (within
``seam_overlap``), the runner-up's samples too: the two grids do not line up there and
the dominant axis alone leaves slivers uncovered (measured: 0.9 % of a sphere's surface
without overlap, none with 0.15).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..errors import InputError, ShapeError
from .hull import HullGrid, _centre_pixel, _proj, projection_matrices

__all__ = [
    "SurfelSample",
    "sample_hull_surfels",
    "hull_normals",
    "hull_normals_reference",
    "pooled_density",
    "silhouette_distance",
]


@dataclass
class SurfelSample:
    """Surfels sampled from the hull (before visibility).

    positions (N, 3) float64 m; normals (N, 3) float32 unit outward; radii (N,) float32 m;
    axis (N,) uint8 LDC axis that produced the sample; spacing_m the LDC sample spacing.
    """

    positions: np.ndarray
    normals: np.ndarray
    radii: np.ndarray
    axis: np.ndarray
    spacing_m: float

    def __len__(self) -> int:
        return int(self.positions.shape[0])


def silhouette_distance(silhouettes, *, shape: tuple[int, int] | None = None, floor_u8: bool = False) -> np.ndarray:
    """Per view, Euclidean distance (pixels) from each silhouette pixel to the nearest
    non-silhouette pixel (0 outside), stacked to (V, Hmax, Wmax) float32. ``shape``
    (Hmax, Wmax) when known: the silhouettes are then read once each, one at a time
    (a sequence that unpacks on access, such as the build's bit-packed masks).
    ``floor_u8``: the distances rounded down and capped at 255, as uint8 (a quarter of
    the bytes; a lower bound of the distance, which is all :func:`_candidate_views`
    needs to skip a view)."""
    import cv2

    if shape is None:
        Hm = max(np.shape(s)[0] for s in silhouettes)
        Wm = max(np.shape(s)[1] for s in silhouettes)
    else:
        Hm, Wm = (int(x) for x in shape)
    out = np.zeros((len(silhouettes), Hm, Wm), np.uint8 if floor_u8 else np.float32)
    for i in range(len(silhouettes)):
        s8 = np.asarray(silhouettes[i], dtype=bool).astype(np.uint8)
        # pad with silhouette so the image border is not a boundary (outside an image
        # nothing is carved); the padding is wide enough for any bracket we test
        pad = 64
        sp = np.pad(s8, pad, constant_values=1)
        d = cv2.distanceTransform(sp, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        d = d[pad:-pad, pad:-pad]
        if floor_u8:
            d = np.minimum(np.floor(d), 255.0).astype(np.uint8)
        out[i, : s8.shape[0], : s8.shape[1]] = d
    return out


#: the candidate test's distance lower bound is kept per block of EDT_BLOCK² pixels (the
#: block's minimum: still a lower bound at each of its pixels, at 1/16 of the bytes)
EDT_BLOCK = 4


def packed_bisection_stacks(silhouettes, cameras, strong_silhouettes=None):
    """What the bisection reads, one view unpacked at a time: ``(bits, strong_bits,
    sizes, edt)`` — the silhouettes and the strong ones bit-packed along rows
    (:func:`numpy.packbits`, (V, Hmax, ceil(Wmax / 8)) uint8; ``strong_bits`` is
    ``bits`` when ``strong_silhouettes`` is None), (V, 2) int64 (width, height), and the
    uint8 floor of :func:`silhouette_distance`, minimum-pooled over blocks of
    :data:`EDT_BLOCK` pixels ((V, ceil(Hmax / 4), ceil(Wmax / 4))). 0.31 B a pixel a view
    instead of the unpacked stacks' 2-3, and never a (V, H, W) array of any kind.

    Raises
    ------
    InputError
        Counts differ, no view, or a strong silhouette not containing its silhouette.
    ShapeError
        A silhouette whose shape is not its camera's (height, width).
    """
    import cv2

    if len(silhouettes) != len(cameras):
        raise InputError(f"{len(silhouettes)} silhouettes for {len(cameras)} cameras")
    if len(cameras) == 0:
        raise InputError("visual hull needs at least one view")
    if strong_silhouettes is not None and len(strong_silhouettes) != len(cameras):
        raise InputError(f"{len(strong_silhouettes)} strong silhouettes for {len(cameras)} views")
    V = len(cameras)
    Hm = max(c.height for c in cameras)
    Wm = max(c.width for c in cameras)
    B = EDT_BLOCK
    bits = np.zeros((V, Hm, (Wm + 7) // 8), np.uint8)
    strong_bits = bits if strong_silhouettes is None else np.zeros_like(bits)
    edt = np.zeros((V, (Hm + B - 1) // B, (Wm + B - 1) // B), np.uint8)
    sizes = np.zeros((V, 2), np.int64)
    pad = 64  # as silhouette_distance: the image border is not a boundary
    for i, c in enumerate(cameras):
        m = np.asarray(silhouettes[i], dtype=bool)
        if m.shape != (c.height, c.width):
            raise ShapeError(f"silhouette {i} ({c.name}) has shape {m.shape}, expected {(c.height, c.width)}")
        sizes[i] = (c.width, c.height)
        bits[i, : c.height, : (c.width + 7) // 8] = np.packbits(m, axis=1)
        if strong_silhouettes is not None:
            t = np.asarray(strong_silhouettes[i], dtype=bool)
            if t.shape != m.shape:
                raise ShapeError(f"strong silhouette {i} ({c.name}) has shape {t.shape}, expected {m.shape}")
            if np.any(m & ~t):
                raise InputError("strong_silhouettes must contain the silhouettes (a superset of their pixels)")
            strong_bits[i, : c.height, : (c.width + 7) // 8] = np.packbits(t, axis=1)
        d = cv2.distanceTransform(
            np.pad(m.astype(np.uint8), pad, constant_values=1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
        )
        d8 = np.zeros((edt.shape[1] * B, edt.shape[2] * B), np.uint8)  # 0 beyond the image: a lower bound
        d8[: c.height, : c.width] = np.minimum(np.floor(d[pad:-pad, pad:-pad]), 255.0).astype(np.uint8)
        edt[i] = d8.reshape(edt.shape[1], B, edt.shape[2], B).min(axis=(1, 3))
    return bits, strong_bits, sizes, edt


@njit(cache=True, inline="always")
def _centre_carves_bits(P, bits, sizes, v, x, y, z):
    """:func:`.hull._centre_carves` on bit-packed silhouettes (the same pixel, so the
    same answer): True when view v carves the point."""
    seen, iu, iv = _centre_pixel(P, sizes, v, x, y, z)
    return seen and ((bits[v, iv, iu >> 3] >> (7 - (iu & 7))) & 1) == 0


@njit(cache=True, nogil=True)
def _candidate_views(P, sizes, edt, pa, pb, cand):
    """Views that might carve some point of the segment [pa, pb] (pa inside). Returns
    the count written to ``cand``. ``edt`` is a lower bound of the silhouette distance
    per block of :data:`EDT_BLOCK` pixels (:func:`packed_bisection_stacks`): a lower
    bound only keeps more views as candidates, and a candidate that accepts every point
    changes no test."""
    V = P.shape[0]
    n = 0
    for v in range(V):
        a0, b0, w0 = _proj(P, v, pa[0], pa[1], pa[2])
        a1, b1, w1 = _proj(P, v, pb[0], pb[1], pb[2])
        if not (w0 > 0.0 and w1 > 0.0):
            cand[n] = v
            n += 1
            continue
        u0 = a0 / w0
        t0 = b0 / w0
        u1 = a1 / w1
        t1 = b1 / w1
        fu = math.floor(u0 + 0.5)
        fv = math.floor(t0 + 0.5)
        L = math.sqrt((u1 - u0) ** 2 + (t1 - t0) ** 2)
        if fu >= 0 and fu < sizes[v, 0] and fv >= 0 and fv < sizes[v, 1]:
            if edt[v, int(fv) // EDT_BLOCK, int(fu) // EDT_BLOCK] > L + 1.5:
                continue  # the whole segment projects inside the silhouette
        elif L < 1e6:  # noqa: SIM102  the off-image twin of the branch above
            # inside end off-image: the view matters only if the segment reaches the image
            if (
                max(u0, u1) < -0.5 - 1.0
                or min(u0, u1) > sizes[v, 0] - 0.5 + 1.0
                or max(t0, t1) < -0.5 - 1.0
                or min(t0, t1) > sizes[v, 1] - 0.5 + 1.0
            ):
                continue
        cand[n] = v
        n += 1
    return n


@njit(cache=True, nogil=True)
def _inside(P, sil, strong, sizes, cand, nc, tol, x, y, z):
    # the point test over views cand[:nc] on bit-packed silhouettes (all views, or the
    # bracket's candidates: views
    # left out of `cand` provably accept every point of the bracket, `strong` being a
    # superset of `sil`, so counting rejections among the candidates counts them among
    # all views)
    rej = 0
    for q in range(nc):
        v = cand[q]
        if _centre_carves_bits(P, sil, sizes, v, x, y, z):
            if _centre_carves_bits(P, strong, sizes, v, x, y, z):
                return False
            rej += 1
            if rej > tol:
                return False
    return True


@njit(cache=True, inline="always")
def _occ_axis(occ, axis, i, b, c):
    if axis == 0:
        return occ[i, b, c]
    elif axis == 1:
        return occ[b, i, c]
    return occ[b, c, i]


@njit(cache=True, parallel=True, nogil=True)
def _count_crossings(occ, axis, nb, nc, na, s, counts):
    for r in prange(nb * s * nc * s):
        qb = r // (nc * s)
        qc = r % (nc * s)
        b = qb // s
        c = qc // s
        n = 0
        prev = 0
        for i in range(na):
            o = _occ_axis(occ, axis, i, b, c)
            if o != prev:
                n += 1
            prev = o
        if prev != 0:
            n += 1  # the hull reaches the far face of the grid
        counts[r] = n


@njit(cache=True, parallel=True, nogil=True)
def _fill_crossings(
    occ, axis, nb, nc, na, s, offsets, lo, h, P, sil, strong, sizes, edt, iters, tol, pos, sign, status
):
    V = P.shape[0]
    every = np.arange(V)
    ax_b = 1 if axis == 0 else 0
    ax_c = 1 if axis == 2 else 2
    for r in prange(nb * s * nc * s):
        qb = r // (nc * s)
        qc = r % (nc * s)
        b = qb // s
        c = qc // s
        cand = np.empty(V, np.int64)
        pa = np.empty(3)
        pb = np.empty(3)
        pm = np.empty(3)
        cb = lo[ax_b] + (qb + 0.5) * (h / s)
        cc = lo[ax_c] + (qc + 0.5) * (h / s)
        if s == 1:
            # the same arithmetic as the carvers, so bracket ends agree with the voxels
            cb = lo[ax_b] + (b + 0.5) * h
            cc = lo[ax_c] + (c + 0.5) * h
        out = offsets[r]
        prev = 0
        for i in range(na + 1):
            o = _occ_axis(occ, axis, i, b, c) if i < na else 0
            if o == prev:
                continue
            # bracket between centre i-1 and centre i (the grid faces at the ends)
            t_prev = lo[axis] + (i - 0.5) * h if i > 0 else lo[axis]
            t_here = lo[axis] + (i + 0.5) * h if i < na else lo[axis] + na * h
            if o == 1:  # entering the hull with increasing t: inside end is t_here
                t_in, t_out, sg = t_here, t_prev, -1
            else:
                t_in, t_out, sg = t_prev, t_here, 1
            prev = o
            pa[axis] = t_in
            pa[ax_b] = cb
            pa[ax_c] = cc
            pb[axis] = t_out
            pb[ax_b] = cb
            pb[ax_c] = cc
            st = 0
            if s == 1 and i > 0 and i < na:
                # both ends are voxel centres: the carve already answered the point test
                in_ok = True
                out_ok = True
            else:
                in_ok = _inside(P, sil, strong, sizes, every, V, tol, pa[0], pa[1], pa[2])
                out_ok = not _inside(P, sil, strong, sizes, every, V, tol, pb[0], pb[1], pb[2])
            if in_ok and out_ok:
                nc_ = _candidate_views(P, sizes, edt, pa, pb, cand)
                lo_t = t_in
                hi_t = t_out
                for _it in range(iters):
                    mt = 0.5 * (lo_t + hi_t)
                    pm[axis] = mt
                    pm[ax_b] = cb
                    pm[ax_c] = cc
                    if _inside(P, sil, strong, sizes, cand, nc_, tol, pm[0], pm[1], pm[2]):
                        lo_t = mt
                    else:
                        hi_t = mt
                tt = 0.5 * (lo_t + hi_t)
            elif in_ok:
                # the outer end is inside too (the hull reaches the grid face): the
                # surfel sits on the face
                tt = t_out
                st = 1
            else:
                # off-centre rays (oversample > 1) can miss the voxels' crossing
                tt = 0.5 * (t_in + t_out)
                st = 2
            pos[out, axis] = tt
            pos[out, ax_b] = cb
            pos[out, ax_c] = cc
            sign[out] = sg
            status[out] = st
            out += 1


@njit(cache=True, parallel=True, nogil=True)
def _normals_kernel(occ, lo, h, pts, sigma_vox, radius, out):
    nx, ny, nz = occ.shape
    inv2s2 = 1.0 / (2.0 * sigma_vox * sigma_vox)
    for n in prange(pts.shape[0]):
        # continuous voxel coordinates (voxel centres at integers)
        fx = (pts[n, 0] - lo[0]) / h - 0.5
        fy = (pts[n, 1] - lo[1]) / h - 0.5
        fz = (pts[n, 2] - lo[2]) / h - 0.5
        cx = int(math.floor(fx + 0.5))
        cy = int(math.floor(fy + 0.5))
        cz = int(math.floor(fz + 0.5))
        gx = 0.0
        gy = 0.0
        gz = 0.0
        for i in range(cx - radius, cx + radius + 1):
            if i < 0 or i >= nx:
                continue
            dx = i - fx
            for j in range(cy - radius, cy + radius + 1):
                if j < 0 or j >= ny:
                    continue
                dy = j - fy
                for k in range(cz - radius, cz + radius + 1):
                    if k < 0 or k >= nz:
                        continue
                    o = occ[i, j, k]
                    if o == 0:
                        continue
                    dz = k - fz
                    g = o * math.exp(-(dx * dx + dy * dy + dz * dz) * inv2s2)
                    # gradient of the smoothed occupancy points inwards (towards the
                    # occupied voxels); the outward normal is its opposite
                    gx += g * dx
                    gy += g * dy
                    gz += g * dz
        out[n, 0] = -gx
        out[n, 1] = -gy
        out[n, 2] = -gz


def pooled_density(occ, grid: HullGrid, factor: int) -> tuple[np.ndarray, HullGrid]:
    """Mean occupancy over ``factor``³ blocks (float32) and the coarser grid it lives on
    (same ``lo``; blocks past the end are padded with 0)."""
    m = int(factor)
    occ = np.asarray(occ, dtype=bool)
    if m <= 1:
        return occ.astype(np.float32), grid
    shp = [-(-n // m) * m for n in occ.shape]
    pad = np.zeros(shp, np.float32)
    pad[: occ.shape[0], : occ.shape[1], : occ.shape[2]] = occ
    d = pad.reshape(shp[0] // m, m, shp[1] // m, m, shp[2] // m, m).mean(axis=(1, 3, 5))
    return d.astype(np.float32), HullGrid(grid.lo, grid.voxel_m * m, d.shape)


def hull_normals(occ, grid: HullGrid, points, *, sigma_vox: float = 1.0, radius_vox: int = 2) -> np.ndarray:
    """Unnormalised outward normals ``-grad (G_sigma * occ)`` at points (N, 3) (numba).

    ``occ`` may be boolean occupancy or a float density (e.g. :func:`pooled_density`);
    the Gaussian (σ in voxels of ``grid``) is truncated at ``radius_vox``. Returns (N, 3)
    float64."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    out = np.empty_like(pts)
    occ = np.asarray(occ)
    occ = np.ascontiguousarray(occ.astype(np.float32) if occ.dtype == bool else occ)
    _normals_kernel(occ, grid.lo, grid.voxel_m, pts, float(sigma_vox), int(radius_vox), out)
    return out


def hull_normals_reference(occ, grid: HullGrid, points, *, sigma_vox: float = 1.0, radius_vox: int = 2) -> np.ndarray:
    """NumPy oracle of :func:`hull_normals` (loops over points; small inputs)."""
    occ = np.asarray(occ, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros_like(pts)
    r = int(radius_vox)
    for n, p in enumerate(pts):
        f = (p - grid.lo) / grid.voxel_m - 0.5
        c = np.floor(f + 0.5).astype(int)
        idx = np.stack(np.meshgrid(*[np.arange(c[i] - r, c[i] + r + 1) for i in range(3)], indexing="ij"), -1).reshape(
            -1, 3
        )
        ok = np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=1)
        idx = idx[ok]
        o = occ[idx[:, 0], idx[:, 1], idx[:, 2]]
        d = idx - f
        g = o * np.exp(-(d * d).sum(1) / (2 * sigma_vox**2))
        out[n] = -(g[:, None] * d).sum(0)
    return out


def sample_hull_surfels(
    occ,
    grid: HullGrid,
    silhouettes,
    cameras,
    *,
    oversample: int = 1,
    bisection_iters: int = 10,
    radius_scale: float = 1.0,
    normal_scale_vox: float = 1.0,
    seam_overlap: float = 0.15,
    tolerance: int = 0,
    strong_silhouettes=None,
) -> SurfelSample:
    """Layered-depth-cube sampling of the visual hull into surfels (see module docstring).

    Parameters
    ----------
    occ : (nx, ny, nz) bool occupancy from a carver.
    grid : its HullGrid.
    silhouettes, cameras : the carve's inputs (pinhole cameras), used for bisection.
    oversample : LDC rays per voxel column along each transverse axis (spacing
        ``voxel / oversample``).
    bisection_iters : bisection steps per crossing (precision ``voxel / 2**iters``).
    radius_scale : multiplies the hole-free radius (> 1 for extra overlap).
    seam_overlap : a sample of axis ``a`` is kept when ``|n_a| >= (1 - seam_overlap)
        max_b |n_b|``: 0 keeps only the dominant axis; a little overlap closes the gaps
        where two axes' sample grids meet.
    normal_scale_vox : scale of the normal estimate in voxels: the occupancy is averaged
        over blocks of ``round(normal_scale_vox)``³ voxels and differentiated with a
        Gaussian of one block. Set it to the pixel footprint on the object (in voxels)
        so the normals see the object's shape rather than the silhouettes' pixel steps.
    tolerance, strong_silhouettes : the carve's rule (see :func:`.hull.carve_octree`): a
        point is inside when no ``strong_silhouettes`` view rejects it and at most
        ``tolerance`` views of ``silhouettes`` do; the bisection uses the same rule as the
        carve that made ``occ``. ``strong_silhouettes`` None means the same silhouettes.

    Returns
    -------
    SurfelSample
    """
    occ = np.ascontiguousarray(np.asarray(occ, dtype=bool)).view(np.uint8)
    if occ.shape != tuple(grid.shape):
        raise InputError(f"occupancy has shape {occ.shape}, grid is {grid.shape}")
    s = int(oversample)
    if s < 1:
        raise InputError(f"oversample must be >= 1, got {oversample}")
    if not 0.0 <= seam_overlap < 1.0:
        raise InputError(f"seam_overlap must be in [0, 1), got {seam_overlap}")
    if not occ.any():
        empty = np.zeros((0, 3))
        return SurfelSample(
            empty, empty.astype(np.float32), np.zeros(0, np.float32), np.zeros(0, np.uint8), grid.voxel_m / s
        )
    # bit-packed silhouettes and a block-pooled uint8 floor of their distance, each view
    # unpacked once and alone: the candidate test only skips views, so a lower bound
    # gives the same surfels
    sil, strong, sizes, edt = packed_bisection_stacks(silhouettes, cameras, strong_silhouettes)
    P = projection_matrices(cameras)
    h = grid.voxel_m
    all_pos, all_axis, all_sign = [], [], []
    for axis in range(3):
        na = grid.shape[axis]
        others = [a for a in range(3) if a != axis]
        nb, nc = grid.shape[others[0]], grid.shape[others[1]]
        counts = np.empty(nb * s * nc * s, np.int64)
        _count_crossings(occ, axis, nb, nc, na, s, counts)
        offsets = np.zeros_like(counts)
        np.cumsum(counts[:-1], out=offsets[1:])
        total = int(counts.sum())
        pos = np.empty((total, 3))
        sign = np.empty(total, np.int8)
        status = np.empty(total, np.uint8)
        _fill_crossings(
            occ,
            axis,
            nb,
            nc,
            na,
            s,
            offsets,
            grid.lo,
            h,
            P,
            sil,
            strong,
            sizes,
            edt,
            int(bisection_iters),
            int(tolerance),
            pos,
            sign,
            status,
        )
        all_pos.append(pos)
        all_axis.append(np.full(total, axis, np.uint8))
        all_sign.append(sign)
    pos = np.concatenate(all_pos)
    axis = np.concatenate(all_axis)
    sign = np.concatenate(all_sign).astype(np.float64)
    dens, dgrid = pooled_density(occ.view(bool), grid, max(1, int(round(normal_scale_vox))))
    g = hull_normals(dens, dgrid, pos, sigma_vox=1.0, radius_vox=2)
    norm = np.linalg.norm(g, axis=1)
    # a vanishing gradient (a one-voxel-thin sheet) falls back to the LDC ray direction
    fallback = norm < 1e-9
    g[fallback] = 0.0
    g[fallback, axis[fallback]] = sign[fallback]
    n = g / np.linalg.norm(g, axis=1, keepdims=True)
    an = np.abs(n)
    # keep the samples of the dominant axis, and near the seams between dominant axes
    # (where the axes' sample grids do not line up) those of the runner-up as well
    keep = an[np.arange(len(n)), axis] >= (1.0 - seam_overlap) * an.max(axis=1)
    pos, n, axis = pos[keep], n[keep], axis[keep]
    spacing = h / s
    na_ = np.maximum(np.abs(n[np.arange(len(n)), axis]), (1.0 - seam_overlap) / math.sqrt(3.0))
    radii = radius_scale * spacing / (math.sqrt(2.0) * na_)
    return SurfelSample(pos, n.astype(np.float32), radii.astype(np.float32), axis, spacing)
