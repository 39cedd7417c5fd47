"""Per-pixel ("deferred") ULR shading of an opacity hull.

The EWA pass is run for geometry only (:func:`rasterize_geometry`): per pixel the
normalised depth Σw·z/Σw of the front surface, the coverage Σw·A and the index of the
*winning* surfel (the largest kernel weight among the front-surface fragments). Each
covered pixel is then shaded at its back-projected surface point X (pixel ray × depth):
the k nearest views by angle among the winner's visible views (same rule, tie-breaking
and ULR weights as the per-surfel shading — the points are fed to
:func:`~opacityhull.render.kernels.ulr_shade` as if they were surfels), bilinear
premultiplied RGBA from each chosen view at X's projection. Colour and **alpha both
come from the blended mattes**: the hull only decides where to look, so the silhouette
is the photographs' and interior α is the mattes'. Texture sharpness is bounded by the
photographs' resolution, not the surfel density.

The driver, :func:`render_deferred` (what :func:`opacityhull.render.renderer.render_image`
runs with ``RenderConfig(shading="pixel")``, the default), lives here beside its parts.
It adds two image-space steps around :func:`deferred_shade`: :func:`close_gbuffer` fills
the geometry buffer's pinholes before shading, and α is clipped to the EWA coverage
afterwards (``coverage_clip``) — beyond the hull's limb the back-projected point lies on
the extrapolated tangent plane and would take opaque matte from the neighbours. The
clip replaces a hard coverage threshold (``min_coverage``, default 0 in the renderer):
a threshold of ½ dropped the fractional silhouette pixels, measured −1.1 dB on the
temple ring against the clip. Inside the hull's projection (``opaque_interior``, the
:func:`hull_interior`) the clip is off and α is
raised to the blend of the views' mattes dilated by the carve's silhouette tolerance, so
that interior α is 1 wherever the source mattes say opaque.

Why the winner's visibility and not each fragment's: visibility vectors are a surfel
property; the winner is the surfel whose centre is nearest the pixel in the kernel's
metric, so its bits are the best estimate for X.

Every kernel here has a NumPy twin in :mod:`opacityhull.render.reference`
(:func:`~opacityhull.render.reference.rasterize_geometry_ref`,
:func:`~opacityhull.render.reference.deferred_shade_reference`).
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit

from ..imageio import straight_from_premul
from ..model import Surfels
from . import kernels as K
from .config import RenderConfig
from .frame import (
    ALPHA_MIN,
    RenderResult,
    _remap_buffers,
    _stage_end,
    _stage_ms,
    _view_stats,
    coverage_from,
    setup_splats,
    surfel_areas,
)
from .view_io import dilated_matte_views
from .views import PreparedViews

__all__ = [
    "MIN_COVERAGE",
    "MIN_VIEW_COS",
    "TILE",
    "close_gbuffer",
    "rasterize_geometry",
    "geometry_frame",
    "backproject",
    "pixel_order",
    "deferred_shade",
    "shade_with",
    "render_deferred",
    "hull_interior",
]

MIN_COVERAGE = 0.5
"""Default of :func:`deferred_shade`: EWA coverage (fraction of full, see
:func:`opacityhull.render.frame.coverage_full`) below which a pixel is outside the
hull's projection and not shaded (α = 0)."""

MIN_VIEW_COS = -1.0
"""Default grazing limit of :func:`deferred_shade` (cos of the angle between a view's ray
and the surface normal; −1: off)."""

TILE = 16
"""Covered pixels are shaded in TILE×TILE tiles (row-major inside a tile), so that the
ULR search's per-block angle bounds (:data:`~opacityhull.render.kernels.ULR_BLOCK`
consecutive points) cover a compact patch of surface."""


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def rasterize_geometry(splat, lists, counts, height, width, cutoff, band_h, lut, geo, zlim, winner, wbest, b0, stride):
    """Two-pass ε-z-buffer EWA splatting of the geometry only (no colour).

    Same fragments, depth test and weights as :func:`~opacityhull.render.kernels.rasterize`
    (pass 1: ``zlim = min(z + ε)``; pass 2: fragments with ``q ≤ cutoff²`` and
    ``z ≤ zlim`` count), but pass 2 accumulates only Σw, Σw·z, Σw·area and keeps the
    surfel with the largest w (the first in surfel order on exact ties).

    Outputs (preallocated; bands ``b0, b0 + stride, …`` only)
    ---------------------------------------------------------
    geo : (H, W, 3) float32, zero: Σw, Σw·z, Σw·area.
    zlim : (H, W) float32, +inf: front depth + ε.
    winner : (H, W) int64, −1: index of the winning surfel.
    wbest : (H, W) float32, 0: its weight.
    """
    nb, c2, lut_scale = K._band_constants(counts, cutoff, lut)
    zero32 = np.float32(0.0)
    for b in range(b0, nb, stride):
        ylo, yhi = K._band_rows(b, band_h, height)
        K._depth_pass(splat, lists, counts[b], counts[b + 1], ylo, yhi, c2, zlim)
        for t in range(counts[b], counts[b + 1]):
            i = lists[t]
            x0, y0, z0, A, B2, C, dzx, dzy, zlo, zhi, xa, xb, ya, yb = K._splat_geometry(splat, i, ylo, yhi)
            w0 = splat[i, K.S_W]
            ar = splat[i, K.S_AREA]
            for y in range(ya, yb + 1):
                tt, cdy, zrow = K._row_terms(y, y0, B2, C, z0, dzy)
                for x in range(xa, xb + 1):
                    q, z, w = K._ewa_weight(A, tt, cdy, x - x0, zrow, dzx, zlo, zhi, c2, lut, lut_scale, w0)
                    w = w if (q <= c2 and z <= zlim[y, x]) else zero32
                    geo[y, x, 0] += w
                    geo[y, x, 1] += w * z
                    geo[y, x, 2] += w * ar
                    if w > wbest[y, x]:
                        wbest[y, x] = w
                        winner[y, x] = i


def geometry_frame(splat, draw, height, width, cutoff, band_h, *, threads: int = 1, scratch=None):
    """Bin and rasterise the drawn splats' geometry (:func:`rasterize_geometry`).

    Returns (geo (H, W, 3) float32 Σw, Σw·z, Σw·A; winner (H, W) int64, −1 where nothing
    was drawn). With ``scratch`` (a :class:`~opacityhull.render.kernels.Scratch`) the
    arrays live in its buffers.
    """
    geo = K.filled(scratch, "geo", (height, width, 3), np.float32, 0.0)
    zlim = K.filled(scratch, "zlim", (height, width), np.float32, np.inf)
    winner = K.filled(scratch, "winner", (height, width), np.int64, -1)
    wbest = K.filled(scratch, "wbest", (height, width), np.float32, 0.0)
    K.splat_bands(
        rasterize_geometry, splat, draw, height, width, cutoff, band_h, (geo, zlim, winner, wbest), threads=threads
    )
    return geo, winner


def close_gbuffer(depth, wsum, coverage, winner, *, size: int = 3):
    """Fill the geometry buffer's pinholes (NumPy, vectorised).

    Sparse or edge-on surfels leave isolated pixels that no front fragment reaches or
    reaches thinly inside the hull's projection (measured on a real 640×480 turntable
    set: ~5 % of the opaque interior below ½ coverage), which would show as speckles
    of α < 1. The coverage is grey-closed (dilation then erosion, ``size``×``size``),
    which fills holes narrower than the window without moving straight or convex
    silhouettes; pixels without a fragment whose closed coverage is positive take the
    depth and winner of their heaviest neighbour (largest Σw).

    Returns (depth, coverage, winner) — new arrays.
    """
    from scipy import ndimage

    cov = ndimage.grey_closing(np.asarray(coverage, np.float32), size=(size, size), mode="constant", cval=0.0)
    cov = np.maximum(cov, coverage).astype(np.float32)
    depth = np.array(depth, np.float32)
    winner = np.array(winner, np.int64)
    hole = (winner < 0) & (cov > 0)
    if hole.any():
        r = size // 2
        pad_w = np.pad(np.asarray(wsum, np.float32), r, constant_values=0.0)
        pad_z = np.pad(depth, r, constant_values=np.inf)
        pad_s = np.pad(winner, r, constant_values=-1)
        H, W = depth.shape
        best = np.zeros((H, W), np.float32)
        for dy in range(size):
            for dx in range(size):
                w = pad_w[dy : dy + H, dx : dx + W]
                take = hole & (w > best) & (pad_s[dy : dy + H, dx : dx + W] >= 0)
                best = np.where(take, w, best)
                depth = np.where(take, pad_z[dy : dy + H, dx : dx + W], depth)
                winner = np.where(take, pad_s[dy : dy + H, dx : dx + W], winner)
        cov = np.where((winner < 0), np.float32(0.0), cov).astype(np.float32)
    return depth, cov, winner


def pixel_order(shaded: np.ndarray, *, tile: int = TILE) -> np.ndarray:
    """(P,) int64 flat indices of the True pixels of ``shaded`` (H, W), tile by tile
    (tiles row-major, pixels row-major inside a tile)."""
    H, W = shaded.shape
    flat = np.flatnonzero(shaded.ravel())
    y, x = np.divmod(flat, W)
    tiles_x = -(-W // tile)
    key = ((y // tile) * tiles_x + x // tile) * (tile * tile) + (y % tile) * tile + (x % tile)
    return flat[np.argsort(key, kind="stable")].astype(np.int64)


@njit(cache=True, nogil=True, error_model="numpy")
def backproject(
    pix,
    depth,
    winner,
    cam,
    visibility,
    normals,
    view_centres,
    min_view_cos,
    allowed,
    fallback,
    out_points,
    out_vis,
    out_ok,
    i0,
    i1,
):
    """Surface points of pixels ``pix[i0:i1]`` (flat indices into (H, W)) of the pinhole
    camera ``cam`` (packed row, distortion ignored), and their candidate views.

    X = camera centre + depth · (Rᵀ ((x − cx)/fx, (y − cy)/fy, 1)) with ``depth`` along the
    optical axis (m). The candidate views are the winner's visibility bits, minus the
    views that see the winner's tangent plane at a grazing angle (``n · (C_v − X)/|C_v − X|
    ≤ min_view_cos``, n its unit normal): X lies on such a view's silhouette, where its
    matte and colour are a mix of object and backdrop. When that leaves no allowed view, or the
    normal is unusable, the bits are kept as they are. With ``fallback``, a winner that
    no allowed view sees (visibility vectors of real hulls leave many surfels unseen:
    29 % on a 16-view ring) gets every allowed view in front of its tangent plane
    (n · (C_v − X) > 0; all allowed views without a usable normal), occlusion ignored:
    the mattes still say where the object is, so the pixel is not left a hole.

    Writes out_points (P, 3) float64 (NaN when not shaded), out_vis (P, B) uint8 and
    out_ok (P,) bool (False where the depth is not finite and positive or there is no
    winner).
    """
    W = depth.shape[1]
    V = view_centres.shape[0]
    fx = cam[12]
    fy = cam[13]
    cx = cam[14]
    cy = cam[15]
    # camera centre −Rᵀt
    c0 = -(cam[0] * cam[9] + cam[3] * cam[10] + cam[6] * cam[11])
    c1 = -(cam[1] * cam[9] + cam[4] * cam[10] + cam[7] * cam[11])
    c2 = -(cam[2] * cam[9] + cam[5] * cam[10] + cam[8] * cam[11])
    nb = visibility.shape[1]
    for i in range(i0, i1):
        p = pix[i]
        y = p // W
        x = p - y * W
        z = np.float64(depth[y, x])
        s = winner[y, x]
        if not (z > 0.0 and math.isfinite(z) and s >= 0):
            out_ok[i] = False
            out_points[i, 0] = np.nan
            out_points[i, 1] = np.nan
            out_points[i, 2] = np.nan
            for b in range(nb):
                out_vis[i, b] = 0
            continue
        a = (x - cx) / fx * z
        bb = (y - cy) / fy * z
        px = c0 + cam[0] * a + cam[3] * bb + cam[6] * z
        py = c1 + cam[1] * a + cam[4] * bb + cam[7] * z
        pz = c2 + cam[2] * a + cam[5] * bb + cam[8] * z
        out_points[i, 0] = px
        out_points[i, 1] = py
        out_points[i, 2] = pz
        out_ok[i] = True
        for b in range(nb):
            out_vis[i, b] = visibility[s, b]
        n0 = np.float64(normals[s, 0])
        n1 = np.float64(normals[s, 1])
        n2 = np.float64(normals[s, 2])
        nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        has_n = nn > 1e-12 and math.isfinite(nn)
        if fallback:
            seen = False
            for v in range(V):
                if allowed[v] != 0 and (out_vis[i, v >> 3] >> (v & 7)) & 1 == 1:
                    seen = True
                    break
            if not seen:
                for v in range(V):
                    if allowed[v] == 0:
                        continue
                    if (
                        has_n
                        and not (
                            n0 * (view_centres[v, 0] - px)
                            + n1 * (view_centres[v, 1] - py)
                            + n2 * (view_centres[v, 2] - pz)
                        )
                        > 0.0
                    ):
                        continue
                    out_vis[i, v >> 3] |= np.uint8(1 << (v & 7))
        if min_view_cos <= -1.0 or not has_n:
            continue
        # two passes, so that when no allowed view passes the bits stay as they were
        for clear in range(2):
            kept = 0
            for v in range(V):
                if (out_vis[i, v >> 3] >> (v & 7)) & 1 == 0:
                    continue
                e0 = view_centres[v, 0] - px
                e1 = view_centres[v, 1] - py
                e2 = view_centres[v, 2] - pz
                ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                if (n0 * e0 + n1 * e1 + n2 * e2) > min_view_cos * nn * ne:
                    if allowed[v] != 0:
                        kept += 1
                elif clear == 1:
                    out_vis[i, v >> 3] &= np.uint8(255 - (1 << (v & 7)))
            if kept == 0:
                break


def deferred_shade(
    depth,
    coverage,
    winner,
    cam_row,
    desired_centre,
    visibility,
    normals,
    views,
    allowed,
    *,
    k: int,
    min_coverage: float = MIN_COVERAGE,
    min_view_cos: float = MIN_VIEW_COS,
    fallback: bool = False,
    threads: int = 1,
    align=None,
) -> tuple[np.ndarray, int]:
    """Per-pixel ULR shading (the fast twin of
    :func:`~opacityhull.render.reference.deferred_shade_reference`).

    Parameters
    ----------
    depth : (H, W) float32, metres along the optical axis (+inf where nothing was drawn).
    coverage : (H, W) float32 EWA coverage in [0, 1]; pixels below ``min_coverage`` are
        not shaded.
    winner : (H, W) int64 winning surfel per pixel (−1: none).
    cam_row : packed pinhole camera of the frame (:func:`~opacityhull.render.views.pack_camera`).
    desired_centre : (3,) its centre, object frame (m).
    visibility : (N, ceil(V/8)) uint8 packed visibility of the surfels.
    normals : (N, 3) surfel normals (object frame; need not be unit).
    min_view_cos : views seeing the winner's tangent plane at cos ≤ this are dropped
        (see :func:`backproject`); −1 keeps every visible view.
    fallback : a winner no allowed view sees takes the allowed views in front of its
        tangent plane (see :func:`backproject`).
    views : :class:`~opacityhull.render.views.PreparedViews` with images.
    allowed : (V,) uint8, 0 for excluded views.
    k : ULR neighbourhood.
    align : optional :class:`~opacityhull.render.floating.FlowAlignConfig`: the chosen
        views are aligned by optical flow before blending (:func:`.floating.float_blend`,
        floating textures); None blends them as they project.

    Returns
    -------
    premul : (H, W, 4) float32 premultiplied RGBA (0 where not shaded or no allowed view
        sees the winner), and the number of pixels shaded.
    """
    H, W = depth.shape
    cov_ok = np.asarray(coverage) >= np.float32(min_coverage)
    pix = pixel_order(cov_ok & (np.asarray(winner) >= 0))
    P = pix.size
    out = np.zeros((H, W, 4), np.float32)
    if P == 0:
        return out, 0
    vis = np.ascontiguousarray(visibility)
    points = np.empty((P, 3), np.float64)
    pvis = np.empty((P, vis.shape[1]), np.uint8)
    pok = np.empty(P, np.bool_)
    K.parallel_for(
        backproject,
        P,
        (
            pix,
            np.ascontiguousarray(depth),
            np.ascontiguousarray(winner),
            cam_row,
            vis,
            np.ascontiguousarray(normals),
            views.centres,
            float(min_view_cos),
            np.ascontiguousarray(allowed, np.uint8),
            bool(fallback),
            points,
            pvis,
            pok,
        ),
        threads=threads,
    )
    rgba = np.zeros((P, 4), np.float32)
    ok = np.zeros(P, np.bool_)
    order, s_lb = np.arange(views.n_views, dtype=np.int64), np.zeros(views.n_views)
    C = np.asarray(desired_centre, np.float64).reshape(3)
    # the points, their visibility and the views: the arguments ulr_shade and ulr_select share
    head = K.UlrHead(points, pvis, pok, allowed, C, views.centres, views.cams, views.sizes)
    if align is not None:
        return _aligned_shade(pix, head, views, order, s_lb, k, (H, W), align, threads)
    K.parallel_for(
        K.ulr_shade,
        P,
        (head, views.offsets, views.texels, order, s_lb, views.tie_rank, int(k), rgba, 0, ok),
        threads=threads,
    )
    flat = out.reshape(-1, 4)
    flat[pix[ok]] = rgba[ok]
    return out, int(ok.sum())


def _aligned_shade(pix, head, views, order, s_lb, k, shape, align, threads):
    """:func:`deferred_shade` with floating-texture alignment: the same view choice and
    weights (``ulr_select`` over ``head``, the arguments it shares with ``ulr_shade``),
    blended by :func:`.floating.float_blend`."""
    from .floating import float_blend

    points = head.positions
    P = pix.size
    kk = max(1, int(k))
    idx = np.empty((P, kk), np.int32)
    w = np.empty((P, kk), np.float32)
    uv = np.empty((P, kk, 2), np.float32)
    count = np.empty(P, np.int32)
    K.parallel_for(K.ulr_select, P, (head, order, s_lb, views.tie_rank, kk, idx, w, uv, count), threads=threads)
    ok = count > 0
    out, _ = float_blend(pix[ok], points[ok], idx[ok], w[ok], uv[ok], views, shape, config=align)
    return out, int(ok.sum())


# --------------------------------------------------------------------------- the pixel-shading driver


def shade_with(
    config: RenderConfig,
    depth,
    coverage,
    winner,
    cam_row,
    desired_centre,
    surfels: Surfels,
    views: PreparedViews,
    allowed,
    *,
    align=None,
) -> tuple[np.ndarray, int]:
    """:func:`deferred_shade` with ``config``'s ULR options (``k``, ``min_coverage``,
    ``min_view_cos``, ``fallback_views``, ``n_threads``) and the surfels' visibility and
    normals: the one call of the splat renderer's per-pixel path and the hybrid's
    triangles (:mod:`.hybrid`)."""
    return deferred_shade(
        depth,
        coverage,
        winner,
        cam_row,
        desired_centre,
        surfels.visibility,
        surfels.normals,
        views,
        allowed,
        k=int(config.k),
        min_coverage=float(config.min_coverage),
        min_view_cos=float(config.min_view_cos),
        fallback=bool(config.fallback_views),
        threads=config.n_threads,
        align=align,
    )


def render_deferred(
    surfels, pv, allowed, camera, pin, grid, cam_row, C, splat, valid, config, exclude_views, progress, times
) -> RenderResult:
    """The rest of :func:`~opacityhull.render.renderer.render_image` with ``shading="pixel"``
    (its camera, the pinhole canvas and remap ``grid``, the packed camera row, the centre
    ``C``, the frame's splat records and the stage ``times`` so far): geometry-only EWA pass
    (depth, coverage, winning surfel), then per-pixel ULR shading (:mod:`.deferred`).
    Every valid splat is geometry, whether or not a view sees it: visibility is decided
    per pixel from the winner's bits."""
    t0, t_prep, t_setup = times
    H, W = pin.height, pin.width
    threads = config.n_threads
    scratch = K.SCRATCH
    draw = np.flatnonzero(valid).astype(np.int64)
    geo, winner = geometry_frame(
        splat, draw, H, W, float(config.cutoff_sigma), int(config.band_rows), threads=threads, scratch=scratch
    )
    wsum = geo[..., 0].copy()
    has = wsum > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(has, geo[..., 1] / np.where(has, wsum, 1.0), np.inf).astype(np.float32)
    cov = coverage_from(geo[..., 2], wsum, config)
    if config.close_holes:
        depth, cov, winner = close_gbuffer(depth, wsum, cov, winner)
    refined = config.shading_surface == "refined" and surfels.depth_m is not None
    if refined:
        depth = _shading_depth(surfels, cam_row, W, H, depth, config, threads, scratch)
    t_raster = _stage_end(progress, 2)

    def shade(views: PreparedViews, align):
        # the same pixels, views and weights for the colour and for the dilated mattes
        return shade_with(config, depth, cov, winner, cam_row, C, surfels, views, allowed, align=align)

    premul, n_shaded = shade(pv, _align_config(config))
    interior = None
    if config.opaque_interior:
        interior = hull_interior(cov, winner, erode_px=int(config.interior_px))
        premul = _opaque_interior(premul, interior, pv, config, shade)
    if config.coverage_clip:
        # inside the hull's projection the coverage's dips are the splats' sampling gaps,
        # not a silhouette: only the outline clips
        clip_to = cov if interior is None else np.where(interior, np.float32(1.0), cov)
        a = premul[..., 3]
        clipped = np.minimum(a, clip_to)
        scale = np.where(a > clipped, clipped / np.where(a > 0, a, 1.0), 1.0).astype(np.float32)
        premul *= scale[..., None]
    t_shade = time.perf_counter()
    if grid is not None:
        premul, wsum, cov, depth = _remap_buffers(premul, wsum, cov, depth, grid)
    rgba_img = straight_from_premul(premul)
    t_end = _stage_end(progress, 3)
    stats = {
        "surfels": len(surfels),
        **_view_stats(camera, config, threads, exclude_views, pv, valid, draw),
        "pixels_covered": int((cov >= config.min_coverage).sum()),
        "pixels_shaded": n_shaded,
        "shading": "pixel",
        "shading_surface": "refined" if refined else "hull",
        "ms": _stage_ms(t0, prepare=t_prep, setup=t_setup, raster=t_raster, shade=t_shade, finish=t_end),
    }
    return RenderResult(rgba_img, depth, np.ascontiguousarray(wsum, dtype=np.float32), cov, camera, config, stats)


def hull_interior(coverage: np.ndarray, winner: np.ndarray, *, erode_px: int = 4, close_px: int = 1) -> np.ndarray:
    """(H, W) bool: the pixels deep inside the hull's projection, where the ray enters the
    hull away from its outline. The covered pixels (coverage ≥ ½ with a winning surfel)
    are closed by a disc of ``close_px`` (the splats' sampling seams are not part of the
    outline; a wider closing also shut the temple's carved see-through slots, −0.03 dB)
    and eroded by a disc of ``erode_px`` (the antialiased outline, where the coverage and
    the blended mattes decide the silhouette, stays out)."""
    import cv2

    m = ((np.asarray(coverage) >= 0.5) & (np.asarray(winner) >= 0)).astype(np.uint8)
    if close_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * close_px + 1, 2 * close_px + 1))
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    if erode_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
        m = cv2.erode(m, k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return m.astype(bool)


def _opaque_interior(premul, interior, pv: PreparedViews, config, shade):
    """Interior α where the source mattes say opaque: inside the hull's projection
    (``interior``) α is raised to the blend, with the same views and weights, of the
    views' mattes whose opaque part is dilated by ``config.matte_tolerance_px``
    (:func:`dilated_matte_views`) — the hull was carved from silhouettes dilated that much, so a
    hull point up to that far outside a view's matte is consistent with it, and on a
    crease the back-projected point lands just there. Colour stays the blend's
    (straight); pixels that no view gave colour take their neighbours' (normalised box
    filter of the premultiplied colour)."""
    if not interior.any():
        return premul
    dil, _ = shade(dilated_matte_views(pv, int(config.matte_tolerance_px)), None)
    a = premul[..., 3]
    target = np.where(interior, np.maximum(a, np.clip(dil[..., 3], 0.0, 1.0)), a).astype(np.float32)
    up = target > a
    if not up.any():
        return premul
    out = premul.copy()
    has = a > ALPHA_MIN
    fix = up & has
    out[fix] *= (target[fix] / a[fix])[:, None]
    none = up & ~has
    if none.any():
        import cv2

        box = cv2.boxFilter(premul, -1, (5, 5), normalize=False, borderType=cv2.BORDER_CONSTANT)
        n = box[..., 3]
        ok = none & (n > ALPHA_MIN)
        out[ok, :3] = box[ok, :3] / n[ok, None] * target[ok, None]
        out[ok, 3] = target[ok]
    return out


def _align_config(config: RenderConfig):
    if config.align == "none":
        return None
    from .floating import FlowAlignConfig

    return FlowAlignConfig()


def _shading_depth(
    surfels: Surfels, cam_row, W: int, H: int, hull_depth: np.ndarray, config: RenderConfig, threads: int, scratch
) -> np.ndarray:
    """Per-pixel depth of the photo-consistent surface: a second geometry-only EWA pass of
    the surfels displaced to ``positions − depth_m·normals``. Pixels it leaves empty keep
    the hull's depth; a displaced point is never in front of the hull (it lies inside it),
    so where the pass reports a nearer depth (a rim splat spreading past the hull's
    outline) the hull's depth is kept too. The coverage and winner of the hull pass are
    left alone: opacity and visibility stay the hull's."""
    N = len(surfels)
    shade_at = surfels.shading_positions()
    splat = scratch.get("splat_shade", (N, K.SPLAT_FIELDS), np.float32)
    valid = scratch.get("valid_shade", (N,), np.bool_)
    setup_splats(surfels, shade_at, surfel_areas(surfels), cam_row, W, H, config, threads, splat, valid)
    draw = np.flatnonzero(valid).astype(np.int64)
    # no scratch here: the hull pass's winner may still live in the scratch buffers
    geo, winner = geometry_frame(splat, draw, H, W, float(config.cutoff_sigma), int(config.band_rows), threads=threads)
    wsum = geo[..., 0]
    has = wsum > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        dr = np.where(has, geo[..., 1] / np.where(has, wsum, 1.0), np.inf).astype(np.float32)
    if config.close_holes:
        cov = coverage_from(geo[..., 2], wsum, config)
        dr, _, _ = close_gbuffer(dr, wsum.copy(), cov, winner)
    use = np.isfinite(dr) & np.isfinite(hull_depth) & (dr >= hull_depth)
    return np.where(use, dr, hull_depth).astype(np.float32)
