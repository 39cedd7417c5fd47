"""``opacityhull demo``: the main job on the built-in simulated rig, end to end."""

from __future__ import annotations

from pathlib import Path

import typer

from .cliutil import cli_errors


def register(app, groups) -> None:
    @app.command("demo")
    @cli_errors
    def demo(
        out: Path = typer.Option(Path("out/demo"), "--out", help="Folder for the session, model and pictures."),
        json_out: bool = typer.Option(False, "--json", help="Print a machine-readable summary."),
        with_glass: bool = typer.Option(
            True,
            "--with-glass/--no-glass",
            help="Add the relit-glass step (natural-illumination capture of sim:builtin:glass, 2-3 minutes).",
        ),
    ):
        """Run capture → build → render → relight on the simulated rig, write the viewer bundle, and say where
        the pictures are and how to open the model in a browser."""
        from .demo_runner import run_demo

        run_demo(out, as_json=json_out, with_glass=with_glass)
