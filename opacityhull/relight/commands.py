"""CLI commands of `opacityhull.relight` (registered by :mod:`opacityhull.cli`):
``opacityhull relight`` and ``opacityhull eval relight``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from ..cliutil import JsonSummaryFlag, cli_errors, console, emit, option_group, progress, writing_to
from ..errors import InputError, check_writable


def _config(kernel: str, kernel_width: float, lower_hemisphere: str, near_light: bool, pca_rank: Optional[int]):
    from typing import Any, cast

    from .basis import KernelConfig
    from .relit import RelightConfig

    # the flags arrive as plain strings; KernelConfig.__post_init__ checks them (ConfigError naming the value)
    kind, lower = cast(Any, kernel), cast(Any, lower_hemisphere)
    return RelightConfig(
        kernel=KernelConfig(kind=kind, width=kernel_width, lower_hemisphere=lower),
        near_light=near_light,
        pca_rank=pca_rank,
    )


def _probe_format(value: str):
    """``--probe-format`` checked and typed (the runners take only the Literal)."""
    from typing import cast

    from .envmap import PROBE_FORMATS, ProbeFormat

    if value not in PROBE_FORMATS:
        raise InputError(f"--probe-format {value!r}: expected one of {', '.join(PROBE_FORMATS)}")
    return cast(ProbeFormat, value)


_ENVMAP_HELP = (
    "Environment map: equirectangular .exr or Radiance .hdr (+Y up, centre column along +Z), or "
    "builtin:NAME for a shipped probe (ennis, grace, pisa, uffizi, wells)."
)
_YAW_HELP = (
    "Rotate the map about +Y by this many degrees after reading (ICT probes put their centre at -Z: use 180). "
    "Default: 180 for builtin: probes, else 0."
)
_FORMAT_HELP = (
    "Layout of the map: latlong (equirectangular), angular (Debevec light probe) or mirror (mirror-ball image)."
)


#: ``--env-yaw-deg`` and its old spelling, read as one value (see :func:`_yaw`).
_YAW_OPTIONS = {
    "env_yaw_deg": (Optional[float], typer.Option(None, "--env-yaw-deg", help=_YAW_HELP)),
    "yaw_deg_alias": (Optional[float], typer.Option(None, "--yaw-deg", hidden=True, help="Old name of --env-yaw-deg.")),
}


def _yaw(env_yaw_deg: Optional[float], yaw_deg_alias: Optional[float]) -> Optional[float]:
    return env_yaw_deg if yaw_deg_alias is None else yaw_deg_alias


#: The flags of ``relight`` and ``eval relight`` that make their RelightConfig (see :func:`_config`).
_CONFIG_OPTIONS = {
    "kernel": (
        str,
        typer.Option(
            "vmf",
            "--kernel",
            help="Light-cell partition: vmf (smooth, default), linear (barycentric on the "
            "lights' triangulation) or voronoi (nearest light).",
        ),
    ),
    "kernel_width": (
        float,
        typer.Option(0.25, "--kernel-width", help="vMF kernel sigma as a fraction of the light spacing."),
    ),
    "lower_hemisphere": (
        str,
        typer.Option(
            "drop",
            "--lower-hemisphere",
            help="Light from below the table plane: drop (the table blocks it) or nearest.",
        ),
    ),
    "near_light": (
        bool,
        typer.Option(
            True,
            "--near-light/--no-near-light",
            help="Correct the one-light images for the lights' finite distance (1/r^2 at the hull surface).",
        ),
    ),
    "pca_rank": (
        Optional[int],
        typer.Option(None, "--pca-rank", help="Relight from a rank-R PCA of each view's data (reports its error)."),
    ),
}


#: Fewer captured light directions than this and ``eval relight`` warns: the light
#: basis is too coarse for an environment map (a judgement, not a measured threshold).
FEW_LIGHTS = 8


def _check_model(model: Path) -> None:
    if not model.exists():
        raise InputError(f"{model}: no such model folder")
    if not model.is_dir():
        raise InputError(f"{model} is a file, expected a model folder (from `opacityhull build`)")


def register(app, groups) -> None:
    """Add ``relight`` to the root app and ``relight`` to the ``eval`` group."""

    @app.command("relight")
    @cli_errors
    @option_group(_YAW_OPTIONS, into="yaw_deg", before="probe_format", build=_yaw)
    @option_group(_CONFIG_OPTIONS, into="config_options", before="exposure")
    def relight(
        model: Path = typer.Argument(..., help="Model folder written by `opacityhull build` (with reflectance data)."),
        out: Path = typer.Option(
            ..., "--out", help="Output folder (EXR + PNG per image, contact sheets, GIF, relight.json)."
        ),
        envmap: Optional[str] = typer.Option(None, "--envmap", help=_ENVMAP_HELP),
        probe_format: str = typer.Option("latlong", "--probe-format", help=_FORMAT_HELP),
        flip_u: bool = typer.Option(False, "--flip-u", help="The lat-long map is stored mirrored left-right."),
        lights: Optional[str] = typer.Option(
            None,
            "--lights",
            help="Directional lights 'dx,dy,dz,r,g,b;...' (direction towards the light in the object frame, RGB "
            "irradiance), or 'point:x,y,z,r,g,b' (position in metres, RGB intensity). Adds to --envmap.",
        ),
        view: Optional[str] = typer.Option(
            None, "--view", help="Also render camera CAM at table angle DEG: 'CAM,DEG'."
        ),
        orbit: Optional[int] = typer.Option(None, "--orbit", help="Also render an orbit of N frames (PNGs + GIF)."),
        fps: float = typer.Option(12.0, "--fps", help="Frame rate of the orbit GIF (> 0; GIF stores 1/100 s delays)."),
        exposure: Optional[float] = typer.Option(
            None, "--exposure", help="PNG exposure multiplier (default: automatic, key 0.18)."
        ),
        no_views: bool = typer.Option(False, "--no-views", help="Do not write the relit captured views."),
        json_out: JsonSummaryFlag = False,
        *,
        yaw_deg: Optional[float],
        config_options: dict,
    ):
        """Relight a captured model under an environment map or lights: every captured view is relit as a weighted
        sum of its one-light images, then (--view/--orbit) blended onto the surfels with ULR over the environment."""
        from .basis import parse_lights
        from .envmap import default_yaw_deg, load_envmap
        from .runner import parse_view_spec, relight_model

        _check_model(model)
        if orbit is not None and orbit < 1:
            raise InputError(f"--orbit {orbit}: expected at least 1 frame")
        if not (math.isfinite(fps) and fps > 0):
            raise InputError(f"--fps {fps}: expected a frame rate > 0")
        if exposure is not None and not (math.isfinite(exposure) and exposure > 0):
            raise InputError(f"--exposure {exposure}: expected a multiplier > 0 (omit it for automatic exposure)")
        check_writable(out)
        cfg = _config(**config_options)
        v = parse_view_spec(view) if view else None
        if envmap is None and not lights:
            raise InputError("give --envmap X.exr|X.hdr or --lights 'dx,dy,dz,r,g,b;...'")
        env = None
        if envmap is not None:
            env = load_envmap(
                envmap,
                yaw_deg=default_yaw_deg(envmap) if yaw_deg is None else yaw_deg,
                probe_format=_probe_format(probe_format),
                flip_u=flip_u,
            )
        light_arrays = parse_lights(lights) if lights else None
        with progress("relight", enabled=not json_out) as cb:
            with writing_to(out):
                s = relight_model(
                    model,
                    out=out,
                    envmap=env,
                    lights=light_arrays,
                    view=v,
                    orbit=orbit,
                    fps=fps,
                    config=cfg,
                    exposure=exposure,
                    write_views=not no_views,
                    progress=cb,
                )

        def human(s):
            c = console()
            c.print(
                f"relit {s['n_views']} views of {s['model']} ({s['n_lights_captured']} captured lights, "
                f"{s['relit_views_per_s']:.1f} views/s)"
            )
            if "pca" in s:
                p = s["pca"]
                c.print(
                    f"PCA rank {p['rank']}: {p['compression_ratio']:.1f}x smaller, reflectance error "
                    f"{100 * p['reflectance_rel_error_mean']:.2f} % (max {100 * p['reflectance_rel_error_max']:.2f} %)"
                )
            if "views_sheet" in s:
                c.print(f"relit views: {s['views_dir']}  contact sheet: {s['views_sheet']}")
            if "view" in s:
                c.print(f"view: {s['view']['png']}")
            if "orbit" in s:
                c.print(f"orbit: {s['orbit']['gif']} ({s['orbit']['frames']} frames, {s['orbit']['render_s']:.1f} s)")
            c.print(f"summary: {s['out']}/relight.json")

        emit(s, json_out, human)

    @groups["eval"].command("relight")
    @cli_errors
    @option_group(_YAW_OPTIONS, into="yaw_deg", before="probe_format", build=_yaw)
    @option_group(_CONFIG_OPTIONS, into="config_options", before="json_out")
    def eval_relight_cmd(
        model: Path = typer.Argument(..., help="Model folder built from a simulated session (with reflectance data)."),
        envmap: str = typer.Option(..., "--envmap", help=_ENVMAP_HELP),
        probe_format: str = typer.Option("latlong", "--probe-format", help=_FORMAT_HELP),
        out: Optional[Path] = typer.Option(
            None,
            "--out",
            help="Folder for the contact sheet and per-view EXRs (default "
            "./MODELNAME_eval_relight in the current folder: an evaluation never "
            "writes into the model).",
        ),
        spp: int = typer.Option(64, "--spp", help="Samples per pixel of Mitsuba's ground-truth render."),
        max_views: Optional[int] = typer.Option(
            None, "--max-views", help="Evaluate at most this many views (spread evenly)."
        ),
        json_out: bool = typer.Option(
            False, "--json", help='Print {"psnr_mean", "rel_err_mean", "per_view", ...} on stdout.'
        ),
        *,
        yaw_deg: Optional[float],
        config_options: dict,
    ):
        """Relit captured views of a simulated model against Mitsuba's direct render of the same object under the
        same environment map from the same cameras: PSNR and relative error inside the mask, and a contact sheet
        (truth | relit | error)."""
        from .envmap import default_yaw_deg, load_envmap
        from .evaluate import eval_relight

        _check_model(model)
        if spp < 1:
            raise InputError(f"--spp {spp}: expected at least 1 sample per pixel")
        if max_views is not None and max_views < 1:
            raise InputError(f"--max-views {max_views}: expected at least 1")
        if out is None:
            # not inside MODEL: a model is an input here (it may be shared or read-only)
            out = Path(f"{model.resolve().name}_eval_relight")
        cfg = _config(**config_options)
        env = load_envmap(
            envmap,
            yaw_deg=default_yaw_deg(envmap) if yaw_deg is None else yaw_deg,
            probe_format=_probe_format(probe_format),
        )
        with progress("eval relight", enabled=not json_out) as cb:
            s = eval_relight(model, envmap=env, out=out, spp=spp, max_views=max_views, config=cfg, progress=cb)

        n_lights = s.get("n_lights_captured")
        if n_lights is not None and n_lights < FEW_LIGHTS:
            s.setdefault("warnings", []).append(
                f"only {n_lights} captured light direction(s): relighting sums one-light images, so an environment "
                f"map is seen through {n_lights} cell(s) of the sphere — expect large errors (the tiny plan's 2 "
                f"lights measured 58-82 %); capture with more lights (plan [phases.reflectance] lights/array_steps)"
            )

        def human(s):
            c = console()
            c.print(
                f"relighting vs Mitsuba over {len(s['per_view'])} views: PSNR {s['psnr_mean']:.2f} dB, "
                f"relative error {100 * s['rel_err_mean']:.2f} %"
            )
            c.print(f"contact sheet (truth | relit | error): {s['sheet']}")
            for w in s.get("warnings", []):
                c.print(f"[yellow]warning:[/] {escape(w)}", highlight=False)

        emit(s, json_out, human)
