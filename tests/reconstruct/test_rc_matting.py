"""Multi-background matting: the numba kernel against the NumPy closed form and the
per-pixel lstsq oracle, the hard cases, and a property test."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.errors import InputError, ShapeError
from opacityhull.reconstruct.matting import (
    FLAG_CHANNEL_LOST,
    FLAG_INVALID,
    FLAG_SATURATED,
    FLAG_UNKNOWN,
    MattingOptions,
    backdrop_from_displays,
    fill_from_neighbours,
    fill_from_neighbours_reference,
    solve_matte,
    solve_matte_numpy,
    solve_matte_reference,
    straight_from_premul,
)
from opacityhull.riggeometry import RigGeometry, back_display


def composite(alpha, F, B, noise=0.0, rng=None):
    """C_k = alpha F + (1 - alpha) B_k (+ noise); alpha (H, W), F (H, W, 3), B (K, H, W, 3)."""
    C = (alpha[..., None] * F)[None] + (1 - alpha)[None, ..., None] * B
    if noise:
        C = C + rng.normal(0, noise, C.shape)
    return C.astype(np.float32)


def scene(K=4, H=12, W=16, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, (H, W))
    a[0, :4] = 0.0
    a[1, :4] = 1.0
    F = rng.uniform(0.05, 0.9, (H, W, 3))
    B = rng.uniform(0.0, 1.0, (K, H, W, 3)).astype(np.float32)
    return a, F, B, composite(a, F, B, noise, rng)


@pytest.mark.parametrize("K", [2, 3, 6])
def test_three_solvers_agree(K):
    a, F, B, C = scene(K=K, noise=0.01, seed=K)
    opts = MattingOptions(max_alpha_std=0.5)
    r1 = solve_matte(C, B, options=opts)
    r2 = solve_matte_numpy(C, B, options=opts)
    r3 = solve_matte_reference(C, B, options=opts)
    for r in (r2, r3):
        np.testing.assert_allclose(r1.alpha, r.alpha, atol=2e-6)
        np.testing.assert_allclose(r1.fg_premul, r.fg_premul, atol=2e-6)
        np.testing.assert_allclose(r1.alpha_std, r.alpha_std, rtol=1e-4, atol=1e-7)
        np.testing.assert_array_equal(r1.flags, r.flags)
    assert abs(r1.noise_sigma - r3.noise_sigma) < 1e-6


def test_noise_free_exact_and_premultiplied():
    a, F, B, C = scene(K=3)
    r = solve_matte(C, B)
    np.testing.assert_allclose(r.alpha, a, atol=1e-5)
    np.testing.assert_allclose(r.fg_premul, a[..., None] * F, atol=1e-5)
    assert not r.unknown.any()
    straight = straight_from_premul(np.dstack([r.fg_premul, r.alpha]))[..., :3]
    np.testing.assert_allclose(straight[a > 0.05], F[a > 0.05], atol=1e-3)


def test_noise_estimate_and_predicted_std():
    """The estimated sigma matches the injected noise, and the spread of alpha errors
    matches the predicted alpha_std (within sampling error)."""
    a, F, B, C = scene(K=6, H=80, W=80, noise=0.01, seed=3)
    r = solve_matte(C, B, options=MattingOptions(max_alpha_std=1.0, fill=False))
    assert 0.008 < r.noise_sigma < 0.012
    inner = (a > 0.1) & (a < 0.9)  # no clamping
    z = (r.alpha - a)[inner] / r.alpha_std[inner]
    assert 0.8 < np.std(z) < 1.2


def test_identical_backdrops_unknown_and_filled():
    """Where every backdrop is the same colour alpha is unobservable: flagged unknown,
    filled from the neighbours, never NaN."""
    a, F, B, C = scene(K=4, H=20, W=20, seed=5)
    a[:] = 1.0
    a[:, :3] = 0.0
    B[:, 8:12, 8:12] = 0.4  # identical backdrops in a 4x4 block inside the opaque object
    C = composite(a, F, B)
    r = solve_matte(C, B)
    blk = np.zeros((20, 20), bool)
    blk[8:12, 8:12] = True
    assert np.array_equal(r.unknown, blk)
    assert np.all(np.isfinite(r.alpha)) and np.all(np.isfinite(r.fg_premul))
    # filled from the (mostly opaque) neighbourhood: push-pull blends a few pixels of the
    # transparent strip 5 px away in at its coarsest levels
    assert r.alpha[blk].min() > 0.9
    assert np.all(r.confidence[blk] == 0)
    r0 = solve_matte(C, B, options=MattingOptions(fill=False))
    assert np.all(r0.alpha[blk] == 0.0)  # S = 0: no estimate, clamped to 0 without filling


def test_nearly_identical_backdrops_flagged_by_predicted_std():
    a, F, B, C = scene(K=2, H=10, W=10, seed=6, noise=0.0)
    B[1] = B[0] + 1e-4  # spread 1e-4: alpha_std = sigma_floor / sqrt(S) >> 0.05
    C = composite(a, F, B)
    r = solve_matte(C, B)
    assert r.unknown.all()


def test_foreground_equal_to_a_backdrop_is_not_degenerate():
    """PITFALLS: F = B_1 is harmless; only alike backdrops degenerate."""
    rng = np.random.default_rng(7)
    B = rng.uniform(0, 1, (3, 8, 8, 3)).astype(np.float32)
    a = np.full((8, 8), 0.6)
    F = B[0].astype(np.float64)
    C = composite(a, F, B)
    r = solve_matte(C, B)
    assert not r.unknown.any()
    np.testing.assert_allclose(r.alpha, 0.6, atol=1e-5)
    np.testing.assert_allclose(r.fg_premul, 0.6 * F, atol=1e-5)


def test_saturated_observations_are_dropped_and_flagged():
    a, F, B, C = scene(K=4, H=10, W=10, seed=8)
    C = C * 2.0
    B = B * 2.0
    a2 = a
    level = 1.2
    sat_any = np.any(C >= level, axis=(0, 3)) | np.any(B >= level, axis=(0, 3))
    clippedC = np.minimum(C, level)
    clippedB = np.minimum(B, level)
    r = solve_matte(
        clippedC, clippedB, c_saturation=level, b_saturation=level, options=MattingOptions(max_alpha_std=10, fill=False)
    )
    assert np.array_equal(r.saturated, sat_any)
    ref = solve_matte_reference(
        clippedC, clippedB, c_saturation=level, b_saturation=level, options=MattingOptions(max_alpha_std=10, fill=False)
    )
    np.testing.assert_allclose(r.alpha, ref.alpha, atol=2e-6)
    # where each channel kept >= 2 unsaturated backdrops the estimate is exact
    ok = np.all(np.sum((clippedC < level) & (clippedB < level), axis=0) >= 2, axis=-1)
    np.testing.assert_allclose(r.alpha[ok], a2[ok], atol=1e-4)
    # naive use of the clipped values is wrong somewhere
    naive = solve_matte(clippedC, clippedB, options=MattingOptions(max_alpha_std=10, fill=False))
    assert np.abs(naive.alpha - a2)[sat_any].max() > 0.05


def test_channel_with_every_observation_saturated():
    a = np.full((2, 2), 1.0)
    F = np.full((2, 2, 3), 0.5)
    F[0, 0, 0] = 3.0  # red clips in every shot of pixel (0, 0)
    B = np.random.default_rng(9).uniform(0, 1, (3, 2, 2, 3)).astype(np.float32)
    C = np.minimum(composite(a, F, B), 2.0)
    r = solve_matte(C, B, c_saturation=2.0, options=MattingOptions(fill=False))
    assert r.flags[0, 0] & FLAG_CHANNEL_LOST and r.flags[0, 0] & FLAG_SATURATED
    assert r.fg_premul[0, 0, 0] == pytest.approx(2.0)  # a lower bound: the clip level
    assert r.alpha[0, 0] == pytest.approx(1.0, abs=1e-5)  # from the green and blue channels


def test_nan_and_inf_inputs_are_dropped_never_propagated():
    a, F, B, C = scene(K=4, H=10, W=10, seed=10)
    C[0, 2, 3, 1] = np.nan
    C[1, 4, 4, :] = np.inf
    B[2, 5, 5, 0] = -np.inf
    B[:, 7, 7, :] = np.nan  # every backdrop of a pixel unusable
    r = solve_matte(C, B)
    assert np.all(np.isfinite(r.alpha)) and np.all(np.isfinite(r.fg_premul)) and np.all(np.isfinite(r.alpha_std))
    for y, x in ((2, 3), (4, 4), (5, 5), (7, 7)):
        assert r.flags[y, x] & FLAG_INVALID
    assert r.flags[7, 7] & FLAG_UNKNOWN
    np.testing.assert_allclose(r.alpha[2, 3], a[2, 3], atol=1e-5)  # the other observations suffice
    ref = solve_matte_reference(C, B, options=MattingOptions(fill=False))
    fast = solve_matte(C, B, options=MattingOptions(fill=False))
    np.testing.assert_allclose(fast.alpha, ref.alpha, atol=2e-6)
    np.testing.assert_array_equal(fast.flags, ref.flags)


def test_alpha_clamped_to_unit_interval():
    rng = np.random.default_rng(11)
    B = rng.uniform(0, 1, (3, 6, 6, 3)).astype(np.float32)
    C = (B * 1.5 - 0.2).astype(np.float32)  # beta = 1.5: alpha = -0.5 unconstrained
    # the clamped fit has large residuals: fix sigma so they are not taken for noise
    opts = MattingOptions(noise_sigma=1e-3)
    r = solve_matte(C, B, options=opts)
    assert r.alpha.min() >= 0 and r.alpha.max() <= 1
    assert np.all(r.alpha == 0.0)
    C2 = (0.3 - 0.5 * B).astype(np.float32)  # beta = -0.5: alpha = 1.5 unconstrained
    r2 = solve_matte(C2, B, options=opts)
    assert np.all(r2.alpha == 1.0)


def test_bad_shapes_and_options():
    with pytest.raises(ShapeError, match="expected \\(K, H, W, 3\\)"):
        solve_matte(np.zeros((2, 4, 4)), np.zeros((2, 4, 4)))
    with pytest.raises(ShapeError, match="one per observation"):
        solve_matte(np.zeros((2, 4, 4, 3)), np.zeros((3, 4, 4, 3)))
    with pytest.raises(InputError, match="at least 2 backdrops"):
        solve_matte(np.zeros((1, 4, 4, 3)), np.zeros((1, 4, 4, 3)))
    with pytest.raises(InputError, match="max_alpha_std"):
        MattingOptions(max_alpha_std=0)
    with pytest.raises(InputError, match="c_saturation"):
        solve_matte(np.zeros((2, 4, 4, 3)), np.zeros((2, 4, 4, 3)), c_saturation=-1)


@settings(max_examples=40, deadline=None)
@given(
    alpha=st.floats(0.0, 1.0),
    f=st.tuples(*[st.floats(0.0, 1.0)] * 3),
    K=st.integers(2, 6),
    seed=st.integers(0, 2**31 - 1),
)
def test_property_recovers_alpha_within_noise(alpha, f, K, seed):
    """For random alpha, F and well-separated backdrops (a complementary pair plus
    random ones), alpha is recovered within 5 predicted standard deviations."""
    rng = np.random.default_rng(seed)
    H = W = 4
    base = rng.uniform(0.0, 1.0, (H, W, 3))
    B = [base, 1.0 - base] + [rng.uniform(0, 1, (H, W, 3)) for _ in range(K - 2)]
    B = np.array(B, dtype=np.float32)
    sigma = 0.003
    a = np.full((H, W), alpha)
    F = np.broadcast_to(np.array(f), (H, W, 3))
    C = composite(a, F, B, sigma, rng)
    r = solve_matte(C, B, options=MattingOptions(noise_sigma=sigma, max_alpha_std=1.0, fill=False))
    tol = 5 * r.alpha_std + 1e-6
    assert np.all(np.abs(r.alpha - a) <= tol)
    assert np.all(np.isfinite(r.fg_premul))


def test_fill_numba_matches_reference_and_keeps_known():
    rng = np.random.default_rng(12)
    for shape in [(1, 1), (1, 9), (7, 5), (33, 47)]:
        v = rng.normal(size=shape + (3,))
        w = (rng.uniform(size=shape) > 0.6).astype(float)
        w.flat[0] = 0.4
        f1 = fill_from_neighbours(v, w)
        f2 = fill_from_neighbours_reference(v, w)
        np.testing.assert_allclose(f1, f2, atol=1e-12)
        assert np.all(np.isfinite(f1))
        np.testing.assert_array_equal(f1[w == 1], v[w == 1])
    assert np.all(fill_from_neighbours(np.ones((4, 4, 2)), np.zeros((4, 4))) == 0)  # nothing known → 0


def test_fill_reproduces_a_linear_ramp_in_a_hole():
    y, x = np.mgrid[0:32, 0:32].astype(float)
    v = (0.02 * x + 0.01 * y)[..., None]
    w = np.ones((32, 32))
    w[12:20, 12:20] = 0
    f = fill_from_neighbours(v, w)
    assert np.abs(f - v)[12:20, 12:20].max() < 0.05  # smooth, bounded by neighbours


def test_backdrop_from_displays_fronto_parallel():
    """A pinhole camera looking straight at the back display sees its pattern: each pixel
    centre's texel (independent: computed from the panel's metric size)."""
    geo = RigGeometry.from_dict(
        {
            "target_m": [0, 0.2, -0.4],
            "cameras": [{"name": "c", "width": 40, "height": 30, "distance_m": 1, "fov_y_deg": 20}],
            "displays": [
                back_display([0.0, 0.2, -0.4], [0.8, 0.6], [8, 6], rotates_with_table=False, max_radiance=2.0)
            ],
        }
    )
    f = 100.0
    K = np.array([[f, 0, 19.5], [0, f, 14.5], [0, 0, 1]])
    T = look_at_world_from_cam((0.0, 0.2, 0.6), (0.0, 0.2, -0.4))
    cam = Camera(K=K, width=40, height=30, world_from_cam=T)
    pat = np.random.default_rng(13).uniform(0, 1, (6, 8, 3)).astype(np.float32)
    B = backdrop_from_displays(cam, 0.0, geo, {"back": pat}, supersample=1)
    # pixel (u, v) sees x = (u - 19.5) / f * 1.0 m, y = 0.2 - (v - 14.5) / f
    for u, v in [(0, 0), (19, 14), (39, 29), (10, 20)]:
        x = (u - 19.5) / f
        yy = -(v - 14.5) / f
        if abs(x) < 0.4 and abs(yy) < 0.3:
            col = int((x + 0.4) / 0.8 * 8)
            row = int((0.3 - yy) / 0.6 * 6)
            np.testing.assert_allclose(B[v, u], 2.0 * pat[row, col], atol=1e-6)
    # the fixed back panel turns by -table_deg in the object frame: at 180 deg it stands
    # between the camera and the target facing away, so the camera sees its dark back
    assert B.shape == (30, 40, 3)
    B180 = backdrop_from_displays(cam, 180.0, geo, {"back": pat}, supersample=1)
    assert np.all(B180 == 0)
