"""Runners of the evaluation commands and of the demo's scores.

``eval loo`` (:func:`run_loo`, and :func:`~.holdout.run_loo_holdouts` for the geometry
holdout), ``eval relight`` (:func:`~.relight.eval_relight`) and the demo's leave-one-out
and relit-vs-Mitsuba figures (:func:`demo_loo`, :func:`demo_relight_eval`). Evaluation
outputs go under the model, ``MODEL/eval/<kind>/``, unless the caller names a folder
(:func:`default_out`).
"""

from __future__ import annotations

import json
from pathlib import Path
from collections.abc import Callable

from ..errors import InputError
from ..render.config import RenderConfig, Twins

__all__ = ["EVAL_DIR", "default_out", "run_loo", "demo_loo", "demo_relight_eval"]

#: Evaluation outputs live in ``MODEL/eval/<kind>/`` (``loo``, ``relight``, ``test``).
EVAL_DIR = "eval"


def default_out(model_path, kind: str) -> Path:
    """``MODEL/eval/<kind>``: where ``eval <kind>`` writes unless ``--out`` says otherwise."""
    return Path(model_path) / EVAL_DIR / kind


def run_loo(
    model_path,
    *,
    views=None,
    config: RenderConfig = RenderConfig(),
    twins: Twins = "together",
    out=None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Leave-one-out evaluation (blend holdout) of a model folder; writes ``loo.json`` and
    ``loo_sheet.png`` to ``out`` (default ``MODEL/eval/loo``). ``twins``: see
    :func:`~opacityhull.evaluate.loo.leave_one_out`."""
    from ..jsonio import to_jsonable
    from ..imageio import atomic_path
    from ..model import OpacityHullModel
    from .loo import leave_one_out, select_views

    model = OpacityHullModel.open(model_path)
    idx = select_views(model, views)
    out = Path(out) if out is not None else default_out(model_path, "loo")
    summary = leave_one_out(
        model, views=idx, config=config, twins=twins, sheet_path=out / "loo_sheet.png", progress=progress
    )
    with atomic_path(out / "loo.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable(summary), indent=1))
    summary["json"] = str(out / "loo.json")
    return summary


def demo_loo(model_path, out, *, views: str | None = "every:2") -> dict:
    """The demo's leave-one-out score (blend holdout over ``views``) into ``out``: the
    figures, the contact sheet and the JSON, ready for the demo's report."""
    loo = run_loo(model_path, views=views, out=out)
    return {
        "loo": {k: loo[k] for k in ("psnr_mean", "ssim_mean", "alpha_mae", "ms_per_view")},
        "loo_sheet": loo.get("sheet"),
        "loo_json": loo["json"],
    }


def demo_relight_eval(model_dir, out, *, probe: str = "grace", views: int | None = 6, spp: int = 32) -> dict:
    """The demo's relit-vs-Mitsuba score: ``views`` relit views of a simulated model under
    the shipped probe ``builtin:<probe>`` against Mitsuba's render (``eval relight``), into
    ``out``. A model that is not simulated has nothing to compare with: ``{"skipped": why}``."""
    from ..relight.runner import builtin_envmap
    from .relight import eval_relight

    try:
        e = eval_relight(model_dir, envmap=builtin_envmap(probe), out=out, max_views=views, spp=spp)
    except InputError as err:
        return {"skipped": str(err)}
    return {
        "rel_err_mean": e["rel_err_mean"],
        "psnr_norm_mean": e["psnr_norm_mean"],
        "psnr_mean": e["psnr_mean"],
        "sheet": e["sheet"],
    }
