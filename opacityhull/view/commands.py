"""CLI of :mod:`opacityhull.view`: ``opacityhull view MODEL [--port P] [--out DIR]``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..cliutil import ModelDirArg, check_model_dir, cli_errors, console, emit, progress, writing_to


def _parse_bg(text: str):
    from ..errors import InputError

    named = {"black": (0, 0, 0), "white": (1, 1, 1), "grey": (0.18, 0.18, 0.18), "gray": (0.18, 0.18, 0.18)}
    if text in named:
        return named[text]
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) == 1:
        vals = vals * 3
    if len(vals) != 3 or not all(0.0 <= v <= 1.0 for v in vals):
        raise InputError(f"--background {text!r}: expected black | white | grey | R,G,B or one value in [0, 1]")
    return tuple(vals)


def _bits(s: dict) -> str:
    b, o = s.get("position_bits_per_coded_surfel"), s.get("position_offset_bits_per_coded_surfel")
    text = "float32" if b is None else f"octree {b:.2f} + offsets {o:.2f} bits/surfel"
    r = s.get("relight")
    if r:
        text += (
            f"; relightable under {', '.join(r['envmaps'])} (PCA rank {r['rank']}, relit error "
            f"{100 * r['relit_rel_error']:.1f} %, {r['bytes_per_view'] / 1e3:.0f} kB/view)"
        )
    return text


_OUT_HELP = (
    "Write the static web bundle here. Alone (without --port) it only writes the bundle, for any static web host."
)
_PORT_HELP = "Serve on 127.0.0.1:PORT (0: any free port; default 8765 when --out is not given)."
_BACKGROUND_HELP = (
    "Initial background: grey (18 %, the default) | black | white | R,G,B; the page switches in one click."
)
_ENVMAP_HELP = (
    "Environment map the page can show behind the "
    "model: an equirectangular .hdr/.exr, or builtin:NAME (ennis grace pisa "
    "uffizi wells)."
)
_ENV_YAW_HELP = "Its rotation about +Y (default 180 for builtin: probes, else 0); the page has a slider."
_CELL_HELP = (
    "Leaf cell edge (m) of the "
    "octree position code (default: the surfels' median spacing; "
    "smaller is more exact and costs more bits)."
)
_OFFSET_BITS_HELP = (
    "Bits of the per-surfel offset along the normal that refines the octree cell centre (0-8; 0: cell centres)."
)
_RELIGHT_HELP = (
    "For a model with reflectance: bundle the relighting data (environment-map picker and rotation slider in the page)."
)
_PROBES_HELP = (
    "Builtin probes to relight with, comma-separated (default: all of ennis grace pisa "
    "uffizi wells); --envmap adds its map."
)
_RELIGHT_ERROR_HELP = "Relative relit error the per-view PCA rank is chosen for."
_RELIGHT_RANK_HELP = "Fix the PCA rank of the relighting data instead (1-16)."
_YAW_STEPS_HELP = "Rotations of each map the light weights are tabulated at (72: every 5 deg)."
_JSON_HELP = "Print a JSON summary (bundle path, bytes, URL, renderer) on stdout."
_RENDERER_HELP = (
    "fitted: bundle the splats of build --optimize, which the page draws (it can switch to ULR) | ulr: leave "
    "them out | auto: fitted when the model has splats fitted from this build."
)


def register(app, groups) -> None:
    @app.command("view")
    @cli_errors
    def view_cmd(
        model: ModelDirArg,
        out: Annotated[Path | None, typer.Option("--out", help=_OUT_HELP)] = None,
        port: Annotated[int | None, typer.Option("--port", help=_PORT_HELP)] = None,
        k: Annotated[int, typer.Option("--k", help="Initial ULR k of the page (1-8; the page has a slider).")] = 4,
        background: Annotated[str, typer.Option("--background", help=_BACKGROUND_HELP)] = "grey",
        envmap: Annotated[str | None, typer.Option("--envmap", help=_ENVMAP_HELP)] = None,
        env_yaw_deg: Annotated[float | None, typer.Option("--env-yaw-deg", help=_ENV_YAW_HELP)] = None,
        position_cell_m: Annotated[float | None, typer.Option("--position-cell-m", help=_CELL_HELP)] = None,
        offset_bits: Annotated[int, typer.Option("--offset-bits", help=_OFFSET_BITS_HELP)] = 3,
        relight: Annotated[bool, typer.Option("--relight/--no-relight", help=_RELIGHT_HELP)] = True,
        probes: Annotated[str | None, typer.Option("--probes", help=_PROBES_HELP)] = None,
        relight_error: Annotated[float, typer.Option("--relight-error", help=_RELIGHT_ERROR_HELP)] = 0.01,
        relight_rank: Annotated[int | None, typer.Option("--relight-rank", help=_RELIGHT_RANK_HELP)] = None,
        yaw_steps: Annotated[int, typer.Option("--yaw-steps", help=_YAW_STEPS_HELP)] = 72,
        renderer: Annotated[str, typer.Option("--renderer", help=_RENDERER_HELP)] = "auto",
        json_out: Annotated[bool, typer.Option("--json", help=_JSON_HELP)] = False,
    ):
        """Open a model in the browser: write a WebGL2 bundle (ULR-blended EWA splats) and serve it on 127.0.0.1."""
        import tempfile
        import time

        from .bundle import write_bundle

        import shutil
        import signal

        check_model_dir(model)
        bg = _parse_bg(background)
        serve = port is not None or out is None
        target = out if out is not None else Path(tempfile.mkdtemp(prefix="opacityhull-view-")) / "bundle"
        try:
            # a full disk met by a write that names no file said "cannot write None"
            with progress("writing viewer bundle", enabled=not json_out) as cb, writing_to(target):
                summary = write_bundle(
                    model,
                    target,
                    k=k,
                    background=bg,
                    envmap=envmap,
                    env_yaw_deg=env_yaw_deg,
                    position_cell_m=position_cell_m,
                    offset_bits=offset_bits,
                    relight=relight,
                    probes=None if probes is None else [p.strip() for p in probes.split(",") if p.strip()],
                    relight_error=relight_error,
                    relight_rank=relight_rank,
                    yaw_steps=yaw_steps,
                    renderer=renderer,
                    progress=cb,
                )
            if not serve:
                emit(
                    summary,
                    json_out,
                    lambda s: console().print(
                        f"wrote viewer bundle {s['out']} ({s['bytes'] / 1e6:.1f} MB, {s['surfels']} surfels, "
                        f"{s['views']} views; positions {_bits(s)}"
                        + (f"; {s['splats']['count']} fitted splats drawn" if s.get("splats") else "")
                        + f"); serve it with any static web server, e.g. "
                        f"python -m http.server -b 127.0.0.1 -d {s['out']} 8765"
                    ),
                )
                return
            from .server import BundleServer

            def _stop(signum, frame):
                raise KeyboardInterrupt

            signal.signal(signal.SIGTERM, _stop)  # `kill PID` stops the server like Ctrl-C
            srv = BundleServer(target, port=8765 if port is None else port)
            summary["url"] = srv.url
            try:  # serving until Ctrl-C / SIGTERM is the normal end: exit 0
                emit(summary, json_out, lambda s: None)
                console().print(
                    f"serving {target} at [bold]{srv.url}[/] — open it in a browser; Ctrl-C stops", highlight=False
                )
                while True:
                    time.sleep(3600)
            except KeyboardInterrupt:
                console().print("stopped")
            finally:
                srv.close()
        finally:
            if out is None:  # the bundle was only for this session
                shutil.rmtree(target.parent, ignore_errors=True)
