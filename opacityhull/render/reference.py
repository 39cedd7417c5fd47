"""Slow, obviously-correct NumPy twins of the renderer's numba kernels.

Each function follows the papers' formulas literally, one surfel or one splat at a time,
using independent building blocks wherever possible (``Camera.project`` for projection
and distortion, an explicit tangent frame for the Jacobian, SciPy's ``map_coordinates``
for bilinear filtering, ``np.exp`` for the Gaussian). The tests compare the fast kernels
against these on small scenes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from . import kernels as K

__all__ = [
    "ulr_weights_ref",
    "bilinear_ref",
    "shade_ref",
    "splat_setup_ref",
    "rasterize_ref",
    "render_image_ref",
    "rasterize_geometry_ref",
    "deferred_shade_reference",
]


def _ulr_row(s_sorted: list[float], k: int) -> list[float]:
    """ULR weights of one surfel's candidates sorted by s = 1 − cos θ (Buehler 2001,
    with the degenerate cases of :func:`opacityhull.render.kernels._weights`)."""
    m = len(s_sorted)
    w = [0.0] * m
    coincide = [i for i in range(m) if s_sorted[i] <= K.S_ONEHOT]
    if coincide:
        for i in coincide:
            w[i] = 1.0 / len(coincide)
        return w
    if k == 1 or m == 1:
        w[0] = 1.0
        return w
    if m >= k:
        thr, n = s_sorted[k - 1], k - 1
    else:
        thr, n = 2.0, m  # fewer than k candidates: threshold at 180 degrees
    r = [max(0.0, (thr - s_sorted[i]) / s_sorted[i]) for i in range(n)]
    tot = sum(r)
    if tot > 0 and math.isfinite(tot):
        for i in range(n):
            w[i] = r[i] / tot
    else:
        w = [1.0 / m] * m
    return w


def ulr_weights_ref(
    positions,
    visible_bool,
    view_cameras: Sequence[Camera],
    desired_centre,
    *,
    k: int = 4,
    exclude_views: Sequence[int] = (),
) -> np.ndarray:
    """Dense (N, V) ULR weight matrix, one surfel at a time.

    For surfel p, the candidates are the views v with the visibility bit set, not
    excluded, and with p projecting inside the image (``Camera.project`` +
    ``Camera.in_image``). They are sorted by ``s = 1 − cos θ = |d − d_v|²/2`` (d, d_v unit
    rays from p to the desired centre and to the view's centre), ties broken by the
    view's centre (x, y, z) and then its index; the first k enter the ULR formula.
    """
    P = np.asarray(positions, dtype=np.float64)
    vis = np.asarray(visible_bool, dtype=bool)
    N, V = vis.shape
    C = np.asarray(desired_centre, dtype=np.float64)
    centres = np.stack([c.centre_world for c in view_cameras])
    inside = np.zeros((N, V), bool)
    for v, cam in enumerate(view_cameras):
        uv, z = cam.project(P)
        inside[:, v] = (z > 0) & cam.in_image(uv)
    excluded = set(int(v) for v in exclude_views)
    W = np.zeros((N, V))
    for i in range(N):
        d = C - P[i]
        nd = np.linalg.norm(d)
        if not nd > 0:
            continue
        d = d / nd
        cands = []
        for v in range(V):
            if not vis[i, v] or v in excluded or not inside[i, v]:
                continue
            e = centres[v] - P[i]
            ne = np.linalg.norm(e)
            if not ne > 0:
                continue
            s = 0.5 * float(np.sum((e / ne - d) ** 2))
            cands.append((s, tuple(centres[v]), v))
        if not cands:
            continue
        cands.sort()
        chosen = cands[:k]
        w = _ulr_row([c[0] for c in chosen], k)
        for (_, _, v), wi in zip(chosen, w, strict=True):
            W[i, v] = wi
    return W


def bilinear_ref(image, uv) -> np.ndarray:
    """Bilinear samples (N, C) of an (H, W, C) image at pixel positions uv (N, 2), pixel
    centres at integers, edges repeated (SciPy ``map_coordinates``, order 1, 'nearest')."""
    from scipy.ndimage import map_coordinates

    img = np.asarray(image, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    coords = [uv[:, 1], uv[:, 0]]
    return np.stack(
        [map_coordinates(img[:, :, c], coords, order=1, mode="nearest") for c in range(img.shape[2])], axis=1
    )


def shade_ref(
    positions, weights_dense, view_cameras: Sequence[Camera], view_rgba_premul: Sequence[np.ndarray]
) -> np.ndarray:
    """(N, 4) premultiplied RGBA: Σ_v w_v · bilinear(view v, project_v(p))."""
    P = np.asarray(positions, dtype=np.float64)
    out = np.zeros((P.shape[0], 4))
    for v, (cam, img) in enumerate(zip(view_cameras, view_rgba_premul, strict=True)):
        rows = np.flatnonzero(weights_dense[:, v] > 0)
        if rows.size == 0:
            continue
        uv, _ = cam.project(P[rows])
        out[rows] += weights_dense[rows, v, None] * bilinear_ref(
            np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0), uv
        )
    return out


def _tangent_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    tu = np.cross(n, a)
    tu /= np.linalg.norm(tu)
    return tu, np.cross(n, tu)


def splat_setup_ref(
    positions,
    normals,
    radii,
    areas,
    camera: Camera,
    *,
    sigma_radius: float,
    filter_var: float,
    cutoff: float,
    eps_z: float,
    cull_backfaces: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """EWA resampling kernels (Zwicker 2001), one surfel at a time, with an explicit
    tangent frame: ``J = ∂(pinhole projection)/∂(u, v)`` at the surfel,
    ``M = J V Jᵀ + H``, ``V = (sigma_radius·r)² I``, ``H = filter_var·I`` (+ the numerical
    floor ``M_FLOOR``), weight ``|det J| / (2π √det M)``; footprint radius = cutoff ×
    the largest eigenvalue's square root of M, back-projected to the surfel's depth; depth
    clamp ``ZDEV_FOOTPRINTS`` footprints, ε = ``eps_z`` footprints.

    Returns (valid (N,), records (N, SPLAT_FIELDS) float32) in the kernel's layout
    (RGBA columns zero).
    """
    P = np.asarray(positions, dtype=np.float64)
    Nn = np.asarray(normals, dtype=np.float64)
    R = np.asarray(radii, dtype=np.float64)
    T = camera.cam_from_world
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height
    valid = np.zeros(len(P), bool)
    rec = np.zeros((len(P), K.SPLAT_FIELDS), np.float32)
    for i in range(len(P)):
        r = R[i]
        if not (r > 0 and np.isfinite(r) and np.all(np.isfinite(P[i]))):
            continue
        pc = T[:3, :3] @ P[i] + T[:3, 3]
        X, Y, Z = pc
        if not Z > 1e-9:
            continue
        nn = np.linalg.norm(Nn[i])
        n = T[:3, :3] @ (Nn[i] / nn) if nn > 1e-12 and np.isfinite(nn) else -pc / np.linalg.norm(pc)
        ndp = float(n @ pc)
        if cull_backfaces and ndp >= 0:
            continue
        # derivative of (fx X/Z + cx, fy Y/Z + cy) with respect to the camera-frame point
        dproj = np.array([[fx / Z, 0.0, -fx * X / Z**2], [0.0, fy / Z, -fy * Y / Z**2]])
        tu, tv = _tangent_frame(n)
        J = dproj @ np.stack([tu, tv], axis=1)  # 2x2, px per metre of tangent plane
        Vk = (sigma_radius * r) ** 2 * np.eye(2)
        M = J @ Vk @ J.T + (filter_var + K.M_FLOOR) * np.eye(2)
        detM = np.linalg.det(M)
        if not (detM > 0 and np.isfinite(detM)):
            continue
        Minv = np.linalg.inv(M)
        x0, y0 = fx * X / Z + cx, fy * Y / Z + cy
        hx, hy = cutoff * math.sqrt(M[0, 0]), cutoff * math.sqrt(M[1, 1])
        lo_x, hi_x = max(x0 - hx, 0.0), min(x0 + hx, W - 1.0)
        lo_y, hi_y = max(y0 - hy, 0.0), min(y0 + hy, H - 1.0)
        if not (lo_x <= hi_x and lo_y <= hi_y):
            continue
        bx0, bx1, by0, by1 = math.ceil(lo_x), math.floor(hi_x), math.ceil(lo_y), math.floor(hi_y)
        if bx0 > bx1 or by0 > by1:
            continue
        # depth on the tangent plane n·(z·ray(x) − pc) = 0, linearised at the centre
        if abs(ndp) > 1e-12 * Z:
            dzx, dzy = -Z * Z * n[0] / (fx * ndp), -Z * Z * n[1] / (fy * ndp)
        else:
            dzx = dzy = 0.0
        foot = cutoff * math.sqrt(np.linalg.eigvalsh(M).max()) * Z / ((fx + fy) / 2)
        rec[i, : K.S_RGBA] = [
            x0,
            y0,
            Z,
            Minv[0, 0],
            Minv[0, 1],
            Minv[1, 1],
            abs(np.linalg.det(J)) / (2 * math.pi * math.sqrt(detM)),
            dzx,
            dzy,
            K.ZDEV_FOOTPRINTS * foot,
            eps_z * foot,
            bx0,
            bx1,
            by0,
            by1,
        ]
        rec[i, K.S_AREA] = areas[i]
        valid[i] = True
    return valid, rec


def rasterize_ref(records, draw, height: int, width: int, cutoff: float) -> tuple[np.ndarray, np.ndarray]:
    """ε-z-buffered EWA splatting, one splat at a time (Zwicker 2001).

    Pass 1 over all splats: ``zlim(x) = min (z_i(x) + ε_i)`` over fragments with
    ``dᵀM⁻¹d ≤ cutoff²``. Pass 2: fragments with ``z ≤ zlim`` add ``W exp(−q/2)`` times
    their RGBA, weight, weight × depth and weight × area. Returns (accum (H, W, 7)
    float32, zlim).
    """
    rec = np.asarray(records, dtype=np.float32)
    zlim = np.full((height, width), np.inf, np.float32)
    accum = np.zeros((height, width, 7), np.float32)
    c2 = float(cutoff) ** 2

    def fragments(sp):
        x0, x1, y0, y1 = (int(sp[c]) for c in (K.S_BX0, K.S_BX1, K.S_BY0, K.S_BY1))
        ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
        dx = xs - float(sp[K.S_X])
        dy = ys - float(sp[K.S_Y])
        q = float(sp[K.S_A]) * dx * dx + 2 * float(sp[K.S_B]) * dx * dy + float(sp[K.S_C]) * dy * dy
        z0, dev = float(sp[K.S_Z]), float(sp[K.S_ZDEV])
        z = np.clip(z0 + float(sp[K.S_DZX]) * dx + float(sp[K.S_DZY]) * dy, z0 - dev, z0 + dev)
        inside = q <= c2
        return ys[inside], xs[inside], q[inside], z[inside]

    for i in draw:
        ys, xs, q, z = fragments(rec[i])
        zl = (z + float(rec[i, K.S_ZEPS])).astype(np.float32)
        np.minimum.at(zlim, (ys, xs), zl)
    for i in draw:
        ys, xs, q, z = fragments(rec[i])
        z32 = z.astype(np.float32)
        keep = z32 <= zlim[ys, xs]
        ys, xs, q, z32 = ys[keep], xs[keep], q[keep], z32[keep]
        w = rec[i, K.S_W] * np.exp(-0.5 * q).astype(np.float32)
        for c in range(4):
            accum[ys, xs, c] += w * rec[i, K.S_RGBA + c]
        accum[ys, xs, 4] += w
        accum[ys, xs, 5] += w * z32
        accum[ys, xs, 6] += w * rec[i, K.S_AREA]
    return accum, zlim


def render_image_ref(
    surfels,
    view_cameras,
    view_rgba_premul,
    camera: Camera,
    *,
    config=None,
    exclude_views: Sequence[int] = (),
    return_margin: bool = False,
):
    """The whole of :func:`opacityhull.render.render_image` from the references
    (distortion-free desired cameras only). Returns (rgba straight, depth, weight), and
    with ``return_margin`` (pixel shading) also the (H, W) bool map of pixels whose
    winning surfel is clear of the runner-up by more than the kernels' exp-table error."""
    from ..imageio import straight_from_premul
    from .config import RenderConfig
    from .frame import coverage_from, normalise, surfel_areas

    cfg = config or RenderConfig(align="none")
    if camera.has_distortion:
        raise NotImplementedError("render_image_ref: distortion-free desired cameras only")
    if cfg.shading == "pixel" and cfg.align != "none":
        raise NotImplementedError("render_image_ref: no flow alignment (pass RenderConfig(align='none'))")
    valid, rec = splat_setup_ref(
        surfels.positions,
        surfels.normals,
        surfels.radii,
        surfel_areas(surfels),
        camera,
        sigma_radius=cfg.sigma_radius,
        filter_var=cfg.filter,
        cutoff=cfg.cutoff_sigma,
        eps_z=cfg.epsilon_z,
        cull_backfaces=cfg.backface_cull,
    )
    if cfg.shading == "pixel":
        from .deferred import close_gbuffer

        geo, winner, best, second = rasterize_geometry_ref(
            rec, np.flatnonzero(valid), camera.height, camera.width, cfg.cutoff_sigma
        )
        wsum = geo[..., 0]
        has = wsum > 0
        depth = np.where(has, geo[..., 1] / np.where(has, wsum, 1.0), np.inf).astype(np.float32)
        cov = coverage_from(geo[..., 2], wsum, cfg)
        if cfg.close_holes:
            depth, cov, winner = close_gbuffer(depth, wsum, cov, winner)
        from functools import partial

        # the same pixels, views and weights for the colour and for the dilated mattes
        shade = partial(
            deferred_shade_reference,
            depth,
            cov,
            winner,
            camera,
            surfels.visible_bool(),
            view_cameras,
            normals=surfels.normals,
            k=cfg.k,
            exclude_views=exclude_views,
            min_coverage=cfg.min_coverage,
            min_view_cos=cfg.min_view_cos,
        )
        premul = shade(view_rgba_premul)
        clip_to = cov
        if cfg.opaque_interior:
            premul, clip_to = _opaque_interior_ref(premul, cov, winner, view_rgba_premul, cfg, shade)
        if cfg.coverage_clip:
            a = premul[..., 3]
            clipped = np.minimum(a, clip_to)
            premul = premul * np.where(a > clipped, clipped / np.where(a > 0, a, 1.0), 1.0)[..., None]
        out = (straight_from_premul(premul.astype(np.float32)), depth, wsum)
        return out + (best > second * (1 + 1e-4),) if return_margin else out
    Wd = ulr_weights_ref(
        surfels.positions,
        surfels.visible_bool(),
        view_cameras,
        camera.centre_world,
        k=cfg.k,
        exclude_views=exclude_views,
    )
    rgba = shade_ref(surfels.positions, Wd, view_cameras, view_rgba_premul)
    drawn = valid & (Wd.sum(axis=1) > 0)
    rec[:, K.S_RGBA : K.S_RGBA + 4] = rgba
    accum, _ = rasterize_ref(rec, np.flatnonzero(drawn), camera.height, camera.width, cfg.cutoff_sigma)
    cov = coverage_from(accum[..., 6], accum[..., 4], cfg)
    out, depth = normalise(accum[..., :4], accum[..., 4], accum[..., 5], cov)
    return out, depth, accum[..., 4]


def rasterize_geometry_ref(records, draw, height: int, width: int, cutoff: float):
    """Geometry-only ε-z-buffered splatting (twin of
    :func:`opacityhull.render.deferred.rasterize_geometry`): Σw, Σw·z, Σw·area from
    :func:`rasterize_ref`, and per pixel the surfel with the largest weight ``W exp(−q/2)``
    among the front-surface fragments (first in ``draw`` order on ties).

    Returns (geo (H, W, 3) float32, winner (H, W) int64 (−1: none), best (H, W) and
    second-best (H, W) weights, so callers can tell near-ties).
    """
    accum, zlim = rasterize_ref(records, draw, height, width, cutoff)
    rec = np.asarray(records, dtype=np.float32)
    c2 = float(cutoff) ** 2
    winner = np.full((height, width), -1, np.int64)
    best = np.zeros((height, width))
    second = np.zeros((height, width))
    for i in draw:
        sp = rec[i]
        for y in range(int(sp[K.S_BY0]), int(sp[K.S_BY1]) + 1):
            for x in range(int(sp[K.S_BX0]), int(sp[K.S_BX1]) + 1):
                dx, dy = x - float(sp[K.S_X]), y - float(sp[K.S_Y])
                q = float(sp[K.S_A]) * dx * dx + 2 * float(sp[K.S_B]) * dx * dy + float(sp[K.S_C]) * dy * dy
                if q > c2:
                    continue
                z0, dev = float(sp[K.S_Z]), float(sp[K.S_ZDEV])
                z = np.float32(min(max(z0 + float(sp[K.S_DZX]) * dx + float(sp[K.S_DZY]) * dy, z0 - dev), z0 + dev))
                if z > zlim[y, x]:
                    continue
                w = float(sp[K.S_W]) * math.exp(-0.5 * q)
                if w > best[y, x]:
                    second[y, x] = best[y, x]
                    best[y, x] = w
                    winner[y, x] = i
                elif w > second[y, x]:
                    second[y, x] = w
    return accum[..., 4:7].copy(), winner, best, second


def deferred_shade_reference(
    depth,
    coverage,
    winner,
    camera: Camera,
    visible_bool,
    view_cameras: Sequence[Camera],
    view_rgba_premul: Sequence[np.ndarray],
    *,
    normals=None,
    k: int = 4,
    exclude_views: Sequence[int] = (),
    min_coverage: float = 0.5,
    min_view_cos: float = -1.0,
    fallback: bool = False,
) -> np.ndarray:
    """Per-pixel ULR shading, one pixel at a time from independent parts (twin of
    :func:`opacityhull.render.deferred.deferred_shade`).

    A pixel is shaded when its coverage ≥ ``min_coverage``, its winner ≥ 0 and its depth
    is finite and > 0: X = centre + t·d on the pixel ray d (``Camera.pixel_rays``) with
    t = depth / (d · forward), so that X's camera-frame z is the depth; the winner's
    visibility row chooses the candidate views (:func:`ulr_weights_ref`), minus those
    with ``cos∠(n, C_v − X) ≤ min_view_cos`` (n the winner's normal) unless that leaves
    no allowed view, and the premultiplied RGBA is :func:`shade_ref`. With ``fallback``, a winner
    no allowed view sees first takes every allowed view with ``n · (C_v − X) > 0`` (all
    allowed views when n is unusable). Others are 0.

    Parameters: depth, coverage (H, W); winner (H, W) int; camera the (pinhole) frame;
    visible_bool (N, V); normals (N, 3) (needed when ``min_view_cos > −1``). Returns
    (H, W, 4) float64 premultiplied RGBA.
    """
    depth = np.asarray(depth, np.float64)
    H, W = depth.shape
    win = np.asarray(winner)
    out = np.zeros((H, W, 4))
    with np.errstate(invalid="ignore"):
        shade = (np.asarray(coverage) >= np.float32(min_coverage)) & (win >= 0) & np.isfinite(depth) & (depth > 0)
    ys, xs = np.nonzero(shade)
    if ys.size == 0:
        return out
    origin, d = camera.pixel_rays(np.stack([xs, ys], axis=1).astype(np.float64))
    t = depth[ys, xs] / (d @ camera.forward_world)
    X = origin + d * t[:, None]
    vis = np.asarray(visible_bool, bool)[win[ys, xs]].copy()
    centres = np.stack([c.centre_world for c in view_cameras])
    if normals is not None:
        n = np.asarray(normals, np.float64)[win[ys, xs]]
        nn = np.linalg.norm(n, axis=1)
        usable = (nn > 1e-12) & np.isfinite(nn)
    allowed = np.ones(len(view_cameras), bool)
    allowed[list(int(v) for v in exclude_views)] = False
    if fallback:
        for j in np.flatnonzero(~(vis & allowed).any(axis=1)):
            front = ((centres - X[j]) @ n[j] > 0) if usable[j] else np.ones(len(view_cameras), bool)
            vis[j] |= allowed & front
    if min_view_cos > -1.0:
        for j in np.flatnonzero(usable):
            e = centres - X[j]
            cos = (e @ n[j]) / (np.linalg.norm(e, axis=1) * nn[j])
            keep = vis[j] & (cos > min_view_cos)
            if (keep & allowed).any():
                vis[j] = keep
    Wd = ulr_weights_ref(X, vis, view_cameras, camera.centre_world, k=k, exclude_views=exclude_views)
    out[ys, xs] = shade_ref(X, Wd, view_cameras, view_rgba_premul)
    return out


def _opaque_interior_ref(premul, cov, winner, view_rgba_premul, cfg, shade):
    """NumPy twin of the renderer's opaque interior (``RenderConfig.opaque_interior``):
    returns the raised premultiplied image and the coverage the clip then uses (1 inside
    the hull's interior). ``shade(views)`` is the deferred shading of the frame."""
    from scipy import ndimage

    from .deferred import hull_interior
    from .frame import ALPHA_MIN
    from .view_io import OPAQUE_MATTE

    interior = hull_interior(cov, winner, erode_px=int(cfg.interior_px))
    r = int(cfg.matte_tolerance_px)
    import cv2

    # the renderer's digital disc (its shape only; the dilation here is SciPy's)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)).astype(bool)
    dil_views = []
    for img in view_rgba_premul:
        a = np.asarray(img, np.float32)[..., 3]
        grown = ndimage.binary_dilation(a >= OPAQUE_MATTE, structure=disc) if r > 0 else a >= OPAQUE_MATTE
        d = np.maximum(a, grown.astype(np.float32))
        dil_views.append(np.repeat(d[..., None], 4, axis=2))
    dil = shade(dil_views)
    a = premul[..., 3]
    target = np.where(interior, np.maximum(a, np.clip(dil[..., 3], 0.0, 1.0)), a)
    out = np.array(premul, np.float32)
    has = a > ALPHA_MIN
    fix = (target > a) & has
    out[fix] *= (target[fix] / a[fix])[:, None]
    none = (target > a) & ~has
    if none.any():
        pm = np.asarray(premul, np.float64)
        box = np.stack([ndimage.uniform_filter(pm[..., c], size=5, mode="constant") * 25.0 for c in range(4)], -1)
        n = box[..., 3]
        ok = none & (n > ALPHA_MIN)
        out[ok, :3] = (box[ok, :3] / n[ok, None] * target[ok, None]).astype(np.float32)
        out[ok, 3] = target[ok]
    return out, np.where(interior, np.float32(1.0), cov).astype(np.float32)
