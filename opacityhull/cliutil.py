"""Shared CLI plumbing: JSON summaries, error → exit-code mapping, progress bars.

Every command keeps stdout for its result (a JSON object with ``--json``) and writes
progress and messages to stderr, so ``opacityhull ... --json | jq`` always works.
"""

from __future__ import annotations

import functools
import json
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, TypeVar, overload
from collections.abc import Callable, Iterator, Mapping, Sequence

import typer

from .errors import EXIT_CODES, InputError, OpacityHullError, Terminated, write_error
from .jsonio import to_jsonable as to_jsonable  # the CLI's --json; library modules import .jsonio

_C = TypeVar("_C", bound=str)

__all__ = [
    "cli_errors",
    "emit",
    "error_message",
    "writing_to",
    "progress",
    "progress_bar",
    "option_group",
    "scheduler_options",
    "console",
    "ProgressCallback",
    "step_progress",
    "to_jsonable",
    "JsonFlag",
    "JsonSummaryFlag",
    "ModelDirArg",
    "SessionDirArg",
    "env_yaw_options",
    "pick_env_yaw",
    "check_choice",
    "check_model_dir",
    "check_orbit_fps",
    "flag_names",
    "terminate_as_interrupt",
]

ProgressCallback = Callable[[int, int], None]

# Options and arguments declared the same way by several commands: one declaration, so
# their flags and help cannot drift apart. Use as ``json_out: JsonFlag = False``.
#: ``--json`` of commands whose result is one JSON object (capture, session, import).
JsonFlag = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")]
#: ``--json`` of commands that print a summary of what they wrote (export, relight).
JsonSummaryFlag = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")]
#: The MODEL argument of the commands that read a built model (export, view).
ModelDirArg = Annotated[Path, typer.Argument(help="Model folder (model.toml, surfels.ply, views/).")]
#: The DIRECTORY argument of ``session verify|info|hdr``.
SessionDirArg = Annotated[Path, typer.Argument(help="Session folder.")]


def env_yaw_options(default: float | None, help: str) -> dict[str, tuple[Any, Any]]:
    """``--env-yaw-deg`` (``default``, ``help``) and its hidden old spelling ``--yaw-deg``,
    for :func:`option_group` with ``build=pick_env_yaw`` (``render``, ``relight``)."""
    return {
        "env_yaw_deg": (float | None, typer.Option(default, "--env-yaw-deg", help=help)),
        "yaw_deg_alias": (
            float | None,
            typer.Option(None, "--yaw-deg", hidden=True, help="Old name of --env-yaw-deg."),
        ),
    }


def pick_env_yaw(env_yaw_deg: float | None, yaw_deg_alias: float | None) -> float | None:
    """The value of :func:`env_yaw_options`: the old spelling wins where it is given."""
    return env_yaw_deg if yaw_deg_alias is None else yaw_deg_alias


@overload
def check_choice(
    flag: str, value: str, choices: Sequence[_C], *, one_of: bool = False, error: type[InputError] = InputError
) -> _C: ...
@overload
def check_choice(
    flag: str, value: None, choices: Sequence[_C], *, one_of: bool = False, error: type[InputError] = InputError
) -> None: ...
@overload
def check_choice(
    flag: str, value: str | None, choices: Sequence[_C], *, one_of: bool = False, error: type[InputError] = InputError
) -> _C | None: ...
def check_choice(
    flag: str, value: str | None, choices: Sequence[_C], *, one_of: bool = False, error: type[InputError] = InputError
) -> _C | None:
    """``value`` of ``flag`` as one of ``choices`` (None stays None: the option was left
    out and the config's default applies), else ``error`` naming the flag, the value and
    the choices: "expected a, b or c", or with ``one_of`` "expected one of a, b, c"."""
    if value is None:
        return None
    for c in choices:
        if value == c:
            return c
    if one_of:
        listing = f"one of {', '.join(choices)}"
    else:
        listing = " or ".join([", ".join(choices[:-1]), choices[-1]]) if len(choices) > 1 else choices[0]
    raise error(f"{flag} {value!r}: expected {listing}")


@contextmanager
def flag_names(fields: Mapping[str, str]) -> Iterator[None]:
    """Name the CLI flags, not the config fields, in the bad-input errors raised inside
    the block: ``fields`` maps a field (``hull_res``, ``RenderConfig.k``) to its flag
    (``--hull-res``, ``--k``). The user typed the flag; the dataclass field means
    nothing to them."""
    import re

    try:
        yield
    except InputError as e:
        msg = str(e)
        new = msg
        for name in sorted(fields, key=len, reverse=True):
            new = re.sub(rf"(?<![\w.-]){re.escape(name)}\b", fields[name], new)
        if new == msg:
            raise
        raise type(e)(new) from None


def check_model_dir(model: Path) -> None:
    """The MODEL argument: a path that is not there, or a file, is bad input (exit 2)."""
    if not model.exists():
        raise InputError(f"{model}: no such model folder")
    if not model.is_dir():
        raise InputError(f"{model} is a file, expected a model folder (from `opacityhull build`)")


def check_orbit_fps(orbit: int | None, fps: float) -> None:
    """``--orbit N`` (frames, when given) and ``--fps`` of the commands that write an orbit."""
    import math

    if orbit is not None and orbit < 1:
        raise InputError(f"--orbit {orbit}: expected at least 1 frame")
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps {fps}: expected a frame rate > 0")


def console():
    from rich.console import Console

    # no emoji: user values reach the messages (`--view 0,:smile:` was shown as '0,😄')
    return Console(stderr=True, emoji=False)


def out_console():
    """A rich console on stdout: for the commands whose job is to print (``sim scenes``,
    ``sim explain``, ``session info``), so ``| less`` and ``> file`` get their text."""
    from rich.console import Console

    return Console(stderr=False)


def emit(summary: dict, as_json: bool, human: Callable[[dict], None] | None = None, *, primary: bool = False) -> None:
    """Print ``summary`` as one JSON line on stdout (``as_json``), else call ``human``.
    ``primary``: ``human`` prints the command's result to stdout (:func:`out_console`),
    so no hint that the text went to stderr."""
    if as_json:
        sys.stdout.write(json.dumps(to_jsonable(summary), sort_keys=False) + "\n")
        sys.stdout.flush()
    elif human is not None:
        human(summary)
        if not primary:
            _stdout_hint()
    else:
        from rich.pretty import pprint

        pprint(to_jsonable(summary), console=console())
        _stdout_hint()


def _stdout_hint() -> None:
    """Human text goes to stderr (stdout is for ``--json``); when stdout is redirected
    (``session info > f``) say so, or the user finds an empty file and no reason."""
    try:
        redirected = not sys.stdout.isatty() and sys.stderr.isatty()
    except (AttributeError, ValueError):
        return
    if redirected and os.environ.get("OPACITYHULL_NO_HINT") is None:
        sys.stderr.write(
            "note: the text above went to stderr; stdout is for --json (add --json to capture the result with > or |)\n"
        )


def error_message(exc: BaseException) -> str:
    """The one-line message for ``exc``, escaped for rich: a message such as "at least
    one [[rig.cameras]] entry is required" must reach the user with its brackets."""
    from rich.markup import escape

    return escape(str(exc) or type(exc).__name__)


def _known_error(exc: BaseException) -> OpacityHullError | None:
    """``exc`` as the error the user can act on, or None for a real bug.

    A full or read-only disk (``OSError`` ENOSPC/EROFS/EACCES) is a :class:`WriteError`
    naming the path; a missing file is bad input (exit 2), not corrupt data."""
    if isinstance(exc, OpacityHullError):
        return exc
    if isinstance(exc, OSError):
        err = write_error(exc)
        if err is not None:
            return err
        if isinstance(exc, (FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError)):
            name = exc.filename if exc.filename is not None else ""
            return InputError(f"{name}: {exc.strerror or exc}".lstrip(": "))
    return None


@contextmanager
def writing_to(path) -> Iterator[None]:
    """Attribute a full or read-only disk met inside the block to ``path`` (the command's
    ``--out``) when the failing call did not say which file it was writing."""
    try:
        yield
    except OSError as e:
        err = write_error(e, e.filename if e.filename is not None else path)
        if err is None:
            raise
        raise err from None


def cli_errors(fn):
    """Decorator for typer commands: known errors become a one-line message on stderr and
    the exit code of their class; Ctrl-C exits 130."""
    import typer

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (OpacityHullError, OSError) as e:
            err = _known_error(e)
            if err is None:
                raise
            # one unbroken line: the message names files and values a user copies (Rich
            # would otherwise break a long path mid-word at its 80-column default)
            console().print(f"[bold red]error:[/] {error_message(err)}", highlight=False, markup=True, soft_wrap=True)
            raise typer.Exit(code=err.exit_code) from None
        except Terminated as e:
            console().print(f"[yellow]{e}[/] (the same clean-up as Ctrl-C ran)")
            raise typer.Exit(code=e.exit_code) from None
        except KeyboardInterrupt:
            console().print("[yellow]interrupted[/]")
            raise typer.Exit(code=EXIT_CODES["interrupted"]) from None

    return wrapper


def progress_bar(label: str = "{task.description}"):
    """The rich ``Progress`` every command shows on stderr: ``label`` (a rich template
    over the task), bar, done/total, elapsed and ETA."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn(f"[bold]{label}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("elapsed"),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        console=console(),
        transient=False,
    )


def option_group(options: Mapping[str, tuple[Any, Any]], *, into: str, before: str | None = None, build=None):
    """Decorator for a typer command: options declared once, shared by several commands.

    ``options`` maps a parameter name to ``(type, typer.Option(default, "--flag", help=...))``.
    They become parameters of the command (typer reads the signature), placed before the
    parameter ``before`` (else last), so ``--help`` lists them where they belong. The
    command takes one keyword-only parameter ``into`` instead: the dict of their values,
    or ``build(**values)`` when ``build`` is given (for conversions that cannot fail:
    checks belong in the command body, in the order its messages promise).
    Put ``@cli_errors`` above this decorator."""
    import inspect

    def decorate(fn):
        sig = inspect.signature(fn, eval_str=True)
        params = [p for p in sig.parameters.values() if p.name != into]
        if len(params) == len(sig.parameters):
            raise TypeError(f"{fn.__name__}: option_group(into={into!r}) needs a keyword-only parameter {into!r}")
        group = [
            inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=option, annotation=kind)
            for name, (kind, option) in options.items()
        ]
        names = [p.name for p in params]
        # default: after the last positional-or-keyword parameter (keyword-only ones stay last)
        ends = [i for i, p in enumerate(params) if p.kind is not inspect.Parameter.POSITIONAL_OR_KEYWORD]
        at = names.index(before) if before is not None else (ends[0] if ends else len(params))
        params[at:at] = group

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            values = {name: kwargs.pop(name) for name in options}
            kwargs[into] = build(**values) if build is not None else values
            return fn(*args, **kwargs)

        # typer builds the command from the signature and the annotations
        setattr(wrapper, "__signature__", sig.replace(parameters=params))  # noqa: B010  pyright: functools wrapper type has no such attribute
        wrapper.__annotations__ = {p.name: p.annotation for p in params}
        return wrapper

    return decorate


def scheduler_options(help: str, *, workers: bool = False) -> dict[str, tuple[Any, Any]]:
    """``--scheduler`` (with ``help``: what runs there), ``--scheduler-timeout`` and, with
    ``workers``, ``--workers``, for :func:`option_group`: their values are the keyword
    arguments of :func:`opacityhull.executor.open_executor`."""
    import typer

    opts: dict[str, tuple[Any, Any]] = {
        "scheduler": (str, typer.Option("serial", "--scheduler", help=help)),
        "timeout_s": (
            float,
            typer.Option(10.0, "--scheduler-timeout", help="Seconds to wait for a tcp:// scheduler to answer."),
        ),
    }
    if workers:
        opts["workers"] = (
            int | None,
            typer.Option(None, "--workers", help="threads/processes: pool size (default: the cores)."),
        )
    return opts


@contextmanager
def progress(description: str, total: int | None = None, *, enabled: bool = True) -> Iterator[ProgressCallback]:
    """A rich progress bar with ETA on stderr; yields ``callback(done, total)``."""
    if not enabled:
        yield lambda done, total=None: None
        return
    with progress_bar() as bar:
        task = bar.add_task(description, total=total)

        def cb(done: int, tot: int | None = None) -> None:
            bar.update(task, completed=done, total=tot if tot is not None else total)

        yield cb


@contextmanager
def step_progress(command: str) -> Iterator[tuple[Callable[[str], None], Callable[..., None]]]:
    """Progress of a command made of named steps, on stderr; yields ``(on_step, progress)``:
    ``on_step(name)`` when a step starts, ``progress(done, total=None, note=None)`` within it
    (``note``: a running figure shown beside the step's name).

    On a terminal there is one live bar line, the current step's (its count and ETA are
    the step's). A pipe or a log gets no live bar (rich draws only its last frame there),
    so each finished step prints ``COMMAND: STEP done in S s`` instead. Either way the
    command ends with ``COMMAND: done in S s``.
    """
    t0 = time.perf_counter()
    with progress_bar(f"{command}: {{task.description}}") as bar:
        plain = not bar.console.is_terminal
        # a new task per step: rich's update() ignores total=None, so resetting one task
        # left the previous step's "0/24" on every later step
        tasks = [bar.add_task("start", total=None)]
        step = {"name": "", "t": t0}

        def finish_step() -> None:
            now = time.perf_counter()
            if plain and step["name"]:
                bar.console.print(f"{command}: {step['name']} done in {now - step['t']:.1f} s", highlight=False)
            step["t"] = now

        def on_step(name: str) -> None:
            finish_step()
            step["name"] = name
            bar.remove_task(tasks[-1])
            tasks.append(bar.add_task(name, total=None))

        def progress(done: int, total: int | None = None, note: str | None = None) -> None:
            # note: a figure of the step's own beside its count (the fit's running PSNR)
            if note is None:
                bar.update(tasks[-1], completed=done, total=total)
            else:
                bar.update(tasks[-1], completed=done, total=total, description=f"{step['name']}: {note}")

        yield on_step, progress
        finish_step()
        bar.remove_task(tasks[-1])
    bar.console.print(f"{command}: done in {time.perf_counter() - t0:.1f} s", highlight=False)


class terminate_as_interrupt:
    """While active (main thread only), SIGTERM and SIGHUP raise :class:`Terminated`, a
    KeyboardInterrupt: a scheduler or systemd stopping the job gets what Ctrl-C gets —
    ``rig.safe()`` (feed hold, lights off, displays blank), the lock removed, a resumable
    session — and the exit code 128 + signal (143, 129). Ctrl-C itself is untouched, and
    so is a signal already ignored (``nohup`` ignores SIGHUP)."""

    SIGNALS = ("SIGTERM", "SIGHUP")

    def __init__(self):
        self._old: dict = {}

    def _raise(self, signum, frame):
        import signal as _signal

        # one is enough: further signals during the clean-up are ignored until we leave
        for name in self.SIGNALS:
            sig = getattr(_signal, name, None)
            if sig is not None:
                _signal.signal(sig, _signal.SIG_IGN)
        raise Terminated(signum)

    def __enter__(self):
        import signal as _signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return self
        for name in self.SIGNALS:
            sig = getattr(_signal, name, None)
            if sig is None:
                continue
            try:
                if _signal.getsignal(sig) is _signal.SIG_IGN:
                    continue  # `nohup opacityhull capture ...` asked to ignore hangups: keep it so
                self._old[sig] = _signal.signal(sig, self._raise)
            except ValueError:  # not the main interpreter
                pass
        return self

    def __exit__(self, *exc):
        import signal as _signal

        for sig, h in self._old.items():
            _signal.signal(sig, h)
        self._old.clear()
        return False
