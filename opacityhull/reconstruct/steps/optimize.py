"""Build step ``optimize`` (``build --optimize none|fast|full``, issue 29): the written
model's surfels fitted to the training views (every view not held out) by differentiable
EWA splatting (:func:`opacityhull.optimize.fit.fit_model`), into ``MODEL/optimized/``
(``splats.ply``, ``fit.json``). The fit checkpoints into ``MODEL/build/optimize/`` and
resumes from there; a finished fit is reused by ``build --resume`` while the written
model, the training views and the options are unchanged. ``report.json``'s ``optimize``
gives the loss and training-PSNR curves and the time per iteration: the fit's wall-clock
times go there only (not into ``fit.json`` or the checkpoint, #35).

``none`` (the default) fits nothing and removes an earlier build's ``optimized/``, which
would no longer match the model."""

from __future__ import annotations

import inspect
import json
import logging
import math
import shutil
from dataclasses import asdict

from ...model import BUILD_DIR
from ...optimize.config import fit_preset
from ...optimize.fit import OPTIMIZED_DIR, SPLATS_PLY, CheckpointError, FitProgress, fit_model
from ..buildstore import cached
from .base import Step

__all__ = ["STEP", "CHECKPOINT_DIR", "fit_config"]

log = logging.getLogger(__name__)

#: the fit's checkpoint folder, under ``MODEL/build/``
CHECKPOINT_DIR = "optimize"


def fit_config(config):
    """The :class:`~opacityhull.optimize.config.FitConfig` of a
    :class:`~..buildconfig.BuildConfig` (``optimize``, ``optimize_iterations``)."""
    if config.optimize == "none":
        return fit_preset("none")
    return fit_preset(config.optimize, iterations=config.optimize_iterations)


def _summary(fit: dict, timings: dict) -> dict:
    """``report.json``'s ``optimize`` from ``fit.json`` and this run's ``timings``
    (:meth:`~opacityhull.optimize.fit.FitReport.timings`; empty when the fit was reused)."""
    keep = ("iterations", "train_psnr_last", "n_surfels_start", "n_surfels_end")
    out = {k: fit[k] for k in keep if k in fit}
    out |= {
        "seconds": timings.get("seconds"),
        "ms_per_iteration": timings.get("ms_per_iteration"),
        "stopped_by": fit.get("stopped_by"),
        "loss": list(fit.get("loss", [])),
        "train_psnr": list(fit.get("psnr", [])),
        "step_ms": list(timings.get("step_ms", [])),
        "train_views": list(fit.get("train_views", [])),
        "splats": SPLATS_PLY,
    }
    return out


def _reporter(ctx, total: int):
    """A :class:`FitProgress` callback feeding the build's ``progress(done, total)`` (with
    the running PSNR as a ``note`` when the callback takes one: the CLI's bar shows it
    beside its count and ETA)."""
    try:
        takes_note = "note" in inspect.signature(ctx.progress).parameters
    except (TypeError, ValueError):
        takes_note = False

    def progress(p: FitProgress) -> None:
        if takes_note:
            psnr = f"{p.psnr:.2f} dB" if math.isfinite(p.psnr) else "-"
            ctx.progress(p.iteration, total, note=f"train PSNR {psnr}, {p.n_surfels} surfels")
        else:
            ctx.progress(p.iteration, total)

    return progress


def run(ctx) -> None:
    fc = fit_config(ctx.config)
    out = ctx.out
    if fc.mode == "none":
        # an earlier build's fit belongs to a model that may no longer be this one
        shutil.rmtree(out / OPTIMIZED_DIR, ignore_errors=True)
        ctx.fit = {"mode": "none"}
        return
    train = list(ctx.split.train)
    # the fit's wall-clock times reach report.json from here, never through a file (#35)
    timings: dict = {}

    def fit() -> dict:
        ckpt_dir = out / BUILD_DIR / CHECKPOINT_DIR
        report = _reporter(ctx, fc.iterations)
        try:
            rep = fit_model(out, train_views=train, config=fc, progress=report, checkpoint_dir=ckpt_dir)
        except CheckpointError as e:
            # a checkpoint of an earlier model or other options: the fit starts over
            ctx.notes.append(f"optimize: {e}; its checkpoint was removed and the fit started over")
            shutil.rmtree(ckpt_dir, ignore_errors=True)
            rep = fit_model(out, train_views=train, config=fc, progress=report, checkpoint_dir=ckpt_dir)
        timings.update(rep.timings())
        return json.loads((out / OPTIMIZED_DIR / "fit.json").read_text())

    def reuse(_entry) -> dict:
        return json.loads((out / OPTIMIZED_DIR / "fit.json").read_text())

    with ctx.timer.step("optimize"):
        got = cached(
            ctx.store,
            "optimize",
            inputs={"write": ctx.model.key, "train": train},
            params=asdict(fc),
            run=fit,
            outputs=[f"{OPTIMIZED_DIR}/{SPLATS_PLY}", f"{OPTIMIZED_DIR}/fit.json"],
            on_reuse=reuse,
        )
    ctx.fit = {"mode": fc.mode, **_summary(got.value, timings)}
    if timings:
        log.info(
            "optimize %s: %s iterations, %.1f ms each", fc.mode, ctx.fit.get("iterations"), timings["ms_per_iteration"]
        )


STEP = Step(
    name="optimize",
    run=run,
    inputs=("model", "split", "config", "store"),
    product="fit",
    params=("optimize", "optimize_iterations"),
)
