"""Session.gain: the one camera-gain lookup (hdr merge, radiance) — no silent 1.0 for a
corrupt rig table."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import pytest

from opacityhull.errors import FormatError, InputError
from opacityhull.riggeometry import RigGeometry
from opacityhull.session import Session
from opacityhull.tomlio import read_toml

RIG_TOML = Path(__file__).parents[2] / "opacityhull" / "sim" / "data" / "rig.toml"


def _session(rig: dict | None) -> Session:
    meta: dict = {"session": {}}
    if rig is not None:
        meta["rig"] = rig
    return Session(Path("/nonexistent/session"), meta, [])


def test_gain_per_camera_from_the_rig(caplog):
    g = read_toml(RIG_TOML)["geometry"]
    geo = RigGeometry.from_dict(g)
    cams = [replace(c, gain=1.5 + i) for i, c in enumerate(geo.cameras)]
    d = dict(g)
    d["cameras"] = [dict(cg, gain=c.gain) for cg, c in zip(g["cameras"], cams, strict=True)]
    s = _session(d)
    assert [s.gain(i) for i in range(len(cams))] == [1.5 + i for i in range(len(cams))]
    with caplog.at_level(logging.WARNING, logger="opacityhull.session"):
        assert s.gain(len(cams) + 3) == 1.0
    assert "not among the rig's" in caplog.text


def test_no_rig_means_gain_one():
    assert _session(None).gain(0) == 1.0


def test_corrupt_rig_table_raises_instead_of_gain_one():
    s = _session({"cameras": [{"nonsense": 1}]})
    with pytest.raises((InputError, FormatError), match="session.toml:rig"):
        s.gain(0)
