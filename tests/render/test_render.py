"""The renderer against exact ground truth (analytic sphere), robustness, backgrounds and
environment maps (Mitsuba as the oracle of the convention), and camera helpers."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage as ndi

import opacityhull
from opacityhull.camera import Camera, look_at_world_from_cam, rot_y
from opacityhull.envmap import EnvironmentMap
from opacityhull.errors import InputError, ShapeError
from opacityhull.model import Surfels
from opacityhull.render.background import (
    direction_to_equirect,
    envmap_background,
    equirect_to_direction,
    load_background,
)
from opacityhull.render.cameras import (
    captured_view_camera,
    look_at_camera,
    orbit_cameras,
    parse_look_at,
    parse_view_spec,
    resize_camera,
    scene_target,
)
from opacityhull.evaluate.loo import _display, loo_metrics
from opacityhull.render.renderer import RenderConfig, render_image, spatially_sorted
from opacityhull.render.synthetic import make_sphere_model
from opacityhull.render.views import prepare_views
from opacityhull.riggeometry import RigGeometry


#: A shipped HDR probe (the same bytes as shared/data/probes/grace.hdr), so the tests need no ../shared.
GRACE = Path(opacityhull.__file__).parent / "data" / "probes" / "grace.hdr"


@pytest.fixture(scope="module")
def sphere64():
    """8000 surfels, 36 views of 64×48 (30° table steps × 3 elevations), view-dependent highlight."""
    m = make_sphere_model(8000, width=64, height=48)
    return m, prepare_views(m.cameras, m.views_premul())


def interior_psnr(photo, render, erode=2):
    inner = ndi.binary_erosion(photo[..., 3] > 0.999, iterations=erode)
    d = (_display(photo) - _display(render))[inner]
    mse = float(np.mean(d**2))
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def shifted(cam: Camera, dx: float) -> Camera:
    K = cam.K.copy()
    K[0, 2] += dx
    return Camera(K=K, width=cam.width, height=cam.height, world_from_cam=cam.world_from_cam, name=cam.name)


def test_captured_view_reproduces_its_photograph(sphere64):
    """With the desired camera on a captured view, ULR is one-hot and every surfel takes its
    colour from that photo: only resampling (bilinear + σ = 0.5 px EWA filter) remains.
    Measured 39.0 dB interior / 26.6 dB over the mask (edges: Gaussian vs box-filtered
    silhouette). The thresholds sit ~3 dB lower; a half-pixel misregistration (measured
    32.6 / 21.9 dB) must fail them, and does."""
    m, pv = sphere64
    photo = m.view_rgba[4]
    surfel = RenderConfig(shading="surfel")
    r = render_image(m.surfels, m.cameras, pv, m.cameras[4], config=surfel)
    met = loo_metrics(photo, r.rgba)
    assert interior_psnr(photo, r.rgba) > 35.5
    assert met["psnr"] > 23.5 and met["ssim"] > 0.97 and met["alpha_mae"] < 0.04
    bad = render_image(m.surfels, m.cameras, pv, shifted(m.cameras[4], 0.5), config=surfel)  # half a pixel off
    assert interior_psnr(photo, bad.rgba) < 35.5 and loo_metrics(photo, bad.rgba)["psnr"] < 23.5  # measured 32.6, 21.9
    # per-pixel shading has no resampling filter: the interior is the photograph itself
    # (tests/render/test_deferred.py has the silhouette)
    px = render_image(m.surfels, m.cameras, pv, m.cameras[4], config=RenderConfig(shading="pixel"))
    assert interior_psnr(photo, px.rgba) > 60 and loo_metrics(photo, px.rgba)["psnr"] > met["psnr"]


@pytest.mark.parametrize("fuzzy", [False, True])
def test_novel_view_matches_exact_ground_truth(sphere64, fuzzy):
    """A camera between captured views (table 15°, between 0° and 30°) against the exact
    supersampled image of the analytic scene. Measured 27.2 dB (opaque) / 28.3 dB (fuzzy),
    SSIM 0.98."""
    if fuzzy:
        m = make_sphere_model(8000, width=64, height=48, fuzzy=True)
        pv = prepare_views(m.cameras, m.views_premul())
    else:
        m, pv = sphere64
    geo = RigGeometry.from_dict(m.rig)
    cam = RigGeometry.view_camera(geo.nominal_cameras()[1], 15.0)
    gt = m.scene.render(cam)
    r = render_image(m.surfels, m.cameras, pv, cam)
    met = loo_metrics(gt, r.rgba)
    assert met["psnr"] > 24.5 and met["ssim"] > 0.965 and met["alpha_mae"] < 0.055
    if fuzzy:  # the opacity light field's alpha comes through, not just a silhouette
        inner = ndi.binary_erosion(gt[..., 3] > 0.01, iterations=3)
        assert np.ptp(gt[..., 3][inner]) > 0.5
        assert np.mean(np.abs(gt[..., 3] - r.alpha)[inner]) < 0.03


def test_leaving_a_view_out_degrades_gracefully_and_uses_neighbours(sphere64):
    m, pv = sphere64
    photo = m.view_rgba[4]
    r = render_image(m.surfels, m.cameras, pv, m.cameras[4], exclude_views=[4])
    met = loo_metrics(photo, r.rgba)
    assert met["psnr"] > 22.0 and met["ssim"] > 0.94  # measured 24.7 dB, 0.959
    full = loo_metrics(photo, render_image(m.surfels, m.cameras, pv, m.cameras[4]).rgba)
    assert met["psnr"] < full["psnr"]  # the held-out view really was not used
    assert r.stats["excluded_views"] == [4]


@pytest.mark.parametrize("shading", ["surfel", "pixel"])
def test_excluding_every_view_draws_nothing(sphere64, shading):
    m, pv = sphere64
    r = render_image(
        m.surfels,
        m.cameras,
        pv,
        m.cameras[0],
        exclude_views=range(len(m.cameras)),
        config=RenderConfig(shading=shading),
    )
    assert np.all(r.rgba == 0)
    if shading == "surfel":
        assert r.stats["splats_drawn"] == 0 and np.all(np.isinf(r.depth))
    else:  # the hull is still geometry (depth), but no pixel is shaded
        assert r.stats["pixels_shaded"] == 0 and np.isfinite(r.depth).any()


def test_depth_is_the_sphere(sphere64):
    m, pv = sphere64
    cam = m.cameras[1]
    r = render_image(m.surfels, m.cameras, pv, cam)
    o, d = cam.pixel_rays()
    t = m.scene.hit(o, d.reshape(-1, 3)).reshape(cam.height, cam.width)
    z_true = t * (d @ cam.forward_world)
    inner = ndi.binary_erosion(np.isfinite(z_true), iterations=2)
    assert np.all(np.isfinite(r.depth[inner]))
    assert np.max(np.abs(r.depth[inner] - z_true[inner])) < 0.004  # surfel radius ≈ 2.3 mm


@pytest.mark.parametrize("k1", [-0.3, 0.3])
def test_lens_distortion_of_the_desired_camera(sphere64, k1):
    """The sphere off the principal point, barrel and pincushion distortion: the rendering
    through the distorted camera matches the exact distorted image (measured 25.4 / 24.9
    dB), and ignoring the distortion would cost ~5 dB (measured 20.0 / 20.1 dB)."""
    m, pv = sphere64
    c = m.cameras[4]
    target = np.asarray(m.scene.centre) + 0.09 * c.world_from_cam[:3, 0] + 0.05 * c.world_from_cam[:3, 1]
    T = look_at_world_from_cam(c.centre_world, target)
    cam = Camera(K=c.K, width=c.width, height=c.height, world_from_cam=T, dist=[k1, 0.0, 0.001, 0, 0])
    gt = m.scene.render(cam)
    met = loo_metrics(gt, render_image(m.surfels, m.cameras, pv, cam).rgba)
    assert met["psnr"] > 23.0 and met["ssim"] > 0.96
    pinhole = Camera(K=c.K, width=c.width, height=c.height, world_from_cam=T)
    assert loo_metrics(gt, render_image(m.surfels, m.cameras, pv, pinhole).rgba)["psnr"] < met["psnr"] - 3


def test_distorted_captured_views_are_projected_with_their_distortion():
    m = make_sphere_model(4000, width=64, height=48, table_step_deg=45, distortion=[-0.2, 0.03, 0, 0, 0])
    pv = prepare_views(m.cameras, m.views_premul())
    geo = RigGeometry.from_dict(m.rig)
    cam = RigGeometry.view_camera(geo.nominal_cameras()[1], 20.0)
    gt = m.scene.render(cam)
    met = loo_metrics(gt, render_image(m.surfels, m.cameras, pv, cam).rgba)
    assert met["psnr"] > 23.0


def test_order_of_surfels_does_not_matter(sphere64):
    m, pv = sphere64
    cam = m.cameras[7]
    a = render_image(m.surfels, m.cameras, pv, cam)
    b = render_image(spatially_sorted(m.surfels), m.cameras, pv, cam)
    np.testing.assert_allclose(a.rgba, b.rgba, atol=1e-4)


def test_bad_inputs_never_produce_nan(sphere64):
    m, _ = sphere64
    views = m.views_premul()
    views[3][10:20, 10:30] = np.nan
    views[5][0:5] = np.inf
    S = m.surfels
    pos = S.positions.copy()
    nrm = S.normals.copy()
    rad = S.radii.copy()
    pos[:50] = np.nan
    nrm[50:100] = 0.0  # no normal: drawn as a camera-facing disc
    rad[100:150] = 0.0
    rad[150:160] = np.inf
    bad = Surfels(pos, nrm, rad, S.visibility, S.n_views)
    pv = prepare_views(m.cameras, views)
    assert pv.nonfinite_texels == 10 * 20 * 4 + 5 * 64 * 4
    cam = RigGeometry.view_camera(RigGeometry.from_dict(m.rig).nominal_cameras()[1], 40.0)
    r = render_image(bad, m.cameras, pv, cam)
    assert np.all(np.isfinite(r.rgba)) and np.all(np.isfinite(r.weight)) and not np.any(np.isnan(r.depth))
    assert r.stats["nonfinite_texels"] == pv.nonfinite_texels
    clean = render_image(m.surfels, m.cameras, m.views_premul(), cam)
    assert loo_metrics(clean.rgba, r.rgba)["psnr"] > 20  # the damage stays local


def test_empty_and_mismatched_inputs(sphere64):
    m, pv = sphere64
    empty = Surfels(
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros(0),
        np.zeros((0, (len(m.cameras) + 7) // 8), np.uint8),
        len(m.cameras),
    )
    r = render_image(empty, m.cameras, pv, m.cameras[0])
    assert r.rgba.shape == (48, 64, 4) and np.all(r.rgba == 0)
    with pytest.raises(InputError, match="visibility for 36 views, 35"):
        render_image(m.surfels, m.cameras[:35], m.views_premul()[:35], m.cameras[0])
    with pytest.raises(ShapeError, match=r"view 0 .* expected \(48, 64, 4\)"):
        render_image(m.surfels, m.cameras, [v[:, :, :3] for v in m.views_premul()], m.cameras[0])
    with pytest.raises(InputError, match="k = 0"):
        RenderConfig(k=0)
    with pytest.raises(InputError, match="filter"):
        RenderConfig(filter=-1.0)
    with pytest.raises(InputError, match="coverage_threshold"):
        RenderConfig(coverage_threshold=0.0)


def test_over_composites_straight_alpha(sphere64):
    m, pv = sphere64
    r = render_image(m.surfels, m.cameras, pv, m.cameras[2], config=RenderConfig(background=(0.0, 0.5, 1.0)))
    a = r.alpha[..., None]
    np.testing.assert_allclose(r.over(), r.rgba[..., :3] * a + np.array([0, 0.5, 1.0]) * (1 - a), atol=1e-6)
    img = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    np.testing.assert_allclose(r.over(img), r.rgba[..., :3] * a + img * (1 - a), atol=1e-6)
    np.testing.assert_allclose(r.over(0.25)[0, 0], 0.25)  # a corner is background
    with pytest.raises(InputError, match="background of shape"):
        r.over(np.zeros((10, 10, 3)))


def test_equirect_convention():
    u, v = direction_to_equirect(np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0], [-1.0, 0, 0], [0, -1.0, 0]]))
    np.testing.assert_allclose(u[[0, 2, 3]], [0.5, 0.25, 0.75])
    np.testing.assert_allclose(v[[0, 1, 2, 4]], [0.5, 0.0, 0.5, 1.0])
    rng = np.random.default_rng(1)
    d = rng.normal(size=(100, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(equirect_to_direction(*direction_to_equirect(d)), d, atol=1e-12)


def test_envmap_lookup_wraps_the_seam_and_clamps_the_poles():
    h, w = 8, 16
    img = np.zeros((h, w, 3), np.float32)
    img[:, :, 0] = np.arange(w)[None, :]  # red = column index
    img[:, :, 1] = np.arange(h)[:, None]  # green = row index
    env = EnvironmentMap(img)
    # −Z is the seam (u = 0 = 1): halfway between the last and the first column
    seam = env.lookup(np.array([[0.0, 0.0, -1.0]]))[0]
    assert seam[0] == pytest.approx((w - 1 + 0) / 2)
    # a quarter texel either side of the seam blends column 0 with column w−1 (not clamped)
    d = equirect_to_direction(np.array([0.25 / w, 1 - 0.25 / w]), np.array([0.5, 0.5]))
    np.testing.assert_allclose(env.lookup(d)[:, 0], [0.25 * (w - 1), 0.75 * (w - 1)], rtol=1e-5)
    # the poles clamp to the first / last row
    assert env.lookup(np.array([[0.0, 1.0, 0.0]]))[0, 1] == pytest.approx(0.0)
    assert env.lookup(np.array([[0.0, -1.0, 0.0]]))[0, 1] == pytest.approx(h - 1)
    # yaw 180° swaps +Z and −Z
    d = np.array([[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(env.rotated(180).lookup(d), env.lookup(-d))
    # a degenerate ray: a background sees the zenith, lighting raises
    np.testing.assert_allclose(env.lookup(np.zeros((1, 3)), invalid="zenith"), env.lookup(np.array([[0, 1.0, 0]])))
    with pytest.raises(InputError, match="zero, NaN or Inf"):
        env.lookup(np.zeros((1, 3)))


@pytest.mark.parametrize("yaw_deg", [0.0, 22.5, 90.0, 180.0, -67.5, 337.5])
def test_a_turned_map_sees_what_the_map_shows_at_the_turned_back_direction(yaw_deg):
    """``rotated(yaw)`` (a column shift, the one way a map is turned) against the
    definition: a direction d sees what the unturned map shows at R_y(−yaw) d. Exact to
    float32 rounding when the yaw is whole texels (every yaw here on a 32-wide map)."""
    rng = np.random.default_rng(3)
    env = EnvironmentMap(rng.random((16, 32, 3)).astype(np.float32))
    d = rng.normal(size=(500, 3))
    turned_back = d @ rot_y(math.radians(-yaw_deg)).T
    np.testing.assert_allclose(env.rotated(yaw_deg).lookup(d), env.lookup(turned_back), atol=2e-6)


def test_envmap_background_agrees_with_mitsuba():
    """Mitsuba's envmap emitter seen through the same camera (pinned by camera.py's
    Mitsuba conversion) is the oracle of the equirect convention; a mirrored map
    differs by ~0.1."""
    import mitsuba as mi

    previous = mi.variant()
    mi.set_variant("scalar_rgb")
    try:
        _envmap_vs_mitsuba(mi)
    finally:  # the variant is process-global: later simulator tests load scenes in theirs
        if previous:
            mi.set_variant(previous)


def _envmap_vs_mitsuba(mi):
    from opacityhull.camera import mitsuba_sensor_params

    h, w = 32, 64
    v, u = np.mgrid[0:h, 0:w]
    env = (0.5 + 0.45 * equirect_to_direction((u + 0.5) / w, (v + 0.5) / h)).astype(np.float32)
    f = 24 / (2 * math.tan(math.radians(50) / 2))
    for target in ((0, 0, 1.0), (1.0, 0, 0.2), (0.3, 0.8, -0.5)):
        cam = Camera(
            K=np.array([[f, 0, 15.5], [0, f, 11.5], [0, 0, 1]]),
            width=32,
            height=24,
            world_from_cam=look_at_world_from_cam((0, 0, 0), target),
        )
        p = mitsuba_sensor_params(cam)
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "direct"},
                "emitter": {"type": "envmap", "bitmap": mi.Bitmap(env)},
                "sensor": {
                    "type": "perspective",
                    "fov": p["fov"],
                    "fov_axis": "y",
                    "principal_point_offset_x": p["principal_point_offset_x"],
                    "principal_point_offset_y": p["principal_point_offset_y"],
                    "to_world": mi.ScalarTransform4f(p["to_world"]),
                    "film": {
                        "type": "hdrfilm",
                        "width": 32,
                        "height": 24,
                        "rfilter": {"type": "box"},
                        "pixel_format": "rgb",
                    },
                    "sampler": {"type": "independent", "sample_count": 16},
                },
            }
        )
        ref = np.array(mi.render(scene))
        mine = envmap_background(EnvironmentMap(env), cam)
        assert np.mean(np.abs(ref - mine)) < 0.01
        assert np.mean(np.abs(ref[:, ::-1] - mine)) > 0.05


def test_envmap_over_and_probe_file(sphere64, tmp_path):
    m, pv = sphere64
    env = load_background(str(GRACE), yaw_deg=180)
    assert isinstance(env, EnvironmentMap)
    cam = m.cameras[0]
    r = render_image(m.surfels, m.cameras, pv, cam)
    out = r.over(env)
    bg = envmap_background(env, cam)
    np.testing.assert_allclose(out[0, 0], bg[0, 0], rtol=1e-6)  # a background corner
    assert np.all(np.isfinite(out)) and bg.max() > 1.0  # HDR values survive
    assert isinstance(load_background(str(GRACE)), EnvironmentMap)
    assert load_background("0.1,0.2,0.3") == (0.1, 0.2, 0.3)
    assert load_background("white") == (1.0, 1.0, 1.0)
    with pytest.raises(InputError, match="neither a colour nor an existing image"):
        load_background(str(tmp_path / "nope.png"))


@pytest.mark.parametrize("bad, what", [(np.nan, "1 NaN"), (-0.5, "1 negative")])
def test_a_background_map_with_bad_radiance_is_refused_naming_the_file(tmp_path, bad, what):
    """The one EnvironmentMap checks a background map as it checks a light: NaN, Inf or
    negative radiance would reach every composited pixel."""
    from opacityhull.imageio import write_exr

    img = np.full((8, 16, 3), 0.5, np.float32)
    img[2, 3, 1] = bad
    path = tmp_path / "sky.exr"
    write_exr(path, img)
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'sky.exr'}: {what}") + ".*row 2, column 3, channel G"):
        load_background(str(path))


def test_camera_helpers(sphere64):
    m, _ = sphere64
    cams = m.cameras
    t = scene_target(cams)
    np.testing.assert_allclose(t, m.scene.centre, atol=1e-9)  # the rig aims at the sphere
    orbit = orbit_cameras(cams, 6, width=80)
    assert len(orbit) == 6 and orbit[0].width == 80 and orbit[0].height == 60
    dists = [np.linalg.norm(c.centre_world - t) for c in orbit]
    np.testing.assert_allclose(dists, 0.5, rtol=1e-9)  # the captured cameras' distance
    el = [math.degrees(math.asin((c.centre_world - t)[1] / 0.5)) for c in orbit]
    np.testing.assert_allclose(el, 35.0, atol=1e-6)  # mean of 5°, 35°, 65°
    for c in orbit:  # each looks at the target
        np.testing.assert_allclose(c.project(t[None])[0][0], [(c.width - 1) / 2, (c.height - 1) / 2], atol=1e-6)
    # a captured view is returned as is; another table angle turns the physical camera
    from opacityhull.model import ViewInfo

    views = [ViewInfo(i, c.name, i % 3, 30.0 * (i // 3), c) for i, c in enumerate(cams)]
    assert captured_view_camera(views, 1, 30.0) is cams[4]
    geo = RigGeometry.from_dict(m.rig)
    novel = captured_view_camera(views, 1, 15.0)
    np.testing.assert_allclose(
        novel.world_from_cam, RigGeometry.view_camera(geo.nominal_cameras()[1], 15.0).world_from_cam, atol=1e-12
    )
    with pytest.raises(InputError, match="no captured camera 7"):
        captured_view_camera(views, 7, 0.0)
    # resizing keeps the vertical field of view and the relative principal point
    c2 = resize_camera(cams[0], 128)
    assert (c2.width, c2.height) == (128, 96)
    assert math.atan(c2.height / 2 / c2.fy) == pytest.approx(math.atan(cams[0].height / 2 / cams[0].fy))
    la = look_at_camera((0, 0.1, 1.0), (0, 0.1, 0), fov_y_deg=40, width=32, height=24)
    np.testing.assert_allclose(la.project(np.array([[0, 0.1, 0.0]]))[0][0], [15.5, 11.5])
    assert parse_view_spec("2, 45.5") == (2, 45.5)
    eye, tgt, fov = parse_look_at("0,0.1,1,0,0.1,0,35")
    assert fov == 35 and np.allclose(eye, [0, 0.1, 1])
    for bad in ("1", "a,b", "1,2,3"):
        with pytest.raises(InputError, match="--view"):
            parse_view_spec(bad)
    with pytest.raises(InputError, match="--look-at"):
        parse_look_at("1,2,3")
    with pytest.raises(InputError, match="coincide"):
        parse_look_at("1,1,1,1,1,1")
