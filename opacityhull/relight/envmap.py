"""Environment maps: reading, validating, orienting and integrating HDR light probes.

In memory an environment map is an equirectangular (latitude-longitude) float32 RGB
image in the project convention (DESIGN.md): +Y up, row 0 looks at the zenith, the
centre column looks along +Z and the column index grows towards −X, so that
``u = 0.25`` is +X and the seam (``u = 0`` / ``u = 1``) is −Z. This is the OpenEXR
``LatLongMap`` and Mitsuba ``envmap`` convention; texel (r, c) has its centre at

    θ = π (r + ½) / H          (polar angle from +Y)
    φ = 2π (c + ½) / W
    d = (sin θ sin φ, cos θ, −sin θ cos φ).

Radiance stays float32 end to end (a sun 10⁵× the median survives, half floats would
not); NaN, Inf and negative radiance are rejected with the file, the count and the
first offending texel. Other layouts are converted on reading: Debevec's *angular*
light-probe map and the *mirror*-ball image (both with +Z at the image centre, +X to
the right and +Y up, the formulas of https://www.pauldebevec.com/Probes/), and
horizontally mirrored lat-long maps (``flip_u``). ``yaw_deg`` rotates the map about +Y
after reading: the ICT probes in ``shared/data/probes`` put their centre at −Z, so
they need ``yaw_deg=180``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..envmap import direction_to_uv as _direction_to_uv
from ..envmap import default_yaw_deg, resolve_envmap_path
from ..errors import FormatError, InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = [
    "EnvironmentMap",
    "require_light",
    "PROBE_FORMATS",
    "load_envmap",
    "validate_radiance",
    "latlong_directions",
    "latlong_solid_angles",
    "direction_to_uv",
    "rotate_latlong_yaw",
    "angular_to_latlong",
    "mirrorball_to_latlong",
    "latlong_to_angular",
    "downsample_latlong",
    "sun_envmap",
    "resolve_envmap_path",
    "default_yaw_deg",
]

PROBE_FORMATS = ("latlong", "angular", "mirror")
ProbeFormat = Literal["latlong", "angular", "mirror"]


# --------------------------------------------------------------------------- geometry


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


def direction_to_uv(directions) -> tuple[np.ndarray, np.ndarray]:
    """Lat-long coordinates of directions (:func:`opacityhull.envmap.direction_to_uv`): a
    zero, NaN or Inf vector raises :class:`InputError` (a light direction that is a bug)."""
    return _direction_to_uv(directions, invalid="raise")


def _bilinear_latlong(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup, periodic in u, clamped in v. img (H, W, C); u, v same shape."""
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
    """An equirectangular HDR environment map in the project convention.

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

    def lookup(self, directions, *, interpolation: Literal["bilinear", "nearest"] = "bilinear") -> np.ndarray:
        """Radiance towards ``directions`` (..., 3) → (..., 3) float32."""
        u, v = direction_to_uv(directions)
        if interpolation == "nearest":
            c = np.minimum((u * self.width).astype(np.int64), self.width - 1)
            r = np.minimum((v * self.height).astype(np.int64), self.height - 1)
            return self.radiance[r, c]
        if interpolation != "bilinear":
            raise InputError(f"interpolation must be 'bilinear' or 'nearest', got {interpolation!r}")
        return _bilinear_latlong(self.radiance.astype(np.float64), u, v).astype(np.float32)

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


def _exr_is_half(path: Path) -> bool:
    """Whether the EXR stores half floats; only chooses the wording of the Inf error."""
    import OpenEXR

    from ..imageio import library_output

    try:
        with library_output(), OpenEXR.File(str(path), separate_channels=True) as f:
            return any(np.asarray(c.pixels).dtype == np.float16 for c in f.channels().values())
    except (OSError, RuntimeError, ValueError) as e:  # OpenEXR's bare RuntimeError on odd files
        log.debug("%s: cannot read the channel types (%s); Inf reported without the half-float hint", path, e)
        return False


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


def _supersampled_inverse_map(out_h: int, out_w: int, fetch, *, ss: int = 4) -> np.ndarray:
    """Average ``fetch(directions)`` over ss×ss sub-texels of each output lat-long texel."""
    acc = np.zeros((out_h, out_w, 3), np.float64)
    for i in range(ss):
        for j in range(ss):
            theta = (np.arange(out_h) + (i + 0.5) / ss) * (math.pi / out_h)
            phi = (np.arange(out_w) + (j + 0.5) / ss) * (2 * math.pi / out_w)
            st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
            d = np.stack(
                np.broadcast_arrays(st * np.sin(phi)[None], ct * np.ones((1, out_w)), -st * np.cos(phi)[None]), -1
            )
            # sub-texels are weighted by their own solid angle (∝ sin θ) so that the
            # texel value is the area mean
            acc += fetch(d) * st[..., None]
    norm = np.zeros((out_h, 1, 1))
    for i in range(ss):
        theta = (np.arange(out_h) + (i + 0.5) / ss) * (math.pi / out_h)
        norm[:, 0, 0] += ss * np.sin(theta)  # ss sub-columns per sub-row
    return (acc / norm).astype(np.float32)


def _bilinear_image(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup at pixel coordinates (centre of pixel (0,0) at (0,0)), clamped."""
    H, W = img.shape[:2]
    x = np.clip(x, 0, W - 1)
    y = np.clip(y, 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros_like(x, np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros_like(y, np.int64)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    im = img.astype(np.float64)
    return (im[y0, x0] * (1 - fx) + im[y0, x1] * fx) * (1 - fy) + (im[y1, x0] * (1 - fx) + im[y1, x1] * fx) * fy


def angular_to_latlong(img: np.ndarray, *, width: int | None = None, supersample: int = 4) -> np.ndarray:
    """Debevec angular map (square, +Z at the centre, −Z on the rim circle, +X right,
    +Y up; the radius in the disc is linear in the angle from +Z) → lat-long (H, 2H, 3).

    Each output texel is the area mean of ``supersample²`` bilinear lookups.
    """
    return _disc_probe_to_latlong(
        img, "angular map", lambda angle: angle / math.pi, width=width, supersample=supersample
    )


def _disc_probe_to_latlong(
    img: np.ndarray, what: str, radius_of_angle, *, width: int | None, supersample: int
) -> np.ndarray:
    """A square probe image whose disc holds direction d at radius ``radius_of_angle(angle(d, +Z))``
    (1 on the rim) along the direction of (dx, dy), +X right, +Y up → lat-long (H, 2H, 3)."""
    S = img.shape[0]
    if img.shape[1] != S:
        raise ShapeError(f"{what} must be square, got {img.shape[:2]}")
    W = int(width or 2 * S)
    H = max(1, W // 2)

    def fetch(d):
        dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
        s = np.hypot(dx, dy)
        r = np.where(s > 1e-12, radius_of_angle(np.arccos(np.clip(dz, -1, 1))) / np.maximum(s, 1e-12), 0.0)
        u, v = dx * r, dy * r  # in [-1, 1]
        return _bilinear_image(img, (u + 1) * 0.5 * S - 0.5, (1 - v) * 0.5 * S - 0.5)

    return _supersampled_inverse_map(H, W, fetch, ss=supersample)


def latlong_to_angular(latlong: np.ndarray, size: int) -> np.ndarray:
    """Inverse of :func:`angular_to_latlong` (used to make test probes): (size, size, 3),
    zero outside the disc."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    u, v = np.meshgrid(c, -c)
    r = np.hypot(u, v)
    theta = math.pi * r
    s = np.where(r > 1e-12, np.sin(theta) / np.maximum(r, 1e-12), math.pi)
    d = np.stack([u * s, v * s, np.cos(theta)], -1)
    uu, vv = direction_to_uv(d)
    out = _bilinear_latlong(np.asarray(latlong, np.float64), uu, vv)
    out[r > 1] = 0
    return out.astype(np.float32)


def mirrorball_to_latlong(img: np.ndarray, *, width: int | None = None, supersample: int = 4) -> np.ndarray:
    """Mirror-ball image (square, ball touching the edges, orthographic view from +Z:
    the centre reflects +Z, the rim −Z, +X right, +Y up) → lat-long (H, 2H, 3)."""
    # the normal bisects d and the view direction +Z: |(u, v)| = sin(angle(d, +Z) / 2)
    return _disc_probe_to_latlong(
        img, "mirror-ball image", lambda angle: np.sin(0.5 * angle), width=width, supersample=supersample
    )


def downsample_latlong(radiance: np.ndarray, factor: int, *, dtype: type[np.floating] = np.float32) -> np.ndarray:
    """Area-weighted box downsampling by an integer ``factor`` in both axes.

    Each coarse texel is the solid-angle-weighted mean of its fine texels, so
    ∫ L dω over the sphere is preserved to rounding (a sun keeps its power; it moves
    by at most half a coarse texel).
    """
    a = np.asarray(radiance, np.float64)
    H, W = a.shape[:2]
    if factor < 1 or H % factor or W % factor:
        raise InputError(f"downsample factor {factor} must divide the map size {W}x{H}")
    if factor == 1:
        return a.astype(dtype)
    w = latlong_solid_angles(H, W)[:, None, None]
    num = (a * w).reshape(H // factor, factor, W // factor, factor, 3).sum(axis=(1, 3))
    den = np.broadcast_to(w, (H, W, 1)).reshape(H // factor, factor, W // factor, factor, 1).sum(axis=(1, 3))
    return (num / den).astype(dtype)


# --------------------------------------------------------------------------- reading


def load_envmap(
    path,
    *,
    yaw_deg: float = 0.0,
    probe_format: ProbeFormat = "latlong",
    flip_u: bool = False,
    width: int | None = None,
) -> EnvironmentMap:
    """Read an environment map file into the project convention.

    Parameters
    ----------
    path : ``.exr`` (float or half) or Radiance ``.hdr``, or ``builtin:NAME`` for a
        shipped probe (its yaw is *not* implied here: see :func:`default_yaw_deg`).
    yaw_deg : rotation about +Y applied after conversion (ICT probes: 180).
    probe_format : ``"latlong"`` (equirectangular, 2:1), ``"angular"`` (Debevec
        angular map) or ``"mirror"`` (mirror-ball image); the latter two are resampled
        to lat-long of width ``width`` (default 2× their size).
    flip_u : the lat-long map is stored mirrored left-right (φ runs the other way).

    Raises
    ------
    InputError : NaN, Inf or negative radiance (with counts and the first texel), an
        unknown format, or a lat-long map that is not 2:1. A half-float EXR with Inf is
        reported as a half overflow (values above 65504 when it was saved).
    FormatError : unreadable file.
    """
    from ..imageio import read_image

    path = resolve_envmap_path(path)
    if probe_format not in PROBE_FORMATS:
        raise InputError(f"environment map {path}: probe format {probe_format!r}, expected one of {PROBE_FORMATS}")
    suffix = path.suffix.lower()
    if suffix not in (".exr", ".hdr", ".pic"):
        raise InputError(f"environment map {path}: expected an .exr or .hdr file, got {suffix!r}")
    img = read_image(path)
    if img.shape[2] == 4:
        img = img[..., :3]
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] != 3:
        raise FormatError(f"environment map {path}: {img.shape[2]} channels, expected RGB")
    if suffix == ".exr" and not np.all(np.isfinite(img)) and np.isinf(img).any() and _exr_is_half(path):
        n = int(np.isinf(img).sum())
        idx = np.argwhere(np.isinf(img))[0]
        raise InputError(
            f"environment map {path}: half-float EXR with {n} Inf values (first at row {idx[0]}, "
            f"column {idx[1]}): radiance above the half-float maximum 65504 overflowed when the "
            "file was saved; re-export it as 32-bit float EXR or scale it down"
        )
    validate_radiance(img, str(path))
    desc = path.name
    if probe_format == "latlong":
        if img.shape[1] != 2 * img.shape[0]:
            raise InputError(
                f"environment map {path}: lat-long maps are 2:1, got {img.shape[1]}x{img.shape[0]} "
                "(use --probe-format angular or mirror for light-probe images)"
            )
        if flip_u:
            img = img[:, ::-1]
            desc += " flipped"
    elif probe_format == "angular":
        img = angular_to_latlong(img, width=width)
        desc += " angular->latlong"
    else:
        img = mirrorball_to_latlong(img, width=width)
        desc += " mirror->latlong"
    env = EnvironmentMap(np.ascontiguousarray(img, dtype=np.float32), desc)
    return env.rotated(yaw_deg)


def sun_envmap(height: int, width: int, direction, radiance_rgb, *, background=0.0) -> EnvironmentMap:
    """A map with one bright texel (a "sun") at the texel containing ``direction`` over a
    constant ``background``: the hard case for aliasing."""
    img = np.full((height, width, 3), background, np.float32)
    u, v = direction_to_uv(np.asarray(direction, float))
    r = min(int(v * height), height - 1)
    c = min(int(u * width), width - 1)
    img[r, c] = np.asarray(radiance_rgb, np.float32)
    return EnvironmentMap(img, f"sun at {np.round(np.asarray(direction, float), 3).tolist()}")


def require_light(env: EnvironmentMap, what: str) -> None:
    """Refuse a map that sends no light (every texel zero): nothing to relight with, and
    every relative figure would divide by a zero truth.

    Raises
    ------
    InputError
        Naming the map's source."""
    if not np.any(env.radiance > 0):
        raise InputError(
            f"{what}: environment map {env.source} is all zero ({env.width}x{env.height} texels): "
            "expected some radiance > 0"
        )
