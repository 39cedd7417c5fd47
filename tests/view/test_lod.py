"""Sequential point tree: the cut is a partition of the surface at every threshold, the
budget is respected, and fewer splats cost little PSNR against the full model."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import InputError
from opacityhull.model import Surfels
from opacityhull.render.config import RenderConfig
from opacityhull.render.renderer import render_image
from opacityhull.render.synthetic import make_sphere_model
from opacityhull.view.lod import build_point_tree, cut_mask, cut_surfels, select_cut


def _paths_count(tree, mask):
    """Per leaf: how many nodes of ``mask`` lie on its path to the root (slow, obvious)."""
    out = []
    for leaf in np.flatnonzero(tree.is_leaf):
        n, c = leaf, 0
        while n >= 0:
            c += bool(mask[n])
            n = tree.parent[n]
        out.append(c)
    return np.array(out)


def _cloud(n, seed, dup=False):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    if dup:
        p[: n // 2] = p[0]  # many identical positions: cells that never split
    nrm = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
    vis = rng.random((n, 11)) < 0.3
    return Surfels.from_bool(p, nrm, rng.uniform(0.01, 0.05, n), vis)


@settings(max_examples=15, deadline=None)
@given(
    n=st.integers(1, 300),
    seed=st.integers(0, 10_000),
    dup=st.booleans(),
    t=st.sampled_from([0.0, 0.01, 0.05, 0.2, 1.0, 100.0]),
)
def test_cut_is_a_partition(n, seed, dup, t):
    s = _cloud(n, seed, dup)
    tree = build_point_tree(s, depth=8)
    assert tree.is_leaf.sum() == n
    np.testing.assert_array_equal(np.sort(tree.leaf_index[tree.is_leaf]), np.arange(n))
    assert np.all(np.diff(tree.r_max) <= 0)  # sequential: sorted by r_max, largest first
    assert np.all(tree.r_min <= tree.r_max)
    mask = (tree.r_min <= t) & (t < tree.r_max)
    assert np.all(_paths_count(tree, mask) == 1)
    # a parent sees whatever its children see; the render radius keeps the disc area
    ch = np.flatnonzero(tree.parent >= 0)
    par = tree.parent[ch]
    assert np.all((tree.visibility[ch] & ~tree.visibility[par]) == 0)
    np.testing.assert_allclose(
        np.sum(tree.radii[mask].astype(float) ** 2), np.sum(s.radii.astype(float) ** 2), rtol=1e-4
    )
    np.testing.assert_allclose(tree.areas[mask].sum(), (np.pi * s.radii.astype(float) ** 2).sum(), rtol=1e-4)


def test_bad_input():
    s = _cloud(10, 1)
    s.positions[3, 1] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        build_point_tree(s)
    tree = build_point_tree(_cloud(10, 2))
    with pytest.raises(InputError, match="--budget"):
        select_cut(tree, [0, 0, 5], 0)


@pytest.fixture(scope="module")
def sphere():
    return make_sphere_model(20000, width=64, height=48, table_step_deg=45.0)


def test_budget_psnr_against_full_model(sphere):
    m = sphere
    tree = build_point_tree(m.surfels)
    cams, pv = [v.camera for v in m.views], m.views_premul()
    cam = m.views[4].camera
    full = render_image(m.surfels, cams, pv, cam, config=RenderConfig(threads=1))
    N = len(m.surfels)
    psnr = {}
    for frac in (1 / 16, 1 / 4, 1):
        budget = int(N * frac)
        tau, mask = select_cut(tree, cam.centre_world, budget)
        assert mask.sum() <= budget and mask.sum() >= 0.8 * budget
        np.testing.assert_array_equal(mask, cut_mask(tree, tau, cam.centre_world))
        s, _ = cut_surfels(tree, mask)
        r = render_image(s, cams, pv, cam, config=RenderConfig(threads=1))
        sel = (full.rgba[..., 3] > 0.01) | (r.rgba[..., 3] > 0.01)
        d = np.concatenate(
            [
                ((r.rgba[..., :3] * r.rgba[..., 3:]) - (full.rgba[..., :3] * full.rgba[..., 3:]))[sel].ravel(),
                (r.rgba[..., 3] - full.rgba[..., 3])[sel],
            ]
        )
        psnr[frac] = np.inf if not d.any() else 10 * np.log10(1 / np.mean(d**2))
    print("LOD PSNR vs full:", psnr)
    assert psnr[1] > 100  # the full budget is the model itself (in another order: float rounding only)
    assert psnr[1 / 4] >= 30.0 and psnr[1 / 16] >= 23.0 and psnr[1 / 4] > psnr[1 / 16]
