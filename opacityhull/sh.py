"""View-dependent colour as real spherical harmonics, in the 3D Gaussian Splatting convention.

3DGS (Kerbl et al. 2023, ``utils/sh_utils.py``) evaluates ``colour = Σ_j c_j Y_j(d) + 0.5``
with d the unit direction from the camera centre to the Gaussian, colours in the
images' [0, 1] (sRGB-encoded) values, and the basis constants below. The fit here is a
per-surfel ridge-regularised least squares over the views that saw the surfel.

In the core: the exporters (``export/formats.py``) and the fitting
(``optimize/appearance.py``, ``optimize/data.py``) use the same basis.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from .errors import InputError
from .model import Surfels

__all__ = ["SH_C0", "sh_basis", "n_coeffs", "ShFit", "fit_sh", "eval_sh"]

SH_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def n_coeffs(degree: int) -> int:
    return (int(degree) + 1) ** 2


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """(n, (degree+1)²) real SH basis of unit ``dirs`` (n, 3), 3DGS order and signs."""
    if not 0 <= int(degree) <= 3:
        raise InputError(f"SH degree {degree!r}: expected 0..3")
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cols = [np.full_like(x, SH_C0)]
    if degree >= 1:
        cols += [-_C1 * y, _C1 * z, -_C1 * x]
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z  # shared by degrees 2 and 3
    if degree >= 2:
        cols += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz, _C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [
            _C3[0] * y * (3 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(cols, axis=1)


def eval_sh(coeffs: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Colour (n, 3) = Σ_j coeffs[:, j] Y_j(dirs) + 0.5 (not clamped); coeffs (n, B, 3)."""
    B = coeffs.shape[1]
    deg = int(round(np.sqrt(B))) - 1
    Y = sh_basis(dirs, deg)
    return np.einsum("nb,nbc->nc", Y, coeffs) + 0.5


@dataclass(frozen=True)
class ShFit:
    """Result of :func:`fit_sh`.

    coeffs : (N, (degree+1)², 3) float32, 3DGS order (DC first).
    rms : {degree: RMS residual over all observations, in [0, 1] sRGB units}.
    n_obs : total observations (surfel, view) used.
    """

    degree: int
    coeffs: np.ndarray
    rms: dict
    n_obs: int


def fit_sh(
    surfels: Surfels,
    cameras: Sequence,
    images: Sequence[np.ndarray],
    *,
    degree: int = 3,
    ridge: float = 1e-2,
    chunk: int = 65536,
) -> ShFit:
    """Least-squares SH colour per surfel from the views that saw it.

    Parameters
    ----------
    surfels, cameras, images : the model (straight RGBA views, linear).
    degree : 0..3, the degree written; the residual is reported for every degree ≤ it.
    ridge : Tikhonov weight on the non-DC coefficients (a surfel seen by few views
        has more unknowns than observations at degree 3; the ridge keeps those at 0).
    chunk : surfels per batch (bounds memory at chunk·B²·8 bytes).

    Returns
    -------
    :class:`ShFit`. The target colour is the sRGB-encoded straight colour (what 3DGS
    trains against); surfels seen by no view get the DC of mid-grey.
    """
    from .imageio import srgb_encode
    from .surfel_samples import iter_view_samples

    if not 0 <= int(degree) <= 3:
        raise InputError(f"SH degree {degree!r}: expected 0..3")
    B = n_coeffs(degree)
    N = len(surfels)
    coeffs = np.zeros((N, B, 3), np.float32)
    sse = {d: 0.0 for d in range(degree + 1)}
    n_obs = 0
    for c0 in range(0, N, chunk):
        idx = np.arange(c0, min(N, c0 + chunk))
        n = idx.size
        AtA = np.zeros((n, B, B))
        Atc = np.zeros((n, B, 3))
        ctc = np.zeros(n)
        for s in iter_view_samples(surfels, cameras, images, subset=idx):
            Y = sh_basis(s.dirs, degree)
            c = srgb_encode(np.clip(s.rgba[:, :3], 0.0, 1.0)).astype(np.float64) - 0.5
            loc = s.index - c0
            np.add.at(AtA, loc, Y[:, :, None] * Y[:, None, :])
            np.add.at(Atc, loc, Y[:, :, None] * c[:, None, :])
            np.add.at(ctc, loc, np.sum(c * c, axis=1))
            n_obs += len(loc)
        for d in range(degree + 1):
            b = n_coeffs(d)
            A = AtA[:, :b, :b].copy()
            reg = np.full(b, ridge)
            reg[0] = 1e-9
            A[:, np.arange(b), np.arange(b)] += reg
            X = np.linalg.solve(A, Atc[:, :b, :])
            # SSE = Σc² − 2 tr(Xᵀ Aᵀc) + tr(Xᵀ AᵀA X), from the normal equations alone
            e = ctc - 2 * np.einsum("nbc,nbc->n", X, Atc[:, :b]) + np.einsum("nbc,nbk,nkc->n", X, AtA[:, :b, :b], X)
            sse[d] += float(np.sum(np.maximum(e, 0.0)))
            if d == degree:
                coeffs[idx] = X.astype(np.float32)
    rms = {d: float(np.sqrt(sse[d] / max(3 * n_obs, 1))) for d in sse}
    return ShFit(int(degree), coeffs, rms, n_obs)
