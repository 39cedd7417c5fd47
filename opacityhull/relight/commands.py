"""CLI commands of `opacityhull.relight` (registered by :mod:`opacityhull.cli`):
``opacityhull relight`` (``eval relight`` is :mod:`opacityhull.evaluate.commands`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from ..cliutil import JsonSummaryFlag, env_yaw_options, option_group, pick_env_yaw
from ..cliutil import check_choice, check_model_dir, check_orbit_fps, cli_errors, console, emit, progress, writing_to
from ..errors import InputError, check_writable
from ..outputs import check_output
from .basis import KernelConfig
from .relit import RelightConfig

# the flags' defaults are the configs' (numpy-only modules: --help stays fast)
_K, _R = KernelConfig(), RelightConfig()


def _config(kernel: str, kernel_width: float, lower_hemisphere: str, near_light: bool, pca_rank: int | None):
    from typing import Any, cast

    # the flags arrive as plain strings; KernelConfig.__post_init__ checks them (ConfigError naming the value)
    kind, lower = cast(Any, kernel), cast(Any, lower_hemisphere)
    return RelightConfig(
        kernel=KernelConfig(kind=kind, width=kernel_width, lower_hemisphere=lower),
        near_light=near_light,
        pca_rank=pca_rank,
    )


def _probe_format(value: str):
    """``--probe-format`` checked and typed (the runners take only the Literal)."""
    from typing import get_args

    from .envmap import ProbeFormat

    return check_choice("--probe-format", value, get_args(ProbeFormat), one_of=True)


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


def _map_options(*, required: bool) -> dict:
    """``--envmap`` (``required``, else None: no map) and how both commands read it: its
    rotation (``--env-yaw-deg``, None: the map's default; and its old spelling) and its
    layout (``--probe-format``). See :func:`_load_map`."""
    kind, default = (str, ...) if required else (str | None, None)
    return {
        "envmap": (kind, typer.Option(default, "--envmap", help=_ENVMAP_HELP)),
        **env_yaw_options(None, _YAW_HELP),
        "probe_format": (str, typer.Option("latlong", "--probe-format", help=_FORMAT_HELP)),
    }


def _load_map(map_options: dict, *, flip_u: bool = False):
    """``--envmap`` read with the rest of :func:`_map_options` (``--probe-format`` checked here)."""
    from .envmap import default_yaw_deg, load_envmap, require_light

    envmap = map_options["envmap"]
    if not str(envmap).startswith("builtin:") and not Path(envmap).is_file():
        # a missing file is bad input naming the flag (it was "image X not found", exit 4)
        raise InputError(f"--envmap {envmap}: no such file (give an .exr/.hdr map or builtin:NAME)")
    yaw = pick_env_yaw(map_options["env_yaw_deg"], map_options["yaw_deg_alias"])
    env = load_envmap(
        envmap,
        yaw_deg=default_yaw_deg(envmap) if yaw is None else yaw,
        probe_format=_probe_format(map_options["probe_format"]),
        flip_u=flip_u,
    )
    require_light(env, f"--envmap {envmap}")
    return env


_MODEL_HELP = "Model folder written by `opacityhull build` (with reflectance data)."
_OUT_HELP = "Output folder (EXR + PNG per image, contact sheets, GIF, relight.json)."
_FLIP_U_HELP = "The lat-long map is stored mirrored left-right."
_LIGHTS_HELP = (
    "Directional lights 'dx,dy,dz,r,g,b;...' (direction towards the light in the object frame, RGB "
    "irradiance), or 'point:x,y,z,r,g,b' (position in metres, RGB intensity). Adds to --envmap."
)
_VIEW_HELP = "Also render camera CAM at table angle DEG: 'CAM,DEG'."
_ORBIT_HELP = "Also render an orbit of N frames (PNGs + GIF)."
_FPS_HELP = "Frame rate of the orbit GIF (> 0; GIF stores 1/100 s delays)."
_EXPOSURE_HELP = "PNG exposure multiplier (default: automatic, key 0.18)."


_KERNEL_HELP = (
    "Light-cell partition: vmf (smooth, default), linear (barycentric on the "
    "lights' triangulation) or voronoi (nearest light)."
)
_KERNEL_WIDTH_HELP = "vMF kernel sigma as a fraction of the light spacing."
_LOWER_HELP = "Light from below the table plane: drop (the table blocks it) or nearest."
_NEAR_HELP = "Correct the one-light images for the lights' finite distance (1/r^2 at the hull surface)."
_PCA_RANK_HELP = "Relight from a rank-R PCA of each view's data (reports its error)."

#: The flags of ``relight`` and ``eval relight`` that make their RelightConfig (see :func:`_config`).
_CONFIG_OPTIONS = {
    "kernel": (str, typer.Option(_K.kind, "--kernel", help=_KERNEL_HELP)),
    "kernel_width": (float, typer.Option(_K.width, "--kernel-width", help=_KERNEL_WIDTH_HELP)),
    "lower_hemisphere": (str, typer.Option(_K.lower_hemisphere, "--lower-hemisphere", help=_LOWER_HELP)),
    "near_light": (bool, typer.Option(_R.near_light, "--near-light/--no-near-light", help=_NEAR_HELP)),
    "pca_rank": (int | None, typer.Option(_R.pca_rank, "--pca-rank", help=_PCA_RANK_HELP)),
}


def _shared_options(*, envmap_required: bool, map_before: str, config_before: str):
    """The flags both commands take: :func:`_map_options` (into ``map_options``) placed
    before the parameter ``map_before``, :data:`_CONFIG_OPTIONS` (``config_options``)
    before ``config_before``."""

    def decorate(fn):
        fn = option_group(_CONFIG_OPTIONS, into="config_options", before=config_before)(fn)
        return option_group(_map_options(required=envmap_required), into="map_options", before=map_before)(fn)

    return decorate


def register(app, groups) -> None:
    """Add ``relight`` to the root app."""

    @app.command("relight")
    @cli_errors
    @_shared_options(envmap_required=False, map_before="flip_u", config_before="exposure")
    def relight(
        model: Annotated[Path, typer.Argument(help=_MODEL_HELP)],
        out: Annotated[Path, typer.Option("--out", help=_OUT_HELP)],
        flip_u: Annotated[bool, typer.Option("--flip-u", help=_FLIP_U_HELP)] = False,
        lights: Annotated[str | None, typer.Option("--lights", help=_LIGHTS_HELP)] = None,
        view: Annotated[str | None, typer.Option("--view", help=_VIEW_HELP)] = None,
        orbit: Annotated[int | None, typer.Option("--orbit", help=_ORBIT_HELP)] = None,
        fps: Annotated[float, typer.Option("--fps", help=_FPS_HELP)] = 12.0,
        exposure: Annotated[float | None, typer.Option("--exposure", help=_EXPOSURE_HELP)] = None,
        no_views: Annotated[bool, typer.Option("--no-views", help="Do not write the relit captured views.")] = False,
        renderer: Annotated[
            str,
            typer.Option(
                "--renderer",
                help="--view/--orbit: fitted (the splats of build --optimize, each coloured by the relit views' ULR "
                "at its nearest hull surfel) | ulr (the hull's surfels) | auto (fitted when the model has current "
                "fitted splats).",
            ),
        ] = "auto",
        json_out: JsonSummaryFlag = False,
        *,
        map_options: dict,
        config_options: dict,
    ):
        """Relight a captured model under an environment map or lights: every captured view is relit as a weighted
        sum of its one-light images, then (--view/--orbit) blended onto the surfels with ULR over the environment."""
        from .basis import parse_lights
        from .runner import parse_view_spec, relight_model

        check_model_dir(model)
        check_orbit_fps(orbit, fps)
        if exposure is not None and not (math.isfinite(exposure) and exposure > 0):
            raise InputError(f"--exposure {exposure}: expected a multiplier > 0 (omit it for automatic exposure)")
        check_output(out, {"MODEL": model, "--envmap": map_options["envmap"]})
        check_writable(out)
        from ..render.splats import resolve_renderer

        resolve_renderer(model, renderer)  # before anything is written
        cfg = _config(**config_options)
        v = parse_view_spec(view) if view else None
        if map_options["envmap"] is None and not lights:
            raise InputError("give --envmap X.exr|X.hdr or --lights 'dx,dy,dz,r,g,b;...'")
        env = None
        if map_options["envmap"] is not None:
            env = _load_map(map_options, flip_u=flip_u)
        light_arrays = parse_lights(lights) if lights else None
        with progress("relight", enabled=not json_out) as cb, writing_to(out):
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
                renderer=renderer,
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
