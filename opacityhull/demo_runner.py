"""The demo job. Grows with the pipeline: each stage adds its step here."""

from __future__ import annotations

from pathlib import Path

from .cliutil import console, emit


def run_demo(out: Path, *, as_json: bool = False) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"out": str(out), "steps": []}
    emit(summary, as_json, lambda s: console().print(f"demo output in {s['out']}"))
    return summary
