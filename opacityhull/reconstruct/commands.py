"""CLI commands of `opacityhull.reconstruct` (registered by :mod:`opacityhull.cli`): ``build``."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..cliutil import cli_errors, console, emit
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
    res = summary.get("resolution") or {}
    if res:
        c.print(f"hull resolution {res['hull_res']}, oversample {res['oversample']}: {res['reason']}", markup=False)
    for n in summary.get("notes", []):
        c.print(f"[yellow]note:[/] {n}")
    c.print(f"pictures: {Path(summary['model']) / 'pictures'}")


def register(app, groups) -> None:
    """Add this stage's commands to the root app and the subcommand groups."""

    @app.command("build")
    @cli_errors
    def build(
        session: Path = typer.Argument(..., help="Session folder (from `capture` or `import colmap`)."),
        out: Path = typer.Option(..., "--out", help="Model folder to write (created; existing files are replaced)."),
        hull_res: Optional[int] = typer.Option(None, "--hull-res",
                                               help="Voxels along the longest side of the hull's box (default: "
                                                    "from the photographs' pixel footprint, one surfel per "
                                                    "projected pixel)."),
        carve_tolerance: Optional[int] = typer.Option(None, "--carve-tolerance",
                                                      help="A voxel survives when at most this many views reject "
                                                           "it (imperfect masks). Default: 1 for imported sets "
                                                           "of 8+ views, 0 for rig sessions."),
        ground_truth: bool = typer.Option(False, "--ground-truth",
                                          help="Compare with the simulator's groundtruth/ (alpha MAE, hull IoU, "
                                               "pose errors) and report the metrics."),
        alpha_threshold: float = typer.Option(0.5, "--alpha-threshold", help="Silhouette = alpha > threshold."),
        cameras: str = typer.Option("auto", "--cameras",
                                    help="auto (calibration phase → calibration/ → cameras/), or for debugging "
                                         "only: groundtruth | nominal."),
        backdrops: str = typer.Option("auto", "--backdrops",
                                      help="Matting backdrops: auto (object-absent captures, else predicted from "
                                           "the display geometry) | object-absent | geometry."),
        exclude_view: Optional[List[str]] = typer.Option(None, "--exclude-view",
                                                         help="Leave a view out (repeatable), e.g. c0_t030.000."),
        bounds: Optional[str] = typer.Option(None, "--bounds",
                                             help="Hull box x0,y0,z0,x1,y1,z1 in metres (object frame); "
                                                  "default: from the silhouettes."),
        oversample: int = typer.Option(1, "--oversample", help="Surfel rays per voxel column per axis."),
        max_alpha_std: float = typer.Option(0.05, "--max-alpha-std",
                                            help="Matting: pixels whose predicted alpha std exceeds this are "
                                                 "filled from their neighbours."),
        require_all_cameras: bool = typer.Option(False, "--require-all-cameras",
                                                 help="With a calibration phase: fail when a camera cannot be "
                                                      "calibrated (default: leave it and its views out, with a "
                                                      "note)."),
        no_reflectance: bool = typer.Option(False, "--no-reflectance", help="Do not attach one-light images."),
        no_pictures: bool = typer.Option(False, "--no-pictures", help="Skip the PNG pictures."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
    ):
        """Build the opacity hull of a session: cameras, matting, visual hull, surfels,
        visibility, per-view RGBA and reflectance, pictures (and ground-truth metrics)."""
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        from .build import BuildConfig, build_model
        from .matting import MattingOptions

        cfg = BuildConfig(hull_res=hull_res, carve_tolerance=carve_tolerance, alpha_threshold=alpha_threshold, cameras=cameras, backdrops=backdrops,
                          exclude_views=tuple(exclude_view or ()), bounds_m=_parse_bounds(bounds),
                          surfel_oversample=oversample, matting=MattingOptions(max_alpha_std=max_alpha_std),
                          reflectance=not no_reflectance, pictures=not no_pictures,
                          drop_uncalibrated_cameras=not require_all_cameras)
        with Progress(TextColumn("[bold]build: {task.description}"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("elapsed"), TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
                      console=console(), transient=False) as bar:
            # one bar for the whole build: its description names the step, its count and
            # ETA are the step's (views matted, images calibrated, files written, ...)
            task = bar.add_task("start", total=None)

            def on_step(name: str) -> None:
                bar.update(task, description=name, completed=0, total=None)

            def prog(done: int, total: int | None = None) -> None:
                bar.update(task, completed=done, total=total)

            report = build_model(session, out, config=cfg, ground_truth=ground_truth, progress=prog,
                                 on_step=on_step)
            bar.update(task, description="done")
        summary = report.summary()
        summary["notes"] = list(report.notes)
        emit(summary, as_json, _human)
