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
    add_completion=True,  # --install-completion / --show-completion for bash, zsh, fish
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
    "opacityhull.calibrate.commands",
    "opacityhull.render.commands",
    "opacityhull.relight.commands",
    "opacityhull.evaluate.commands",
    "opacityhull.export.commands",
    "opacityhull.view.commands",
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
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Print the version and exit."
    ),
):
    """opacityhull — capture, reconstruct, render and relight opacity hulls."""


_register_all()


_BOOL_WORDS = {"true": True, "1": True, "yes": True, "on": True, "false": False, "0": False, "no": False, "off": False}


def normalize_argv(argv: list[str]) -> list[str]:
    """``--json true`` / ``--json=false`` as well as plain ``--json``.

    typer's help shows every flag as ``--json <bool>``, so users type a value after it;
    click would then take ``true`` as an extra argument. A boolean word right after a
    flag (or after ``=``) is folded into the flag: true keeps it, false drops it.
    Only the flags listed here are rewritten, so no option's real value is touched."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        name, eq, val = a.partition("=")
        if name in _FOLDED_FLAGS and eq:
            if val.lower() not in _BOOL_WORDS:
                out.append(a)  # let click report it
            elif _BOOL_WORDS[val.lower()]:
                out.append(name)
            i += 1
            continue
        if a in _FOLDED_FLAGS and i + 1 < len(argv) and argv[i + 1].lower() in _BOOL_WORDS:
            if _BOOL_WORDS[argv[i + 1].lower()]:
                out.append(a)
            i += 2
            continue
        out.append(a)
        i += 1
    return out


_FOLDED_FLAGS = {"--json"}


def main() -> None:  # console-script entry point
    import faulthandler
    import signal
    import sys

    # `kill -USR1 PID` prints every thread's stack to stderr: what a stuck capture or build
    # is waiting on, without stopping it (the tests send it before giving up on a child).
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    app(args=normalize_argv(sys.argv[1:]), prog_name="opacityhull")


if __name__ == "__main__":
    main()
