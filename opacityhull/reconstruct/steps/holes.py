"""Build step ``holes``: each view's colour photograph, and the holes of imported masks
judged by it (:func:`..holes.fill_shadow_holes`): shadow holes filled in the views'
alpha, see-through holes and bright extensions handed to the geometry step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ...errors import FormatError
from ..holes import fill_shadow_holes
from .base import Step
from .cameras import _colour_shot


@dataclass(frozen=True, kw_only=True)
class HolesProduct:
    """The colour shot of each view ``(object shot, object-absent shot)``, what was filled
    (``{"views", "px"}``), and the open holes and bright extensions found on the way
    (:class:`..lazyviews.PackedMasks` or None)."""

    colour_shots: list
    shadow_filled: dict
    open_holes: Any
    extensions: Any


def run(ctx) -> None:
    session, views, vids = ctx.session, ctx.cameras.views, ctx.cameras.vids
    colour_shots = [_colour_shot(session, c, a) for c, a in views]
    missing_colour = [vids[i] for i, (s, _) in enumerate(colour_shots) if s is None]
    if missing_colour:
        raise FormatError(
            f"{session.root}: no lightfield (or displays-off matting) image for views "
            f"{missing_colour[:5]}: nothing to colour the model with"
        )
    with ctx.timer.step("holes"):
        mattes, shadow_filled, open_holes, extensions = fill_shadow_holes(
            session, ctx.mattes, colour_shots, vids, ctx.config, ctx.store
        )
    # the views' alphas from here on are the filled ones (a new content digest)
    ctx.mattes = mattes
    if shadow_filled["px"]:
        ctx.notes.append(
            f"mask holes: {shadow_filled['px']} px in {shadow_filled['views']} view(s) show no backdrop "
            "(shadows a threshold lost) and are opaque in the views' alpha (build/filled_holes.npz)"
        )
    ctx.holes = HolesProduct(
        colour_shots=colour_shots, shadow_filled=shadow_filled, open_holes=open_holes, extensions=extensions
    )


STEP = Step(
    name="holes",
    run=run,
    inputs=("session", "cameras", "mattes", "config", "store"),
    product="holes",
    params=("fill_shadow_holes", "backdrop_holes", "doubt_bright_extensions", "alpha_threshold"),
)
