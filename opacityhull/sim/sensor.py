"""A camera sensor model for simulated captures (off unless asked for).

The ideal simulated camera returns ``gain * exposure_s * radiance``. :class:`SensorModel`
turns that expected signal (in units of the white level) into what a real sensor would
deliver: photon shot noise (Poisson in electrons, ``full_well_e`` electrons at the white
level), Gaussian read noise, clipping at the white level, and quantisation to
``bit_depth`` bits. It is a pure function of the signal and a NumPy generator.

Optionally each shot also drifts photometrically, as real rigs do (plasma displays warm
up, cameras re-meter exposure and white balance between shots): the expected signal is
multiplied by ``exp(N(0, exposure_drift_sigma))`` and, per colour channel, by
``exp(N(0, white_balance_drift_sigma))``, drawn from the shot's generator. Off by
default (both 0), in which case the generator's stream is exactly as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

__all__ = ["SensorModel"]


@dataclass(frozen=True)
class SensorModel:
    """Shot noise, read noise, clipping and quantisation.

    Parameters
    ----------
    full_well_e : float
        Electrons collected at the white level (sets the shot-noise SNR: a pixel at the
        white level has SNR ``sqrt(full_well_e)``).
    read_noise : float
        Standard deviation of the read noise, in white-level units.
    white_level : float
        Value at which the sensor saturates (1.0 for the simulated cameras).
    bit_depth : int
        ADC bits; values are quantised to ``white_level / (2**bit_depth - 1)`` steps.
    exposure_drift_sigma : float
        Per-shot log-normal exposure drift (0.06 ≈ the 6 % seen on real two-backdrop
        shots). 0 = off.
    white_balance_drift_sigma : float
        Per-shot, per-channel log-normal white-balance drift (applied to the last axis
        when it has 3 channels). 0 = off.
    """

    full_well_e: float = 20000.0
    read_noise: float = 0.001
    white_level: float = 1.0
    bit_depth: int = 12
    exposure_drift_sigma: float = 0.0
    white_balance_drift_sigma: float = 0.0

    def __post_init__(self):
        if not self.full_well_e > 0:
            raise ConfigError(f"sensor model: full_well_e must be > 0, got {self.full_well_e}")
        if not self.read_noise >= 0:
            raise ConfigError(f"sensor model: read_noise must be >= 0, got {self.read_noise}")
        if not self.white_level > 0:
            raise ConfigError(f"sensor model: white_level must be > 0, got {self.white_level}")
        if not 1 <= int(self.bit_depth) <= 32:
            raise ConfigError(f"sensor model: bit_depth must be in 1..32, got {self.bit_depth}")
        for name in ("exposure_drift_sigma", "white_balance_drift_sigma"):
            v = getattr(self, name)
            if not (v >= 0 and np.isfinite(v)):
                raise ConfigError(f"sensor model: {name} must be finite and >= 0, got {v}")

    def drift_factors(self, rng: np.random.Generator) -> np.ndarray:
        """The (3,) per-channel gain of one shot (ones when drift is off; then nothing is
        drawn from ``rng``)."""
        f = np.ones(3)
        if self.exposure_drift_sigma > 0:
            f = f * np.exp(rng.normal(0.0, self.exposure_drift_sigma))
        if self.white_balance_drift_sigma > 0:
            f = f * np.exp(rng.normal(0.0, self.white_balance_drift_sigma, size=3))
        return f

    def apply(self, signal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Sensor output (same shape, float32) for the expected ``signal`` (>= 0).

        NaN or negative inputs are treated as 0 (no light).
        """
        s = np.nan_to_num(np.asarray(signal, dtype=np.float64), nan=0.0, posinf=self.white_level * 1e6)
        s = np.maximum(s, 0.0)
        if self.exposure_drift_sigma > 0 or self.white_balance_drift_sigma > 0:
            f = self.drift_factors(rng)
            s = s * (f if s.ndim and s.shape[-1] == 3 else f[0])
        # electrons beyond ~10 full wells are saturated anyway; cap to keep Poisson finite
        electrons = np.minimum(s / self.white_level * self.full_well_e, 10.0 * self.full_well_e)
        counts = rng.poisson(electrons).astype(np.float64)
        v = counts / self.full_well_e * self.white_level
        if self.read_noise > 0:
            v = v + rng.normal(0.0, self.read_noise, size=v.shape)
        v = np.clip(v, 0.0, self.white_level)
        levels = float(2 ** int(self.bit_depth) - 1)
        v = np.round(v / self.white_level * levels) / levels * self.white_level
        return v.astype(np.float32)

    def to_dict(self) -> dict:
        return {
            "full_well_e": self.full_well_e,
            "read_noise": self.read_noise,
            "white_level": self.white_level,
            "bit_depth": int(self.bit_depth),
            "exposure_drift_sigma": self.exposure_drift_sigma,
            "white_balance_drift_sigma": self.white_balance_drift_sigma,
        }
