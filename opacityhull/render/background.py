"""Backgrounds for compositing: a colour, an image, or an environment map.

Environment maps are equirectangular (lat-long), +Y up, the centre column looking along
+Z — the OpenEXR / Mitsuba convention. A direction d = (x, y, z) maps to

    u = atan2(x, −z) / 2π  (wrapped to [0, 1)),   v = acos(y) / π,

so +Z is the centre column, −Z the left/right seam, +X a quarter of the width left of
centre (the map is seen from inside), +Y the top row. Texel (i, j) has its centre at
((j + 0.5)/W, (i + 0.5)/H). Lookups are bilinear, wrapping across the seam and clamping at
the poles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera, rot_y
from ..envmap import direction_to_uv, uv_to_direction
from ..errors import InputError, ShapeError

__all__ = [
    "EnvMap",
    "envmap_lookup",
    "direction_to_equirect",
    "equirect_to_direction",
    "resolve_background",
    "composite_over",
]


def direction_to_equirect(directions) -> tuple[np.ndarray, np.ndarray]:
    """(…, 3) directions → (u, v) in [0, 1) × [0, 1]: :func:`opacityhull.envmap.direction_to_uv`
    with degenerate rays mapped to the zenith (a background never stops a render)."""
    return direction_to_uv(directions, invalid="zenith")


def equirect_to_direction(u, v) -> np.ndarray:
    """Inverse of :func:`direction_to_equirect`: unit directions (…, 3)."""
    return uv_to_direction(u, v)


def envmap_lookup(image, directions, *, yaw_deg: float = 0.0) -> np.ndarray:
    """Bilinear radiance of an equirectangular map in the given directions.

    Parameters
    ----------
    image : (h, w, C) float array, equirectangular (module convention).
    directions : (…, 3) world directions (need not be unit).
    yaw_deg : the map is rotated by ``yaw_deg`` about +Y before the lookup (a direction
        d sees what the unrotated map shows at ``R_y(−yaw) d``). ICT light probes put
        their centre at −Z: use 180.

    Returns
    -------
    (…, C) float32.
    """
    env = np.asarray(image, dtype=np.float32)
    if env.ndim == 2:
        env = env[:, :, None]
    if env.ndim != 3 or env.shape[0] < 1 or env.shape[1] < 1:
        raise ShapeError(f"environment map has shape {np.shape(image)}, expected (h, w, C)")
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1] != 3:
        raise ShapeError(f"directions have shape {d.shape}, expected (..., 3)")
    if yaw_deg:
        d = d @ rot_y(math.radians(-yaw_deg)).T
    h, w = env.shape[:2]
    u, v = direction_to_equirect(d)
    x = u * w - 0.5
    y = v * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    ax = (x - x0)[..., None].astype(np.float32)
    ay = (y - y0)[..., None].astype(np.float32)
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    xa = np.mod(x0, w)  # wrap across the seam
    xb = np.mod(x0 + 1, w)
    ya = np.clip(y0, 0, h - 1)  # clamp at the poles
    yb = np.clip(y0 + 1, 0, h - 1)
    out = (
        env[ya, xa] * (1 - ax) * (1 - ay)
        + env[ya, xb] * ax * (1 - ay)
        + env[yb, xa] * (1 - ax) * ay
        + env[yb, xb] * ax * ay
    )
    return out.astype(np.float32)


@dataclass(frozen=True, eq=False)
class EnvMap:
    """An equirectangular environment map used as a background (or for lighting).

    Attributes
    ----------
    image : (h, w, 3) float32 linear RGB.
    yaw_deg : rotation about +Y applied at lookup (see :func:`envmap_lookup`).
    """

    image: np.ndarray
    yaw_deg: float = 0.0

    def __post_init__(self):
        a = np.asarray(self.image, dtype=np.float32)
        if a.ndim != 3 or a.shape[2] < 3:
            raise ShapeError(f"environment map has shape {a.shape}, expected (h, w, 3)")
        object.__setattr__(self, "image", np.ascontiguousarray(a[:, :, :3]))

    @classmethod
    def from_file(cls, path, *, yaw_deg: float = 0.0) -> EnvMap:
        from ..imageio import read_image

        return cls(read_image(path), yaw_deg=yaw_deg)

    def lookup(self, directions) -> np.ndarray:
        return envmap_lookup(self.image, directions, yaw_deg=self.yaw_deg)

    def render(self, camera: Camera) -> np.ndarray:
        """(H, W, 3) what ``camera`` sees of the environment (one ray per pixel centre)."""
        _, d = camera.pixel_rays()
        return self.lookup(d)


def resolve_background(background, camera: Camera) -> np.ndarray:
    """A background as an (H, W, 3) float32 image for ``camera``.

    ``background`` may be None (black), a number (grey), a sequence of 3 numbers (linear
    RGB), an (H, W, 3|4) image of the camera's size, or an :class:`EnvMap`.
    """
    H, W = camera.height, camera.width
    if background is None:
        return np.zeros((H, W, 3), np.float32)
    if isinstance(background, EnvMap):
        return background.render(camera)
    if isinstance(background, (int, float, np.floating, np.integer)):
        return np.full((H, W, 3), float(background), np.float32)
    a = np.asarray(background, dtype=np.float32)
    if a.shape == (3,):
        return np.broadcast_to(a, (H, W, 3)).copy()
    if a.ndim == 3 and a.shape[:2] == (H, W) and a.shape[2] in (3, 4):
        return np.ascontiguousarray(a[:, :, :3])
    raise InputError(f"background of shape {a.shape}: expected a colour (3,), an image ({H}, {W}, 3|4) or an EnvMap")


def composite_over(rgba_straight, background_rgb) -> np.ndarray:
    """``C·α + B·(1 − α)`` for straight RGBA (H, W, 4) over an (H, W, 3) background."""
    a = np.asarray(rgba_straight, dtype=np.float32)
    alpha = np.clip(a[..., 3:4], 0.0, 1.0)
    return (a[..., :3] * alpha + np.asarray(background_rgb, np.float32) * (1.0 - alpha)).astype(np.float32)


def load_background(spec: str, *, yaw_deg: float | None = None, kind: str = "auto"):
    """Parse a CLI background: a colour (``0.2,0.3,0.4``, ``0.5``, ``#rrggbb``,
    ``black``/``white``/``grey``), an image path, or ``builtin:NAME`` (a shipped probe,
    as ``relight --envmap`` takes it: :func:`opacityhull.envmap.resolve_envmap_path`).
    ``kind='auto'`` treats a ``.hdr`` or a 2:1 EXR as an environment map and anything
    else as a backdrop image. ``yaw_deg`` None: the map's default
    (:func:`opacityhull.envmap.default_yaw_deg`: 180° for the shipped ICT probes, else 0)."""
    from ..envmap import default_yaw_deg, is_builtin_probe, resolve_envmap_path
    from ..imageio import read_image

    if yaw_deg is None:
        yaw_deg = default_yaw_deg(spec)
    if is_builtin_probe(spec):
        return EnvMap(read_image(resolve_envmap_path(spec)), yaw_deg=yaw_deg)

    names = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "grey": (0.18, 0.18, 0.18), "gray": (0.18, 0.18, 0.18)}
    s = spec.strip()
    if s.lower() in names:
        return names[s.lower()]
    if s.startswith("#") and len(s) == 7:
        try:
            from ..imageio import srgb_decode

            rgb = [int(s[i : i + 2], 16) / 255.0 for i in (1, 3, 5)]
            return tuple(float(x) for x in srgb_decode(np.array(rgb)))
        except ValueError:
            raise InputError(f"--background {spec!r}: not a #rrggbb colour") from None
    parts = s.split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = None
    if vals is not None:
        if len(vals) == 1:
            return (vals[0],) * 3
        if len(vals) == 3:
            return tuple(vals)
        raise InputError(f"--background {spec!r}: a colour needs 1 or 3 numbers")
    p = Path(s)
    if not p.is_file():
        raise InputError(f"--background {spec!r}: neither a colour nor an existing image file")
    img = read_image(p)
    if kind not in ("auto", "image", "envmap"):
        raise InputError(f"--background-kind {kind!r}: expected auto, image or envmap")
    is_env = kind == "envmap" or (
        kind == "auto"
        and (p.suffix.lower() in (".hdr", ".pic") or (p.suffix.lower() == ".exr" and img.shape[1] == 2 * img.shape[0]))
    )
    if is_env:
        return EnvMap(img, yaw_deg=yaw_deg)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return img[:, :, :3]


def fit_image(image: np.ndarray, camera: Camera) -> np.ndarray:
    """Resize a backdrop image to the camera's size (area filter when shrinking)."""
    import cv2

    if image.shape[:2] == (camera.height, camera.width):
        return image
    shrink = image.shape[0] > camera.height
    return cv2.resize(
        image, (camera.width, camera.height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )
