"""CLI commands of `opacityhull.render` (registered by :mod:`opacityhull.cli`):
``opacityhull render`` and ``opacityhull eval loo``."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..cliutil import cli_errors, console, emit, option_group, progress, scheduler_options, writing_to
from ..errors import InputError
from .config import RenderConfig

_D = RenderConfig()


def _config(k, filter_var, epsilon_z, cutoff, sigma_radius, shading=_D.shading):
    if shading not in ("pixel", "surfel"):
        from ..errors import InputError

        raise InputError(f"--shading {shading!r}: expected pixel or surfel")
    return RenderConfig(
        k=k, filter=filter_var, epsilon_z=epsilon_z, cutoff_sigma=cutoff, sigma_radius=sigma_radius, shading=shading
    )


_K_HELP = "ULR neighbourhood: the k nearest visible views by angle (k-1 blend; the k-th is the threshold)."
_FILTER_HELP = "EWA low-pass prefilter variance in px² (H = FILTER·I); 0 disables it."
_EPS_HELP = "ε-z-buffer tolerance in surfel radii: fragments this close behind the front-most one blend."
_CUTOFF_HELP = "Evaluate each EWA kernel within this Mahalanobis radius."
_SIGMA_HELP = "Tangent-plane Gaussian σ as a fraction of the surfel radius."
_SHADING_HELP = (
    "pixel: ULR per pixel at the back-projected surface point, colour and alpha from the blended mattes "
    "| surfel: ULR per surfel, splatted."
)

#: The flags of ``render`` and ``eval loo`` that make their RenderConfig (see :func:`_config`).
_RENDER_OPTIONS = {
    "k": (int, typer.Option(_D.k, "--k", help=_K_HELP)),
    "filter_var": (float, typer.Option(_D.filter, "--filter", help=_FILTER_HELP)),
    "epsilon_z": (float, typer.Option(_D.epsilon_z, "--epsilon-z", help=_EPS_HELP)),
    "cutoff": (float, typer.Option(_D.cutoff_sigma, "--cutoff", help=_CUTOFF_HELP)),
    "sigma_radius": (float, typer.Option(_D.sigma_radius, "--sigma-radius", help=_SIGMA_HELP)),
    "shading": (str, typer.Option(_D.shading, "--shading", help=_SHADING_HELP)),
}


#: Largest image ``render`` makes (64 Mpx: 8192 x 8192). The renderer keeps several float
#: buffers per pixel; 100000 px wide asked for 196 GiB and died in the allocator.
MAX_RENDER_PIXELS = 8192 * 8192

BACKGROUND_KINDS = ("auto", "image", "envmap")


_SCHEDULER_HELP = (
    "Where per-view work runs: serial | threads | processes | tcp://HOST:PORT (a dask scheduler; "
    "see docs/distributed.md)."
)
_LOO_SCHEDULER = scheduler_options(
    _SCHEDULER_HELP + " With --holdout geometry|both the geometry rebuilds (the costly part) run there; "
    "the renders run here."
)


def open_model_arg(model: Path):
    """The model folder argument, opened; a path that is not there is bad input (exit 2)."""
    from ..errors import InputError
    from ..model import OpacityHullModel

    if not model.exists():
        raise InputError(f"{model}: no such model folder")
    if not model.is_dir():
        raise InputError(f"{model} is a file, expected a model folder (from `opacityhull build`)")
    return OpacityHullModel.open(model)


def check_render_args(
    model: Path,
    *,
    width=None,
    height=None,
    orbit=None,
    fps=12.0,
    background_kind="auto",
    exclude=(),
    out: Path | None = None,
    budget=None,
) -> None:
    """Reject bad ``render`` options before anything is rendered or written (exit 2),
    naming the flag, the value and what is expected."""
    import math

    from ..errors import InputError, check_writable

    for flag, v in (("--width", width), ("--height", height)):
        if v is not None and v < 1:
            raise InputError(f"{flag} {v}: expected a positive number of pixels")
    if budget is not None:
        from .runner import check_budget

        try:
            check_budget(budget)
        except InputError:
            raise InputError(f"--budget {budget}: expected a whole number of splats >= 1") from None
    if orbit is not None and orbit < 1:
        raise InputError(f"--orbit {orbit}: expected at least 1 frame")
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps {fps}: expected a frame rate > 0")
    if background_kind not in BACKGROUND_KINDS:
        raise InputError(f"--background-kind {background_kind!r}: expected one of {', '.join(BACKGROUND_KINDS)}")
    m = open_model_arg(model)
    if out is not None:
        check_writable(out)
    ref = m.views[0].camera
    w = int(width) if width else ref.width
    h = int(height) if height else (ref.height if not width else max(1, round(ref.height * w / ref.width)))
    if w * h > MAX_RENDER_PIXELS:
        raise InputError(
            f"--width/--height: {w} x {h} = {w * h / 1e6:.0f} Mpx is more than the "
            f"{MAX_RENDER_PIXELS / 1e6:.0f} Mpx limit (MAX_RENDER_PIXELS)"
        )
    if exclude:
        left = set(range(len(m.views)))
        for e in exclude:
            left.discard(int(e) if str(e).isdigit() else m.view_index(str(e)))
        if not left:
            raise InputError(
                f"--exclude-view: all {len(m.views)} views of {model} are excluded; nothing would be "
                "blended (a transparent black image)"
            )


def register(app, groups) -> None:
    """Add ``render`` to the root app and ``loo`` to the ``eval`` group."""

    @app.command("render")
    @cli_errors
    @option_group(_RENDER_OPTIONS, into="render_options", before="background")
    @option_group(scheduler_options(_SCHEDULER_HELP), into="executor", before="json_out")
    def render_cmd(
        model: Path = typer.Argument(..., help="Model folder (model.toml, surfels.ply, views/)."),
        out: Path = typer.Option(
            ..., "--out", help="Output image: X.png or X.exr (orbits write X_000.png ... and X.gif)."
        ),
        view: Optional[str] = typer.Option(
            None,
            "--view",
            help="CAM,TABLE_DEG: captured camera CAM with the table at TABLE_DEG "
            "(any angle; captured views are reproduced exactly). Default: the first view.",
        ),
        look_at: Optional[str] = typer.Option(
            None,
            "--look-at",
            help="EX,EY,EZ,TX,TY,TZ[,FOV_DEG]: eye and target in the "
            "object frame (metres), vertical field of view (default: the cameras').",
        ),
        orbit: Optional[int] = typer.Option(
            None,
            "--orbit",
            help="N frames on a circle around the model at the captured "
            "cameras' mean elevation and distance; also writes an animated GIF.",
        ),
        background: Optional[str] = typer.Option(
            None,
            "--background",
            help="Composite over a colour (0.2,0.3,0.4 | 0.5 | "
            "#rrggbb | black | white | grey), an image, or an environment map "
            "(.hdr, or a 2:1 .exr). Without it, images keep their alpha.",
        ),
        background_kind: str = typer.Option("auto", "--background-kind", help="auto | image | envmap."),
        env_yaw_deg: float = typer.Option(
            0.0, "--env-yaw-deg", help="Rotate the environment map about +Y (ICT probes: 180)."
        ),
        yaw_deg_alias: Optional[float] = typer.Option(
            None, "--yaw-deg", hidden=True, help="Old name of --env-yaw-deg (relight's spelling)."
        ),
        width: Optional[int] = typer.Option(None, "--width", help="Output width in pixels (default: the views')."),
        height: Optional[int] = typer.Option(
            None, "--height", help="Output height in pixels (default: keeps the aspect)."
        ),
        exclude: List[str] = typer.Option([], "--exclude-view", help="View id or index not to blend (repeatable)."),
        exclude_alias: List[str] = typer.Option([], "--exclude", hidden=True, help="Old name of --exclude-view."),
        fps: float = typer.Option(12.0, "--fps", help="Frame rate of the orbit animation (> 0)."),
        budget: Optional[int] = typer.Option(
            None,
            "--budget",
            help="Draw at most N splats per frame: the finest "
            "view-dependent cut of the sequential point tree (the viewer's level "
            "of detail). Default: every surfel.",
        ),
        json_out: bool = typer.Option(
            False, "--json", help="Print a JSON summary (frames, paths, ms per frame) on stdout."
        ),
        *,
        render_options: dict,
        executor: dict,
    ):
        """Render a model from a captured view, a look-at camera, or an orbit (ULR-blended EWA surfel splatting)."""
        from ..executor import open_executor, parse_scheduler
        from .runner import run_render

        serial = parse_scheduler(executor["scheduler"]).kind == "serial"

        if yaw_deg_alias is not None:
            env_yaw_deg = yaw_deg_alias
        exclude = list(exclude) + list(exclude_alias)
        check_render_args(
            model,
            width=width,
            height=height,
            orbit=orbit,
            fps=fps,
            background_kind=background_kind,
            exclude=exclude,
            out=out,
            budget=budget,
        )

        from .cameras import parse_look_at, parse_view_spec

        given = [n for n, v in (("--view", view), ("--look-at", look_at), ("--orbit", orbit)) if v is not None]
        if len(given) > 1:
            raise InputError(f"give only one of --view, --look-at, --orbit (got {', '.join(given)})")
        if out.suffix.lower() not in (".png", ".exr"):
            raise InputError(f"--out {out}: expected a .png or .exr file name")
        view_t = parse_view_spec(view) if view is not None else None
        look_t = parse_look_at(look_at) if look_at is not None else None
        cfg = _config(**render_options)
        n = orbit if orbit is not None else 1
        # the frames render on the scheduler's workers (each opens the model from its path
        # and writes its frames beside --out); serial renders here, with no executor at all
        with (
            open_executor(**executor) as ex,
            progress("rendering", n, enabled=n > 1) as cb,
            writing_to(out),
        ):
            summary = run_render(
                model,
                out,
                view=view_t,
                look_at=look_t,
                orbit=orbit,
                width=width,
                height=height,
                config=cfg,
                background=background,
                background_kind=background_kind,
                env_yaw_deg=env_yaw_deg,
                exclude=exclude,
                fps=fps,
                budget=budget,
                progress=cb,
                executor=None if serial else ex,
            )

        def human(s):
            c = console()
            c.print(
                f"rendered {s['frames']} frame(s) {s['width']}x{s['height']}, {s['ms_per_frame']:.0f} ms/frame "
                f"({s['surfels']} surfels, k={s['k']})"
            )
            if s.get("budget") is not None:
                c.print(f"  budget {s['budget']} splats: drew {max(s['splats_per_frame'])} at most per frame")
            c.print(f"  {s['paths'][0]}" + (f" ... {s['paths'][-1]}" if len(s["paths"]) > 1 else ""))
            if "gif" in s:
                c.print(f"  animation: {s['gif']}")

        emit(summary, json_out, human)

    @groups["eval"].command("loo")
    @cli_errors
    @option_group(_RENDER_OPTIONS, into="render_options", before="out")
    @option_group(_LOO_SCHEDULER, into="executor", before="json_out")
    def loo_cmd(
        model: Path = typer.Argument(..., help="Model folder."),
        views: Optional[str] = typer.Option(
            None, "--views", help="all (default) | every:N | camera:C | comma list of view ids or indices."
        ),
        out: Optional[Path] = typer.Option(
            None,
            "--out",
            help="Folder for loo.json and loo_sheet.png (default "
            "./MODELNAME_loo in the current folder: an evaluation never writes into "
            "the model).",
        ),
        holdout: str = typer.Option(
            "blend",
            "--holdout",
            help="blend: leave the view out of the ULR blend only | geometry: also rebuild "
            "hull, surfels and visibility without it (honest, slower) | both.",
        ),
        json_out: bool = typer.Option(
            False, "--json", help="Print {views, psnr_mean, ssim_mean, alpha_mae, per_view} on stdout."
        ),
        *,
        render_options: dict,
        executor: dict,
    ):
        """Leave-one-out: render each chosen captured view without blending it, compare with its photograph
        (PSNR, SSIM, alpha MAE inside the union of the masks), and write a contact sheet photo | render | error."""
        from .evaluate import select_views  # noqa: F401  (fail fast on import errors)
        from .runner import run_loo

        open_model_arg(model)
        if out is None:
            # not MODEL/pictures: a model is an input here (it may be shared or read-only)
            out = Path(f"{model.resolve().name}_loo")
        cfg = _config(**render_options)
        if holdout not in ("blend", "geometry", "both"):
            raise InputError(f"--holdout {holdout!r}: expected blend, geometry or both")
        from ..executor import open_executor, parse_scheduler

        if parse_scheduler(executor["scheduler"]).kind != "serial" and holdout == "blend":
            raise InputError(
                f"--scheduler {executor['scheduler']}: with --holdout blend there is no per-view rebuild to "
                "distribute (the renders run in this process); use --holdout geometry|both, or "
                "--scheduler serial"
            )
        with open_executor(**executor) as ex, progress("leave-one-out", None) as cb:
            if holdout == "blend":
                summary = run_loo(model, views=views, config=cfg, out=out, progress=cb)
            else:
                # the CLI composes stages: the geometry holdout rebuilds the hull (reconstruct)
                from ..reconstruct.holdout import run_loo_holdouts

                summary = run_loo_holdouts(
                    model, views=views, config=cfg, holdout=holdout, out=out, progress=cb, executor=ex
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
            if "sheet" in s:
                c.print(f"  contact sheet: {s['sheet']}")
            c.print(f"  details: {s['json']}")

        emit(summary, json_out, human)
