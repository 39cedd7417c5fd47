"""CLI commands of `opacityhull.reconstruct` (registered by :mod:`opacityhull.cli`): ``build``."""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Literal, get_args
from collections.abc import Iterator

import typer

from ..cliutil import JsonFlag, option_group, scheduler_options
from ..cliutil import check_choice, cli_errors, console, emit, flag_names, step_progress, writing_to
from ..errors import ConfigError

__all__ = ["register"]


def _parse_bounds(text: str | None):
    if text is None:
        return None
    try:
        v = [float(x) for x in text.replace(" ", "").split(",")]
    except ValueError:
        raise ConfigError(f"--bounds {text!r}: expected six numbers x0,y0,z0,x1,y1,z1 (metres)") from None
    if len(v) != 6:
        raise ConfigError(f"--bounds {text!r}: expected six numbers x0,y0,z0,x1,y1,z1 (metres), got {len(v)}")
    return (tuple(v[:3]), tuple(v[3:]))


def _human(summary: dict) -> None:
    from rich.markup import escape
    from rich.table import Table

    c = console()
    t = Table(title=f"model {summary['model']}: {summary['views']} views, {summary['surfels']} surfels")
    t.add_column("step")
    t.add_column("seconds", justify="right")
    for k, v in summary["seconds"].items():
        t.add_row(k, f"{v:.2f}")
    c.print(t)
    opt = summary.get("optimize") or {}
    if opt.get("mode", "none") != "none":
        c.print(
            f"optimize {opt['mode']}: {opt.get('iterations')} iterations"
            + (f", {opt['ms_per_iteration']:.1f} ms each" if opt.get("ms_per_iteration") is not None else " (reused)")
            + ", "
            f"training PSNR {opt.get('train_psnr_last', float('nan')):.2f} dB, {opt.get('n_surfels_end')} splats "
            "(loss curve in report.json; `eval test` scores the held-out views from them)",
            markup=False,
        )
    if summary["metrics"]:
        checks = summary["metrics"].get("ground_truth_checks") or {}
        m = Table(title="metrics" + (" (against the ground truth: bounds in reconstruct/metrics.py)" if checks else ""))
        m.add_column("metric")
        m.add_column("value", justify="right")
        if checks:
            m.add_column("bound")
            m.add_column("", justify="center")
        for k, v in summary["metrics"].items():
            if isinstance(v, (dict, list)):
                continue
            row = [k, f"{v:.4g}" if isinstance(v, float) else str(v)]
            if checks:
                ch = checks.get(k)
                verdict = "" if ch is None or ch["ok"] is None else ("[green]✓[/]" if ch["ok"] else "[red]✗[/]")
                row += [escape(ch["bound"]) if ch else "", verdict]
            m.add_row(*row)
        c.print(m)
        failed = [k for k, ch in checks.items() if ch["ok"] is False]
        for k in failed:
            c.print(
                f"[red]✗[/] {k} = {checks[k]['value']:.4g}, bound {escape(checks[k]['bound'])}: {escape(checks[k]['why'])}"
            )
    c.print(f"cameras: {summary['camera_source']}; backdrops: {summary['backdrop_source']}")
    reused = {k: v for k, v in (summary.get("steps") or {}).items() if v != "ran"}
    if reused:
        c.print("resumed: " + ", ".join(f"{k} {v}" for k, v in reused.items()), markup=False)
    res = summary.get("resolution") or {}
    if res:
        c.print(f"hull resolution {res['hull_res']}, oversample {res['oversample']}: {res['reason']}", markup=False)
    for n in summary.get("notes", []):
        c.print(f"[yellow]note:[/] {escape(str(n))}")
    c.print(f"pictures: {Path(summary['model']) / 'pictures'}")


def check_build_paths(session: Path, out: Path) -> None:
    """Reject ``build SESSION --out OUT`` before any work when OUT cannot be the model
    folder: an existing file, the session folder itself, or a folder inside it (the model
    would be written among the photographs), or a session path that is not there."""
    from ..errors import InputError, check_writable

    if not session.exists():
        raise InputError(f"{session}: no such session folder")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is an existing file, expected a model folder (new, or an earlier model)")
    s, o = session.resolve(), out.resolve()
    if o == s:
        raise InputError(f"--out {out}: is the session folder {session}; give a separate model folder")
    if s in o.parents:
        raise InputError(f"--out {out}: is inside the session folder {session}; give a folder outside it")
    if o in s.parents:
        raise InputError(f"--out {out}: contains the session folder {session}; the build would write over it")
    for p in (o, *o.parents):
        if p.exists():
            if (p / "session.toml").is_file() or (p / "manifest.jsonl").is_file():
                raise InputError(f"--out {out}: is inside another session folder {p}")
            break
    check_writable(out)


#: BuildConfig / MattingOptions fields as `build`'s flags name them (for messages).
BUILD_FLAGS = {
    "hull_res": "--hull-res",
    "bounds_m": "--bounds",
    "alpha_threshold": "--alpha-threshold",
    "carve_tolerance": "--carve-tolerance",
    "exclude_views": "--exclude-view",
    "hold_out": "--hold-out",
    "optimize": "--optimize",
    "optimize_iterations": "--optimize-iterations",
    "surfel_oversample": "--oversample",
    "matting max_alpha_std": "--max-alpha-std",
    "max_alpha_std": "--max-alpha-std",
    "matting_drift": "--matting-drift",
    "pca_error": "--pca-error",
    "pca_rank": "--pca-rank",
    "pca_block": "--pca-block",
}


@contextmanager
def _terminated_says_resume() -> Iterator[None]:
    """A SIGTERM'd (or SIGHUP'd) build exited 143 without a word: say how to go on, as
    ``capture`` does. The exit code stays 128 + the signal (cli_errors)."""
    from ..cliutil import terminate_as_interrupt
    from ..errors import Terminated

    try:
        with terminate_as_interrupt():
            yield
    except Terminated as e:
        console().print(
            f"[yellow]{e}[/]: the steps finished so far are kept; `build --resume` continues", highlight=False
        )
        raise


def _parse_image_lists(args, flags) -> dict:
    """``--object A B --backdrop C D`` (one flag, several files; or the flag repeated)
    from the arguments click left over; anything else is an error naming it."""
    from ..errors import InputError

    lists = {f: [] for f in flags}
    cur = None
    for a in args:
        if a in lists:
            cur = a
        elif a.startswith("--") and "=" in a and a.split("=", 1)[0] in lists:
            cur = a.split("=", 1)[0]
            lists[cur].append(Path(a.split("=", 1)[1]))
        elif a.startswith("-") and len(a) > 1:
            raise InputError(
                f"unknown option {a!r} (expected one of {', '.join(flags)}, --out, --over, --drift, "
                "--max-alpha-std, --json)"
            )
        elif cur is None:
            raise InputError(f"{a!r}: give image files after {' or '.join(flags)}")
        else:
            lists[cur].append(Path(a))
    for f in flags:
        if not lists[f]:
            raise InputError(f"{f} is required: {f} A.jpg B.jpg ...")
    return lists


def _human_matte(summary: dict) -> None:
    c = console()
    c.print(f"matte {summary['width']}x{summary['height']} from {summary['pairs']} pairs → {summary['out']}")
    c.print(
        f"clear (alpha<0.05) {summary['clear_fraction']:.1%}, opaque (>0.95) {summary['opaque_fraction']:.1%}, "
        f"fractional {summary['fractional_fraction']:.1%}, unknown {summary['unknown_fraction']:.2%}"
    )
    if summary["drift"]:
        for k, s in enumerate(summary["drift"]["shots"]):
            sh = s["shift_px"]
            shift = (
                "n/a" if sh is None else f"({sh[0]:+.2f}, {sh[1]:+.2f}) px" + (" applied" if s["shift_applied"] else "")
            )
            fl = s.get("flow_px_p50")
            flow = "" if fl is None else f"; non-rigid flow median {fl:.2f} px (p99 {s['flow_px_p99']:.2f})"
            c.print(
                f"pair {k}: drift gain R,G,B = {', '.join(f'{g:.3f}' for g in s['gain'])}; registration {shift}{flow}"
            )
    for n in summary.get("notes", []):
        c.print(f"[yellow]note:[/] {n}")


#: ``--refine``: BuildConfig.refine's words (it also takes True/False, which the flag does not).
REFINE_MODES: tuple[Literal["shading", "surfels", "none"], ...] = ("shading", "surfels", "none")

_OUT_HELP = "Model folder to write (created; existing files are replaced)."
_HULL_RES_HELP = (
    "Voxels along the longest side of the hull's box (default: "
    "from the photographs' pixel footprint, one surfel per "
    "projected pixel)."
)
_MATTING_DRIFT_HELP = (
    "Correct photometric drift and misregistration between backdrop and "
    "object shots: auto (field, except on a drift-free simulated rig) | "
    "none | gain | affine | field."
)
_CARVE_HELP = (
    "A voxel survives when at most this many views reject "
    "it (imperfect masks). Default: for imported sets 1 "
    "from 8 views, 2 from 16; 0 for rig sessions."
)
_REFINE_HELP = (
    "Photo-consistent depth inside the hull: shading (surfels stay "
    "on the hull and carry the depth the renderer shades at) | "
    "surfels (move the surfels there) | none. Default: "
    "BuildConfig.refine (shading)."
)
_GROUND_TRUTH_HELP = (
    "Compare with the simulator's groundtruth/ (alpha MAE, hull IoU, pose errors) and report the metrics."
)
_ALPHA_HELP = "Silhouette = alpha > threshold (default: BuildConfig.alpha_threshold)."
_CAMERAS_HELP = "auto (calibration phase → calibration/ → cameras/), or for debugging only: groundtruth | nominal."
_BACKDROPS_HELP = (
    "Matting backdrops: auto (object-absent captures, else predicted from "
    "the display geometry) | object-absent | geometry."
)
_HOLD_OUT_HELP = (
    "Test views kept out of every step (hull, surfels, visibility, refinement, blending) but kept on record in "
    "the model, for `eval test`: every:N (views 0, N, 2N, ...) or a comma list of view ids or indices."
)
_OPTIMIZE_HELP = (
    "Fit the surfels to the training views by differentiable splatting (a resumable build step into "
    "MODEL/optimized/; `eval test` then renders the fitted splats): none, fast or full. Default fast; fast "
    "(900 steps at half resolution) measured +1.4 to +4.5 dB on held-out views over the unfitted model "
    "(templeSR, dinoSR, the simulated demo cup) in 0.5 to 2.5 minutes of steps."
)
_OPTIMIZE_MODES: tuple[Literal["none", "fast", "full"], ...] = ("none", "fast", "full")
_OPTIMIZE_ITERATIONS_HELP = "Iterations of the fit (default: the --optimize preset's; fast 900, full 3000)."
_EXCLUDE_HELP = "Leave a view out (repeatable), e.g. c0_t030.000."
_BOUNDS_HELP = "Hull box x0,y0,z0,x1,y1,z1 in metres (object frame); default: from the silhouettes."
_OVERSAMPLE_HELP = "Surfel rays per voxel column per axis (default: BuildConfig.surfel_oversample)."
# build's and matte's --max-alpha-std are the same option (MattingOptions.max_alpha_std)
_ALPHA_STD_HELP = (
    "pixels whose predicted alpha std exceeds this are filled from their neighbours "
    "(default: MattingOptions.max_alpha_std)."
)
_BUILD_ALPHA_STD_HELP = "Matting: " + _ALPHA_STD_HELP
_MATTE_ALPHA_STD_HELP = _ALPHA_STD_HELP[0].upper() + _ALPHA_STD_HELP[1:]
_REQUIRE_ALL_HELP = (
    "With a calibration phase: fail when a camera cannot be "
    "calibrated (default: leave it and its views out, with a "
    "note)."
)
_NO_REFLECTANCE_HELP = "Do not attach one-light images."
_STORAGE_HELP = (
    "Pixel type of the model's view and reflectance EXRs: half (16-bit, half "
    "the bytes; values beyond 65504 are clamped and listed in the report) | float "
    "(32-bit). Default: BuildConfig.storage (half)."
)
_REFLECTANCE_STORAGE_HELP = (
    "How the model stores the one-light images: layers (one EXR layer per "
    "light) | pca (a PCA per pixel block of each view, error and ranks in the report; readers get "
    "the layers back). Default: BuildConfig.reflectance_storage (layers)."
)
_PCA_ERROR_HELP = (
    "With --reflectance-storage pca: per view the fewest components over its "
    "blocks whose relative Frobenius error is at most this (default: "
    "BuildConfig.pca_error, 0.01)."
)
_PCA_RANK_HELP = "With --reflectance-storage pca: this rank for every block (instead of --pca-error)."
_PCA_BLOCK_HELP = (
    "With --reflectance-storage pca: one PCA per block of this many pixels "
    "square; 0 = one PCA per view (default: BuildConfig.pca_block, 8)."
)
_MEMORY_HELP = (
    "Memory budget of the build, GB (default: a quarter of the RAM). Every "
    "per-view step reads, processes and writes one view at a time; the budget caps "
    "the views matted at once on --scheduler threads|processes (fewer than --workers "
    "when one view's images would not fit) and the views the carve stacks at once. "
    "The model does not depend on it; report.json gives memory_budget_gb and "
    "peak_rss_mb."
)
_RESUME_HELP = (
    "Reuse the steps of an earlier (or interrupted) build into --out whose "
    "inputs and options are unchanged (OUT/build/manifest.json); the report "
    "says which steps were reused."
)
_MATTE_OUT_HELP = "Folder to write alpha.png, foreground_premul.png/.exr, composite.png and matte.json (created)."
_DRIFT_HELP = (
    "Photometric drift correction of the backdrops: field (smooth per-channel "
    "gain over the frame) | affine (3x3 + offset) | gain | none."
)

_BUILD_SCHEDULER = scheduler_options(
    "Where the per-view steps run: serial | threads | processes | "
    "tcp://HOST:PORT (a dask scheduler; see docs/distributed.md).",
    workers=True,
)


def register(app, groups) -> None:
    """Add ``build`` and ``matte`` to the root app."""

    @app.command("build")
    @cli_errors
    @option_group(_BUILD_SCHEDULER, into="executor", before="as_json")
    def build(
        session: Annotated[Path, typer.Argument(help="Session folder (from `capture` or `import colmap`).")],
        out: Annotated[Path, typer.Option("--out", help=_OUT_HELP)],
        hull_res: Annotated[int | None, typer.Option("--hull-res", help=_HULL_RES_HELP)] = None,
        matting_drift: Annotated[str, typer.Option("--matting-drift", help=_MATTING_DRIFT_HELP)] = "auto",
        carve_tolerance: Annotated[int | None, typer.Option("--carve-tolerance", help=_CARVE_HELP)] = None,
        refine: Annotated[str | None, typer.Option("--refine", help=_REFINE_HELP)] = None,
        ground_truth: Annotated[bool, typer.Option("--ground-truth", help=_GROUND_TRUTH_HELP)] = False,
        alpha_threshold: Annotated[float | None, typer.Option("--alpha-threshold", help=_ALPHA_HELP)] = None,
        cameras: Annotated[str, typer.Option("--cameras", help=_CAMERAS_HELP)] = "auto",
        backdrops: Annotated[str, typer.Option("--backdrops", help=_BACKDROPS_HELP)] = "auto",
        exclude_view: Annotated[list[str] | None, typer.Option("--exclude-view", help=_EXCLUDE_HELP)] = None,
        hold_out: Annotated[str | None, typer.Option("--hold-out", help=_HOLD_OUT_HELP)] = None,
        optimize: Annotated[str, typer.Option("--optimize", help=_OPTIMIZE_HELP)] = "fast",
        optimize_iterations: Annotated[
            int | None, typer.Option("--optimize-iterations", help=_OPTIMIZE_ITERATIONS_HELP)
        ] = None,
        bounds: Annotated[str | None, typer.Option("--bounds", help=_BOUNDS_HELP)] = None,
        oversample: Annotated[int | None, typer.Option("--oversample", help=_OVERSAMPLE_HELP)] = None,
        max_alpha_std: Annotated[float | None, typer.Option("--max-alpha-std", help=_BUILD_ALPHA_STD_HELP)] = None,
        require_all_cameras: Annotated[bool, typer.Option("--require-all-cameras", help=_REQUIRE_ALL_HELP)] = False,
        no_reflectance: Annotated[bool, typer.Option("--no-reflectance", help=_NO_REFLECTANCE_HELP)] = False,
        no_pictures: Annotated[bool, typer.Option("--no-pictures", help="Skip the PNG pictures.")] = False,
        storage: Annotated[str | None, typer.Option("--storage", help=_STORAGE_HELP)] = None,
        reflectance_storage: Annotated[
            str | None, typer.Option("--reflectance-storage", help=_REFLECTANCE_STORAGE_HELP)
        ] = None,
        pca_error: Annotated[float | None, typer.Option("--pca-error", help=_PCA_ERROR_HELP)] = None,
        pca_rank: Annotated[int | None, typer.Option("--pca-rank", help=_PCA_RANK_HELP)] = None,
        pca_block: Annotated[int | None, typer.Option("--pca-block", help=_PCA_BLOCK_HELP)] = None,
        memory_gb: Annotated[float | None, typer.Option("--memory-gb", help=_MEMORY_HELP)] = None,
        resume: Annotated[bool, typer.Option("--resume", help=_RESUME_HELP)] = False,
        as_json: JsonFlag = False,
        *,
        executor: dict,
    ):
        """Build the opacity hull of a session: cameras, matting, visual hull, surfels,
        visibility, per-view RGBA and reflectance, pictures (and ground-truth metrics)."""
        from ..executor import open_executor, parse_scheduler
        from ..model import Storage
        from ..reflectance_pca import ReflectanceStorage
        from .build import DRIFT_MODES, BuildConfig, build_model
        from .matting import MattingOptions

        parse_scheduler(executor["scheduler"])
        check_build_paths(session, out)
        from .build import check_memory_gb

        if memory_gb is not None:
            check_memory_gb(memory_gb)  # exit 2 naming --memory-gb, before any work

        drift_mode = check_choice("--matting-drift", matting_drift, DRIFT_MODES, one_of=True, error=ConfigError)
        refine_mode = check_choice("--refine", refine, REFINE_MODES, error=ConfigError)
        optimize_mode = check_choice("--optimize", optimize, _OPTIMIZE_MODES, error=ConfigError)
        if optimize_iterations is not None and optimize_iterations < 1:
            raise ConfigError(f"--optimize-iterations {optimize_iterations}: expected a count >= 1")
        storage_type = check_choice("--storage", storage, get_args(Storage), error=ConfigError)
        refl_storage = check_choice(
            "--reflectance-storage", reflectance_storage, get_args(ReflectanceStorage), error=ConfigError
        )
        if pca_rank is not None and pca_error is not None:
            raise ConfigError("--pca-rank and --pca-error: give one (a fixed rank, or the error that chooses it)")
        if (pca_rank is not None or pca_error is not None or pca_block is not None) and reflectance_storage != "pca":
            raise ConfigError("--pca-rank / --pca-error / --pca-block need --reflectance-storage pca")
        if pca_block is not None and (pca_block < 0 or pca_block == 1):
            raise ConfigError(f"--pca-block {pca_block}: expected 0 (one PCA per view) or an edge of >= 2 pixels")
        if pca_rank is not None and pca_rank < 1:
            raise ConfigError(f"--pca-rank {pca_rank}: expected an integer >= 1")
        if pca_error is not None and not 0.0 < pca_error < 1.0:
            raise ConfigError(f"--pca-error {pca_error}: expected a relative error in (0, 1), e.g. 0.01")
        # options left out keep the config dataclasses' defaults (one place for them)
        d, dm = BuildConfig(), MattingOptions()
        with flag_names(BUILD_FLAGS):
            matting = MattingOptions(max_alpha_std=dm.max_alpha_std if max_alpha_std is None else max_alpha_std)
            cfg = _build_config(
                d,
                hull_res=hull_res,
                carve_tolerance=carve_tolerance,
                drift_mode=drift_mode,
                cameras=cameras,
                backdrops=backdrops,
                alpha_threshold=alpha_threshold,
                oversample=oversample,
                exclude_view=exclude_view,
                hold_out=hold_out,
                bounds=bounds,
                matting=matting,
                no_reflectance=no_reflectance,
                no_pictures=no_pictures,
                require_all_cameras=require_all_cameras,
                refine_mode=refine_mode,
                storage_type=storage_type,
                refl_storage=refl_storage,
                pca_rank=pca_rank,
                pca_error=pca_error,
                pca_block=pca_block,
            )
            cfg = replace(cfg, optimize=optimize_mode, optimize_iterations=optimize_iterations)
        with (
            step_progress("build") as (on_step, prog),
            flag_names(BUILD_FLAGS),
            _terminated_says_resume(),
            open_executor(**executor) as ex,
            writing_to(out),
        ):
            report = build_model(
                session,
                out,
                config=cfg,
                ground_truth=ground_truth,
                progress=prog,
                on_step=on_step,
                resume=resume,
                executor=ex,
                memory_gb=memory_gb,
            )
        summary = report.summary()
        summary["notes"] = list(report.notes)
        emit(summary, as_json, _human)

    def _build_config(
        d,
        *,
        hull_res,
        carve_tolerance,
        drift_mode,
        cameras,
        backdrops,
        alpha_threshold,
        oversample,
        exclude_view,
        hold_out,
        bounds,
        matting,
        no_reflectance,
        no_pictures,
        require_all_cameras,
        refine_mode,
        storage_type,
        refl_storage,
        pca_rank,
        pca_error,
        pca_block,
    ):
        from .build import BuildConfig

        return BuildConfig(
            hull_res=hull_res,
            carve_tolerance=carve_tolerance,
            matting_drift=drift_mode,
            cameras=cameras,
            backdrops=backdrops,
            alpha_threshold=d.alpha_threshold if alpha_threshold is None else alpha_threshold,
            surfel_oversample=d.surfel_oversample if oversample is None else oversample,
            exclude_views=tuple(exclude_view or ()),
            hold_out=hold_out,
            bounds_m=_parse_bounds(bounds),
            matting=matting,
            reflectance=not no_reflectance,
            pictures=not no_pictures,
            drop_uncalibrated_cameras=not require_all_cameras,
            refine=d.refine if refine_mode is None else refine_mode,
            storage=d.storage if storage_type is None else storage_type,
            reflectance_storage=d.reflectance_storage if refl_storage is None else refl_storage,
            pca_rank=pca_rank,
            pca_error=d.pca_error if pca_error is None else pca_error,
            pca_block=d.pca_block if pca_block is None else (pca_block or None),
        )

    @app.command("matte", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
    @cli_errors
    def matte(
        ctx: typer.Context,
        out: Annotated[Path, typer.Option("--out", help=_MATTE_OUT_HELP)],
        over: Annotated[Path | None, typer.Option("--over", help="New background for composite.png.")] = None,
        drift: Annotated[str, typer.Option("--drift", help=_DRIFT_HELP)] = "field",
        max_alpha_std: Annotated[float | None, typer.Option("--max-alpha-std", help=_MATTE_ALPHA_STD_HELP)] = None,
        as_json: JsonFlag = False,
    ):
        """Triangulation matting of your own shots: --object A.jpg B.jpg [...] --backdrop A.jpg
        B.jpg [...] (pair k = object k in front of backdrop k, backdrop k alone; at least 2
        pairs of the same view). JPEG/PNG are decoded from sRGB to linear."""
        from .matte_files import matte_files

        lists = _parse_image_lists(ctx.args, ("--object", "--backdrop"))
        summary = matte_files(
            lists["--object"], lists["--backdrop"], out, over=over, drift=drift, max_alpha_std=max_alpha_std
        )
        emit(summary, as_json, _human_matte)
