"""CLI commands of `opacityhull.evaluate` (registered by :mod:`opacityhull.cli`):
``opacityhull eval loo``, ``opacityhull eval test`` and ``opacityhull eval relight``.

Every evaluation writes under the model, ``MODEL/eval/<kind>/``, unless ``--out`` names
another folder (:func:`.runner.default_out`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, get_args

import typer
from rich.markup import escape

from ..cliutil import check_choice, check_model_dir, cli_errors, console, emit, option_group, progress
from ..cliutil import scheduler_options, step_progress
from ..errors import InputError
from ..outputs import check_output
from ..relight.commands import _config as _relight_config
from ..relight.commands import _load_map, _shared_options
from ..render.commands import _RENDER_OPTIONS, _SCHEDULER_HELP, open_model_arg
from ..render.commands import _config as _render_config
from ..render.config import Twins

HOLDOUTS = ("blend", "geometry", "both")

_LOO_VIEWS_HELP = "all (default) | every:N | camera:C | comma list of view ids or indices."
_LOO_OUT_HELP = "Folder for loo.json and the contact sheets (default MODEL/eval/loo)."
_TWINS_HELP = (
    "together: hold out a view's coincident twins (the same viewpoint photographed again) with it | "
    "keep: leave them in the model (a plain leave-one-out script's protocol; the twin's score is no novel view)."
)
_HOLDOUT_HELP = (
    "blend: leave the view out of the ULR blend only | geometry: also rebuild "
    "hull, surfels and visibility without it (honest, slower) | both."
)
_LOO_JSON_HELP = "Print {views, psnr_mean, ssim_mean, alpha_mae, per_view} on stdout."
_LOO_SCHEDULER = scheduler_options(
    _SCHEDULER_HELP + " With --holdout geometry|both the geometry rebuilds (the costly part) run there; "
    "the renders run here."
)

_TEST_BG_HELP = "white | black: the background photograph and rendering are composited over for the whole-image metric."
_TEST_RENDERER_HELP = (
    "auto | fitted | ulr: the fitted splats of `build --optimize` or the hull blended from the training views "
    '(ULR); auto takes the fitted splats when the model has them. The summary\'s "renderer" says which.'
)
_TEST_OUT_HELP = "Folder for test.json and test_sheet.png (default MODEL/eval/test)."
_TEST_JSON_HELP = 'Print {"psnr_mean", "ssim_mean", "psnr_mask_mean", "ssim_mask_mean", "per_view", ...} on stdout.'

_EVAL_MODEL_HELP = "Model folder built from a simulated session (with reflectance data)."
_EVAL_OUT_HELP = "Folder for the contact sheet and per-view EXRs (default MODEL/eval/relight)."
_MAX_VIEWS_HELP = "Evaluate at most this many views (spread evenly)."
_EVAL_JSON_HELP = 'Print {"rel_err_mean", "psnr_norm_mean", "psnr_mean", "per_view", ...} on stdout.'


def register(app, groups) -> None:
    """Add ``loo``, ``test`` and ``relight`` to the ``eval`` group."""

    @groups["eval"].command("loo")
    @cli_errors
    @option_group(_RENDER_OPTIONS, into="render_options", before="out")
    @option_group(_LOO_SCHEDULER, into="executor", before="json_out")
    def loo_cmd(
        model: Annotated[Path, typer.Argument(help="Model folder.")],
        views: Annotated[str | None, typer.Option("--views", help=_LOO_VIEWS_HELP)] = None,
        out: Annotated[Path | None, typer.Option("--out", help=_LOO_OUT_HELP)] = None,
        holdout: Annotated[str, typer.Option("--holdout", help=_HOLDOUT_HELP)] = "blend",
        twins: Annotated[str, typer.Option("--twins", help=_TWINS_HELP)] = "together",
        json_out: Annotated[bool, typer.Option("--json", help=_LOO_JSON_HELP)] = False,
        *,
        render_options: dict,
        executor: dict,
    ):
        """Leave-one-out: render each chosen captured view without blending it, compare with its photograph
        (PSNR, SSIM, alpha MAE inside the union of the masks), and write a contact sheet photo | render | error."""
        from .loo import select_views  # noqa: F401  (fail fast on import errors)
        from .runner import default_out, run_loo

        open_model_arg(model)
        if out is not None:
            check_output(out, {"MODEL": model})
        if out is None:
            out = default_out(model, "loo")
        cfg = _render_config(**render_options)
        check_choice("--holdout", holdout, HOLDOUTS)
        twins_mode = check_choice("--twins", twins, get_args(Twins))
        from ..executor import open_executor, parse_scheduler

        if parse_scheduler(executor["scheduler"]).kind != "serial" and holdout == "blend":
            raise InputError(
                f"--scheduler {executor['scheduler']}: with --holdout blend there is no per-view rebuild to "
                "distribute (the renders run in this process); use --holdout geometry|both, or "
                "--scheduler serial"
            )
        with open_executor(**executor) as ex, step_progress("leave-one-out") as (on_step, cb):
            if holdout == "blend":
                on_step("blend holdout")
                summary = run_loo(model, views=views, config=cfg, twins=twins_mode, out=out, progress=cb)
            else:
                from .holdout import run_loo_holdouts

                summary = run_loo_holdouts(
                    model,
                    views=views,
                    config=cfg,
                    holdout=holdout,
                    twins=twins_mode,
                    out=out,
                    progress=cb,
                    executor=ex,
                    on_step=on_step,
                )
            summary["scheduler"] = ex.scheduler

        def human(s):
            c = console()
            for kind, h in (s.get("holdouts") or {s.get("holdout", "blend"): s}).items():
                c.print(
                    f"leave-one-out ({kind} holdout) over {len(s['views'])} views: PSNR {h['psnr_mean']:.2f} dB "
                    f"(interior {h['psnr_interior_mean']:.2f}, band {h['psnr_band_mean']:.2f}), "
                    f"SSIM {h['ssim_mean']:.4f}, alpha MAE {h['alpha_mae']:.4f}, coverage IoU "
                    f"{h['coverage_iou_mean']:.4f}, interior alpha deficit {h['interior_alpha_deficit_mean']:.4f} "
                    f"({h['ms_per_view']:.0f} ms/view)",
                    markup=False,
                )
                if any(p.get("shadow_holes_px") for p in s.get("per_view", ())):
                    c.print(
                        f"  against the masks with the shadow holes the build filled: PSNR "
                        f"{h['psnr_holes_filled_mean']:.2f} dB, coverage IoU {h['coverage_iou_holes_filled_mean']:.4f}",
                        markup=False,
                    )
            for g in s.get("coincident_views") or ():
                how = "held out together" if s.get("twins") == "together" else "kept in (--twins keep)"
                c.print(f"  coincident views {' = '.join(g)}: {how}", markup=False)
            if "sheet" in s:
                c.print(f"  contact sheet: {s['sheet']}")
            c.print(f"  details: {s['json']}")

        emit(summary, json_out, human)

    @groups["eval"].command("test")
    @cli_errors
    @option_group(_RENDER_OPTIONS, into="render_options", before="out")
    def test_cmd(
        model: Annotated[Path, typer.Argument(help="Model folder built with --hold-out.")],
        background: Annotated[str, typer.Option("--background", help=_TEST_BG_HELP)] = "white",
        renderer: Annotated[str, typer.Option("--renderer", help=_TEST_RENDERER_HELP)] = "auto",
        out: Annotated[Path | None, typer.Option("--out", help=_TEST_OUT_HELP)] = None,
        json_out: Annotated[bool, typer.Option("--json", help=_TEST_JSON_HELP)] = False,
        *,
        render_options: dict,
    ):
        """Render every test view of a model built with `build --hold-out` (views it never saw) and compare with
        its photograph: PSNR and SSIM over the whole image on --background (the NeRF papers' protocol) and over the
        union of the masks (eval loo's metric), per view, and a contact sheet."""
        from .heldout import BACKGROUNDS, RENDERERS, eval_test

        open_model_arg(model)
        bg = check_choice("--background", background, BACKGROUNDS)
        rd = check_choice("--renderer", renderer, RENDERERS)
        cfg = _render_config(**render_options)
        with progress("eval test", enabled=not json_out) as cb:
            s = eval_test(model, background=bg, config=cfg, renderer=rd, out=out, progress=cb)

        def human(s):
            c = console()
            c.print(
                f"test views ({s['hold_out']}, {len(s['views'])} held out, {s['train_views']} built from; "
                f"{s['renderer']} renderer): "
                f"PSNR {s['psnr_mean']:.2f} dB, SSIM {s['ssim_mean']:.4f} on {s['background']}; mask union "
                f"PSNR {s['psnr_mask_mean']:.2f} dB, SSIM {s['ssim_mask_mean']:.4f}",
                markup=False,
            )
            for p in s["per_view"]:
                c.print(
                    f"  {p['view']}: {p['psnr']:.2f} dB / {p['ssim']:.4f}; mask {p['psnr_mask']:.2f} dB / "
                    f"{p['ssim_mask']:.4f}",
                    markup=False,
                )
            if "sheet" in s:
                c.print(f"  contact sheet: {s['sheet']}")
            c.print(f"  details: {s['json']}")

        emit(s, json_out, human)

    @groups["eval"].command("relight")
    @cli_errors
    @_shared_options(envmap_required=True, map_before="out", config_before="json_out")
    def eval_relight_cmd(
        model: Annotated[Path, typer.Argument(help=_EVAL_MODEL_HELP)],
        out: Annotated[Path | None, typer.Option("--out", help=_EVAL_OUT_HELP)] = None,
        spp: Annotated[int, typer.Option("--spp", help="Samples per pixel of Mitsuba's ground-truth render.")] = 64,
        max_views: Annotated[int | None, typer.Option("--max-views", help=_MAX_VIEWS_HELP)] = None,
        json_out: Annotated[bool, typer.Option("--json", help=_EVAL_JSON_HELP)] = False,
        *,
        map_options: dict,
        config_options: dict,
    ):
        """Relit captured views of a simulated model against Mitsuba's direct render of the same object under the
        same environment map from the same cameras: PSNR and relative error inside the mask, and a contact sheet
        (truth | relit | error)."""
        from .relight import eval_relight
        from .runner import default_out

        check_model_dir(model)
        if spp < 1:
            raise InputError(f"--spp {spp}: expected at least 1 sample per pixel")
        if max_views is not None and max_views < 1:
            raise InputError(f"--max-views {max_views}: expected at least 1")
        if out is not None:
            check_output(out, {"MODEL": model, "--envmap": map_options["envmap"]})
        if out is None:
            out = default_out(model, "relight")
        cfg = _relight_config(**config_options)
        env = _load_map(map_options)
        with progress("eval relight", enabled=not json_out) as cb:
            s = eval_relight(model, envmap=env, out=out, spp=spp, max_views=max_views, config=cfg, progress=cb)

        # a capture with few lights: eval_relight put the warning in s['warnings'] and on the sheet

        def human(s):
            c = console()
            c.print(
                f"relighting vs Mitsuba over {len(s['per_view'])} views: relative error "
                f"{100 * s['rel_err_mean']:.2f} %, PSNR {s.get('psnr_norm_mean', float('nan')):.2f} dB normalised by the truth's "
                f"mean ({s['psnr_mean']:.2f} dB against its peak)"
            )
            c.print(f"contact sheet (truth | relit | error): {s['sheet']}")
            for w in s.get("warnings", []):
                c.print(f"[yellow]warning:[/] {escape(w)}", highlight=False)

        emit(s, json_out, human)
