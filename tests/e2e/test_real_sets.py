"""The pipeline on real photographs made by others: the Middlebury templeSR and dinoSR
rings (vendored in tests/data/real, imperfect thresholded masks), through
``import colmap`` → ``build`` (defaults) → ``eval loo`` with both holdouts.

Thresholds come from measurement (see THRESHOLDS) with margins from the spread between
views and configurations; they are well above the plain baseline (voxel carving +
per-pixel ULR, hull rebuilt without the held-out view: 17.9 dB temple, 17.6 dB dino).
"""

from __future__ import annotations

from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[1] / "data" / "real"

pytestmark = pytest.mark.slow

# Measured with the defaults (auto resolution, robust carve with see-through mask holes
# judged by the photograph, pixel shading at the photo-consistent shading depth, views
# aligned by optical flow), every 4th view held out (4 views): temple blend 20.10 dB /
# geometry 18.91 dB; dino blend 19.82 / geometry 17.85. Without the flow alignment: temple
# 20.07 / 18.86, coverage IoU 0.945, interior alpha 0.975; dino 19.48 / 17.55, IoU 0.960,
# interior alpha 0.976 (no dino hole shows the backdrop: unchanged by that rule). The
# computation is deterministic (fixed data, no sampling; DIS flow is deterministic); the
# margins of 0.5 dB / 0.015 are what single features moved by (backdrop holes +0.66 /
# +0.19 dB on the temple, flow +0.35 / +0.30 dB on the dino, shading depth +0.45 / +0.67
# dB, robust carving +0.45 dB, pixel shading +0.6 dB), so losing any one of them fails.
# Below the goals (baseline + 3 dB; IoU 0.97, interior alpha 0.99): see the
# closing note.
THRESHOLDS = {
    "temple": {"geometry_psnr": 18.4, "blend_psnr": 19.6, "iou": 0.93, "interior_alpha": 0.96},
    "dino": {"geometry_psnr": 17.35, "blend_psnr": 19.3, "iou": 0.945, "interior_alpha": 0.961},
}


@pytest.fixture(scope="module", params=["temple", "dino"])
def real_model(request, tmp_path_factory):
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    name = request.param
    src = DATA / f"{name}SR"
    tmp = tmp_path_factory.mktemp(name)
    import_colmap(src / "sparse", src / "images", tmp / "session", masks_dir=src / "masks")
    report = build_model(tmp / "session", tmp / "model", config=BuildConfig(pictures=False))
    return name, tmp, report


def test_default_build_reaches_capture_resolution(real_model):
    """No flag needed: the default grid puts one surfel per projected pixel."""
    name, tmp, report = real_model
    res = report.hull["resolution"]
    assert res["surfel_spacing_m"] <= 1.01 * res["pixel_footprint_m"], res
    assert res["reason"].startswith("auto")
    assert report.hull["carve_tolerance"] == 1  # imported thresholded masks: robust carve
    assert report.surfels > 300_000
    # the photo-consistent shading depth is on by default and stored with the surfels
    from opacityhull.model import read_surfels_ply

    assert report.hull["refine"]["mode"] == "shading"
    depth = read_surfels_ply(tmp / "model" / "surfels.ply").depth_m
    assert depth is not None and 0.1 < float((depth > 0).mean()) < 0.9  # measured 0.48 temple, 0.20 dino


def test_real_loo_both_holdouts(real_model):
    from opacityhull.reconstruct.holdout import run_loo_holdouts

    name, tmp, _ = real_model
    s = run_loo_holdouts(tmp / "model", views="every:4", holdout="both", out=tmp / "loo")
    g, b = s["holdouts"]["geometry"], s["holdouts"]["blend"]
    t = THRESHOLDS[name]
    assert g["psnr_mean"] > t["geometry_psnr"], g
    assert b["psnr_mean"] > t["blend_psnr"], b
    # the honest holdout can only be harder: the held-out silhouette no longer carves
    assert g["psnr_mean"] <= b["psnr_mean"] + 0.3
    assert b["coverage_iou_mean"] > t["iou"] and b["interior_alpha_mean"] > t["interior_alpha"], b
    # where the hull draws, the blended mattes are nearly opaque (measured 0.983 temple,
    # 0.986 dino); the rest of the deficit is the masks' own blobs and shadow holes
    assert b["interior_alpha_covered_mean"] > 0.97, b
    # the interior is what geometry can explain; the band is where the silhouettes decide
    assert b["psnr_interior_mean"] > b["psnr_band_mean"] + 3.0
    assert (tmp / "loo" / "loo.json").is_file()


def test_geometry_holdout_of_a_refined_build(tmp_path):
    """A build with photo-consistent refinement is held out with refinement too, and the
    held-out photograph never enters the photo-consistency cost (it is not loaded)."""
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.model import OpacityHullModel
    from opacityhull.reconstruct.build import BuildConfig, build_model
    from opacityhull.reconstruct.holdout import build_config_of, geometry_without

    src = DATA / "templeSR"
    import_colmap(src / "sparse", src / "images", tmp_path / "s", masks_dir=src / "masks")
    rep = build_model(tmp_path / "s", tmp_path / "m", config=BuildConfig(hull_res=64, refine=True, pictures=False))
    assert rep.hull["refine"]["n_surfels"] == rep.surfels
    model = OpacityHullModel.open(tmp_path / "m")
    assert build_config_of(model)[0].refine
    loaded = []
    orig = model.load_view_rgba
    model.load_view_rgba = lambda i: (loaded.append(i), orig(i))[1]
    s = geometry_without(model)(3)
    assert len(s) > 1000 and not s.visible_bool()[:, 3].any()
    assert loaded.count(3) == 1  # its alpha is read once up front (then dropped), never its colour
