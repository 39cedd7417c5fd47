"""The sensor model: shot noise, read noise, clipping, quantisation (a pure function)."""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.errors import ConfigError
from opacityhull.sim.sensor import SensorModel


def test_noise_statistics_match_the_model():
    m = SensorModel(full_well_e=10000.0, read_noise=0.002, bit_depth=16)
    rng = np.random.default_rng(0)
    for level in (0.05, 0.3, 0.8):
        out = m.apply(np.full(200_000, level), rng).astype(np.float64)
        assert out.mean() == pytest.approx(level, abs=3e-4)
        expected_var = level / m.full_well_e + m.read_noise**2  # Poisson + Gaussian
        assert out.var() == pytest.approx(expected_var, rel=0.03)


def test_clipping_and_quantisation():
    m = SensorModel(full_well_e=1e6, read_noise=0.0, bit_depth=8)
    out = m.apply(np.array([-1.0, np.nan, 0.5, 1.0, 7.0, np.inf]), np.random.default_rng(1))
    assert out[0] == 0 and out[1] == 0
    assert out[3] == 1.0 and out[4] == 1.0 and out[5] == 1.0
    assert np.allclose(out * 255, np.round(out * 255))
    assert out[2] == pytest.approx(0.5, abs=1 / 255)


def test_seeded_noise_is_reproducible():
    m = SensorModel()
    x = np.random.default_rng(3).random((20, 30, 3))
    a = m.apply(x, np.random.default_rng([1, 2, 3]))
    b = m.apply(x, np.random.default_rng([1, 2, 3]))
    c = m.apply(x, np.random.default_rng([1, 2, 4]))
    assert np.array_equal(a, b) and not np.array_equal(a, c) and a.dtype == np.float32


@pytest.mark.parametrize("kw", [{"full_well_e": 0}, {"read_noise": -1}, {"white_level": 0}, {"bit_depth": 0}])
def test_bad_parameters(kw):
    with pytest.raises(ConfigError):
        SensorModel(**kw)
