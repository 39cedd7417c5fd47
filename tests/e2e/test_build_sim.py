"""`build` on sessions captured from the Mitsuba-simulated rig (real drivers, emulators,
renders), measured against the simulator's ground truth.

One capture per scene (module fixture) with a CI plan (tests/e2e/data/rc_ci.toml: 3
cameras × 4 table angles, one backdrop pattern pair with object-absent shots, lightfield,
one light) at half the rig's resolution (100×75). The plan has no calibration phase, so the tests take the simulator's true
cameras — explicitly (``cameras="groundtruth"``): calibration is measured by its own
tests, these measure matting, carving and the model.

Thresholds (measured values in the reconstruct report; margins for Monte Carlo noise):

* diffuse cup: alpha MAE < 0.03 (measured ~0.012: edge pixels of the 4-px backdrop cells
  are noisy with one pattern pair); hull IoU in (0.15, 0.6) — the cup's open cavity
  and flutes are invisible to any visual hull: the hull carved from the *true* alphas
  with the same cameras scores the same IoU (0.251 vs 0.251 on the demo plan), so the
  test also requires IoU > 0.95 against that hull; the hull contains ≥ 99.5 % of the
  object.
* fuzzy tuft: alpha MAE < 0.05 (measured 0.023 at full resolution) and ≥ 50 % of the
  pixels with fractional true alpha (0.05..0.95, the sub-pixel fibres) get a fractional
  matte (0.02..0.98; measured 99 %) — a binary mask would score 0 %.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from opacityhull.model import OpacityHullModel
from opacityhull.reconstruct.build import BuildConfig, build_model

PLAN = Path(__file__).parent / "data" / "rc_ci.toml"

pytestmark = pytest.mark.slow


SCALE = 0.5  # 100x75 images: a quarter of the render time


def capture(scene: str, out: Path) -> Path:
    env = dict(os.environ, COLUMNS="400")
    p = subprocess.run([sys.executable, "-m", "opacityhull.cli", "capture", "--rig",
                        f"sim:builtin:{scene}?scale={SCALE}",
                        "--plan", str(PLAN), "--out", str(out), "--json"], capture_output=True, text=True,
                       timeout=1500, env=env)
    if p.returncode != 0:
        raise AssertionError(f"capture failed ({p.returncode}): {p.stderr[-2000:]}")
    return out


@pytest.fixture(scope="module")
def diffuse(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim_diffuse")
    sess = capture("diffuse", root / "session")
    rep = build_model(sess, root / "model", config=BuildConfig(hull_res=96, cameras="groundtruth"),
                      ground_truth=True)
    return sess, root / "model", rep


@pytest.fixture(scope="module")
def fuzzy(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim_fuzzy")
    sess = capture("fuzzy", root / "session")
    rep = build_model(sess, root / "model", config=BuildConfig(hull_res=96, cameras="groundtruth",
                                                               reflectance=False), ground_truth=True)
    return sess, root / "model", rep


def test_diffuse_cup(diffuse):
    sess, model_dir, r = diffuse
    m = r.metrics
    assert m["alpha_views_compared"] == 12
    assert m["alpha_mae"] < 0.03
    assert 0.15 < m["hull_iou"] < 0.6
    assert m["hull_object_in_hull"] > 0.995
    # what the hull loses to the cavity is no fault of ours: against the hull carved
    # from the true alphas with the same cameras, ours agrees to 99.5 % (demo plan)
    assert m["hull_iou_vs_true_alpha_hull"] > 0.95
    assert "debug" in r.camera_source and r.backdrop_source == "object-absent captures"
    model = OpacityHullModel.open(model_dir)
    assert len(model.views) == 12 and len(model.surfels) > 1000
    assert model.has_reflectance and len(model.light_samples) == 1
    rep = json.loads((model_dir / "report.json").read_text())
    assert rep["metrics"]["alpha_mae"] == pytest.approx(m["alpha_mae"])


def test_fuzzy_tuft_mattes_are_fractional(fuzzy):
    sess, model_dir, r = fuzzy
    m = r.metrics
    assert m["alpha_mae"] < 0.05
    assert m["alpha_fractional_pixels"] > 200
    assert m["alpha_fractional_recovered"] > 0.5
    # fibres thinner than a pixel stay below the 0.5 silhouette threshold, so the hull
    # misses the voxels they occupy (measured 3 %; the hull of the *true* alphas misses
    # the same voxels, none of them in the core)
    assert m["hull_object_in_hull"] > 0.95
    model = OpacityHullModel.open(model_dir)
    a = np.stack([model.load_view_rgba(i)[..., 3] for i in range(len(model.views))])
    assert np.mean((a > 0.05) & (a < 0.95)) > 0.005
