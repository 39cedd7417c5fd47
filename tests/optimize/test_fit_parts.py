"""The fitting's parts against independent references: SH and SSIM gradients against
finite differences, SSIM against scikit-image, Adam against a hand-computed step,
densification invariants, the splat PLY round trip, the config's named errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import ConfigError
from opacityhull.optimize.adam import Adam, exp_decay
from opacityhull.optimize.appearance import sh_colors, sh_colors_backward
from opacityhull.optimize.config import FitConfig, fit_preset
from opacityhull.optimize.densify import GradStats, densify_and_prune
from opacityhull.optimize.fit import step_loss
from opacityhull.optimize.splatply import read_splat_ply, write_splat_ply
from opacityhull.optimize.ssim import ssim_and_grad, ssim_map
from opacityhull.optimize.surfelparams import normals_of, quat_to_rotmat, quats_from_normals, start_params


def _unit(rng, n):
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), degree=st.integers(0, 3))
def test_sh_gradient_equals_finite_differences(seed, degree):
    rng = np.random.default_rng(seed)
    n, B = 5, (degree + 1) ** 2
    coeffs = rng.normal(0, 0.3, (n, 16, 3)).astype(np.float64)
    dirs = _unit(rng, n)
    w = rng.standard_normal((n, 3))

    def loss(c):
        col, _, _ = sh_colors(c, dirs, degree=degree)
        return float(np.sum(w * col.astype(np.float64)))

    col, Y, pos = sh_colors(coeffs, dirs, degree=degree)
    g = sh_colors_backward(w.astype(np.float32), Y, pos, 16)
    assert np.all(g[:, B:, :] == 0)
    h = 1e-3
    for _ in range(6):
        i, j, c = rng.integers(n), rng.integers(B), rng.integers(3)
        raw = float(np.dot(Y[i].astype(np.float64), coeffs[i, :B, c]) + 0.5)
        if abs(raw) < 0.05:  # the clamp's kink
            continue
        e = np.zeros_like(coeffs)
        e[i, j, c] = h
        fd = (loss(coeffs + e) - loss(coeffs - e)) / (2 * h)
        assert g[i, j, c] == pytest.approx(fd, rel=2e-3, abs=2e-4)


def test_sh_dc_only_is_the_3dgs_constant():
    c = np.zeros((1, 1, 3))
    c[0, 0] = (1.0, -1.0, 0.0)
    col, _, pos = sh_colors(c, np.array([[0.0, 0.0, 1.0]]), degree=0)
    np.testing.assert_allclose(col[0], [0.5 + 0.28209479, 0.5 - 0.28209479, 0.5], rtol=1e-6)
    assert pos.all()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_sh_residual_over_a_base_equals_the_degree_one_formula_and_its_finite_differences(seed):
    # the sh+ulr mode: colour = max(base + Σ c_j Y_j, 0) with a per-surfel base (the ULR
    # colour), no ½; the degree-1 basis written out (3DGS: C0, −C1·y, C1·z, −C1·x)
    rng = np.random.default_rng(seed)
    n = 6
    coeffs = rng.normal(0, 0.3, (n, 16, 3))
    dirs = _unit(rng, n)
    base = rng.uniform(-0.2, 1.2, (n, 3))
    w = rng.standard_normal((n, 3))
    C0, C1 = 0.28209479177387814, 0.4886025119029199
    x, y, z = dirs.T
    Y = np.stack([np.full(n, C0), -C1 * y, C1 * z, -C1 * x], axis=1)
    ref = np.maximum(base + np.einsum("nb,nbc->nc", Y, coeffs[:, :4]), 0.0)
    col, basis, pos = sh_colors(coeffs, dirs, degree=1, base=base)
    np.testing.assert_allclose(col, ref, atol=1e-5)
    zero, _, _ = sh_colors(np.zeros_like(coeffs), dirs, degree=1, base=base)
    np.testing.assert_allclose(zero, np.maximum(base, 0), atol=1e-6)  # a zero residual is the base
    g = sh_colors_backward(w.astype(np.float32), basis, pos, 16)
    assert np.all(g[:, 4:] == 0) and np.all(g[~pos[:, None, :].repeat(16, 1)] == 0)

    def loss(c):
        cc, _, _ = sh_colors(c, dirs, degree=1, base=base)
        return float(np.sum(w * cc.astype(np.float64)))

    h = 1e-3
    for i in range(n):
        for c in range(3):
            raw = base[i, c] + float(Y[i] @ coeffs[i, :4, c])
            if abs(raw) < 0.05:  # the clamp's kink
                continue
            j = int(rng.integers(4))
            e = np.zeros_like(coeffs)
            e[i, j, c] = h
            fd = (loss(coeffs + e) - loss(coeffs - e)) / (2 * h)
            assert g[i, j, c] == pytest.approx(fd, rel=2e-3, abs=2e-4)


def test_ssim_equals_skimage_away_from_the_border():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(1)
    y = rng.random((40, 48))
    x = np.clip(y + rng.normal(0, 0.1, y.shape), 0, 1)
    _, ref = structural_similarity(
        x, y, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True
    )
    mine = ssim_map(x, y)
    np.testing.assert_allclose(mine[5:-5, 5:-5], ref[5:-5, 5:-5], atol=1e-10)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_ssim_gradient_equals_finite_differences(seed):
    rng = np.random.default_rng(seed)
    y = rng.random((16, 18, 3))
    x = np.clip(y + rng.normal(0, 0.2, y.shape), 0, 1)
    s, g = ssim_and_grad(x, y)
    assert s == pytest.approx(float(ssim_map(x, y).mean()), abs=1e-12)
    h = 1e-5
    for _ in range(8):
        idx = tuple(int(rng.integers(k)) for k in x.shape)
        e = np.zeros_like(x)
        e[idx] = h
        fd = (ssim_map(x + e, y).mean() - ssim_map(x - e, y).mean()) / (2 * h)
        assert g[idx] == pytest.approx(fd, rel=1e-3, abs=1e-7)


def test_adam_equals_a_hand_computed_step():
    p = {"a": np.array([1.0, -2.0], np.float32)}
    g = {"a": np.array([0.5, -0.25], np.float32)}
    opt = Adam(p, eps=1e-8)
    opt.step(p, g, {"a": 0.1})
    # first step: m̂ = g, v̂ = g², so the update is lr·g/(|g| + ε) = ±lr
    np.testing.assert_allclose(p["a"], [0.9, -1.9], rtol=1e-6)
    opt.step(p, g, {"a": 0.1})
    m = 0.9 * 0.1 * g["a"] + 0.1 * g["a"]
    v = 0.999 * 0.001 * g["a"] ** 2 + 0.001 * g["a"] ** 2
    upd = 0.1 * (m / (1 - 0.9**2)) / (np.sqrt(v / (1 - 0.999**2)) + 1e-8)
    np.testing.assert_allclose(p["a"], np.array([0.9, -1.9]) - upd, rtol=1e-5)


def test_adam_per_coefficient_rates_and_inactive_columns():
    sh = np.zeros((2, 3, 3), np.float32)
    p = {"sh": sh}
    g = {"sh": np.ones_like(sh)}
    opt = Adam(p, eps=1e-8)
    lr = np.array([[0.1], [0.01], [0.001]], np.float32)  # per coefficient, broadcast over RGB
    opt.step(p, g, {"sh": lr}, active_cols={"sh": 6})  # the first two coefficients only
    np.testing.assert_allclose(p["sh"][:, 0], -0.1, rtol=1e-5)
    np.testing.assert_allclose(p["sh"][:, 1], -0.01, rtol=1e-5)
    assert np.all(p["sh"][:, 2] == 0) and np.all(opt.m["sh"][:, 2] == 0)


def test_exp_decay_ends():
    assert exp_decay(0, 10, start=1.0, final=0.01) == pytest.approx(1.0)
    assert exp_decay(5, 10, start=1.0, final=0.01) == pytest.approx(0.1)
    assert exp_decay(10, 10, start=1.0, final=0.01) == pytest.approx(0.01)


def test_quaternions_from_normals_give_the_normals():
    rng = np.random.default_rng(2)
    n = np.concatenate([_unit(rng, 50), [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]])
    q = quats_from_normals(n)
    np.testing.assert_allclose(normals_of(q), n, atol=1e-6)
    R = quat_to_rotmat(q)
    np.testing.assert_allclose(np.einsum("nij,nik->njk", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)


def _params(rng, n):
    return start_params(
        rng.standard_normal((n, 3)), _unit(rng, n), rng.uniform(0.01, 0.2, n), rng.standard_normal((n, 3)), sh_degree=1
    )


def test_densify_and_prune_invariants():
    rng = np.random.default_rng(3)
    p = _params(rng, 40)
    p["opacity_logits"][:5] = -10.0  # transparent: pruned
    opt = Adam(p)
    opt.step(p, {k: np.ones_like(v) for k, v in p.items()}, dict.fromkeys(p, 0.0))
    stats = GradStats(40)
    g = np.zeros(40)
    g[10:20] = 1.0  # hot
    stats.add(g, np.ones(40, bool))
    scale = np.exp(p["log_scales"]).max(axis=1)
    limit = float(np.median(scale))
    n_small = int(np.sum(scale[10:20] <= limit))
    before = {k: v.copy() for k, v in p.items()}
    out, res = densify_and_prune(
        p,
        opt,
        stats,
        grad_threshold=0.5,
        scale_limit_m=limit,
        prune_opacity=0.005,
        prune_scale_m=10.0,
        max_surfels=1000,
        rng=np.random.default_rng(0),
    )
    assert res.n_cloned == n_small and res.n_split == 10 - n_small and res.n_pruned == 5
    assert res.n_after == 40 - 5 + n_small + res.n_split * (2 - 1)
    assert all(len(v) == res.n_after for v in out.values())
    assert all(len(v) == res.n_after for v in opt.m.values())
    # the untouched surfels keep their parameters (and order), in front
    keep = [i for i in range(40) if i >= 5 and not (10 <= i < 20 and scale[i] > limit)]
    np.testing.assert_array_equal(out["means"][: len(keep)], before["means"][keep])
    # split copies are 1/1.6 the size and lie on their parent's tangent plane
    split = [i for i in range(10, 20) if scale[i] > limit]
    copies = out["log_scales"][-2 * len(split) :]
    np.testing.assert_allclose(copies[: len(split)], before["log_scales"][split] - np.log(1.6), atol=1e-6)
    nrm = normals_of(before["quats"][split])
    off = out["means"][-len(split) :] - before["means"][split]
    np.testing.assert_allclose(np.sum(off * nrm, axis=1), 0.0, atol=1e-5)
    # new rows start with zero moments
    assert np.all(opt.m["means"][len(keep) :] == 0)
    assert np.all(np.isfinite(out["means"]))


def test_densify_respects_max_surfels():
    rng = np.random.default_rng(4)
    p = _params(rng, 30)
    opt = Adam(p)
    stats = GradStats(30)
    stats.add(np.ones(30), np.ones(30, bool))
    out, res = densify_and_prune(
        p,
        opt,
        stats,
        grad_threshold=0.5,
        scale_limit_m=10.0,
        prune_opacity=0.0,
        prune_scale_m=10.0,
        max_surfels=34,
        rng=np.random.default_rng(0),
    )
    assert res.n_after == 34 and res.n_cloned == 4


def test_splat_ply_round_trip(tmp_path):
    from plyfile import PlyData

    rng = np.random.default_rng(5)
    p = start_params(
        rng.standard_normal((7, 3)), _unit(rng, 7), np.full(7, 0.1), rng.standard_normal((7, 3)), sh_degree=3
    )
    p["sh"] = rng.standard_normal(p["sh"].shape).astype(np.float32)
    write_splat_ply(tmp_path / "s.ply", p)
    names = PlyData.read(str(tmp_path / "s.ply"))["vertex"].data.dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    assert sum(n.startswith("f_rest_") for n in names) == 45 and "scale_1" in names and "scale_2" not in names
    back = read_splat_ply(tmp_path / "s.ply")
    for k in p:
        np.testing.assert_array_equal(back[k], p[k])


@pytest.mark.parametrize(
    "kw",
    [
        {"mode": "fastest"},
        {"iterations": 0},
        {"iterations": -5},
        {"time_budget_s": 0.0},
        {"time_budget_s": -1.0},
        {"sh_degree": 4},
        {"train_scale": 0.0},
        {"start_surface": "middle"},
        {"color_loss": "l3"},
    ],
)
def test_config_bad_values_are_named_errors(kw):
    with pytest.raises(ConfigError, match="optimize"):
        FitConfig(**kw)


def test_presets():
    assert fit_preset("none").iterations == 0
    assert fit_preset("full").iterations > fit_preset("fast").iterations
    assert fit_preset("fast", seed=3).seed == 3
    with pytest.raises(ConfigError, match="fastest"):
        fit_preset("fastest")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="fits nothing"):
        fit_preset("none", iterations=10)


def _shortened_oracle(mode, n):
    """The schedule ``build --optimize-iterations N`` fitted with before #34 (written
    out in reconstruct/steps/optimize.fit_config: the preset's fields, then each window
    clipped to the N steps)."""
    fc = replace(fit_preset(mode), iterations=n)
    return replace(
        fc,
        densify_from=min(fc.densify_from, n // 4),
        densify_until=min(fc.densify_until, (3 * n) // 4),
        densify_every=max(1, min(fc.densify_every, n // 4)),
        sh_degree_every=min(fc.sh_degree_every, max(1, n // (fc.sh_degree + 1))),
        checkpoint_every=min(fc.checkpoint_every, max(1, n // 2)) if fc.checkpoint_every else 0,
    )


@settings(max_examples=60, deadline=None)
@given(mode=st.sampled_from(["fast", "full"]), n=st.integers(1, 20_000))
def test_preset_iterations_keep_the_schedules_inside_them(mode, n):
    from opacityhull.reconstruct.buildconfig import BuildConfig
    from opacityhull.reconstruct.steps.optimize import fit_config

    fc = fit_preset(mode, iterations=n)
    assert fc == _shortened_oracle(mode, n)
    assert fit_config(BuildConfig(optimize=mode, optimize_iterations=n)) == fc  # what build fits
    assert fc.iterations == n and fc.densify_until <= max(3 * n // 4, 0) and fc.densify_every >= 1
    # an explicit field still wins over the shortened schedule
    assert fit_preset(mode, iterations=n, densify_every=7).densify_every == 7


def test_build_without_iterations_fits_the_preset():
    from opacityhull.reconstruct.buildconfig import BuildConfig
    from opacityhull.reconstruct.steps.optimize import fit_config

    assert fit_config(BuildConfig(optimize="full")) == fit_preset("full")
    assert fit_config(BuildConfig(optimize="none", optimize_iterations=5)) == fit_preset("none")
    assert fit_preset("fast", iterations=900) == fit_preset("fast")  # the preset's own length


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), color_loss=st.sampled_from(["l1", "l2"]))
def test_step_loss_gradient_equals_finite_differences(seed, color_loss):
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 1, (12, 13, 3))
    tgt = rng.uniform(0, 1, (12, 13, 3))
    a, m = rng.uniform(0, 1, (12, 13)), rng.uniform(0, 1, (12, 13))

    def loss(i, al):
        return step_loss(i, al, tgt, m, ssim_weight=0.2, alpha_weight=0.5, color_loss=color_loss)

    _, g_img, g_a = loss(img, a)
    h = 1e-6
    for _ in range(6):  # |x| is smooth away from 0: the random values are almost surely away from it
        y, x, c = rng.integers(12), rng.integers(13), rng.integers(3)
        up, dn = img.copy(), img.copy()
        up[y, x, c] += h
        dn[y, x, c] -= h
        fd = (loss(up, a)[0] - loss(dn, a)[0]) / (2 * h)
        assert g_img[y, x, c] == pytest.approx(fd, rel=1e-3, abs=1e-9)
        up, dn = a.copy(), a.copy()
        up[y, x] += h
        dn[y, x] -= h
        fd = (loss(img, up)[0] - loss(img, dn)[0]) / (2 * h)
        assert g_a[y, x] == pytest.approx(fd, rel=1e-3, abs=1e-9)


def test_position_rate_follows_the_view_count_unless_given():
    """The default position rate is the sparse-view one up to SPARSE_VIEWS training views
    and 3e-3 -> 3e-4 above (the measured table in position_rates); a given rate wins."""
    from opacityhull.optimize.config import SPARSE_VIEWS, FitConfig, position_rates

    cfg = FitConfig()
    assert position_rates(cfg, 12) == pytest.approx((1e-2, 1e-3))
    assert position_rates(cfg, SPARSE_VIEWS) == pytest.approx((1e-2, 1e-3))
    assert position_rates(cfg, SPARSE_VIEWS + 1) == pytest.approx((3e-3, 3e-4))
    assert position_rates(cfg, 90) == pytest.approx((3e-3, 3e-4))
    given = FitConfig(lr_position=5e-3, lr_position_final=2e-4)
    assert position_rates(given, 12) == pytest.approx((5e-3, 2e-4))
    assert position_rates(given, 90) == pytest.approx((5e-3, 2e-4))
    with pytest.raises(ConfigError):
        FitConfig(lr_position=-1.0)
