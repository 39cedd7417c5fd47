"""Image metrics of relighting: relit against true radiance inside a mask.

A leaf module so that the evaluation (:mod:`.evaluate`) and the natural-illumination
evaluation (:mod:`.natural`) share it without importing each other.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["relight_metrics"]


def relight_metrics(relit_rgb: np.ndarray, truth_rgb: np.ndarray, mask: np.ndarray) -> dict:
    """PSNR (dB) and relative L2 error of ``relit_rgb`` against ``truth_rgb`` (H, W, 3)
    over ``mask`` (H, W) bool. NaN metrics when the mask is empty; PSNR is +inf for an
    exact match and NaN for an all-zero truth.

    ``psnr`` takes the truth's peak as the signal (HDR images have no white), so a dim
    map with one bright highlight scores high however wrong the rest is; ``psnr_norm``
    divides both images by the truth's mean first, ``10 log10(mean(truth)² / MSE)``:
    independent of the map's brightness and of its brightest pixel, the figure to read
    next to ``rel_err``."""
    m = np.asarray(mask, bool)
    n = int(m.sum())
    if n == 0:
        nan = float("nan")
        return {"pixels": 0, "psnr": nan, "psnr_norm": nan, "rel_err": nan, "mse": nan}
    a = np.asarray(relit_rgb, np.float64)[m]
    b = np.asarray(truth_rgb, np.float64)[m]
    mse = float(np.mean((a - b) ** 2))
    nb = float(np.linalg.norm(b))
    peak = float(b.max())
    rel = float(np.linalg.norm(a - b) / nb) if nb > 0 else (0.0 if mse == 0 else float("inf"))
    if peak <= 0:
        psnr = float("nan")
    elif mse == 0:
        psnr = float("inf")
    else:
        psnr = 10 * math.log10(peak**2 / mse)
    mean = float(b.mean())
    if mean <= 0:
        psnr_norm = float("nan")
    elif mse == 0:
        psnr_norm = float("inf")
    else:
        psnr_norm = 10 * math.log10(mean**2 / mse)
    return {"pixels": n, "psnr": psnr, "psnr_norm": psnr_norm, "rel_err": rel, "mse": mse, "peak": peak}
