"""The one place of the environment-map convention: direction ↔ equirectangular (u, v).

Environment maps are equirectangular (lat-long), +Y up, the centre column looking along
+Z — the OpenEXR / Mitsuba convention (pinned against Mitsuba's own ``envmap`` emitter by
``tests/sim/test_sim_groundtruth.py``). A direction d = (x, y, z) maps to

    u = atan2(x, −z) / 2π  (wrapped to [0, 1)),   v = acos(y / |d|) / π,

so +Z is the centre column (u = ½), −Z the left/right seam, +X at u = ¼ (the map is seen
from inside), +Y the top row. Texel (i, j) has its centre at ((j + ½)/W, (i + ½)/H).

A zero, NaN or Inf direction has no (u, v): ``invalid="raise"`` (the default: lighting
code, where such a direction is a bug) raises :class:`InputError`; ``invalid="zenith"``
(backgrounds, where a degenerate pixel ray must not stop a render) maps it to the top
row, u = 0. Exactly at a pole u is undefined and set to 0 (every column is that point).

The render stage's backgrounds (``render/background.py``), the relighting's
``EnvironmentMap`` (``relight/envmap.py``) and the simulator's ground truth
(``sim/groundtruth.py``) all convert through these two functions.

A map given by name (``builtin:NAME``, a probe shipped in :mod:`opacityhull.data`) is
resolved here too, for every command that takes one (``render --background``,
``relight --envmap``, ``view --envmap``): :func:`resolve_envmap_path` and its yaw,
:func:`default_yaw_deg`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np

from .errors import InputError, ShapeError

__all__ = ["direction_to_uv", "uv_to_direction", "resolve_envmap_path", "default_yaw_deg", "is_builtin_probe"]


def is_builtin_probe(spec) -> bool:
    """Whether ``spec`` names a shipped probe (``builtin:NAME``)."""
    return isinstance(spec, str) and spec.strip().startswith("builtin:")


def resolve_envmap_path(spec) -> Path:
    """A path, or ``builtin:NAME`` for a probe shipped with the package
    (:func:`opacityhull.data.probe_path`: ennis, grace, pisa, uffizi, wells; an unknown
    name is an :class:`InputError` listing them)."""
    if is_builtin_probe(spec):
        from .data import probe_path

        return probe_path(spec.strip())
    return Path(spec)


def default_yaw_deg(spec) -> float:
    """The yaw that brings ``spec`` to the project convention when the user gives none:
    180° for the shipped ICT-convention probes (``builtin:NAME``), else 0."""
    if is_builtin_probe(spec):
        from .data import PROBE_YAW_DEG

        return PROBE_YAW_DEG
    return 0.0


def direction_to_uv(directions, *, invalid: Literal["raise", "zenith"] = "raise") -> tuple[np.ndarray, np.ndarray]:
    """(…, 3) directions (any length) → (u, v), u ∈ [0, 1), v ∈ [0, 1] (module docstring)."""
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ShapeError(f"directions have shape {d.shape}, expected (..., 3)")
    n = np.linalg.norm(d, axis=-1)
    bad = ~np.isfinite(n) | (n < 1e-12)
    if np.any(bad):
        if invalid == "raise":
            raise InputError(
                f"{int(np.count_nonzero(bad))} direction(s) are zero, NaN or Inf; expected finite non-zero vectors"
            )
        if invalid != "zenith":
            raise InputError(f"invalid={invalid!r}: expected 'raise' or 'zenith'")
        d = np.where(bad[..., None], np.array([0.0, 1.0, 0.0]), d)
        n = np.where(bad, 1.0, n)
    # atan2 of (distance from the axis, height) rather than arccos(y / n): arccos loses
    # all precision within ~1e-8 rad of the poles (1 − cos θ falls below the float64 step)
    v = np.arctan2(np.hypot(d[..., 0], d[..., 2]), d[..., 1]) / math.pi
    u = np.arctan2(d[..., 0], -d[..., 2]) / (2.0 * math.pi)
    u = u - np.floor(u)
    u = np.where(u >= 1.0, 0.0, u)  # -0.0 and rounding can give exactly 1
    return u, v


def uv_to_direction(u, v) -> np.ndarray:
    """Inverse of :func:`direction_to_uv`: unit directions (…, 3) of (u, v)."""
    phi = 2.0 * math.pi * np.asarray(u, dtype=np.float64)
    theta = math.pi * np.asarray(v, dtype=np.float64)
    s = np.sin(theta)
    return np.stack(np.broadcast_arrays(s * np.sin(phi), np.cos(theta), -s * np.cos(phi)), axis=-1)
