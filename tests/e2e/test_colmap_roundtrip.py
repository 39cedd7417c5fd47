"""#33: the project's COLMAP export keeps α (RGBA PNG), so export colmap → import colmap →
build round-trips on the tiny plan (it wrote RGB over black and could not be imported)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import invoke_cli

pytestmark = pytest.mark.slow


def test_export_colmap_import_build_round_trip(sim_cache, tmp_path):
    from opacityhull.model import OpacityHullModel

    model_dir = sim_cache.built("diffuse", "builtin:tiny", 1.0, cameras="auto", reflectance=True)
    ex, sess, again = tmp_path / "colmap", tmp_path / "session", tmp_path / "model"
    r = invoke_cli(["export", model_dir, "--format", "colmap", "--out", ex])
    assert r.exit_code == 0, r.output
    r = invoke_cli(["import", "colmap", "--model", ex / "sparse" / "0", "--images", ex / "images", "--out", sess])
    assert r.exit_code == 0, r.output
    r = invoke_cli(["build", sess, "--out", again, "--no-pictures"])
    assert r.exit_code == 0, r.output
    a, b = OpacityHullModel.open(model_dir), OpacityHullModel.open(again)
    assert len(b.views) == len(a.views) and len(b.surfels) > 0
    # the rebuilt hull images where the original does: the mattes' coverage agrees
    cov = [(a.load_view_rgba(i)[..., 3] > 0.5, b.load_view_rgba(i)[..., 3] > 0.5) for i in range(len(a.views))]
    iou = np.mean([(x & y).sum() / max(1, (x | y).sum()) for x, y in cov])
    assert iou > 0.95, iou
