"""A small fitted model for the tests of what reads ``MODEL/optimized/`` (render,
export, view): the analytic sphere model of :mod:`opacityhull.render.synthetic` (a
model folder written directly, no capture or build) with its surfels fitted to all its
views by :func:`opacityhull.optimize.fit.fit_model` (a few seconds at 64×48), so the
SH, the tangent scales and the opacities are the fitting's own, not a start value.

    import fitted                                  # tests/ is on sys.path
    root = fitted.sphere(tmp_path_factory)         # built once per run (memoised)
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

_MEMO: dict[str, Path] = {}

#: 60 steps, SH grown to degree 1 at step 30 and one densification at step 40: every
#: parameter the consumers read differs from its start value, and the f_rest_* columns exist
FIT = {"iterations": 60, "sh_degree": 1, "sh_degree_every": 30, "densify_from": 40, "densify_every": 100}


def sphere(tmp_path_factory, *, n_surfels: int = 2000, width: int = 64, height: int = 48) -> Path:
    """The fitted analytic sphere (24 views, 8 table angles × 3 elevations); the same
    folder for the same arguments within a run (callers must not modify it)."""
    key = f"{n_surfels}-{width}-{height}"
    if key in _MEMO:
        return _MEMO[key]
    from opacityhull.model import OpacityHullModel
    from opacityhull.optimize.config import fit_preset
    from opacityhull.optimize.fit import fit_model
    from opacityhull.render.synthetic import write_sphere_model

    root = tmp_path_factory.mktemp("fitted") / "sphere"
    write_sphere_model(root, n_surfels=n_surfels, width=width, height=height, table_step_deg=45.0)
    V = len(OpacityHullModel.open(root).views)
    fit_model(root, train_views=list(range(V)), config=replace(fit_preset("fast"), **FIT))
    _MEMO[key] = root
    return root
