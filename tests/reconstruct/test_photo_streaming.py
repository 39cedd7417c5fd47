"""The streamed photo refinement (reconstruct/photo.py, issue #14): the cost volume computed
a few views at a time equals the full-stack kernel bit for bit at any memory budget; the
batched hull test equals the all-view one; the whole refinement equals a full-stack
reference path; each photograph is read once when the budget allows, and the refinement's
traced memory stays far below the (V, H, W) stacks it used to build."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import rcsynth

from opacityhull.errors import ConfigError
from opacityhull.reconstruct import photo
from opacityhull.reconstruct.hull import point_in_hull
from opacityhull.reconstruct.photo import PhotoConfig, cost_volume, refine_surfels, select_views

R_HULL = 0.05
R_TRUE = 0.8 * R_HULL
DIST = 0.16


def cameras(n, sizes=((64, 64),)):
    return rcsynth.sphere_cameras(n, distance_m=DIST, sizes=sizes)


def render(cam, seed=1):
    return rcsynth.sphere_photo(cam, r_true=R_TRUE, r_hull=R_HULL, seed=seed)


def surfels(cams, n):
    return rcsynth.sphere_hull_surfels(n, radius=R_HULL, cameras=cams)


class Counted:
    """A per-view sequence that counts how often each view is read."""

    def __init__(self, arrays):
        self.arrays = list(arrays)
        self.reads = np.zeros(len(self.arrays), int)

    def __len__(self):
        return len(self.arrays)

    def __getitem__(self, i):
        self.reads[i] += 1
        return self.arrays[i]


@pytest.fixture(scope="module")
def scene():
    cams = cameras(20, sizes=((64, 64), (56, 48), (72, 60)))
    imgs, alphas = map(list, zip(*[render(c) for c in cams], strict=True))
    # non-finite pixels and mattes: a NaN pixel invalidates patches, a NaN matte is outside
    imgs[3][20:26, 30:34] = np.nan
    alphas[5][10:40, 25:30] = np.nan
    pos, nrm, rad, vis = surfels(cams, 700)
    return cams, imgs, alphas, pos, nrm, rad, vis


def _full_stack_scores(pos, nrm, cams, imgs, alphas, views, step, spacing, cfg):
    grey = photo._stack("images", imgs, cams, 3)
    alpha = photo._stack("alphas", alphas, cams, 1)
    np.nan_to_num(alpha, copy=False, nan=0.0)
    kernel = {k: getattr(cfg, k) for k in ("n_depths", "patch_size", "texture_std", "alpha_threshold", "n_best")}
    return cost_volume(pos, nrm, cams, grey, alpha, views, step, spacing, **kernel)


@pytest.mark.parametrize("n_views,n_best,cap", [(5, 0, 5), (5, 2, 7), (3, 0, 3), (4, 0, 64)])
def test_streamed_cost_volume_equals_the_full_stack_bit_for_bit(scene, n_views, n_best, cap):
    cams, imgs, alphas, pos, nrm, _, vis = scene
    cfg = PhotoConfig(n_views=n_views, n_best=n_best, max_views_in_memory=max(cap, n_views))
    views = select_views(pos, nrm, vis, cams, n_views=n_views, exclude_views=[1])
    rng = np.random.default_rng(n_views + cap)
    step = rng.uniform(0.2e-3, 0.6e-3, len(pos))
    spacing = rng.uniform(0.3e-3, 0.8e-3, len(pos))
    ref = _full_stack_scores(pos, nrm, cams, imgs, alphas, views, step, spacing, cfg)
    img_reads, alpha_reads = Counted(imgs), Counted(alphas)
    got, counts = photo._streamed_cost_volume(
        pos, nrm, cams, img_reads, alpha_reads, views, step, spacing, config=cfg, cap=cap
    )
    np.testing.assert_array_equal(got, ref)  # NaN where NaN, every other bit equal
    assert np.isfinite(ref).mean() > 0.3  # the comparison is not vacuous
    used = np.unique(views[(views >= 0).sum(1) >= 2])
    used = used[used >= 0]
    assert counts["views_in_memory"] == min(cap, used.size) <= cap
    assert img_reads.reads[1] == 0  # the excluded view is never read
    if cap >= used.size:
        # everything fits: each photograph used is read exactly once, the others never
        np.testing.assert_array_equal(img_reads.reads[used], 1)
        assert img_reads.reads.sum() == used.size
    else:
        assert counts["n_view_loads"] == img_reads.reads.sum() > used.size  # evicted views read again
    np.testing.assert_array_equal(img_reads.reads, alpha_reads.reads)


def test_batches_cover_every_scored_surfel_once_within_the_budget(scene):
    cams, _, _, pos, nrm, _, vis = scene
    views = select_views(pos, nrm, vis, cams, n_views=5)
    views[:7] = -1  # no views
    views[7:11, 1:] = -1  # one view: NaN rows, never scored
    for cap in (5, 6, 9, 40):
        batches = photo._cost_batches(views, cap)
        allb = np.concatenate(batches)
        np.testing.assert_array_equal(np.sort(allb), np.flatnonzero((views >= 0).sum(1) >= 2))
        for b in batches:
            vv = views[b]
            assert b.size and np.unique(vv[vv >= 0]).size <= cap
        refs = [int(views[b[0], 0]) for b in batches]
        assert refs == sorted(refs)  # in reference-view order
        assert all(np.all(views[b, 0] == views[b[0], 0]) for b in batches)


def test_batched_hull_test_equals_all_views(scene):
    cams, _, alphas, _, _, _, _ = scene
    sils = photo._silhouettes(alphas, cams, 0.5)
    full = [np.nan_to_num(a, nan=0.0) > 0.5 for a in alphas]
    for v in range(len(cams)):
        np.testing.assert_array_equal(sils[v], full[v])
    pts = np.random.default_rng(3).uniform(-1.2 * R_HULL, 1.2 * R_HULL, (4000, 3))
    ref = point_in_hull(pts, full, cams)
    assert 0.2 < ref.mean() < 0.8
    for batch in (1, 3, 7, 100):
        np.testing.assert_array_equal(photo._in_hull(pts, sils, cams, batch=batch), ref)


def _full_stack_path(monkeypatch):
    """refine_surfels with the cost volume over full (V, H, W) stacks and the hull test
    over every view at once: the pre-streaming arithmetic."""

    def scores(pos, nrm, cameras, images, alphas, views, step, spacing, *, config, cap):
        s = _full_stack_scores(pos, nrm, cameras, list(images), list(alphas), views, step, spacing, config)
        return s, {"n_view_loads": len(cameras), "n_cost_batches": 1, "views_in_memory": len(cameras)}

    monkeypatch.setattr(photo, "_streamed_cost_volume", scores)
    monkeypatch.setattr(photo, "_in_hull", lambda p, sils, cams, *, batch: point_in_hull(p, list(sils), list(cams)))


@pytest.mark.parametrize(
    "cfg",
    [
        PhotoConfig(keep_coverage=False, radius_neighbours=0, max_views_in_memory=5),  # the build's shading mode
        PhotoConfig(rim_cos=0.3, n_best=2, keep_coverage=False, max_views_in_memory=6),
        PhotoConfig(normals="pca", n_views=4, max_views_in_memory=4, coverage_rounds=2),
    ],
)
def test_refinement_equals_the_full_stack_reference(scene, monkeypatch, cfg):
    cams, imgs, alphas, pos, nrm, rad, vis = scene
    got = refine_surfels(pos, nrm, rad, vis, cams, imgs, alphas, config=cfg, exclude_views=[2])
    with monkeypatch.context() as m:
        _full_stack_path(m)
        ref = refine_surfels(pos, nrm, rad, vis, cams, imgs, alphas, config=cfg, exclude_views=[2])
    for a, b in zip(got[:3], ref[:3], strict=True):
        np.testing.assert_array_equal(a, b)
    for key in ("depth_m", "confident", "rim", "ncc"):
        np.testing.assert_array_equal(got[3][key], ref[3][key])
    # not vacuous: confident depths, and each configuration moves, holds at the rim or
    # restores outlines for a good part of the surfels
    st = got[3]
    assert st["n_confident"] > 0.5 * len(pos)
    assert st["n_moved"] + st["n_rim"] + st["n_restored_for_coverage"] > 0.3 * len(pos), st
    assert got[3]["views_in_memory"] <= cfg.max_views_in_memory


def _traced_peak(n_cams, cap, side=96, n_surfels=300):
    cams = cameras(n_cams, sizes=((side, side),))
    rendered = [render(c) for c in cams]
    pos, nrm, rad, vis = surfels(cams, n_surfels)

    class Lazy:  # photographs made when read, like the build's deferred views
        def __init__(self, k):
            self.k = k

        def __len__(self):
            return len(cams)

        def __getitem__(self, i):
            return rendered[i][self.k].copy()

    cfg = PhotoConfig(keep_coverage=False, radius_neighbours=0, max_views_in_memory=cap)  # the build's mode
    tracemalloc.start()
    try:
        _, _, _, st = refine_surfels(pos, nrm, rad, vis, cams, Lazy(0), Lazy(1), config=cfg)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert st["n_moved"] > 0.3 * n_surfels and st["views_in_memory"] == cap
    return peak


def test_refinement_memory_does_not_grow_with_the_views(monkeypatch):
    """Traced peak (NumPy allocations) of the build's shading-mode refinement with an
    8-view budget (and the view selection's chunk at 64 kB): 120 views within 1.5x of 30
    views, and below a quarter of the (V, H, W) grey + alpha + silhouette stacks (9 B a
    pixel a view) the full-stack path allocated."""
    monkeypatch.setattr(photo, "SELECT_CHUNK_BYTES", 1 << 16)
    _traced_peak(12, 8, side=32, n_surfels=50)  # numba compiled and loaded before measuring
    p30, p120 = _traced_peak(30, 8), _traced_peak(120, 8)
    assert p120 < 1.5 * p30, (p30, p120)
    assert p120 < 120 * 96 * 96 * 9 / 4, p120


def test_select_views_in_chunks_is_the_same(scene, monkeypatch):
    cams, _, _, pos, nrm, _, vis = scene
    ref = select_views(pos, nrm, vis, cams, n_views=5, exclude_views=[4])
    monkeypatch.setattr(photo, "SELECT_CHUNK_BYTES", 64 * len(cams) * 13)  # 13 surfels a chunk
    np.testing.assert_array_equal(select_views(pos, nrm, vis, cams, n_views=5, exclude_views=[4]), ref)


def test_budget_below_the_views_per_surfel_is_refused():
    with pytest.raises(ConfigError, match="max_views_in_memory"):
        PhotoConfig(n_views=5, max_views_in_memory=4)
