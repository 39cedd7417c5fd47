"""Rendering opacity hulls: Unstructured-Lumigraph blending per surfel (Buehler et al.
2001), EWA surface splatting with an ε-z-buffer (Zwicker et al. 2001), compositing over
colours, images and environment maps, novel-view cameras, and leave-one-out evaluation.

Public API (used by ``relight`` and the CLI)::

    RenderConfig, RenderResult, render_image, render_model, ulr_weights, UlrWeights,
    PreparedViews, prepare_views, prepare_model_views, envmap_background,
    composite_over, spatially_sorted

(The environment map itself is the core's :class:`opacityhull.envmap.EnvironmentMap`.)

Imports are lazy: numba kernels load (or compile) on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what the lazy __getattr__ below resolves, for type checkers
    from .background import composite_over, envmap_background
    from .config import RenderConfig
    from .renderer import (
        RenderResult,
        UlrWeights,
        prepare_model_views,
        render_image,
        render_model,
        spatially_sorted,
        ulr_weights,
    )
    from .views import PreparedViews, prepare_views

_EXPORTS = {
    "RenderConfig": ".config",
    "RenderResult": ".renderer",
    "UlrWeights": ".renderer",
    "render_image": ".renderer",
    "render_model": ".renderer",
    "ulr_weights": ".renderer",
    "prepare_model_views": ".renderer",
    "spatially_sorted": ".renderer",
    "PreparedViews": ".views",
    "prepare_views": ".views",
    "envmap_background": ".background",
    "composite_over": ".background",
}


def __getattr__(name):  # lazy: `opacityhull render --help` must not load numba
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "RenderConfig",
    "RenderResult",
    "UlrWeights",
    "render_image",
    "render_model",
    "ulr_weights",
    "PreparedViews",
    "prepare_views",
    "prepare_model_views",
    "spatially_sorted",
    "envmap_background",
    "composite_over",
]
