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
:mod:`opacityhull.render.deferred`, colour and alpha from the blended mattes; that
module's :func:`~opacityhull.render.deferred.render_deferred` is the per-pixel driver.

What both drivers share (the frame, splat setup, coverage, surfel areas, the distorted
camera's canvas) is :mod:`.frame`; the views' texels as read from a model folder
(memory-mapped) are :mod:`.view_io`; Morton order is :mod:`.morton`. Their public names
are re-exported here.
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass
from collections.abc import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..model import OpacityHullModel, Surfels
from . import kernels as K
from .config import RenderConfig
from .frame import (
    ALPHA_MIN,
    RenderResult,
    _pinhole_for,
    _remap_buffers,
    _stage_end,
    _stage_ms,
    _view_stats,
    coverage_full,
    setup_splats,
    surfel_areas,
)
from .morton import morton_codes
from .view_io import prepare_model_views
from .views import PreparedViews, pack_camera, prepare_views, scan_order

# moved to .frame, .deferred and .view_io; still importable from here
from ..imageio import straight_from_premul as straight_from_premul
from .deferred import hull_interior as hull_interior
from .frame import coverage_from as coverage_from
from .frame import normalise as normalise
from .view_io import OPAQUE_MATTE as OPAQUE_MATTE
from .view_io import dilated_matte_views as dilated_matte_views

__all__ = ["RenderConfig", "RenderResult", "UlrWeights", "render_image", "render_model", "ulr_weights", "ALPHA_MIN"]


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
    setup_splats(surfels, surfels.positions, areas, cam_row, W, H, config, threads, splat, valid, cov6)
    t_setup = _stage_end(progress, 1)

    if config.shading == "pixel":
        from .deferred import render_deferred

        return render_deferred(
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


def spatially_sorted(surfels: Surfels, *, bits: int = 16) -> Surfels:
    """The surfels reordered along a 3-D Morton (Z-order) curve.

    Rendered images do not depend on the order (up to float rounding of the sums);
    spatially coherent order makes the texel fetches and the rasteriser's record
    reads cache-friendly. :func:`render_model` and the CLI sort once per model.
    """
    if len(surfels) == 0:
        return surfels
    code = morton_codes(surfels.positions, bits=bits)
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
