"""Helpers shared by the benchmark scripts, which import it from their own folder
(``python benchmarks/<name>.py`` puts ``benchmarks/`` first on ``sys.path``).

Running this file does nothing: ``make bench`` runs every ``benchmarks/*.py``.

Where reports go is decided here, once (:func:`out_dir`): a full run writes the tracked
tables and plots in ``benchmarks/out/``; a ``--quick`` run (what ``make bench`` does)
writes the same names under ``benchmarks/out/quick/``, which git ignores, so a quick run
never rewrites a tracked table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from distributed import LocalCluster

#: The tracked reports of full runs.
OUT_FULL = Path(__file__).resolve().parent / "out"
#: Where ``--quick`` runs write (ignored by git).
OUT_QUICK = OUT_FULL / "quick"


def out_dir(argv=None) -> Path:
    """The folder a benchmark writes its reports to: :data:`OUT_QUICK` when its command
    line (``argv``, default ``sys.argv[1:]``) has ``--quick``, else :data:`OUT_FULL`.
    The scripts set their module-level ``OUT`` from it, so the rule is this one place."""
    args = sys.argv[1:] if argv is None else list(argv)
    return OUT_QUICK if "--quick" in args else OUT_FULL


def parser(doc: str | None) -> argparse.ArgumentParser:
    """The command line of a benchmark: ``--help`` prints its module docstring ``doc``
    as written (what it measures and how to read the report)."""
    return argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display needed; the
    backend must be chosen before pyplot is first imported)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def report_head(title: str, *paragraphs: str) -> list[str]:
    """The first lines of a benchmark's Markdown report: the ``# title`` and the
    paragraphs under it (what ran, on which machine), each followed by a blank line."""
    out = [f"# {title}", ""]
    for p in paragraphs:
        out += [p, ""]
    return out


def save_figure(fig, path: Path, *, dpi: float | None = None) -> None:
    """Write the matplotlib figure ``fig`` to ``path`` (the format from its suffix; ``dpi``
    None: the figure's own) as a whole file or none (a temporary file renamed), and
    close the figure."""
    from opacityhull.imageio import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    pyplot().close(fig)


def print_result(res: dict, report: Path, *, as_json: bool) -> None:
    """Print ``res`` as one JSON object on stdout (``--json``), else the Markdown report
    the benchmark wrote at ``report``."""
    if as_json:
        from opacityhull.jsonio import to_jsonable

        print(json.dumps(to_jsonable(res)))
    else:
        print(report.read_text())


@contextlib.contextmanager
def local_cluster(*, n_workers: int, threads_per_worker: int) -> Iterator[LocalCluster]:
    """A Dask ``distributed.LocalCluster`` of ``n_workers`` worker processes with
    ``threads_per_worker`` threads each, on 127.0.0.1, without a dashboard and with its
    logs below ERROR silenced; closed when the block ends. The benchmarks open their
    executor (and so their Client) on its ``scheduler_address``
    (``opacityhull.executor.open_executor``)."""
    from distributed import LocalCluster

    lc = LocalCluster(
        n_workers=n_workers,
        threads_per_worker=threads_per_worker,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,  # pyright: ignore[reportArgumentType]  (None: no dashboard, as distributed documents)
        silence_logs=logging.ERROR,
    )
    try:
        yield lc
    finally:
        lc.close()
