"""Honest held-out evaluation: rebuild the geometry without the held-out view.

``eval loo --holdout blend`` only leaves a view out of the ULR blend; its silhouette
still carved the hull and its depth test still decided the visibility, so the
comparison flatters the model (the hull fits the held-out silhouette exactly).
``--holdout geometry`` rebuilds silhouettes → hull → surfels → visibility from the
other views with the build's own options (:func:`.build.build_geometry`, the same code
the build ran), at the build's resolution, so the score says how the model does on a
view it has never seen. The mattes are the model's own view alphas, so no session is
needed.
"""

from __future__ import annotations

import json
import logging
from dataclasses import fields, replace
from functools import lru_cache
from pathlib import Path
from typing import Literal
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import FormatError, InputError
from ..model import OpacityHullModel, Surfels
from ..render.config import Twins
from ..reconstruct.build import BuildConfig, build_geometry, default_dilate_base_px
from ..reconstruct.matting import MattingOptions

__all__ = ["build_config_of", "geometry_without", "rebuild_without", "run_loo_holdouts"]

log = logging.getLogger(__name__)


def build_config_of(model: OpacityHullModel) -> tuple[BuildConfig, dict]:
    """The :class:`BuildConfig` a model was built with (from ``model.toml``'s
    provenance) pinned to the resolution the build chose, and its ``report.json`` hull
    section (empty when absent)."""
    report = {}
    rp = model.root / "report.json"
    if rp.is_file():
        try:
            report = json.loads(rp.read_text()).get("hull", {})
        except (OSError, ValueError) as e:
            raise FormatError(f"{rp}: unreadable build report ({e})") from None
    cfg_d = model.build_config  # a TOML table, or the JSON string of older models
    names = {f.name for f in fields(BuildConfig)}
    kw = {k: v for k, v in cfg_d.items() if k in names and k != "matting"}
    for k in ("bounds_m",):
        if kw.get(k) is not None:
            kw[k] = tuple(tuple(x) for x in kw[k])
    kw["exclude_views"] = tuple(kw.get("exclude_views", ()))
    if isinstance(cfg_d.get("matting"), dict):
        mnames = {f.name for f in fields(MattingOptions)}
        kw["matting"] = MattingOptions(**{k: v for k, v in cfg_d["matting"].items() if k in mnames})
    cfg = BuildConfig(**kw)
    res = report.get("resolution")
    if res:
        cfg = replace(cfg, hull_res=int(res["hull_res"]), surfel_oversample=int(res["oversample"]))
    if report.get("carve_tolerance") is not None:
        cfg = replace(cfg, carve_tolerance=int(report["carve_tolerance"]))
    return replace(cfg, pictures=False, reflectance=False), report


def geometry_without(
    model: OpacityHullModel, *, config: BuildConfig | None = None
) -> Callable[[int | Sequence[int]], Surfels]:
    """A function ``i → Surfels`` rebuilding the model's geometry without view ``i``, or
    without every view of a tuple ``i`` (a view and its coincident twins,
    :func:`~opacityhull.camera.coincident_views`, held out together).

    The surfels' visibility covers all V views in the model's bit order, the held-out
    views' bits clear. ``config`` defaults to the build's own (:func:`build_config_of`); a
    tolerant carve keeps its tolerance unless that would exceed V − 2. The test views of a
    model built with ``--hold-out`` are left out of every rebuild as well.
    """
    cfg, report = build_config_of(model) if config is None else (config, {})
    cams = [v.camera for v in model.views]
    V = len(cams)
    alphas = [model.load_view_rgba(i)[..., 3] for i in range(V)]
    dil = report.get("dilate_px_per_view", {})
    # the build dilated by base + rms; recover the rms part per view (0 when unknown)
    rig_session = not str(model.meta.get("provenance", {}).get("rig_source", "")).startswith("import:")
    base_px = default_dilate_base_px(cfg, rig_session=rig_session)
    rms = [max(0.0, float(dil.get(v.id, 0)) - base_px) if dil else 0.0 for v in model.views]
    lo, hi = report.get("lo_m"), report.get("hi_m")
    fallback = (np.asarray(lo), np.asarray(hi)) if lo and hi else None
    from ..model import BRIGHT_EXTENSIONS, BUILD_DIR, OPEN_HOLES, read_hole_masks

    stored = read_hole_masks(Path(model.root) / BUILD_DIR / OPEN_HOLES)
    holes = [stored.get(v.id) for v in model.views]
    # the outline extensions the build doubted are doubted again (no photograph needed)
    doubted = read_hole_masks(Path(model.root) / BUILD_DIR / BRIGHT_EXTENSIONS)
    extensions = [doubted.get(v.id) for v in model.views]

    # a model built with --hold-out: its test views stay out of every rebuild too
    test_views = {model.view_index(str(v)) for v in (model.meta.get("split") or {}).get("held_out", [])}

    def rebuild(i: int | Sequence[int]) -> Surfels:
        held = {int(i)} if isinstance(i, (int, np.integer)) else {int(j) for j in i}
        if not held or not all(0 <= j < V for j in held):
            raise InputError(f"geometry_without: views {sorted(held)} are not indices of the model's {V} views")
        keep = [j for j in range(V) if j not in held and j not in test_views]
        c = cfg
        if c.carve_tolerance is not None and c.carve_tolerance > max(0, len(keep) - 2):
            c = replace(c, carve_tolerance=max(0, len(keep) - 2))
        images: Callable[[int], np.ndarray] | None = None
        if c.refine != "none":  # the photo-consistency cost never sees the held-out photograph

            def kept_rgb(q: int, keep=keep) -> np.ndarray:
                return model.load_view_rgba(keep[q])[..., :3]

            images = kept_rgb
        g = build_geometry(
            [alphas[j] for j in keep],
            [cams[j] for j in keep],
            [rms[j] for j in keep],
            [model.views[j].id for j in keep],
            config=c,
            rig_session=rig_session,
            fallback_box=fallback,
            images=images,
            open_holes=[holes[j] for j in keep] if stored else None,
            doubtful_extensions=[extensions[j] for j in keep] if doubted else None,
        )
        s = g.surfels
        vis = np.zeros((len(s), V), bool)
        vis[:, keep] = s.visible_bool()
        log.info(
            "holdout %s: %d surfels rebuilt from %d views",
            "+".join(model.views[j].id for j in sorted(held)),
            len(s),
            len(keep),
        )
        out = Surfels.from_bool(s.positions, s.normals, s.radii, vis)
        out.depth_m = s.depth_m
        return out

    return rebuild


@lru_cache(maxsize=2)
def _rebuilder(root: str, mtime_ns: int) -> Callable[[int | Sequence[int]], Surfels]:
    # one model (its alphas loaded once) per worker process, re-read if rewritten
    return geometry_without(OpacityHullModel.open(root))


def rebuild_without(item: tuple) -> Surfels:
    """``(model folder, i)`` → the model's surfels rebuilt without view ``i`` (an index or
    a tuple of them, :func:`geometry_without`): the per-view task of ``eval loo --holdout
    geometry --scheduler ...``. Workers open the model from its path (a folder they all
    see)."""
    root, i = item
    try:
        m = (Path(root) / "model.toml").stat().st_mtime_ns
    except OSError:
        m = -1  # OpacityHullModel.open names the problem
    return _rebuilder(str(root), m)(i)


class _Prefetched:
    """``held → Surfels`` for the held-out views of ``order`` (each a view index or a
    tuple of them), rebuilt ``batch`` at a time through ``executor`` and dropped once
    handed out: memory holds one batch of rebuilt geometries, not one per view."""

    def __init__(self, executor, root: Path, order, *, batch: int):
        self.ex, self.root, self.order = executor, str(root), list(order)
        self.batch = max(1, int(batch))
        self.cache: dict = {}

    def __call__(self, i) -> Surfels:
        if i not in self.cache:
            k = self.order.index(i) if i in self.order else None
            todo = [i] if k is None else [j for j in self.order[k : k + self.batch] if j not in self.cache]
            for j, s in zip(todo, self.ex.map(rebuild_without, [(self.root, j) for j in todo]), strict=True):
                self.cache[j] = s
        return self.cache.pop(i)


def run_loo_holdouts(
    model_path,
    *,
    views=None,
    config=None,
    holdout: str = "both",
    twins: Twins = "together",
    out=None,
    progress=None,
    executor=None,
    on_step: Callable[[str], None] | None = None,
) -> dict:
    """``eval loo`` with ``--holdout blend|geometry|both``: the render stage's
    leave-one-out (:func:`opacityhull.evaluate.loo.leave_one_out`) with the geometry
    rebuilt here. ``both`` reports both; the top-level figures are the geometry
    holdout's (the honest one). ``twins``: a view's coincident twins are held out with
    it (``"together"``) or stay in the model (``"keep"``), see :func:`leave_one_out`.
    Writes ``loo.json`` and the contact sheets to ``out``.

    ``executor`` (:mod:`opacityhull.executor`, default serial): the geometry rebuilds,
    the costly part, run there two per worker ahead of the renders; the figures are
    the same as serial (each rebuild is the same deterministic function of the model).
    ``rebuild_ms`` then measures the wait for a rebuild, not its cost. ``on_step(name)``
    is called as each holdout starts (``"blend holdout"``, ``"geometry holdout"``), and
    ``progress(done, total)`` counts that holdout's views."""
    from ..jsonio import to_jsonable
    from ..imageio import atomic_path
    from .loo import held_out_groups, leave_one_out, select_views
    from .runner import default_out
    from ..render.renderer import RenderConfig, prepare_model_views

    if holdout not in ("blend", "geometry", "both"):
        raise InputError(f"holdout {holdout!r}: expected blend, geometry or both")
    model = OpacityHullModel.open(model_path)
    idx = select_views(model, views)
    config = config or RenderConfig()
    out = Path(out) if out is not None else default_out(model_path, "loo")
    pv = prepare_model_views(model)
    results = {}
    kinds: list[Literal["blend", "geometry"]] = (
        ["blend", "geometry"] if holdout == "both" else ["geometry" if holdout == "geometry" else "blend"]
    )
    for kind in kinds:
        if on_step is not None:
            on_step(f"{kind} holdout")
        gw = None
        if kind == "geometry":
            if executor is not None and executor.scheduler != "serial":
                held = held_out_groups(model, idx, twins=twins)
                gw = _Prefetched(executor, model.root, [held[i] for i in idx], batch=2 * executor.n_workers)
            else:
                gw = geometry_without(model)
        sheet = out / ("loo_sheet.png" if len(kinds) == 1 else f"loo_sheet_{kind}.png")
        results[kind] = leave_one_out(
            model,
            views=idx,
            config=config,
            sheet_path=sheet,
            prepared=pv,
            progress=progress,
            holdout=kind,
            twins=twins,
            geometry_without=gw,
        )
    main = results["geometry" if "geometry" in results else "blend"]
    summary = dict(main)
    if len(results) > 1:
        keys = [
            k
            for k in main
            if k.endswith("_mean")
            or k in ("alpha_mae", "coverage_iou_min", "ms_per_view", "rebuild_ms_per_view", "sheet", "twins")
        ]
        summary["holdouts"] = {k: {kk: r.get(kk) for kk in keys} for k, r in results.items()}
    with atomic_path(out / "loo.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable({**summary, "all": results if len(results) > 1 else None}), indent=1))
    summary["json"] = str(out / "loo.json")
    return summary
