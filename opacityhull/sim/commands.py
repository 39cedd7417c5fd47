"""CLI commands of `opacityhull.sim` (registered by :mod:`opacityhull.cli`):
``opacityhull sim render``, ``opacityhull sim explain``, ``opacityhull sim scenes``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from ..cliutil import cli_errors, console, emit, out_console

__all__ = ["register", "make_pattern", "PATTERNS"]

PATTERNS = ("white", "black", "grey", "checker", "stripes", "random")


def make_pattern(name: str, width: int, height: int, *, seed: int = 0):
    """A display pattern uint8 (height, width, 3) by name (see :data:`PATTERNS`) or from an
    image file (linear values are sRGB-encoded back to the 8-bit drive levels)."""
    import numpy as np

    from ..errors import InputError

    if name == "white":
        return np.full((height, width, 3), 255, np.uint8)
    if name == "black":
        return np.zeros((height, width, 3), np.uint8)
    if name == "grey":
        return np.full((height, width, 3), 128, np.uint8)
    if name == "checker":
        v, u = np.mgrid[0:height, 0:width]
        c = (((u * 8) // width + (v * 8) // height) % 2 * 255).astype(np.uint8)
        return np.repeat(c[:, :, None], 3, axis=2)
    if name == "stripes":
        u = np.arange(width)
        c = (((u * 8) // width) % 2 * 255).astype(np.uint8)
        return np.repeat(np.tile(c, (height, 1))[:, :, None], 3, axis=2)
    if name == "random":
        return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
    p = Path(name)
    if p.is_file():
        from ..imageio import read_image, srgb_encode

        img = read_image(p)
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        return np.round(srgb_encode(img[:, :, :3]) * 255).astype(np.uint8)
    raise InputError(f"--pattern {name!r}: expected one of {list(PATTERNS)} or an image file")


def _camera_index(geometry, camera: str) -> int:
    from ..errors import InputError

    names = [c.name for c in geometry.cameras]
    if camera in names:
        return names.index(camera)
    try:
        i = int(camera)
    except ValueError:
        raise InputError(f"--camera {camera!r}: not a camera name or index (cameras: {names})") from None
    if not 0 <= i < len(names):
        raise InputError(f"--camera {i}: index not in 0..{len(names) - 1} (cameras: {names})")
    return i


#: ``--scene`` of ``sim render`` and ``sim explain``.
_SceneOpt = Annotated[str, typer.Option("--scene", help="Scene: builtin:NAME or a scene TOML path.")]
_LIGHT_HELP = "Light id to switch on at full level (repeatable; default: all lights)."
_PATTERN_HELP = f"Show a pattern on every display: {', '.join(PATTERNS)} or an image file (default: displays blank)."
_BOARD_HELP = "Put the scene's (or a default) ChArUco board on the table instead of the object."
_RIG_HELP = "Rig TOML (default: the built-in simulated rig)."
_SPP_HELP = "Samples per pixel (default: effect selection)."
_OUT_HELP = "Output image (.exr linear radiance; .png sRGB preview; an .exr also gets a .png preview beside it)."
_PHASE_HELP = "calibration, matting, lightfield, reflectance, envmatte or groundtruth."
_CAMERA_SIZE_HELP = "WxH of the camera the shots are for (matting samples, and envmatte samples of some kinds, depend on it); default: the built-in rig's."


def register(app, groups) -> None:
    """Add ``sim render``, ``sim explain`` and ``sim scenes`` to the ``sim`` group."""

    @groups["sim"].command("render")
    @cli_errors
    def render(
        scene: _SceneOpt,
        camera: Annotated[str, typer.Option("--camera", help="Camera name or index in the rig.")] = "0",
        table_deg: Annotated[float, typer.Option("--table-deg", help="Turntable angle (degrees).")] = 0.0,
        light: Annotated[list[int] | None, typer.Option("--light", help=_LIGHT_HELP)] = None,
        lights_off: Annotated[bool, typer.Option("--lights-off", help="Switch every light off.")] = False,
        array_deg: Annotated[float, typer.Option("--array-deg", help="Light-array rotation (degrees).")] = 0.0,
        pattern: Annotated[str | None, typer.Option("--pattern", help=_PATTERN_HELP)] = None,
        board: Annotated[bool, typer.Option("--board", help=_BOARD_HELP)] = False,
        rig: Annotated[Path | None, typer.Option("--rig", help=_RIG_HELP)] = None,
        scale: Annotated[float, typer.Option("--scale", min=0.01, help="Multiply the camera resolution.")] = 1.0,
        spp: Annotated[int | None, typer.Option("--spp", min=1, help=_SPP_HELP)] = None,
        seed: Annotated[int, typer.Option("--seed", help="Render seed.")] = 0,
        out: Annotated[Path | None, typer.Option("--out", help=_OUT_HELP)] = None,
        json_out: Annotated[bool, typer.Option("--json", help="Print a one-line JSON summary.")] = False,
    ):
        """Render one camera of the simulated rig in a given state (no emulators involved).

        The effect selection (integrator, depth, spp, emitters) follows the state — lights
        on: lightfield/reflectance, patterns only: matting, --board: calibration — and is
        printed with the result.
        """
        import time

        import numpy as np

        from ..errors import InputError
        from ..imageio import write_image, write_png
        from .render import SimRenderer, SimState
        from .scenes import load_scene
        from .simrig import sim_rig_config
        from ..riggeometry import RigGeometry

        if light and lights_off:
            raise InputError("--light and --lights-off exclude each other")
        sc = load_scene(scene)
        cfg = sim_rig_config(None, rig_toml=rig, scale=scale)
        geometry = RigGeometry.from_dict(cfg["geometry"], where=f"{rig or 'built-in rig'}: geometry")
        ci = _camera_index(geometry, camera)
        ids = [L.id for L in geometry.lights]
        if lights_off:
            levels = {}
        elif light:
            for lid in light:
                if lid not in ids:
                    raise InputError(f"--light {lid}: no such light (ids: {ids})")
            levels = {lid: 255 for lid in light}
        else:
            levels = {lid: 255 for lid in ids}
        displays = {}
        if pattern is not None:
            for d in geometry.displays:
                displays[d.name] = make_pattern(pattern, d.resolution[0], d.resolution[1], seed=seed)
        state = SimState(
            table_deg=table_deg,
            array_deg=array_deg,
            light_levels=levels,
            displays=displays,
            content="board" if board else "object",
        )
        r = SimRenderer(sc, geometry, overrides={"spp": spp} if spp else None)
        cam = geometry.nominal_cameras()[ci]
        eff = r.effects_for(state, camera=cam)
        passes = r.passes_for(state, camera=cam)
        t0 = time.perf_counter()
        img = r.render(cam, state, seed=seed)
        dt = time.perf_counter() - t0
        summary = {
            "scene": sc.source,
            "camera": geometry.cameras[ci].name,
            "table_deg": table_deg,
            "array_deg": array_deg,
            "lights": sorted(k for k, v in levels.items() if v > 0),
            "pattern": pattern,
            "board": board,
            "width": img.shape[1],
            "height": img.shape[0],
            "variant": r.mi.variant(),
            "effects": eff.to_json(),
            "passes": [p.to_json() for p in passes],
            "seconds": dt,
            "mean_radiance": float(np.mean(img)),
            "max_radiance": float(np.max(img)),
            "out": None,
            "preview": None,
        }
        if out is not None:
            write_image(out, img)
            summary["out"] = str(out)
            if out.suffix.lower() == ".exr":
                prev = out.with_suffix(".png")
                peak = float(np.percentile(img, 99.5)) or 1.0
                write_png(prev, np.clip(img / max(peak, 1e-12), 0.0, 1.0))
                summary["preview"] = str(prev)

        def human(s):
            e = s["effects"]
            console().print(
                f"{s['scene']} from {s['camera']} at table {s['table_deg']:g}°: {s['width']}x{s['height']}"
                f" in {s['seconds']:.3f} s ({s['variant']}); phase {e['phase']}, "
                f"{len(s['passes'])} Mitsuba pass(es): "
                + (
                    ", ".join(
                        f"{p['group']}{'' if p['light'] is None else ' ' + str(p['light'][0])} "
                        f"{p['integrator']} d{p['max_depth']} {p['spp']} spp"
                        for p in s["passes"]
                    )
                    or "none (nothing emits)"
                )
                + f"; mean radiance {s['mean_radiance']:.4g}"
                + (f" → {s['out']}" if s["out"] else ""),
                highlight=False,
                markup=False,
            )

        emit(summary, json_out, human)

    @groups["sim"].command("explain")
    @cli_errors
    def explain(
        scene: _SceneOpt,
        phase: Annotated[str, typer.Option("--phase", help=_PHASE_HELP)],
        camera_size: Annotated[str, typer.Option("--camera-size", help=_CAMERA_SIZE_HELP)] = "",
        json_out: Annotated[bool, typer.Option("--json", help="Print the selection as one JSON line.")] = False,
    ):
        """Say which effects the simulator renders for a scene in a capture phase, and why;
        its expected cost relative to the full-effects reference, and the Mitsuba variant."""
        from ..errors import InputError
        from .effects import expected_cost, select_effects
        from .groundtruth import default_geometry
        from .scenes import load_scene
        from .variants import variant_report

        from .render import lamp_radius

        geom = default_geometry()
        radius = lamp_radius(geom)
        if camera_size:
            try:
                w, h = (int(v) for v in camera_size.lower().split("x"))
                if w <= 0 or h <= 0:
                    raise ValueError
            except ValueError:
                raise InputError(f"--camera-size {camera_size!r}: expected WIDTHxHEIGHT, e.g. 400x300") from None
        else:
            c0 = geom.nominal_cameras()[0]
            w, h = c0.width, c0.height
        sc = load_scene(scene)
        cfg = select_effects(sc, phase, pixels=w * h, lamp_radius_m=radius)
        summary = {
            "scene": sc.source,
            "camera_size": [w, h],
            "lamp_radius_m": radius,
            **cfg.to_json(),
            "expected_cost": expected_cost(sc, phase, lamp_radius_m=radius),
            "variant": variant_report(),
        }
        if phase == "matting":
            # what a displays-on shot gets when the capture does not declare its phase
            und = select_effects(sc, phase, declared=False)
            summary["undeclared"] = {"integrator": und.integrator, "max_depth": und.max_depth, "spp": und.spp}

        def human(s):
            c = out_console()
            c.print(
                f"[bold]{escape(str(s['scene']))}[/] — phase [bold]{s['phase']}[/]: {s['integrator']} "
                f"(max_depth {s['max_depth']}), {s['spp']} spp ({s['sampler']}), "
                f"emitters {s['emitters'] or 'none'}, shapes {s['shapes']}; promises {s['error_metric']} "
                f"<= {s['error_bound']} against the full-effects reference"
            )
            ec = s["expected_cost"]
            if ec.get("vs_reference") == 0:
                c.print(f"  expected cost: nothing is rendered (provably black; {ec['measured']})", highlight=False)
            elif ec.get("vs_reference") is not None:
                c.print(
                    f"  expected cost: {ec['vs_reference']:.2f}x the reference's time "
                    f"({1.0 / ec['vs_reference']:.1f}x faster; {ec['measured']})",
                    highlight=False,
                )
            else:
                c.print(f"  expected cost: not measured ({ec['measured']})", highlight=False)
            if "undeclared" in s:
                u = s["undeclared"]
                c.print(
                    f"  a shot whose capture does not declare the phase (it may be envmatte): {u['integrator']} "
                    f"(max_depth {u['max_depth']}), {u['spp']} spp",
                    highlight=False,
                )
            v = s["variant"]
            c.print(f"  Mitsuba variant: {v['variant']}{' (GPU)' if v['gpu'] else ''} — {v['source']}", highlight=False)
            for r in s["reasons"]:
                c.print(f"  • {r}", highlight=False, markup=False)

        emit(summary, json_out, human, primary=True)

    @groups["sim"].command("scenes")
    @cli_errors
    def scenes(json_out: Annotated[bool, typer.Option("--json", help="Print the list as one JSON line.")] = False):
        """List the built-in scenes (use them as builtin:NAME)."""
        from .scenes import builtin_names, load_scene

        items = []
        for n in builtin_names():
            s = load_scene(f"builtin:{n}")
            items.append(
                {
                    "name": f"builtin:{n}",
                    "description": s.description,
                    "effect_classes": sorted(s.effect_classes),
                    "parts": [p.kind for p in s.parts],
                }
            )

        def human(s: dict) -> None:
            for i in s["scenes"]:
                out_console().print(f"[bold]{escape(i['name'])}[/]: {escape(i['description'])}", highlight=False)

        emit({"scenes": items}, json_out, human, primary=True)
