"""The session format as acquire writes it: last record of an id wins, torn manifest
tails, a failing manifest append, reader accessors."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from opacityhull.errors import FormatError, InputError
from opacityhull.session import Session, SessionWriter, read_manifest

GEO = {"target_m": [0, 0, 0], "cameras": [{"name": "c", "width": 4, "height": 3, "distance_m": 1.0, "gain": 2.0}]}


def _new(tmp_path):
    w = SessionWriter(tmp_path / "s").create(
        {
            "rig": GEO,
            "session": {"white_level": 0.5},
            "charuco": {"squares_x": 5, "squares_y": 4, "square_m": 0.04, "marker_m": 0.03},
        }
    )
    return w


def test_last_record_of_an_id_wins(tmp_path):
    w = _new(tmp_path)
    img = np.full((3, 4, 3), 0.25, np.float32)
    add_one = partial(  # one image id, written three times
        w.add_image,
        id="lightfield/c0_t000.000/img/e0",
        shot="lightfield/c0_t000.000/img",
        phase="lightfield",
        camera=0,
        table_deg=0.0,
        rel_path="images/a.exr",
        exposure_s=0.5,
    )
    add_one(img)
    with pytest.raises(InputError, match="already in"):
        add_one(img)
    add_one(img * 2, replace=True)
    w.close()
    s = Session.open(tmp_path / "s")
    assert len(s.records) == 1 and s.superseded == 1
    assert len(list(read_manifest(tmp_path / "s" / "manifest.jsonl"))) == 2
    # radiance = value / (gain * t)
    np.testing.assert_allclose(s.load_radiance("lightfield/c0_t000.000/img"), 0.5 / (2.0 * 0.5))
    assert s.white_level == 0.5
    assert s.charuco.squares_y == 4


def test_torn_tail_is_cut_on_resume(tmp_path):
    w = _new(tmp_path)
    img = np.zeros((3, 4, 3), np.float32)
    for i in range(2):
        w.add_image(
            img, id=f"x{i}", shot=f"s{i}", phase="lightfield", camera=0, table_deg=0.0, rel_path=f"images/{i}.exr"
        )
    w.close()
    m = tmp_path / "s" / "manifest.jsonl"
    good = m.read_bytes()
    m.write_bytes(good + b'{"id": "x2", "shot": "s')  # crash mid-append
    assert [r.id for r in read_manifest(m)] == ["x0", "x1"]
    w = SessionWriter(tmp_path / "s").resume()
    assert m.read_bytes() == good
    w.add_image(img, id="x2", shot="s2", phase="lightfield", camera=0, table_deg=0.0, rel_path="images/2.exr")
    w.close()
    assert [r.id for r in read_manifest(m)] == ["x0", "x1", "x2"]
    # a corrupt line that is not the last one is an error naming the line
    lines = m.read_bytes().split(b"\n")
    lines[1] = b"{not json"
    m.write_bytes(b"\n".join(lines))
    with pytest.raises(FormatError, match=r"manifest.jsonl:2"):
        Session.open(tmp_path / "s")


class _FailingFile:
    """A manifest file whose next write stops half-way and fails (a full disk)."""

    def __init__(self, f):
        self.f = f

    def write(self, b):
        self.f.write(b[: len(b) // 2])
        raise OSError(28, "No space left on device")

    def __getattr__(self, k):
        return getattr(self.f, k)


def test_failed_append_leaves_no_half_record(tmp_path):
    w = _new(tmp_path)
    img = np.zeros((3, 4, 3), np.float32)
    w.add_image(img, id="x0", shot="s0", phase="lightfield", camera=0, table_deg=0.0, rel_path="images/0.exr")
    m = tmp_path / "s" / "manifest.jsonl"
    before = m.read_bytes()
    w._manifest = _FailingFile(w._manifest)
    with pytest.raises(OSError):
        w.add_image(img, id="x1", shot="s1", phase="lightfield", camera=0, table_deg=0.0, rel_path="images/1.exr")
    assert m.read_bytes() == before
    assert "x1" not in w.ids
