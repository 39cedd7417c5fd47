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
import time
from pathlib import Path
from typing import Literal, Sequence

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
]

Renderer = Literal["auto", "fitted", "ulr"]
RENDERERS: tuple[Renderer, ...] = ("auto", "fitted", "ulr")
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

    @classmethod
    def load(cls, model_root: Path) -> "FittedSplats":
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
            stats={"splats": len(self), "ms_total": 1e3 * (time.perf_counter() - t)},
        )
