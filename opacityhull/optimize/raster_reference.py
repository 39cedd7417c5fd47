"""Slow, obviously-correct NumPy twin of :func:`opacityhull.optimize.raster.rasterize`.

Float64 throughout, matrices written as in the papers: the rotation from SciPy's
``Rotation`` (scalar-first quaternion), the disc's 3-D covariance ``R diag(su², sv², 0) Rᵀ``,
the camera rotation ``W``, the perspective Jacobian ``J`` at the centre, the screen
covariance ``J W Σ Wᵀ Jᵀ + lowpass·I`` and its inverse by ``np.linalg.inv``. Then every
pixel composites every surfel in (float32 view depth, index) order — no tiles, no
bounding boxes: a surfel whose cutoff ellipse misses the frame simply never passes the
``q <= cutoff²`` test. The loop runs over surfels, each step vectorised over all pixels.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .raster import ALPHA_MAX, RasterCamera, RasterConfig, SplatParams

__all__ = ["rasterize_reference", "screen_covariance_reference"]


def screen_covariance_reference(params: SplatParams, cam: RasterCamera, *, config: RasterConfig = RasterConfig()):
    """Per surfel: camera-frame centre (N, 3), projected centre (N, 2) px and screen
    covariance (N, 2, 2) px², float64 (rows behind the camera are meaningless)."""
    q = np.asarray(params.quats, np.float64)
    norm = np.linalg.norm(q, axis=1)
    q = np.where(norm[:, None] > 1e-12, q, [1.0, 0.0, 0.0, 0.0])
    R = Rotation.from_quat(q, scalar_first=True).as_matrix()
    s = np.exp(np.asarray(params.log_scales, np.float64))
    S = np.zeros((len(q), 3, 3))
    S[:, 0, 0] = s[:, 0] ** 2
    S[:, 1, 1] = s[:, 1] ** 2
    sigma_world = R @ S @ np.swapaxes(R, 1, 2)
    Wr = cam.cam_from_world[:, :3]
    t = np.asarray(params.means, np.float64) @ Wr.T + cam.cam_from_world[:, 3]
    K = cam.K
    x, y, z = t[:, 0], t[:, 1], t[:, 2]
    mu = np.stack([(K[0, 0] * x + K[0, 1] * y) / z + K[0, 2], (K[1, 0] * x + K[1, 1] * y) / z + K[1, 2]], axis=1)
    J = np.zeros((len(q), 2, 3))
    for r in range(2):
        J[:, r, 0] = K[r, 0] / z
        J[:, r, 1] = K[r, 1] / z
        J[:, r, 2] = -(K[r, 0] * x + K[r, 1] * y) / z**2
    cov = J @ Wr @ sigma_world @ Wr.T @ np.swapaxes(J, 1, 2) + config.lowpass_px2 * np.eye(2)
    return t, mu, cov


def rasterize_reference(params: SplatParams, cam: RasterCamera, *, config: RasterConfig = RasterConfig()):
    """The rasterizer's image (H, W, 3), alpha (H, W) and alpha-weighted depth (H, W),
    float64, by the definition in :mod:`opacityhull.optimize.raster`."""
    t, mu, cov = screen_covariance_reference(params, cam, config=config)
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(params.opacity_logits, np.float64)))
    colors = np.asarray(params.colors, np.float64)
    z = t[:, 2]
    front = np.flatnonzero(z >= config.near_m)
    order = front[np.lexsort((front, z[front].astype(np.float32)))]
    H, W = cam.height, cam.width
    py, px = np.mgrid[0:H, 0:W].astype(np.float64)
    T = np.ones((H, W))
    rgb = np.zeros((H, W, 3))
    depth = np.zeros((H, W))
    alive = np.ones((H, W), bool)
    cut2 = config.cutoff_sigma**2
    for i in order:
        conic = np.linalg.inv(cov[i])
        if not np.all(np.isfinite(conic)) or not np.all(np.isfinite(mu[i])):
            continue
        d = np.stack([px - mu[i, 0], py - mu[i, 1]], axis=-1)
        q = np.einsum("...i,ij,...j->...", d, conic, d)
        a = np.minimum(ALPHA_MAX, opacity[i] * np.exp(-0.5 * q))
        hit = alive & (q <= cut2) & (a >= config.alpha_min)
        w = np.where(hit, a * T, 0.0)
        rgb += w[..., None] * colors[i]
        depth += w * z[i]
        T = np.where(hit, T * (1.0 - a), T)
        alive &= ~(hit & (T < config.transmittance_min))
    image = rgb + T[..., None] * np.asarray(config.background, np.float64)
    return image, 1.0 - T, depth
