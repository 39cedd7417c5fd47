"""Ground truth: analytic sphere silhouettes, depth and normals, environment-map convention."""

from __future__ import annotations


import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.errors import InputError, ShapeError
from opacityhull.riggeometry import RigGeometry
from opacityhull.sim.groundtruth import direction_to_equirect, envmap_for_mitsuba, equirect_direction
from opacityhull.sim.groundtruth import render_ground_truth, render_under_envmap
from opacityhull.sim.render import SimRenderer
from opacityhull.sim.scenes import load_scene

from conftest import conic_area_centre, oracle_coverage, sphere_conic

CENTRE = np.array([0.0, 0.08, 0.0])
RADIUS = 0.08


@pytest.fixture(scope="module")
def sphere_gt(sphere_scene):
    cam = Camera(
        K=np.array([[120.0, 0, 47.6], [0, 120.0, 34.1], [0, 0, 1]]),
        width=96,
        height=72,
        world_from_cam=look_at_world_from_cam((0.3, 0.5, 0.8), (0.01, 0.09, 0.0)),
    )
    r = SimRenderer(sphere_scene, None)
    return cam, render_ground_truth(sphere_scene, cam, renderer=r)


def test_sphere_alpha_equals_the_analytic_silhouette(sphere_gt):
    cam, gt = sphere_gt
    Q = sphere_conic(cam, CENTRE, RADIUS)
    area, _ = conic_area_centre(Q)
    alpha = gt["alpha"].astype(np.float64)
    assert alpha.min() >= 0 and alpha.max() <= 1
    assert alpha.sum() == pytest.approx(area, rel=3e-3)  # area
    oracle = oracle_coverage(Q, cam.width, cam.height, n=32)
    assert np.abs(alpha - oracle).mean() < 2e-3
    assert np.abs(alpha - oracle).max() < 0.1
    # boundary: partially covered pixels are exactly the analytic boundary pixels (+-1 px)
    import cv2

    part = (alpha > 0.02) & (alpha < 0.98)
    oracle_part = ((oracle > 0) & (oracle < 1)).astype(np.uint8)
    near = cv2.dilate(oracle_part, np.ones((3, 3), np.uint8)) > 0
    assert part.sum() > 20 and np.all(near[part])


def _ray_sphere(cam: Camera):
    o, d = cam.pixel_rays()
    oc = o - CENTRE
    b = d @ oc
    c = oc @ oc - RADIUS**2
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0))
    return o + t[..., None] * d, disc > 0


def test_sphere_depth_and_normals(sphere_gt):
    cam, gt = sphere_gt
    hit, valid = _ray_sphere(cam)
    import cv2

    inner = cv2.erode((gt["alpha"] > 0.999).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert inner.sum() > 100 and np.all(valid[inner])
    z_true = cam.world_to_cam(hit[inner])[:, 2]
    assert np.max(np.abs(gt["depth"][inner] - z_true)) < 1.5e-3  # pixel-area average vs centre ray
    n_true = (hit[inner] - CENTRE) / RADIUS
    cosang = np.einsum("ij,ij->i", gt["normals"][inner], n_true)
    assert np.degrees(np.arccos(np.clip(cosang.min(), -1, 1))) < 2.0
    assert np.all(np.isnan(gt["depth"][gt["alpha"] == 0]))
    assert np.all(gt["normals"][gt["alpha"] == 0] == 0)
    assert set(np.unique(gt["shape_id"])) == {0, 1}


def test_shape_ids_name_the_parts(small_geometry):
    scene = load_scene("builtin:glossy")  # dome (part 0) and ring (part 1)
    cam = RigGeometry.view_camera(small_geometry.nominal_cameras()[4], 10.0)
    gt = render_ground_truth(scene, cam, spp=16)
    ids = gt["shape_id"]
    assert set(np.unique(ids)) == {0, 1, 2}
    # the ring lies on the table around the dome: its pixels are lower in the image on average
    v = np.mgrid[0 : cam.height, 0 : cam.width][0]
    assert v[ids == 2].mean() > v[ids == 1].mean()
    # one sample per pixel for ids, 16 for alpha: they agree except at thin edges
    assert np.all(ids[gt["alpha"] > 0.999] > 0)
    assert np.mean(gt["alpha"][ids > 0] > 0) > 0.97


def test_empty_parts_give_empty_ground_truth(sphere_scene):
    cam = Camera(K=np.array([[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]]), width=32, height=24)
    gt = render_ground_truth(sphere_scene, cam, parts=())
    assert gt["alpha"].sum() == 0 and np.all(np.isnan(gt["depth"])) and gt["shape_id"].max() == 0


@settings(max_examples=50, deadline=None)
@given(u=st.floats(0.0, 0.999), v=st.floats(0.01, 0.99))
def test_equirect_direction_roundtrip(u, v):
    d = equirect_direction(u, v)
    assert np.linalg.norm(d) == pytest.approx(1.0)
    u2, v2 = direction_to_equirect(d)
    assert min(abs(u2 - u), 1 - abs(u2 - u)) < 1e-9 and abs(v2 - v) < 1e-9


def test_equirect_convention_axes():
    assert np.allclose(equirect_direction(0.5, 0.5), [0, 0, 1], atol=1e-12)  # centre column looks along +Z
    assert np.allclose(equirect_direction(0.25, 0.5), [1, 0, 0], atol=1e-12)
    assert np.allclose(equirect_direction(0.3, 0.0), [0, 1, 0], atol=1e-12)  # top row is +Y


def test_envmap_validation():
    with pytest.raises(ShapeError):
        envmap_for_mitsuba(np.zeros((4, 8)))
    with pytest.raises(InputError):
        envmap_for_mitsuba(np.full((4, 8, 3), -1.0))


def _spot_map(direction, rows=64, cols=128, half_width_px=2):
    u, v = direction_to_equirect(np.asarray(direction, dtype=np.float64))
    env = np.zeros((rows, cols, 3), np.float32)
    r, c = int(v * rows), int(u * cols) % cols
    env[
        max(r - half_width_px, 0) : r + half_width_px + 1,
        [(c + k) % cols for k in range(-half_width_px, half_width_px + 1)],
    ] = 50.0
    return env


@pytest.fixture(scope="module")
def no_display_geometry():
    return RigGeometry.from_dict(
        {
            "target_m": [0, 0.08, 0],
            "cameras": [
                {"name": "c", "width": 48, "height": 36, "distance_m": 1.0, "elevation_deg": 10.0, "fov_y_deg": 14.0}
            ],
        }
    )


@pytest.mark.parametrize("direction", [(1.0, 0.2, 0.0), (-0.3, 0.5, 0.8), (0.0, 0.3, -1.0)])
def test_envmap_bright_in_one_direction_lights_the_side_facing_it(sphere_scene, no_display_geometry, direction):
    """A map bright only around direction d lights a Lambertian sphere like a distant
    light from d: the shading follows max(0, n.d) with n from the ground-truth normals;
    the mirrored convention (u -> 1 - u) would not."""
    d = np.asarray(direction) / np.linalg.norm(direction)
    cam = no_display_geometry.nominal_cameras()[0].with_pose(
        look_at_world_from_cam(CENTRE + 0.6 * np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), CENTRE)
    )
    r = SimRenderer(sphere_scene, no_display_geometry)
    out = render_under_envmap(sphere_scene, cam, _spot_map(d), spp=64, rig=no_display_geometry, renderer=r)
    assert out.shape == (36, 48, 4)
    gt = render_ground_truth(sphere_scene, cam, renderer=r)
    m = gt["alpha"] > 0.999
    lum = out[..., :3].mean(axis=2)[m]
    n = gt["normals"][m]
    good = np.maximum(n @ d, 0)
    mirrored = d * np.array([-1, 1, 1])  # u -> 1 - u swaps +X and -X
    bad = np.maximum(n @ mirrored, 0)
    corr_good = np.corrcoef(lum, good)[0, 1]
    assert corr_good > 0.97
    if abs(d[0]) > 0.2:
        assert np.corrcoef(lum, bad)[0, 1] < corr_good - 0.2
    assert np.allclose(out[..., 3], gt["alpha"], atol=0.03)


def test_envmap_displays_off_hide_the_environment_behind_them(sphere_scene, small_geometry):
    """The bottom display (off) blocks the lower hemisphere: a map bright only below the
    table leaves the sphere black; the same map without displays lights it."""
    env = np.zeros((32, 64, 3), np.float32)
    env[24:] = 5.0  # below the horizon only
    cam = RigGeometry.view_camera(small_geometry.nominal_cameras()[0], 0.0)
    with_panels = render_under_envmap(sphere_scene, cam, env, spp=16, rig=small_geometry)
    assert with_panels[..., :3].max() < 1e-3
    nodisp = RigGeometry(target_m=small_geometry.target_m, cameras=small_geometry.cameras)
    without = render_under_envmap(sphere_scene, cam, env, spp=16, rig=nodisp)
    assert without[..., :3].max() > 0.05


def test_envmap_table_angle_moves_only_the_rig_fixed_display(sphere_scene, small_geometry):
    """The map and the object stay put in the object frame; turning the table only moves
    the back display (fixed in the rig), which hides a different part of the map."""
    env = np.zeros((32, 64, 3), np.float32)
    u, v = direction_to_equirect(np.array([0.0, 0.15, -1.0]))  # low, behind: where the back panel is at 0 deg
    cols = [(int(u * 64) + k) % 64 for k in range(-3, 4)]  # -Z is at the seam u = 0
    env[int(v * 32) - 2 : int(v * 32) + 3, cols] = 30.0
    cam = RigGeometry.view_camera(small_geometry.nominal_cameras()[5], 180.0)  # from -Z, above the back panel
    r = SimRenderer(sphere_scene, small_geometry)
    at0 = render_under_envmap(sphere_scene, cam, env, spp=16, rig=small_geometry, table_deg=0.0, renderer=r)
    at180 = render_under_envmap(sphere_scene, cam, env, spp=16, rig=small_geometry, table_deg=180.0, renderer=r)
    assert at0[..., :3].max() < 1e-3  # the back panel is between the light and the sphere
    assert at180[..., :3].max() > 0.05  # the panel swung to +Z in the object frame: the light gets through
    assert np.allclose(at0[..., 3], at180[..., 3], atol=0.05)
    assert r.loads <= 3  # one envmap scene + ground truth scenes: the table angle only updates parameters
