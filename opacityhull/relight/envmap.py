"""Environment maps from files: reading, validating and converting HDR light probes.

The in-memory map is :class:`opacityhull.envmap.EnvironmentMap` (the core: one class
for render backgrounds and relighting): an equirectangular (latitude-longitude) float32
RGB image in the project convention (DESIGN.md): +Y up, row 0 looks at the zenith, the
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
from pathlib import Path
from typing import Literal

import numpy as np

from ..envmap import (
    EnvironmentMap,
    bilinear_latlong,
    default_yaw_deg,
    direction_to_uv,
    latlong_solid_angles,
    resolve_envmap_path,
    validate_radiance,
)
from ..errors import FormatError, InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = [
    "require_light",
    "PROBE_FORMATS",
    "load_envmap",
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


# --------------------------------------------------------------------------- file checks


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


# --------------------------------------------------------------------------- probe layouts


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
    out = bilinear_latlong(np.asarray(latlong, np.float64), uu, vv)
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
