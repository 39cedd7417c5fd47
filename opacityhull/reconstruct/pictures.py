"""Pictures of a build (PNG under ``MODEL/pictures/``): what a user looks at to trust it.

* :func:`matte_contact_sheet` — every view's alpha matte, labelled, in a grid.
* :func:`hull_overlays` — per view (a sample): the view's colour image, the silhouette
  outline (green) and the outline of the surfels splatted into that view (red). Where
  red runs outside green the hull is fatter than the silhouette there (expected: other
  views' silhouettes bound it); red *inside* green means the hull cuts the object
  (calibration error or a bad matte).
* :func:`reprojection_histogram` — histogram of calibration corner residuals (px), or a
  bar chart of per-camera RMS when only those are known.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..imageio import srgb_encode, write_png

__all__ = ["matte_contact_sheet", "hull_overlays", "reprojection_histogram", "surfel_mask"]


def _label(img8: np.ndarray, text: str) -> np.ndarray:
    import cv2

    out = np.ascontiguousarray(img8)
    scale = max(0.3, min(0.5, out.shape[1] / 400.0))
    cv2.putText(out, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 2, cv2.LINE_AA)
    cv2.putText(out, text, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 0), 1, cv2.LINE_AA)
    return out


def _resize(img: np.ndarray, h: int) -> np.ndarray:
    import cv2

    w = max(1, int(round(img.shape[1] * h / img.shape[0])))
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)


def _grid(tiles: list[np.ndarray], cols: int) -> np.ndarray:
    h = max(t.shape[0] for t in tiles)
    w = max(t.shape[1] for t in tiles)
    rows = math.ceil(len(tiles) / cols)
    sheet = np.full((rows * (h + 2), cols * (w + 2), 3), 40, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * (h + 2) : r * (h + 2) + t.shape[0], c * (w + 2) : c * (w + 2) + t.shape[1]] = t
    return sheet


def _write_rgb8(path, rgb8: np.ndarray) -> Path:
    write_png(path, rgb8.astype(np.float32) / 255.0, linear=True)
    return Path(path)


def matte_contact_sheet(alphas: Sequence[np.ndarray], names: Sequence[str], out_path, *, thumb_h: int = 120,
                        max_views: int = 48) -> Path:
    """Grid of alpha mattes (white = opaque) labelled with view ids; PNG at ``out_path``."""
    idx = np.linspace(0, len(alphas) - 1, min(len(alphas), max_views)).round().astype(int) if len(alphas) else []
    tiles = []
    for i in dict.fromkeys(idx):
        a = np.clip(np.nan_to_num(np.asarray(alphas[i], dtype=np.float32)), 0, 1)
        g = (a * 255).round().astype(np.uint8)
        t = _resize(np.repeat(g[..., None], 3, axis=2), thumb_h)
        tiles.append(_label(t, names[i]))
    if not tiles:
        tiles = [np.zeros((thumb_h, thumb_h, 3), np.uint8)]
    return _write_rgb8(out_path, _grid(tiles, cols=min(8, len(tiles))))


def surfel_mask(positions, radii, camera) -> np.ndarray:
    """(H, W) bool: pixels covered by surfel discs splatted as squares of their projected
    radius (pinhole projection of ``camera``)."""
    H, W = camera.height, camera.width
    m = np.zeros((H, W), bool)
    if len(positions) == 0:
        return m
    P = camera.projection_matrix()
    X = np.asarray(positions, dtype=np.float64) @ P[:, :3].T + P[:, 3]
    z = X[:, 2]
    ok = z > 0
    u = X[ok, 0] / z[ok]
    v = X[ok, 1] / z[ok]
    rho = np.maximum(0.5, min(camera.fx, camera.fy) * np.asarray(radii)[ok] / z[ok])
    r = int(np.ceil(rho.max())) if rho.size else 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            sel = (np.abs(dx) <= rho + 0.5) & (np.abs(dy) <= rho + 0.5)
            x = np.floor(u[sel] + dx + 0.5).astype(int)
            y = np.floor(v[sel] + dy + 0.5).astype(int)
            inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            m[y[inside], x[inside]] = True
    return m


def hull_overlays(images: Sequence[np.ndarray], silhouettes: Sequence[np.ndarray], surfel_masks: Sequence[np.ndarray],
                  names: Sequence[str], out_path, *, thumb_h: int = 240) -> Path:
    """Colour image (sRGB, normalised to its 99th percentile) with the silhouette outline
    in green and the splatted-surfel outline in red, one tile per given view."""
    import cv2

    tiles = []
    for img, sil, sm, name in zip(images, silhouettes, surfel_masks, names):
        rgb = np.nan_to_num(np.asarray(img, dtype=np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
        scale = float(np.percentile(rgb, 99))
        scale = scale if scale > 0 else 1.0
        base = (srgb_encode(rgb / scale) * 255).round().astype(np.uint8)
        base = np.ascontiguousarray(base)
        for mask, colour in ((sil, (0, 255, 0)), (sm, (255, 0, 0))):
            cs, _ = cv2.findContours(np.asarray(mask, dtype=np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(base, cs, -1, colour, 1)
        tiles.append(_label(_resize(base, thumb_h), name))
    if not tiles:
        tiles = [np.zeros((thumb_h, thumb_h, 3), np.uint8)]
    return _write_rgb8(out_path, _grid(tiles, cols=min(4, len(tiles))))


def reprojection_histogram(out_path, *, residuals_px=None, rms_per_camera: dict | None = None) -> Path | None:
    """Histogram of corner residual lengths (px) or, failing those, per-camera RMS bars.
    Returns the path, or None when there is nothing to plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..imageio import atomic_path

    res = None if residuals_px is None else np.asarray(residuals_px, dtype=np.float64)
    if res is not None and res.ndim == 2 and res.shape[0] > 0:
        e = np.linalg.norm(res, axis=1)
        fig, ax = plt.subplots(figsize=(5, 3.2), dpi=110)
        ax.hist(e, bins=40, color="#4477aa")
        rms = float(np.sqrt(np.mean(e**2)))
        ax.axvline(rms, color="k", ls="--", lw=1, label=f"RMS {rms:.3f} px")
        ax.set_xlabel("corner reprojection error (px)")
        ax.set_ylabel("corners")
        ax.legend()
    elif rms_per_camera:
        fig, ax = plt.subplots(figsize=(5, 3.2), dpi=110)
        names = list(rms_per_camera)
        ax.bar(names, [rms_per_camera[n] for n in names], color="#4477aa")
        ax.set_ylabel("reprojection RMS (px)")
    else:
        return None
    ax.set_title("calibration reprojection error")
    fig.tight_layout()
    out_path = Path(out_path)
    with atomic_path(out_path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out_path
