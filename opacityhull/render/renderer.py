"""Rendering an opacity hull: ULR-blended RGBA per surfel, EWA surface splatting with an
ε-z-buffer, normalisation, and compositing.

Pipeline of :func:`render_image` (every step a numba kernel with a NumPy twin in
:mod:`opacityhull.render.reference`):

1. :func:`~opacityhull.render.kernels.splat_setup` — project each surfel, cull it when
   behind the camera, facing away, or off-screen, and build its EWA resampling kernel
   ``M = J V Jᵀ + H`` (Zwicker et al. 2001).
2. :func:`~opacityhull.render.kernels.ulr_shade` — for each surviving surfel, the k
   nearest views by angle among those in its visibility vector (minus excluded views,
   minus views it projects outside of), Unstructured-Lumigraph weights (Buehler et al.
   2001), bilinear fetch of premultiplied RGBA from the chosen views.
3. :func:`~opacityhull.render.kernels.rasterize` — ε-z-buffer: a depth pass, then the
   fragments within ε of the front-most depth accumulate ``w·RGBA``; normalised by Σw.

Only the first visible surface is rendered: the opacity light field's alpha already
holds the total coverage along each ray (the matte saw all layers at once), so the
splatted RGBA is composited directly over the background.

That is ``shading="surfel"``. With ``shading="pixel"`` (the default) step 2 is skipped
and step 3 rasterises geometry only (depth, coverage, winning surfel); each covered
pixel is then shaded at its back-projected surface point by
:mod:`opacityhull.render.deferred`, colour and alpha from the blended mattes.
"""

from __future__ import annotations

import math
import time
import weakref
from dataclasses import dataclass, field
from collections.abc import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import ALPHA_CUTOFF, straight_from_premul
from ..model import OpacityHullModel, Surfels
from . import kernels as K
from .background import composite_over, resolve_background
from .config import RenderConfig
from .views import PreparedViews, pack_camera, prepare_views, scan_order

__all__ = ["RenderConfig", "RenderResult", "UlrWeights", "render_image", "render_model", "ulr_weights", "ALPHA_MIN"]

ALPHA_MIN = ALPHA_CUTOFF  # the project's one straight-colour cut-off (imageio)
"""Below this alpha a pixel's straight colour is reported as 0 (premultiplied colour / α
is meaningless there)."""


@dataclass
class RenderResult:
    """A rendered frame.

    Attributes
    ----------
    rgba : (H, W, 4) float32, straight alpha (colour 0 where α < ALPHA_MIN).
    depth : (H, W) float32, weighted mean z (metres along the optical axis) of the blended
        fragments; +inf where nothing was drawn.
    weight : (H, W) float32, Σ of the EWA kernel weights (0 where nothing was drawn).
    coverage : (H, W) float32 in [0, 1], geometric coverage of each pixel's filter footprint
        by the splatted surface (1 everywhere drawn when ``config.edge_coverage`` is off).
    camera : the camera rendered.
    config : the options used.
    stats : counts (surfels, splats drawn, ...) and timings in ms.
    """

    rgba: np.ndarray
    depth: np.ndarray
    weight: np.ndarray
    coverage: np.ndarray
    camera: Camera
    config: RenderConfig = field(default_factory=RenderConfig)
    stats: dict = field(default_factory=dict)

    @property
    def premul(self) -> np.ndarray:
        """(H, W, 4) premultiplied RGBA."""
        out = self.rgba.copy()
        out[..., :3] *= out[..., 3:4]
        return out

    @property
    def alpha(self) -> np.ndarray:
        return self.rgba[..., 3]

    def over(self, background=None) -> np.ndarray:
        """Composite over a background: None (``config.background``, else black), a
        colour (number or RGB triple), an (H, W, 3|4) image, or an :class:`EnvMap`
        (looked up along this camera's pixel rays). Returns (H, W, 3) float32 linear."""
        bg = self.config.background if background is None else background
        return composite_over(self.rgba, resolve_background(bg, self.camera))


@dataclass(frozen=True)
class UlrWeights:
    """ULR blending of every surfel for one desired viewpoint.

    index : (N, k) int32 view indices, −1 where unused. weight : (N, k) float32, each row
    sums to 1 for drawn surfels, 0 otherwise. uv : (N, k, 2) float32 pixel position of the
    surfel in each chosen view. count : (N,) int32 candidates found (0 = not drawn).
    """

    index: np.ndarray
    weight: np.ndarray
    uv: np.ndarray
    count: np.ndarray

    def dense(self, n_views: int) -> np.ndarray:
        """(N, V) float64 weight matrix."""
        W = np.zeros((self.index.shape[0], n_views))
        rows = np.repeat(np.arange(self.index.shape[0]), self.index.shape[1])
        idx = self.index.ravel()
        ok = idx >= 0
        np.add.at(W, (rows[ok], idx[ok]), self.weight.ravel()[ok])
        return W


def _allowed(n_views: int, exclude_views: Sequence[int]) -> np.ndarray:
    allowed = np.ones(n_views, np.uint8)
    for v in exclude_views:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise InputError(f"exclude_views: {v!r} is not a view index")
        if not 0 <= int(v) < n_views:
            raise InputError(f"exclude_views: view index {v} out of range [0, {n_views})")
        allowed[int(v)] = 0
    return allowed


def _check_views(surfels: Surfels, views: PreparedViews) -> None:
    if surfels.n_views != views.n_views:
        raise InputError(f"surfels carry visibility for {surfels.n_views} views, {views.n_views} views given")


def _as_prepared(view_cameras, view_rgba_premul) -> PreparedViews:
    if isinstance(view_rgba_premul, PreparedViews):
        pv = view_rgba_premul
        if view_cameras is not None and len(view_cameras) != pv.n_views:
            raise InputError(f"{len(view_cameras)} view cameras for {pv.n_views} prepared views")
        return pv
    return prepare_views(view_cameras, view_rgba_premul)


def ulr_weights(
    surfels: Surfels,
    view_cameras: Sequence[Camera] | PreparedViews,
    desired_centre,
    *,
    k: int = 4,
    exclude_views: Sequence[int] = (),
    threads: int | None = 1,
) -> UlrWeights:
    """Unstructured-Lumigraph blending weights of every surfel (no culling, no images).

    Parameters
    ----------
    surfels : the model's surfels (visibility vectors over V views).
    view_cameras : V cameras, or :class:`PreparedViews`.
    desired_centre : (3,) centre of the desired camera, object frame, metres.
    k : ULR neighbourhood (see :class:`RenderConfig`).
    exclude_views : view indices that must not be blended.
    """
    cfg = RenderConfig(k=k, threads=threads)  # validates k
    pv = view_cameras if isinstance(view_cameras, PreparedViews) else prepare_views(view_cameras)
    _check_views(surfels, pv)
    C = np.asarray(desired_centre, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(C)):
        raise InputError(f"desired camera centre {C.tolist()} is not finite")
    allowed = _allowed(pv.n_views, exclude_views)
    o, rho = K.bounding_sphere(surfels.positions)
    order, s_lb = scan_order(pv.centres, C, o, rho)
    N = len(surfels)
    idx = np.empty((N, k), np.int32)
    w = np.empty((N, k), np.float32)
    uv = np.empty((N, k, 2), np.float32)
    count = np.empty(N, np.int32)
    drawable = np.ones(N, np.bool_)
    K.parallel_for(
        K.ulr_select,
        N,
        (
            K.UlrHead(surfels.positions, surfels.visibility, drawable, allowed, C, pv.centres, pv.cams, pv.sizes),
            order,
            s_lb,
            pv.tie_rank,
            int(k),
            idx,
            w,
            uv,
            count,
        ),
        threads=cfg.n_threads,
    )
    return UlrWeights(idx, w, uv, count)


def _pinhole_for(camera: Camera) -> tuple[Camera, np.ndarray | None]:
    """A distortion-free camera covering ``camera``'s field of view, and the remap grid
    (H, W, 2) from the distorted image to it (None when there is no distortion)."""
    if not camera.has_distortion:
        return camera, None
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    xyd = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    xy = camera.undistort_normalized(xyd)
    pu = camera.fx * xy[:, 0] + camera.cx
    pv = camera.fy * xy[:, 1] + camera.cy
    # a canvas covering every undistorted pixel, at most twice the image each way
    lo_u = max(np.floor(np.nanmin(pu)) - 1, -camera.width / 2)
    hi_u = min(np.ceil(np.nanmax(pu)) + 1, 1.5 * camera.width)
    lo_v = max(np.floor(np.nanmin(pv)) - 1, -camera.height / 2)
    hi_v = min(np.ceil(np.nanmax(pv)) + 1, 1.5 * camera.height)
    lo_u, lo_v = min(lo_u, 0.0), min(lo_v, 0.0)
    hi_u, hi_v = max(hi_u, camera.width - 1.0), max(hi_v, camera.height - 1.0)
    Kp = camera.K.copy()
    Kp[0, 2] -= lo_u
    Kp[1, 2] -= lo_v
    pin = Camera(
        K=Kp,
        width=int(hi_u - lo_u) + 1,
        height=int(hi_v - lo_v) + 1,
        world_from_cam=camera.world_from_cam,
        name=camera.name,
    )
    grid = np.stack([pu - lo_u, pv - lo_v], axis=1).reshape(camera.height, camera.width, 2).astype(np.float32)
    return pin, grid


def _remap(img: np.ndarray, grid: np.ndarray, *, nearest: bool = False, border=0.0) -> np.ndarray:
    import cv2

    return cv2.remap(
        img,
        grid[..., 0],
        grid[..., 1],
        cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border,
    )


def _remap_buffers(premul, wsum, cov, depth, grid):
    """The rendered buffers resampled through the distortion ``grid``; depth by nearest
    neighbour (blending depths across a silhouette would invent surfaces), inf outside."""
    return (
        _remap(premul, grid),
        _remap(np.ascontiguousarray(wsum), grid),
        _remap(cov, grid),
        _remap(depth, grid, nearest=True, border=float("inf")),
    )


def _stage_end(progress, done: int) -> float:
    """The ``perf_counter`` time a render stage ended, after reporting ``done`` of the 3 stages to ``progress``."""
    t = time.perf_counter()
    if progress:
        progress(done, 3)
    return t


def _stage_ms(t0: float, **ends: float) -> dict:
    """Milliseconds per stage from the ``perf_counter`` time each stage ended (in order), and the total."""
    ms, prev = {}, t0
    for stage, t in ends.items():
        ms[stage], prev = 1e3 * (t - prev), t
    ms["total"] = 1e3 * (prev - t0)
    return ms


def _view_stats(camera, config, threads, exclude_views, pv, valid, draw) -> dict:
    """The stats entries both shading modes report alike."""
    return {
        "splats_setup": int(valid.sum()),
        "splats_drawn": int(draw.size),
        "width": camera.width,
        "height": camera.height,
        "k": int(config.k),
        "threads": threads,
        "excluded_views": [int(v) for v in exclude_views],
        "nonfinite_texels": pv.nonfinite_texels,
    }


def render_image(
    surfels: Surfels,
    view_cameras: Sequence[Camera],
    view_rgba_premul: Sequence[np.ndarray] | PreparedViews,
    camera: Camera,
    *,
    config: RenderConfig = RenderConfig(),
    exclude_views: Sequence[int] = (),
    progress: Callable[[int, int], None] | None = None,
    splat_cov: np.ndarray | None = None,
) -> RenderResult:
    """Render the opacity hull from ``camera``.

    Parameters
    ----------
    surfels : positions (N, 3), normals, radii (metres) and visibility over V views.
    view_cameras : V object-frame cameras of the captured views (bit order).
    view_rgba_premul : V premultiplied RGBA images (H_v, W_v, 4), or a
        :class:`PreparedViews` built once by :func:`prepare_views` (reuse it across frames).
    camera : the desired camera. With lens distortion, the frame is rendered through a
        distortion-free camera covering the same field of view and remapped.
    config : :class:`RenderConfig` (``config.shading``: per-pixel or per-surfel ULR).
    exclude_views : views not used for blending (leave-one-out); they still count for
        nothing else, since visibility and geometry come from the model.
    progress : callable(done, total) over the 3 stages.
    splat_cov : (N, 6) or None: anisotropic radius tensors (xx, xy, xz, yy, yz, zz, m²;
        a surfel's disc is ``r²(I − n nᵀ)``) instead of the discs — the statistical nodes
        of a level-of-detail cut (:func:`opacityhull.render.spg.radius_tensors`).

    Returns
    -------
    :class:`RenderResult` with straight RGBA, depth, weight.
    """
    t0 = time.perf_counter()
    pv = _as_prepared(view_cameras, view_rgba_premul)
    if not pv.has_images:
        raise InputError("render_image needs the views' RGBA images (prepared without images)")
    _check_views(surfels, pv)
    allowed = _allowed(pv.n_views, exclude_views)
    pin, grid = _pinhole_for(camera)
    H, W = pin.height, pin.width
    cam_row = pack_camera(pin, ignore_distortion=True)
    C = pin.centre_world
    N = len(surfels)
    t_prep = time.perf_counter()

    threads = config.n_threads
    scratch = K.SCRATCH
    splat = scratch.get("splat", (N, K.SPLAT_FIELDS), np.float32)
    areas = surfel_areas(surfels)
    valid = scratch.get("valid", (N,), np.bool_)
    cov6 = None if splat_cov is None else np.ascontiguousarray(splat_cov, np.float64).reshape(N, 6)
    _setup_splats(surfels, surfels.positions, areas, cam_row, W, H, config, threads, splat, valid, cov6)
    t_setup = _stage_end(progress, 1)

    if config.shading == "pixel":
        return _render_deferred(
            surfels,
            pv,
            allowed,
            camera,
            pin,
            grid,
            cam_row,
            C,
            splat,
            valid,
            config,
            exclude_views,
            progress,
            (t0, t_prep, t_setup),
        )

    # the kernel bounds each block of surfels itself (K.ULR_BLOCK): no per-frame scan order
    order, s_lb = np.arange(pv.n_views, dtype=np.int64), np.zeros(pv.n_views)
    ok = scratch.get("ok", (N,), np.bool_)
    K.parallel_for(
        K.ulr_shade,
        N,
        (
            K.UlrHead(surfels.positions, surfels.visibility, valid, allowed, C, pv.centres, pv.cams, pv.sizes),
            pv.offsets,
            pv.texels,
            order,
            s_lb,
            pv.tie_rank,
            int(config.k),
            splat,
            K.S_RGBA,
            ok,
        ),
        threads=threads,
    )
    t_shade = _stage_end(progress, 2)

    draw = np.flatnonzero(ok).astype(np.int64)
    accum, _ = K.splat_frame(
        splat, draw, H, W, float(config.cutoff_sigma), int(config.band_rows), threads=threads, scratch=scratch
    )
    t_raster = time.perf_counter()

    rgba_img = np.empty((H, W, 4), np.float32)
    depth = np.empty((H, W), np.float32)
    wsum = np.empty((H, W), np.float32)
    cov = np.empty((H, W), np.float32)
    K.parallel_for(
        K.resolve,
        H,
        (accum, coverage_full(config), bool(config.edge_coverage), ALPHA_MIN, rgba_img, depth, wsum, cov),
        threads=threads,
        chunk=64,
    )
    if grid is not None:
        premul = rgba_img.copy()
        premul[..., :3] *= premul[..., 3:4]
        premul, wsum, cov, depth = _remap_buffers(premul, wsum, cov, depth, grid)
        rgba_img = straight_from_premul(premul)
    t_end = _stage_end(progress, 3)
    stats = {
        "surfels": N,
        **_view_stats(camera, config, threads, exclude_views, pv, valid, draw),
        "not_drawn_no_view": int(valid.sum() - draw.size),
        "shading": "surfel",
        "ms": _stage_ms(t0, prepare=t_prep, setup=t_setup, shade=t_shade, raster=t_raster, finish=t_end),
    }
    return RenderResult(rgba_img, depth, np.ascontiguousarray(wsum), cov, camera, config, stats)


def _render_deferred(
    surfels, pv, allowed, camera, pin, grid, cam_row, C, splat, valid, config, exclude_views, progress, times
) -> RenderResult:
    """The rest of :func:`render_image` with ``shading="pixel"``: geometry-only EWA pass
    (depth, coverage, winning surfel), then per-pixel ULR shading (:mod:`.deferred`).
    Every valid splat is geometry, whether or not a view sees it: visibility is decided
    per pixel from the winner's bits."""
    from . import deferred as D

    t0, t_prep, t_setup = times
    H, W = pin.height, pin.width
    threads = config.n_threads
    scratch = K.SCRATCH
    draw = np.flatnonzero(valid).astype(np.int64)
    geo, winner = D.geometry_frame(
        splat, draw, H, W, float(config.cutoff_sigma), int(config.band_rows), threads=threads, scratch=scratch
    )
    wsum = geo[..., 0].copy()
    has = wsum > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(has, geo[..., 1] / np.where(has, wsum, 1.0), np.inf).astype(np.float32)
    cov = coverage_from(geo[..., 2], wsum, config)
    if config.close_holes:
        depth, cov, winner = D.close_gbuffer(depth, wsum, cov, winner)
    refined = config.shading_surface == "refined" and surfels.depth_m is not None
    if refined:
        depth = _shading_depth(surfels, cam_row, W, H, depth, config, threads, scratch)
    t_raster = _stage_end(progress, 2)

    def shade(views: PreparedViews, align):
        # the same pixels, views and weights for the colour and for the dilated mattes
        return D.deferred_shade(
            depth,
            cov,
            winner,
            cam_row,
            C,
            surfels.visibility,
            surfels.normals,
            views,
            allowed,
            k=int(config.k),
            min_coverage=float(config.min_coverage),
            min_view_cos=float(config.min_view_cos),
            fallback=bool(config.fallback_views),
            threads=threads,
            align=align,
        )

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


_DILATED_CACHE: dict = {}

OPAQUE_MATTE = 0.99
"""A view's matte α from which it counts as opaque (:func:`dilated_matte_views`)."""


def dilated_matte_views(pv: PreparedViews, radius_px: int, *, opaque: float = OPAQUE_MATTE) -> PreparedViews:
    """``pv`` with every texel's four channels replaced by its view's matte α, or 1
    where the matte is opaque (α ≥ ``opaque``) within a disc of ``radius_px``: what a
    view's matte says once the carve's silhouette dilation is allowed for. Only the
    opaque part grows; fractional mattes (fur, glass) keep their values. Cached for the
    last ``pv`` (one model renders many frames)."""
    import mmap
    from dataclasses import replace

    import cv2

    key = (id(pv.texels), int(radius_px), float(opaque))
    hit = _DILATED_CACHE.get("last")
    if hit is not None and hit[0] == key and hit[1] is pv.texels:
        return hit[2]
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))

    src = pv.texels.base if isinstance(pv.texels.base, mmap.mmap) else None

    def rows():
        for v in range(pv.n_views):
            w, h = int(pv.sizes[v, 0]), int(pv.sizes[v, 1])
            o = int(pv.offsets[v])
            a = np.array(pv.texels[o : o + w * h, 3]).reshape(h, w)
            if src is not None:
                # every view's pages were just read: unmap them again (clean private file
                # pages — nothing writes the texels — come back from the page cache when a
                # frame uses the view), so the renderer's RSS stays flat in the views
                lo = -(-o * 16 // mmap.PAGESIZE) * mmap.PAGESIZE
                hi = (o + w * h) * 16 // mmap.PAGESIZE * mmap.PAGESIZE
                if hi > lo:
                    src.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
            b = (a >= opaque).astype(np.uint8)
            d = np.maximum(a, cv2.dilate(b, k) if radius_px > 0 else b)
            yield o, np.repeat(d.reshape(-1, 1).astype(np.float32), 4, axis=1)

    if src is not None:  # mapped views (the default): map these too
        tex = _map_texel_rows(int(pv.texels.shape[0]), rows())
    else:
        tex = np.empty_like(pv.texels)
        for o, t in rows():
            tex[o : o + t.shape[0]] = t
    out = replace(pv, texels=tex)
    _DILATED_CACHE["last"] = (key, pv.texels, out)
    return out


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


def _setup_splats(
    surfels, positions, areas, cam_row, W, H, config: RenderConfig, threads, splat, valid, cov6=None
) -> None:
    """Splat records of ``surfels`` centred at ``positions`` (the hull's, or the shading
    depth's displaced ones) for the frame ``cam_row`` (W×H), in parallel; ``cov6``:
    anisotropic radius tensors (:func:`render_image`)."""
    K.parallel_for(
        K.splat_setup,
        len(surfels),
        (
            positions,
            surfels.normals,
            surfels.radii,
            areas,
            cam_row,
            W,
            H,
            float(config.sigma_radius),
            float(config.filter),
            float(config.cutoff_sigma),
            float(config.epsilon_z),
            bool(config.backface_cull),
            K.NO_COV if cov6 is None else cov6,
            splat,
            valid,
        ),
        threads=threads,
    )


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
    from . import deferred as D

    N = len(surfels)
    shade_at = surfels.shading_positions()
    splat = scratch.get("splat_shade", (N, K.SPLAT_FIELDS), np.float32)
    valid = scratch.get("valid_shade", (N,), np.bool_)
    _setup_splats(surfels, shade_at, surfel_areas(surfels), cam_row, W, H, config, threads, splat, valid)
    draw = np.flatnonzero(valid).astype(np.int64)
    # no scratch here: the hull pass's winner may still live in the scratch buffers
    geo, winner = D.geometry_frame(
        splat, draw, H, W, float(config.cutoff_sigma), int(config.band_rows), threads=threads
    )
    wsum = geo[..., 0]
    has = wsum > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        dr = np.where(has, geo[..., 1] / np.where(has, wsum, 1.0), np.inf).astype(np.float32)
    if config.close_holes:
        cov = coverage_from(geo[..., 2], wsum, config)
        dr, _, _ = D.close_gbuffer(dr, wsum.copy(), cov, winner)
    use = np.isfinite(dr) & np.isfinite(hull_depth) & (dr >= hull_depth)
    return np.where(use, dr, hull_depth).astype(np.float32)


def coverage_full(config: RenderConfig) -> float:
    """The area-weighted kernel sum Σw·A that counts as full coverage: inside a surface
    Σw·A ≈ the Gaussian's mass within the cutoff, ``1 − exp(−c²/2)``, times
    ``coverage_threshold``."""
    return config.coverage_threshold * (1.0 - math.exp(-0.5 * config.cutoff_sigma**2))


def coverage_from(area_sum: np.ndarray, wsum: np.ndarray, config: RenderConfig) -> np.ndarray:
    """Pixel coverage in [0, 1] from the area-weighted kernel sum Σw·A: Σw·A over
    :func:`coverage_full`, clipped to [0, 1] (0 where nothing was drawn). NumPy reference
    of the coverage part of :func:`~opacityhull.render.kernels.resolve`."""
    if not config.edge_coverage:
        return (wsum > 0).astype(np.float32)
    cov = np.clip(area_sum / coverage_full(config), 0.0, 1.0).astype(np.float32)
    return np.where(wsum > 0, cov, np.float32(0.0)).astype(np.float32)


def normalise(
    acc: np.ndarray, wsum: np.ndarray, zsum: np.ndarray, coverage: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """EWA normalisation (NumPy reference of :func:`~opacityhull.render.kernels.resolve`):
    premultiplied RGBA Σw·c / Σw (times ``coverage`` when given) → straight RGBA; depth
    Σw·z / Σw (inf where Σw = 0) — the depth is not scaled by the coverage."""
    has = wsum > 0
    inv = np.where(has, 1.0 / np.where(has, wsum, 1.0), 0.0).astype(np.float32)
    depth = np.where(has, zsum * inv, np.inf).astype(np.float32)
    if coverage is not None:
        inv = inv * coverage
    premul = acc * inv[..., None]
    return straight_from_premul(premul), depth


_AREA_CACHE: dict = {}


def surfel_areas(surfels: Surfels, *, neighbours: int = 12) -> np.ndarray:
    """(N,) float32 surface area represented by each surfel (m²), for edge coverage.

    From the k nearest neighbours (SciPy KDTree): the j-th neighbour at distance r_j
    means about j surfels per π r_j², so A ≈ mean over j of π r_j² / j; the estimate is
    then averaged over each surfel's neighbourhood, which removes the banding a regular
    lattice gives single-k estimates. Cached per Surfels object (a model is opened once,
    rendered many times).
    """
    import weakref

    key = id(surfels)
    hit = _AREA_CACHE.get(key)
    if hit is not None and hit[0]() is surfels and hit[1].shape[0] == len(surfels):
        return hit[1]
    from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

    N = len(surfels)
    P = np.asarray(surfels.positions, dtype=np.float64)
    fin = np.all(np.isfinite(P), axis=1)
    areas = np.zeros(N, np.float32)
    n_ok = int(fin.sum())
    if n_ok >= 2:
        k = min(neighbours, n_ok - 1)
        tree = KDTree(P[fin])
        d, nb = tree.query(P[fin], k=k + 1)
        j = np.arange(1, k + 1)
        a = np.pi * np.mean(d[:, 1:] ** 2 / j, axis=1)
        a = np.mean(a[nb], axis=1)
        areas[fin] = a
    elif n_ok == 1:
        r = np.asarray(surfels.radii, np.float64)[fin]
        areas[fin] = np.pi * r**2
    ref = weakref.ref(surfels, lambda _r, key=key: _AREA_CACHE.pop(key, None))
    _AREA_CACHE[key] = (ref, areas)
    return areas


def _part1by2(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def spatially_sorted(surfels: Surfels, *, bits: int = 16) -> Surfels:
    """The surfels reordered along a 3-D Morton (Z-order) curve.

    Rendered images do not depend on the order (up to float rounding of the sums);
    spatially coherent order makes the texel fetches and the rasteriser's record
    reads cache-friendly. :func:`render_model` and the CLI sort once per model.
    """
    P = np.asarray(surfels.positions, dtype=np.float64)
    if len(P) == 0:
        return surfels
    fin = np.all(np.isfinite(P), axis=1)
    lo = P[fin].min(axis=0) if fin.any() else np.zeros(3)
    span = float((P[fin].max(axis=0) - lo).max()) if fin.any() else 1.0
    q = np.clip(np.nan_to_num((P - lo) / (span or 1.0)) * (2**bits - 1), 0, 2**bits - 1).astype(np.uint64)
    code = _part1by2(q[:, 0]) | (_part1by2(q[:, 1]) << np.uint64(1)) | (_part1by2(q[:, 2]) << np.uint64(2))
    return surfels.subset(np.argsort(code, kind="stable"))


def model_surfels(model: OpacityHullModel) -> Surfels:
    """The model's surfels in Morton order (computed once per opened model)."""
    cached = _SORTED_SURFELS.get(model)
    if cached is None:
        cached = spatially_sorted(model.surfels)
        _SORTED_SURFELS[model] = cached
    return cached


# weak keys: the sorted copy lives exactly as long as the opened model
_SORTED_SURFELS: weakref.WeakKeyDictionary[OpacityHullModel, Surfels] = weakref.WeakKeyDictionary()


def render_model(
    model: OpacityHullModel,
    camera: Camera,
    *,
    config: RenderConfig = RenderConfig(),
    exclude_views: Sequence[int] = (),
    views_rgba_premul: Sequence[np.ndarray] | PreparedViews | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> RenderResult:
    """Render a model folder's opacity hull from ``camera`` (loads the views unless given)."""
    cams = [v.camera for v in model.views]
    if views_rgba_premul is None:
        views_rgba_premul = prepare_model_views(model)
    return render_image(
        model_surfels(model),
        cams,
        views_rgba_premul,
        camera,
        config=config,
        exclude_views=exclude_views,
        progress=progress,
    )


def prepare_model_views(model: OpacityHullModel, *, mapped: bool = True) -> PreparedViews:
    """Pack all views of a model once (for several frames), texel for texel what
    ``prepare_views(cameras, model.load_views_premul())`` packs.

    ``mapped`` (default): the views are read one at a time (each view's file decoded,
    converted to float32 and its non-finite texels zeroed) into an unlinked temporary
    file that the texel buffer memory-maps (copy-on-write). A frame then makes resident
    only the pages of the views its surfels sample (the k nearest of each), so a
    432-view model costs what the views one frame needs cost, not 432 float32 images;
    the OS drops the pages again under memory pressure. ``mapped=False`` holds them in
    memory (the eager path; the images are equal)."""
    cams = [v.camera for v in model.views]
    if not mapped:
        return prepare_views(cams, model.load_views_premul())
    from dataclasses import replace

    pv = prepare_views(cams)  # cameras, offsets and tie ranks; no texels
    texels, bad = _mapped_texels(model, cams, pv.offsets)
    return replace(pv, texels=texels, nonfinite_texels=bad)


def _mapped_texels(model: OpacityHullModel, cams: Sequence[Camera], offsets: np.ndarray) -> tuple[np.ndarray, int]:
    """(P, 4) float32 texels of every view in a memory-mapped temporary file, written one
    view at a time, and the number of non-finite values replaced by 0."""
    from ..errors import ShapeError

    total = int(sum(c.width * c.height for c in cams))
    bad = 0

    def rows():
        nonlocal bad
        for v, c in enumerate(cams):
            a = model.load_views_premul([v])[0]
            if a.shape != (c.height, c.width, 4):
                raise ShapeError(
                    f"view {v} ({c.name or 'unnamed'}) RGBA has shape {a.shape}, expected ({c.height}, {c.width}, 4)"
                )
            t = np.ascontiguousarray(a.reshape(-1, 4), np.float32)
            del a
            fin = np.isfinite(t)
            if not fin.all():
                t = t.copy() if not t.flags.writeable else t
                bad += int((~fin).sum())
                t[~fin] = 0.0
            yield int(offsets[v]), t

    return _map_texel_rows(total, rows()), bad


def _map_texel_rows(total: int, rows) -> np.ndarray:
    """(total, 4) float32 texels in a memory-mapped temporary file, written from ``rows``
    (``(texel offset, (n, 4) float32)`` in order, one view at a time): the renderer's
    views stay out of the process's anonymous memory, whatever their number."""
    import mmap
    import tempfile

    if total == 0:
        return np.zeros((0, 4), np.float32)
    with tempfile.TemporaryFile(prefix="opacityhull-views-") as f:
        for off, t in rows:
            if f.tell() != off * 16:
                raise AssertionError("view offsets out of step with the texel file")
            f.write(np.ascontiguousarray(t, np.float32).data.cast("B"))
        f.flush()
        # copy-on-write: writable like an ordinary array (the kernels' signatures are
        # those of in-memory texels: no recompilation), never written back to the file
        mm = mmap.mmap(f.fileno(), total * 16, access=mmap.ACCESS_COPY)
    return np.ndarray((total, 4), dtype=np.float32, buffer=mm)
