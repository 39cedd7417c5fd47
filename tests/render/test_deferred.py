"""Per-pixel ("deferred") ULR shading: the kernels against their NumPy references, and
the exact-silhouette behaviour on the analytic sphere (exact ground truth)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from splat_cases import make_cam, random_surfels, setup_fast

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.errors import InputError
from opacityhull.model import Surfels
from opacityhull.render import deferred as D
from opacityhull.render.reference import deferred_shade_reference, rasterize_geometry_ref, rasterize_ref
from opacityhull.render.renderer import RenderConfig, _allowed, render_image, surfel_areas
from opacityhull.render.synthetic import make_sphere_model
from opacityhull.render.views import pack_camera, prepare_views


@pytest.fixture(scope="module")
def sphere():
    """8000 surfels, 36 views of 64×48 (12 table angles × 3 elevations)."""
    m = make_sphere_model(8000, width=64, height=48)
    return m, prepare_views(m.cameras, m.views_premul())


def _scene(seed, n_views, size, nan_texels=False):
    rng = np.random.default_rng(seed)
    W, H = size
    cams = []
    for _v in range(n_views):
        az = rng.uniform(0, 2 * math.pi)
        el = rng.uniform(-0.6, 0.9)
        d = rng.uniform(0.4, 0.7)
        eye = (d * math.cos(el) * math.sin(az), 0.1 + d * math.sin(el), d * math.cos(el) * math.cos(az))
        cams.append(make_cam(eye, size=(int(rng.integers(12, 24)), int(rng.integers(10, 20)))))
    imgs = []
    for c in cams:
        img = rng.random((c.height, c.width, 4)).astype(np.float32)
        img[..., :3] *= img[..., 3:4]
        if nan_texels:
            img[rng.random(img.shape[:2]) < 0.1] = np.nan
        imgs.append(img)
    frame = make_cam((0.3, 0.25, 0.5), size=size)
    depth = rng.uniform(0.4, 0.75, size=(H, W)).astype(np.float32)
    depth[rng.random((H, W)) < 0.1] = np.inf
    coverage = rng.random((H, W)).astype(np.float32)
    N = 30
    winner = rng.integers(-1, N, size=(H, W)).astype(np.int64)
    vis = rng.random((N, n_views)) < 0.6
    vis[: N // 5] = False  # surfels no view sees (the fallback's case)
    return cams, imgs, frame, depth, coverage, winner, vis


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_views=st.integers(1, 11),
    k=st.integers(1, 6),
    min_cov=st.sampled_from([0.0, 0.5, 0.9]),
    excl=st.booleans(),
    nan_texels=st.booleans(),
    min_view_cos=st.sampled_from([-1.0, 0.0, 0.3]),
    fallback=st.booleans(),
)
def test_deferred_shade_equals_reference(seed, n_views, k, min_cov, excl, nan_texels, min_view_cos, fallback):
    cams, imgs, frame, depth, coverage, winner, vis = _scene(seed, n_views, (14, 11), nan_texels)
    normals = np.random.default_rng(seed + 1).normal(size=(vis.shape[0], 3)).astype(np.float32)
    normals[0] = 0.0  # unusable normal: every visible view is kept
    exclude = [0] if excl else []
    pv = prepare_views(cams, imgs)
    packed = np.packbits(vis, axis=1, bitorder="little")
    fast, n = D.deferred_shade(
        depth,
        coverage,
        winner,
        pack_camera(frame),
        frame.centre_world,
        packed,
        normals,
        pv,
        _allowed(n_views, exclude),
        k=k,
        min_coverage=min_cov,
        min_view_cos=min_view_cos,
        fallback=fallback,
        threads=2,
    )
    ref = deferred_shade_reference(
        depth,
        coverage,
        winner,
        frame,
        vis,
        cams,
        imgs,
        normals=normals,
        k=k,
        exclude_views=exclude,
        min_coverage=min_cov,
        min_view_cos=min_view_cos,
        fallback=fallback,
    )
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast, ref, atol=2e-5)
    assert n >= int((np.abs(ref).sum(axis=2) > 0).sum())
    # nothing outside the shaded set
    assert not np.any(fast[(coverage < np.float32(min_cov)) | (winner < 0) | ~np.isfinite(depth)])


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), band_rows=st.sampled_from([1, 4, 16]), threads=st.sampled_from([1, 2]))
def test_rasterize_geometry_equals_reference(seed, band_rows, threads):
    rng = np.random.default_rng(seed)
    s = random_surfels(rng, 60)
    cam = make_cam((0.2, 0.3, 0.45), size=(32, 24))
    cfg = RenderConfig()
    areas = surfel_areas(s)
    valid, rec = setup_fast(s, cam, cfg, areas)
    draw = np.flatnonzero(valid).astype(np.int64)
    geo, winner = D.geometry_frame(rec, draw, cam.height, cam.width, cfg.cutoff_sigma, band_rows, threads=threads)
    geo_r, win_r, best, second = rasterize_geometry_ref(rec, draw, cam.height, cam.width, cfg.cutoff_sigma)
    np.testing.assert_allclose(geo, geo_r, rtol=2e-5, atol=1e-7)
    # the colour rasteriser's Σw channels agree too (same fragments and depth test)
    acc, _ = rasterize_ref(rec, draw, cam.height, cam.width, cfg.cutoff_sigma)
    np.testing.assert_allclose(geo[..., 0], acc[..., 4], rtol=2e-5, atol=1e-7)
    clear = best > second * (1 + 1e-4)  # the LUT exp differs from np.exp by ~1e-6
    np.testing.assert_array_equal(winner[clear], win_r[clear])
    assert np.array_equal(winner >= 0, win_r >= 0)


def _render(m, pv, cam, *, exclude=(), **cfg):
    return render_image(
        m.surfels, m.cameras, pv, cam, config=RenderConfig(shading="pixel", **cfg), exclude_views=exclude
    )


def test_captured_view_reproduces_the_photograph_exactly(sphere):
    """Without the coverage clip, a captured camera (one-hot on its own view) gives back
    its photograph, fractional silhouette pixels included, and draws nothing outside."""
    m, pv = sphere
    for i in (1, 4, 20):
        res = _render(m, pv, m.cameras[i], coverage_clip=False)
        photo = m.view_rgba[i]
        true = photo[..., 3] > 0
        pp = photo.copy()
        pp[..., :3] *= pp[..., 3:4]
        mse = float(np.mean((res.premul[true] - pp[true]) ** 2))
        assert mse == 0 or 10 * math.log10(1 / mse) > 40
        opaque = photo[..., 3] >= 0.999
        assert res.alpha[opaque].min() >= 0.999
        a, b = photo[..., 3] > 0.5, res.alpha > 0.5
        assert (a & b).sum() / (a | b).sum() >= 0.99
        # nothing outside the true silhouette dilated by 1 px
        assert not np.any(res.alpha[~ndimage.binary_dilation(true, iterations=1)] > 0)
        assert res.stats["shading"] == "pixel" and res.stats["pixels_shaded"] > 0


def test_captured_view_with_the_default_coverage_clip(sphere):
    """The default clips α to the hull's coverage: the opaque interior is still the
    photograph, α only drops at the (analytic) hull's own antialiased edge."""
    m, pv = sphere
    for i in (1, 4, 20):
        res = _render(m, pv, m.cameras[i])
        photo = m.view_rgba[i]
        opaque = photo[..., 3] >= 0.999
        pp = photo.copy()
        pp[..., :3] *= pp[..., 3:4]
        mse = float(np.mean((res.premul[opaque] - pp[opaque]) ** 2))
        assert mse == 0 or 10 * math.log10(1 / mse) > 40
        assert res.alpha[opaque].min() >= 0.999
        a, b = photo[..., 3] > 0.5, res.alpha > 0.5
        assert (a & b).sum() / (a | b).sum() >= 0.98
        assert np.all(res.alpha <= np.maximum(photo[..., 3], 0) + 1e-6)  # the clip only lowers α
        assert not np.any(res.alpha[~ndimage.binary_dilation(photo[..., 3] > 0, iterations=1)] > 0)


def test_grazing_views_are_left_out_on_the_sphere(sphere):
    """Leave-one-out on the analytic sphere: dropping views that see the surface at a
    grazing angle (their silhouette) brings the interior α of novel views to ~1 and
    improves PSNR (measured 24.3 → 28.0 dB over every 2nd view at 0.3)."""
    m, pv = sphere
    out = {}
    for mvc in (-1.0, 0.3):
        errs, alphas = [], []
        for i in (4, 10, 22):
            photo = m.view_rgba[i]
            opaque = ndimage.binary_erosion(photo[..., 3] >= 0.999, iterations=2)
            res = _render(m, pv, m.cameras[i], exclude=[i], min_view_cos=mvc)
            pp = photo.copy()
            pp[..., :3] *= pp[..., 3:4]
            errs.append(float(np.mean((res.premul[opaque] - pp[opaque]) ** 2)))
            alphas.append(float(res.alpha[opaque].mean()))
        out[mvc] = (np.mean(errs), np.mean(alphas))
    assert out[0.3][1] >= 0.99 > out[-1.0][1]
    assert out[0.3][0] < 0.7 * out[-1.0][0]


def test_close_gbuffer_fills_pinholes_only():
    cov = np.zeros((12, 12), np.float32)
    cov[2:10, 2:10] = 1.0
    cov[5, 5] = 0.0  # a pinhole without a fragment
    cov[6, 7] = 0.3  # a thin spot
    winner = np.where(cov > 0, np.arange(144).reshape(12, 12), -1).astype(np.int64)
    depth = np.where(cov > 0, 1.0 + np.arange(144).reshape(12, 12) / 1000, np.inf).astype(np.float32)
    wsum = cov.copy()
    wsum[4, 5] = 2.0  # the heaviest neighbour of the pinhole
    d2, c2, w2 = D.close_gbuffer(depth, wsum, cov, winner)
    assert c2[5, 5] == 1.0 and c2[6, 7] == 1.0
    assert w2[5, 5] == winner[4, 5] and d2[5, 5] == depth[4, 5]
    outside = np.ones_like(cov, bool)
    outside[2:10, 2:10] = False
    assert not np.any(c2[outside]) and np.all(w2[outside] == -1)  # the square did not grow
    np.testing.assert_array_equal(w2[cov > 0], winner[cov > 0])


def test_one_hot_when_the_camera_coincides_with_a_captured_one(sphere):
    m, pv = sphere
    i = 7
    res = _render(m, pv, m.cameras[i])
    # excluding every other view changes nothing: the coinciding view had all the weight
    only = _render(m, pv, m.cameras[i], exclude=[v for v in range(pv.n_views) if v != i])
    np.testing.assert_array_equal(res.rgba, only.rgba)


def test_pixel_mode_is_sharper_than_surfel_density_allows():
    # few, large surfels: per-surfel shading blurs the texture, per-pixel shading does not
    m = make_sphere_model(1500, width=64, height=48, texture_freq=3.0, specular=0.0)
    pv = prepare_views(m.cameras, m.views_premul())
    i = 4
    photo = m.view_rgba[i]
    inner = ndimage.binary_erosion(photo[..., 3] >= 0.999, iterations=2)
    pp = photo.copy()
    pp[..., :3] *= pp[..., 3:4]
    err = {}
    for sh in ("surfel", "pixel"):
        r = render_image(m.surfels, m.cameras, pv, m.cameras[i], config=RenderConfig(shading=sh))
        err[sh] = float(np.mean((r.premul[inner] - pp[inner]) ** 2))
    assert err["pixel"] < 0.1 * err["surfel"]


def test_no_visible_view_is_not_drawn(sphere):
    m, pv = sphere
    res = _render(m, pv, m.cameras[3], exclude=list(range(pv.n_views)))
    assert not np.any(res.rgba) and res.stats["pixels_shaded"] == 0
    # surfels nobody sees are geometry; without the fallback (the default) they are not drawn
    blind = Surfels(
        m.surfels.positions, m.surfels.normals, m.surfels.radii, np.zeros_like(m.surfels.visibility), m.surfels.n_views
    )
    res = render_image(blind, m.cameras, pv, m.cameras[3], config=RenderConfig(shading="pixel", fallback_views=False))
    assert not np.any(res.rgba) and np.isfinite(res.depth).any()
    # with it, the views in front of each tangent plane shade them (the sphere is convex:
    # in front = visible, so this is the same image as with the true visibility)
    fb = render_image(blind, m.cameras, pv, m.cameras[3], config=RenderConfig(shading="pixel", fallback_views=True))
    true = render_image(m.surfels, m.cameras, pv, m.cameras[3], config=RenderConfig(shading="pixel"))
    a, b = fb.alpha > 0.5, true.alpha > 0.5
    assert (a & b).sum() / (a | b).sum() > 0.99


def test_nan_texels_stay_finite(sphere):
    m, _ = sphere
    imgs = [a.copy() for a in m.views_premul()]
    for a in imgs:
        a[::3, ::2] = np.nan
        a[1::5, ::3] = np.inf
    pv = prepare_views(m.cameras, imgs)
    cam = m.cameras[5].with_pose(look_at_world_from_cam((0.1, 0.3, 0.45), (0.0, 0.1, 0.0)))
    res = _render(m, pv, cam)
    assert np.all(np.isfinite(res.rgba)) and res.alpha.max() > 0.5


def test_novel_view_close_to_ground_truth_and_within_the_silhouette(sphere):
    m, pv = sphere
    cam = m.cameras[4].with_pose(look_at_world_from_cam((0.12, 0.32, 0.42), m.scene.centre))
    truth = m.scene.render(cam)
    res = _render(m, pv, cam)
    a, b = truth[..., 3] > 0.5, res.alpha > 0.5
    assert (a & b).sum() / (a | b).sum() >= 0.95
    assert not np.any(res.alpha[~ndimage.binary_dilation(truth[..., 3] > 0, iterations=1)] > 1e-3)


def test_distorted_desired_camera_in_pixel_mode(sphere):
    m, pv = sphere
    c = m.cameras[4]
    cam = Camera(
        K=c.K,
        width=c.width,
        height=c.height,
        world_from_cam=c.world_from_cam,
        dist=np.array([-0.15, 0.0, 0.0, 0.0, 0.0]),
    )
    res = _render(m, pv, cam)
    truth = m.scene.render(cam)
    a, b = truth[..., 3] > 0.5, res.alpha > 0.5
    assert (a & b).sum() / (a | b).sum() >= 0.95 and np.all(np.isfinite(res.rgba))


def test_config_rejects_unknown_shading_and_bad_min_coverage():
    with pytest.raises(InputError, match="shading"):
        RenderConfig(shading="vertex")
    with pytest.raises(InputError, match="min_coverage"):
        RenderConfig(min_coverage=1.5)


REAL = Path(__file__).resolve().parents[1] / "data" / "real" / "templeSR"


@pytest.fixture(scope="module")
def temple_model(tmp_path_factory):
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    if not (REAL / "sparse").is_dir():
        pytest.skip(f"{REAL} not vendored")
    tmp = tmp_path_factory.mktemp("temple")
    import_colmap(REAL / "sparse", REAL / "images", tmp / "session", masks_dir=REAL / "masks")
    # pixel against surfel shading of the hull-and-blend model: built without the default fit
    build_model(tmp / "session", tmp / "model", config=BuildConfig(pictures=False, hull_res=192, optimize="none"))
    return tmp / "model"


@pytest.mark.slow
def test_real_temple_pixel_shading_beats_surfel_shading(temple_model):
    """The Middlebury temple ring (16 real photographs, thresholded masks; hull-res 192,
    every 4th view held out of the blend). Measured pixel / surfel: PSNR 18.59 / 18.09
    dB, interior 20.92 / 20.10, SSIM 0.559 / 0.500, coverage IoU 0.921 / 0.906, interior
    α 0.958 / 0.936 (deterministic: no Monte Carlo in the data). Neither reaches IoU
    0.97 / interior α 0.99 on this set: the tolerant carve and the 1-px silhouette
    dilation put hull points 1–2 px outside the neighbouring views' masks, and many
    surfels have no visible view (29 % at hull-res 384)."""
    from opacityhull.model import OpacityHullModel
    from opacityhull.evaluate.loo import leave_one_out
    from opacityhull.render.renderer import prepare_model_views

    m = OpacityHullModel.open(temple_model)
    pv = prepare_model_views(m)
    s = {
        sh: leave_one_out(m, views=[0, 4, 8, 12], config=RenderConfig(shading=sh), prepared=pv)
        for sh in ("surfel", "pixel")
    }
    px, sf = s["pixel"], s["surfel"]
    assert px["psnr_mean"] > sf["psnr_mean"] + 0.3 and px["psnr_mean"] > 18.3
    assert px["psnr_interior_mean"] > sf["psnr_interior_mean"] + 0.5
    assert px["ssim_mean"] > sf["ssim_mean"] + 0.03
    assert px["coverage_iou_mean"] > sf["coverage_iou_mean"] + 0.01 and px["coverage_iou_mean"] > 0.91
    assert px["interior_alpha_mean"] > sf["interior_alpha_mean"] + 0.015 and px["interior_alpha_mean"] > 0.95
