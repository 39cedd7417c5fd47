"""The pipeline on real photographs made by others: the Middlebury templeSR and dinoSR
rings (vendored in tests/data/real, imperfect thresholded masks), through
``import colmap`` → ``build`` (defaults) → ``eval loo`` with both holdouts.

Thresholds come from measurement (see THRESHOLDS) with margins from the spread between
views and configurations; they are well above the plain baseline (voxel carving +
per-pixel ULR, hull rebuilt without the held-out view: 17.9 dB temple, 17.6 dB dino).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1] / "data" / "real"

pytestmark = pytest.mark.slow

# Measured with the defaults (auto resolution, robust carve with see-through mask holes
# judged by the photograph and shadow holes filled in the views' alpha, pixel shading at
# the photo-consistent shading depth, views aligned by optical flow), every 4th view held
# out (4 views), against the photographs' own masks: temple blend 20.36 dB / geometry
# 19.05 dB, coverage IoU 0.946 (0.959 against the filled masks), interior alpha 0.982
# (0.995 where the hull draws); dino blend 19.90 / geometry 17.93, IoU 0.957 (0.972),
# interior alpha 0.983 (0.994). Without the shadow-hole filling: temple 20.10 / 18.91, dino
# 19.82 / 17.85, interior alpha 0.975 / 0.978. The computation is deterministic (fixed
# data, no sampling; DIS flow is deterministic); the margins of 0.5 dB / 0.015 are what
# single features moved by (backdrop holes +0.66 / +0.19 dB on the temple, flow +0.35 /
# +0.30 dB on the dino, shading depth +0.45 / +0.67 dB, robust carving +0.45 dB, pixel
# shading +0.6 dB), so losing any one of them fails. Below the goals (baseline +
# 3 dB; IoU 0.97 against the masks; interior alpha 0.99): see the closing note.
# With the opaque interior (RenderConfig.opaque_interior, the default since): temple
# blend 20.35 / geometry 19.04 dB, IoU 0.948, interior alpha 0.985 (0.998 where the hull
# draws); dino 19.93 / 17.95 dB, IoU 0.958, interior alpha 0.986 (0.997). What is left is
# the masks': an oracle drawing the hull exactly, with the shadow holes the build filled
# drawn opaque, reaches IoU 0.961 / 0.972 and interior alpha 0.987 / 0.990 on these four
# views (temple view 0's lit cloth fold, 5.6 k px the other views' outlines carve; the
# dino's feet, lost at the outline of the neighbours' masks in views 8 and 12).
# With the bright extensions doubted (BuildConfig.doubt_bright_extensions, the default
# since: thick bright parts just outside a mask's outline, which the threshold lost, are
# carved only by two views): temple blend 20.30 / geometry 19.01 dB, IoU 0.948, interior
# alpha 0.986 (0.998 where the hull draws); dino blend 20.67 / geometry 18.39 dB, IoU
# 0.964, interior alpha 0.9925 (0.996). The dino's thresholds sit between the rule's
# figures and those without it (19.93 / 17.95 dB, alpha 0.986), so losing it fails.
# With the carve tolerance 2 of 16 imported views (build.default_carve_tolerance, was 1)
# and the shading depth's fainter texture (build.SHADING_TEXTURE_STD 0.003, was 0.01):
# temple blend 20.28 / geometry 19.02 dB, IoU 0.949, interior alpha 0.988; dino blend
# 21.26 / geometry 18.90 dB, IoU 0.967 (0.981 against the filled masks), interior alpha
# 0.995 (0.997 where the hull draws). The dino's thresholds again sit between these and
# the figures without the change (20.67 / 18.39 dB, IoU 0.964, alpha 0.9925).
# The temple ring photographs its first viewpoint twice (templeSR0001 and templeSR0011:
# the same pose, the photographs 41.5 dB apart), so eval loo holds c0 and c10 out together
# (camera.coincident_views, the default since): with its twin in the model view c0 scored
# 25.3 dB, without it 14.8 dB (geometry holdout). Every 4th view, twins held out
# together: temple blend 18.50 / geometry 16.38 dB, IoU 0.946, interior alpha 0.988
# (the figures above are the twins-kept protocol); the dino has no twins, unchanged.
# Imported masks no longer dilated by a pixel (build.default_dilate_base_px: 0 for
# imported sets, ½ px rounded up to 1 before): temple blend 19.37 / geometry 16.89 dB,
# IoU 0.946, interior alpha 0.987; dino blend 21.97 / geometry 19.29 dB, IoU 0.967,
# interior alpha 0.994. Both sets' PSNR thresholds sit between these and the dilated
# figures (temple 18.50 / 16.38, dino 21.26 / 18.90), so restoring the dilation fails.
THRESHOLDS = {
    "temple": {"geometry_psnr": 16.6, "blend_psnr": 18.95, "iou": 0.932, "interior_alpha": 0.969},
    "dino": {"geometry_psnr": 19.05, "blend_psnr": 21.6, "iou": 0.958, "interior_alpha": 0.992},
}


RINGS = ("temple", "dino")


def build_ring(name: str, out: Path) -> None:
    """``import colmap`` and the build of ring ``name`` into ``out/session``, ``out/model``."""
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    src = DATA / f"{name}SR"
    import_colmap(src / "sparse", src / "images", out / "session", masks_dir=src / "masks")
    # the hull-and-blend model these leave-one-out figures score: no fit (the default
    # --optimize fast adds MODEL/optimized/, which eval loo does not read)
    build_model(out / "session", out / "model", config=BuildConfig(pictures=False, optimize="none"))


def prebuild(rings: tuple[str, ...] = RINGS) -> dict[str, Path]:
    """The rings' builds as background jobs from the start of the run
    (tests/background.py). Returns each ring's job folder."""
    import background

    return {name: background.start(f"real_loo_{name}", [sys.executable, __file__, name, "."]) for name in rings}


@pytest.fixture(scope="module", params=RINGS)
def real_model(request):
    """(ring, its folder, the build's report.json as attributes: ``hull``, ``surfels``...)."""
    import background

    name = request.param
    tmp = prebuild((name,))[name]  # already started with the run, unless under xdist
    background.wait(f"real_loo_{name}", timeout_s=1500)
    return name, tmp, SimpleNamespace(**json.loads((tmp / "model" / "report.json").read_text()))


def test_default_build_reaches_capture_resolution(real_model):
    """No flag needed: the default grid puts one surfel per projected pixel."""
    name, tmp, report = real_model
    res = report.hull["resolution"]
    assert res["surfel_spacing_m"] <= 1.01 * res["pixel_footprint_m"], res
    assert res["reason"].startswith("auto")
    assert report.hull["carve_tolerance"] == 2  # 16 imported thresholded masks: robust carve
    # another tool's masks are taken as they are: no silhouette dilation
    assert report.hull["dilate_base_px"] == 0.0 and set(report.hull["dilate_px_per_view"].values()) == {0}
    assert report.surfels > 300_000
    # the photo-consistent shading depth is on by default and stored with the surfels
    from opacityhull.model import read_surfels_ply

    assert report.hull["refine"]["mode"] == "shading"
    depth = read_surfels_ply(tmp / "model" / "surfels.ply").depth_m
    assert depth is not None and 0.1 < float((depth > 0).mean()) < 0.9  # measured 0.48 temple, 0.20 dino


def test_shadow_holes_are_filled_in_the_views_and_the_evaluation_keeps_the_mask(real_model):
    """The masks' enclosed holes that show no backdrop (the dino's shadows; the temple's
    few dark corners) are opaque in the model's views, exactly there: the views' alpha is
    the photograph's mask or the filled holes; eval loo compares with the mask itself."""
    import imageio.v3 as iio

    from opacityhull.model import BUILD_DIR, FILLED_HOLES, OpacityHullModel, read_hole_masks

    name, tmp, report = real_model
    filled = report.hull["shadow_holes_filled"]
    holes = read_hole_masks(tmp / "model" / BUILD_DIR / FILLED_HOLES)
    assert filled["px"] == sum(int(h.sum()) for h in holes.values()) > 0
    # measured: dino 30 k hole pixels, none shows the backdrop; temple 14 k of 172 k
    assert filled["px"] > (25_000 if name == "dino" else 5_000), filled
    model = OpacityHullModel.open(tmp / "model")
    src = DATA / f"{name}SR" / "masks"
    for i, v in enumerate(model.views[:6]):
        a = model.load_view_rgba(i)[..., 3] > 0.5
        masks = sorted(src.glob(f"*{Path(v.id).stem}*")) or sorted(src.iterdir())[i : i + 1]
        mask = np.asarray(iio.imread(masks[0]))
        mask = (mask if mask.ndim == 2 else mask[..., 0]) > 127
        h = holes.get(v.id, np.zeros_like(a))
        assert np.array_equal(a, mask | h), v.id
        assert not (mask & h).any()


def test_real_loo_both_holdouts(real_model):
    from opacityhull.evaluate.holdout import run_loo_holdouts

    name, tmp, _ = real_model
    s = run_loo_holdouts(tmp / "model", views="every:4", holdout="both", out=tmp / "loo")
    g, b = s["holdouts"]["geometry"], s["holdouts"]["blend"]
    t = THRESHOLDS[name]
    twins = [["c0_t000.000", "c10_t000.000"]] if name == "temple" else []
    assert s["coincident_views"] == twins and s["twins"] == "together"
    first = s["per_view"][0]  # the geometry holdout's
    assert first["view"] == "c0_t000.000" and first["held_out_with"] == [v for g_ in twins for v in g_[1:]]
    assert g["psnr_mean"] > t["geometry_psnr"], g
    assert b["psnr_mean"] > t["blend_psnr"], b
    # the honest holdout can only be harder: the held-out silhouette no longer carves
    assert g["psnr_mean"] <= b["psnr_mean"] + 0.3
    assert b["coverage_iou_mean"] > t["iou"] and b["interior_alpha_mean"] > t["interior_alpha"], b
    # where the hull draws, the blended mattes are opaque (measured 0.998 temple, 0.997
    # dino; 0.995 / 0.994 without the opaque interior); the rest of the deficit is where
    # the held-out mask and the hull disagree
    assert b["interior_alpha_covered_mean"] > 0.994, b
    assert g["interior_alpha_covered_mean"] > 0.993, g  # measured 0.998 / 0.996
    # against the mask with its shadow holes filled the rendering agrees better
    assert b["coverage_iou_holes_filled_mean"] >= b["coverage_iou_mean"], b
    # ... and scores better: the shadows a threshold lost are object, and the rendering
    # draws them (measured +0.35 dB dino, +0.17 temple); views without holes score alike
    assert b["psnr_holes_filled_mean"] > b["psnr_mean"] + 0.1, b
    blend_views = json.loads((tmp / "loo" / "loo.json").read_text())["all"]["blend"]["per_view"]
    assert all(p["psnr_holes_filled"] == p["psnr"] for p in blend_views if p["shadow_holes_px"] == 0)
    assert all(p["psnr_holes_filled"] > p["psnr"] - 0.05 for p in blend_views), blend_views
    # the interior is what geometry can explain; the band is where the silhouettes decide
    assert b["psnr_interior_mean"] > b["psnr_band_mean"] + 3.0
    assert (tmp / "loo" / "loo.json").is_file()


def test_geometry_holdout_of_a_refined_build(tmp_path):
    """A build with photo-consistent refinement is held out with refinement too, and the
    held-out photograph never enters the photo-consistency cost (it is not loaded)."""
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.model import OpacityHullModel
    from opacityhull.reconstruct.build import BuildConfig, build_model
    from opacityhull.evaluate.holdout import build_config_of, geometry_without

    src = DATA / "templeSR"
    import_colmap(src / "sparse", src / "images", tmp_path / "s", masks_dir=src / "masks")
    rep = build_model(
        tmp_path / "s", tmp_path / "m", config=BuildConfig(hull_res=64, refine=True, pictures=False, optimize="none")
    )
    assert rep.hull["refine"]["n_surfels"] == rep.surfels
    model = OpacityHullModel.open(tmp_path / "m")
    assert build_config_of(model)[0].refine
    loaded = []
    orig = model.load_view_rgba
    model.load_view_rgba = lambda i: (loaded.append(i), orig(i))[1]
    s = geometry_without(model)(3)
    assert len(s) > 1000 and not s.visible_bool()[:, 3].any()
    assert loaded.count(3) == 1  # its alpha is read once up front (then dropped), never its colour


if __name__ == "__main__":  # a background job of prebuild(): RING OUT_DIR
    build_ring(sys.argv[1], Path(sys.argv[2]).resolve())
