"""Per-surfel view-dependent colour: real spherical harmonics evaluated per view.

The basis is :func:`opacityhull.sh.sh_basis` (3DGS constants, order and signs),
and the convention is 3DGS's: ``colour = Σ_j c_j Y_j(d) + ½``, clamped at 0, in the
display (sRGB-encoded) space, d the unit direction from the camera centre to the
surfel. With a per-surfel ``base`` colour instead of ½ the same coefficients model a
signed residual over another shading (``colour = base + Σ_j c_j Y_j``, e.g. over the
ULR blend of the captured views: ``benchmarks/optimize.py``'s ``sh+ulr`` mode). The fitted model's PLY is then what a 3DGS/2DGS viewer expects as it is.
The gradient is taken with respect to the coefficients only (as the direction depends
on the position only through d, whose effect on a surfel's colour is second order
next to the image-space gradient of its position).
"""

from __future__ import annotations

import numpy as np

from ..sh import sh_basis

__all__ = ["view_dirs", "sh_colors", "sh_colors_backward"]


def view_dirs(means: np.ndarray, centre_world: np.ndarray) -> np.ndarray:
    """(N, 3) unit directions from the camera centre (3,) to ``means`` (N, 3), m."""
    d = np.asarray(means, np.float64) - np.asarray(centre_world, np.float64)[None, :]
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(n, 1e-12)


def sh_colors(
    coeffs: np.ndarray, dirs: np.ndarray, *, degree: int, base: float | np.ndarray = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour of every surfel seen along ``dirs``.

    Parameters
    ----------
    coeffs : (N, B, 3) SH coefficients, B ≥ (degree+1)², 3DGS order (DC first).
    dirs : (N, 3) unit view directions.
    degree : the degree evaluated (the higher coefficients are ignored).
    base : the colour the SH sum is added to: ½ (3DGS), or (N, 3) per-surfel colours
        in the same display space (the SH then a signed residual over them).

    Returns
    -------
    colors : (N, 3) float32, ``max(Σ_j c_j Y_j + base, 0)``.
    basis : (N, (degree+1)²) float32, the basis values (for :func:`sh_colors_backward`).
    positive : (N, 3) bool, where the clamp let the gradient through.
    """
    b = (int(degree) + 1) ** 2
    Y = sh_basis(dirs, int(degree)).astype(np.float32)
    raw = np.einsum("nb,nbc->nc", Y, coeffs[:, :b, :]) + np.asarray(base, np.float32)
    positive = raw > 0
    return np.where(positive, raw, 0.0).astype(np.float32), Y, positive


def sh_colors_backward(dL_dcolors: np.ndarray, basis: np.ndarray, positive: np.ndarray, n_coeffs: int) -> np.ndarray:
    """∂L/∂coeffs (N, n_coeffs, 3) from ∂L/∂colors (N, 3) through :func:`sh_colors`
    (coefficients beyond the evaluated degree get 0)."""
    g = np.where(positive, dL_dcolors, 0.0).astype(np.float32)
    out = np.zeros((g.shape[0], int(n_coeffs), 3), np.float32)
    b = basis.shape[1]
    out[:, :b, :] = basis[:, :, None] * g[:, None, :]
    return out
