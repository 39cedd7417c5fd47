"""Unstructured-Lumigraph weights: properties (hypothesis), degenerate cases, and the fast
kernel against the one-surfel-at-a-time reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.errors import InputError
from opacityhull.model import Surfels
from opacityhull.render import kernels as K
from opacityhull.render.reference import ulr_weights_ref
from opacityhull.render.renderer import ulr_weights
from opacityhull.render.views import prepare_views, scan_order


def cam_at(eye, target=(0.0, 0.0, 0.0), fov_deg=100.0, size=64, up=(0.0, 1.0, 0.0)):
    f = size / (2 * math.tan(math.radians(fov_deg) / 2))
    K_ = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    eye = np.asarray(eye, float)
    target = np.asarray(target, float)
    d = (target - eye) / np.linalg.norm(target - eye)
    if abs(d @ np.asarray(up)) > 0.99:
        up = (1.0, 0.0, 0.0)
    return Camera(K=K_, width=size, height=size, world_from_cam=look_at_world_from_cam(eye, target, up))


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@st.composite
def scenes(draw, max_views=10):
    """Views on a sphere of radius ~1 looking at the origin, surfels within 0.1 of it,
    random visibility, a desired centre on the same sphere."""
    V = draw(st.integers(1, max_views))
    N = draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    eyes = [unit(rng.normal(size=3)) * rng.uniform(0.8, 1.2) for _ in range(V)]
    cams = [cam_at(e) for e in eyes]
    pos = rng.uniform(-0.1, 0.1, size=(N, 3))
    vis = rng.random((N, V)) < draw(st.floats(0.2, 1.0))
    normals = np.tile([0.0, 0.0, 1.0], (N, 1))
    surf = Surfels.from_bool(pos, normals, np.full(N, 0.01), vis)
    desired = unit(rng.normal(size=3)) * rng.uniform(0.8, 1.2)
    k = draw(st.integers(1, 8))
    return cams, surf, desired, k, rng


@settings(max_examples=60, deadline=None)
@given(scenes())
def test_weights_finite_nonnegative_normalised_and_equal_reference(scene):
    cams, surf, desired, k, _ = scene
    uw = ulr_weights(surf, cams, desired, k=k)
    W = uw.dense(len(cams))
    assert np.all(np.isfinite(W)) and np.all(W >= 0)
    vis = surf.visible_bool()
    drawn = vis.any(axis=1)  # every view sees every surfel inside its image here
    np.testing.assert_array_equal(uw.count > 0, drawn)
    np.testing.assert_allclose(W.sum(axis=1)[drawn], 1.0, atol=1e-6)
    assert np.all(W[~drawn] == 0)
    assert np.all(W[~vis] == 0), "a view outside the visibility vector got weight"
    R = ulr_weights_ref(surf.positions, vis, cams, desired, k=k)
    np.testing.assert_allclose(W, R, atol=2e-6)


@settings(max_examples=60, deadline=None)
@given(scenes())
def test_blends_at_most_k_minus_1_views_unless_degenerate(scene):
    cams, surf, desired, k, _ = scene
    W = ulr_weights(surf, cams, desired, k=k).dense(len(cams))
    n_vis = surf.visible_bool().sum(axis=1)
    nz = (W > 0).sum(axis=1)
    for i in range(len(n_vis)):
        if n_vis[i] == 0:
            assert nz[i] == 0
        elif k == 1 or n_vis[i] == 1:
            assert nz[i] == 1
        elif n_vis[i] >= k:
            assert 1 <= nz[i] <= k - 1  # the k-th nearest is the threshold (weight 0)
        else:
            assert nz[i] == n_vis[i]  # fewer than k: all blend, threshold at 180 degrees


@settings(max_examples=40, deadline=None)
@given(scenes())
def test_weights_invariant_to_view_order(scene):
    cams, surf, desired, k, rng = scene
    V = len(cams)
    perm = rng.permutation(V)
    vis = surf.visible_bool()
    surf_p = Surfels.from_bool(surf.positions, surf.normals, surf.radii, vis[:, perm])
    W = ulr_weights(surf, cams, desired, k=k).dense(V)
    Wp = ulr_weights(surf_p, [cams[j] for j in perm], desired, k=k).dense(V)
    np.testing.assert_allclose(Wp, W[:, perm], atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(scenes(max_views=8), st.integers(0, 7), st.integers(0, 2**31 - 1))
def test_weights_continuous_as_desired_view_approaches_a_captured_view(scene, which, seed):
    cams, surf, _, k, _ = scene
    v = which % len(cams)
    vis = surf.visible_bool()
    rows = np.flatnonzero(vis[:, v])
    if rows.size == 0:
        return
    C = cams[v].centre_world
    direction = unit(np.random.default_rng(seed).normal(size=3))
    # the approach is measured in units of the distance to the nearest other view: two
    # random views may nearly coincide, and then the hand-over happens on that scale
    others = [np.linalg.norm(c.centre_world - C) for j, c in enumerate(cams) if j != v]
    scale = min([1.0] + [d for d in others if d > 0])
    prev_gap = None
    prev_w = None
    for t in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6):
        w = ulr_weights(surf, cams, C + scale * t * direction, k=k).dense(len(cams))[rows]
        gap = np.max(1.0 - w[:, v])
        assert np.all(np.isfinite(w))
        if prev_gap is not None and t <= 1e-3:
            # in the limit the other views' weights vanish like θ², θ ∝ t
            assert gap <= prev_gap * 0.5 + 1e-9
        if prev_w is not None and t <= 1e-4:
            assert np.max(np.abs(w - prev_w)) < 1e-3  # no jump on the way in
        prev_gap, prev_w = gap, w
    assert prev_gap < 1e-6
    w0 = ulr_weights(surf, cams, C, k=k).dense(len(cams))[rows]
    assert np.all(w0[:, v] == 1.0), "coinciding rays must give exactly one-hot weights"
    assert np.all(np.delete(w0, v, axis=1) == 0.0)
    assert np.max(np.abs(w0 - prev_w)) < 1e-6


def _ring_scene(angles_deg, k, *, surfel=(0.0, 0.0, 0.0)):
    """Views at angle a from +Z in azimuth phi (degrees), seen from a surfel at the origin;
    azimuths that are multiples of 90 use exact ±sin a coordinates, so equal angles tie
    exactly in floating point."""
    cams = []
    for a, phi in angles_deg:
        sa, ca = math.sin(math.radians(a)), math.cos(math.radians(a))
        exact = {0: (sa, 0.0), 90: (0.0, sa), 180: (-sa, 0.0), 270: (0.0, -sa)}
        x, y = exact.get(phi, (sa * math.cos(math.radians(phi)), sa * math.sin(math.radians(phi))))
        cams.append(cam_at(np.array([x, y, ca])))
    surf = Surfels.from_bool(
        np.array([surfel]), np.array([[0.0, 0, 1]]), np.array([0.01]), np.ones((1, len(cams)), bool)
    )
    return cams, surf


def test_exactly_one_hot_when_desired_centre_is_a_view_centre(sphere_small):
    m = sphere_small
    v = 7
    uw = ulr_weights(m.surfels, m.cameras, m.cameras[v].centre_world, k=4)
    W = uw.dense(len(m.cameras))
    rows = m.surfels.visible_in(v)
    assert rows.sum() > 100
    assert np.all(W[rows, v] == 1.0)
    assert np.all(np.delete(W[rows], v, axis=1) == 0.0)


def test_duplicate_cameras_share_the_one_hot_weight():
    cams, surf = _ring_scene([(30, 0), (30, 0), (40, 90)], k=4)
    W = ulr_weights(surf, cams, cams[0].centre_world, k=4).dense(3)
    np.testing.assert_array_equal(W[0], [0.5, 0.5, 0.0])


@pytest.mark.parametrize("k", [2, 3, 4, 5])
def test_uniform_when_all_penalties_tie(k):
    # four views at the same angle (mirror-symmetric coordinates: the ties are exact)
    cams, surf = _ring_scene([(20, 0), (20, 90), (20, 180), (20, 270)], k=k)
    W = ulr_weights(surf, cams, (0.0, 0.0, 1.0), k=k).dense(4)
    n = min(k, 4)
    assert (W[0] > 0).sum() == n
    np.testing.assert_allclose(W[0][W[0] > 0], 1.0 / n)
    # which tied views are chosen depends on their centres, not on their order
    perm = [2, 0, 3, 1]
    surf_p = Surfels.from_bool(surf.positions, surf.normals, surf.radii, np.ones((1, 4), bool))
    Wp = ulr_weights(surf_p, [cams[j] for j in perm], (0.0, 0.0, 1.0), k=k).dense(4)
    np.testing.assert_allclose(Wp, W[:, perm])
    np.testing.assert_allclose(W, ulr_weights_ref(surf.positions, np.ones((1, 4), bool), cams, (0, 0, 1.0), k=k))


def test_buehler_formula_with_k_th_view_as_threshold():
    cams, surf = _ring_scene([(10, 0), (20, 90), (30, 180), (40, 270), (50, 45)], k=4)
    W = ulr_weights(surf, cams, (0.0, 0.0, 1.0), k=4).dense(5)
    c = np.cos(np.radians([10, 20, 30, 40]))
    r = (c[:3] - c[3]) / (1 - c[:3])
    np.testing.assert_allclose(W[0, :3], r / r.sum(), rtol=1e-6)
    assert W[0, 3] == 0 and W[0, 4] == 0


def test_fewer_visible_views_than_k_blend_all_with_threshold_at_180_degrees():
    cams, surf = _ring_scene([(10, 0), (35, 90)], k=4)
    W = ulr_weights(surf, cams, (0.0, 0.0, 1.0), k=4).dense(2)
    c = np.cos(np.radians([10, 35]))
    r = (1 + c) / (1 - c)
    np.testing.assert_allclose(W[0], r / r.sum(), rtol=1e-6)
    # a single visible view gets everything
    one = Surfels.from_bool(surf.positions, surf.normals, surf.radii, np.array([[False, True]]))
    np.testing.assert_array_equal(ulr_weights(one, cams, (0.0, 0.0, 1.0), k=4).dense(2)[0], [0.0, 1.0])


def test_k_equal_one_is_nearest_view():
    cams, surf = _ring_scene([(10, 0), (20, 90), (30, 180)], k=1)
    W = ulr_weights(surf, cams, (0.0, 0.0, 1.0), k=1).dense(3)
    np.testing.assert_array_equal(W[0], [1.0, 0.0, 0.0])


def test_no_visible_or_degenerate_surfel_is_not_drawn_and_never_nan():
    cams, _ = _ring_scene([(10, 0), (20, 90)], k=4)
    pos = np.array([[0.0, 0, 0], [0.0, 0, 1.0], [np.nan, 0, 0], [0.05, 0, 0]])
    vis = np.array([[False, False], [True, True], [True, True], [True, False]])
    surf = Surfels.from_bool(pos, np.tile([0.0, 0, 1], (4, 1)), np.full(4, 0.01), vis)
    uw = ulr_weights(surf, cams, (0.0, 0.0, 1.0), k=4)
    # no visible view; surfel on the desired centre; NaN position; one visible view
    np.testing.assert_array_equal(uw.count, [0, 0, 0, 1])
    W = uw.dense(2)
    assert np.all(np.isfinite(W)) and np.all(np.isfinite(uw.weight))
    np.testing.assert_array_equal(W[:3], 0.0)
    np.testing.assert_array_equal(W[3], [1.0, 0.0])


def test_excluded_views_never_blend(sphere_small):
    m = sphere_small
    C = m.cameras[4].centre_world
    W = ulr_weights(m.surfels, m.cameras, C, k=4, exclude_views=[4, 5]).dense(len(m.cameras))
    assert np.all(W[:, [4, 5]] == 0)
    drawn = W.sum(axis=1) > 0
    np.testing.assert_allclose(W.sum(axis=1)[drawn], 1.0, atol=1e-6)
    R = ulr_weights_ref(m.surfels.positions, m.surfels.visible_bool(), m.cameras, C, k=4, exclude_views=[4, 5])
    np.testing.assert_allclose(W, R, atol=2e-6)
    with pytest.raises(InputError, match="out of range"):
        ulr_weights(m.surfels, m.cameras, C, exclude_views=[99])


def test_view_projecting_outside_its_image_is_not_a_candidate():
    # a narrow camera that cannot see the surfel although its visibility bit is set
    narrow = cam_at((0.0, 0.0, 1.0), target=(0.0, 0.5, 0.0), fov_deg=10)
    wide = cam_at((0.3, 0.0, 1.0))
    surf = Surfels.from_bool(np.zeros((1, 3)), np.array([[0.0, 0, 1]]), np.array([0.01]), np.ones((1, 2), bool))
    W = ulr_weights(surf, [narrow, wide], (0.0, 0.0, 1.0), k=4).dense(2)
    np.testing.assert_array_equal(W[0], [0.0, 1.0])


@settings(max_examples=40, deadline=None)
@given(scenes())
def test_scan_order_lower_bounds_hold_for_every_surfel(scene):
    cams, surf, desired, _, _ = scene
    pv = prepare_views(cams)
    o, rho = K.bounding_sphere(surf.positions)
    order, s_lb = scan_order(pv.centres, desired, o, rho)
    assert np.all(np.diff(s_lb) >= 0)
    P = surf.positions.astype(np.float64)
    d = desired - P
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for j, v in enumerate(order):
        e = pv.centres[v] - P
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        s = 0.5 * np.sum((e - d) ** 2, axis=1)
        assert np.all(s >= s_lb[j] - 1e-12)


@settings(max_examples=40, deadline=None)
@given(scenes(), st.integers(0, 5))
def test_block_bounds_hold_for_every_surfel_of_the_block(scene, start):
    cams, surf, desired, _, _ = scene
    pv = prepare_views(cams)
    N = len(surf)
    i0 = min(start, N - 1)
    order = np.empty(pv.n_views, np.int64)
    s_lb = np.empty(pv.n_views)
    K.block_bounds(surf.positions, i0, N, np.asarray(desired, float), pv.centres, order, s_lb)
    assert sorted(order.tolist()) == list(range(pv.n_views)) and np.all(np.diff(s_lb) >= 0)
    P = surf.positions[i0:].astype(np.float64)
    d = desired - P
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for j, v in enumerate(order):
        e = pv.centres[v] - P
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        assert np.all(0.5 * np.sum((e - d) ** 2, axis=1) >= s_lb[j] - 1e-12)


def test_block_search_equals_frame_search(sphere_small):
    """Per-block bounds (the default) and per-frame bounds select the same views."""
    m = sphere_small
    pv = prepare_views(m.cameras)
    N = len(m.surfels)
    C = np.array([0.2, 0.3, 0.4])
    o, rho = K.bounding_sphere(m.surfels.positions)
    order, s_lb = scan_order(pv.centres, C, o, rho)
    outs = []
    for block in (0, 7, 512):
        idx = np.empty((N, 4), np.int32)
        w = np.empty((N, 4), np.float32)
        uv = np.empty((N, 4, 2), np.float32)
        cnt = np.empty(N, np.int32)
        surfels = (m.surfels.positions, m.surfels.visibility, np.ones(N, bool))  # every surfel drawable
        views = (np.ones(pv.n_views, np.uint8), C, pv.centres, pv.cams, pv.sizes)  # every view allowed
        K.ulr_select(K.UlrHead(*surfels, *views), order, s_lb, pv.tie_rank, 4, idx, w, uv, cnt, 0, N, block=block)
        outs.append((idx, w))
    for idx, w in outs[1:]:
        np.testing.assert_array_equal(idx, outs[0][0])
        np.testing.assert_array_equal(w, outs[0][1])
