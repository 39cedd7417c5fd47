"""Rig geometry parsing and frames; the model format round trip; the ChArUco board."""

import math

import numpy as np
import pytest

from opacityhull.camera import rig_from_object
from opacityhull.charuco import CharucoSpec
from opacityhull.errors import ConfigError, FormatError, InputError, ShapeError
from opacityhull.model import (
    LightSample,
    OpacityHullModel,
    Surfels,
    ViewInfo,
    light_key,
    read_surfels_ply,
    write_model,
    write_surfels_ply,
)
from opacityhull.riggeometry import RigGeometry, back_display, bottom_display, parse_view_id, view_id

GEOM = {
    "target_m": [0.0, 0.08, 0.0],
    "cameras": [
        {"name": "cam0", "width": 64, "height": 48, "distance_m": 1.0, "elevation_deg": 0.0, "fov_y_deg": 20.0},
        {"name": "cam1", "width": 64, "height": 48, "distance_m": 1.0, "elevation_deg": 60.0, "fov_y_deg": 20.0},
    ],
    "lights": [{"id": i, "elevation_deg": 40.0 + 10 * i, "azimuth_deg": 0.0, "distance_m": 1.2} for i in range(4)],
    "displays": [bottom_display([0.6, 0.6], [32, 32]), back_display([0, 0.2, -0.35], [0.8, 0.45], [64, 36])],
}


def test_nominal_cameras_aim_at_target():
    g = RigGeometry.from_dict(GEOM)
    for cam, spec in zip(g.nominal_cameras(), g.cameras, strict=True):
        uv, z = cam.project(np.array([g.target_m]))
        np.testing.assert_allclose(uv[0], [(cam.width - 1) / 2, (cam.height - 1) / 2], atol=1e-9)
        assert z[0] == pytest.approx(spec.distance_m)
    # camera 1 at 60 deg elevation looks down
    assert g.nominal_cameras()[1].forward_world[1] == pytest.approx(-math.sin(math.radians(60)))


def test_view_camera_sees_rotated_object_like_rig_camera():
    g = RigGeometry.from_dict(GEOM)
    cam = g.nominal_cameras()[0]
    p_obj = np.array([[0.03, 0.1, -0.02]])
    for a in (0.0, 45.0, 190.0):
        vc = g.view_camera(cam, a)
        p_rig = (rig_from_object(a) @ np.append(p_obj[0], 1.0))[:3]
        np.testing.assert_allclose(vc.project(p_obj)[0], cam.project(p_rig[None])[0], atol=1e-9)


def test_light_direction_rotates_with_array_minus_table():
    g = RigGeometry.from_dict(GEOM)
    d1 = g.light_direction_object(0, table_deg=30.0, array_deg=50.0)
    d2 = g.light_direction_object(0, table_deg=0.0, array_deg=20.0)
    np.testing.assert_allclose(d1, d2, atol=1e-12)  # only b - a matters
    assert np.linalg.norm(d1) == pytest.approx(1.0)


def test_display_corners_rotate_with_table_only_if_asked():
    g = RigGeometry.from_dict(GEOM)
    bottom, back = g.display("bottom"), g.display("back")
    np.testing.assert_allclose(back.corners_rig(90.0), back.corners_rig(0.0))
    c0, c90 = bottom.corners_rig(0.0), bottom.corners_rig(90.0)
    assert not np.allclose(c0, c90)
    np.testing.assert_allclose(np.linalg.norm(c0, axis=1), np.linalg.norm(c90, axis=1))
    # back panel: top-left corner is up and to the left as seen from +Z
    tl = back.corners_rig()[0]
    assert tl[0] < 0 and tl[1] > 0.2


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda g: g["cameras"][0].pop("distance_m"), r"cameras\[0\]: missing key 'distance_m'"),
        (lambda g: g["cameras"][1].update(name="cam0"), "duplicate camera name"),
        (lambda g: g["cameras"][0].update(zoom=2), r"unknown key\(s\) \['zoom'\]"),
        (lambda g: g["lights"][1].update(id=0), "duplicate light id"),
        (lambda g: g["displays"][0].update(up=[0, 2, 0]), "must not be parallel"),
        (lambda g: g["cameras"][0].update(width=-3), "must be > 0"),
        (lambda g: g.update(cameras=[]), "at least one"),
    ],
)
def test_geometry_errors_name_the_key(mutate, message):
    import copy

    g = copy.deepcopy(GEOM)
    mutate(g)
    with pytest.raises(ConfigError, match=message):
        RigGeometry.from_dict(g)


def test_view_id_roundtrip():
    assert view_id(3, 30.0) == "c3_t030.000"
    assert view_id(0, -5.0) == "c0_t355.000"
    assert parse_view_id("c3_t030.000") == (3, 30.0)
    with pytest.raises(ConfigError):
        parse_view_id("cam3")


def _surfels(n=50, v=11, seed=0):
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return Surfels.from_bool(rng.normal(size=(n, 3)), nrm, rng.uniform(0.001, 0.01, n), rng.random((n, v)) > 0.4)


def test_surfels_ply_roundtrip_keeps_visibility_bits(tmp_path):
    s = _surfels()
    write_surfels_ply(tmp_path / "s.ply", s)
    b = read_surfels_ply(tmp_path / "s.ply")
    assert b.n_views == 11
    np.testing.assert_array_equal(b.visible_bool(), s.visible_bool())
    np.testing.assert_allclose(b.positions, s.positions)
    for v in range(11):
        np.testing.assert_array_equal(b.visible_in(v), s.visible_bool()[:, v])
    with pytest.raises(ShapeError):
        Surfels(s.positions, s.normals[:3], s.radii, s.visibility, 11)


def test_model_roundtrip(tmp_path):
    g = RigGeometry.from_dict(GEOM)
    cams = g.nominal_cameras()
    views = [
        ViewInfo(i, view_id(c, a), c, a, g.view_camera(cams[c], a, view_id(c, a)))
        for i, (c, a) in enumerate([(0, 0.0), (1, 0.0), (0, 90.0)])
    ]
    rng = np.random.default_rng(3)
    rgba = [rng.random((48, 64, 4)).astype(np.float32) for _ in views]
    lights = [LightSample(light_key(lt, b), lt, b) for lt in range(2) for b in (0.0, 22.5)]
    refl = {i: {L.key: rng.random((48, 64, 3)).astype(np.float32) for L in lights} for i in range(3)}
    s = _surfels(v=3)
    write_model(
        tmp_path / "m",
        views=views,
        surfels=s,
        view_rgba=rgba,
        rig=g.to_dict(),
        provenance={"session": "x"},
        reflectance={"lights": lights, "images": lambda i: refl[i]},
    )
    m = OpacityHullModel.open(tmp_path / "m")
    assert [v.id for v in m.views] == [v.id for v in views]
    for v, w in zip(m.views, views, strict=True):
        np.testing.assert_allclose(v.camera.world_from_cam, w.camera.world_from_cam, atol=1e-9)
        np.testing.assert_allclose(v.camera.K, w.camera.K, atol=1e-9)
    # format 2 stores premultiplied colour: straight colour comes back to float rounding
    back = m.load_view_rgba(2)
    np.testing.assert_array_equal(back[..., 3], rgba[2][..., 3])
    # ... above the one straight-colour cut-off (imageio.ALPHA_CUTOFF, 2^-12); 0 below it
    from opacityhull.imageio import ALPHA_CUTOFF

    seen = rgba[2][..., 3] >= ALPHA_CUTOFF
    assert (~seen).any()  # the random alphas reach below it
    np.testing.assert_allclose(back[..., :3][seen], rgba[2][..., :3][seen], rtol=1e-6, atol=0)
    assert np.all(back[..., :3][~seen] == 0)
    premul = m.load_views_premul([1])[0]
    np.testing.assert_array_equal(premul[..., :3], rgba[1][..., :3] * rgba[1][..., 3:])
    assert m.has_reflectance and [L.key for L in m.light_samples] == [L.key for L in lights]
    np.testing.assert_array_equal(m.load_reflectance(0)[lights[3].key], refl[0][lights[3].key])
    np.testing.assert_allclose(m.light_direction(2, lights[1]), g.light_direction_object(0, 90.0, 22.5))
    assert m.find_view(0, 90.0) == 2 and m.view_index("c1_t000.000") == 1
    with pytest.raises(InputError):
        m.find_view(5, 0.0)


def _small_model(tmp_path, *, alpha_zero_corner=True):
    g = RigGeometry.from_dict(GEOM)
    cams = g.nominal_cameras()
    views = [
        ViewInfo(i, view_id(c, a), c, a, g.view_camera(cams[c], a, view_id(c, a)))
        for i, (c, a) in enumerate([(0, 0.0), (1, 135.0)])
    ]
    rng = np.random.default_rng(5)
    rgba = [rng.random((48, 64, 4)).astype(np.float32) for _ in views]
    if alpha_zero_corner:
        for a in rgba:
            a[:4, :4, 3] = 0.0  # straight colour there is undefined
    lights = [LightSample(light_key(lt, b), lt, b) for lt in (1, 3) for b in (0.0, 40.0)]
    refl = {i: {L.key: rng.random((48, 64, 3)).astype(np.float32) for L in lights} for i in range(2)}
    write_model(
        tmp_path / "m",
        views=views,
        surfels=_surfels(v=2),
        view_rgba=rgba,
        rig=g.to_dict(),
        reflectance={"lights": lights, "images": lambda i: refl[i]},
    )
    return tmp_path / "m", g, views, rgba, lights


def test_view_exr_is_premultiplied_with_chromaticities_read_by_openexr(tmp_path):
    """The file itself, read with the OpenEXR package (not our reader): premultiplied
    colour, alpha unchanged, Rec.709/D65 chromaticities."""
    import OpenEXR

    root, _, views, rgba, _ = _small_model(tmp_path)
    with OpenEXR.File(str(root / "views" / f"{views[1].id}.exr"), separate_channels=True) as f:
        ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
        chroma = f.header()["chromaticities"]
    assert sorted(ch) == ["A", "B", "G", "R"] and ch["R"].dtype == np.float32
    a = rgba[1]
    np.testing.assert_array_equal(ch["A"], a[..., 3])
    for i, c in enumerate("RGB"):
        np.testing.assert_array_equal(ch[c], a[..., i] * a[..., 3])
    assert np.all(ch["R"][:4, :4] == 0)
    np.testing.assert_allclose(chroma, [0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290], atol=1e-7)
    # our reader gives straight colour back, 0 where alpha is 0
    m = OpacityHullModel.open(root)
    assert m.format == "opacityhull-model/2" and m.views_premultiplied
    s = m.load_view_rgba(1)
    assert np.all(s[:4, :4] == 0)
    from opacityhull.imageio import ALPHA_CUTOFF  # below the one cut-off: no colour

    seen = a[4:, 4:, 3] >= ALPHA_CUTOFF
    np.testing.assert_allclose(s[4:, 4:][seen], a[4:, 4:][seen], rtol=2e-6)
    assert np.all(s[4:, 4:, :3][~seen] == 0)


def test_reflectance_layers_carry_their_light(tmp_path):
    import OpenEXR

    root, g, views, _, lights = _small_model(tmp_path)
    m = OpacityHullModel.open(root)
    with OpenEXR.File(str(root / "reflectance" / f"{views[1].id}.exr"), header_only=True) as f:
        h = dict(f.header())  # the package empties its header dict when the file closes
    assert h["view"] == views[1].id and h["tableAngleDeg"] == pytest.approx(135.0)
    assert len(h["chromaticities"]) == 8
    for L in lights:
        d = np.asarray(h[f"{L.key}.lightDirection"])
        assert d.dtype == np.float32 and d.shape == (3,)
        # the direction relight uses for this view (table 135 deg): object frame, b - a matters
        np.testing.assert_allclose(d, m.light_direction(1, L), atol=1e-6)
        np.testing.assert_allclose(d, g.light_direction_object(L.light_id, 0.0, L.array_deg - 135.0), atol=1e-6)
        np.testing.assert_allclose(
            np.asarray(h[f"{L.key}.lightPosition"]), g.light_position_object(L.light_id, 135.0, L.array_deg), atol=1e-6
        )
        assert h[f"{L.key}.lightId"] == L.light_id and h[f"{L.key}.arrayAngleDeg"] == L.array_deg
        assert h[f"{L.key}.lightIntensity"] == pytest.approx(1.0)
    meta = m.reflectance_metadata(0)
    L = lights[3]
    assert meta[L.key]["light_id"] == 3 and meta[L.key]["array_deg"] == 40.0
    np.testing.assert_allclose(meta[L.key]["direction"], m.light_direction(0, L), atol=1e-6)
    np.testing.assert_allclose(meta[L.key]["output_rgb"], [1.0, 1.0, 1.0])


def test_format_1_model_still_opens_with_straight_views(tmp_path):
    """A model written before format 2 (straight colour in views/) reads as before."""
    import tomllib

    from opacityhull.imageio import write_exr
    from opacityhull.tomlio import toml_dumps

    root, _, views, rgba, _ = _small_model(tmp_path)
    meta = tomllib.loads((root / "model.toml").read_text())
    meta["model"]["format"] = "opacityhull-model/1"
    (root / "model.toml").write_text(toml_dumps(meta))
    for v, a in zip(views, rgba, strict=True):
        write_exr(root / "views" / f"{v.id}.exr", a)  # straight, as format 1 wrote them
    m = OpacityHullModel.open(root)
    assert not m.views_premultiplied
    np.testing.assert_array_equal(m.load_view_rgba(0), rgba[0])  # exactly, straight colour at alpha 0 kept
    np.testing.assert_array_equal(m.load_views_premul([0])[0][..., :3], rgba[0][..., :3] * rgba[0][..., 3:])


def test_model_missing_light_named(tmp_path):
    g = RigGeometry.from_dict(GEOM)
    cam = g.view_camera(g.nominal_cameras()[0], 0.0, "c0_t000.000")
    lights = [LightSample(light_key(0, 0.0), 0, 0.0)]
    write_model(
        tmp_path / "m",
        views=[ViewInfo(0, "c0_t000.000", 0, 0.0, cam)],
        surfels=_surfels(v=1),
        rig=g.to_dict(),
        reflectance={"lights": lights, "images": lambda i: {lights[0].key: np.zeros((48, 64, 3), np.float32)}},
    )
    import tomllib

    from opacityhull.tomlio import toml_dumps

    meta = tomllib.loads((tmp_path / "m" / "model.toml").read_text())
    meta["reflectance"]["lights"].append({"key": light_key(1, 15.0), "light_id": 1, "array_deg": 15.0})
    (tmp_path / "m" / "model.toml").write_text(toml_dumps(meta))
    with pytest.raises(FormatError, match=r"a015p000_l1 \(light 1 at array 15.0 deg\) missing"):
        OpacityHullModel.open(tmp_path / "m").load_reflectance(0)


def test_model_open_errors(tmp_path):
    with pytest.raises(FormatError, match="model.toml not found"):
        OpacityHullModel.open(tmp_path)
    (tmp_path / "model.toml").write_text('[model]\nformat = "other/9"\n')
    with pytest.raises(FormatError, match="'other/9', expected one of 'opacityhull-model/1', 'opacityhull-model/2'"):
        OpacityHullModel.open(tmp_path)


def test_charuco_board_placement_and_detection():
    import cv2

    spec = CharucoSpec()
    T = spec.object_from_board()
    w, h = spec.size_m
    # the board centre sits at the table centre, its normal (board z) points down into the table
    np.testing.assert_allclose((T @ [w / 2, h / 2, 0, 1])[:3], [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0, -1, 0])
    img = spec.image(px_per_square=60)
    img = cv2.copyMakeBorder(img, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(spec.board()).detectBoard(img)
    assert ids is not None and len(ids) == (spec.squares_x - 1) * (spec.squares_y - 1)
    with pytest.raises(ConfigError, match="marker_m"):
        CharucoSpec(marker_m=0.05)
    with pytest.raises(ConfigError, match="unknown key"):
        CharucoSpec.from_dict({"squares": 3})
