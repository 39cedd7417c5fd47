"""The one place of the environment-map convention: direction ↔ equirectangular (u, v).

Environment maps are equirectangular (lat-long), +Y up, the centre column looking along
+Z — the OpenEXR / Mitsuba convention (pinned against Mitsuba's own ``envmap`` emitter by
``tests/sim/test_sim_groundtruth.py``). A direction d = (x, y, z) maps to

    u = atan2(x, −z) / 2π  (wrapped to [0, 1)),   v = acos(y / |d|) / π,

so +Z is the centre column (u = ½), −Z the left/right seam, +X at u = ¼ (the map is seen
from inside), +Y the top row. Texel (i, j) has its centre at ((j + ½)/W, (i + ½)/H).

A zero, NaN or Inf direction has no (u, v): ``invalid="raise"`` (the default: lighting
code, where such a direction is a bug) raises :class:`InputError`; ``invalid="zenith"``
(backgrounds, where a degenerate pixel ray must not stop a render) maps it to the top
row, u = 0. Exactly at a pole u is undefined and set to 0 (every column is that point).

The render stage's backgrounds (``render/background.py``), the relighting and the
simulator's ground truth (``sim/groundtruth.py``) all convert through these two functions.

:class:`EnvironmentMap` is the one in-memory environment map, for backgrounds and for
lighting alike: (H, W, 3) float32 radiance, finite and ≥ 0, already turned to its
orientation (a yaw is applied once, by :meth:`EnvironmentMap.rotated`, a column shift;
lookups never rotate), looked up bilinearly in float64 (wrapping across the seam,
clamping at the poles). Reading files and light-probe layouts lives in
``relight/envmap.py`` (:func:`~opacityhull.relight.envmap.load_envmap`) and, for
backgrounds, ``render/background.py`` (``load_background``).

A map given by name (``builtin:NAME``, a probe shipped in :mod:`opacityhull.data`) is
resolved here too, for every command that takes one (``render --background``,
``relight --envmap``, ``view --envmap``): :func:`resolve_envmap_path` and its yaw,
:func:`default_yaw_deg`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from .errors import InputError, ShapeError

__all__ = [
    "EnvironmentMap",
    "direction_to_uv",
    "uv_to_direction",
    "latlong_directions",
    "latlong_solid_angles",
    "bilinear_latlong",
    "rotate_latlong_yaw",
    "validate_radiance",
    "resolve_envmap_path",
    "default_yaw_deg",
    "is_builtin_probe",
]


def is_builtin_probe(spec) -> bool:
    """Whether ``spec`` names a shipped probe (``builtin:NAME``)."""
    return isinstance(spec, str) and spec.strip().startswith("builtin:")


def resolve_envmap_path(spec) -> Path:
    """A path, or ``builtin:NAME`` for a probe shipped with the package
    (:func:`opacityhull.data.probe_path`: ennis, grace, pisa, uffizi, wells; an unknown
    name is an :class:`InputError` listing them)."""
    if is_builtin_probe(spec):
        from .data import probe_path

        return probe_path(spec.strip())
    return Path(spec)


def default_yaw_deg(spec) -> float:
    """The yaw that brings ``spec`` to the project convention when the user gives none:
    180° for the shipped ICT-convention probes (``builtin:NAME``), else 0."""
    if is_builtin_probe(spec):
        from .data import PROBE_YAW_DEG

        return PROBE_YAW_DEG
    return 0.0


def direction_to_uv(directions, *, invalid: Literal["raise", "zenith"] = "raise") -> tuple[np.ndarray, np.ndarray]:
    """(…, 3) directions (any length) → (u, v), u ∈ [0, 1), v ∈ [0, 1] (module docstring)."""
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ShapeError(f"directions have shape {d.shape}, expected (..., 3)")
    n = np.linalg.norm(d, axis=-1)
    bad = ~np.isfinite(n) | (n < 1e-12)
    if np.any(bad):
        if invalid == "raise":
            raise InputError(
                f"{int(np.count_nonzero(bad))} direction(s) are zero, NaN or Inf; expected finite non-zero vectors"
            )
        if invalid != "zenith":
            raise InputError(f"invalid={invalid!r}: expected 'raise' or 'zenith'")
        d = np.where(bad[..., None], np.array([0.0, 1.0, 0.0]), d)
        n = np.where(bad, 1.0, n)
    # atan2 of (distance from the axis, height) rather than arccos(y / n): arccos loses
    # all precision within ~1e-8 rad of the poles (1 − cos θ falls below the float64 step)
    v = np.arctan2(np.hypot(d[..., 0], d[..., 2]), d[..., 1]) / math.pi
    u = np.arctan2(d[..., 0], -d[..., 2]) / (2.0 * math.pi)
    u = u - np.floor(u)
    u = np.where(u >= 1.0, 0.0, u)  # -0.0 and rounding can give exactly 1
    return u, v


def uv_to_direction(u, v) -> np.ndarray:
    """Inverse of :func:`direction_to_uv`: unit directions (…, 3) of (u, v)."""
    phi = 2.0 * math.pi * np.asarray(u, dtype=np.float64)
    theta = math.pi * np.asarray(v, dtype=np.float64)
    s = np.sin(theta)
    return np.stack(np.broadcast_arrays(s * np.sin(phi), np.cos(theta), -s * np.cos(phi)), axis=-1)


# --------------------------------------------------------------------------- texel geometry


def latlong_directions(height: int, width: int) -> np.ndarray:
    """Unit directions of texel centres, (H, W, 3) float64, project convention."""
    theta = (np.arange(height) + 0.5) * (math.pi / height)
    phi = (np.arange(width) + 0.5) * (2.0 * math.pi / width)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    sp, cp = np.sin(phi)[None, :], np.cos(phi)[None, :]
    return np.stack(np.broadcast_arrays(st * sp, ct * np.ones_like(sp), -st * cp), axis=-1)


def latlong_solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle of each texel row, (H,) float64 steradians.

    Exact for the row's band: ``(2π / W) (cos θ₀ − cos θ₁)`` (the integral of sin θ
    over the row), so the rows sum to 4π to rounding — the sin θ-at-the-centre rule
    would be off by O(Δθ²) and never exactly 4π.
    """
    edges = np.arange(height + 1) * (math.pi / height)
    return (2.0 * math.pi / width) * (np.cos(edges[:-1]) - np.cos(edges[1:]))


def bilinear_latlong(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup, periodic in u, clamped in v. img (H, W, C); u, v same shape; float64
    (float32 texels promote exactly)."""
    H, W = img.shape[:2]
    x = u * W - 0.5
    y = np.clip(v * H - 0.5, 0.0, H - 1.0)
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x0 = x0.astype(np.int64) % W
    x1 = (x0 + 1) % W
    y0 = y0.astype(np.int64)
    y1 = np.minimum(y0 + 1, H - 1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


# --------------------------------------------------------------------------- class


@dataclass(frozen=True, eq=False)
class EnvironmentMap:
    """An equirectangular HDR environment map in the project convention (module
    docstring): the one class for render backgrounds and relighting.

    Attributes
    ----------
    radiance : (H, W, 3) float32, linear Rec.709 radiance, finite and ≥ 0.
    source : str, where it came from (file name and conversions), for messages.
    """

    radiance: np.ndarray
    source: str = "<array>"

    def __post_init__(self):
        a = np.asarray(self.radiance)
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
            raise ShapeError(f"environment map {self.source} has shape {a.shape}, expected (H, W, 3)")
        a = np.array(a, dtype=np.float32, order="C", copy=True)  # never freeze the caller's array
        validate_radiance(a, self.source)
        a.setflags(write=False)
        object.__setattr__(self, "radiance", a)

    @property
    def height(self) -> int:
        return self.radiance.shape[0]

    @property
    def width(self) -> int:
        return self.radiance.shape[1]

    def directions(self) -> np.ndarray:
        """(H, W, 3) float64 unit directions of the texel centres."""
        return latlong_directions(self.height, self.width)

    def solid_angles(self) -> np.ndarray:
        """(H, W) float64 per-texel solid angles in steradians (sum 4π)."""
        return np.broadcast_to(latlong_solid_angles(self.height, self.width)[:, None], (self.height, self.width))

    def lookup(
        self,
        directions,
        *,
        interpolation: Literal["bilinear", "nearest"] = "bilinear",
        invalid: Literal["raise", "zenith"] = "raise",
    ) -> np.ndarray:
        """Radiance towards ``directions`` (..., 3), any length → (..., 3) float32.

        ``invalid``: what a zero, NaN or Inf direction does (:func:`direction_to_uv`):
        raise (lighting) or see the zenith (backgrounds: a degenerate pixel ray must not
        stop a render). Bilinear weights are float64 (the float32 texels promote
        exactly), the result is rounded to float32 once.
        """
        u, v = direction_to_uv(directions, invalid=invalid)
        if interpolation == "nearest":
            c = np.minimum((u * self.width).astype(np.int64), self.width - 1)
            r = np.minimum((v * self.height).astype(np.int64), self.height - 1)
            return self.radiance[r, c]
        if interpolation != "bilinear":
            raise InputError(f"interpolation must be 'bilinear' or 'nearest', got {interpolation!r}")
        return bilinear_latlong(self.radiance, u, v).astype(np.float32)

    def integral(self, *, upper_only: bool = False) -> np.ndarray:
        """∫ L dω over the sphere (or the upper hemisphere, θ < 90°), (3,) float64.

        With ``upper_only`` a row straddling the horizon (odd H) counts half.
        """
        w = latlong_solid_angles(self.height, self.width)
        if upper_only:
            w = w * _upper_fraction(self.height)
        return np.einsum("h,hwc->c", w, self.radiance.astype(np.float64))

    def rotated(self, yaw_deg: float) -> EnvironmentMap:
        """The map turned by ``yaw_deg`` about +Y (+Z towards +X): the radiance that came
        from d now comes from R_y(yaw) d."""
        if yaw_deg % 360.0 == 0.0:
            return self
        return EnvironmentMap(rotate_latlong_yaw(self.radiance, yaw_deg), f"{self.source} yaw {yaw_deg:g}")

    def scaled(self, factor: float) -> EnvironmentMap:
        return EnvironmentMap(self.radiance * np.float32(factor), f"{factor:g} x {self.source}")

    def stats(self) -> dict:
        lum = self.radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        med = float(np.median(lum))
        return {
            "source": self.source,
            "size": [self.width, self.height],
            "max": float(self.radiance.max()),
            "median_luminance": med,
            "dynamic_range": float(lum.max() / med) if med > 0 else None,
            "integral_rgb": self.integral().tolist(),
        }


def _upper_fraction(height: int) -> np.ndarray:
    """(H,) fraction of each row's solid angle above the horizon (θ < π/2)."""
    edges = np.arange(height + 1) * (math.pi / height)
    c0, c1 = np.cos(edges[:-1]), np.cos(edges[1:])
    # fraction of ∫ sin θ over the row with cos θ > 0
    up = np.clip(c0, 0, None) - np.clip(c1, 0, None)
    return np.where(c0 - c1 > 0, up / (c0 - c1), 0.0)


# --------------------------------------------------------------------------- validation


def validate_radiance(radiance: np.ndarray, where: str) -> None:
    """Raise :class:`InputError` unless every value is finite and ≥ 0.

    The message names ``where``, the number of bad values and the first bad texel
    (row, column, channel), because a single Inf texel would turn every relit pixel
    into Inf or NaN.
    """
    a = np.asarray(radiance)
    bad_nan = np.isnan(a)
    bad_inf = np.isinf(a)
    if bad_nan.any() or bad_inf.any():
        idx = np.argwhere(bad_nan | bad_inf)[0]
        raise InputError(
            f"environment map {where}: {int(bad_nan.sum())} NaN and {int(bad_inf.sum())} Inf values "
            f"(first at row {idx[0]}, column {idx[1]}, channel {'RGB'[idx[2]] if len(idx) > 2 else 0}); "
            "radiance must be finite"
        )
    neg = a < 0
    if neg.any():
        idx = np.argwhere(neg)[0]
        raise InputError(
            f"environment map {where}: {int(neg.sum())} negative radiance values "
            f"(min {float(a.min()):.6g}, first at row {idx[0]}, column {idx[1]}, "
            f"channel {'RGB'[idx[2]] if len(idx) > 2 else 0}); radiance must be >= 0"
        )


# --------------------------------------------------------------------------- orientation


def rotate_latlong_yaw(radiance: np.ndarray, yaw_deg: float) -> np.ndarray:
    """Rotate an equirectangular map about +Y: ``out(R_y(yaw) d) = in(d)``.

    R_y(α) d(φ) = d(φ − α), so out(φ) = in(φ + α): a shift of the columns by
    α W / 360. Whole-texel shifts are an exact ``np.roll``; fractional ones are
    linear interpolation along the (periodic) rows, which keeps each row's integral
    exactly.
    """
    a = np.asarray(radiance, dtype=np.float32)
    W = a.shape[1]
    shift = (float(yaw_deg) / 360.0) * W  # out[c] = in[c + shift]
    k = math.floor(shift)
    f = shift - k
    out = np.roll(a, -k, axis=1)
    if f > 1e-9:
        out = (1.0 - f) * out + f * np.roll(out, -1, axis=1)
    return np.ascontiguousarray(out, dtype=np.float32)
