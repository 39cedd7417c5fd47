"""Shared CLI plumbing: JSON summaries, error → exit-code mapping, progress bars.

Every command keeps stdout for its result (a JSON object with ``--json``) and writes
progress and messages to stderr, so ``opacityhull ... --json | jq`` always works.
"""

from __future__ import annotations

import functools
import json
import sys
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numpy as np

from .errors import EXIT_CODES, OpacityHullError

__all__ = ["cli_errors", "emit", "progress", "console", "ProgressCallback", "to_jsonable"]

ProgressCallback = Callable[[int, int], None]


def console():
    from rich.console import Console

    return Console(stderr=True)


def to_jsonable(obj: Any):
    """Recursively convert numpy scalars/arrays and paths for ``json.dumps``."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and (obj != obj or obj in (float("inf"), float("-inf"))):
        return None  # JSON has no NaN/Inf
    if hasattr(obj, "__fspath__"):
        return str(obj)
    return obj


def emit(summary: dict, as_json: bool, human: Callable[[dict], None] | None = None) -> None:
    """Print ``summary`` as one JSON line on stdout (``as_json``), else call ``human``."""
    if as_json:
        sys.stdout.write(json.dumps(to_jsonable(summary), sort_keys=False) + "\n")
        sys.stdout.flush()
    elif human is not None:
        human(summary)
    else:
        from rich.pretty import pprint

        pprint(to_jsonable(summary), console=console())


def cli_errors(fn):
    """Decorator for typer commands: known errors become a one-line message on stderr and
    the exit code of their class; Ctrl-C exits 130."""
    import typer

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except OpacityHullError as e:
            console().print(f"[bold red]error:[/] {e}", highlight=False, markup=True)
            raise typer.Exit(code=e.exit_code) from None
        except KeyboardInterrupt:
            console().print("[yellow]interrupted[/]")
            raise typer.Exit(code=EXIT_CODES["interrupted"]) from None

    return wrapper


@contextmanager
def progress(description: str, total: int | None = None, *, enabled: bool = True) -> Iterator[ProgressCallback]:
    """A rich progress bar with ETA on stderr; yields ``callback(done, total)``."""
    if not enabled:
        yield lambda done, total=None: None
        return
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("elapsed"),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        console=console(),
        transient=False,
    ) as bar:
        task = bar.add_task(description, total=total)

        def cb(done: int, tot: int | None = None) -> None:
            bar.update(task, completed=done, total=tot if tot is not None else total)

        yield cb
