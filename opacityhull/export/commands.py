"""CLI of :mod:`opacityhull.export`: ``opacityhull export MODEL --format F --out DIR``."""

from __future__ import annotations

from pathlib import Path

import typer

from ..cliutil import JsonSummaryFlag, ModelDirArg, check_model_dir, cli_errors, console, emit


def register(app, groups) -> None:
    @app.command("export")
    @cli_errors
    def export_cmd(
        model: ModelDirArg,
        fmt: str = typer.Option(..., "--format", help="nerfstudio | colmap | ply | opencv | mesh."),
        out: Path = typer.Option(..., "--out", help="Output folder (created; must be empty unless --overwrite)."),
        overwrite: bool = typer.Option(
            False,
            "--overwrite",
            help="Replace an earlier export in --out (only a folder holding nothing but what export wrote there).",
        ),
        sh_degree: int = typer.Option(
            3, "--sh-degree", help="ply: SH degree (1-3) of splats.ply's view-dependent colour."
        ),
        splats: str = typer.Option(
            "auto",
            "--splats",
            help="ply: fitted (the splats of build --optimize) | hull (the hull's surfels, SH fit to the views) "
            "| auto (fitted when the model has splats fitted from this build).",
        ),
        max_points: int = typer.Option(50000, "--max-points", help="colmap: at most this many surfels as points3D."),
        nerfstudio_alpha: str = typer.Option(
            "rgba", "--nerfstudio-alpha", help="nerfstudio: 'rgba' PNGs, or 'mask' (RGB + single-channel mask_path)."
        ),
        mesh_method: str = typer.Option(
            "marching-cubes", "--mesh-method", help="mesh: 'marching-cubes' (watertight) or 'umbrella' (PMR)."
        ),
        json_out: JsonSummaryFlag = False,
    ):
        """Export a model for other tools: nerfstudio, COLMAP (sparse/0 text+binary), PLY (points + 3DGS splats), OpenCV YAML, mesh (PLY + OBJ with vertex colours)."""
        from .formats import FORMATS, export_model

        check_model_dir(model)
        if fmt not in FORMATS:
            from ..errors import InputError

            raise InputError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
        opts = {
            "ply": {"sh_degree": sh_degree, "splats": splats},
            "colmap": {"max_points": max_points},
            "nerfstudio": {"alpha": nerfstudio_alpha},
            "mesh": {"method": mesh_method},
        }.get(fmt, {})
        summary = export_model(model, fmt, out, overwrite=overwrite, **opts)

        def human(s):
            extra = ", ".join(f"{k} {v}" for k, v in s.items() if k not in ("format", "model", "out"))
            console().print(f"exported {s['model']} as {s['format']} to {s['out']} ({extra})")

        emit(summary, json_out, human)
