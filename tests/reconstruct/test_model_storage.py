"""The model's view RGBA and reflectance in half or float32 pixels (issue 14, item 1):
the pixel type on disk, what half costs (rendering, relighting inputs), the bytes it
saves, values beyond the half range, and the build's ``--storage`` flag and report."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from helpers import invoke_cli
from opacityhull.errors import ConfigError, FormatError, InputError
from opacityhull.imageio import HalfOverflowWarning
from opacityhull.model import OpacityHullModel, Storage, ViewInfo, copy_model, write_model

# half rounds to nearest with 10 fraction bits: |error| <= 2**-11 |x| for normal numbers,
# <= 2**-25 below 2**-14 (subnormals)
HALF_REL = 2.0**-11
HALF_ABS = 2.0**-25


def _copy(m: OpacityHullModel, dst: Path, storage: Storage) -> OpacityHullModel:
    """``m`` written again in ``storage``: both copies of a pair come from the same arrays
    and differ only in the pixel type."""
    return copy_model(m, dst, storage=storage)


@pytest.fixture(scope="module")
def relit_pair(tmp_path_factory):
    """The analytic Lambertian sphere with one-light images (8 views, 20 light samples),
    as a float and a half model."""
    from opacityhull.relight.synthetic import write_sphere_model

    tmp = tmp_path_factory.mktemp("storage")
    src = OpacityHullModel.open(write_sphere_model(tmp / "src", width=32, height=24, n_positions=5))
    return {st: _copy(src, tmp / st, st) for st in ("float", "half")}


def _pixel_types(path: Path) -> set:
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {c.type() for c in f.channels().values()}


@pytest.mark.parametrize("storage, pixel", [("half", OpenEXR.HALF), ("float", OpenEXR.FLOAT)])
def test_every_view_and_reflectance_channel_has_the_requested_pixel_type(relit_pair, storage, pixel):
    m = relit_pair[storage]
    assert m.storage == storage
    meta = tomllib.loads((m.root / "model.toml").read_text())
    assert meta["storage"]["pixel_type"] == storage and meta["storage"]["clamped_values"] == 0
    files = [m.view_path(i) for i in range(len(m.views))]
    files += [m.root / "reflectance" / f"{v.id}.exr" for v in m.views]
    assert len(files) == 16
    for p in files:
        assert _pixel_types(p) == {pixel}, p


def test_half_reflectance_is_the_float_value_rounded_to_half(relit_pair):
    f, h = relit_pair["float"], relit_pair["half"]
    for i in range(len(f.views)):
        a, b = f.load_reflectance(i), h.load_reflectance(i)
        assert set(a) == set(b) and len(a) == 20
        for k in a:
            assert b[k].dtype == np.float32
            # numpy's own float16 rounding is the oracle
            np.testing.assert_array_equal(b[k], a[k].astype(np.float16).astype(np.float32))
            assert np.all(np.abs(b[k] - a[k]) <= HALF_REL * np.abs(a[k]) + HALF_ABS)
        # the light attributes are the same header values in both
        ma, mb = f.reflectance_metadata(i), h.reflectance_metadata(i)
        for k in ma:
            np.testing.assert_array_equal(ma[k]["direction"], mb[k]["direction"])
    # and half did round something: the pair is not trivially equal
    a, b = f.load_reflectance(0), h.load_reflectance(0)
    assert any(np.any(a[k] != b[k]) for k in a)


def test_half_relights_like_float(relit_pair):
    from opacityhull.relight.envmap import sun_envmap
    from opacityhull.relight.relit import Relighter

    env = sun_envmap(16, 32, [0.3, 0.8, 0.5], [2.0, 1.8, 1.5], background=0.05)
    rf, rh = Relighter(relit_pair["float"]), Relighter(relit_pair["half"])
    for i in (0, 5):
        a, b = rf.relight_view(i, envmap=env), rh.relight_view(i, envmap=env)
        m = a[..., 3] > 0.5
        rel = np.linalg.norm(b[..., :3][m] - a[..., :3][m]) / np.linalg.norm(a[..., :3][m])
        # a weighted sum of values each within 2**-11: the same bound holds for the sum
        assert 0 < rel < HALF_REL, rel
        np.testing.assert_allclose(b[..., 3], a[..., 3], atol=1e-3)


def test_half_takes_about_half_the_bytes_per_view(relit_pair):
    def per_view(m, d):
        return sum((m.root / d / f"{v.id}.exr").stat().st_size for v in m.views) / len(m.views)

    for d in ("views", "reflectance"):
        ratio = per_view(relit_pair["half"], d) / per_view(relit_pair["float"], d)
        assert 0.35 < ratio < 0.65, (d, ratio)


def test_a_half_model_renders_within_half_precision_of_the_float_model(tmp_path):
    from opacityhull.render.cameras import look_at_camera
    from opacityhull.render.renderer import RenderConfig, render_image
    from opacityhull.render.synthetic import make_sphere_model

    s = make_sphere_model(3000, width=40, height=30, table_step_deg=60.0, supersample=2)
    models = {}
    for st in ("float", "half"):
        write_model(tmp_path / st, views=s.views, surfels=s.surfels, view_rgba=s.view_rgba, rig=s.rig, storage=st)
        models[st] = OpacityHullModel.open(tmp_path / st)
    cam = look_at_camera([0.3, 0.25, 0.35], s.scene.centre, fov_y_deg=30.0, width=40, height=30)
    out = {}
    cfg = RenderConfig(align="none")
    for st, m in models.items():
        # the blend alone: flow alignment estimates its displacements on 8-bit images, so
        # a half-precision change can move a flow vector by a quantisation step
        r = render_image(m.surfels, [v.camera for v in m.views], m.load_views_premul(), cam, config=cfg)
        out[st] = np.concatenate([r.rgba[..., :3] * r.rgba[..., 3:4], r.rgba[..., 3:4]], axis=-1)
    assert out["float"][..., 3].max() > 0.99  # the sphere is in the frame
    d = np.abs(out["half"] - out["float"])
    # premultiplied values are <= ~1.07 (specular): each view texel moved by <= 2**-11 of
    # it; the ULR blend is a convex combination of them, so the frame moves as little
    assert 0 < d.max() <= 1.5 * HALF_REL, d.max()


def _one_view_model(tmp_path, storage, rgba, refl):
    from opacityhull.model import LightSample, Surfels
    from opacityhull.render.synthetic import rig_dict
    from opacityhull.riggeometry import RigGeometry

    rig = rig_dict(elevations_deg=(20.0,), width=4, height=3)
    rig["lights"] = [{"id": 0, "elevation_deg": 40.0, "azimuth_deg": 90.0, "distance_m": 1.0}]
    geo = RigGeometry.from_dict(rig)
    cam = RigGeometry.view_camera(geo.nominal_cameras()[0], 0.0, name="c0_t000.000")
    view = ViewInfo(0, "c0_t000.000", 0, 0.0, cam)
    surfels = Surfels.from_bool(np.zeros((1, 3)), [[0.0, 0.0, 1.0]], [0.01], np.ones((1, 1), bool))
    light = LightSample("a000p000_l0", 0, 0.0)
    root = tmp_path / storage
    write_model(
        root,
        views=[view],
        surfels=surfels,
        view_rgba=[rgba],
        rig=rig,
        reflectance={"lights": [light], "images": lambda i: {light.key: refl}},
        storage=storage,
    )
    return OpacityHullModel.open(root)


def _hard_inputs():
    rgba = np.full((3, 4, 4), 0.5, np.float32)
    rgba[..., 3] = 1.0
    rgba[0, 0, 0] = 1.0e5  # beyond half
    rgba[0, 1, 1] = -7.0e4  # beyond half, negative
    rgba[1, 0, 2] = np.inf
    rgba[1, 1, 0] = np.nan
    rgba[2, 3, 0] = 6.0e4  # inside the range: kept
    refl = np.full((3, 4, 3), 2.0, np.float32)
    refl[2, 2, 1] = 3.0e5
    refl[0, 3, 0] = -np.inf
    return rgba, refl


def test_values_beyond_half_are_clamped_with_a_warning_naming_the_file_and_listed(tmp_path):
    rgba, refl = _hard_inputs()
    with pytest.warns(HalfOverflowWarning) as rec:
        m = _one_view_model(tmp_path, "half", rgba, refl)
    msgs = [str(w.message) for w in rec]
    view_file = str(tmp_path / "half" / "views" / "c0_t000.000.exr")
    refl_file = str(tmp_path / "half" / "reflectance" / "c0_t000.000.exr")
    assert any(msg.startswith(f"{view_file}: 2 values beyond the half-float range") for msg in msgs), msgs
    assert any(msg.startswith(f"{refl_file}: 1 values beyond the half-float range") for msg in msgs), msgs
    got = m.load_views_premul()[0]
    assert got[0, 0, 0] == 65504.0 and got[0, 1, 1] == -65504.0
    assert got[2, 3, 0] == np.float32(np.float16(6.0e4))
    # NaN and Inf are stored as they are, as float32 storage stores them
    assert got[1, 0, 2] == np.inf and np.isnan(got[1, 1, 0])
    r = m.load_reflectance(0)["a000p000_l0"]
    assert r[2, 2, 1] == 65504.0 and r[0, 3, 0] == -np.inf and r[1, 1, 1] == 2.0
    assert m.storage_clamped == [
        {"file": view_file, "values": 2, "max_abs": 1.0e5},
        {"file": refl_file, "values": 1, "max_abs": 3.0e5},
    ]
    assert m.meta["storage"]["clamped_values"] == 3

    # the build report lists them: a note naming the files, the count in the metrics
    from opacityhull.reconstruct.build import _storage_metrics

    notes: list = []
    met = _storage_metrics(m.root, ["c0_t000.000"], notes)
    assert met["storage_pixel_type"] == "half" and met["storage_clamped_values"] == 3
    assert [c["file"] for c in met["storage_clamped_files"]] == [view_file, refl_file]
    assert len(notes) == 1 and view_file in notes[0] and refl_file in notes[0] and "--storage float" in notes[0]


def test_float_storage_keeps_every_value_and_warns_nothing(tmp_path, recwarn):
    rgba, refl = _hard_inputs()
    m = _one_view_model(tmp_path, "float", rgba, refl)
    assert not [w for w in recwarn if issubclass(w.category, HalfOverflowWarning)]
    got = m.load_views_premul()[0]
    assert got[0, 0, 0] == 1.0e5 and got[1, 0, 2] == np.inf and np.isnan(got[1, 1, 0])
    assert m.load_reflectance(0)["a000p000_l0"][2, 2, 1] == 3.0e5
    assert m.storage == "float" and m.storage_clamped == []


def test_a_model_without_a_storage_table_is_float_and_a_bad_one_is_named(relit_pair, tmp_path):
    import shutil

    from opacityhull.tomlio import toml_dumps

    root = tmp_path / "old"
    shutil.copytree(relit_pair["float"].root, root)
    meta = tomllib.loads((root / "model.toml").read_text())
    del meta["storage"]
    (root / "model.toml").write_text(toml_dumps(meta))
    assert OpacityHullModel.open(root).storage == "float"
    meta["storage"] = {"pixel_type": "bfloat16"}
    (root / "model.toml").write_text(toml_dumps(meta))
    with pytest.raises(
        FormatError, match=r"model\.toml: storage\.pixel_type 'bfloat16', expected one of 'half', 'float'"
    ):
        _ = OpacityHullModel.open(root).storage


def test_bad_storage_values_are_refused(tmp_path, relit_pair):
    from opacityhull.reconstruct.build import BuildConfig

    assert BuildConfig().storage == "half"
    with pytest.raises(ConfigError, match=r"storage must be one of 'half', 'float', got 'double'"):
        BuildConfig(storage="double")  # type: ignore[arg-type]
    m = relit_pair["float"]
    with pytest.raises(InputError, match=r"write_model storage 'f16': expected one of 'half', 'float'"):
        write_model(tmp_path / "m", views=m.views, surfels=m.surfels, storage="f16")  # type: ignore[arg-type]
    assert not (tmp_path / "m").exists()


# --------------------------------------------------------------------------- build CLI


def test_build_storage_flag_and_the_bytes_per_view_in_the_report(cli_session, tmp_path):
    out = tmp_path / "model"
    base = ["build", cli_session, "--out", out, "--hull-res", "24", "--no-pictures", "--json"]
    res = invoke_cli([*base, "--storage", "float"])
    assert res.exit_code == 0, res.output
    summ = json.loads(res.stdout)
    m = OpacityHullModel.open(out)
    assert m.storage == "float" and m.has_reflectance and len(m.views) == 6
    assert _pixel_types(m.view_path(0)) == {OpenEXR.FLOAT}

    def on_disk(d):
        return sum((out / d / f"{v.id}.exr").stat().st_size for v in m.views) / len(m.views)

    met = summ["metrics"]
    assert met["storage_pixel_type"] == "float"
    assert met["disk_bytes_per_view_views"] == on_disk("views") > 0
    assert met["disk_bytes_per_view_reflectance"] == on_disk("reflectance") > 0
    assert met["disk_bytes_per_view"] == on_disk("views") + on_disk("reflectance")
    assert json.loads((out / "report.json").read_text())["metrics"]["disk_bytes_per_view"] == met["disk_bytes_per_view"]
    float_views = m.load_views_premul()
    float_bytes = met["disk_bytes_per_view"]

    # the default (half) on resume: only the write step reruns, the pixels are the float
    # build's rounded to half, in about half the bytes
    res = invoke_cli([*base, "--resume"])
    assert res.exit_code == 0, res.output
    summ = json.loads(res.stdout)
    assert summ["steps"]["write"] == "ran"
    assert summ["steps"]["matting"] == "reused" and summ["steps"]["geometry"] == "reused"
    m = OpacityHullModel.open(out)
    assert m.storage == "half" and summ["metrics"]["storage_pixel_type"] == "half"
    assert _pixel_types(m.view_path(0)) == {OpenEXR.HALF}
    assert _pixel_types(out / "reflectance" / f"{m.views[0].id}.exr") == {OpenEXR.HALF}
    for a, b in zip(float_views, m.load_views_premul(), strict=True):
        np.testing.assert_array_equal(b, a.astype(np.float16).astype(np.float32))
    assert 0.35 < summ["metrics"]["disk_bytes_per_view"] / float_bytes < 0.7
    assert summ["metrics"]["storage_clamped_values"] == 0


def test_a_bad_storage_flag_is_exit_2_naming_it(cli_session, tmp_path):
    res = invoke_cli(["build", cli_session, "--out", tmp_path / "m", "--storage", "double"])
    assert res.exit_code == 2, res.output
    assert "--storage 'double': expected half or float" in " ".join(res.stderr.split())
    assert "Traceback" not in res.output
    assert not (tmp_path / "m").exists()


def test_half_range_constants():
    # the bound the tests rely on: float16's epsilon is 2**-10, half of it the rounding
    assert float(np.finfo(np.float16).eps) / 2 == HALF_REL
    assert float(np.finfo(np.float16).smallest_subnormal) / 2 == HALF_ABS
    assert math.isclose(float(np.finfo(np.float16).max), 65504.0)
