"""Every fast kernel against its NumPy reference, plus independent checks of the EWA
geometry (Jacobian by finite differences of Camera.project)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from splat_cases import make_cam, random_surfels, setup_fast

from opacityhull.model import Surfels
from opacityhull.render import kernels as K
from opacityhull.render.reference import (
    bilinear_ref,
    rasterize_ref,
    render_image_ref,
    shade_ref,
    splat_setup_ref,
    ulr_weights_ref,
)
from opacityhull.render.renderer import RenderConfig, render_image, surfel_areas
from opacityhull.render.views import prepare_views, scan_order


def test_bilinear_fetch_equals_scipy_map_coordinates():
    rng = np.random.default_rng(0)
    img = rng.random((7, 9, 4)).astype(np.float32)
    pv = prepare_views([make_cam((0, 0.1, 1.0), size=(9, 7))], [img])
    # inside, on texel centres, on the half-pixel border, and beyond it (clamped)
    uv = np.concatenate(
        [
            rng.uniform(-0.5, 8.5, size=(200, 2)) * [1, 6.0 / 8],
            [[0, 0], [8, 6], [-0.5, -0.5], [8.5, 6.5], [3.0, 2.0], [-3, 2], [4, 40]],
        ]
    )
    out = np.empty((len(uv), 4), np.float32)
    K.bilinear_fetch(pv.texels, pv.offsets[0], 9, 7, uv, out)
    np.testing.assert_allclose(out, bilinear_ref(img, uv), atol=1e-6)
    np.testing.assert_allclose(out[-3], img[2, 3], atol=1e-7)  # texel centre = the texel


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    filt=st.sampled_from([0.0, 0.25, 1.0]),
    cutoff=st.floats(1.0, 3.0),
    sigma=st.floats(0.3, 0.8),
    cull=st.booleans(),
)
def test_splat_setup_equals_reference(seed, filt, cutoff, sigma, cull):
    rng = np.random.default_rng(seed)
    surf = random_surfels(rng, 60)
    eye = rng.normal(size=3)
    eye = 0.5 * eye / np.linalg.norm(eye) + [0, 0.1, 0]
    cam = make_cam(eye)
    cfg = RenderConfig(filter=filt, cutoff_sigma=cutoff, sigma_radius=sigma, backface_cull=cull)
    areas = rng.uniform(1e-6, 1e-4, size=len(surf)).astype(np.float32)
    v1, r1 = setup_fast(surf, cam, cfg, areas)
    v2, r2 = splat_setup_ref(
        surf.positions,
        surf.normals,
        surf.radii,
        areas,
        cam,
        sigma_radius=sigma,
        filter_var=filt,
        cutoff=cutoff,
        eps_z=cfg.epsilon_z,
        cull_backfaces=cull,
    )
    np.testing.assert_array_equal(v1, v2)
    # a camera that sees none of the 60 surfels (seed 2770056: all culled) tests nothing more
    assume(v1.any())
    cols = list(range(K.S_RGBA)) + [K.S_AREA]
    np.testing.assert_allclose(r1[v1][:, cols], r2[v2][:, cols], rtol=2e-5, atol=1e-6)


def test_ewa_kernel_matches_finite_difference_jacobian():
    """M = J V Jᵀ + H with J from central differences of Camera.project along two tangent
    vectors — independent of both implementations' analytic derivative."""
    rng = np.random.default_rng(3)
    surf = random_surfels(rng, 40)
    cam = make_cam((0.3, 0.4, 0.5))
    cfg = RenderConfig(filter=0.5, sigma_radius=0.5, backface_cull=False)
    valid, rec = setup_fast(surf, cam, cfg, np.ones(len(surf), np.float32))
    checked = 0
    for i in np.flatnonzero(valid):
        n = surf.normals[i].astype(np.float64)
        a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
        tu = np.cross(n, a)
        tu /= np.linalg.norm(tu)
        tv = np.cross(n, tu)
        h = 1e-6
        p = surf.positions[i].astype(np.float64)
        cols = []
        for t in (tu, tv):
            up, _ = cam.project(np.stack([p + h * t, p - h * t]))
            cols.append((up[0] - up[1]) / (2 * h))
        J = np.stack(cols, axis=1)
        M = (0.5 * surf.radii[i]) ** 2 * J @ J.T + (0.5 + K.M_FLOOR) * np.eye(2)
        Minv = np.linalg.inv(M)
        got = np.array([[rec[i, K.S_A], rec[i, K.S_B]], [rec[i, K.S_B], rec[i, K.S_C]]])
        np.testing.assert_allclose(got, Minv, rtol=1e-4)
        w = abs(np.linalg.det(J)) / (2 * math.pi * math.sqrt(np.linalg.det(M)))
        assert rec[i, K.S_W] == pytest.approx(w, rel=1e-4)
        uv, z = cam.project(p[None])
        assert rec[i, K.S_X] == pytest.approx(uv[0, 0], abs=1e-4)
        assert rec[i, K.S_Z] == pytest.approx(z[0], rel=1e-6)
        checked += 1
    assert checked > 20


def test_depth_gradient_is_the_tangent_plane():
    """Linearised depth at a nearby pixel equals the depth where that pixel's ray meets the
    surfel's tangent plane (to first order)."""
    rng = np.random.default_rng(5)
    surf = random_surfels(rng, 30)
    cam = make_cam((0.2, 0.3, 0.6))
    valid, rec = setup_fast(surf, cam, RenderConfig(), np.ones(len(surf), np.float32))
    for i in np.flatnonzero(valid)[:15]:
        p = surf.positions[i].astype(np.float64)
        n = surf.normals[i].astype(np.float64)
        for du, dv in ((1e-3, 0), (0, 1e-3)):
            uv = np.array([[rec[i, K.S_X] + du, rec[i, K.S_Y] + dv]])
            o, d = cam.pixel_rays(uv)
            t = n @ (p - o) / (n @ d[0])
            z = cam.world_to_cam((o + t * d[0])[None])[0, 2]
            lin = rec[i, K.S_Z] + rec[i, K.S_DZX] * du + rec[i, K.S_DZY] * dv
            assert lin == pytest.approx(z, abs=1e-7)


@pytest.mark.parametrize("band_rows,threads", [(16, 1), (3, 2), (64, 1)])
def test_rasterize_equals_reference(band_rows, threads):
    rng = np.random.default_rng(11)
    surf = random_surfels(rng, 400)
    cam = make_cam((0.1, 0.3, 0.5))
    cfg = RenderConfig(filter=0.5)
    areas = rng.uniform(1e-5, 1e-4, size=len(surf)).astype(np.float32)
    valid, rec = setup_fast(surf, cam, cfg, areas)
    rec[:, K.S_RGBA : K.S_RGBA + 4] = rng.random((len(surf), 4))
    draw = np.flatnonzero(valid)
    assert draw.size > 100
    acc, zlim = K.splat_frame(
        rec, draw.astype(np.int64), cam.height, cam.width, cfg.cutoff_sigma, band_rows, threads=threads
    )
    acc_r, zlim_r = rasterize_ref(rec, draw, cam.height, cam.width, cfg.cutoff_sigma)
    np.testing.assert_array_equal(np.isfinite(zlim), np.isfinite(zlim_r))
    np.testing.assert_allclose(zlim[np.isfinite(zlim)], zlim_r[np.isfinite(zlim_r)], rtol=1e-6)
    scale = np.abs(acc_r).max(axis=(0, 1))
    np.testing.assert_allclose(acc / scale, acc_r / scale, atol=2e-5)
    # the ε-z-buffer really discarded something: surfels overlap in depth here
    acc_noz, _ = rasterize_ref(rec, draw[:1], cam.height, cam.width, cfg.cutoff_sigma)
    assert (acc[..., 4] > 0).sum() > (acc_noz[..., 4] > 0).sum()


def test_eps_z_buffer_keeps_front_surface_and_discards_back():
    """Two parallel sheets 5 cm apart, different colours: only the front one is seen; with
    a huge ε both would blend."""
    g = np.linspace(-0.05, 0.05, 25)
    X, Y = np.meshgrid(g, g)
    front = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    back = front + [0, 0, -0.05]
    pos = np.concatenate([back, front])  # back first: order must not matter
    n = np.tile([0.0, 0, 1], (len(pos), 1))
    rad = np.full(len(pos), 0.004)
    surf = Surfels.from_bool(pos, n, rad, np.ones((len(pos), 1), bool))
    cam = make_cam((0.0, 0.0, 0.4), target=(0, 0, 0), size=(32, 32))
    for eps, expect_red in ((2.0, 1.0), (1e4, 0.5)):
        cfg = RenderConfig(epsilon_z=eps)
        valid, rec = setup_fast(surf, cam, cfg, surfel_areas(surf))
        rgba = np.zeros((len(pos), 4), np.float32)
        rgba[len(back) :] = [1, 0, 0, 1]  # front red
        rgba[: len(back)] = [0, 0, 1, 1]  # back blue
        rec[:, K.S_RGBA : K.S_RGBA + 4] = rgba
        acc, _ = K.splat_frame(rec, np.flatnonzero(valid).astype(np.int64), 32, 32, cfg.cutoff_sigma, 8)
        centre = acc[16, 16]
        assert centre[0] / centre[4] == pytest.approx(expect_red, abs=0.15)


def test_shading_equals_reference(sphere_small, sphere_views_premul):
    m = sphere_small
    pv = prepare_views(m.cameras, sphere_views_premul)
    C = np.array([0.1, 0.35, 0.45])
    N = len(m.surfels)
    o, rho = K.bounding_sphere(m.surfels.positions)
    order, s_lb = scan_order(pv.centres, C, o, rho)
    out = np.zeros((N, 4), np.float32)
    ok = np.empty(N, bool)
    surfels = (m.surfels.positions, m.surfels.visibility, np.ones(N, bool))  # every surfel drawable
    views = (np.ones(pv.n_views, np.uint8), C, pv.centres, pv.cams, pv.sizes)  # every view allowed
    K.ulr_shade(K.UlrHead(*surfels, *views), pv.offsets, pv.texels, order, s_lb, pv.tie_rank, 4, out, 0, ok, 0, N)
    Wd = ulr_weights_ref(m.surfels.positions, m.surfels.visible_bool(), m.cameras, C, k=4)
    ref = shade_ref(m.surfels.positions, Wd, m.cameras, sphere_views_premul)
    np.testing.assert_array_equal(ok, Wd.sum(axis=1) > 0)
    np.testing.assert_allclose(out[ok], ref[ok], atol=2e-6)


@pytest.mark.parametrize(
    "cfg",
    [
        RenderConfig(shading="surfel"),
        RenderConfig(shading="surfel", k=2, filter=1.0, cutoff_sigma=2.5),
        RenderConfig(shading="surfel", k=6, edge_coverage=False, epsilon_z=4.0),
    ],
)
def test_render_image_equals_reference(sphere_small, sphere_views_premul, cfg):
    m = sphere_small
    cam = make_cam((0.25, 0.3, 0.4), size=(40, 30))
    fast = render_image(m.surfels, m.cameras, sphere_views_premul, cam, config=cfg)
    rgba, depth, weight = render_image_ref(m.surfels, m.cameras, sphere_views_premul, cam, config=cfg)
    assert (fast.alpha > 0).sum() > 200
    np.testing.assert_allclose(fast.rgba, rgba, atol=2e-5)
    np.testing.assert_array_equal(np.isfinite(fast.depth), np.isfinite(depth))
    fin = np.isfinite(depth)
    np.testing.assert_allclose(fast.depth[fin], depth[fin], rtol=1e-5)
    np.testing.assert_allclose(fast.weight / weight.max(), weight / weight.max(), atol=1e-5)


@pytest.mark.parametrize(
    "cfg",
    [
        # the NumPy reference blends the views as they project (flow alignment has its
        # own tests, tests/render/test_floating.py)
        RenderConfig(shading="pixel", align="none"),
        RenderConfig(shading="pixel", align="none", k=2, min_view_cos=0.3, min_coverage=0.5),
        RenderConfig(shading="pixel", align="none", k=6, edge_coverage=False, coverage_clip=False, close_holes=False),
    ],
)
def test_render_image_pixel_shading_equals_reference(sphere_small, sphere_views_premul, cfg):
    """Per-pixel shading end to end. The kernels' exp table and np.exp differ by ~1e-6,
    which can swap the winning surfel where two fragments weigh the same: the image must
    agree wherever the winner is clear (and those pixels are nearly all of them)."""
    m = sphere_small
    cam = make_cam((0.25, 0.3, 0.4), size=(40, 30))
    fast = render_image(m.surfels, m.cameras, sphere_views_premul, cam, config=cfg)
    rgba, depth, weight, clear = render_image_ref(
        m.surfels, m.cameras, sphere_views_premul, cam, config=cfg, return_margin=True
    )
    drawn = rgba[..., 3] > 0
    assert drawn.sum() > 200 and (clear & drawn).sum() > 0.97 * drawn.sum()
    # pinhole filling looks at neighbours: compare where the 3x3 neighbourhood is clear too
    from scipy.ndimage import binary_erosion

    ok = binary_erosion(clear | ~(weight > 0), iterations=1, border_value=1)
    np.testing.assert_allclose(fast.rgba[ok], rgba[ok], atol=2e-5)
    np.testing.assert_array_equal(np.isfinite(fast.depth), np.isfinite(depth))
    fin = np.isfinite(depth)
    np.testing.assert_allclose(fast.depth[fin], depth[fin], rtol=1e-5)
    np.testing.assert_allclose(fast.weight / weight.max(), weight / weight.max(), atol=1e-5)


def test_threads_do_not_change_the_image(sphere_small, sphere_views_premul):
    m = sphere_small
    cam = make_cam((0.25, 0.3, 0.4), size=(40, 30))
    a = render_image(m.surfels, m.cameras, sphere_views_premul, cam, config=RenderConfig(threads=1))
    b = render_image(m.surfels, m.cameras, sphere_views_premul, cam, config=RenderConfig(threads=3, band_rows=2))
    np.testing.assert_array_equal(a.rgba, b.rgba)
    np.testing.assert_array_equal(a.weight, b.weight)


def test_bounding_sphere_ignores_nonfinite():
    P = np.array([[0.0, 0, 0], [1.0, 0, 0], [np.nan, 5, 5], [0.0, 2.0, 0]], np.float32)
    c, r = K.bounding_sphere(P)
    np.testing.assert_allclose(c, [0.5, 1.0, 0.0])
    assert r == pytest.approx(math.hypot(0.5, 1.0))
    c, r = K.bounding_sphere(np.zeros((0, 3), np.float32))
    assert r == 0.0


# --------------------------------------------------------------------------- rasteriser helpers


@pytest.mark.parametrize("height,band_h", [(1, 1), (30, 7), (32, 8), (24, 64)])
def test_band_rows_cover_every_row_once(height, band_h):
    counts = np.zeros(-(-height // band_h) + 1, np.int64)
    nb, c2, scale = K._band_constants(counts, 2.0, K.exp_table(2.0))
    assert nb == counts.shape[0] - 1 and c2 == 4.0 and scale == K.EXP_LUT_SIZE / 4.0
    rows = []
    for b in range(nb):
        ylo, yhi = K._band_rows(b, band_h, height)
        rows += range(ylo, yhi + 1)
    assert rows == list(range(height))


@settings(max_examples=50, deadline=None)
@given(
    coef=st.lists(st.floats(-50.0, 50.0), min_size=7, max_size=7),
    dx=st.integers(-20, 20),
    y=st.integers(0, 40),
    y0=st.floats(-5.0, 45.0),
)
def test_fragment_is_the_conic_and_the_clamped_tangent_plane(coef, dx, y, y0):
    """The footprint both passes test, to the bit: q = A dx² + 2B dx dy + C dy² (Horner
    order) and z = clip(z0 + dz/dx·dx + dz/dy·dy, zlo, zhi)."""
    A, B2, C, z0, dzx, dzy, dev = coef
    zlo, zhi = z0 - abs(dev), z0 + abs(dev)
    tt, cdy, zrow = K._row_terms(y, y0, B2, C, z0, dzy)
    q, z = K._fragment(A, tt, cdy, float(dx), zrow, dzx, zlo, zhi)
    dy = y - y0
    assert q == (A * dx + B2 * dy) * dx + C * dy * dy
    assert z == min(max(z0 + dzy * dy + dzx * dx, zlo), zhi)
    q2, z32, _ = K._ewa_weight(A, tt, cdy, float(dx), zrow, dzx, zlo, zhi, 9.0, K.exp_table(3.0), 1.0, np.float32(1.0))
    assert q2 == q and z32 == np.float32(z)


def test_splat_geometry_rows_are_the_box_clipped_to_the_band():
    rec = np.zeros((1, K.SPLAT_FIELDS), np.float32)
    rec[0, [K.S_BX0, K.S_BX1, K.S_BY0, K.S_BY1]] = [3, 9, 5, 12]
    for ylo, yhi, want in ((0, 7, (5, 7)), (8, 15, (8, 12)), (6, 10, (6, 10)), (13, 20, (13, 12))):
        g = K._splat_geometry(rec, 0, ylo, yhi)
        assert g[10:12] == (3, 9) and g[12:] == want


def test_filled_buffers_with_and_without_scratch():
    a = K.filled(None, "x", (3, 4), np.float32, np.inf)
    assert a.dtype == np.float32 and a.shape == (3, 4) and np.all(np.isinf(a))
    s = K.Scratch()
    b = K.filled(s, "x", (3, 4), np.int64, -1)
    b[:] = 7
    c = K.filled(s, "x", (2, 2), np.int64, -1)  # the same buffer, refilled
    assert np.shares_memory(b, c) and np.all(c == -1)


def test_band_threads_are_bit_for_bit_the_serial_frame():
    from opacityhull.render import deferred as D

    rng = np.random.default_rng(3)
    surf = random_surfels(rng, 300)
    cam = make_cam((0.1, 0.3, 0.5))
    cfg = RenderConfig(filter=0.5)
    valid, rec = setup_fast(surf, cam, cfg, rng.uniform(1e-5, 1e-4, size=len(surf)).astype(np.float32))
    rec[:, K.S_RGBA : K.S_RGBA + 4] = rng.random((len(surf), 4))
    draw = np.flatnonzero(valid).astype(np.int64)
    args = (rec, draw, cam.height, cam.width, cfg.cutoff_sigma, 4)
    for frame in (K.splat_frame, D.geometry_frame):
        serial = frame(*args, threads=1)
        for got in (frame(*args, threads=3), frame(*args, threads=3, scratch=K.Scratch())):
            for x, y in zip(serial, got, strict=True):
                np.testing.assert_array_equal(x, y)
