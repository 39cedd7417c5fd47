"""The readers of saved calibration inputs: the corners npz (``calibrate/corners.py``) and
caliscope's camera_array.toml (``calibrate/caliscope.py``), on the vendored caliscope files
(tests/data/real/calibration/caliscope, see SOURCE.txt)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from opacityhull.calibrate.caliscope import read_camera_array
from opacityhull.calibrate.corners import KEYS, read_corners, write_corners
from opacityhull.calibrate.inputs import parse_board
from opacityhull.errors import FormatError, InputError

CALISCOPE = Path(__file__).resolve().parents[1] / "data" / "real" / "calibration" / "caliscope"
NPZ = CALISCOPE / "extrinsic_corners.npz"


@pytest.fixture(scope="module")
def spec():
    return parse_board(str(CALISCOPE / "charuco.toml"))


def test_read_vendored_corners(spec):
    z = np.load(NPZ)
    dets = read_corners(NPZ, charuco=spec, size=(1280, 720), sources=[f"cam_{i}.mp4" for i in range(4)])
    assert [d.camera.index for d in dets] == [0, 1, 2, 3]
    assert [len(d.observations) for d in dets] == np.bincount(z["camera"], minlength=4).tolist()
    assert sum(len(o.detection) for d in dets for o in d.observations) == len(z["corner_id"]) == 1969
    board = np.asarray(spec.board().getChessboardCorners(), np.float64).reshape(-1, 3)
    o = dets[0].observations[0]
    assert o.where == f"cam_0.mp4#{z['frame'][0]}" and o.instant == str(z["instant"][0])
    assert o.detection.ids.dtype == np.int32 and o.detection.image_points.dtype == np.float64
    np.testing.assert_array_equal(o.detection.image_points, z["corner_xy"][: z["start"][1]])
    np.testing.assert_array_equal(o.detection.object_points, board[z["corner_id"][: z["start"][1]]])
    assert o.detection.inverted and not o.detection.mirrored  # caliscope's board is printed inverted
    assert all(d.size == (1280, 720) and d.frames_read == 0 and not d.rejected for d in dets)


def test_corners_round_trip_is_the_vendored_file(spec, tmp_path):
    """What read_corners gives, written again, is the vendored file array for array."""
    dets = read_corners(NPZ, charuco=spec, size=(1280, 720))
    out = tmp_path / "again.npz"
    write_corners(out, dets)
    a, b = np.load(NPZ), np.load(out)
    assert sorted(b.files) == sorted(KEYS)
    for k in KEYS:
        assert a[k].dtype == b[k].dtype, k
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_write_corners_refuses_image_frames(spec, tmp_path):
    from dataclasses import replace

    (d, *_) = read_corners(NPZ, charuco=spec, size=(1280, 720))
    d.observations[0] = replace(d.observations[0], where="frames/img_00.jpg")
    with pytest.raises(InputError, match="img_00.jpg"):
        write_corners(tmp_path / "x.npz", [d])


def test_read_corners_bad_files(spec, tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        read_corners(tmp_path / "missing.npz", charuco=spec, size=(1280, 720))
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(FormatError, match="junk.npz"):
        read_corners(junk, charuco=spec, size=(1280, 720))
    z = dict(np.load(NPZ))
    np.savez(tmp_path / "nokey.npz", **{k: v for k, v in z.items() if k != "start"})
    with pytest.raises(FormatError, match=r"missing \['start'\]"):
        read_corners(tmp_path / "nokey.npz", charuco=spec, size=(1280, 720))
    np.savez(tmp_path / "short.npz", **{**z, "start": z["start"][:-1]})
    with pytest.raises(FormatError, match="arrays disagree"):
        read_corners(tmp_path / "short.npz", charuco=spec, size=(1280, 720))
    small = parse_board("squares=3x3,square_m=0.054,marker_m=0.04,dictionary=DICT_4X4_1000")
    with pytest.raises(FormatError, match="board has 4 corners"):
        read_corners(NPZ, charuco=small, size=(1280, 720))


def test_read_camera_array_vendored():
    """Against the TOML read independently: K, distortion, and centres with R C + t = 0."""
    raw = tomllib.loads((CALISCOPE / "camera_array.toml").read_text())["cameras"]
    cams = read_camera_array(CALISCOPE / "camera_array.toml")
    assert list(cams) == [0, 1, 2, 3]
    for i, c in cams.items():
        assert c.index == i and c.size == (1280, 720)
        np.testing.assert_array_equal(c.K, raw[str(i)]["matrix"])
        np.testing.assert_array_equal(c.dist, raw[str(i)]["distortions"])
        np.testing.assert_allclose(c.R_cam_from_world @ c.R_cam_from_world.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(c.R_cam_from_world @ c.centre_world + c.t_cam_from_world, 0, atol=1e-15)


def test_read_camera_array_bad_files(tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        read_camera_array(tmp_path / "camera_array.toml")
    p = tmp_path / "bad.toml"
    p.write_text("[cameras.0\n")
    with pytest.raises(FormatError, match="cannot be read as TOML"):
        read_camera_array(p)
    p.write_text("[charuco]\ncolumns = 4\n")
    with pytest.raises(FormatError, match=r"no \[cameras.N\]"):
        read_camera_array(p)
    text = (CALISCOPE / "camera_array.toml").read_text()
    p.write_text("\n".join(line for line in text.splitlines() if not line.startswith("rotation =")))
    with pytest.raises(FormatError, match=r"\[cameras.0\] has no rotation"):
        read_camera_array(p)
    p.write_text(text.replace("size = [1280, 720]", "size = [1280]", 1))
    with pytest.raises(FormatError, match=r"\[cameras.0\] size"):
        read_camera_array(p)
