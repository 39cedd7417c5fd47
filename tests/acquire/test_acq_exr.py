"""Capture EXR writing: every compression round-trips exactly; half clamps with a warning."""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.acquire.exr import COMPRESSIONS, write_capture_exr
from opacityhull.errors import ConfigError, ShapeError
from opacityhull.imageio import HalfOverflowWarning, read_exr


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_roundtrip_exact(tmp_path, compression):
    rng = np.random.default_rng(0)
    img = rng.random((7, 9, 3)).astype(np.float32)
    img[0, 0] = [0.0, np.inf, np.nan]
    write_capture_exr(tmp_path / "a.exr", img, compression=compression)
    back = read_exr(tmp_path / "a.exr")
    np.testing.assert_array_equal(back, img)  # NaN == NaN positions, inf kept
    write_capture_exr(tmp_path / "m.exr", img[..., 0], compression=compression)
    assert read_exr(tmp_path / "m.exr").shape == (7, 9, 1)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp")] == []


def test_half_clamps_and_warns(tmp_path):
    img = np.full((2, 2, 3), 1e6, np.float32)
    with pytest.warns(HalfOverflowWarning, match="a.exr"):
        write_capture_exr(tmp_path / "a.exr", img, half=True)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), 65504.0)


def test_bad_input(tmp_path):
    with pytest.raises(ShapeError):
        write_capture_exr(tmp_path / "a.exr", np.zeros((2, 2, 2)))
    with pytest.raises(ConfigError):
        write_capture_exr(tmp_path / "a.exr", np.zeros((2, 2, 3)), compression="lzma")
    assert not any(tmp_path.iterdir())
