"""The simulated rig end to end: the real drivers move the real emulators over real bytes
(ptys), and the cameras render what the emulators say."""

from __future__ import annotations

import json

import numpy as np
import pytest

from opacityhull.camera import read_colmap_text, read_opencv_yaml
from opacityhull.errors import ConfigError, InputError
from opacityhull.imageio import read_exr
from opacityhull.riggeometry import RigGeometry, view_id
from opacityhull.rigs.interfaces import CameraDevice, Rig
from opacityhull.sim.evaluate import detect_corners
from opacityhull.sim.groundtruth import render_ground_truth
from opacityhull.sim.render import SimState
from opacityhull.sim.scenes import board_parts, load_scene
from opacityhull.sim.shapes import read_ply_mesh
from opacityhull.sim.simrig import open_sim_rig, parse_sim_spec, sim_rig_config

ALL = {0: 255, 1: 255, 2: 255, 3: 255}


@pytest.fixture(scope="module")
def rig():
    r = open_sim_rig("sim:builtin:diffuse", scale=0.5, seed=3)
    try:
        yield r
    finally:
        r.close()


@pytest.fixture
def safe_rig(rig):
    """The module rig, object on the table, left safe (lights off, displays blank) after each test."""
    rig.operator("remove_board")
    rig.operator("place_object")
    with rig.safe():
        yield rig


def _emu(rig, device):
    return rig.emulators.by_device[device]


def test_it_is_a_rig_with_the_real_drivers(rig):
    assert isinstance(rig, Rig)
    assert all(isinstance(c, CameraDevice) for c in rig.cameras)
    assert type(rig.turntable).__name__ == "GrblAxis"
    assert type(rig.light_array).__name__ == "DmxLightArray"
    assert type(rig.backdrops).__name__ == "DisplayController"
    for url in rig.emulators.urls.values():
        assert url.startswith("/dev/pts/")  # real ptys
    infos = rig.check()
    assert infos and all(i.ok for i in infos), infos
    d = rig.describe()
    assert d["devices"]["turntable"]["url"] == "emulator:grbl"
    assert d["sim"]["scene"] == "builtin:diffuse" and d["sim"]["seed"] == 3
    RigGeometry.from_dict(d["geometry"])  # the geometry is a valid rig geometry
    assert rig.cameras[0].info().width == 100 and rig.cameras[0].info().linear


def test_moving_the_table_rotates_the_object(safe_rig):
    rig = safe_rig
    cam = rig.cameras[2]
    rig.light_array.set_levels(ALL)
    rig.turntable.move_to(0.0)
    a0 = cam.capture(1.0)
    reached = rig.turntable.move_to(40.0)
    assert reached == pytest.approx(40.0, abs=0.02)
    assert _emu(rig, "turntable").position_deg("X") == pytest.approx(40.0, abs=0.02)
    a40 = cam.capture(1.0)
    assert cam.last_state.table_deg == pytest.approx(40.0, abs=0.02)
    # the capture is the render of the state the emulators report (same seed: same samples)
    direct = rig.renderer.render(cam.camera, SimState(table_deg=40.0, light_levels=ALL), seed=cam.last_seed)
    assert np.allclose(a40, direct, rtol=1e-4, atol=1e-7)
    assert np.abs(a40 - a0).mean() > 0.2 * a0.mean()  # the texture moved


def test_gain_and_exposure_scale_the_values(safe_rig):
    rig = safe_rig
    rig.light_array.set_levels({1: 255})
    cam = rig.cameras[1]
    a = cam.capture(0.5)
    b = cam.capture(2.0)
    assert b.sum() == pytest.approx(4.0 * a.sum(), rel=0.01)
    with pytest.raises(InputError):
        cam.capture(0.0)


def test_lights_through_dmx(safe_rig):
    rig = safe_rig
    cam = rig.cameras[3]
    rig.light_array.all_off()
    dark = cam.capture(1.0)
    assert np.all(dark == 0.0)  # no emitter on: nothing rendered at all
    rig.light_array.set_levels({2: 255})
    assert rig.state().light_levels == {0: 0, 1: 0, 2: 255, 3: 0}  # waits for the bytes to arrive
    assert _emu(rig, "light_array").levels()[2] == 255  # light 2 is DMX channel 3: universe index 2
    full = cam.capture(1.0)
    assert full.mean() > 0
    rig.light_array.set_levels({2: 128})
    half = cam.capture(1.0)
    assert half.sum() / full.sum() == pytest.approx(128 / 255, rel=0.01)  # linear in the DMX level


def test_light_array_rotation(safe_rig):
    rig = safe_rig
    cam = rig.cameras[2]
    rig.light_array.set_levels({0: 255})
    rig.light_array.rotation.move_to(0.0)
    a = cam.capture(1.0)
    rig.light_array.rotation.move_to(90.0)
    b = cam.capture(1.0)
    assert cam.last_state.array_deg == pytest.approx(90.0, abs=0.02)
    assert np.abs(a - b).mean() > 0.2 * a.mean()
    direct = rig.renderer.render(
        cam.camera,
        SimState(array_deg=90.0, light_levels={0: 255}, table_deg=cam.last_state.table_deg),
        seed=cam.last_seed,
    )
    assert np.allclose(b, direct, rtol=1e-4, atol=1e-7)
    rig.light_array.rotation.move_to(0.0)


def test_pattern_shown_appears_behind_the_object(safe_rig):
    rig = safe_rig
    cam = rig.cameras[1]
    rig.light_array.all_off()
    rig.turntable.move_to(0.0)
    for name, pid in (("back", 7), ("bottom", 9)):
        d = rig.geometry.display(name)
        pat = np.zeros((d.resolution[1], d.resolution[0], 3), np.uint8)
        pat[:, : d.resolution[0] // 2] = 255 if name == "back" else 0
        pat[:, d.resolution[0] // 2 :] = 255 if name == "bottom" else 0
        pat[: d.resolution[1] // 2] = 255  # top half white on both
        rig.backdrops.upload(name, pid, pat)
        rig.backdrops.show(name, pid)
    assert _emu(rig, "backdrops").shown(1) == 7 and _emu(rig, "backdrops").shown(0) == 9
    with_obj = cam.capture(1.0)
    rig.operator("remove_object")
    backdrop = cam.capture(1.0)
    rig.operator("place_object")
    alpha = render_ground_truth(rig.scene, RigGeometry.view_camera(cam.camera, 0.0), spp=16, renderer=rig.renderer)[
        "alpha"
    ]
    import cv2

    bg = cv2.erode((alpha == 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    fg = cv2.erode((alpha > 0.999).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert backdrop.max() > 0.9  # the white half of the pattern is seen
    # around the object: the display itself (up to anti-aliasing where the pattern's edge crosses a pixel)
    diff_bg = np.abs(with_obj - backdrop).max(axis=2)[bg]
    assert np.mean(diff_bg > 1e-6) < 0.03 and diff_bg.mean() < 2e-3
    hidden = fg & (backdrop.mean(axis=2) > 0.99)  # object pixels in front of the white half
    assert hidden.sum() > 20
    assert np.abs(with_obj - backdrop).mean(axis=2)[hidden].min() > 0.5  # the object hides it
    # the all-black pattern: no emitter, black capture
    for name in ("back", "bottom"):
        d = rig.geometry.display(name)
        rig.backdrops.upload(name, 8, np.zeros((d.resolution[1], d.resolution[0], 3), np.uint8))
        rig.backdrops.show(name, 8)
    assert np.all(cam.capture(1.0) == 0.0)
    rig.backdrops.blank()
    assert np.all(cam.capture(1.0) == 0.0)


def test_declared_phase_reaches_the_renderer(safe_rig):
    """note_phase: a declared matting shot gets the cheaper matting selection, an
    undeclared one (the default) the samples that keep the envmatte bound too."""
    from opacityhull.sim.effects import select_effects

    rig = safe_rig
    cam = rig.cameras[1]
    d = rig.geometry.display("back")
    rig.backdrops.upload("back", 5, np.full((d.resolution[1], d.resolution[0], 3), 200, np.uint8))
    rig.backdrops.show("back", 5)
    try:
        assert rig.phase is None and rig.state().phase is None
        cam.capture(1.0)
        assert cam.last_passes[0].effects.spp == select_effects(rig.scene, "matting", declared=False).spp
        rig.note_phase("matting")
        assert rig.state().phase == "matting"
        cam.capture(1.0)
        assert cam.last_passes[0].effects.spp == select_effects(rig.scene, "matting").spp < 64
        with pytest.raises(InputError, match="note_phase: phase 'mating'"):
            rig.note_phase("mating")
        assert rig.phase == "matting"  # a refused phase changes nothing
    finally:
        rig.note_phase(None)


def test_board_placed_by_the_operator_is_detected(safe_rig):
    rig = safe_rig
    spec = load_scene("builtin:charuco").parts[0].charuco
    rig.light_array.set_levels(ALL)
    rig.turntable.move_to(20.0)
    rig.operator("place_board", charuco=spec)
    cam = rig.cameras[5]
    img = cam.capture(1.0)
    assert cam.last_effects.phase == "calibration" and cam.last_state.content == "board"
    # what is lit is the board where it lies at table 20 (it turns with the table), not the object
    board = render_ground_truth(
        rig.scene, RigGeometry.view_camera(cam.camera, 20.0), spp=16, parts=board_parts(spec), renderer=rig.renderer
    )["alpha"]
    import cv2

    lit = img.mean(axis=2) > 0
    near_board = cv2.dilate((board > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert lit.sum() > 500 and np.all(near_board[lit])
    assert lit[board > 0.999].mean() > 0.9
    rig.operator("remove_board")
    assert rig.state().content == "object"
    with pytest.raises(InputError, match="operator action"):
        rig.operator("dance")
    with pytest.raises(InputError, match="CharucoSpec"):
        rig.operator("place_board", charuco="7x5")


def test_ground_truth_folder(rig, tmp_path):
    views = [(0, 0.0), (2, 30.0), (2, 30.0), (5, 355.5)]
    gt = rig.ground_truth(tmp_path, views)
    assert gt == tmp_path / "groundtruth"
    cams = dict(read_colmap_text(gt / "cameras"))
    names = [view_id(c, a) for c, a in [(0, 0.0), (2, 30.0), (5, 355.5)]]
    assert sorted(cams) == sorted(names)
    for c, a in [(0, 0.0), (2, 30.0), (5, 355.5)]:
        truth = RigGeometry.view_camera(rig.true_cameras[c], a)
        got = cams[view_id(c, a)]
        assert np.allclose(got.world_from_cam, truth.world_from_cam, atol=1e-9)
        assert np.allclose(got.K, truth.K, atol=1e-9)
        alpha = read_exr(gt / "alpha" / f"{view_id(c, a)}.exr")
        assert alpha.shape == (truth.height, truth.width, 1)
        assert 0 < alpha.sum() < alpha.size
        depth = read_exr(gt / "depth" / f"{view_id(c, a)}.exr")[..., 0]
        assert np.all(np.isnan(depth[alpha[..., 0] == 0])) and np.all(depth[alpha[..., 0] > 0.5] > 0.5)
        n = read_exr(gt / "normals" / f"{view_id(c, a)}.exr")
        assert n.shape[2] == 3
    for cam in rig.true_cameras:
        y = read_opencv_yaml(gt / "calibration" / f"{cam.name}.yaml")
        assert np.allclose(y.world_from_cam, cam.world_from_cam) and np.allclose(y.K, cam.K)
    mesh = read_ply_mesh(gt / "object.ply")
    assert mesh.signed_volume() > 0
    lights = json.loads((gt / "lights.json").read_text())
    assert [L["id"] for L in lights["lights"]] == [L.id for L in rig.geometry.lights]
    assert np.allclose(lights["lights"][0]["position_m"], rig.geometry.lights[0].position_m)
    assert load_scene(gt / "scene.toml").effect_classes == rig.scene.effect_classes
    import pycolmap

    rec = pycolmap.Reconstruction(str(gt / "cameras"))
    assert len(rec.images) == 3


def test_sensor_noise_rig():
    with open_sim_rig("sim:sphere?scale=0.3&noise=1&seed=4") as r, r.safe():
        assert r.sensor is not None
        r.light_array.set_levels({1: 255})
        cam = r.cameras[2]
        a, b = cam.capture(20.0), cam.capture(20.0)
        assert a.max() <= 1.0 and np.any(a == 1.0)  # clipped at the white level
        levels = a * 4095
        assert np.allclose(levels, np.round(levels), atol=1e-3)  # 12-bit steps
        assert np.any(a != b)  # fresh noise per capture


def test_spec_parsing_and_geometry_only_rig(tmp_path):
    assert parse_sim_spec("sim:diffuse") == ("builtin:diffuse", None, {})
    assert parse_sim_spec("sim:builtin:glass@r.toml?scale=0.5&seed=2") == (
        "builtin:glass",
        "r.toml",
        {"scale": 0.5, "seed": 2},
    )
    with pytest.raises(ConfigError, match="unknown option"):
        parse_sim_spec("sim:diffuse?colour=1")
    with pytest.raises(ConfigError):
        parse_sim_spec("diffuse")
    assert sim_rig_config(scale=0.5)["geometry"]["cameras"][0]["width"] == 100
    geo_only = tmp_path / "geo.toml"
    geo_only.write_text("""
[geometry]
target_m = [0.0, 0.08, 0.0]
[[geometry.cameras]]
name = "a"
width = 40
height = 30
distance_m = 1.0
elevation_deg = 30.0
[[geometry.lights]]
id = 5
elevation_deg = 60.0
distance_m = 1.0
[[geometry.displays]]
name = "back"
centre_m = [0.0, 0.3, -0.4]
normal = [0.0, 0.0, 1.0]
up = [0.0, 1.0, 0.0]
size_m = [1.0, 0.6]
resolution = [16, 9]
""")
    with open_sim_rig(f"sim:sphere@{geo_only}") as r, r.safe():
        assert r.config.light_array.channel_map == {5: 1}
        r.light_array.set_levels({5: 255})
        img = r.cameras[0].capture(1.0)
        assert img.shape == (30, 40, 3) and img.max() > 0
    hw = tmp_path / "hw.toml"
    hw.write_text(geo_only.read_text() + '\n[devices.turntable]\nurl = "/dev/ttyUSB0"\n')
    with pytest.raises(ConfigError, match="emulators only"):
        open_sim_rig(f"sim:sphere@{hw}")


def test_charuco_detected_from_every_camera():
    """The built-in board, lit by the array, is found by OpenCV in every camera of the
    default rig (at twice the CI resolution: 400x300)."""
    with open_sim_rig("sim:charuco?scale=2") as r, r.safe():
        spec = r.scene.parts[0].charuco
        r.operator("place_board", charuco=spec)
        r.light_array.set_levels(ALL)
        r.turntable.move_to(0.0)
        found = [len(detect_corners(c.capture(1.0), spec)) for c in r.cameras]
    assert all(n >= 4 for n in found), found
