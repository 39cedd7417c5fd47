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


def test_photometric_drift_off_by_default_and_per_shot_when_on():
    """Drift off: output identical to the plain model (same generator stream). On: each
    shot is scaled by its own per-channel gain, log-normal with the given sigmas, and
    the matting drift correction recovers it."""
    x = np.full((64, 64, 3), 0.4)
    plain = SensorModel(read_noise=0.0, bit_depth=16)
    assert np.array_equal(
        SensorModel(read_noise=0.0, bit_depth=16, exposure_drift_sigma=0.0).apply(x, np.random.default_rng(5)),
        plain.apply(x, np.random.default_rng(5)),
    )
    m = SensorModel(
        full_well_e=1e7, read_noise=0.0, bit_depth=16, exposure_drift_sigma=0.05, white_balance_drift_sigma=0.1
    )
    for shot in range(10):
        f = m.drift_factors(np.random.default_rng([7, shot]))
        out = m.apply(x, np.random.default_rng([7, shot]))
        np.testing.assert_allclose(out.reshape(-1, 3).mean(0), 0.4 * f, rtol=1e-3)
    g = np.log([m.drift_factors(np.random.default_rng([8, shot])) for shot in range(4000)])
    # log gain = exposure (shared) + white balance (per channel): var 0.05² + 0.1²
    assert np.std(g, axis=0) == pytest.approx(np.hypot(0.05, 0.1), rel=0.05)
    # the shared exposure part correlates the channels: cov = 0.05² (sampling std ~8 %)
    assert np.cov(g[:, 0], g[:, 1])[0, 1] == pytest.approx(0.05**2, rel=0.3)
    assert m.to_dict()["white_balance_drift_sigma"] == 0.1


def test_drifted_shots_are_corrected_by_matting():
    from opacityhull.reconstruct.matting import DriftOptions, correct_photometric_drift

    H, W = 40, 56
    y, x = np.mgrid[0:H, 0:W]
    B = np.stack([0.3 + 0.1 * np.sin(0.3 * x + 0.2 * y + c) for c in range(3)], -1)
    backs = np.stack([B * 1.6, B * 0.2])
    alpha = (np.hypot(x - 30, y - 20) < 8).astype(float)[..., None]
    m = SensorModel(
        full_well_e=1e6, read_noise=0.0, bit_depth=16, exposure_drift_sigma=0.05, white_balance_drift_sigma=0.05
    )
    obs = np.stack([m.apply(alpha * 0.5 + (1 - alpha) * backs[k], np.random.default_rng([1, k])) for k in range(2)])
    truth = np.stack([m.drift_factors(np.random.default_rng([1, k])) for k in range(2)])
    _, rep = correct_photometric_drift(
        obs, backs.astype(np.float32), mode="gain", options=DriftOptions(rounds=2, register=False)
    )
    for k in range(2):
        np.testing.assert_allclose(rep.shots[k].gain, truth[k], rtol=5e-3)


@pytest.mark.parametrize("kw", [{"exposure_drift_sigma": -0.1}, {"white_balance_drift_sigma": float("nan")}])
def test_bad_drift_parameters(kw):
    with pytest.raises(ConfigError, match=next(iter(kw))):
        SensorModel(**kw)
