"""Crop rendering: only the pixels whose rays can meet the object are rendered; the rest
comes from the exact backdrop-only render (displays) or is exactly black (lights).

Oracles: the analytic silhouette of the sphere (conftest.oracle_coverage), camera.py's
projection, and full-frame renders of the same state with the same estimator.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.riggeometry import RigGeometry
from opacityhull.sim.effects import reference_effects, select_effects
from opacityhull.sim.evaluate import triangulation_alpha
from opacityhull.sim.groundtruth import default_geometry, render_ground_truth
from opacityhull.sim.render import (
    CROP_STEPS,
    SimRenderer,
    SimState,
    crop_camera,
    crop_window,
    footprint_window,
    turntable_box,
)
from opacityhull.sim.scenes import load_scene, parts_bounds

from conftest import oracle_coverage, sphere_conic


def _camera(eye, target=(0.0, 0.08, 0.0), w=160, h=120, f=150.0, cx=None, cy=None) -> Camera:
    K = np.array(
        [[f, 0.0, (w - 1) / 2 if cx is None else cx], [0.0, f, (h - 1) / 2 if cy is None else cy], [0.0, 0.0, 1.0]]
    )
    return Camera(K=K, width=w, height=h, world_from_cam=look_at_world_from_cam(eye, target))


@pytest.mark.parametrize(
    "eye,target,cx",
    [
        ((0.0, 0.3, 0.7), (0.0, 0.08, 0.0), None),  # centred
        ((0.45, 0.2, 0.5), (0.0, 0.08, 0.0), 20.0),  # off-centre principal point
        ((0.3, 0.6, 0.3), (0.12, 0.0, 0.1), None),  # object partly out of frame
        ((0.0, 0.9, 0.01), (0.0, 0.0, 0.0), None),  # straight down the table axis
    ],
)
def test_footprint_contains_every_pixel_the_sphere_covers(eye, target, cx):
    """Every pixel with analytic coverage > 0 of the sphere lies in the footprint window,
    and the window is at most 2 px (filter support + margin + rounding) wider than the
    silhouette's bounding box on each side."""
    scene = load_scene("builtin:sphere")
    cam = _camera(eye, target, cx=cx)
    lo, hi = scene.bounds()
    x0, y0, x1, y1 = footprint_window(cam, lo, hi)
    cov = oracle_coverage(sphere_conic(cam, (0, 0.08, 0), 0.08), cam.width, cam.height, n=8)
    v, u = np.nonzero(cov > 0)
    assert u.size > 0
    assert u.min() >= x0 and u.max() < x1 and v.min() >= y0 and v.max() < y1
    # not much more than the box: compare with the projected box corners
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv, _ = cam.project(corners)
    assert x0 >= max(0, np.floor(uv[:, 0].min()) - 2) and x1 <= min(cam.width, np.ceil(uv[:, 0].max()) + 3)
    assert y0 >= max(0, np.floor(uv[:, 1].min()) - 2) and y1 <= min(cam.height, np.ceil(uv[:, 1].max()) + 3)


def test_footprint_hard_cases():
    lo, hi = np.array([-0.1, 0.0, -0.1]), np.array([0.1, 0.2, 0.1])
    inside = _camera((0.0, 0.1, 0.05), (0.0, 0.1, -1.0))  # camera inside the box: any pixel
    assert footprint_window(inside, lo, hi) is None
    away = _camera((0.0, 0.1, 1.0), (0.0, 0.1, 2.0))  # box behind the camera
    assert footprint_window(away, lo, hi) is None
    aside = _camera((0.0, 0.1, 1.0), (3.0, 0.1, 0.0))  # box in front but outside the frame
    assert footprint_window(aside, lo, hi) == (0, 0, 0, 0)
    assert crop_window((0, 0, 0, 0), 100, 80) == (0, 0, 0, 0)
    # a degenerate (flat) box still gets a window: the board lies flat on the table
    flat = footprint_window(_camera((0.0, 0.5, 0.5)), np.array([-0.1, 0.0, -0.1]), np.array([0.1, 0.0, 0.1]))
    assert flat is not None and flat[2] > flat[0] and flat[3] > flat[1]


@settings(max_examples=200, deadline=None)
@given(W=st.integers(1, 900), H=st.integers(1, 700), data=st.data())
def test_crop_window_contains_the_footprint_on_the_size_grid(W, H, data):
    x0 = data.draw(st.integers(0, W - 1))
    x1 = data.draw(st.integers(x0 + 1, W))
    y0 = data.draw(st.integers(0, H - 1))
    y1 = data.draw(st.integers(y0 + 1, H))
    cx, cy, w, h = crop_window((x0, y0, x1, y1), W, H)
    assert 0 <= cx and cx + w <= W and 0 <= cy and cy + h <= H
    assert cx <= x0 and cx + w >= x1 and cy <= y0 and cy + h >= y1
    qx, qy = max(8, -(-W // CROP_STEPS)), max(8, -(-H // CROP_STEPS))
    assert w == W or w % qx == 0
    assert h == H or h % qy == 0


def test_crop_camera_projects_like_the_crop_of_the_full_image():
    cam = _camera((0.3, 0.4, 0.6), cx=70.3, cy=66.1)
    sub = crop_camera(cam, 37, 21, 48, 64)
    P = np.random.default_rng(0).uniform(-0.1, 0.2, (50, 3))
    uv, z = cam.project(P)
    uv2, z2 = sub.project(P)
    np.testing.assert_allclose(uv2, uv - [37, 21], atol=1e-9)
    np.testing.assert_allclose(z2, z)


def test_one_crop_size_per_camera_at_every_table_angle():
    """Dr.Jit compiles a kernel per film size: the window's size depends on the camera
    only (the turntable box), its position follows the object; 6 cameras x 24 table
    angles meet 6 sizes at most, and every window holds that angle's footprint."""
    g = default_geometry()
    sc = load_scene("builtin:glossy")
    r = SimRenderer(sc, g)
    sel = select_effects(sc, "matting")
    lo, hi = sc.bounds()
    for cam in g.nominal_cameras():
        sizes = set()
        for t in range(0, 360, 15):
            x0, y0, w, h = r.crop_for(cam, SimState(table_deg=float(t)), sel, sc.parts)
            fx0, fy0, fx1, fy1 = footprint_window(RigGeometry.view_camera(cam, t), lo, hi)
            assert x0 <= fx0 and y0 <= fy0 and x0 + w >= fx1 and y0 + h >= fy1
            sizes.add((w, h))
        assert len(sizes) == 1, (cam.name, sizes)


@settings(max_examples=100, deadline=None)
@given(c=st.lists(st.floats(-0.3, 0.3), min_size=6, max_size=6), t=st.floats(0.0, 360.0))
def test_turntable_box_contains_the_box_at_every_angle(c, t):
    from opacityhull.camera import rig_from_object

    lo, hi = np.minimum(c[:3], c[3:]), np.maximum(c[:3], c[3:])
    tlo, thi = turntable_box(lo, hi)
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    P = (rig_from_object(t) @ corners.T).T[:, :3]
    assert np.all(P >= tlo - 1e-12) and np.all(P <= thi + 1e-12)


# ------------------------------------------------------------------ renders


@pytest.fixture(scope="module")
def diffuse_renderer():
    return SimRenderer(load_scene("builtin:diffuse"), default_geometry())


def _patterns(g, seed):
    # like acquire/patterns.py: every channel in [0, 63] or [192, 255], so the backdrops
    # of a pair differ by >= 129/255 everywhere and triangulation matting is well posed
    rng = np.random.default_rng(seed)
    p1 = {}
    for d in g.displays:
        v = rng.integers(0, 64, (d.resolution[1], d.resolution[0], 3))
        p1[d.name] = np.where(rng.random(v.shape) < 0.5, v, 255 - v).astype(np.uint8)
    return p1, {k: (255 - v).astype(np.uint8) for k, v in p1.items()}


def _window(r, cam, state, cfg):
    return r.crop_for(cam, state, cfg, r.scene.parts)


def _constant(g, rgb):
    return {
        d.name: np.broadcast_to(np.asarray(rgb, np.uint8), (d.resolution[1], d.resolution[0], 3)).copy()
        for d in g.displays
    }


@pytest.mark.parametrize("patterns,declared", [("constant", True), ("cells", True), ("cells", False)])
def test_cropped_matting_matches_the_full_render_at_the_crop_border(diffuse_renderer, patterns, declared):
    """Triangulation alpha from cropped shots against full-frame shots (the same estimator,
    independent seeds) on the two pixel rings either side of the window's border.

    Constant complementary backdrops: no texel edges, so a background pixel is
    noise-free in any render — every ring pixel must be within the matting bound (a seam
    or a cut-off object would show). Random cells: texel edges make a single pixel's
    alpha noisy in *any* render, so against the truth there (coverage 0: the aov ground
    truth shows the object does not reach the ring) the ring's mean error is held to the
    bound and to that of the full render. Outside the window the composite is exactly
    the backdrop shot (alpha exactly 0). Both the declared matting selection (its
    measured candidate's spp) and the undeclared one (the envmatte-safe spp)."""
    r = diffuse_renderer
    g = r.geometry
    cam = g.nominal_cameras()[2]
    sel = select_effects(r.scene, "matting", declared=declared)
    phase = "matting" if declared else None
    full = replace(sel, crop=False)
    if patterns == "constant":
        p1, p2 = _constant(g, (255, 0, 200)), _constant(g, (0, 255, 55))
    else:
        p1, p2 = _patterns(g, 3)
    s1, s2 = SimState(table_deg=35.0, displays=p1, phase=phase), SimState(table_deg=35.0, displays=p2, phase=phase)
    assert r.passes_for(s1)[0].effects.spp == sel.spp
    x0, y0, w, h = _window(r, cam, s1, sel)
    assert 0 < w * h < 0.5 * cam.width * cam.height
    r.clear_radiance_cache()
    b1 = r.render(cam, replace(s1, content="none"), seed=1)
    b2 = r.render(cam, replace(s2, content="none"), seed=2)
    renders0 = r.renders
    c1, c2 = r.render(cam, s1, seed=3), r.render(cam, s2, seed=4)
    assert r.renders - renders0 == 2  # the backdrops came from the cache: one crop render per shot
    f1, f2 = (r.render(cam, s, effects=full, seed=k, use_cache=False) for k, s in ((5, s1), (6, s2)))
    a_crop = triangulation_alpha(c1, c2, b1, b2)
    a_full = triangulation_alpha(f1, f2, b1, b2)
    inside = np.zeros(a_crop.shape, bool)
    inside[y0 : y0 + h, x0 : x0 + w] = True
    np.testing.assert_array_equal(c1[~inside], b1[~inside])
    assert np.all(a_crop[~inside] == 0.0)
    ring = np.zeros_like(inside)
    ring[max(y0 - 2, 0) : y0 + h + 2, max(x0 - 2, 0) : x0 + w + 2] = True
    ring[y0 + 2 : y0 + h - 2, x0 + 2 : x0 + w - 2] = False
    if patterns == "constant":
        d = np.abs(a_crop - a_full)[ring]
        assert d.max() <= sel.error_bound, d.max()
    else:
        cov = render_ground_truth(r.scene, RigGeometry.view_camera(cam, 35.0), spp=16, renderer=r)["alpha"]
        assert cov[ring].max() == 0.0 and cov[inside].sum() > 100
        e_crop, e_full = np.abs(a_crop[ring]).mean(), np.abs(a_full[ring]).mean()
        assert e_crop <= sel.error_bound and e_crop <= e_full + 1e-4, (e_crop, e_full)
    # the object is inside and the estimate is the same there: mean alpha agrees
    assert a_full[inside].mean() > 0.1
    assert abs(a_crop[inside].mean() - a_full[inside].mean()) < 0.2 * sel.error_bound
    assert np.abs(f1[~inside] - b1[~inside]).mean() < 0.03 * b1.mean()  # anti-aliasing noise only


def test_light_pass_outside_the_window_is_exactly_black(diffuse_renderer):
    """Under the light array a ray that misses the object sees black panels: a full
    render is exactly 0 outside the window, and the cropped render agrees inside
    (direct lighting from a point light: the same estimator; stratified AA noise only)."""
    r = diffuse_renderer
    cam = r.geometry.nominal_cameras()[1]
    st_ = SimState(table_deg=80.0, light_levels={1: 255})
    sel = select_effects(r.scene, "reflectance")
    x0, y0, w, h = _window(r, cam, st_, sel)
    crop = r.render(cam, st_, seed=1, use_cache=False)
    full = r.render(cam, st_, effects=replace(sel, crop=False), seed=2, use_cache=False)
    inside = np.zeros(full.shape[:2], bool)
    inside[y0 : y0 + h, x0 : x0 + w] = True
    assert np.all(full[~inside] == 0.0) and np.all(crop[~inside] == 0.0)
    assert full[inside].mean() > 0
    assert abs(crop[inside].mean() / full[inside].mean() - 1.0) < 0.01


def test_object_out_of_view_costs_only_the_backdrop(diffuse_renderer):
    r = diffuse_renderer
    g = r.geometry
    base = g.nominal_cameras()[0]
    # look at the back display, well above the object
    cam = replace(base, world_from_cam=look_at_world_from_cam(base.centre_world, (0.0, 0.9, -0.6)))
    p1, _ = _patterns(g, 5)
    s = SimState(table_deg=0.0, displays=p1)
    assert _window(r, cam, s, select_effects(r.scene, "matting")) == (0, 0, 0, 0)
    r.clear_radiance_cache()
    b = r.render(cam, replace(s, content="none"), seed=1)
    n = r.renders
    img = r.render(cam, s, seed=2)
    assert r.renders == n  # nothing to render: the backdrop shot is the image
    np.testing.assert_array_equal(img, b)


def test_reference_renders_the_whole_frame():
    sc = load_scene("builtin:glossy")
    assert select_effects(sc, "matting").crop and not reference_effects(sc, "matting").crop
    assert not select_effects(sc, "groundtruth").crop
    assert not select_effects(sc, "matting", overrides={"crop": False}).crop
    assert parts_bounds(sc.parts)[0].shape == (3,)
