"""A camera sensor model for simulated captures (off unless asked for).

The ideal simulated camera returns ``gain * exposure_s * radiance``. :class:`SensorModel`
turns that expected signal (in units of the white level) into what a real sensor would
deliver: photon shot noise (Poisson in electrons, ``full_well_e`` electrons at the white
level), Gaussian read noise, clipping at the white level, and quantisation to
``bit_depth`` bits. It is a pure function of the signal and a NumPy generator.
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
    """

    full_well_e: float = 20000.0
    read_noise: float = 0.001
    white_level: float = 1.0
    bit_depth: int = 12

    def __post_init__(self):
        if not self.full_well_e > 0:
            raise ConfigError(f"sensor model: full_well_e must be > 0, got {self.full_well_e}")
        if not self.read_noise >= 0:
            raise ConfigError(f"sensor model: read_noise must be >= 0, got {self.read_noise}")
        if not self.white_level > 0:
            raise ConfigError(f"sensor model: white_level must be > 0, got {self.white_level}")
        if not 1 <= int(self.bit_depth) <= 32:
            raise ConfigError(f"sensor model: bit_depth must be in 1..32, got {self.bit_depth}")

    def apply(self, signal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Sensor output (same shape, float32) for the expected ``signal`` (>= 0).

        NaN or negative inputs are treated as 0 (no light).
        """
        s = np.nan_to_num(np.asarray(signal, dtype=np.float64), nan=0.0, posinf=self.white_level * 1e6)
        s = np.maximum(s, 0.0)
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
        return {"full_well_e": self.full_well_e, "read_noise": self.read_noise, "white_level": self.white_level,
                "bit_depth": int(self.bit_depth)}
