"""A model's views relit by their natural-illumination fields
(:mod:`opacityhull.reconstruct.natural`): the display-domain part of each captured view
under an environment map, added to the light-array part before ULR. Here, not beside the
estimation, because the display directions are taken from the rendered model's surfels
(:func:`~opacityhull.render.renderer.model_surfels`)."""

from __future__ import annotations

import logging

import numpy as np

from ..errors import FormatError
from ..reconstruct.natural import load_view_fields, relight_view_natural

__all__ = ["natural_centre_m", "relight_model_views_natural", "field_displays", "array_envmap"]

log = logging.getLogger(__name__)


def natural_centre_m(model) -> np.ndarray:
    """The point the display directions are taken from (object frame, metres): the
    surfels' centroid, or the rig's aim point for a model whose surfels are missing or
    empty (a corrupt or partial model; its views can still be relit)."""
    try:
        from ..render.renderer import model_surfels

        pos = np.asarray(model_surfels(model).positions, np.float64)
    except (OSError, KeyError, ValueError) as e:  # FormatError/InputError are ValueErrors
        log.warning("%s: no surfels (%s); display directions from the rig's aim point", model.root, e)
        pos = np.zeros((0, 3))
    if pos.size and np.all(np.isfinite(pos)):
        return pos.mean(axis=0)
    g = model.geometry
    return np.asarray(g.target_m if g is not None else (0.0, 0.0, 0.0), np.float64)


def relight_model_views_natural(model, envmap, *, centre_m=None, supersample: int = 3) -> list:
    """Display-domain parts of every captured view of ``model`` under ``envmap``:
    a list (one per view, model order) of float32 (H, W, 3) premultiplied radiance, or
    None for a view without natural fields. Add them to the light-array relit views
    (``rgba[..., :3] += part``) before ULR blending (:func:`~opacityhull.render.render_image`).

    ``centre_m`` (object frame): default the surfels' centroid (the point the display
    directions are taken from)."""
    if centre_m is None:
        centre_m = natural_centre_m(model)
    g = model.geometry
    out = []
    for v in model.views:
        fields = load_view_fields(model.root, v.id)
        if not fields:
            out.append(None)
            continue
        if g is None:
            raise FormatError(f"{model.root / 'model.toml'}: no [rig] table, the displays' geometry is unknown")
        out.append(relight_view_natural(fields, envmap, g, v.table_deg, centre_m=centre_m, supersample=supersample))
    return out


def field_displays(model) -> tuple:
    """The rig's displays the model has natural-illumination fields for (``model.toml``
    ``[natural] displays``; every display of the rig when the list is missing)."""
    g = model.geometry
    if g is None:
        return ()
    nat = model.meta.get("natural", {}) or {}
    names = sorted(nat.get("displays", {}) or {}) or [d.name for d in g.displays]
    return tuple(g.display(n) for n in names)


def array_envmap(model, envmap, table_deg: float, *, centre_m, supersample: int = 2):
    """The light array's share of ``envmap`` for a view at ``table_deg`` of a model with
    display fields: the map times the split's ``array_weight``
    (:func:`~opacityhull.relight.split.sphere_split`), so the directions the display
    fields relight are not lit a second time by the one-light images. Without fields the
    map itself."""
    from .split import sphere_split, split_envmap

    displays = field_displays(model)
    if not displays:
        return envmap
    s = sphere_split(envmap.height, envmap.width, displays, table_deg, centre_m=centre_m, supersample=supersample)
    return split_envmap(envmap, s)[0]
