"""JSON-ready values: the one conversion every ``report.json``, ``--json`` summary and
manifest goes through (NumPy scalars and arrays made plain, paths as strings, NaN and
Inf as null). Library modules import it from here, not from the CLI's ``cliutil``
(which pulls typer and rich)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["to_jsonable"]


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
