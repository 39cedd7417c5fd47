"""Point/triangle hybrid rendering (PMR, Dey & Hudson 2002, §3 "Point vs. umbrella").

Every surfel carries the umbrella of the model's umbrella mesh
(:func:`opacityhull.render.pmr.umbrella_triangulation`): the mesh triangles incident to
it, and the umbrella radius, the largest distance from the surfel to a vertex of those
triangles. Per frame, a surfel whose umbrella projects larger than a pixel threshold
(``2 · radius · f / z > threshold_px``, the paper's "twice the umbrella radius against
the pixel size", computed per surfel rather than per octree leaf) is drawn as its
umbrella triangles; every other surfel, and every surfel whose umbrella is open (a
boundary or non-manifold edge: a hole of the mesh, where triangles alone would leave a
gap), is drawn as its EWA splat by the unchanged splat renderer
(:func:`~opacityhull.render.renderer.render_image`).

The triangles go through a z-buffer rasteriser (:func:`rasterize_triangles`, numba, with
the NumPy twin :func:`rasterize_triangles_reference`): perspective-correct depth and
barycentrics at the pixel centres (integer coordinates, the project's convention),
triangles with a vertex at or behind the near plane skipped (not clipped), degenerate
triangles skipped. A triangle pixel is shaded like the splat renderer's per-pixel path:
ULR at the back-projected surface point (:func:`~opacityhull.render.deferred.shade_with`),
its visibility and normal those of the triangle's nearest vertex. The two layers meet in
a depth test: the triangle wins where it is not behind the splats by more than the
ε-z-buffer's tolerance.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Literal
from collections.abc import Sequence

import numpy as np
from numba import njit

from ..camera import Camera
from ..errors import InputError
from ..imageio import straight_from_premul
from ..model import Surfels
from .config import RenderConfig
from .views import PreparedViews, pack_camera, prepare_views

log = logging.getLogger(__name__)

__all__ = [
    "Primitives",
    "HybridMesh",
    "build_hybrid_mesh",
    "triangle_nodes",
    "project_vertices",
    "rasterize_triangles",
    "rasterize_triangles_reference",
    "render_hybrid",
    "DEFAULT_THRESHOLD_PX",
]

Primitives = Literal["splats", "hybrid"]

#: Umbrella size (px) above which a surfel is drawn as triangles: the issue's "~2 px".
DEFAULT_THRESHOLD_PX = 2.0

#: Samples per pixel side of the triangles' coverage (odd: the middle one is the centre).
SUPERSAMPLE = 3

#: Vertices nearer than this (m, along the optical axis) skip their triangles.
NEAR_M = 1e-6


@dataclass(frozen=True)
class HybridMesh:
    """The umbrella mesh of a model's surfels, ready for :func:`render_hybrid`.

    Attributes
    ----------
    vertices : (N, 3) float64 m, one per surfel: the hull point (or the refined surface
        point ``p − depth_m·n``, see :func:`build_hybrid_mesh`).
    triangles : (T, 3) int64 surfel indices.
    umbrella_radius : (N,) float64 m: farthest vertex of the surfel's incident triangles
        (0 without any).
    closed : (N,) bool: the surfel has triangles and each of its edges has exactly two.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    umbrella_radius: np.ndarray
    closed: np.ndarray


def build_hybrid_mesh(surfels: Surfels, *, max_points: int = 10000, refined: bool = False) -> HybridMesh:
    """Umbrella mesh of ``surfels`` (:mod:`.pmr`) with per-surfel umbrella radii and closure.

    Parameters
    ----------
    surfels : the model's surfels (the order :func:`render_hybrid` is given).
    max_points : surfels per octree leaf of the triangulation.
    refined : put the vertices on the photo-consistent surface when ``depth_m`` is known.
        Off by default: ``depth_m`` varies from surfel to surfel (0 to 8.5 mm on the
        simulated cup), and triangles between refined points fold; at a 4x close-up of
        the cup the pixels left transparent inside the object went from 236 (hull
        points) to 3420.
    """
    from .pmr import umbrella_triangulation

    P = surfels.positions.astype(np.float64)
    Nrm = surfels.normals.astype(np.float64)
    u = umbrella_triangulation(P, Nrm, max_points=max_points)
    return hybrid_mesh_from(P, Nrm, u.triangles, depth_m=surfels.depth_m if refined else None)


#: Rings of vertices around an open umbrella that stay splats (see :func:`hybrid_mesh_from`).
OPEN_RINGS = 2


def hybrid_mesh_from(positions, normals, triangles, *, depth_m=None, open_rings: int = OPEN_RINGS) -> HybridMesh:
    """:class:`HybridMesh` of a given triangulation over the surfels (see :func:`build_hybrid_mesh`).

    ``open_rings``: the surfels within this many edges of an open umbrella are not
    ``closed`` either (they stay splats): the triangles around a mesh hole are often
    folded. Measured at a 4x close-up of the simulated cup (23.5 k surfels, 54 % of the
    umbrellas closed), interior pixels left see-through: 3.9 % with 0 rings, 2.7 % with 1,
    1.7 % with 2 (splats only: 1.2 %)."""
    P = np.asarray(positions, np.float64)
    F = np.asarray(triangles, np.int64).reshape(-1, 3)
    N = len(P)
    if len(F) and (F.min() < 0 or F.max() >= N):
        raise InputError(f"hybrid mesh: triangle indices outside [0, {N})")
    V = P.copy()
    if depth_m is not None:
        nrm = np.asarray(normals, np.float64)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
        V = P - np.asarray(depth_m, np.float64)[:, None] * nrm
    ur = np.zeros(N)
    for a in range(3):
        for b in range(3):
            if a != b:
                np.maximum.at(ur, F[:, a], np.linalg.norm(V[F[:, b]] - V[F[:, a]], axis=1))
    closed = np.zeros(N, bool)
    if len(F):
        closed[np.unique(F)] = True
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        ue, cnt = np.unique(e, axis=0, return_counts=True)
        closed[ue[cnt != 2].ravel()] = False
        for _ in range(int(open_rings)):
            near_open = (~closed[F]).any(axis=1)
            closed[F[near_open].ravel()] = False
    return HybridMesh(vertices=V, triangles=F, umbrella_radius=ur, closed=closed)


def triangle_nodes(umbrella_radius_m, z_m, focal_px: float, *, threshold_px: float) -> np.ndarray:
    """(N,) bool: the surfels drawn as umbrella triangles, ``2 · r · f / z > threshold_px``.

    Parameters
    ----------
    umbrella_radius_m : (N,) m.  z_m : (N,) depth along the optical axis (m); z ≤ 0 is
        never triangles.  focal_px : focal length (px).  threshold_px : umbrella size (px).
    """
    r = np.asarray(umbrella_radius_m, np.float64)
    z = np.asarray(z_m, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        size = np.where(z > 0, 2.0 * r * float(focal_px) / np.where(z > 0, z, 1.0), 0.0)
    return size > float(threshold_px)


def project_vertices(vertices, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection (distortion ignored): (N, 2) float64 pixel coordinates and (N,) z (m)."""
    Pc = camera.world_to_cam(np.asarray(vertices, np.float64))
    z = Pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = camera.fx * Pc[:, 0] / z + camera.cx
        y = camera.fy * Pc[:, 1] / z + camera.cy
    return np.stack([x, y], 1), z


@njit(cache=True, nogil=True, error_model="numpy")
def _raster(xy, z, tris, near, depth, tri_id, bary):  # pragma: no cover - numba (twin below)
    H, W = depth.shape
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        za, zb, zc = z[a], z[b], z[c]
        if not (za > near and zb > near and zc > near):  # also rejects NaN
            continue
        xa, ya, xb, yb, xc, yc = xy[a, 0], xy[a, 1], xy[b, 0], xy[b, 1], xy[c, 0], xy[c, 1]
        area = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        if not (abs(area) > 1e-12) or not np.isfinite(area):
            continue
        x0 = max(0, int(np.ceil(min(xa, xb, xc))))
        x1 = min(W - 1, int(np.floor(max(xa, xb, xc))))
        y0 = max(0, int(np.ceil(min(ya, yb, yc))))
        y1 = min(H - 1, int(np.floor(max(ya, yb, yc))))
        inv = 1.0 / area
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                w0 = ((xc - xb) * (py - yb) - (yc - yb) * (px - xb)) * inv
                w1 = ((xa - xc) * (py - yc) - (ya - yc) * (px - xc)) * inv
                w2 = ((xb - xa) * (py - ya) - (yb - ya) * (px - xa)) * inv
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                q0, q1, q2 = w0 / za, w1 / zb, w2 / zc
                s = q0 + q1 + q2
                d = 1.0 / s
                if d < depth[py, px]:
                    depth[py, px] = d
                    tri_id[py, px] = t
                    bary[py, px, 0] = q0 * d
                    bary[py, px, 1] = q1 * d
                    bary[py, px, 2] = q2 * d


def _check_raster_args(xy, z, triangles, height, width):
    xy = np.ascontiguousarray(xy, np.float64).reshape(-1, 2)
    z = np.ascontiguousarray(z, np.float64).reshape(-1)
    F = np.ascontiguousarray(triangles, np.int64).reshape(-1, 3)
    if len(z) != len(xy):
        raise InputError(f"rasterize_triangles: {len(xy)} vertices but {len(z)} depths")
    if len(F) and (F.min() < 0 or F.max() >= len(xy)):
        raise InputError(f"rasterize_triangles: triangle indices outside [0, {len(xy)})")
    if int(height) < 1 or int(width) < 1:
        raise InputError(f"rasterize_triangles: image {width} x {height}, expected a positive size")
    return xy, z, F


def _buffers(height, width):
    return (
        np.full((int(height), int(width)), np.inf, np.float64),
        np.full((int(height), int(width)), -1, np.int64),
        np.zeros((int(height), int(width), 3), np.float64),
    )


def rasterize_triangles(xy, z, triangles, height: int, width: int, *, near: float = NEAR_M):
    """Z-buffer of triangles at the pixel centres.

    Parameters
    ----------
    xy : (N, 2) vertex pixel coordinates (pixel (0, 0)'s centre at 0, 0).  z : (N,) vertex
        depth along the optical axis (m).  triangles : (T, 3) vertex indices.
    height, width : image size (px).  near : a triangle with a vertex at z ≤ near is skipped.

    Returns
    -------
    depth : (H, W) float64 m, +inf where no triangle covers the pixel centre.
    tri_id : (H, W) int64 front triangle (−1: none); the first drawn wins exact ties.
    bary : (H, W, 3) float64 perspective-correct barycentrics of the front triangle.

    A pixel centre on an edge (all edge functions ≥ 0) belongs to both triangles.
    """
    xy, z, F = _check_raster_args(xy, z, triangles, height, width)
    depth, tri_id, bary = _buffers(height, width)
    _raster(xy, z, F, float(near), depth, tri_id, bary)
    return depth, tri_id, bary


def rasterize_triangles_reference(xy, z, triangles, height: int, width: int, *, near: float = NEAR_M):
    """NumPy twin of :func:`rasterize_triangles` (one triangle at a time, its pixels vectorised)."""
    xy, z, F = _check_raster_args(xy, z, triangles, height, width)
    depth, tri_id, bary = _buffers(height, width)
    H, W = depth.shape
    for t, (a, b, c) in enumerate(F):
        za, zb, zc = z[a], z[b], z[c]
        if not (za > near and zb > near and zc > near):
            continue
        (xa, ya), (xb, yb), (xc, yc) = xy[a], xy[b], xy[c]
        area = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        if not (abs(area) > 1e-12) or not np.isfinite(area):
            continue
        x0, x1 = max(0, int(np.ceil(min(xa, xb, xc)))), min(W - 1, int(np.floor(max(xa, xb, xc))))
        y0, y1 = max(0, int(np.ceil(min(ya, yb, yc)))), min(H - 1, int(np.floor(max(ya, yb, yc))))
        if x1 < x0 or y1 < y0:
            continue
        py, px = np.mgrid[y0 : y1 + 1, x0 : x1 + 1].astype(np.float64)
        inv = 1.0 / area
        w0 = ((xc - xb) * (py - yb) - (yc - yb) * (px - xb)) * inv
        w1 = ((xa - xc) * (py - yc) - (ya - yc) * (px - xc)) * inv
        w2 = ((xb - xa) * (py - ya) - (yb - ya) * (px - xa)) * inv
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        q0, q1, q2 = w0 / za, w1 / zb, w2 / zc
        with np.errstate(divide="ignore"):
            d = 1.0 / (q0 + q1 + q2)
        iy, ix = py.astype(np.int64), px.astype(np.int64)
        win = inside & (d < depth[iy, ix])
        yy, xx, dd = iy[win], ix[win], d[win]
        depth[yy, xx] = dd
        tri_id[yy, xx] = t
        bary[yy, xx] = np.stack([q0[win] * dd, q1[win] * dd, q2[win] * dd], 1)
    return depth, tri_id, bary


def _allowed(n_views: int, exclude_views: Sequence[int]) -> np.ndarray:
    allowed = np.ones(n_views, np.uint8)
    for v in exclude_views:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) < n_views:
            raise InputError(f"exclude_views: {v!r} is not a view index in [0, {n_views})")
        allowed[int(v)] = 0
    return allowed


def _opaque_interior(premul, front, coverage, winner, pv, config, shade):
    """The splat renderer's ``opaque_interior`` for the triangle pixels: deep inside the
    projection (:func:`~opacityhull.render.renderer.hull_interior`) α is raised to the
    blend of the views' mattes with their opaque part dilated by the carve's tolerance
    (:func:`~opacityhull.render.renderer.dilated_matte_views`); colour stays straight."""
    from .renderer import dilated_matte_views, hull_interior

    interior = hull_interior(coverage, winner, erode_px=int(config.interior_px)) & front
    if not interior.any():
        return premul
    dil = shade(dilated_matte_views(pv, int(config.matte_tolerance_px)))
    a = premul[..., 3]
    target = np.where(interior, np.maximum(a, np.clip(dil[..., 3], 0.0, 1.0)), a)
    up = (target > a) & (a > 1e-6)
    out = premul.copy()
    out[up] *= (target[up] / a[up])[:, None]
    return out


def _seed_areas(surfels: Surfels, areas: np.ndarray) -> None:
    """Hand ``render_image`` the full model's areas for the splat part
    (:func:`.frame.seed_surfel_areas`)."""
    from .frame import seed_surfel_areas

    seed_surfel_areas(surfels, areas)


def render_hybrid(
    surfels: Surfels,
    view_cameras: Sequence[Camera],
    view_rgba_premul: Sequence[np.ndarray] | PreparedViews,
    camera: Camera,
    *,
    mesh: HybridMesh,
    config: RenderConfig = RenderConfig(),
    threshold_px: float = DEFAULT_THRESHOLD_PX,
    exclude_views: Sequence[int] = (),
):
    """Render ``camera`` with umbrella triangles close up and splats elsewhere.

    Parameters
    ----------
    surfels, view_cameras, view_rgba_premul, config, exclude_views : as
        :func:`~opacityhull.render.renderer.render_image`.
    camera : a pinhole camera (no lens distortion).
    mesh : :func:`build_hybrid_mesh` of the same ``surfels``.
    threshold_px : umbrella size in pixels above which a surfel is drawn as triangles
        (:func:`triangle_nodes`); +inf draws splats only.

    Returns
    -------
    :class:`~opacityhull.render.renderer.RenderResult`; ``stats`` adds ``triangles`` drawn,
    ``triangle_nodes``, ``splats`` drawn and ``primitives`` (their sum), and
    ``triangle_pixels``.
    """
    from . import deferred as D
    from .renderer import RenderResult, render_image, surfel_areas

    t0 = time.perf_counter()
    if camera.has_distortion:
        raise InputError("hybrid rendering: the camera has lens distortion; expected a pinhole camera")
    if not float(threshold_px) >= 0:  # (NaN fails too; +inf: splats only)
        raise InputError(f"hybrid threshold {threshold_px!r} px: expected a number >= 0 (or inf)")
    N = len(surfels)
    if mesh.vertices.shape != (N, 3):
        raise InputError(f"hybrid mesh has {len(mesh.vertices)} vertices for {N} surfels")
    pv = (
        view_rgba_premul
        if isinstance(view_rgba_premul, PreparedViews)
        else prepare_views(view_cameras, view_rgba_premul)
    )
    H, W = camera.height, camera.width
    xy, z = project_vertices(mesh.vertices, camera)
    f = float(np.sqrt(camera.fx * camera.fy))
    tri_node = triangle_nodes(mesh.umbrella_radius, z, f, threshold_px=threshold_px) & mesh.closed
    F = mesh.triangles[tri_node[mesh.triangles].any(axis=1)] if len(mesh.triangles) else mesh.triangles
    if config.backface_cull and len(F):
        # the mesh is wound counter-clockwise seen from outside (:mod:`.pmr`); the splats'
        # cull is the same test on the surfel normal
        Vt = mesh.vertices[F]
        fn = np.cross(Vt[:, 1] - Vt[:, 0], Vt[:, 2] - Vt[:, 0])
        F = F[np.einsum("ij,ij->i", fn, camera.centre_world - Vt.mean(axis=1)) > 0]
    splat_mask = ~tri_node
    n_splats = int(splat_mask.sum())
    t_choose = time.perf_counter()

    if n_splats == N:
        res = render_image(surfels, view_cameras, pv, camera, config=config, exclude_views=exclude_views)
    elif n_splats:
        areas = surfel_areas(surfels)
        sub = Surfels(
            surfels.positions[splat_mask],
            surfels.normals[splat_mask],
            surfels.radii[splat_mask],
            surfels.visibility[splat_mask],
            surfels.n_views,
            None if surfels.depth_m is None else surfels.depth_m[splat_mask],
        )
        # the full model's areas: a k-NN estimate over the subset would inflate the splats
        # next to the triangles' region
        _seed_areas(sub, areas[splat_mask])
        res = render_image(sub, view_cameras, pv, camera, config=config, exclude_views=exclude_views)
    else:
        res = None
    t_splat = time.perf_counter()

    # the triangles' edge coverage from SS x SS samples a pixel (SS odd: the middle sample
    # is the pixel centre); depth and winner from the nearest covered sample
    ss = SUPERSAMPLE
    depth_s, tri_s, bary_s = rasterize_triangles(xy * ss + (ss - 1) / 2, z, F, H * ss, W * ss)
    blk = depth_s.reshape(H, ss, W, ss).transpose(0, 2, 1, 3).reshape(H, W, ss * ss)
    pick = np.argmin(blk, axis=2)
    depth_t = np.take_along_axis(blk, pick[..., None], axis=2)[..., 0]
    cov_tri = np.isfinite(blk).mean(axis=2).astype(np.float32)
    iy = np.arange(H)[:, None] * ss + pick // ss
    ix = np.arange(W)[None, :] * ss + pick % ss
    tri_id, bary = tri_s[iy, ix], bary_s[iy, ix]
    covered = tri_id >= 0
    if res is None:
        s_premul = np.zeros((H, W, 4), np.float32)
        s_depth = np.full((H, W), np.inf, np.float32)
        s_weight = np.zeros((H, W), np.float32)
        s_cov = np.zeros((H, W), np.float32)
    else:
        s_premul, s_depth, s_weight, s_cov = res.premul, res.depth, res.weight, res.coverage
    tol = float(config.epsilon_z) * float(np.median(surfels.radii)) if N else 0.0
    front = covered & ~(s_depth.astype(np.float64) + tol < depth_t)
    n_front = int(front.sum())
    premul = s_premul.astype(np.float32, copy=True)
    if n_front:
        verts = F[np.maximum(tri_id, 0)]  # (H, W, 3) surfel ids
        nearest = np.take_along_axis(verts, np.argmax(bary, axis=2)[..., None], axis=2)[..., 0]
        winner = np.where(front, nearest, -1).astype(np.int64)
        d_t = np.where(front, depth_t, np.inf).astype(np.float32)
        cam_row = pack_camera(camera, ignore_distortion=True)
        allowed = _allowed(pv.n_views, exclude_views)

        def shade(views):
            coverage = front.astype(np.float32)
            return D.shade_with(config, d_t, coverage, winner, cam_row, camera.centre_world, surfels, views, allowed)[0]

        premul_t = shade(pv)
        if config.opaque_interior:
            premul_t = _opaque_interior(premul_t, front, cov_tri, winner, pv, config, shade)
        # where the splats also cover the pixel the surface goes on behind the triangle's
        # edge: the larger coverage (the outline is where only the triangles draw)
        cover = np.maximum(cov_tri, np.where(np.isfinite(s_depth), s_cov, 0.0))
        if config.coverage_clip:
            a = premul_t[..., 3]
            scale = np.where(a > cover, cover / np.where(a > 0, a, 1.0), 1.0).astype(np.float32)
            premul_t = premul_t * scale[..., None]
        premul[front] = premul_t[front]
    t_tri = time.perf_counter()
    depth = np.where(front, depth_t, s_depth).astype(np.float32)
    weight = np.where(front, np.float32(1.0), s_weight).astype(np.float32)
    cov = np.where(front, cov_tri, s_cov).astype(np.float32)
    stats = dict(res.stats) if res is not None else {}
    stats.update(
        {
            "surfels": N,
            "primitives_mode": "hybrid",
            "threshold_px": float(threshold_px),
            "triangle_nodes": int(tri_node.sum()),
            "triangles": int(len(F)),
            "splats": n_splats,
            "primitives": int(len(F)) + n_splats,
            "triangle_pixels": n_front,
            "ms_hybrid": {
                "choose": 1e3 * (t_choose - t0),
                "splats": 1e3 * (t_splat - t_choose),
                "triangles": 1e3 * (t_tri - t_splat),
                "total": 1e3 * (time.perf_counter() - t0),
            },
        }
    )
    return RenderResult(straight_from_premul(premul), depth, weight, cov, camera, config, stats)
