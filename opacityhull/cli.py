"""The ``opacityhull`` command: one entry point, subcommands per stage.

The CLI only parses arguments and calls runners. Each stage contributes its commands
through a ``register(app, groups)`` function in ``opacityhull/<stage>/commands.py``;
heavy imports (Mitsuba, OpenCV, numba) happen inside the commands, so ``--help`` is
fast.
"""

from __future__ import annotations

import importlib

import typer

from . import __version__

app = typer.Typer(
    name="opacityhull",
    help="Image-based 3D photography with opacity hulls: drive the rig, capture, build, render, relight.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

GROUPS = {
    "rig": typer.Typer(help="Talk to the rig's devices or emulate them.", no_args_is_help=True),
    "sim": typer.Typer(help="The simulated rig (Mitsuba 3): render, explain effect selection.", no_args_is_help=True),
    "session": typer.Typer(help="Inspect, verify and post-process capture sessions.", no_args_is_help=True),
    "import": typer.Typer(help="Turn external calibrated image sets into sessions.", no_args_is_help=True),
    "eval": typer.Typer(help="Measure a model against held-out photographs or ground truth.", no_args_is_help=True),
}
for _name, _group in GROUPS.items():
    app.add_typer(_group, name=_name)

#: Modules exposing ``register(app, groups)``; order is the order in ``--help``.
COMMAND_MODULES = (
    "opacityhull.rigs.commands",
    "opacityhull.sim.commands",
    "opacityhull.acquire.commands",
    "opacityhull.reconstruct.commands",
    "opacityhull.render.commands",
    "opacityhull.relight.commands",
    "opacityhull.demo",
)


def _register_all() -> None:
    for mod in COMMAND_MODULES:
        importlib.import_module(mod).register(app, GROUPS)


def _version_callback(value: bool):
    if value:
        typer.echo(f"opacityhull {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True,
                                 help="Print the version and exit."),
):
    """opacityhull — capture, reconstruct, render and relight opacity hulls."""


_register_all()


def main() -> None:  # console-script entry point
    app()


if __name__ == "__main__":
    main()
