"""CLI commands of `opacityhull.relight` (registered by :mod:`opacityhull.cli`)."""

from __future__ import annotations


def register(app, groups) -> None:
    """Add this stage's commands to the root app and the subcommand groups."""
