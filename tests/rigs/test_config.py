"""Rig TOML parsing: the example rig, round trips, and precise errors naming file and key."""

import copy
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from opacityhull.errors import ConfigError
from opacityhull.rigs.backdrops import DISPLAY_SERIAL
from opacityhull.rigs.config import RigConfig, load_rig_config, parse_emulator_url, parse_rig_config
from opacityhull.rigs.lights import DMX_SERIAL
from opacityhull.rigs.motion import GRBL_SERIAL
from opacityhull.tomlio import toml_dumps

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig-emulated.toml"


@pytest.fixture(scope="module")
def example_dict():
    return tomllib.loads(EXAMPLE.read_text())


def write(tmp_path, d, name="rig.toml") -> Path:
    p = tmp_path / name
    p.write_text(toml_dumps(d))
    return p


def test_example_rig_parses(example_dict):
    cfg = load_rig_config(EXAMPLE)
    assert cfg.name == "paper rig (emulated)"
    assert cfg.device_urls() == {
        "turntable": "emulator:grbl",
        "light_array": "emulator:enttec",
        "light_array.rotation": "emulator:grbl",
        "backdrops": "emulator:display",
    }
    ports = cfg.grbl_ports()
    assert list(ports) == ["emulator:grbl"] and [a.axis for a in ports["emulator:grbl"]] == ["X", "Y"]
    assert cfg.light_array.channel_map == {0: 1, 1: 2, 2: 3, 3: 4}
    assert cfg.backdrops.output_map == {"bottom": 0, "back": 1}
    assert [c.name for c in cfg.cameras] == [f"cam{i}" for i in range(6)]
    assert all(c.driver == "sim" and (c.width, c.height) == (640, 480) for c in cfg.cameras)
    els = [c.elevation_deg for c in cfg.geometry.cameras]
    assert els[0] == 0.0 and els[-1] == 60.0 and np.all(np.diff(els) > 0)
    assert {c.azimuth_deg for c in cfg.geometry.cameras} == {0.0}
    assert {c.distance_m for c in cfg.geometry.cameras} == {1.0}
    assert len(cfg.geometry.lights) == 4 and cfg.emulated()


def test_example_rig_displays_cover_the_object():
    """From every camera, every ray through the object cube (0.2 m, centred 0.08 m above the
    table, the part above the table top) lands on a display beyond the object, and the cube
    projects inside the image. The rotating bottom panel only counts with its inscribed disc,
    so the check holds at every table angle."""
    g = load_rig_config(EXAMPLE).geometry
    lo, hi = np.array([-0.1, 0.0, -0.1]), np.array([0.1, 0.18, 0.1])
    axes = [np.linspace(a, b, 17) for a, b in zip(lo, hi, strict=True)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    bottom, back = g.display("bottom"), g.display("back")
    assert bottom.rotates_with_table and not back.rotates_with_table
    r_disc = min(bottom.size_m) / 2
    bc = back.corners_rig()  # tl, tr, br, bl
    x0, x1 = bc[:, 0].min(), bc[:, 0].max()
    y0, y1 = bc[:, 1].min(), bc[:, 1].max()
    z_back = bc[0, 2]
    assert np.allclose(bc[:, 2], z_back) and np.allclose(back.normal, [0, 0, 1])
    for cam in g.nominal_cameras():
        C = cam.world_from_cam[:3, 3]
        Xc = (np.linalg.inv(cam.world_from_cam) @ np.c_[P, np.ones(len(P))].T)[:3]
        uv = (cam.K @ Xc)[:2] / Xc[2]
        assert np.all(Xc[2] > 0)
        assert uv.min() >= 0 and uv[0].max() <= cam.width - 1 and uv[1].max() <= cam.height - 1, cam.name
        d = P - C
        t_p = 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            t_b = np.where(d[:, 1] < 0, -C[1] / d[:, 1], np.inf)  # P = C + t d; t=1 at the object point
            t_k = np.where(d[:, 2] < 0, (z_back - C[2]) / d[:, 2], np.inf)
        Qb = C + np.where(np.isfinite(t_b), t_b, 0)[:, None] * d
        Qk = C + np.where(np.isfinite(t_k), t_k, 0)[:, None] * d
        hit_bottom = np.isfinite(t_b) & (t_b >= t_p) & (np.hypot(Qb[:, 0], Qb[:, 2]) <= r_disc)
        hit_back = (
            np.isfinite(t_k) & (t_k >= t_p) & (Qk[:, 0] >= x0) & (Qk[:, 0] <= x1) & (Qk[:, 1] >= y0) & (Qk[:, 1] <= y1)
        )
        assert np.all(hit_bottom | hit_back), f"{cam.name}: {np.count_nonzero(~(hit_bottom | hit_back))} rays miss"
    # the rotating bottom panel passes under the back panel: its lower edge is above the table top
    assert y0 > 0 and np.hypot(*bottom.size_m) / 2 > abs(z_back)


def test_roundtrip_and_url_rewrite(tmp_path, example_dict):
    cfg = load_rig_config(EXAMPLE)
    p = cfg.with_urls({"emulator:grbl": "/dev/pts/7", "emulator:display": "socket://127.0.0.1:4000"}).write(
        tmp_path / "runtime.toml"
    )
    again = load_rig_config(p)
    assert again.device_urls() == {
        "turntable": "/dev/pts/7",
        "light_array": "emulator:enttec",
        "light_array.rotation": "/dev/pts/7",
        "backdrops": "socket://127.0.0.1:4000",
    }
    for f in ("name", "cameras"):
        assert getattr(again, f) == getattr(cfg, f)
    assert again.turntable == cfg.turntable.__class__(**{**cfg.turntable.__dict__, "url": "/dev/pts/7"})
    assert again.light_array.channels == cfg.light_array.channels
    assert again.geometry.to_dict() == cfg.geometry.to_dict()
    np.testing.assert_allclose(
        again.geometry.nominal_cameras()[3].world_from_cam, cfg.geometry.nominal_cameras()[3].world_from_cam
    )
    assert cfg.raw["devices"]["turntable"]["url"] == "emulator:grbl"  # the original is untouched


def test_serial_settings_are_the_table_over_the_driver_defaults(example_dict):
    d = copy.deepcopy(example_dict)
    d["devices"]["backdrops"].update(retries=5, timeout_s=0.5)
    d["devices"]["light_array"].pop("timeout_s")
    d["devices"]["light_array"]["rotation"]["baudrate"] = 250000
    d["devices"]["turntable"]["baudrate"] = 250000
    cfg = parse_rig_config(d)
    assert cfg.turntable.serial == replace(GRBL_SERIAL, baudrate=250000)  # retries and reconnects: GRBL's
    assert cfg.light_array.serial == DMX_SERIAL
    assert cfg.light_array.rotation.serial == cfg.turntable.serial
    assert cfg.backdrops.serial == replace(DISPLAY_SERIAL, retries=5, timeout_s=0.5)


def test_parse_emulator_url():
    assert parse_emulator_url("emulator:grbl#b") == ("grbl", "b")
    assert parse_emulator_url("emulator:display") == ("display", "")
    assert parse_emulator_url("/dev/ttyUSB0") is None


def _err(tmp_path, d, match):
    p = write(tmp_path, d)
    with pytest.raises(ConfigError, match=match) as ei:
        load_rig_config(p)
    assert str(ei.value).startswith(str(p) + ": ") or str(p) in str(ei.value)
    return str(ei.value)


_DEL = object()  # an edit that deletes the key


def _swap_first_cameras(d):
    cams = d["devices"]["cameras"]
    cams[0], cams[1] = cams[1], cams[0]


# (case id, edits, expected message): each edit is (key path, value or _DEL) or a callable on the dict
_BAD_RIG = [
    (
        "url-scheme",
        [(("devices", "turntable", "url"), "http://grbl.local")],
        r"rig.toml: devices.turntable.url: unknown URL scheme in 'http://grbl.local'",
    ),
    (
        "emulator-kind",
        [(("devices", "light_array", "rotation", "url"), "emulator:stepper")],
        r"devices.light_array.rotation.url: unknown emulator kind 'stepper'",
    ),
    (
        "emulator-device",
        [(("devices", "backdrops", "url"), "emulator:grbl")],
        r"devices.backdrops.url: 'emulator:grbl' emulates a grbl device, but this device is a display",
    ),
    (
        "dmx-missing",
        [(("devices", "light_array", "channels", "2"), _DEL)],
        r"devices.light_array.channels: no DMX channel for light 2 \(geometry.lights\[2\]\)",
    ),
    (
        "dmx-unknown-light",
        [(("devices", "light_array", "channels", "9"), 9)],
        r"devices.light_array.channels.9: no light with id 9 in geometry.lights",
    ),
    (
        "dmx-reused",
        [(("devices", "light_array", "channels", "3"), 1)],
        r"devices.light_array.channels.3: DMX channel 1 is already used by light 0",
    ),
    (
        "dmx-range",
        [(("devices", "light_array", "channels", "3"), 513)],
        r"channels.3: expected a DMX channel 1..512, got 513",
    ),
    (
        "no-light-array",
        [(("devices", "light_array"), _DEL)],
        r"devices: geometry.lights has 4 light\(s\) but there is no \[devices.light_array\]",
    ),
    (
        "dup-camera",
        [(("devices", "cameras", 4, "name"), "cam1")],
        r"devices.cameras\[4\].name: duplicate camera name 'cam1' \(also devices.cameras\[1\]\)",
    ),
    (
        "dup-axis",
        [(("devices", "light_array", "rotation", "axis"), "X")],
        r"devices.light_array.rotation.axis: axis X of the controller at 'emulator:grbl' is already "
        r"devices.turntable",
    ),
    (
        "dup-port",
        [(("devices", "backdrops", "url"), "/dev/ttyUSB0"), (("devices", "light_array", "url"), "/dev/ttyUSB0")],
        r"devices.backdrops.url: '/dev/ttyUSB0' is also devices.light_array.url \(a enttec device\)",
    ),
    ("camera-order", [_swap_first_cameras], r"same names in a different order"),
    ("camera-missing", [lambda d: d["devices"]["cameras"].pop()], r"missing \['cam5'\]"),
    (
        "output-missing",
        [(("devices", "backdrops", "outputs", "back"), _DEL)],
        r"devices.backdrops.outputs: no controller output for display 'back' \(geometry.displays\[1\]\)",
    ),
    (
        "output-unknown-display",
        [(("devices", "backdrops", "outputs", "side"), 2)],
        r"devices.backdrops.outputs.side: no display named 'side' in geometry.displays",
    ),
    (
        "output-reused",
        [(("devices", "backdrops", "outputs", "back"), 0)],
        r"outputs.back: output 0 is already used by display 'bottom'",
    ),
    (
        "slots-zero",
        [(("devices", "backdrops", "slots"), 0)],
        r"devices.backdrops.slots: expected an integer in 1..65535, got 0",
    ),
    (
        "no-backdrops",
        [(("devices", "backdrops"), _DEL)],
        r"geometry.displays has 2 display\(s\) but there is no \[devices.backdrops\]",
    ),
    (
        "number-type",
        [(("devices", "turntable", "steps_per_deg"), "80")],
        r"devices.turntable.steps_per_deg: expected a number, got '80'",
    ),
    (
        "timeout-range",
        [(("devices", "turntable", "timeout_s"), -1)],
        r"devices.turntable.timeout_s: must be > 0, got -1",
    ),
    ("unknown-key", [(("devices", "turntable", "speed"), 3)], r"devices.turntable: unknown key\(s\) \['speed'\]"),
    ("axis-letter", [(("devices", "turntable", "axis"), "Q")], r"devices.turntable.axis: expected a GRBL axis letter"),
    (
        "table-type",
        [(("devices", "backdrops", "outputs"), 3)],
        r"devices.backdrops.outputs: expected a table, got int 3",
    ),
    (
        "bool-type",
        [(("devices", "cameras", 0), {"name": "cam0", "driver": "opencv", "device": 0, "exposure_control": "yes"})],
        r"devices.cameras\[0\].exposure_control: expected true or false",
    ),
    (
        "camera-driver",
        [(("devices", "cameras", 0), {"name": "cam0", "driver": "gphoto"})],
        r"devices.cameras\[0\].driver: unknown camera driver 'gphoto'",
    ),
    (
        "camera-unknown-key",
        [(("devices", "cameras", 0), {"name": "cam0", "driver": "opencv", "device": 0, "pattern": "*.png"})],
        r"devices.cameras\[0\]: unknown key\(s\) \['pattern'\]",
    ),
    (
        "geometry-number",
        [(("geometry", "cameras", 0, "width"), "wide")],
        r"rig.toml: geometry.cameras\[0\].width: expected a number",
    ),
    (
        "soft-limits",
        [(("devices", "turntable", "soft_limits_deg"), [10, -10])],
        r"soft_limits_deg: expected \[min_deg, max_deg\] with min < max",
    ),
]


def _edited(example_dict, edits):
    d = copy.deepcopy(example_dict)
    for edit in edits:
        if callable(edit):
            edit(d)
            continue
        path, value = edit
        parent = d
        for k in path[:-1]:
            parent = parent[k]
        if value is _DEL:
            del parent[path[-1]]
        else:
            parent[path[-1]] = value
    return d


@pytest.mark.parametrize("edits, match", [c[1:] for c in _BAD_RIG], ids=[c[0] for c in _BAD_RIG])
def test_bad_rig_config_names_file_and_key(tmp_path, example_dict, edits, match):
    _err(tmp_path, _edited(example_dict, edits), match)


def test_duplicate_device_table_is_invalid_toml(tmp_path):
    p = tmp_path / "dup.toml"
    p.write_text(EXAMPLE.read_text() + '\n[devices.turntable]\nurl = "/dev/ttyUSB3"\n')
    with pytest.raises(ConfigError, match=r"dup.toml: invalid TOML \(.*turntable.*"):
        load_rig_config(p)


def test_camera_names_must_match_geometry(tmp_path, example_dict):
    d = _edited(example_dict, [(("devices", "cameras", 2, "name"), "camX")])
    msg = _err(tmp_path, d, r"devices.cameras: camera names .* must match geometry.cameras")
    assert "missing ['cam2']" in msg and "not in geometry.cameras: ['camX']" in msg


def test_missing_or_invalid_file(tmp_path):
    with pytest.raises(ConfigError, match="rig config .*nope.toml not found"):
        load_rig_config(tmp_path / "nope.toml")
    (tmp_path / "bad.toml").write_text("[rig\nname=")
    with pytest.raises(ConfigError, match=r"bad.toml: invalid TOML"):
        load_rig_config(tmp_path / "bad.toml")


def test_directory_camera_folder_is_relative_to_the_config(tmp_path, example_dict):
    d = copy.deepcopy(example_dict)
    d["devices"]["cameras"][1] = {
        "name": "cam1",
        "driver": "directory",
        "device": "shots/cam1",
        "settle_s": 0.5,
        "trigger": ["gphoto2", "--capture-image-and-download"],
    }
    d["devices"]["cameras"][2] = {"name": "cam2", "driver": "opencv", "device": "/dev/video2", "fourcc": "MJPG"}
    cfg = load_rig_config(write(tmp_path, d))
    assert cfg.cameras[1].device == str(tmp_path / "shots" / "cam1")
    assert cfg.cameras[1].option("settle_s") == 0.5 and cfg.cameras[2].option("fourcc") == "MJPG"
    assert isinstance(parse_rig_config(d), RigConfig)  # from a dict: source "<rig config>"
    d["devices"]["turntable"]["url"] = 5
    with pytest.raises(ConfigError, match=r"<rig config>: devices.turntable.url: expected a serial URL string"):
        parse_rig_config(d)
