"""SSIM with a Gaussian window (11 taps, σ 1.5) and its gradient, for the D-SSIM loss.

Wang et al. 2004 with the Gaussian-weighted statistics (population covariance), the
same as ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False)`` away from the border. The filter pads with zeros
(``mode="constant"``): a symmetric kernel with zero padding is its own adjoint, so the
backward pass is the same filter; the border, where skimage reflects, is black
background in the fitted images anyway.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

__all__ = ["SSIM_SIGMA", "SSIM_TRUNCATE", "ssim_map", "ssim_and_grad"]

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # radius int(3.5·1.5 + 0.5) = 5: an 11-tap window, as skimage
_K1, _K2 = 0.01, 0.03


def _blur(a: np.ndarray) -> np.ndarray:
    # filter over the two image axes only; channels stay separate
    sig = (SSIM_SIGMA, SSIM_SIGMA) + (0.0,) * (a.ndim - 2)
    return gaussian_filter(a, sigma=sig, truncate=SSIM_TRUNCATE, mode="constant")


def _stats(x: np.ndarray, y: np.ndarray, data_range: float):
    c1, c2 = (_K1 * data_range) ** 2, (_K2 * data_range) ** 2
    mx, my = _blur(x), _blur(y)
    sxx = _blur(x * x) - mx * mx
    syy = _blur(y * y) - my * my
    sxy = _blur(x * y) - mx * my
    a1 = 2 * mx * my + c1
    a2 = 2 * sxy + c2
    b1 = mx * mx + my * my + c1
    b2 = sxx + syy + c2
    return mx, my, a1, a2, b1, b2


def ssim_map(x: np.ndarray, y: np.ndarray, *, data_range: float = 1.0) -> np.ndarray:
    """Per-pixel (and per-channel) SSIM of images ``x`` and ``y`` (H, W[, C]), float64."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    _, _, a1, a2, b1, b2 = _stats(x, y, data_range)
    return (a1 * a2) / (b1 * b2)


def ssim_and_grad(x: np.ndarray, y: np.ndarray, *, data_range: float = 1.0) -> tuple[float, np.ndarray]:
    """Mean SSIM of ``x`` against the reference ``y`` (H, W[, C]) and its gradient
    ∂mean/∂x (same shape as ``x``, float32).

    With S = A1·A2/(B1·B2) per pixel, A1 = 2μxμy + C1, A2 = 2σxy + C2, B1 = μx² + μy² + C1,
    B2 = σx² + σy² + C2, and μ, σ Gaussian-filtered moments, the chain rule through
    the filter's adjoint (itself) gives ∂S̄/∂x = G(∂S/∂μx) + 2x·G(∂S/∂E[x²]) + y·G(∂S/∂E[xy]).
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    mx, my, a1, a2, b1, b2 = _stats(x, y, data_range)
    s = (a1 * a2) / (b1 * b2)
    n = s.size
    # partials of S with respect to the filtered quantities μx, E[x²], E[xy]
    d_a1 = a2 / (b1 * b2)
    d_a2 = a1 / (b1 * b2)
    d_b1 = -s / b1
    d_b2 = -s / b2
    # A2 = 2(E[xy] − μxμy) + C2, B2 = E[x²] − μx² + E[y²] − μy² + C2
    g_exy = 2 * d_a2
    g_exx = d_b2
    g_mx = d_a1 * 2 * my + d_b1 * 2 * mx + d_a2 * (-2 * my) + d_b2 * (-2 * mx)
    grad = _blur(g_mx) + 2 * x * _blur(g_exx) + y * _blur(g_exy)
    return float(s.mean()), (grad / n).astype(np.float32)
