"""Build step ``pictures``: matte sheet, hull overlays, reprojection histogram."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..buildstore import cached
from ..matte_step import _rgb
from ..lazyviews import _Subset
from .base import Step

log = logging.getLogger(__name__)


def _pictures(out: Path, session, views, vids, alphas, sils, pin, surfels, cams, colour_shots) -> list[str]:
    from ..pictures import hull_overlays, matte_contact_sheet, reprojection_histogram, surfel_mask

    pics = out / "pictures"
    made = [matte_contact_sheet(alphas, vids, pics / "mattes.png")]
    pick = sorted(set(np.linspace(0, len(views) - 1, min(8, len(views))).round().astype(int).tolist()))
    imgs, ss, ms, names = [], [], [], []
    for i in pick:
        obj, _ = colour_shots[i]
        imgs.append(_rgb(session.load_radiance(obj)))
        ss.append(sils[i])
        ms.append(surfel_mask(surfels.positions, surfels.radii, pin[i]))
        names.append(vids[i])
    made.append(hull_overlays(imgs, ss, ms, names, pics / "hull_overlay.png"))
    cal = cams.calibration
    p = None
    if cal is not None:
        p = reprojection_histogram(
            pics / "reprojection.png",
            residuals_px=cal.residuals_px,
            rms_per_camera={cal.rig_cameras[c].name: cal.reproj_rms_px[c] for c in cal.camera_indices},
        )
    elif cams.rms_px and cams.rig:
        p = reprojection_histogram(
            pics / "reprojection.png", rms_per_camera={f"cam{i}": r for i, r in cams.rms_px.items()}
        )
    if p is not None:
        made.append(p)
    return [str(Path(m).relative_to(out)) for m in made]


def run(ctx) -> None:
    pictures: list = []
    with ctx.timer.step("pictures"):
        if ctx.config.pictures:
            g = ctx.geometry.geometry
            # the geometry's per-view lists follow the training views (all without --hold-out)
            t = list(ctx.geometry.train)
            views, vids = [ctx.cameras.views[j] for j in t], [ctx.cameras.vids[j] for j in t]
            alphas = ctx.mattes.alphas if len(t) == len(ctx.cameras.views) else _Subset(ctx.mattes.alphas, t)

            def draw() -> list:
                return _pictures(
                    ctx.out,
                    ctx.session,
                    views,
                    vids,
                    alphas,
                    g.sils,
                    g.pin,
                    g.surfels,
                    ctx.cameras.cams,
                    [ctx.holes.colour_shots[j] for j in t],
                )

            pictures = cached(
                ctx.store,
                "pictures",
                inputs={"write": ctx.model.key},
                params={},
                run=draw,
                outputs=lambda pics: pics,
                on_reuse=lambda entry: list(entry.get("outputs", [])),
            ).value
    ctx.pictures = pictures


STEP = Step(
    name="pictures",
    run=run,
    inputs=("session", "cameras", "mattes", "holes", "geometry", "model", "config", "store"),
    product="pictures",
    params=("pictures",),
)
