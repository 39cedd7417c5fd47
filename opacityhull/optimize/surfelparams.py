"""The fitted surfels' parameters as named arrays, their start from the hull's surfels,
and the conversions between quaternions, tangent frames and normals.

A surfel's frame is ``R(q)`` (q = wxyz, normalised): columns 0 and 1 are its tangent
axes (the two std-devs ``exp(log_scales)``), column 2 its normal (2DGS convention).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "PARAM_NAMES",
    "quat_to_rotmat",
    "quats_from_normals",
    "normals_of",
    "sigmoid",
    "logit",
    "scene_extent",
    "start_params",
    "thin_start",
]

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh")


def sigmoid(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return (0.5 * (1.0 + np.tanh(0.5 * x))).astype(np.float32)  # overflow-free logistic


def logit(p) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p)).astype(np.float32)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of quaternions ``q`` (N, 4) wxyz (normalised here; a zero
    quaternion gives the identity)."""
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(n > 1e-12, q / np.maximum(n, 1e-12), np.array([1.0, 0, 0, 0]))
    w, x, y, z = q.T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quats_from_normals(normals: np.ndarray) -> np.ndarray:
    """(N, 4) wxyz quaternions of the shortest rotation taking +z to each unit normal
    (N, 3); the antipode of +z (no unique shortest arc) rotates by π about x."""
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    # q = (1 + z·n, z × n) normalised; z × n = (−n_y, n_x, 0)
    w = 1.0 + n[:, 2]
    q = np.stack([w, -n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)
    flip = w < 1e-9
    q[flip] = (0.0, 1.0, 0.0, 0.0)
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def normals_of(quats: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals (third frame column) of quaternions (N, 4) wxyz."""
    return quat_to_rotmat(quats)[:, :, 2].astype(np.float32)


def scene_extent(positions: np.ndarray) -> float:
    """Radius (m) of the sphere about the positions' centroid holding them all: the
    scale of the position learning rate and of the densification's size tests."""
    p = np.asarray(positions, np.float64)
    if len(p) == 0:
        return 1.0
    return float(max(np.linalg.norm(p - p.mean(axis=0), axis=1).max(), 1e-6))


def start_params(
    positions: np.ndarray,
    normals: np.ndarray,
    radii: np.ndarray,
    sh_dc: np.ndarray,
    *,
    sh_degree: int,
    sigma_radius: float = 0.5,
    opacity: float = 0.9,
) -> dict[str, np.ndarray]:
    """The fitting's start from hull surfels.

    Parameters
    ----------
    positions, normals : (N, 3) m, unit.
    radii : (N,) m, the disc radii that cover the hull without holes; the Gaussian's
        tangent std-dev is ``sigma_radius · radius`` (the renderer's own
        :attr:`~opacityhull.render.config.RenderConfig.sigma_radius`).
    sh_dc : (N, 3) the SH DC coefficients (:func:`opacityhull.sh.fit_sh`).
    sh_degree : the coefficients allocated, (sh_degree+1)² per channel, the rest 0.
    opacity : start opacity of every surfel.
    """
    N = len(positions)
    B = (int(sh_degree) + 1) ** 2
    sh = np.zeros((N, B, 3), np.float32)
    sh[:, 0, :] = sh_dc
    s = np.log(np.maximum(np.asarray(radii, np.float64) * sigma_radius, 1e-7)).astype(np.float32)
    return {
        "means": np.asarray(positions, np.float32).copy(),
        "quats": quats_from_normals(normals),
        "log_scales": np.stack([s, s], axis=1),
        "opacity_logits": np.full(N, logit(opacity), np.float32),
        "sh": sh,
    }


def thin_start(n: int, max_n: int | None, *, seed: int) -> tuple[np.ndarray, float]:
    """A seeded subset of at most ``max_n`` of ``n`` start surfels (sorted indices) and
    the factor √(n / kept) their radii grow by to cover the same area. The hull samples
    a surfel per projected pixel (templeSR: 364 k); the rasterizer's cost grows with
    the count, and densification adds surfels back where the photographs ask for them."""
    if max_n is None or n <= max_n:
        return np.arange(n), 1.0
    rng = np.random.default_rng([seed, 7])
    keep = np.sort(rng.choice(n, size=int(max_n), replace=False))
    return keep, float(np.sqrt(n / max_n))
