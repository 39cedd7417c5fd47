"""Statistical point geometry (seed 000): node statistics against a slow NumPy reference,
the paper's degenerate clusters, codebook and record round trips, and the anisotropic
node splats against the isotropic ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.model import Surfels
from opacityhull.render.lod import build_point_tree, select_cut
from opacityhull.render.spg import (
    LEAF_DTYPE,
    NODE_DTYPE,
    fit_codebook,
    node_statistics,
    oct_decode,
    oct_encode,
    pack_nodes,
    radius_tensors,
    statistical_cut,
    unpack_nodes,
)


def _subtree_leaves(tree):
    """Per node, the list of leaf node ids below it (slow, obvious)."""
    out = [[] for _ in range(len(tree))]
    for leaf in np.flatnonzero(tree.is_leaf):
        n = leaf
        while n >= 0:
            out[n].append(leaf)
            n = tree.parent[n]
    return out


def _reference(tree):
    """(mean, covariance, mean normal, normal-spread covariance in any tangent basis) per node."""
    P = tree.positions.astype(np.float64)
    N = tree.normals.astype(np.float64)
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)  # (only the leaves' are used)
    a_disc = tree.areas.astype(np.float64)
    pos_a = a_disc[tree.is_leaf & (a_disc > 0)]
    w_all = np.where(a_disc > 0, a_disc, np.median(pos_a) if pos_a.size else 1.0)
    res = []
    for leaves in _subtree_leaves(tree):
        lv = np.array(leaves)
        w = w_all[lv]
        mu = (w[:, None] * P[lv]).sum(0) / w.sum()
        C = np.zeros((3, 3))
        for i, wi in zip(lv, w, strict=True):
            d = P[i] - mu
            C += wi * (np.outer(d, d) + a_disc[i] / (4 * np.pi) * (np.eye(3) - np.outer(N[i], N[i])))
        C /= w.sum()
        m = (w[:, None] * N[lv]).sum(0)
        m = m / np.linalg.norm(m) if np.linalg.norm(m) > 1e-12 else None
        res.append((mu, C, m, lv, w))
    return res


def _log_map_cov(normals, w, m):
    """2x2 covariance of the normals' azimuthal-equidistant coordinates at pole m, in the
    basis (e1, e2) built by Gram-Schmidt from the coordinate axes (independent of the code)."""
    e = np.eye(3)[np.argmin(np.abs(m))]
    e1 = e - (e @ m) * m
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    uv = []
    for n in normals:
        theta = np.arctan2(np.linalg.norm(np.cross(m, n)), n @ m)
        t = n - (n @ m) * m
        t = t / np.linalg.norm(t) if np.linalg.norm(t) > 1e-15 else np.zeros(3)
        uv.append(theta * np.array([t @ e1, t @ e2]))
    uv = np.array(uv)
    mu = (w[:, None] * uv).sum(0) / w.sum()
    d = uv - mu
    return (w[:, None, None] * np.einsum("ni,nj->nij", d, d)).sum(0) / w.sum(), e1, e2


def _check(tree, stats):
    ref = _reference(tree)
    F = stats.frame_p
    np.testing.assert_allclose(np.einsum("mij,mkj->mik", F, F), np.broadcast_to(np.eye(3), F.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-9)  # right-handed
    assert np.all(np.diff(stats.sigma_p, axis=1) <= 1e-12)  # descending
    Cs = stats.covariance()
    scale = max(float(np.ptp(tree.positions, axis=0).max()), 1e-3)
    for i, (mu, C, m, lv, w) in enumerate(ref):
        np.testing.assert_allclose(stats.mean[i], mu, atol=1e-9 * scale + 1e-12)
        # (the stored σ are floored at 1e-6 of the extent: variances differ by ≤ that²)
        np.testing.assert_allclose(Cs[i], C, atol=1e-9 * scale**2 + 2e-12 * max(scale, 1.0) ** 2)
        if m is None:
            continue
        np.testing.assert_allclose(stats.normal[i], m, atol=1e-9)
        assert F[i, 2] @ m >= -1e-12  # the thin axis on the normals' side
        Cn, e1, e2 = _log_map_cov(tree.normals[lv].astype(np.float64), w, m)
        np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(Cn))[::-1], stats.sigma_n[i] ** 2, atol=1e-10)
        # the stored x axis is the major axis of the spread
        x = stats.frame_n[i, 0]
        xv = np.array([x @ e1, x @ e2])
        assert xv @ Cn @ xv >= stats.sigma_n[i, 0] ** 2 - 1e-10


def _cloud(n, seed, kind):
    rng = np.random.default_rng(seed)
    if kind == "random":
        p = rng.normal(size=(n, 3))
    elif kind == "collinear":
        p = np.outer(rng.normal(size=n), [1.0, 2.0, -0.5])
    elif kind == "coincident":
        p = np.tile(rng.normal(size=3), (n, 1))
    else:  # a plane with a few duplicates
        p = np.c_[rng.normal(size=(n, 2)), np.zeros(n)]
        p[: n // 3] = p[0]
    nrm = rng.normal(size=(n, 3)) * 0.3 + [0.0, 0.0, 1.0]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return Surfels.from_bool(p, nrm, rng.uniform(0.01, 0.05, n), rng.random((n, 9)) < 0.4)


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(1, 60),
    seed=st.integers(0, 10_000),
    kind=st.sampled_from(["random", "collinear", "coincident", "plane"]),
    zero_area=st.booleans(),
)
def test_node_statistics_match_the_numpy_reference(n, seed, kind, zero_area):
    s = _cloud(n, seed, kind)
    areas = np.zeros(n) if zero_area else None
    tree = build_point_tree(s, areas, depth=8)
    _check(tree, node_statistics(tree))


def test_degenerate_clusters_follow_the_paper():
    # collinear points without area: two zero variances; the principal direction is
    # kept and z turned to the mean normal
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    p = np.outer(np.linspace(-1, 1, 9), d)
    nrm = np.tile([0.0, 0.0, 1.0], (9, 1))
    tree = build_point_tree(Surfels.from_bool(p, nrm, np.full(9, 0.01), np.ones((9, 3), bool)), np.zeros(9))
    st_ = node_statistics(tree)
    root = int(np.argmax(tree.r_max))
    assert abs(st_.frame_p[root, 0] @ d) == pytest.approx(1.0, abs=1e-9)
    z = np.array([0.0, 0.0, 1.0]) - d[2] * d
    np.testing.assert_allclose(st_.frame_p[root, 2], z / np.linalg.norm(z), atol=1e-9)
    assert st_.sigma_p[root, 1] == st_.sigma_p[root, 2] > 0  # floored, not zero
    # coincident points without area: three zero variances, z along the normal
    p = np.zeros((5, 3))
    nrm = np.tile([0.6, 0.0, 0.8], (5, 1))
    tree = build_point_tree(Surfels.from_bool(p, nrm, np.full(5, 0.01), np.ones((5, 3), bool)), np.zeros(5))
    st_ = node_statistics(tree)
    np.testing.assert_allclose(st_.frame_p[:, 2], np.broadcast_to(nrm[0], (len(tree), 3)), atol=1e-9)
    np.testing.assert_allclose(st_.sigma_n, 0.0, atol=1e-7)
    # a single surfel with area: its statistics are its own disc
    s = Surfels.from_bool(np.zeros((1, 3)), [[0.0, 1.0, 0.0]], [0.02], np.ones((1, 3), bool))
    tree = build_point_tree(s, np.array([np.pi * 0.02**2]))
    st_ = node_statistics(tree)
    np.testing.assert_allclose(st_.sigma_p[0, :2], 0.01, rtol=1e-6)  # √(a/4π) = r/2 (float32 area)
    np.testing.assert_allclose(st_.frame_p[0, 2], [0.0, 1.0, 0.0], atol=1e-12)
    R = radius_tensors(st_.covariance(), st_.normal, scale=1.0)
    np.testing.assert_allclose(R[0], 0.02**2 * np.array([1, 0, 0, 0, 0, 1]), atol=1e-10)  # r²(I − nnᵀ)


@settings(max_examples=30, deadline=None)
@given(
    v=st.tuples(*[st.floats(-1, 1, allow_nan=False) for _ in range(3)]).filter(lambda t: np.linalg.norm(t) > 1e-3),
    bits=st.sampled_from([8, 12]),
)
def test_octahedral_normals_round_trip(v, bits):
    n = np.asarray(v) / np.linalg.norm(v)
    u, w = oct_encode(n[None], bits)
    back = oct_decode(u, w, bits)[0]
    # measured over 400 000 random normals: max error 4.2 / 2^bits rad (0.94° at 8 bits, 0.059° at 12)
    assert np.degrees(np.arccos(np.clip(back @ n, -1, 1))) < np.degrees(4.5 / 2**bits)
    np.testing.assert_allclose(np.linalg.norm(back), 1.0, rtol=1e-12)


def test_codebook_round_trips():
    from scipy.cluster.vq import vq

    rng = np.random.default_rng(3)
    few = np.exp(rng.normal(size=(40, 3)))
    cb = fit_codebook(np.repeat(few, 5, axis=0), size=64, floor=1e-9)
    assert len(cb.centres) == 40  # fewer distinct values than centres: exact
    np.testing.assert_allclose(cb.decode(cb.encode(few, floor=1e-9)), few, rtol=1e-6)
    many = np.exp(rng.normal(size=(3000, 2)) * 0.5)
    cb = fit_codebook(many, size=128, floor=1e-9)
    assert len(cb.centres) == 128
    idx = cb.encode(many, floor=1e-9)
    ref, _ = vq(np.log(many), cb.centres.astype(np.float64))  # the nearest centre, brute force
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_allclose(cb.decode(idx), np.exp(cb.centres[ref]), rtol=1e-6)
    # the quantised spreads are close: k-means in log space
    assert np.median(np.abs(np.log(cb.decode(idx) / many))) < 0.1


def test_packed_records_round_trip():
    rng = np.random.default_rng(5)
    n = 3000
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    s = Surfels.from_bool(p, p, np.full(n, 0.05), rng.random((n, 20)) < 0.5)
    tree = build_point_tree(s, depth=12)
    stats = node_statistics(tree)
    pk = pack_nodes(tree, stats, codebook_p=256, codebook_n=256)
    assert NODE_DTYPE.itemsize == 17 and LEAF_DTYPE.itemsize == 8
    assert len(pk.inner) == int((~tree.is_leaf).sum()) and len(pk.leaves) == n
    t2, s2 = unpack_nodes(pk, leaf_positions=tree.positions[pk.leaf_ids])
    np.testing.assert_array_equal(t2.visibility, tree.visibility)  # the dictionary is lossless
    assert t2.visibility.shape[1] == tree.visibility.shape[1]
    # one monotone code for both ends: child r_max == parent r_min exactly, so every
    # threshold still cuts each leaf-to-root path once
    ch = np.flatnonzero(tree.parent >= 0)
    np.testing.assert_array_equal(t2.r_max[ch], t2.r_min[tree.parent[ch]])
    assert np.all(t2.r_min[tree.is_leaf] == 0) and np.isinf(t2.r_max[tree.parent < 0]).all()
    rel = np.abs(t2.r_min[~tree.is_leaf] / tree.r_min[~tree.is_leaf] - 1)
    half_step = 0.5 * np.log(tree.r_min[tree.r_min > 0].max() / tree.r_min[tree.r_min > 0].min()) / 253
    assert rel.max() < np.expm1(half_step) + 1e-5
    inner = ~tree.is_leaf
    step = np.ptp(tree.positions, axis=0).max() / 1023
    assert np.abs(s2.mean[inner] - stats.mean[inner]).max() <= 0.5 * step + 1e-9
    ang = np.degrees(np.arccos(np.clip((s2.normal[inner] * stats.normal[inner]).sum(1), -1, 1)))
    assert ang.max() < 1.0
    lang = np.degrees(np.arccos(np.clip((t2.normals[tree.is_leaf] * tree.normals[tree.is_leaf]).sum(1), -1, 1)))
    assert lang.max() < 0.1
    np.testing.assert_allclose(t2.radii[tree.is_leaf], tree.radii[tree.is_leaf], rtol=1e-5)
    # the ellipse: covariance close in the tangent plane
    big = inner & (stats.sigma_p[:, 1] > 0.05)
    c1, c0 = s2.covariance()[big], stats.covariance()[big]
    assert np.median(np.linalg.norm(c1 - c0, axis=(1, 2)) / np.linalg.norm(c0, axis=(1, 2))) < 0.15


def _psnr(a, b):
    sel = (a.rgba[..., 3] > 0.01) | (b.rgba[..., 3] > 0.01)
    d = np.concatenate(
        [
            (a.rgba[..., :3] * a.rgba[..., 3:] - b.rgba[..., :3] * b.rgba[..., 3:])[sel].ravel(),
            (a.rgba[..., 3] - b.rgba[..., 3])[sel],
        ]
    )
    return float(10 * np.log10(1 / np.mean(d**2)))


def test_statistical_nodes_beat_isotropic_discs_at_a_sixteenth(sphere_stats):
    """Measured (20 000 surfels, 64×48, view 4): N/16 isotropic 31.8 dB, statistical 36.5 dB."""
    from opacityhull.render.config import RenderConfig
    from opacityhull.render.renderer import render_image
    from opacityhull.render.runner import _seed_surfel_areas

    m, tree, stats, pv = sphere_stats
    cams = [v.camera for v in m.views]
    cam = m.views[4].camera
    cfg = RenderConfig(threads=1)
    full = render_image(m.surfels, cams, pv, cam, config=cfg)
    _, mask = select_cut(tree, cam.centre_world, len(m.surfels) // 16)
    idx = np.flatnonzero(mask)
    iso = Surfels(tree.positions[idx], tree.normals[idx], tree.radii[idx], tree.visibility[idx], tree.n_views)
    _seed_surfel_areas(iso, tree.areas[idx])
    p_iso = _psnr(render_image(iso, cams, pv, cam, config=cfg), full)
    s, areas, cov = statistical_cut(tree, stats, mask)
    _seed_surfel_areas(s, areas)
    p_spg = _psnr(render_image(s, cams, pv, cam, config=cfg, splat_cov=cov), full)
    assert p_spg >= p_iso + 1.0, (p_iso, p_spg)
    # a leaf's tensor is its disc: drawing the leaves through the tensors is the model itself
    leaves = tree.is_leaf
    s, areas, cov = statistical_cut(tree, stats, leaves)
    _seed_surfel_areas(s, areas)
    same = render_image(s, cams, pv, cam, config=cfg, splat_cov=cov)
    ref_s = Surfels(s.positions, s.normals, s.radii, s.visibility, s.n_views)
    _seed_surfel_areas(ref_s, areas)
    ref = render_image(ref_s, cams, pv, cam, config=cfg)
    np.testing.assert_allclose(same.rgba, ref.rgba, atol=2e-4)


@pytest.fixture(scope="module")
def sphere_stats():
    from opacityhull.render.renderer import surfel_areas
    from opacityhull.render.synthetic import make_sphere_model
    from opacityhull.render.views import prepare_views

    m = make_sphere_model(20000, width=64, height=48, table_step_deg=45.0)
    tree = build_point_tree(m.surfels, surfel_areas(m.surfels))
    pv = prepare_views([v.camera for v in m.views], m.views_premul())
    return m, tree, node_statistics(tree), pv
