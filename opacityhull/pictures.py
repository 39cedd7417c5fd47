"""Pictures for people: sRGB 8-bit tiles, labelled contact sheets and animations.

Every contact sheet and animation the stages write goes through here, so labels,
column headers, colour bars and frame rates look and behave the same everywhere.

* :func:`to_srgb8` — linear (or display-linear) [0, 1] RGB → sRGB-encoded uint8.
* :func:`encoded_to_u8` — already sRGB-encoded [0, 1] values (colour maps) → uint8.
* :func:`heat` — a scalar error map through a matplotlib colour map → uint8.
* :func:`contact_sheet` — uint8 tiles in a grid with per-tile labels, optional column
  headers and an optional :class:`ColorBar`; :func:`write_sheet` writes it as PNG.
* :func:`write_animation` — frames at a given ``fps`` as a looping GIF (delay
  ``100 / fps`` centiseconds, GIF's unit) or, where an ffmpeg writer exists, an MP4.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast
from collections.abc import Sequence

import numpy as np

from .errors import InputError
from .imageio import atomic_path, srgb_encode, write_png

log = logging.getLogger(__name__)

__all__ = [
    "ColorBar",
    "auto_exposure",
    "to_srgb8",
    "encoded_to_u8",
    "heat",
    "label_tile",
    "contact_sheet",
    "write_sheet",
    "write_animation",
]

_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX, without importing cv2 at module import


@dataclass(frozen=True, kw_only=True)
class ColorBar:
    """A horizontal colour bar under a contact sheet: ``cmap`` from ``vmin`` to ``vmax``,
    captioned ``label`` (say what the colours measure and in which unit)."""

    cmap: str = "inferno"
    vmin: float = 0.0
    vmax: float = 1.0
    label: str = ""


def auto_exposure(rgb_premul: np.ndarray, alpha: np.ndarray, *, key: float = 0.18) -> float:
    """Exposure multiplier mapping the log-average luminance of the object (alpha >
    0.5) to ``key`` (Reinhard's key value); 1 when the object is black or absent.

    ``rgb_premul`` is (H, W, 3) premultiplied linear RGB, ``alpha`` (H, W)."""
    lum = np.asarray(rgb_premul[..., :3], np.float64) @ [0.2126, 0.7152, 0.0722]
    m = np.asarray(alpha) > 0.5
    if not m.any():
        return 1.0
    a = np.clip(np.asarray(alpha)[m], 1e-6, None)
    L = lum[m] / a
    L = L[L > 0]
    if L.size == 0:
        return 1.0
    return float(key / math.exp(np.mean(np.log(L + 1e-12))))


def to_srgb8(rgb, *, exposure: float = 1.0) -> np.ndarray:
    """(H, W, C≥3) linear RGB(A) → (H, W, 3) uint8 sRGB: × ``exposure``, clipped to
    [0, 1] (NaN → 0), IEC 61966-2-1 encoded, rounded. Alpha is dropped."""
    a = np.asarray(rgb, np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] < 3:
        raise InputError(f"to_srgb8: image of shape {a.shape}, expected (H, W) or (H, W, C>=3)")
    return np.round(srgb_encode(a[..., :3] * np.float32(exposure)) * 255.0).astype(np.uint8)


def encoded_to_u8(encoded) -> np.ndarray:
    """Already display-encoded values in [0, 1] (sRGB colours, colour-map output) →
    uint8, clipped, NaN → 0, grey (H, W) expanded to three channels."""
    a = np.nan_to_num(np.asarray(encoded, np.float32), nan=0.0)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    return np.round(np.clip(a[..., :3], 0.0, 1.0) * 255.0).astype(np.uint8)


def heat(values, *, vmin: float = 0.0, vmax: float = 1.0, cmap: str = "inferno") -> np.ndarray:
    """(H, W) scalars → (H, W, 3) uint8 through the matplotlib colour map ``cmap``,
    ``vmin`` → the first colour, ``vmax`` → the last (clipped; NaN → ``vmin``)."""
    import matplotlib

    if not (math.isfinite(vmin) and math.isfinite(vmax) and vmax > vmin):
        raise InputError(f"heat: vmin {vmin}, vmax {vmax}: expected finite vmin < vmax")
    v = np.nan_to_num(np.asarray(values, np.float64), nan=vmin)
    t = np.clip((v - vmin) / (vmax - vmin), 0.0, 1.0)
    return encoded_to_u8(matplotlib.colormaps[cmap](t)[..., :3])


def _text_size(text: str, scale: float) -> tuple[int, int, int]:
    import cv2

    (tw, th), base = cv2.getTextSize(text, _FONT, scale, 1)
    return tw, th, base


def _put_text(img8: np.ndarray, text: str, x: int, y: int, scale: float) -> None:
    import cv2

    cv2.putText(img8, text, (x, y), _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)


def label_tile(tile8: np.ndarray, text: str, *, scale: float = 0.4) -> np.ndarray:
    """Copy of ``tile8`` with ``text`` in white on a darkened band along its top (so it
    reads on any content); the font shrinks to fit the tile's width."""
    out = np.ascontiguousarray(tile8, dtype=np.uint8).copy()
    if not text:
        return out
    tw, th, base = _text_size(text, scale)
    if tw > out.shape[1] - 4:
        scale *= max(out.shape[1] - 4, 1) / tw
        tw, th, base = _text_size(text, scale)
    band = min(out.shape[0], th + base + 4)
    out[:band] = (out[:band].astype(np.float32) * 0.35).round().astype(np.uint8)
    _put_text(out, text, 2, th + 2, scale)
    return out


def _as_tile(i: int, t) -> np.ndarray:
    a = np.asarray(t)
    if a.dtype != np.uint8:
        raise InputError(
            f"contact sheet tile {i}: dtype {a.dtype}, expected uint8 (convert with to_srgb8, encoded_to_u8 or heat)"
        )
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] < 3 or a.shape[0] == 0 or a.shape[1] == 0:
        raise InputError(f"contact sheet tile {i}: shape {a.shape}, expected (H, W) or (H, W, 3) non-empty")
    return a[..., :3]


def _resize(a: np.ndarray, fx: float) -> np.ndarray:
    import cv2

    h, w = a.shape[:2]
    size = (max(1, int(round(w * fx))), max(1, int(round(h * fx))))
    return cv2.resize(a, size, interpolation=cv2.INTER_AREA if fx < 1 else cv2.INTER_NEAREST)


def _header_strip(headers: Sequence[str], cols: int, w: int, gap: int, width: int, background: int) -> np.ndarray:
    scale = 0.45
    th = max(_text_size(h, scale)[1] for h in headers if h) if any(headers) else _text_size("X", scale)[1]
    strip = np.full((th + 10, width, 3), background, np.uint8)
    for c, text in enumerate(headers[:cols]):
        if not text:
            continue
        s = scale
        tw = _text_size(text, s)[0]
        if tw > w - 4:
            s *= max(w - 4, 1) / tw
            tw = _text_size(text, s)[0]
        x0 = gap + c * (w + gap) + max(0, (w - tw) // 2)
        _put_text(strip, text, x0, th + 4, s)
    return strip


def _colorbar_strip(bar: ColorBar, width: int, gap: int, background: int) -> np.ndarray:
    scale = 0.4
    lo, hi = f"{bar.vmin:.3g}", f"{bar.vmax:.3g}"
    _, th, base = _text_size("0", scale)
    bar_h = 12
    h = gap + bar_h + 4 + th + base + 4
    strip = np.full((h, width, 3), background, np.uint8)
    margin = gap + 4
    span = max(1, width - 2 * margin)
    ramp = heat(np.linspace(bar.vmin, bar.vmax, span)[None, :], vmin=bar.vmin, vmax=bar.vmax, cmap=bar.cmap)
    strip[gap : gap + bar_h, margin : margin + span] = ramp
    y = gap + bar_h + 4 + th
    _put_text(strip, lo, margin, y, scale)
    tw_hi = _text_size(hi, scale)[0]
    _put_text(strip, hi, max(margin, margin + span - tw_hi), y, scale)
    if bar.label:
        tw = _text_size(bar.label, scale)[0]
        _put_text(strip, bar.label, max(margin, margin + (span - tw) // 2), y, scale)
    return strip


#: Colour of the warnings a sheet carries (:func:`contact_sheet` ``notes``), sRGB 8-bit.
WARNING_RGB = (255, 200, 40)


def _ascii(text: str) -> str:
    """``text`` for OpenCV's ASCII-only font: dashes, quotes and comparison signs spelled
    in ASCII, anything else left as "?"."""
    table = {"—": "-", "–": "-", "’": "'", "‘": "'", "“": '"', "”": '"', "≤": "<=", "≥": ">=", "×": "x", "°": " deg"}
    return "".join(table.get(c, c) for c in text).encode("ascii", "replace").decode("ascii")


def _wrap(text: str, scale: float, width: int) -> list[str]:
    """``text`` broken into lines at most ``width`` px wide at ``scale`` (word wrap)."""
    lines: list[str] = []
    for word in text.split():
        if lines and _text_size(f"{lines[-1]} {word}", scale)[0] <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines or [""]


def _notes_strip(notes: Sequence[str], width: int, gap: int, background: int) -> np.ndarray:
    """The sheet's warnings, word-wrapped, in :data:`WARNING_RGB` on the sheet's
    background: what the terminal said about the picture, printed on it."""
    import cv2

    scale = 0.42
    _, th, base = _text_size("Xg", scale)
    # OpenCV's Hershey font is ASCII only: a dash or ≤ would print as "?"
    ascii_ = [_ascii(n) for n in notes]
    lines = [ln for n in ascii_ for ln in _wrap(f"warning: {n}", scale, max(1, width - 2 * gap - 8))]
    line_h = th + base + 4
    strip = np.full((gap + 4 + line_h * len(lines) + 2, width, 3), background, np.uint8)
    for i, ln in enumerate(lines):
        y = gap + 4 + th + i * line_h
        cv2.putText(strip, ln, (gap + 4, y), _FONT, scale, WARNING_RGB, 1, cv2.LINE_AA)
    return strip


def _legend_strip(legend: Sequence[tuple[tuple[int, int, int], str]], width: int, gap: int, background: int):
    """One row of (colour swatch, meaning) pairs: what the colours drawn on the tiles
    mean; wraps onto more rows when the sheet is narrow."""
    import cv2

    scale = 0.42
    _, th, base = _text_size("Xg", scale)
    sw, pad = 14, 12
    items = [(tuple(int(c) for c in colour), str(text)) for colour, text in legend]
    rows: list[list[tuple[tuple[int, ...], str]]] = [[]]
    used = gap + 4
    for colour, text in items:
        w = sw + 6 + _text_size(text, scale)[0] + pad
        if rows[-1] and used + w > width - gap:
            rows.append([])
            used = gap + 4
        rows[-1].append((colour, text))
        used += w
    line_h = max(sw, th + base) + 6
    strip = np.full((gap + 4 + line_h * len(rows), width, 3), background, np.uint8)
    for r, row in enumerate(rows):
        x, y0 = gap + 4, gap + 4 + r * line_h
        for colour, text in row:
            ym = y0 + th // 2
            strip[ym : ym + 3, x : x + sw] = colour  # a line sample, as drawn on the tiles
            cv2.putText(strip, text, (x + sw + 6, y0 + th + 1), _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)
            x += sw + 6 + _text_size(text, scale)[0] + pad
    return strip


def contact_sheet(
    tiles: Sequence[np.ndarray],
    *,
    columns: int | None = None,
    labels: Sequence[str] | None = None,
    headers: Sequence[str] | None = None,
    colorbar: ColorBar | None = None,
    legend: Sequence[tuple[tuple[int, int, int], str]] | None = None,
    notes: Sequence[str] | None = None,
    gap: int = 2,
    min_width: int = 0,
    max_width: int | None = None,
    background: int = 64,
) -> np.ndarray:
    """Tile uint8 images (possibly of different sizes) into one (H, W, 3) uint8 sheet.

    Parameters
    ----------
    tiles : sequence of (h, w[, 3]) uint8
        sRGB-encoded tiles (:func:`to_srgb8`, :func:`encoded_to_u8`, :func:`heat`),
        placed row by row, each in a cell of the largest tile's size.
    columns : int, optional
        Cells per row (default: a square-ish grid).
    labels : sequence of str, optional
        One per tile (empty for none), drawn by :func:`label_tile`.
    headers : sequence of str, optional
        One caption per column, centred above it in a strip at the top.
    colorbar : ColorBar, optional
        A colour bar with its range and caption in a strip at the bottom.
    legend : sequence of ((r, g, b), text), optional
        What each colour drawn on the tiles means (outlines, marks), in a strip at the
        bottom: a picture says what it shows.
    notes : sequence of str, optional
        Warnings about what the sheet shows (the ones the command prints), word-wrapped
        in a strip at the top in :data:`WARNING_RGB`, so the picture carries them too.
    gap : int
        Pixels between cells, and around the grid.
    min_width, max_width : int
        Tiles narrower than ``min_width`` px are enlarged by an integer factor
        (nearest, so pixels stay visible and labels readable); tiles wider than
        ``max_width`` are shrunk (area average).
    background : int
        Grey level 0–255 between cells.
    """
    if len(tiles) == 0:
        raise InputError("contact sheet of no tiles")
    if labels is not None and len(labels) != len(tiles):
        raise InputError(f"contact sheet: {len(labels)} labels for {len(tiles)} tiles")
    if gap < 0 or not (0 <= background <= 255):
        raise InputError(
            f"contact sheet: gap {gap}, background {background}: expected gap >= 0 and 0 <= background <= 255"
        )
    ims = [_as_tile(i, t) for i, t in enumerate(tiles)]
    widest = max(t.shape[1] for t in ims)
    if min_width and widest < min_width:
        f = int(math.ceil(min_width / widest))
        ims = [np.repeat(np.repeat(t, f, axis=0), f, axis=1) for t in ims]
    if max_width is not None:
        ims = [_resize(t, max_width / t.shape[1]) if t.shape[1] > max_width else t for t in ims]
    if labels is not None:
        ims = [label_tile(t, str(s)) if s else t for t, s in zip(ims, labels, strict=True)]
    n = len(ims)
    cols = max(1, min(int(columns), n) if columns else int(math.ceil(math.sqrt(n))))
    rows = int(math.ceil(n / cols))
    h = max(t.shape[0] for t in ims)
    w = max(t.shape[1] for t in ims)
    width = cols * (w + gap) + gap
    grid = np.full((rows * (h + gap) + gap, width, 3), background, np.uint8)
    for i, t in enumerate(ims):
        r, c = divmod(i, cols)
        y, x = gap + r * (h + gap), gap + c * (w + gap)
        grid[y : y + t.shape[0], x : x + t.shape[1]] = t
    parts = []
    if notes:
        parts.append(_notes_strip([str(n) for n in notes], width, gap, background))
    if headers:
        parts.append(_header_strip(list(headers), cols, w, gap, width, background))
    parts.append(grid)
    if colorbar is not None:
        parts.append(_colorbar_strip(colorbar, width, gap, background))
    if legend:
        parts.append(_legend_strip(legend, width, gap, background))
    return np.concatenate(parts, axis=0) if len(parts) > 1 else grid


def write_sheet(path, sheet8: np.ndarray) -> Path:
    """Write a uint8 sheet (already sRGB-encoded) as an 8-bit PNG, atomically."""
    a = np.asarray(sheet8)
    if a.dtype != np.uint8:
        raise InputError(f"{path}: sheet of dtype {a.dtype}, expected uint8")
    write_png(path, a.astype(np.float32) / 255.0, linear=True)
    return Path(path)


def write_animation(path, frames8: Sequence[np.ndarray], *, fps: float, loop: int = 0) -> Path:
    """Write uint8 frames as an animation at ``fps`` frames per second, atomically.

    ``.gif``: looping (``loop=0`` forever) with a frame delay of ``round(100 / fps)``
    centiseconds — GIF stores delays in 1/100 s, so 12 fps plays at 12.5 fps. ``.mp4``:
    through imageio's ffmpeg writer (an :class:`InputError` if it is not installed).
    Frames are (H, W, 3) uint8 (see :func:`to_srgb8`), all the same size.
    """
    path = Path(path)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError(f"{path}: fps {fps!r}, expected a frame rate > 0")
    if len(frames8) == 0:
        raise InputError(f"{path}: animation of no frames")
    ims = [_as_tile(i, f) for i, f in enumerate(frames8)]
    if len({t.shape for t in ims}) != 1:
        raise InputError(f"{path}: frames of different sizes {sorted({t.shape for t in ims})}")
    suffix = path.suffix.lower()
    if suffix == ".gif":
        from PIL import Image

        delay_ms = 10 * max(1, round(100.0 / fps))  # Pillow stores duration // 10 cs
        pil = [Image.fromarray(np.ascontiguousarray(t)) for t in ims]
        with atomic_path(path) as tmp:
            # Pillow merges repeated frames into one with the summed delay: same playback
            pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:], duration=delay_ms, loop=loop)
    elif suffix == ".mp4":
        import imageio.v2 as iio

        with atomic_path(path) as tmp:
            try:
                iio.mimsave(tmp, cast(Any, ims), fps=fps, format="FFMPEG")  # imageio's stubs want List[ArrayLike]
            except (ValueError, RuntimeError, ImportError) as e:  # the optional ffmpeg plugin
                raise InputError(f"{path}: no MP4 writer ({e})") from None
    else:
        raise InputError(f"{path}: animation suffix {path.suffix!r}, expected .gif or .mp4")
    log.debug("wrote %s: %d frames at %g fps", path, len(ims), fps)
    return path
