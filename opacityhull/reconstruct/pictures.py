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

from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..pictures import contact_sheet, encoded_to_u8, to_srgb8, write_sheet

__all__ = ["matte_contact_sheet", "hull_overlays", "HULL_OVERLAY_LEGEND", "reprojection_histogram", "surfel_mask"]


def _resize(img: np.ndarray, h: int) -> np.ndarray:
    import cv2

    w = max(1, int(round(img.shape[1] * h / img.shape[0])))
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)


def matte_contact_sheet(
    alphas: Sequence[np.ndarray], names: Sequence[str], out_path, *, thumb_h: int = 120, max_views: int = 48
) -> Path:
    """Grid of alpha mattes (white = opaque) labelled with view ids; PNG at ``out_path``."""
    idx = np.linspace(0, len(alphas) - 1, min(len(alphas), max_views)).round().astype(int) if len(alphas) else []
    tiles, labels = [], []
    for i in dict.fromkeys(idx):
        a = np.clip(np.nan_to_num(np.asarray(alphas[i], dtype=np.float32)), 0, 1)
        tiles.append(_resize(encoded_to_u8(a), thumb_h))  # alpha is data: shown as is, not sRGB-encoded
        labels.append(str(names[i]))
    if not tiles:
        tiles, labels = [np.zeros((thumb_h, thumb_h, 3), np.uint8)], ["no views"]
    return write_sheet(out_path, contact_sheet(tiles, columns=min(8, len(tiles)), labels=labels, background=40))


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


#: The outlines of ``hull_overlay.png`` and what they mean (sRGB 8-bit colour, text).
HULL_OVERLAY_LEGEND = (
    ((0, 255, 0), "silhouette the hull was carved from (matte, dilated)"),
    ((255, 0, 0), "hull surfels splatted into the view"),
)


def hull_overlays(
    images: Sequence[np.ndarray],
    silhouettes: Sequence[np.ndarray],
    surfel_masks: Sequence[np.ndarray],
    names: Sequence[str],
    out_path,
    *,
    thumb_h: int = 240,
) -> Path:
    """Colour image (sRGB, normalised to its 99th percentile) with the silhouette outline
    in green and the splatted-surfel outline in red, one tile per given view; a legend
    under the tiles says which is which (:data:`HULL_OVERLAY_LEGEND`)."""
    import cv2

    tiles, labels = [], []
    for img, sil, sm, name in zip(images, silhouettes, surfel_masks, names, strict=True):
        rgb = np.nan_to_num(np.asarray(img, dtype=np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
        scale = float(np.percentile(rgb, 99))
        scale = scale if scale > 0 else 1.0
        base = np.ascontiguousarray(to_srgb8(rgb / scale))
        for mask, colour in ((sil, HULL_OVERLAY_LEGEND[0][0]), (sm, HULL_OVERLAY_LEGEND[1][0])):
            cs, _ = cv2.findContours(np.asarray(mask, dtype=np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(base, cs, -1, colour, 1)
        tiles.append(_resize(base, thumb_h))
        labels.append(str(name))
    if not tiles:
        tiles, labels = [np.zeros((thumb_h, thumb_h, 3), np.uint8)], ["no views"]
    sheet = contact_sheet(tiles, columns=min(4, len(tiles)), labels=labels, background=40, legend=HULL_OVERLAY_LEGEND)
    return write_sheet(out_path, sheet)


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
