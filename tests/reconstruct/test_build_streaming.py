"""The build streams its views (issue 14): the structure, not the time.

The build's per-view loaders register every full-resolution per-view array they hand
out (alpha, RGBA, photograph) with :data:`opacityhull.reconstruct.perview.LIVE_VIEWS`, a
finaliser counting each out when it is freed. Its ``peak`` (distinct views alive at
once) must stay at the views in flight — one when serial, the pool's size (or fewer,
as the ``--memory-gb`` budget allows) on threads — however many views the session has.
The budget changes nothing in the model (the carve batches intersect to the same hull);
the renderer's memory-mapped views render what the in-memory ones do; a bad
``--memory-gb`` is exit 2 naming the flag.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from opacityhull.acquire.synthetic import SyntheticSessionConfig, write_synthetic_session
from opacityhull.executor import open_executor
from opacityhull.model import OpacityHullModel
from opacityhull.reconstruct.build import PHOTO_MIN_SLOTS, BuildConfig, MemoryPlan, PackedMasks, build_model
from opacityhull.reconstruct.liveviews import LIVE_VIEWS

CLI = Path(sys.executable).with_name("opacityhull")
CFG = BuildConfig(pictures=False, reflectance=False)


def _session(root: Path, n_table: int) -> Path:
    write_synthetic_session(
        root, SyntheticSessionConfig(n_table=n_table, width_px=40, height_px=30, groundtruth=False, threads=1)
    )
    return root


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    d = tmp_path_factory.mktemp("stream")
    return {v: _session(d / f"s{v}", v // 6) for v in (12, 42)}


@pytest.fixture(scope="module")
def serial_models(sessions, tmp_path_factory):
    d = tmp_path_factory.mktemp("stream_models")
    out = {}
    for v, s in sessions.items():
        LIVE_VIEWS.reset()
        rep = build_model(s, d / f"m{v}", config=CFG)
        out[v] = (d / f"m{v}", rep, LIVE_VIEWS.peak, LIVE_VIEWS.tracked)
    return out


def assert_same_model(a, b):
    ma, mb = OpacityHullModel.open(a), OpacityHullModel.open(b)
    assert [v.id for v in ma.views] == [v.id for v in mb.views]
    np.testing.assert_array_equal(ma.surfels.positions, mb.surfels.positions)
    np.testing.assert_array_equal(ma.surfels.normals, mb.surfels.normals)
    np.testing.assert_array_equal(ma.surfels.radii, mb.surfels.radii)
    np.testing.assert_array_equal(ma.surfels.visible_bool(), mb.surfels.visible_bool())
    assert (ma.surfels.depth_m is None) == (mb.surfels.depth_m is None)
    if ma.surfels.depth_m is not None:
        np.testing.assert_array_equal(ma.surfels.depth_m, mb.surfels.depth_m)
    for i in range(len(ma.views)):
        np.testing.assert_array_equal(ma.load_view_rgba(i), mb.load_view_rgba(i))


def test_serial_build_holds_one_view_at_a_time_whatever_the_view_count(serial_models):
    for v, (_, rep, peak, tracked) in serial_models.items():
        assert rep.views == v
        # every view went through the loaders (mattes, refine photographs, RGBA) ...
        assert tracked >= 3 * v
        # ... and never two views at once
        assert peak == 1, (v, peak)
    assert LIVE_VIEWS.live == 0  # nothing of any view left behind


def test_threads_hold_at_most_the_views_in_flight(sessions, serial_models, tmp_path):
    s = sessions[42]
    with open_executor("threads", workers=2) as ex:
        LIVE_VIEWS.reset()
        rep = build_model(s, tmp_path / "m2", config=CFG, executor=ex)
        assert rep.memory["in_flight"] == 2
        assert LIVE_VIEWS.peak <= 2
        # a budget too small for two views' matting images: one view in flight
        LIVE_VIEWS.reset()
        rep1 = build_model(s, tmp_path / "m1", config=CFG, executor=ex, memory_gb=1e-4)
        assert rep1.memory["in_flight"] == 1
        assert LIVE_VIEWS.peak == 1
    assert_same_model(tmp_path / "m2", serial_models[42][0])
    assert_same_model(tmp_path / "m1", serial_models[42][0])


def test_memory_budget_is_reported_and_changes_nothing_in_the_model(sessions, serial_models, tmp_path):
    ref, ref_rep, _, _ = serial_models[42]
    assert ref_rep.memory["carve_batch"] == 42  # the default budget stacks all 42 views
    rep = build_model(sessions[42], tmp_path / "tiny", config=CFG, memory_gb=1e-5)
    # the carve ran one view per batch, the batches' hulls intersected: the same hull
    assert rep.memory["carve_batch"] == 1 and rep.hull["carve_batches"] >= 2
    # the photo refinement held only the plan's few slots of the 42 views (and read the
    # photographs again as needed), where the default budget holds them all
    assert rep.memory["photo_slots"] == PHOTO_MIN_SLOTS and ref_rep.memory["photo_slots"] == 42
    assert ref_rep.hull["refine"]["views_in_memory"] > PHOTO_MIN_SLOTS
    assert rep.hull["refine"]["views_in_memory"] <= PHOTO_MIN_SLOTS
    assert rep.hull["refine"]["n_view_loads"] > ref_rep.hull["refine"]["n_view_loads"]
    assert rep.hull["occupied_voxels"] == ref_rep.hull["occupied_voxels"]
    assert_same_model(tmp_path / "tiny", ref)
    d = json.loads((tmp_path / "tiny" / "report.json").read_text())
    assert d["memory_budget_gb"] == pytest.approx(1e-5)
    assert d["peak_rss_mb"] > 0
    # the silhouettes are held bit-packed between the stages: 1 bit a pixel
    assert d["memory"]["silhouettes_packed_bytes"] == 42 * 30 * 5


def test_memory_plan_caps_in_flight_by_the_budget_not_the_views():
    kw = dict(pixels=1360 * 1032, images_per_view=4, workers=8)
    small = MemoryPlan.for_build(0.1, views=48, **kw)
    big = MemoryPlan.for_build(64.0, views=432, **kw)
    assert small.in_flight == 1 and big.in_flight == 8
    assert small.carve_batch < big.carve_batch <= 48
    # the refinement's slots: a quarter of the budget at 8 bytes a pixel, between its
    # floor and the view count
    assert small.photo_slots == PHOTO_MIN_SLOTS and big.photo_slots == 432
    assert MemoryPlan.for_build(2.0, views=432, **kw).photo_slots == int(0.25 * 2 * 2**30 // (8 * 1360 * 1032))
    # the plan depends on the views only through these upper bounds
    more = MemoryPlan.for_build(64.0, views=4320, **kw)
    assert more.photo_slots == int(0.25 * 64 * 2**30 // (8 * 1360 * 1032)) > big.photo_slots
    assert replace(more, photo_slots=big.photo_slots) == big


def test_packed_masks_round_trip():
    rng = np.random.default_rng(0)
    masks = [rng.random((7, 13)) > 0.5, None, rng.random((5, 9)) > 0.3]
    pm = PackedMasks(masks)
    assert len(pm) == 3 and pm[1] is None
    for m, got in zip(masks, pm, strict=True):
        if m is None:
            assert got is None
        else:
            assert got.dtype == bool
            np.testing.assert_array_equal(got, m)
    assert pm.nbytes == 7 * 2 + 5 * 2
    sub = pm[2:]
    assert isinstance(sub, PackedMasks) and len(sub) == 1
    tail = sub[0]
    assert tail is not None
    np.testing.assert_array_equal(tail, masks[2])


def test_mapped_renderer_views_equal_the_eager_ones(serial_models):
    from opacityhull.render.renderer import RenderConfig, model_surfels, prepare_model_views, render_image

    m = OpacityHullModel.open(serial_models[42][0])
    cams = [v.camera for v in m.views]
    lazy, eager = prepare_model_views(m), prepare_model_views(m, mapped=False)
    assert not lazy.texels.flags.owndata  # a mapping, not an in-memory copy
    np.testing.assert_array_equal(lazy.texels, eager.texels)
    np.testing.assert_array_equal(lazy.offsets, eager.offsets)
    assert lazy.nonfinite_texels == eager.nonfinite_texels
    s = model_surfels(m)
    for i in (0, 17):
        a = render_image(s, cams, lazy, cams[i], config=RenderConfig())
        b = render_image(s, cams, eager, cams[i], config=RenderConfig())
        np.testing.assert_array_equal(a.rgba, b.rgba)


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_bad_memory_budget_is_exit_2_naming_the_flag(sessions, tmp_path, value):
    res = subprocess.run(
        [str(CLI), "build", str(sessions[12]), "--out", str(tmp_path / "m"), f"--memory-gb={value}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2, res.stderr
    assert "--memory-gb" in res.stderr
    assert not (tmp_path / "m" / "model.toml").exists()
