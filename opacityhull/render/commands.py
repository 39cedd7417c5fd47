"""CLI commands of `opacityhull.render` (registered by :mod:`opacityhull.cli`):
``opacityhull render`` and ``opacityhull eval loo``."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..cliutil import cli_errors, console, emit, progress
from .config import RenderConfig

_D = RenderConfig()


def _config(k, filter_var, epsilon_z, cutoff, sigma_radius):
    return RenderConfig(k=k, filter=filter_var, epsilon_z=epsilon_z, cutoff_sigma=cutoff, sigma_radius=sigma_radius)


_K_HELP = "ULR neighbourhood: the k nearest visible views by angle (k-1 blend; the k-th is the threshold)."
_FILTER_HELP = "EWA low-pass prefilter variance in px² (H = FILTER·I); 0 disables it."
_EPS_HELP = "ε-z-buffer tolerance in surfel radii: fragments this close behind the front-most one blend."
_CUTOFF_HELP = "Evaluate each EWA kernel within this Mahalanobis radius."
_SIGMA_HELP = "Tangent-plane Gaussian σ as a fraction of the surfel radius."


def register(app, groups) -> None:
    """Add ``render`` to the root app and ``loo`` to the ``eval`` group."""

    @app.command("render")
    @cli_errors
    def render_cmd(
        model: Path = typer.Argument(..., help="Model folder (model.toml, surfels.ply, views/)."),
        out: Path = typer.Option(..., "--out", help="Output image: X.png or X.exr (orbits write X_000.png ... and X.gif)."),
        view: Optional[str] = typer.Option(None, "--view", help="CAM,TABLE_DEG: captured camera CAM with the table at TABLE_DEG "
                                           "(any angle; captured views are reproduced exactly). Default: the first view."),
        look_at: Optional[str] = typer.Option(None, "--look-at", help="EX,EY,EZ,TX,TY,TZ[,FOV_DEG]: eye and target in the "
                                              "object frame (metres), vertical field of view (default: the cameras')."),
        orbit: Optional[int] = typer.Option(None, "--orbit", help="N frames on a circle around the model at the captured "
                                            "cameras' mean elevation and distance; also writes an animated GIF."),
        k: int = typer.Option(_D.k, "--k", help=_K_HELP),
        background: Optional[str] = typer.Option(None, "--background", help="Composite over a colour (0.2,0.3,0.4 | 0.5 | "
                                                 "#rrggbb | black | white | grey), an image, or an environment map "
                                                 "(.hdr, or a 2:1 .exr). Without it, images keep their alpha."),
        background_kind: str = typer.Option("auto", "--background-kind", help="auto | image | envmap."),
        env_yaw_deg: float = typer.Option(0.0, "--env-yaw-deg", help="Rotate the environment map about +Y (ICT probes: 180)."),
        width: Optional[int] = typer.Option(None, "--width", help="Output width in pixels (default: the views')."),
        height: Optional[int] = typer.Option(None, "--height", help="Output height in pixels (default: keeps the aspect)."),
        filter_var: float = typer.Option(_D.filter, "--filter", help=_FILTER_HELP),
        epsilon_z: float = typer.Option(_D.epsilon_z, "--epsilon-z", help=_EPS_HELP),
        cutoff: float = typer.Option(_D.cutoff_sigma, "--cutoff", help=_CUTOFF_HELP),
        sigma_radius: float = typer.Option(_D.sigma_radius, "--sigma-radius", help=_SIGMA_HELP),
        exclude: List[str] = typer.Option([], "--exclude", help="View id or index not to blend (repeatable)."),
        fps: float = typer.Option(12.0, "--fps", help="Frame rate of the orbit animation."),
        json_out: bool = typer.Option(False, "--json", help="Print a JSON summary (frames, paths, ms per frame) on stdout."),
    ):
        """Render a model from a captured view, a look-at camera, or an orbit (ULR-blended EWA surfel splatting)."""
        from .runner import run_render

        cfg = _config(k, filter_var, epsilon_z, cutoff, sigma_radius)
        n = orbit if orbit is not None else 1
        with progress("rendering", n, enabled=n > 1) as cb:
            summary = run_render(model, out, view=view, look_at=look_at, orbit=orbit, width=width, height=height,
                                 config=cfg, background=background, background_kind=background_kind,
                                 env_yaw_deg=env_yaw_deg, exclude=exclude, fps=fps, progress=cb)

        def human(s):
            c = console()
            c.print(f"rendered {s['frames']} frame(s) {s['width']}x{s['height']}, {s['ms_per_frame']:.0f} ms/frame "
                    f"({s['surfels']} surfels, k={s['k']})")
            c.print(f"  {s['paths'][0]}" + (f" ... {s['paths'][-1]}" if len(s['paths']) > 1 else ""))
            if "gif" in s:
                c.print(f"  animation: {s['gif']}")

        emit(summary, json_out, human)

    @groups["eval"].command("loo")
    @cli_errors
    def loo_cmd(
        model: Path = typer.Argument(..., help="Model folder."),
        views: Optional[str] = typer.Option(None, "--views", help="all (default) | every:N | camera:C | comma list of "
                                            "view ids or indices."),
        k: int = typer.Option(_D.k, "--k", help=_K_HELP),
        filter_var: float = typer.Option(_D.filter, "--filter", help=_FILTER_HELP),
        epsilon_z: float = typer.Option(_D.epsilon_z, "--epsilon-z", help=_EPS_HELP),
        cutoff: float = typer.Option(_D.cutoff_sigma, "--cutoff", help=_CUTOFF_HELP),
        sigma_radius: float = typer.Option(_D.sigma_radius, "--sigma-radius", help=_SIGMA_HELP),
        out: Optional[Path] = typer.Option(None, "--out", help="Folder for loo.json and loo_sheet.png (default MODEL/pictures)."),
        json_out: bool = typer.Option(False, "--json", help="Print {views, psnr_mean, ssim_mean, alpha_mae, per_view} on stdout."),
    ):
        """Leave-one-out: render each chosen captured view without blending it, compare with its photograph
        (PSNR, SSIM, alpha MAE inside the union of the masks), and write a contact sheet photo | render | error."""
        from .evaluate import select_views  # noqa: F401  (fail fast on import errors)
        from .runner import run_loo

        cfg = _config(k, filter_var, epsilon_z, cutoff, sigma_radius)
        with progress("leave-one-out", None) as cb:
            summary = run_loo(model, views=views, config=cfg, out=out, progress=cb)

        def human(s):
            c = console()
            c.print(f"leave-one-out over {len(s['views'])} views: PSNR {s['psnr_mean']:.2f} dB, "
                    f"SSIM {s['ssim_mean']:.4f}, alpha MAE {s['alpha_mae']:.4f} ({s['ms_per_view']:.0f} ms/view)")
            if "sheet" in s:
                c.print(f"  contact sheet: {s['sheet']}")
            c.print(f"  details: {s['json']}")

        emit(summary, json_out, human)
