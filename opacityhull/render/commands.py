"""CLI commands of `opacityhull.render` (registered by :mod:`opacityhull.cli`):
``opacityhull render`` (``eval loo`` is :mod:`opacityhull.evaluate.commands`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, get_args

import typer

from ..cliutil import ModelDirArg, env_yaw_options, flag_names, option_group, pick_env_yaw, scheduler_options
from ..cliutil import (
    check_choice,
    check_model_dir,
    check_orbit_fps,
    cli_errors,
    console,
    emit,
    progress,
    writing_to,
)
from ..errors import InputError
from ..outputs import check_output
from .config import RenderConfig, Shading

_D = RenderConfig()


def _config(k, filter_var, epsilon_z, cutoff, sigma_radius, shading=_D.shading):
    shading = check_choice("--shading", shading, get_args(Shading))
    with flag_names(RENDER_FLAGS):
        return RenderConfig(
            k=k, filter=filter_var, epsilon_z=epsilon_z, cutoff_sigma=cutoff, sigma_radius=sigma_radius, shading=shading
        )


#: RenderConfig's fields as the flags of `render` and `eval loo` name them (for messages).
RENDER_FLAGS = {
    f"{p}{k}": v
    for p in ("RenderConfig.", "")
    for k, v in {
        "k": "--k",
        "filter": "--filter",
        "epsilon_z": "--epsilon-z",
        "cutoff_sigma": "--cutoff",
        "sigma_radius": "--sigma-radius",
        "shading": "--shading",
    }.items()
    if p or len(k) > 1
}


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

_OUT_HELP = "Output image: X.png or X.exr (orbits write X_000.png ... and X.gif)."
_VIEW_HELP = (
    "CAM,TABLE_DEG: captured camera CAM with the table at TABLE_DEG "
    "(any angle; captured views are reproduced exactly). Default: the first view."
)
_LOOK_AT_HELP = (
    "EX,EY,EZ,TX,TY,TZ[,FOV_DEG]: eye and target in the "
    "object frame (metres), vertical field of view (default: the cameras')."
)
_ORBIT_HELP = (
    "N frames on a circle around the model at the captured "
    "cameras' mean elevation and distance; also writes an animated GIF."
)
_BACKGROUND_HELP = (
    "Composite over a colour (0.2,0.3,0.4 | 0.5 | "
    "#rrggbb | black | white | grey), an image, or an environment map "
    "(.hdr, or a 2:1 .exr; builtin:NAME for a shipped probe: ennis, grace, pisa, uffizi, wells). "
    "Without it, images keep their alpha."
)
_ENV_YAW_HELP = "Rotate the environment map about +Y. Default: 180 for builtin: probes, else 0."
_WIDTH_HELP = "Output width in pixels (default: the views')."
_HEIGHT_HELP = "Output height in pixels (default: keeps the aspect)."
_EXCLUDE_HELP = "View id or index not to blend (repeatable)."
_BUDGET_HELP = (
    "Draw at most N splats per frame: the finest "
    "view-dependent cut of the sequential point tree (the viewer's level "
    "of detail). Default: every surfel."
)
_JSON_HELP = "Print a JSON summary (frames, paths, ms per frame, renderer) on stdout."
_RENDERER_HELP = (
    "fitted: the splats of build --optimize (optimized/splats.ply) | ulr: the hull's surfels blended "
    "from the captured views | auto: fitted when the model has splats fitted from this build, else ulr."
)
_PRIMITIVES_HELP = (
    "splats: EWA splats only | hybrid: a surfel whose umbrella (PMR umbrella mesh) projects larger than "
    "--hybrid-px pixels is drawn as its triangles, the others as splats (close-ups; no --budget)."
)
_HYBRID_PX_HELP = "With --primitives hybrid: umbrella size in pixels above which a surfel is drawn as triangles."

_SCHEDULER_HELP = (
    "Where per-view work runs: serial | threads | processes | tcp://HOST:PORT (a dask scheduler; "
    "see docs/distributed.md)."
)


def open_model_arg(model: Path):
    """The model folder argument, opened; a path that is not there is bad input (exit 2)."""
    from ..model import OpacityHullModel

    check_model_dir(model)
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
    background: str | None = None,
) -> None:
    """Reject bad ``render`` options before anything is rendered or written (exit 2),
    naming the flag, the value and what is expected."""
    from ..errors import check_writable

    for flag, v in (("--width", width), ("--height", height)):
        if v is not None and v < 1:
            raise InputError(f"{flag} {v}: expected a positive number of pixels")
    if budget is not None:
        from .runner import check_budget

        try:
            check_budget(budget)
        except InputError:
            raise InputError(f"--budget {budget}: expected a whole number of splats >= 1") from None
    check_orbit_fps(orbit, fps)
    check_choice("--background-kind", background_kind, BACKGROUND_KINDS, one_of=True)
    m = open_model_arg(model)
    if out is not None:
        check_output(out, {"MODEL": model, "--background": background})
        check_writable(out)
    from .cameras import resize_camera

    # the largest frame any camera choice gives: captured views and orbits keep each
    # view's aspect (`--height` alone scales the width too), a look-at camera takes the
    # first view's width when only --height is given
    ref = m.views[0].camera
    sizes = [(c.width, c.height) for c in (resize_camera(v.camera, width, height) for v in m.views)]
    lw = int(width) if width else ref.width
    sizes.append(
        (lw, int(height) if height else (ref.height if not width else max(1, round(ref.height * lw / ref.width))))
    )
    w, h = max(sizes, key=lambda s: s[0] * s[1])
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
    """Add ``render`` to the root app."""

    @app.command("render")
    @cli_errors
    @option_group(_RENDER_OPTIONS, into="render_options", before="background")
    @option_group(env_yaw_options(None, _ENV_YAW_HELP), into="env_yaw_deg", before="width", build=pick_env_yaw)
    @option_group(scheduler_options(_SCHEDULER_HELP), into="executor", before="json_out")
    def render_cmd(
        model: ModelDirArg,
        out: Annotated[Path, typer.Option("--out", help=_OUT_HELP)],
        view: Annotated[str | None, typer.Option("--view", help=_VIEW_HELP)] = None,
        look_at: Annotated[str | None, typer.Option("--look-at", help=_LOOK_AT_HELP)] = None,
        orbit: Annotated[int | None, typer.Option("--orbit", help=_ORBIT_HELP)] = None,
        background: Annotated[str | None, typer.Option("--background", help=_BACKGROUND_HELP)] = None,
        background_kind: Annotated[str, typer.Option("--background-kind", help="auto | image | envmap.")] = "auto",
        width: Annotated[int | None, typer.Option("--width", help=_WIDTH_HELP)] = None,
        height: Annotated[int | None, typer.Option("--height", help=_HEIGHT_HELP)] = None,
        exclude: Annotated[list[str], typer.Option("--exclude-view", help=_EXCLUDE_HELP)] = [],  # noqa: B006  typer hands the body a fresh list; the body only reads it
        exclude_alias: Annotated[
            list[str], typer.Option("--exclude", hidden=True, help="Old name of --exclude-view.")
        ] = [],  # noqa: B006  typer hands the body a fresh list; the body only reads it
        fps: Annotated[float, typer.Option("--fps", help="Frame rate of the orbit animation (> 0).")] = 12.0,
        budget: Annotated[int | None, typer.Option("--budget", help=_BUDGET_HELP)] = None,
        renderer: Annotated[str, typer.Option("--renderer", help=_RENDERER_HELP)] = "auto",
        primitives: Annotated[str, typer.Option("--primitives", help=_PRIMITIVES_HELP)] = "splats",
        hybrid_px: Annotated[float, typer.Option("--hybrid-px", help=_HYBRID_PX_HELP)] = 2.0,
        json_out: Annotated[bool, typer.Option("--json", help=_JSON_HELP)] = False,
        *,
        render_options: dict,
        env_yaw_deg: float | None,
        executor: dict,
    ):
        """Render a model from a captured view, a look-at camera, or an orbit (ULR-blended EWA surfel splatting)."""
        from ..executor import open_executor, parse_scheduler
        from .runner import run_render

        serial = parse_scheduler(executor["scheduler"]).kind == "serial"

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
            background=background,
        )
        from .runner import check_primitives

        check_primitives(primitives, hybrid_px, budget)

        from .splats import resolve_renderer

        resolve_renderer(
            model,
            renderer,
            ulr_only=(
                ("--budget", budget is not None),
                ("--exclude-view", bool(exclude)),
                ("--primitives hybrid", primitives == "hybrid"),
            ),
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
                renderer=renderer,
                progress=cb,
                executor=None if serial else ex,
                primitives=primitives,
                hybrid_px=hybrid_px,
            )

        def human(s):
            c = console()
            c.print(
                f"rendered {s['frames']} frame(s) {s['width']}x{s['height']}, {s['ms_per_frame']:.0f} ms/frame "
                + (
                    f"({s['surfels']} fitted splats)"
                    if s["renderer"] == "fitted"
                    else f"({s['surfels']} surfels, k={s['k']})"
                )
                + f"; warm-up {s['ms_warmup']:.0f} ms and model load "
                f"{s['ms_load']:.0f} ms apart"
            )
            if s.get("budget") is not None:
                c.print(f"  budget {s['budget']} splats: drew {max(s['splats_per_frame'])} at most per frame")
            if s.get("primitives") == "hybrid":
                c.print(
                    f"  hybrid (> {s['hybrid_px']:g} px: triangles): {max(s['triangles_per_frame'])} triangles and "
                    f"{max(s['splats_per_frame'])} splats at most per frame; umbrella mesh "
                    f"{s['ms_hybrid_mesh']:.0f} ms"
                )
            c.print(f"  {s['paths'][0]}" + (f" ... {s['paths'][-1]}" if len(s["paths"]) > 1 else ""))
            if "gif" in s:
                c.print(f"  animation: {s['gif']}")

        emit(summary, json_out, human)
