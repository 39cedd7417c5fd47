"""Leave-one-out on the demo plan's views (`capture` → `build` → leave-one-out), for
``builtin:diffuse`` and ``builtin:fuzzy``.

The plan is ``tests/render/data/demo_views.toml``: builtin:demo's 6 cameras × 8 table
angles (48 views, 45° apart on the table), its two backdrop pattern pairs with
object-absent shots and its lightfield, without the calibration and reflectance phases
(leave-one-out needs neither; a test below keeps the shared sections equal to the
builtin plan). Models are built with the simulator's true cameras, hull resolution 96,
like tests/render/test_loo_sim.py, whose 18-view CI plan these results must beat.

The fuzzy tuft's demo-plan capture also serves the reconstruction e2e test of fractional
mattes (tests/e2e/test_build_sim.py), so the suite captures the tuft once.

How the thresholds were chosen (measured values in the test docstrings):

* Absolute floors: the measured means minus 0.7 dB PSNR, 0.02 SSIM, plus 0.01 alpha
  MAE. The captures are Monte Carlo renders of random backdrop patterns with a fixed
  seed; re-capturing the diffuse cup with another seed (12 instead of 11) moved the
  means by 0.06 dB, 0.0014 SSIM and 0.0003 alpha MAE, so the margins are ten times the
  seed spread, yet smaller than what losing a renderer feature costs (on the CI plan:
  edge coverage off −1.0 dB, the textbook prefilter H = I −2.4 dB).
* Relative checks carry the meaning: blending (k = 4) must beat the nearest remaining
  view alone (k = 1, measured +0.9 dB diffuse, +0.7 dB fuzzy), and the demo plan's 48
  views must beat the CI plan's 18 on the diffuse cup by at least 2 dB (measured +3.1
  dB) — view interpolation improves when the held-out view's neighbours are closer (45°
  instead of 60° on the table, six camera heights instead of three).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import simcache
from opacityhull.model import OpacityHullModel
from opacityhull.evaluate.loo import leave_one_out
from opacityhull.render.renderer import RenderConfig, prepare_model_views

pytestmark = pytest.mark.slow

PLAN = Path(__file__).parent / "data" / "demo_views.toml"
# leave-one-out scores the hull-and-blend model (ULR): built without the default fit
BUILD = dict(hull_res=96, cameras="groundtruth", reflectance=False, pictures=False, optimize="none")


def build(scene: str, plan, *, alpha_threshold: float) -> Path:
    return simcache.built(scene, plan, simcache.CI_SCALE, alpha_threshold=alpha_threshold, **BUILD)


def prebuild() -> None:
    """The 48-view captures, taken in the background from the start of the run
    (tests/simcache.py :func:`~simcache.prefetch`)."""
    for scene, plan in (("diffuse", PLAN), ("fuzzy", PLAN), ("diffuse", simcache.CI_PLAN)):
        simcache.prefetch(scene, plan, simcache.CI_SCALE)


def test_plan_is_the_demo_plan_without_calibration_and_reflectance():
    import opacityhull.acquire.plan as plan_mod

    demo = tomllib.loads((Path(plan_mod.__file__).with_name("plans") / "demo.toml").read_text())
    ours = tomllib.loads(PLAN.read_text())
    for section in ("table", "exposures", "timing"):
        assert ours[section] == demo[section], section
    assert ours["plan"]["seed"] == demo["plan"]["seed"]
    assert ours["plan"].get("cameras") == demo["plan"].get("cameras")  # all cameras in both
    assert set(ours["phases"]) == {"matting", "lightfield"}
    for phase in ("matting", "lightfield"):
        assert ours["phases"][phase] == demo["phases"][phase], phase


def loo(model_dir: Path, **cfg):
    m = OpacityHullModel.open(model_dir)
    pv = prepare_model_views(m)
    return m, pv, leave_one_out(m, prepared=pv, config=RenderConfig(**cfg))


@pytest.mark.timeout(2400)
def test_loo_demo_plan_builtin_diffuse(tmp_path):
    """Measured (pixel shading, crop-rendered captures, whose mattes no longer carry
    background specks into the metric's mask): PSNR 24.32 dB, SSIM 0.891, alpha MAE
    0.025; surfel shading 23.75 / 0.871 / 0.032; k = 1 23.04 dB; the CI plan 20.69 dB.
    Margins as before (about 10x the seed spread). Former simulator, surfel shading:
    PSNR 25.05 dB, SSIM 0.904, alpha MAE 0.028 over the 48 views (seed 12:
    25.11 dB, 0.906, 0.028); nearest view only (k = 1) 24.15 dB; the CI plan's 18 views
    21.93 dB."""
    model = build("diffuse", PLAN, alpha_threshold=0.5)
    m, pv, s = loo(model)
    assert len(s["per_view"]) == 48
    assert s["psnr_mean"] > 23.8 and s["ssim_mean"] > 0.875 and s["alpha_mae"] < 0.035
    nearest = leave_one_out(m, prepared=pv, config=RenderConfig(k=1))
    assert s["psnr_mean"] > nearest["psnr_mean"] + 0.5
    ci = loo(build("diffuse", simcache.CI_PLAN, alpha_threshold=0.5))[2]
    assert len(ci["per_view"]) == 18
    assert s["psnr_mean"] > ci["psnr_mean"] + 2.0


@pytest.mark.timeout(2400)  # the tuft's capture took ~300 s on the shared 2-core machine
def test_loo_demo_plan_builtin_fuzzy_cli(tmp_path):
    """Through the CLI (`eval loo --json`), on a conservative hull (silhouette = alpha >
    0.05, as in the opacity-hull paper: the fibres' fringe has alpha < 0.5 and the
    default hull cuts it off). Measured (pixel shading, crop-rendered captures): PSNR
    22.73 dB, SSIM 0.705, alpha MAE 0.081; surfel 22.51 / 0.675 / 0.083; k = 1 21.62 dB.
    Former simulator, surfel shading: PSNR 23.25 dB, SSIM 0.725, alpha MAE 0.071 over
    the 48 views; nearest view only 22.52 dB."""
    model = build("fuzzy", PLAN, alpha_threshold=0.05)
    p = subprocess.run(
        [sys.executable, "-m", "opacityhull.cli", "eval", "loo", str(model), "--out", str(tmp_path), "--json"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    s = json.loads(p.stdout.strip().splitlines()[-1])
    assert len(s["views"]) == 48 and len(s["per_view"]) == 48 and Path(s["sheet"]).is_file()
    assert s["psnr_mean"] > 22.25 and s["ssim_mean"] > 0.69 and s["alpha_mae"] < 0.09
    m = OpacityHullModel.open(model)
    nearest = leave_one_out(m, prepared=prepare_model_views(m), config=RenderConfig(k=1))
    assert s["psnr_mean"] > nearest["psnr_mean"] + 0.4
