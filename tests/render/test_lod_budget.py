"""`render --budget N`: the CPU renderer draws the viewer's level of detail (a
view-dependent cut of the sequential point tree) with at most N splats."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from opacityhull.cli import app
from opacityhull.errors import InputError
from opacityhull.imageio import read_exr
from opacityhull.model import OpacityHullModel
from opacityhull.render.runner import check_budget, choose_cameras, run_render


def _psnr_premul(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB, peak 1) of premultiplied RGB and alpha where either image covers."""
    sel = (a[..., 3] > 0.01) | (b[..., 3] > 0.01)
    pa = np.concatenate([a[..., :3] * a[..., 3:], a[..., 3:]], -1)
    pb = np.concatenate([b[..., :3] * b[..., 3:], b[..., 3:]], -1)
    d = (pa - pb)[sel]
    return float("inf") if not d.any() else float(10 * np.log10(1.0 / np.mean(d**2)))


def test_view_lod_is_the_render_lod():
    import opacityhull.render.lod as r
    import opacityhull.view.lod as v

    for name in r.__all__:
        assert getattr(v, name) is getattr(r, name)


def test_budget_at_or_above_the_model_is_the_model_exactly(sphere_dir, tmp_path):
    root, m = sphere_dir
    n = len(m.surfels)
    full = run_render(root, tmp_path / "full.exr", view=(1, 30.0))
    assert full["budget"] is None and full["splats_per_frame"] == [n]
    for b in (n, 10 * n):
        s = run_render(root, tmp_path / f"b{b}.exr", view=(1, 30.0), budget=b)
        assert s["splats_per_frame"] == [n] and s["lod_tau"] == [0.0]
        np.testing.assert_array_equal(read_exr(tmp_path / f"b{b}.exr"), read_exr(tmp_path / "full.exr"))


def test_budget_draws_at_most_n_splats_and_keeps_psnr(sphere_dir, tmp_path):
    """Measured on this model (8000 surfels, 64x48; captured views 0, 4, 13, 30): PSNR
    against the full render 28.6-35.9 dB at 1/4 of the surfels, 25.8-31.0 dB at 1/16
    (with the renderer's own k-NN areas of the cut instead of the nodes' subtree areas:
    27.6-33.7 and 22.4-22.8 dB); this orbit: 30.4 and 29.3 dB."""
    from opacityhull.render.lod import build_point_tree, select_cut
    from opacityhull.render.renderer import model_surfels, surfel_areas

    root, m = sphere_dir
    n = len(m.surfels)
    run_render(root, tmp_path / "full.exr", orbit=2)
    full = [read_exr(tmp_path / f"full_{i:03d}.exr") for i in range(2)]
    model = OpacityHullModel.open(root)
    cams = choose_cameras(model, orbit=2)
    surf = model_surfels(model)
    tree = build_point_tree(surf, surfel_areas(surf))
    psnr = {}
    for frac in (4, 16):
        b = n // frac
        s = run_render(root, tmp_path / f"q{frac}.exr", orbit=2, budget=b)
        assert s["budget"] == b
        for k, cam in zip(s["splats_per_frame"], cams, strict=True):
            assert 0.8 * b <= k <= b
            # the same cut as the LOD module's own selection for this camera
            _, mask = select_cut(tree, cam.centre_world, b)
            assert k == int(mask.sum())
        imgs = [read_exr(tmp_path / f"q{frac}_{i:03d}.exr") for i in range(2)]
        assert all(np.all(np.isfinite(x)) for x in imgs)
        psnr[frac] = min(_psnr_premul(x, f) for x, f in zip(imgs, full, strict=True))
    print("budget PSNR vs full (dB):", psnr)
    assert psnr[4] >= 27.0 and psnr[16] >= 24.0


def test_cut_carries_subtree_areas_to_the_renderer(sphere_dir):
    """The renderer's edge coverage uses each node's summed subtree area (seeded into its
    area cache), not a k-NN estimate on the irregular cut."""
    from opacityhull.render.lod import cut_mask
    from opacityhull.render.renderer import model_surfels, surfel_areas
    from opacityhull.render.runner import LodCuts

    root, m = sphere_dir
    model = OpacityHullModel.open(root)
    surf = model_surfels(model)
    lod = LodCuts(surf)
    cam = model.views[7].camera
    drawn, tau = lod.cut(cam, 1500)
    assert tau > 0 and len(drawn) <= 1500
    mask = cut_mask(lod.tree, tau, cam.centre_world)
    np.testing.assert_array_equal(drawn.positions, lod.tree.positions[mask])
    np.testing.assert_array_equal(surfel_areas(drawn), lod.tree.areas[mask])
    # a node's area is the sum of its leaves' areas (the model's own k-NN areas)
    leaf_area = surfel_areas(surf)
    tree = lod.tree
    node = int(np.flatnonzero(~tree.is_leaf & (tree.parent >= 0))[0])
    below = np.zeros(len(tree), bool)
    for i in np.flatnonzero(tree.is_leaf):
        n = i
        while n >= 0 and n != node:
            n = tree.parent[n]
        below[i] = n == node
    np.testing.assert_allclose(tree.areas[node], leaf_area[tree.leaf_index[below]].sum(), rtol=1e-5)


def test_budget_one_draws_the_root(sphere_dir, tmp_path):
    root, _ = sphere_dir
    s = run_render(root, tmp_path / "one.exr", view=(0, 0.0), budget=1)
    assert s["splats_per_frame"] == [1]
    img = read_exr(tmp_path / "one.exr")
    assert np.all(np.isfinite(img)) and img[..., 3].max() > 0


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(2, 400),
    seed=st.integers(0, 10_000),
    budget=st.integers(1, 400),
    eye_scale=st.sampled_from([0.0, 0.5, 3.0, 50.0]),
)
def test_select_cut_respects_any_budget(n, seed, budget, eye_scale):
    """Any budget ≥ 1, any eye (inside the cloud too): 1 ≤ splats ≤ budget. (The cut
    once took τ = max r_min/d as its coarsest start, and drew 5 splats for budget 1.)"""
    from opacityhull.model import Surfels
    from opacityhull.render.lod import build_point_tree, select_cut

    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    s = Surfels.from_bool(
        p, p / np.linalg.norm(p, axis=1, keepdims=True), rng.uniform(0.01, 0.1, n), rng.random((n, 5)) < 0.5
    )
    tree = build_point_tree(s, depth=10)
    eye = rng.normal(size=3) * eye_scale
    tau, mask = select_cut(tree, eye, budget)
    if budget >= n:
        assert tau == 0.0 and mask.sum() == n
    else:
        assert 1 <= mask.sum() <= budget


@pytest.mark.parametrize("bad", [0, -3, 2.5, float("nan"), "many", True])
def test_check_budget_rejects(bad):
    with pytest.raises(InputError, match="splat budget"):
        check_budget(bad)


def test_cli_budget(sphere_dir, tmp_path):
    import json

    root, m = sphere_dir
    runner = CliRunner()
    res = runner.invoke(app, ["render", str(root), "--out", str(tmp_path / "x.png"), "--budget", "0"])
    assert res.exit_code == 2, res.output
    assert "--budget 0" in " ".join(res.output.split())
    assert not (tmp_path / "x.png").exists()
    res = runner.invoke(app, ["render", str(root), "--out", str(tmp_path / "y.png"), "--budget", "1000", "--json"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout.strip().splitlines()[-1])
    assert s["budget"] == 1000 and 800 <= s["splats_per_frame"][0] <= 1000
    assert (tmp_path / "y.png").is_file()
