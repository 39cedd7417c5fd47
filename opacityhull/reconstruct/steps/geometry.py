"""Build step ``geometry`` (silhouettes, hull, surfels, visibility, refine)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np

from ...model import BRIGHT_EXTENSIONS, BUILD_DIR, OPEN_HOLES, write_hole_masks
from ...riggeometry import view_id
from ...session import Session
from dataclasses import replace
from collections.abc import Sequence

from ...model import Surfels
from ..lazyviews import _Subset
from ..buildconfig import BuildConfig, _is_rig_session, default_carve_tolerance
from ..buildstore import _NOT_GEOMETRY, _digest, _records_digest, _StepStore, cached, pop_timings
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
    open_holes: PackedMasks | None = None,
    extensions: PackedMasks | None = None,
    train: Sequence[int] | None = None,
    timings: dict | None = None,
) -> tuple[Geometry, str]:
    """Steps 3-6 (silhouettes, hull, surfels, visibility, refine): :func:`build_geometry`
    over the mattes, stored as ``build/geometry.pkl``. ``open_holes`` and ``extensions``: the
    see-through holes and the bright extensions per view if already judged
    (:func:`fill_shadow_holes`), else judged here. ``train``: the views the geometry is
    built from (``build --hold-out``; None: all); the other views' visibility bits stay
    clear and the returned geometry's per-view lists (silhouettes, pinhole cameras,
    dilations) cover the training views only. The photo refinement's seconds go to
    ``timings``, not into the pickled geometry."""
    vids = [view_id(c, a) for c, a in views]
    rig_session = _is_rig_session(session)
    # imported sessions have no [rig] table; a corrupt one is a FormatError, not "no rig"
    geo = session.geometry if "rig" in session.meta else None
    fallback = _rig_volume(geo) if rig_session else None
    rms_per_view = [cams.rms_px.get(c, 0.0) for c, _ in views]
    params = {k: v for k, v in config.to_dict().items() if k not in _NOT_GEOMETRY}
    keep = list(range(len(views))) if train is None else [int(i) for i in train]
    subset = len(keep) < len(views)
    inputs = {
        **({"train": keep} if subset else {}),
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
        if subset:
            # the held-out views are not there for the geometry: no silhouette, no
            # photo-consistency, no visibility (their bits are set below, clear)
            return _expanded(
                build_geometry(
                    _Subset(mattes.alphas, keep),
                    [cams.views[j] for j in keep],
                    [rms_per_view[j] for j in keep],
                    [vids[j] for j in keep],
                    config=config,
                    rig_session=rig_session,
                    fallback_box=fallback,
                    step=step,
                    progress=progress,
                    images=None if images is None else (lambda q, f=images: f(keep[q])),
                    open_holes=None if holes is None else _Subset(holes, keep),
                    doubtful_extensions=None if doubtful is None else _Subset(doubtful, keep),
                    carve_batch=carve_batch,
                    photo_slots=photo_slots,
                ),
                keep,
                len(views),
            )
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
                write_hole_masks(store.dir / name, {v: h for v, h in zip(vids, masks, strict=True) if h is not None})
            else:
                (store.dir / name).unlink(missing_ok=True)
        return g

    def untimed() -> Geometry:
        g = make()
        refine = g.info.get("refine")
        if isinstance(refine, dict):
            got = pop_timings(refine)
            if timings is not None:
                timings.update(got)
        return g

    got = cached(
        store,
        "geometry",
        inputs=inputs,
        params=params,
        run=untimed,
        pickle_as=f"{BUILD_DIR}/geometry.pkl",
        expect=Geometry,
        outputs=lambda _: [f"{BUILD_DIR}/{n}" for n in (OPEN_HOLES, BRIGHT_EXTENSIONS) if (store.dir / n).is_file()],
    )
    return got.value, got.key


def _expanded(g: Geometry, keep: Sequence[int], n_views: int) -> Geometry:
    """``g`` built from the views ``keep`` with its surfels' visibility over all
    ``n_views`` views in model order (the others' bits clear)."""
    s = g.surfels
    vis = np.zeros((len(s), n_views), bool)
    vis[:, list(keep)] = s.visible_bool()
    out = Surfels.from_bool(s.positions, s.normals, s.radii, vis)
    out.depth_m = s.depth_m
    return replace(g, surfels=out)


@dataclass(frozen=True, kw_only=True)
class GeometryProduct:
    """The geometry step's product: :class:`..geometry.Geometry`, its key, what goes into
    the report's ``hull`` section, and each camera's silhouette dilation (px)."""

    geometry: Geometry
    key: str
    hull_info: dict
    dilations: dict
    #: the views it was built from (indices in model order; ``Geometry``'s per-view lists
    #: follow them)
    train: tuple


def run(ctx) -> None:
    views = ctx.cameras.views
    train = ctx.split.train
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
        train=train if len(train) < len(views) else None,
        timings=ctx.timer.detail.setdefault("refine", {}),
    )
    ctx.notes.extend(g.notes)
    hull_info = dict(g.info)
    dilations = {views[j][0]: g.dilations[i] for i, j in enumerate(train)}
    hull_info["dilate_px_per_camera"] = {str(k): v for k, v in sorted(dilations.items())}
    hull_info["shadow_holes_filled"] = ctx.holes.shadow_filled
    if ctx.split.held_out:
        hull_info["held_out"] = [ctx.cameras.vids[i] for i in ctx.split.held_out]
    ctx.geometry = GeometryProduct(geometry=g, key=key, hull_info=hull_info, dilations=dilations, train=tuple(train))


STEP = Step(
    name="geometry",
    run=run,
    inputs=("session", "cameras", "plan", "split", "mattes", "holes", "config", "store"),
    product="geometry",
    params=("all BuildConfig fields but those in buildstore._NOT_GEOMETRY",),
)
