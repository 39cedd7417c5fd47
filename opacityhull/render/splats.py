"""Rendering the fitted splats of ``build --optimize fast|full`` (``MODEL/optimized/``).

The one driver every consumer of the fitted model goes through: ``render`` (frames,
orbits), ``eval test`` and the viewer's CPU reference. The pixels come from the fitting
library's own forward pass (:func:`opacityhull.optimize.fit.render_params`: SH colour
for the camera's direction, the differentiable EWA rasterizer's forward pass, display
colour decoded to linear), so what is rendered is exactly what was fitted. The splats
are rasterized through an undistorted pinhole; :func:`distorted` resamples the picture
onto a distorted camera's pixel grid, where its photograph lives.

Which renderer draws a model is one rule for every command (``--renderer``):
``fitted`` the splats, ``ulr`` the hull's surfels blended from the captured views
(:func:`~opacityhull.render.renderer.render_image`), ``auto`` the splats when the model
has them and they were fitted from this very build (:func:`fitted_state`), else ULR.

This module is ``render``'s one arrow into ``optimize`` (``tests/test_imports.py``
``EXCEPTIONS``): the fitted splats are part of the model format, their rasterizer lives
with the fitting.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Literal
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError

__all__ = [
    "Renderer",
    "RENDERERS",
    "FittedState",
    "fitted_state",
    "resolve_renderer",
    "distorted",
    "FittedSplats",
    "ulr_surfel_colours",
]

Renderer = Literal["auto", "fitted", "ulr"]
RENDERERS: tuple[Renderer, ...] = ("auto", "fitted", "ulr")

log = logging.getLogger(__name__)
FittedState = Literal["fitted", "stale", "none"]


def fitted_state(model_root: Path) -> FittedState:
    """Whether the model has fitted splats its renderers can use: ``"fitted"`` (the
    ``optimize`` step's ``MODEL/optimized/splats.ply``, fitted from this very model:
    ``fit.json``'s fingerprint matches ``model.toml`` + ``surfels.ply``), ``"stale"``
    (fitted from another build of the folder) or ``"none"``."""
    from ..optimize.data import model_fingerprint
    from ..optimize.fit import OPTIMIZED_DIR, SPLATS_PLY

    d = Path(model_root) / OPTIMIZED_DIR
    if not (d / SPLATS_PLY).is_file() or not (d / "fit.json").is_file():
        return "none"
    try:
        fp = json.loads((d / "fit.json").read_text()).get("model")
    except (OSError, ValueError, AttributeError):
        return "stale"
    return "fitted" if fp == model_fingerprint(Path(model_root)) else "stale"


def resolve_renderer(
    model_root: Path,
    renderer: str,
    *,
    flag: str = "--renderer",
    ulr_only: Sequence[tuple[str, bool]] = (),
) -> Literal["fitted", "ulr"]:
    """The renderer ``renderer`` (auto | fitted | ulr) means for the model at
    ``model_root``; an :class:`InputError` naming ``flag`` for an unknown value, for
    ``fitted`` on a model without (current) fitted splats, and for any of ``ulr_only``
    — (flag, given) pairs of options only the ULR renderer has — given while the splats
    draw."""
    if renderer not in RENDERERS:
        raise InputError(f"{flag} {renderer!r}: expected one of {', '.join(RENDERERS)}")
    state = fitted_state(Path(model_root))
    if renderer == "fitted" and state != "fitted":
        why = "were fitted from an earlier build of this folder" if state == "stale" else "are missing"
        raise InputError(
            f"{flag} fitted: {model_root}'s fitted splats (optimized/splats.ply) {why}; "
            "build with --optimize fast or full"
        )
    if renderer == "auto" and state == "stale":
        log.warning(
            "%s: its fitted splats (optimized/) were fitted from an earlier build of this folder; drawing the hull "
            "(build again with --optimize to fit this one)",
            model_root,
        )
    used: Literal["fitted", "ulr"] = (
        "fitted" if renderer == "fitted" or (renderer == "auto" and state == "fitted") else "ulr"
    )
    if used == "fitted":
        given = [f for f, on in ulr_only if on]
        if given:
            how = "" if renderer == "fitted" else f" ({flag} auto picks them: the model was built with --optimize)"
            raise InputError(
                f"{', '.join(given)}: an option of the ULR renderer, but the fitted splats draw{how}; "
                f"give {flag} ulr to render the hull's surfels"
            )
    return used


def distorted(rgba: np.ndarray, cam: Camera) -> np.ndarray:
    """A pinhole rendering (the fitted splats are rasterized without distortion) resampled
    onto ``cam``'s distorted pixel grid, where the photograph lives (unchanged for a
    camera without distortion)."""
    if not np.any(np.asarray(cam.dist) != 0):
        return rgba
    import cv2

    H, W = rgba.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    K = np.asarray(cam.K, np.float64)
    und = cv2.undistortPoints(pts, K, np.asarray(cam.dist, np.float64), P=K).reshape(H, W, 2)
    return cv2.remap(rgba, und[..., 0], und[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


class FittedSplats:
    """The fitted splats of a model, read once (:func:`opacityhull.optimize.fit.load_fitted`),
    rendered for any camera.

    Attributes
    ----------
    params : the splat parameters (``means`` (N, 3) m, ``quats`` (N, 4) wxyz,
        ``log_scales`` (N, 2) log m, ``opacity_logits`` (N,), ``sh`` (N, B, 3)).
    sh_degree : the SH degree stored (B = (degree+1)²).
    """

    def __init__(self, params: dict[str, np.ndarray]):
        self.params = params
        self.sh_degree = int(round(np.sqrt(params["sh"].shape[1]))) - 1
        self._nn: np.ndarray | None = None  # nearest hull surfel per splat (nearest_surfels)
        self._nn_key: int | None = None

    @classmethod
    def load(cls, model_root: Path) -> FittedSplats:
        from ..optimize.fit import load_fitted

        return cls(load_fitted(Path(model_root)))

    def __len__(self) -> int:
        return len(self.params["means"])

    def rgba(self, camera: Camera) -> np.ndarray:
        """(H, W, 4) float32 straight linear RGBA seen by ``camera`` (distortion
        included): the image type of ``render_image``'s ``rgba``."""
        from ..optimize.fit import render_params

        return distorted(render_params(self.params, camera), camera)

    def render(self, camera: Camera):
        """The splats seen by ``camera`` as a :class:`~opacityhull.render.renderer.RenderResult`
        (so ``render``'s writers, ``over`` and backgrounds apply unchanged): ``rgba`` as
        :meth:`rgba`; ``weight`` and ``coverage`` the composited opacity; ``depth`` +inf
        where nothing was drawn and NaN elsewhere (the fitted forward pass's depth is not
        passed out; no consumer of ``render`` reads it)."""
        from .renderer import RenderResult

        t = time.perf_counter()
        rgba = self.rgba(camera)
        a = rgba[..., 3]
        drawn = a > 0
        return RenderResult(
            rgba=rgba,
            depth=np.where(drawn, np.float32(np.nan), np.float32(np.inf)).astype(np.float32),
            weight=a.copy(),
            coverage=np.clip(a, 0.0, 1.0).astype(np.float32),
            camera=camera,
            stats={"splats": len(self), "ms": {"total": 1e3 * (time.perf_counter() - t)}},
        )

    def nearest_surfels(self, surfels) -> np.ndarray:
        """(N,) index of the hull surfel nearest to each fitted splat's centre (computed
        once per ``surfels``): what a splat takes its reflectance from."""
        key = id(surfels)
        if self._nn is None or self._nn_key != key:
            from scipy.spatial import KDTree

            _, nn = KDTree(np.asarray(surfels.positions, np.float64)).query(np.asarray(self.params["means"]), 1)
            self._nn, self._nn_key = np.asarray(nn, np.int64), key
        return self._nn

    def render_colours(self, camera: Camera, colours: np.ndarray, *, drawn: np.ndarray | None = None):
        """The splats' geometry and opacity with given linear ``colours`` (N, 3) (relit
        colours, say) seen by ``camera``: a :class:`RenderResult` whose ``rgba`` is the
        straight linear composite (no SH, no display decoding; distortion included).
        ``drawn`` (N,) bool: splats left out (an opacity of zero) where False."""
        from ..optimize.raster import RasterCamera, RasterConfig, SplatParams, rasterize
        from .renderer import RenderResult

        t = time.perf_counter()
        p = self.params
        logits = np.asarray(p["opacity_logits"], np.float32)
        if drawn is not None:
            logits = np.where(drawn, logits, np.float32(-1e4)).astype(np.float32)
        sp = SplatParams(
            means=p["means"],
            quats=p["quats"],
            log_scales=p["log_scales"],
            opacity_logits=logits,
            colors=np.ascontiguousarray(colours, np.float32),
        )
        rc = RasterCamera(
            K=np.asarray(camera.K, np.float64),
            cam_from_world=np.asarray(camera.cam_from_world, np.float64)[:3, :4],
            width=int(camera.width),
            height=int(camera.height),
        )
        out = rasterize(sp, rc, config=RasterConfig())
        a = np.clip(out.alpha, 0.0, 1.0).astype(np.float32)
        straight = np.where(a[..., None] > 1e-6, out.image / np.maximum(a[..., None], 1e-6), 0.0)
        rgba = distorted(np.concatenate([straight, a[..., None]], axis=2).astype(np.float32), camera)
        a = rgba[..., 3]
        return RenderResult(
            rgba=rgba,
            depth=np.where(a > 0, np.float32(np.nan), np.float32(np.inf)).astype(np.float32),
            weight=a.copy(),
            coverage=np.clip(a, 0.0, 1.0).astype(np.float32),
            camera=camera,
            stats={"splats": len(self), "ms": {"total": 1e3 * (time.perf_counter() - t)}},
        )

    def render_relit(self, camera: Camera, surfels, view_cameras, images, *, k: int = 4, exclude_views=()):
        """The splats seen by ``camera``, each with the Unstructured-Lumigraph blend of
        ``images`` (e.g. relit views, premultiplied) sampled where the splat itself
        projects (:func:`ulr_surfel_colours`), over the views that see its nearest hull
        surfel (the splats carry no visibility of their own): a relit picture of the fitted
        geometry. Splats whose nearest surfel no view sees are left out."""
        from ..model import Surfels

        nn = self.nearest_surfels(surfels)
        at = Surfels(
            positions=self.params["means"],
            normals=np.asarray(surfels.normals)[nn],
            radii=np.exp(np.asarray(self.params["log_scales"], np.float32).max(axis=1)),
            visibility=np.asarray(surfels.visibility)[nn],
            n_views=surfels.n_views,
        )
        rgba, count = ulr_surfel_colours(
            at, view_cameras, images, camera.centre_world, k=k, exclude_views=exclude_views
        )
        a = rgba[:, 3:4]
        straight = np.where(a > 1e-6, rgba[:, :3] / np.maximum(a, 1e-6), 0.0)
        return self.render_colours(camera, straight, drawn=count > 0)


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(M, C) bilinear samples of ``img`` (H, W, C) at pixel coordinates ``uv`` (M, 2)
    (OpenCV: (0, 0) the top-left pixel's centre); zero outside the image."""
    H, W = img.shape[:2]
    x, y = uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    out = np.zeros((len(uv), img.shape[2]), np.float64)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        ok = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
        out[ok] += w[ok] * img[yi[ok], xi[ok]]
    return out


def ulr_surfel_colours(
    surfels, view_cameras, images, desired_centre, *, k: int = 4, exclude_views=()
) -> tuple[np.ndarray, np.ndarray]:
    """Per surfel the Unstructured-Lumigraph blend of ``images`` (V premultiplied RGBA
    (H, W, 4), one per camera) for a camera at ``desired_centre``: the weights of
    :func:`~opacityhull.render.renderer.ulr_weights`, each view sampled bilinearly at the
    surfel's projection. Returns (N, 4) float32 premultiplied RGBA and (N,) the number of
    candidate views (0: no view sees the surfel, its colour is 0)."""
    from .renderer import ulr_weights

    w = ulr_weights(surfels, list(view_cameras), desired_centre, k=k, exclude_views=list(exclude_views))
    N = len(surfels)
    out = np.zeros((N, 4), np.float64)
    for j in range(w.index.shape[1]):
        vi = w.index[:, j]
        for v in np.unique(vi[vi >= 0]):
            sel = np.flatnonzero(vi == v)
            out[sel] += w.weight[sel, j, None] * _bilinear(np.asarray(images[v], np.float32), w.uv[sel, j])
    return out.astype(np.float32), np.asarray(w.count)
