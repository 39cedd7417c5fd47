"""Rendering the rig: camera model, table rotation, displays, lights, hard cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from opacityhull.camera import Camera, look_at_world_from_cam, rig_from_object
from opacityhull.riggeometry import CameraSpec, RigGeometry
from opacityhull.sim.commands import make_pattern
from opacityhull.sim.groundtruth import render_ground_truth
from opacityhull.sim.mitsuba_sensor import sensor_dict
from opacityhull.sim.render import SimRenderer, SimState
from opacityhull.sim.scenes import builtin_names, load_scene
from opacityhull.sim.variants import use_mitsuba

from conftest import conic_area_centre, oracle_coverage, sphere_conic


def _spec_with_half_fov(name: str, width: int, height: int, *, half_fov_y_deg: float, **pose) -> CameraSpec:
    """A :class:`CameraSpec` of ``width`` x ``height`` px whose vertical half field of
    view is ``half_fov_y_deg``; ``pose`` is ``distance_m``, ``elevation_deg``, ``azimuth_deg``."""
    focal_px = height / (2 * math.tan(math.radians(half_fov_y_deg)))
    return CameraSpec(name=name, width=width, height=height, focal_px=focal_px, **pose)


def _off_centre_camera(eye=(0.25, 0.45, 0.85), target=(0.0, 0.08, 0.0)) -> Camera:
    K = np.array([[118.0, 0.0, 43.2], [0.0, 118.0, 31.7], [0.0, 0.0, 1.0]])
    return Camera(K=K, width=96, height=72, world_from_cam=look_at_world_from_cam(eye, target), name="odd")


def test_sensor_rays_project_back_to_their_pixels():
    """Mitsuba's sensor built from camera.py (and re-posed through params.update) shoots
    rays that camera.py projects to the pixel they came from: < 0.05 px."""
    mi = use_mitsuba()
    cam = _off_centre_camera()
    uv = np.array([[0, 0], [95, 71], [43.2, 31.7], [10.25, 60.75], [80, 5]], dtype=np.float64)

    def check(sensor, c):
        o, d = [], []
        for p in uv:  # one ray per call works in every variant (scalar and JIT)
            film_xy = mi.Point2f(float((p[0] + 0.5) / c.width), float((p[1] + 0.5) / c.height))
            ray, _ = sensor.sample_ray(0.0, 0.5, film_xy, mi.Point2f(0.5, 0.5))
            o.append(np.array(ray.o, dtype=np.float64).ravel())
            d.append(np.array(ray.d, dtype=np.float64).ravel())
        o, d = np.array(o), np.array(d)
        proj, z = c.project(o + 0.7 * d)
        assert np.all(z > 0)
        assert np.max(np.abs(proj - uv)) < 0.05

    scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(mi, cam, sampler="independent", spp=1)})
    check(scene.sensors()[0], cam)
    # the capture path re-poses a loaded sensor: change pose and field of view through params
    r = SimRenderer(load_scene("builtin:sphere"), None)
    from opacityhull.sim.render import _Loaded

    loaded = _Loaded(scene, mi.traverse(scene), {})
    cam2 = Camera(
        K=np.array([[140.0, 0, 50.9], [0, 140.0, 30.2], [0, 0, 1]]),
        width=96,
        height=72,
        world_from_cam=look_at_world_from_cam((-0.4, 0.6, 0.5), (0.02, 0.1, -0.01)),
    )
    r._set_sensor(loaded, "sensor", cam2)
    loaded.params.update()
    check(scene.sensors()[0], cam2)


@pytest.fixture(scope="module")
def sphere_renderer(small_geometry):
    return SimRenderer(load_scene("builtin:sphere"), small_geometry)


def test_rendered_sphere_silhouette_matches_camera_py(sphere_renderer):
    """Image-level check of the whole camera model (off-centre principal point): the
    coverage centroid equals the analytic silhouette centre to < 0.05 px."""
    cam = _off_centre_camera()
    gt = render_ground_truth(sphere_renderer.scene, cam, spp=256, renderer=sphere_renderer)
    Q = sphere_conic(cam, (0, 0.08, 0), 0.08)
    area, centre = conic_area_centre(Q)
    a = gt["alpha"].astype(np.float64)
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    c_img = np.array([(a * u).sum(), (a * v).sum()]) / a.sum()
    assert a.sum() == pytest.approx(area, rel=3e-3)
    # the centroid of the silhouette region is not the projection of the sphere centre;
    # compare like with like: the oracle's coverage centroid
    o = oracle_coverage(Q, cam.width, cam.height, n=32)
    c_or = np.array([(o * u).sum(), (o * v).sum()]) / o.sum()
    assert np.linalg.norm(c_img - c_or) < 0.05
    assert np.linalg.norm(c_or - centre) < 0.05  # and the region's centroid is the ellipse centre


def test_table_rotation_turns_the_object_about_plus_y(small_geometry, tmp_path):
    """An off-axis sphere at table angle a appears where camera.py projects
    rig_from_object(a) @ centre, seen by the fixed rig camera."""
    p = tmp_path / "offaxis.toml"
    p.write_text(
        '[materials.m]\ntype = "diffuse"\n[[objects]]\nshape = "sphere"\nmaterial = "m"\n'
        "radius_m = 0.03\ncentre_m = [0.06, 0.03, 0.0]\n"
    )
    scene = load_scene(p)
    r = SimRenderer(scene, small_geometry)
    cam = small_geometry.nominal_cameras()[2]
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    for a in (0.0, 70.0, 200.0):
        view = RigGeometry.view_camera(cam, a)
        alpha = render_ground_truth(scene, view, spp=64, renderer=r)["alpha"].astype(np.float64)
        c_rig = (rig_from_object(a) @ np.array([0.06, 0.03, 0.0, 1.0]))[:3]
        o = oracle_coverage(sphere_conic(cam, c_rig, 0.03), cam.width, cam.height, n=8)
        c_img = np.array([(alpha * u).sum(), (alpha * v).sum()]) / alpha.sum()
        c_or = np.array([(o * u).sum(), (o * v).sum()]) / o.sum()
        assert np.linalg.norm(c_img - c_or) < 0.1, f"table {a}"


def test_camera_looking_straight_down_the_table_axis(sphere_renderer):
    """Elevation 90: the look-at picks a deterministic 'up'; the render and the analytic
    silhouette agree, and a capture renders finite values."""
    spec = CameraSpec(
        name="top", width=80, height=60, distance_m=1.0, elevation_deg=90.0, azimuth_deg=0.0, focal_px=150.0
    )
    cam = spec.nominal_camera(np.array([0.0, 0.08, 0.0]))
    assert np.allclose(cam.forward_world, [0, -1, 0], atol=1e-9)
    gt = render_ground_truth(sphere_renderer.scene, cam, spp=64, renderer=sphere_renderer)
    area, centre = conic_area_centre(sphere_conic(cam, (0, 0.08, 0), 0.08))
    a = gt["alpha"].astype(np.float64)
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    assert a.sum() == pytest.approx(area, rel=5e-3)
    assert np.linalg.norm(np.array([(a * u).sum(), (a * v).sum()]) / a.sum() - centre) < 0.05
    img = sphere_renderer.render(cam, SimState(table_deg=33.0, light_levels={3: 255}))
    assert np.all(np.isfinite(img)) and img.max() > 0


def _geometry_without_displays(light_position) -> RigGeometry:
    return RigGeometry.from_dict(
        {
            "target_m": [0.0, 0.08, 0.0],
            "cameras": [
                {
                    "name": "c",
                    "width": 64,
                    "height": 48,
                    "distance_m": 0.8,
                    "elevation_deg": 20.0,
                    "azimuth_deg": 30.0,
                    "fov_y_deg": 24.0,
                }
            ],
            "lights": [{"id": 0, "position_m": list(map(float, light_position))}],
        }
    )


def test_light_exactly_behind_the_object_leaves_the_visible_side_black(sphere_scene):
    spec = _spec_with_half_fov("c", 64, 48, half_fov_y_deg=12, distance_m=0.8, elevation_deg=20.0, azimuth_deg=30.0)
    target = np.array([0.0, 0.08, 0.0])
    cam = spec.nominal_camera(target)
    behind = target + (target - cam.centre_world) * 1.5  # on the camera's optical axis, behind the sphere
    g = _geometry_without_displays(behind)
    img = SimRenderer(sphere_scene, g).render(g.nominal_cameras()[0], SimState(light_levels={0: 255}))
    assert np.all(np.isfinite(img))
    assert img.max() == 0.0  # the lit cap and the visible cap of a sphere are disjoint
    # the same light moved 100 degrees round the table lights part of the visible side
    side = (rig_from_object(100.0)[:3, :3] @ (behind - target)) + target
    g2 = _geometry_without_displays(side)
    img2 = SimRenderer(sphere_scene, g2).render(g2.nominal_cameras()[0], SimState(light_levels={0: 255}))
    assert img2.max() > 0.01


def test_all_black_pattern_costs_nothing_and_renders_black(small_geometry):
    r = SimRenderer(load_scene("builtin:diffuse"), small_geometry)
    black = {d.name: np.zeros((d.resolution[1], d.resolution[0], 3), np.uint8) for d in small_geometry.displays}
    img = r.render(small_geometry.nominal_cameras()[1], SimState(displays=black))
    assert img.shape == (75, 100, 3) and np.all(img == 0.0)
    assert r.loads == 0 and r.renders == 0  # no emitter: no Mitsuba scene at all
    img = r.render(small_geometry.nominal_cameras()[1], SimState(light_levels={0: 0, 1: 0}))
    assert np.all(img == 0.0) and r.loads == 0


def _inside_polygon(points_uv: np.ndarray, poly: np.ndarray) -> np.ndarray:
    import cv2

    c = poly.astype(np.float32).reshape(-1, 1, 2)
    return np.array([cv2.pointPolygonTest(c, (float(x), float(y)), True) for x, y in points_uv])


@pytest.mark.parametrize("display,table_deg,camera", [("back", 30.0, 1), ("bottom", 30.0, 4), ("bottom", 200.0, 5)])
def test_pattern_row0_is_up_and_col0_left_on_the_panel(small_geometry, display, table_deg, camera):
    """The bottom-left quadrant of a pattern (rows h/2.., columns ..w/2) lights the
    bottom-left quadrant of the panel as seen from its emitting side (row 0 towards the
    panel's ``up``, column 0 on the left), wherever the table is."""
    d = small_geometry.display(display)
    w, h = d.resolution
    pat = np.zeros((h, w, 3), np.uint8)
    pat[h // 2 :, : w // 2] = 255
    r = SimRenderer(load_scene("builtin:sphere"), small_geometry)
    cam = small_geometry.nominal_cameras()[camera]
    img = r.render(cam, SimState(table_deg=table_deg, displays={display: pat}, content="none"))
    # quadrant corners in the panel frame (x right, y up), then into the rig frame
    W, H = d.size_m
    local = np.array([[-W / 2, 0, 0, 1], [0, 0, 0, 1], [0, -H / 2, 0, 1], [-W / 2, -H / 2, 0, 1]])
    P = (d.frame() @ local.T).T[:, :3]
    if d.rotates_with_table:
        P = P @ rig_from_object(table_deg)[:3, :3].T
    poly, _ = cam.project(P)
    bright = np.argwhere(img.mean(axis=2) > 0.5)[:, ::-1].astype(np.float64)
    assert bright.shape[0] > 50
    dist = _inside_polygon(bright, poly)
    assert np.mean(dist >= -1.0) > 0.99, "lit pixels outside the bottom-left quadrant"
    # and the quadrant's interior (away from its edges and inside the image) is lit
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    pts = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    inside = _inside_polygon(pts, poly).reshape(cam.height, cam.width) > 1.5
    assert inside.sum() > 20
    assert np.all(img.mean(axis=2)[inside] > 0.5)


def test_display_radiance_is_linear_in_the_pattern(small_geometry):
    r = SimRenderer(load_scene("builtin:sphere"), small_geometry)
    cam = small_geometry.nominal_cameras()[1]
    d = small_geometry.display("back")
    full = np.full((d.resolution[1], d.resolution[0], 3), 255, np.uint8)
    half = np.full_like(full, 51)
    a = r.render(cam, SimState(displays={"back": full}, content="none"))
    b = r.render(cam, SimState(displays={"back": half}, content="none"))
    lit = a.mean(axis=2) > 0.99 * d.max_radiance
    assert lit.sum() > 100
    assert np.allclose(b[lit], 51 / 255 * d.max_radiance, rtol=1e-4)


def test_light_intensity_gives_unit_irradiance_at_the_origin():
    """A light of intensity 1 at any distance gives irradiance 1 at the rig origin: a
    white Lambertian disc there (facing the light) has radiance 1/pi."""
    for dist in (0.5, 2.0):
        g = RigGeometry.from_dict(
            {
                "target_m": [0.0, 0.0, 0.0],
                "cameras": [
                    {
                        "name": "c",
                        "width": 16,
                        "height": 12,
                        "distance_m": 1.0,
                        "elevation_deg": 90.0,
                        "azimuth_deg": 0.0,
                        "fov_y_deg": 2.0,
                    }
                ],
                "lights": [{"id": 0, "position_m": [0.0, dist, 0.0], "intensity": 1.0}],
            }
        )
        import tempfile
        from pathlib import Path

        with tempfile.TemporaryDirectory() as td:
            p = Path(td) / "disc.toml"
            p.write_text(
                '[materials.w]\ntype = "diffuse"\nreflectance = 1.0\n[[objects]]\nshape = "disk"\n'
                'material = "w"\nradius_m = 0.2\n'
            )
            scene = load_scene(p)
        cam = g.nominal_cameras()[0]
        img = SimRenderer(scene, g).render(cam, SimState(light_levels={0: 255}))
        # analytic: the pixel's ray meets the table plane at distance rho from the axis, where
        # the irradiance is cos^3 of the angle to the light: d^3 / (d^2 + rho^2)^1.5
        o, dirs = cam.pixel_rays()
        t = -o[1] / dirs[..., 1]
        hit = o + t[..., None] * dirs
        rho2 = hit[..., 0] ** 2 + hit[..., 2] ** 2
        expect = dist**3 / (dist**2 + rho2) ** 1.5 / math.pi
        assert np.allclose(img[..., 0], expect, rtol=5e-4)
        half = SimRenderer(scene, g).render(g.nominal_cameras()[0], SimState(light_levels={0: 51}))
        assert np.allclose(half, 0.2 * img, rtol=1e-5)


def test_object_larger_than_the_displays(small_geometry, tmp_path):
    p = tmp_path / "huge.toml"
    p.write_text(
        '[materials.m]\ntype = "diffuse"\nreflectance = 0.5\n[[objects]]\nshape = "sphere"\nmaterial = "m"\n'
        "radius_m = 0.6\ncentre_m = [0.0, 0.6, 0.0]\n"
    )
    scene = load_scene(p)
    r = SimRenderer(scene, small_geometry, overrides={"spp": 16})
    # a wide camera, far back: sees the whole 1.2 m sphere and the edges of both panels
    spec = _spec_with_half_fov("wide", 96, 72, half_fov_y_deg=35, distance_m=2.5, elevation_deg=15.0, azimuth_deg=20.0)
    cam = spec.nominal_camera(np.array([0.0, 0.5, 0.0]))
    white = {d.name: make_pattern("white", *d.resolution) for d in small_geometry.displays}
    img = r.render(cam, SimState(displays=white))
    back_only = r.render(cam, SimState(displays=white, content="none"))
    alpha = render_ground_truth(scene, cam, spp=16, renderer=r)["alpha"]
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    covered = alpha > 0.999
    behind = back_only.mean(axis=2)
    assert covered.mean() > 0.05
    assert np.any(covered & (behind == 0.0)), "the object should stick out beyond the displays"
    assert np.any(covered & (behind > 0.5))
    assert np.all(img[covered] < 0.99 * behind.max())  # covered pixels show the object, not the display


def test_spp_one_renders(small_geometry):
    for name in ("diffuse", "glass"):
        r = SimRenderer(load_scene(f"builtin:{name}"), small_geometry, overrides={"spp": 1})
        st = SimState(
            table_deg=10.0,
            light_levels={0: 255, 2: 255},
            displays={d.name: make_pattern("checker", *d.resolution) for d in small_geometry.displays},
        )
        cfg = r.effects_for(st)
        assert cfg.spp == 1
        img = r.render(small_geometry.nominal_cameras()[2], st, effects=cfg)
        assert img.shape == (75, 100, 3) and np.all(np.isfinite(img)) and img.mean() > 0.01


@pytest.mark.parametrize("name", sorted(builtin_names()))
def test_every_builtin_renders_from_every_camera(small_geometry, name):
    scene = load_scene(f"builtin:{name}")
    r = SimRenderer(scene, small_geometry, overrides={"spp": 4})
    pats = {d.name: make_pattern("random", *d.resolution, seed=2) for d in small_geometry.displays}
    for i, cam in enumerate(small_geometry.nominal_cameras()):
        st = SimState(
            table_deg=15.0 * i, light_levels={1: 255}, displays=pats, content="board" if name == "charuco" else "object"
        )
        img = r.render(cam, st)
        assert img.shape == (cam.height, cam.width, 3)
        assert np.all(np.isfinite(img)) and np.all(img >= 0)
        parts = r._content_parts(st)
        alpha = render_ground_truth(scene, RigGeometry.view_camera(cam, st.table_deg), spp=4, renderer=r, parts=parts)[
            "alpha"
        ]
        assert alpha.sum() > 20, f"{name} not visible from {cam.name}"
        assert img.mean(axis=2)[alpha > 0.99].mean() > 0.0
