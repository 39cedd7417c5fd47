"""What ``opacityhull demo`` says the fitting bought (#29 item 3), on the analytic session
of ``test_hold_out.py`` instead of the demo's capture: a fitted build with every 8th view
held out and ground truth on (the demo's build; the ground-truth metrics once failed on a
hold-out build), its held-out views scored by ``eval test`` with the fitted splats and with
the hull blended by ULR, the held-out table angle found, and the demo's one line."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import pytest

import rcsynth
from opacityhull.demo_runner import fitting_line, fitting_step, held_out_angle, train_views_every
from opacityhull.model import OpacityHullModel
from opacityhull.reconstruct.build import BuildConfig, build_model

CFG = BuildConfig(hull_res=40, pictures=False, reflectance=False)


@pytest.fixture(scope="module")
def demo_like(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("demofit")
    session = tmp / "session"
    # 3 cameras x 8 table angles, camera-major: every:8 holds out table angle 0 of each camera
    rcsynth.make_session(session, kind="sphere", n_angles=8, reflectance=False, seed=13)
    fit = replace(CFG, hold_out="every:8", optimize="fast", optimize_iterations=60)
    report = build_model(session, tmp / "model", config=fit, ground_truth=True)
    return tmp, session, report, fitting_step(tmp / "model", tmp / "render")


def test_a_fitted_hold_out_build_has_its_ground_truth_metrics(demo_like):
    _, _, report, _ = demo_like
    assert report.optimize["mode"] == "fast" and report.optimize["iterations"] == 60
    # the hull the training views' true mattes carve: computed over the training views' cameras
    assert 0.5 < report.metrics["hull_iou_vs_true_alpha_hull"] <= 1.0
    assert report.metrics["alpha_views_compared"] == 21


def test_both_figures_are_eval_tests_own(demo_like):
    tmp, _, report, f = demo_like
    for renderer in ("fitted", "ulr"):
        written = json.loads((tmp / "render" / f"test-{renderer}" / "test.json").read_text())
        assert written["renderer"] == renderer
        assert f[f"psnr_mask_{renderer}"] == written["psnr_mask_mean"]
        assert f[f"psnr_white_{renderer}"] == written["psnr_mean"]
        assert f[f"sheet_{renderer}"] == str(tmp / "render" / f"test-{renderer}" / "test_sheet.png")
        assert (tmp / "render" / f"test-{renderer}" / "test_sheet.png").is_file()
    assert f["held_out_views"] == ["c0_t000.000", "c1_t000.000", "c2_t000.000"]
    assert f["iterations"] == 60 and f["seconds"] == report.optimize["seconds"]
    assert f["held_out_table_deg"] == 0.0


def test_the_line_says_what_the_fitting_bought(demo_like):
    _, _, _, f = demo_like
    line = fitting_line(f)
    got = re.search(r"held-out PSNR ([\d.]+) dB \(hull\+ULR ([\d.]+) dB\), mask union", line)
    assert got, line
    assert float(got[1]) == pytest.approx(f["psnr_mask_fitted"], abs=0.05)
    assert float(got[2]) == pytest.approx(f["psnr_mask_ulr"], abs=0.05)
    assert line.startswith("fitting (60 iterations, ") and "held-out table angle 0 deg" in line


def test_no_table_angle_claim_when_the_held_out_views_share_none(demo_like, tmp_path):
    _, session, _, f = demo_like
    # every:4 holds out table angles 0 and 180
    build_model(session, tmp_path / "m", config=replace(CFG, hold_out="every:4"))
    m = OpacityHullModel.open(tmp_path / "m")
    assert held_out_angle(m) is None
    assert "table angle" not in fitting_line(f | {"held_out_table_deg": None})
    # the hull's leave-one-out keeps to training views
    picked = [int(i) for i in train_views_every(tmp_path / "m", 2).split(",")]
    assert picked == [i for i in range(0, 24, 2) if i % 4]
