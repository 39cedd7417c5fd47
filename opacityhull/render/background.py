"""Backgrounds for compositing: a colour, an image, or an environment map.

An environment map is :class:`opacityhull.envmap.EnvironmentMap` (the core's one class,
shared with relighting): equirectangular, +Y up, the centre column looking along +Z (the
OpenEXR / Mitsuba convention, :mod:`opacityhull.envmap`), already turned by its yaw when
it was loaded (:func:`load_background`). Lookups are bilinear, wrapping across the seam
and clamping at the poles; a degenerate pixel ray sees the zenith.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..envmap import EnvironmentMap, direction_to_uv, uv_to_direction
from ..errors import InputError

__all__ = [
    "envmap_background",
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


def envmap_background(env: EnvironmentMap, camera: Camera) -> np.ndarray:
    """(H, W, 3) float32: what ``camera`` sees of ``env`` (one ray per pixel centre)."""
    _, d = camera.pixel_rays()
    return env.lookup(d, invalid="zenith")


def resolve_background(background, camera: Camera) -> np.ndarray:
    """A background as an (H, W, 3) float32 image for ``camera``.

    ``background`` may be None (black), a number (grey), a sequence of 3 numbers (linear
    RGB), an (H, W, 3|4) image of the camera's size, or an
    :class:`~opacityhull.envmap.EnvironmentMap`.
    """
    H, W = camera.height, camera.width
    if background is None:
        return np.zeros((H, W, 3), np.float32)
    if isinstance(background, EnvironmentMap):
        return envmap_background(background, camera)
    if isinstance(background, (int, float, np.floating, np.integer)):
        return np.full((H, W, 3), float(background), np.float32)
    a = np.asarray(background, dtype=np.float32)
    if a.shape == (3,):
        return np.broadcast_to(a, (H, W, 3)).copy()
    if a.ndim == 3 and a.shape[:2] == (H, W) and a.shape[2] in (3, 4):
        return np.ascontiguousarray(a[:, :, :3])
    raise InputError(
        f"background of shape {a.shape}: expected a colour (3,), an image ({H}, {W}, 3|4) or an EnvironmentMap"
    )


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
    else as a backdrop image. An environment map comes back as an
    :class:`~opacityhull.envmap.EnvironmentMap` already turned by ``yaw_deg`` (None: the
    map's default, :func:`opacityhull.envmap.default_yaw_deg`: 180° for the shipped ICT
    probes, else 0); its radiance must be finite and ≥ 0 (:class:`InputError` naming the
    file and the first bad texel)."""
    from ..envmap import default_yaw_deg, is_builtin_probe, resolve_envmap_path
    from ..imageio import read_image

    if yaw_deg is None:
        yaw_deg = default_yaw_deg(spec)
    if is_builtin_probe(spec):
        path = resolve_envmap_path(spec)
        return _envmap(read_image(path), path, yaw_deg)

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
        return _envmap(img, p, yaw_deg)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return img[:, :, :3]


def _envmap(img: np.ndarray, path: Path, yaw_deg: float) -> EnvironmentMap:
    """An image read from ``path`` as a map turned by ``yaw_deg`` (grey repeated to RGB,
    alpha dropped)."""
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return EnvironmentMap(img[:, :, :3], str(path)).rotated(yaw_deg)


def fit_image(image: np.ndarray, camera: Camera) -> np.ndarray:
    """Resize a backdrop image to the camera's size (area filter when shrinking)."""
    import cv2

    if image.shape[:2] == (camera.height, camera.width):
        return image
    shrink = image.shape[0] > camera.height
    return cv2.resize(
        image, (camera.width, camera.height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )
