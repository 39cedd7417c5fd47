"""Build step ``geometry`` (silhouettes, hull, surfels, visibility, refine)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...model import (
    BRIGHT_EXTENSIONS,
    BUILD_DIR,
    OPEN_HOLES,
    write_hole_masks,
)
from ...riggeometry import view_id
from ...session import Session
from ..buildconfig import BuildConfig, _is_rig_session, default_carve_tolerance
from ..buildstore import _NOT_GEOMETRY, _digest, _records_digest, _StepStore, cached
from ..geometry import Geometry, build_geometry
from ..holes import _extensions_apply, bright_extension_masks, open_hole_masks
from ..lazyviews import Mattes, PackedMasks, _view_rgba
from ..matte_step import _rgb
from .base import Step
from .cameras import _Cameras, _rig_volume

log = logging.getLogger(__name__)


def step_geometry(
    session: Session,
    views,
    cams: _Cameras,
    mattes: Mattes,
    cameras_key: str,
    config: BuildConfig,
    store: _StepStore,
    *,
    colour=None,
    step=None,
    progress=None,
    carve_batch: int | None = None,
    photo_slots: int | None = None,
    open_holes: "PackedMasks | None" = None,
    extensions: "PackedMasks | None" = None,
) -> tuple[Geometry, str]:
    """Steps 3-6 (silhouettes, hull, surfels, visibility, refine): :func:`build_geometry`
    over the mattes, stored as ``build/geometry.pkl``. ``open_holes`` and ``extensions``: the
    see-through holes and the bright extensions per view if already judged
    (:func:`fill_shadow_holes`), else judged here."""
    vids = [view_id(c, a) for c, a in views]
    rig_session = _is_rig_session(session)
    # imported sessions have no [rig] table; a corrupt one is a FormatError, not "no rig"
    geo = session.geometry if "rig" in session.meta else None
    fallback = _rig_volume(geo) if rig_session else None
    rms_per_view = [cams.rms_px.get(c, 0.0) for c, _ in views]
    params = {k: v for k, v in config.to_dict().items() if k not in _NOT_GEOMETRY}
    inputs = {
        "mattes": mattes.content,
        "cameras": cameras_key,
        "rig_session": rig_session,
        "colour": (
            _digest([_records_digest(session, session.select(shot=s, kind=None)) for s, _ in colour])
            if (config.refine != "none" or config.carve_tolerance != 0) and colour
            else ""
        ),
    }

    def make() -> Geometry:
        images: Callable[[int], np.ndarray] | None = None
        if config.refine != "none":
            shots = list(colour or [])

            def view_rgb(i: int) -> np.ndarray:
                from ..liveviews import LIVE_VIEWS

                rgba = _view_rgba(
                    session, shots[i], mattes.alphas[i], use_masks=mattes.use_masks, alpha_eps=config.alpha_eps
                )
                return LIVE_VIEWS.track(vids[i], rgba[..., :3])

            images = view_rgb
        holes = None
        tolerant = default_carve_tolerance(config, rig_session=rig_session, n_views=len(vids))
        want_holes = bool(tolerant and colour and config.backdrop_holes)
        want_ext = bool(colour) and _extensions_apply(config, bool(tolerant), mattes.use_masks)
        holes = open_holes if want_holes and open_holes is not None else None
        doubtful = extensions if want_ext and extensions is not None else None
        if (want_holes and holes is None) or (want_ext and doubtful is None):
            # one photograph at a time, the masks bit-packed
            new_holes = PackedMasks() if want_holes and holes is None else None
            new_ext = PackedMasks() if want_ext and doubtful is None else None
            for i, shot in enumerate(colour or []):
                rgb = None if shot[0] is None else _rgb(session.load_radiance(shot[0]))
                if new_holes is not None:
                    new_holes.append(
                        None
                        if rgb is None
                        else open_hole_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
                    )
                if new_ext is not None:
                    new_ext.append(
                        None
                        if rgb is None
                        else bright_extension_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
                    )
                del rgb
            holes = new_holes if new_holes is not None else holes
            doubtful = new_ext if new_ext is not None else doubtful
        g = build_geometry(
            mattes.alphas,
            cams.views,
            rms_per_view,
            vids,
            config=config,
            rig_session=rig_session,
            fallback_box=fallback,
            step=step,
            progress=progress,
            images=images,
            open_holes=holes,
            doubtful_extensions=doubtful,
            carve_batch=carve_batch,
            photo_slots=photo_slots,
        )
        # a stale file from an earlier build would make the geometry holdout carve differently
        for name, masks in ((OPEN_HOLES, holes), (BRIGHT_EXTENSIONS, doubtful)):
            if masks is not None:
                write_hole_masks(store.dir / name, {v: h for v, h in zip(vids, masks) if h is not None})
            else:
                (store.dir / name).unlink(missing_ok=True)
        return g

    got = cached(
        store,
        "geometry",
        inputs=inputs,
        params=params,
        run=make,
        pickle_as=f"{BUILD_DIR}/geometry.pkl",
        expect=Geometry,
        outputs=lambda _: [f"{BUILD_DIR}/{n}" for n in (OPEN_HOLES, BRIGHT_EXTENSIONS) if (store.dir / n).is_file()],
    )
    return got.value, got.key


@dataclass(frozen=True, kw_only=True)
class GeometryProduct:
    """The geometry step's product: :class:`..geometry.Geometry`, its key, what goes into
    the report's ``hull`` section, and each camera's silhouette dilation (px)."""

    geometry: Geometry
    key: str
    hull_info: dict
    dilations: dict


def run(ctx) -> None:
    views = ctx.cameras.views
    g, key = step_geometry(
        ctx.session,
        views,
        ctx.cameras.cams,
        ctx.mattes,
        ctx.cameras.key,
        ctx.config,
        ctx.store,
        colour=ctx.holes.colour_shots,
        step=ctx.timer.step,
        progress=ctx.progress,
        carve_batch=ctx.plan.carve_batch,
        photo_slots=ctx.plan.photo_slots,
        open_holes=ctx.holes.open_holes,
        extensions=ctx.holes.extensions,
    )
    ctx.notes.extend(g.notes)
    hull_info = dict(g.info)
    dilations = {c: g.dilations[i] for i, (c, _) in enumerate(views)}
    hull_info["dilate_px_per_camera"] = {str(k): v for k, v in sorted(dilations.items())}
    hull_info["shadow_holes_filled"] = ctx.holes.shadow_filled
    ctx.geometry = GeometryProduct(geometry=g, key=key, hull_info=hull_info, dilations=dilations)


STEP = Step(
    name="geometry",
    run=run,
    inputs=("session", "cameras", "plan", "mattes", "holes", "config", "store"),
    product="geometry",
    params=("all BuildConfig fields but those in buildstore._NOT_GEOMETRY",),
)
