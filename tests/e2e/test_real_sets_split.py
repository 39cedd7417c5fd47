"""The train/test protocol (#29) on real photographs made by others: the Middlebury
templeSR and dinoSR rings (tests/data/real) through ``import colmap`` → ``build
--hold-out every:4`` (views 0, 4, 8, 12 never seen: 12 views to build from) → ``eval
test`` on white and black.

Measured with the defaults, that is with the fit (``--optimize fast``, 900 steps at
half resolution; 2 cores shared by 4 jobs; deterministic: fixed data, seeded fit, no
sampling), mask-union PSNR per test view:

* temple 27.44 / 19.45 / 19.46 / 21.56 dB (mean 21.98, SSIM 0.663); whole image on
  white 19.86 dB (SSIM 0.854), on black 26.37 dB. Its view 0 has a coincident twin (view
  10) among the training views, as in a plain script's split: hence 27.4 dB.
* dino 27.72 / 15.45 / 23.04 / 18.33 dB (mean 21.13, SSIM 0.757); on white 19.90 dB
  (SSIM 0.874), on black 24.69 dB. View 4 sees the dino's underside, which no training
  view's silhouette carves.

Without the fit (``--optimize none``, the hull blended by ULR) the same split scored
temple 18.32 dB (min view 14.96; white 18.78, SSIM 0.884) and dino 17.09 dB (min 10.94;
white 19.27, SSIM 0.875): the fit gains +3.7 / +4.0 dB on the mask union. Whole-image
SSIM on white drops on the temple (0.884 → 0.854): the fitted splats' soft edges against
the ULR's hard silhouette on a large white background. The plain baseline under the same
split (``benchmarks/baseline.py --split every:4``, hull of the 12 training views +
per-pixel ULR) scores 17.72 dB temple / 15.50 dB dino (#29 quotes 17.0 / 16.0 for its own
script): the default build is +4.3 / +5.6 dB above it, past #29's +3 dB goal. The
per-view spread (15-28 dB) says another split would move the mean by a few dB, but this
split is fixed and the computation deterministic: the thresholds sit 0.5 dB below the
means (what single features of the pipeline moved, see test_real_sets.py), so losing one
fails, and at the minimum view 0.5 dB below it; SSIM 0.015 below.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1] / "data" / "real"

pytestmark = pytest.mark.slow

MEASURED = {
    "temple": {"psnr_mask": 21.98, "min_view_mask": 19.45, "psnr_white": 19.86, "ssim_white": 0.854},
    "dino": {"psnr_mask": 21.13, "min_view_mask": 15.45, "psnr_white": 19.90, "ssim_white": 0.874},
}
MARGIN_DB, MARGIN_SSIM = 0.5, 0.015


RINGS = ("temple", "dino")


def build_split(name: str, out: Path) -> None:
    """``import colmap`` and the default build (held out every 4th view) of ring
    ``name`` into ``out/session``, ``out/model``."""
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    src = DATA / f"{name}SR"
    import_colmap(src / "sparse", src / "images", out / "session", masks_dir=src / "masks")
    build_model(out / "session", out / "model", config=replace(BuildConfig(pictures=False), hold_out="every:4"))


def prebuild(rings: tuple[str, ...] = RINGS) -> dict[str, Path]:
    """The rings' builds as background jobs (tests/background.py), started with the test
    run: they are nearly all of this module's time (the fit ~90 % of a build: templeSR
    88 s of 99 s), 28 % of the fit's single-threaded time is NumPy outside its parallel
    kernels, and the rest of the suite leaves ~0.6 of the 2 cores idle on average. With
    one numba thread each they gave the figures above to the last digit (335 CPU-s for
    the module, both rings). Returns each ring's job folder."""
    import background

    return {name: background.start(f"real_split_{name}", [sys.executable, __file__, name, "."]) for name in rings}


@pytest.fixture(scope="module", params=RINGS)
def split_model(request):
    import background

    name = request.param
    job = prebuild((name,))[name]  # already started with the run, unless under xdist
    background.wait(f"real_split_{name}", timeout_s=1500)
    return name, job / "model"


@pytest.mark.timeout(1800)  # run alone, the first test waits for the build
def test_eval_test_on_the_real_rings(split_model):
    from opacityhull.evaluate.heldout import eval_test
    from opacityhull.model import OpacityHullModel

    name, model = split_model
    m = OpacityHullModel.open(model)
    assert m.meta["split"]["held_out"] == [m.views[i].id for i in (0, 4, 8, 12)]
    white = eval_test(model)
    assert white["renderer"] == "fitted"  # the default build fits (--optimize fast)
    black = eval_test(model, background="black", out=model / "eval" / "test_black")
    ref = MEASURED[name]
    assert white["psnr_mask_mean"] >= ref["psnr_mask"] - MARGIN_DB, white
    assert min(p["psnr_mask"] for p in white["per_view"]) >= ref["min_view_mask"] - MARGIN_DB
    assert white["psnr_mean"] >= ref["psnr_white"] - MARGIN_DB
    assert white["ssim_mean"] >= ref["ssim_white"] - MARGIN_SSIM
    # the mask-union metric does not depend on the background
    assert black["psnr_mask_mean"] == pytest.approx(white["psnr_mask_mean"], abs=1e-9)
    assert json.loads((model / "eval" / "test" / "test.json").read_text())["views"] == white["views"]
    assert Path(white["sheet"]).is_file()


if __name__ == "__main__":  # a background job of prebuild(): RING OUT_DIR
    build_split(sys.argv[1], Path(sys.argv[2]).resolve())
