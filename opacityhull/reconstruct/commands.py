"""CLI commands of `opacityhull.reconstruct` (registered by :mod:`opacityhull.cli`): ``build``."""

from __future__ import annotations

from pathlib import Path
from typing import List, Literal, Optional, cast

import typer

from ..cliutil import cli_errors, console, emit, option_group, progress_bar, scheduler_options, writing_to
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
    if summary["metrics"]:
        m = Table(title="metrics")
        m.add_column("metric")
        m.add_column("value", justify="right")
        for k, v in summary["metrics"].items():
            if isinstance(v, (dict, list)):
                continue
            m.add_row(k, f"{v:.4g}" if isinstance(v, float) else str(v))
        c.print(m)
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
            c.print(f"pair {k}: drift gain R,G,B = {', '.join(f'{g:.3f}' for g in s['gain'])}; registration {shift}")
    for n in summary.get("notes", []):
        c.print(f"[yellow]note:[/] {n}")


_BUILD_SCHEDULER = scheduler_options(
    "Where the per-view steps run: serial | threads | processes | "
    "tcp://HOST:PORT (a dask scheduler; see docs/distributed.md).",
    workers=True,
)


def register(app, groups) -> None:
    """Add this stage's commands to the root app and the subcommand groups."""

    @app.command("build")
    @cli_errors
    @option_group(_BUILD_SCHEDULER, into="executor", before="as_json")
    def build(
        session: Path = typer.Argument(..., help="Session folder (from `capture` or `import colmap`)."),
        out: Path = typer.Option(..., "--out", help="Model folder to write (created; existing files are replaced)."),
        hull_res: Optional[int] = typer.Option(
            None,
            "--hull-res",
            help="Voxels along the longest side of the hull's box (default: "
            "from the photographs' pixel footprint, one surfel per "
            "projected pixel).",
        ),
        matting_drift: str = typer.Option(
            "auto",
            "--matting-drift",
            help="Correct photometric drift and misregistration between backdrop and "
            "object shots: auto (field, except on a drift-free simulated rig) | "
            "none | gain | affine | field.",
        ),
        carve_tolerance: Optional[int] = typer.Option(
            None,
            "--carve-tolerance",
            help="A voxel survives when at most this many views reject "
            "it (imperfect masks). Default: 1 for imported sets "
            "of 8+ views, 0 for rig sessions.",
        ),
        refine: Optional[str] = typer.Option(
            None,
            "--refine",
            help="Photo-consistent depth inside the hull: shading (surfels stay "
            "on the hull and carry the depth the renderer shades at) | "
            "surfels (move the surfels there) | none. Default: "
            "BuildConfig.refine (shading).",
        ),
        ground_truth: bool = typer.Option(
            False,
            "--ground-truth",
            help="Compare with the simulator's groundtruth/ (alpha MAE, hull IoU, pose errors) and report the metrics.",
        ),
        alpha_threshold: Optional[float] = typer.Option(
            None, "--alpha-threshold", help="Silhouette = alpha > threshold (default: BuildConfig.alpha_threshold)."
        ),
        cameras: str = typer.Option(
            "auto",
            "--cameras",
            help="auto (calibration phase → calibration/ → cameras/), or for debugging only: groundtruth | nominal.",
        ),
        backdrops: str = typer.Option(
            "auto",
            "--backdrops",
            help="Matting backdrops: auto (object-absent captures, else predicted from "
            "the display geometry) | object-absent | geometry.",
        ),
        exclude_view: Optional[List[str]] = typer.Option(
            None, "--exclude-view", help="Leave a view out (repeatable), e.g. c0_t030.000."
        ),
        bounds: Optional[str] = typer.Option(
            None, "--bounds", help="Hull box x0,y0,z0,x1,y1,z1 in metres (object frame); default: from the silhouettes."
        ),
        oversample: Optional[int] = typer.Option(
            None, "--oversample", help="Surfel rays per voxel column per axis (default: BuildConfig.surfel_oversample)."
        ),
        max_alpha_std: Optional[float] = typer.Option(
            None,
            "--max-alpha-std",
            help="Matting: pixels whose predicted alpha std exceeds this "
            "are filled from their neighbours (default: "
            "MattingOptions.max_alpha_std).",
        ),
        require_all_cameras: bool = typer.Option(
            False,
            "--require-all-cameras",
            help="With a calibration phase: fail when a camera cannot be "
            "calibrated (default: leave it and its views out, with a "
            "note).",
        ),
        no_reflectance: bool = typer.Option(False, "--no-reflectance", help="Do not attach one-light images."),
        no_pictures: bool = typer.Option(False, "--no-pictures", help="Skip the PNG pictures."),
        storage: Optional[str] = typer.Option(
            None,
            "--storage",
            help="Pixel type of the model's view and reflectance EXRs: half (16-bit, half "
            "the bytes; values beyond 65504 are clamped and listed in the report) | float "
            "(32-bit). Default: BuildConfig.storage (half).",
        ),
        reflectance_storage: Optional[str] = typer.Option(
            None,
            "--reflectance-storage",
            help="How the model stores the one-light images: layers (one EXR layer per "
            "light) | pca (a PCA per pixel block of each view, error and ranks in the report; readers get "
            "the layers back). Default: BuildConfig.reflectance_storage (layers).",
        ),
        pca_error: Optional[float] = typer.Option(
            None,
            "--pca-error",
            help="With --reflectance-storage pca: per view the fewest components over its "
            "blocks whose relative Frobenius error is at most this (default: "
            "BuildConfig.pca_error, 0.01).",
        ),
        pca_rank: Optional[int] = typer.Option(
            None,
            "--pca-rank",
            help="With --reflectance-storage pca: this rank for every block (instead of --pca-error).",
        ),
        pca_block: Optional[int] = typer.Option(
            None,
            "--pca-block",
            help="With --reflectance-storage pca: one PCA per block of this many pixels "
            "square; 0 = one PCA per view (default: BuildConfig.pca_block, 8).",
        ),
        memory_gb: Optional[float] = typer.Option(
            None,
            "--memory-gb",
            help="Memory budget of the build, GB (default: a quarter of the RAM). Every "
            "per-view step reads, processes and writes one view at a time; the budget caps "
            "the views matted at once on --scheduler threads|processes (fewer than --workers "
            "when one view's images would not fit) and the views the carve stacks at once. "
            "The model does not depend on it; report.json gives memory_budget_gb and "
            "peak_rss_mb.",
        ),
        resume: bool = typer.Option(
            False,
            "--resume",
            help="Reuse the steps of an earlier (or interrupted) build into --out whose "
            "inputs and options are unchanged (OUT/build/manifest.json); the report "
            "says which steps were reused.",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
        *,
        executor: dict,
    ):
        """Build the opacity hull of a session: cameras, matting, visual hull, surfels,
        visibility, per-view RGBA and reflectance, pictures (and ground-truth metrics)."""
        from ..executor import open_executor, parse_scheduler
        from .build import DRIFT_MODES, BuildConfig, build_model
        from .matting import MattingOptions

        parse_scheduler(executor["scheduler"])
        check_build_paths(session, out)
        from .build import check_memory_gb

        if memory_gb is not None:
            check_memory_gb(memory_gb)  # exit 2 naming --memory-gb, before any work

        if matting_drift not in DRIFT_MODES:
            raise ConfigError(f"--matting-drift {matting_drift!r}: expected one of {', '.join(DRIFT_MODES)}")
        if refine is not None and refine not in ("shading", "surfels", "none"):
            raise ConfigError(f"--refine {refine!r}: expected shading, surfels or none")
        if storage is not None and storage not in ("half", "float"):
            raise ConfigError(f"--storage {storage!r}: expected half or float")
        if reflectance_storage is not None and reflectance_storage not in ("layers", "pca"):
            raise ConfigError(f"--reflectance-storage {reflectance_storage!r}: expected layers or pca")
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
        matting = MattingOptions(max_alpha_std=dm.max_alpha_std if max_alpha_std is None else max_alpha_std)
        cfg = BuildConfig(
            hull_res=hull_res,
            carve_tolerance=carve_tolerance,
            matting_drift=matting_drift,
            cameras=cameras,
            backdrops=backdrops,
            alpha_threshold=d.alpha_threshold if alpha_threshold is None else alpha_threshold,
            surfel_oversample=d.surfel_oversample if oversample is None else oversample,
            exclude_views=tuple(exclude_view or ()),
            bounds_m=_parse_bounds(bounds),
            matting=matting,
            reflectance=not no_reflectance,
            pictures=not no_pictures,
            drop_uncalibrated_cameras=not require_all_cameras,
            refine=d.refine if refine is None else cast(Literal["shading", "surfels", "none"], refine),
            storage=d.storage if storage is None else cast(Literal["half", "float"], storage),
            reflectance_storage=(
                d.reflectance_storage
                if reflectance_storage is None
                else cast(Literal["layers", "pca"], reflectance_storage)
            ),
            pca_rank=pca_rank,
            pca_error=d.pca_error if pca_error is None else pca_error,
            pca_block=d.pca_block if pca_block is None else (pca_block or None),
        )
        with progress_bar("build: {task.description}") as bar:
            # one bar line per step: its description names the step, its count and ETA
            # are the step's (views matted, images calibrated, ...). A new task per step:
            # rich's update() ignores total=None, so resetting one task left the previous
            # step's "0/24" on every later step.
            tasks = [bar.add_task("start", total=None)]

            def on_step(name: str) -> None:
                bar.remove_task(tasks[-1])
                tasks.append(bar.add_task(name, total=None))

            def prog(done: int, total: int | None = None) -> None:
                bar.update(tasks[-1], completed=done, total=total)

            with open_executor(**executor) as ex, writing_to(out):
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
            bar.update(tasks[-1], description="done")
        summary = report.summary()
        summary["notes"] = list(report.notes)
        emit(summary, as_json, _human)

    @app.command("matte", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
    @cli_errors
    def matte(
        ctx: typer.Context,
        out: Path = typer.Option(
            ...,
            "--out",
            help="Folder to write alpha.png, foreground_premul.png/.exr, composite.png and matte.json (created).",
        ),
        over: Optional[Path] = typer.Option(None, "--over", help="New background for composite.png."),
        drift: str = typer.Option(
            "field",
            "--drift",
            help="Photometric drift correction of the backdrops: field (smooth per-channel "
            "gain over the frame) | affine (3x3 + offset) | gain | none.",
        ),
        max_alpha_std: Optional[float] = typer.Option(
            None,
            "--max-alpha-std",
            help="Pixels whose predicted alpha std exceeds this are "
            "filled from their neighbours (default: "
            "MattingOptions.max_alpha_std).",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
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
