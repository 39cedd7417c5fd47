"""``build --hold-out`` (#29, the nerfstudio train/test protocol) on an analytic session:
the test views stay on record (cameras, photographs, listed in ``model.toml``) but no
step that shapes the model sees them — the geometry equals a build without those views
at all, their visibility bits are clear, so ``render --view`` of one renders it from the
others — and ``eval test`` scores each against its photograph."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

import rcsynth
from opacityhull.model import OpacityHullModel, read_surfels_ply
from opacityhull.reconstruct.build import BuildConfig, build_model
from opacityhull.reconstruct.steps.split import resolve_hold_out

# the split of the hull-and-blend model (ULR renders the test views): no fit
CFG = BuildConfig(hull_res=40, pictures=False, reflectance=False, optimize="none")


def invoke(argv):
    from typer.testing import CliRunner

    from opacityhull.cli import app, normalize_argv

    return CliRunner().invoke(app, normalize_argv([str(a) for a in argv]), env={"COLUMNS": "4000"})


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("holdout")
    session = tmp / "session"
    rcsynth.make_session(session, kind="sphere", n_angles=8, reflectance=False, seed=13)
    held = build_model(session, tmp / "held", config=replace(CFG, hold_out="every:4"))
    m = OpacityHullModel.open(tmp / "held")
    ids = [m.views[i].id for i in range(0, len(m.views), 4)]
    without = build_model(session, tmp / "without", config=replace(CFG, exclude_views=tuple(ids)))
    return tmp, held, without, ids


def test_the_split_resolves_like_nerfstudio():
    ids = [f"v{i}" for i in range(10)]
    assert resolve_hold_out("every:4", ids) == (0, 4, 8)
    assert resolve_hold_out("v3, 1 ,v3", ids) == (1, 3)
    assert resolve_hold_out(None, ids) == ()


def test_test_views_stay_on_record_and_out_of_the_geometry(models):
    tmp, rep, without, ids = models
    m = OpacityHullModel.open(tmp / "held")
    assert m.meta["split"]["held_out"] == ids and m.meta["split"]["hold_out"] == "every:4"
    assert len(m.views) == 24 and all((tmp / "held" / "views" / f"{v}.exr").is_file() for v in ids)
    assert rep.hull["held_out"] == ids and any("hold-out (every:4)" in n for n in rep.notes)
    held = [m.view_index(v) for v in ids]
    train = [i for i in range(len(m.views)) if i not in held]
    vis = m.surfels.visible_bool()
    assert not vis[:, held].any()  # never blended
    # the same geometry as a build that never had those views
    a = read_surfels_ply(tmp / "held" / "surfels.ply")
    b = read_surfels_ply(tmp / "without" / "surfels.ply")
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    np.testing.assert_array_equal(vis[:, train], b.visible_bool())
    assert rep.hull["carve_tolerance"] == without.hull["carve_tolerance"]
    # the training views' colour is the same too
    mw = OpacityHullModel.open(tmp / "without")
    for i in train[:3]:
        np.testing.assert_array_equal(m.load_view_rgba(i), mw.load_view_rgba(mw.view_index(m.views[i].id)))


def test_a_test_view_renders_from_the_model_and_eval_test_scores_it(models):
    tmp, _, _, ids = models
    m = OpacityHullModel.open(tmp / "held")
    v = m.views[m.view_index(ids[1])]
    spec = f"{v.camera_index},{v.table_deg:g}"
    r = invoke(["render", tmp / "held", "--view", spec, "--out", tmp / "a.exr", "--json"])
    assert r.exit_code == 0, r.output
    r = invoke(["render", tmp / "held", "--view", spec, "--exclude-view", ids[1], "--out", tmp / "b.exr", "--json"])
    assert r.exit_code == 0, r.output
    from opacityhull.imageio import read_exr

    a, b = read_exr(tmp / "a.exr"), read_exr(tmp / "b.exr")
    np.testing.assert_array_equal(a, b)  # excluding it changes nothing: it was never blended
    assert not np.array_equal(a, m.load_view_rgba(m.view_index(ids[1])))  # not its photograph

    r = invoke(["eval", "test", tmp / "held", "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["views"] == ids and s["background"] == "white" and s["train_views"] == 18
    assert (tmp / "held" / "eval" / "test" / "test.json").is_file() and s["sheet"].endswith("test_sheet.png")
    for p in s["per_view"]:
        # a 40-voxel hull of an analytic sphere: measured 22.7-29.2 dB on white (SSIM 0.92-0.97), 21.6-25.0 dB
        # in the mask; the bounds catch a test view blended in (it would score far higher) or a broken render
        assert 20.0 < p["psnr"] < 40.0 and 18.0 < p["psnr_mask"] < 40.0 and 0.5 < p["ssim"] <= 1.0, p
    black = json.loads(invoke(["eval", "test", tmp / "held", "--background", "black", "--json"]).stdout)
    # the mask-union metric does not depend on the background; the whole-image one does
    assert black["psnr_mask_mean"] == pytest.approx(s["psnr_mask_mean"], abs=1e-9)
    assert black["psnr_mean"] != pytest.approx(s["psnr_mean"], abs=1e-3)


def test_eval_test_refuses_a_model_without_test_views_and_a_bad_background(models):
    tmp, _, _, _ = models
    r = invoke(["eval", "test", tmp / "without"])
    assert r.exit_code == 2 and "built without --hold-out" in r.stderr and "Traceback" not in r.output
    assert not (tmp / "without" / "eval").exists()
    r = invoke(["eval", "test", tmp / "held", "--background", "grey", "--out", tmp / "e"])
    assert r.exit_code == 2 and "--background" in r.stderr and not (tmp / "e").exists()
