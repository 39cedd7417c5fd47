"""Statistical point geometry (Kalaiah & Varshney 2003) on the sequential point tree.

Every node of :class:`~opacityhull.render.lod.PointTree` gets the PCA of the surface it
stands for and of its normals (seed 000, §3):

* **positions** — the area-weighted covariance of its leaves, each leaf a uniform disc
  of its area ``a`` in its tangent plane (covariance ``a/(4π)·(I − n nᵀ)``):
  ``C = Σ a_i [(p_i − μ)(p_i − μ)ᵀ + a_i/(4π)(I − n_i n_iᵀ)] / Σ a_i``. Its eigen-frame
  ``f_p`` (rows, σ descending) and standard deviations ``σ_p`` (floored, as the paper
  floors zero variances) are the node's ellipsoid. The disc term makes a leaf the
  ellipse of its own disc (σ = √(a/4π) twice, 0 along the normal), so a node of
  coincident or collinear points still has the extent of their surface.
* **normals** — the frame ``f_n`` whose z is the area-weighted mean normal, with the
  normals unwrapped onto the tangent plane at that pole (``(θ sin φ, θ cos φ)``, arc
  lengths kept along the meridians) and the x, y axes along the principal axes of that
  2-D spread ``σ_n`` (radians).

Degenerate clusters follow the paper: with two (near-)zero position variances the
principal direction is kept and z is turned to the mean normal; with three, z is the
mean normal and x, y any tangent pair.

Rendering (the paper's future work, "an EWA-style rendering of the PCA nodes"): a node
of a cut is one anisotropic EWA splat with the *radius tensor* ``R² = s·4·(I − m mᵀ) C
(I − m mᵀ)`` — the position ellipse projected onto the plane of its mean normal ``m``,
semi-axes 2σ (the ellipse of a uniform patch of that covariance) — where a leaf's is
``r² (I − n nᵀ)``, its own disc (:func:`radius_tensors`,
:func:`opacityhull.render.renderer.render_image`'s ``splat_cov``). ``s = 1`` matches the
second moments of the children's splats; :data:`NODE_SCALE` was measured best. The
normal spread is stored, not drawn: widening the back-face test to the cone ``GAMMA·σ_n¹``
(so that silhouette nodes whose mean normal faces away stay) measured 0.2–2.9 dB worse
on the 50 k sphere.

Storage (§3.1, :func:`pack_nodes`): k-means codebooks (``scipy.cluster.vq.kmeans2``)
quantise ``log σ_p`` and ``log σ_n``; an inner node is a 17-byte record (the paper's 13
bytes of geometry, plus the level-of-detail interval and a visibility index, see
:data:`NODE_DTYPE`), a leaf an 8-byte record (:data:`LEAF_DTYPE`). Visibility patterns
are coherent (the 50 k sphere: 1 275 distinct 36-bit patterns over 72 796 nodes), so a
lossless dictionary with a 16-bit index replaces the 16 bytes of bits per record.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import FormatError, InputError
from ..model import Surfels
from .lod import PointTree

log = logging.getLogger(__name__)

__all__ = [
    "NodeStats",
    "node_statistics",
    "radius_tensors",
    "disc_over_area",
    "Codebook",
    "fit_codebook",
    "PackedNodes",
    "pack_nodes",
    "unpack_nodes",
    "NODE_DTYPE",
    "LEAF_DTYPE",
    "oct_encode",
    "oct_decode",
    "tangent_basis",
    "statistical_cut",
    "NODE_SCALE",
]

GAMMA = 3.5
"""The paper's extent of a node's distribution (σ multiples, > 99.7 %)."""

NODE_SCALE = 0.7
"""``s`` of the node splats' radius tensor ``4 s C``. Measured PSNR against the full
render on the 50 k sphere (views 4, 13, 20; s = 0.4 / 0.55 / 0.7 / 0.85): at N/16
38.9 / 37.2 / 40.1 / 38.8, 38.9 / 39.5 / 38.9 / 39.5, 38.4 / 39.2 / 39.9 / 40.7 dB; at
N/64 25.7 / 31.6 / 32.9 / 30.5 dB (view 4): 0.7 is the best all round (1.0: 38.2 dB at
N/16, view 4)."""

SIGMA_FLOOR_REL = 1e-6
"""Smallest position σ, relative to the model's extent (the paper's 10⁻¹⁵ floor; above the eigen-solver's noise of ~1e-8)."""

SIGMA_N_FLOOR = 1e-4
"""Smallest normal σ (radians) before the logarithm of the codebook."""


@dataclass(frozen=True)
class NodeStats:
    """PCA statistics of every node of a :class:`PointTree` (same node order).

    Attributes
    ----------
    mean : (M, 3) float64 area-weighted mean position μ_p (m).
    frame_p : (M, 3, 3) float64, rows f_p¹ f_p² f_p³ (orthonormal, right-handed).
    sigma_p : (M, 3) float64 standard deviations along them (m), descending, ≥ floor.
    frame_n : (M, 3, 3) float64, rows x y z; z the mean normal m.
    sigma_n : (M, 2) float64 spread of the unwrapped normals along x, y (rad), descending.
    area : (M,) float64 the weight Σa of the subtree (its surface area, m²; a zero-area
        leaf counts with the leaves' median area).
    """

    mean: np.ndarray
    frame_p: np.ndarray
    sigma_p: np.ndarray
    frame_n: np.ndarray
    sigma_n: np.ndarray
    area: np.ndarray

    def covariance(self) -> np.ndarray:
        """(M, 3, 3) position covariance ``f_pᵀ diag(σ_p²) f_p`` (m²)."""
        F = self.frame_p
        return np.einsum("mki,mk,mkj->mij", F, self.sigma_p**2, F)

    @property
    def normal(self) -> np.ndarray:
        """(M, 3) mean normal (unit)."""
        return self.frame_n[:, 2]


def tangent_basis(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y): an orthonormal tangent pair of unit vectors ``z`` (..., 3), continuous
    except at z = −e_z (Duff et al. 2017, "Building an orthonormal basis, revisited")."""
    z = np.asarray(z, np.float64)
    s = np.where(z[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + z[..., 2])
    b = z[..., 0] * z[..., 1] * a
    x = np.stack([1.0 + s * z[..., 0] ** 2 * a, s * b, -s * z[..., 0]], -1)
    y = np.stack([b, s + z[..., 1] ** 2 * a, -z[..., 1]], -1)
    return x, y


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = n > 1e-12
    return np.where(ok, v / np.where(ok, n, 1.0), fallback)


def _ancestor_levels(tree: PointTree):
    """Yield (leaf node ids, ancestor node ids) level by level: first the leaves
    themselves, then their parents, ... (every (leaf, node-above-or-at) pair once)."""
    leaves = np.flatnonzero(tree.is_leaf)
    cur = leaves.copy()
    keep = np.ones(len(leaves), bool)
    while keep.any():
        yield leaves[keep], cur[keep]
        nxt = np.where(keep, tree.parent[np.where(keep, cur, 0)], -1)
        keep = nxt >= 0
        cur = np.where(keep, nxt, 0)


def node_statistics(tree: PointTree, *, sigma_floor: float | None = None) -> NodeStats:
    """The PCA ellipsoid of positions and the normal spread of every node of ``tree``.

    Parameters
    ----------
    tree : the sequential point tree (its leaves carry position, normal and area).
    sigma_floor : smallest position σ (m); default ``SIGMA_FLOOR_REL`` × the extent.

    Returns
    -------
    :class:`NodeStats`, node order of ``tree``.
    """
    M = len(tree)
    P = tree.positions.astype(np.float64)
    Nrm = tree.normals.astype(np.float64)
    Ad = np.maximum(tree.areas.astype(np.float64), 0.0)  # disc areas
    if not np.all(np.isfinite(P)) or not np.all(np.isfinite(Ad)):
        raise InputError("node_statistics: non-finite node positions or areas")
    leaf = tree.is_leaf
    # weights: the areas; zero-area leaves (points) still count, with the typical weight
    pos_a = Ad[leaf & (Ad > 0)]
    A = np.where(Ad > 0, Ad, float(np.median(pos_a)) if pos_a.size else 1.0)
    lo = P[leaf].min(axis=0)
    span = float((P[leaf].max(axis=0) - lo).max()) or 1.0
    floor = SIGMA_FLOOR_REL * span if sigma_floor is None else float(sigma_floor)
    o = 0.5 * (P[leaf].min(axis=0) + P[leaf].max(axis=0))  # centre: moments without cancellation
    Q = P - o
    nn = _unit(Nrm, np.array([0.0, 0.0, 1.0]))
    # pass 1: area, Σa p, Σa p pᵀ + disc, Σa n over each node's leaves
    iu = np.triu_indices(3)
    W = np.zeros(M)
    S1 = np.zeros((M, 3))
    S2 = np.zeros((M, 6))
    Sn = np.zeros((M, 3))
    leaf_pp = np.einsum("ni,nj->nij", Q, Q)[:, iu[0], iu[1]]
    disc = (Ad / (4 * np.pi))[:, None, None] * (np.eye(3)[None] - np.einsum("ni,nj->nij", nn, nn))
    leaf_m2 = A[:, None] * (leaf_pp + disc[:, iu[0], iu[1]])
    for lf, nd in _ancestor_levels(tree):
        a = A[lf]
        W += np.bincount(nd, a, minlength=M)
        for j in range(3):
            S1[:, j] += np.bincount(nd, a * Q[lf, j], minlength=M)
            Sn[:, j] += np.bincount(nd, a * nn[lf, j], minlength=M)
        for j in range(6):
            S2[:, j] += np.bincount(nd, leaf_m2[lf, j], minlength=M)
    mu = S1 / W[:, None]
    C6 = S2 / W[:, None]
    C = np.empty((M, 3, 3))
    C[:, iu[0], iu[1]] = C6
    C[:, iu[1], iu[0]] = C6
    C -= np.einsum("mi,mj->mij", mu, mu)
    C = 0.5 * (C + np.transpose(C, (0, 2, 1)))
    lam, vec = np.linalg.eigh(C)  # ascending
    lam = lam[:, ::-1]
    F = np.transpose(vec[:, :, ::-1], (0, 2, 1))  # rows = axes, σ descending
    sig = np.sqrt(np.maximum(lam, 0.0))
    # mean normal; where the normals cancel, the thinnest position axis
    m = _unit(Sn, F[:, 2])
    # frames: z along the mean normal's side; the paper's degenerate cases
    f1, f3 = F[:, 0].copy(), F[:, 2].copy()
    two_zero = sig[:, 1] <= floor
    three_zero = sig[:, 0] <= floor
    z_from_m = _unit(m - (m * f1).sum(1, keepdims=True) * f1, tangent_basis(f1)[0])
    f3 = np.where(two_zero[:, None], z_from_m, f3)
    tx, _ = tangent_basis(m)
    f3 = np.where(three_zero[:, None], m, f3)
    f1 = np.where(three_zero[:, None], tx, f1)
    f3 = np.where(((f3 * m).sum(1) < 0)[:, None], -f3, f3)
    f2 = np.cross(f3, f1)
    frame_p = np.stack([f1, f2, f3], 1)
    sigma_p = np.maximum(sig, floor)
    # pass 2: normals unwrapped at each node's pole (azimuthal equidistant map)
    bx, by = tangent_basis(m)
    Su = np.zeros((M, 2))
    Suu = np.zeros((M, 3))
    for lf, nd in _ancestor_levels(tree):
        n = nn[lf]
        z = m[nd]
        c = np.clip((n * z).sum(1), -1.0, 1.0)
        t = n - c[:, None] * z
        tl = np.linalg.norm(t, axis=1)
        th = np.arccos(c)
        s = np.where(tl > 1e-15, th / np.where(tl > 1e-15, tl, 1.0), 0.0)
        u = s * (t * bx[nd]).sum(1)
        v = s * (t * by[nd]).sum(1)
        a = A[lf]
        Su[:, 0] += np.bincount(nd, a * u, minlength=M)
        Su[:, 1] += np.bincount(nd, a * v, minlength=M)
        Suu[:, 0] += np.bincount(nd, a * u * u, minlength=M)
        Suu[:, 1] += np.bincount(nd, a * u * v, minlength=M)
        Suu[:, 2] += np.bincount(nd, a * v * v, minlength=M)
    mu_uv = Su / W[:, None]
    cuu = Suu[:, 0] / W - mu_uv[:, 0] ** 2
    cuv = Suu[:, 1] / W - mu_uv[:, 0] * mu_uv[:, 1]
    cvv = Suu[:, 2] / W - mu_uv[:, 1] ** 2
    tr = 0.5 * (cuu + cvv)
    dis = np.sqrt(np.maximum(0.25 * (cuu - cvv) ** 2 + cuv**2, 0.0))
    l1, l2 = tr + dis, tr - dis
    ang = 0.5 * np.arctan2(2 * cuv, cuu - cvv)  # major axis angle in the (bx, by) plane
    nx = np.cos(ang)[:, None] * bx + np.sin(ang)[:, None] * by
    ny = np.cross(m, nx)
    frame_n = np.stack([nx, ny, m], 1)
    sigma_n = np.sqrt(np.maximum(np.stack([l1, l2], 1), 0.0))
    return NodeStats(mean=mu + o, frame_p=frame_p, sigma_p=sigma_p, frame_n=frame_n, sigma_n=sigma_n, area=W)


def disc_over_area(tree: PointTree) -> float:
    """κ = median over the leaves of π r² / a: how much the model's discs overlap."""
    lf = tree.is_leaf & (tree.areas > 0)
    if not lf.any():
        return 1.0
    return float(np.median(np.pi * tree.radii[lf].astype(np.float64) ** 2 / tree.areas[lf]))


def radius_tensors(
    cov: np.ndarray, normals: np.ndarray, *, scale: float = NODE_SCALE, leaf_radii: np.ndarray | None = None
) -> np.ndarray:
    """(M, 6) radius tensors ``R² = 4s (I − m mᵀ) C (I − m mᵀ)`` as xx, xy, xz, yy, yz, zz (m²).

    Parameters
    ----------
    cov : (M, 3, 3) position covariances (:meth:`NodeStats.covariance`).
    normals : (M, 3) unit splat normals m.  scale : s (:data:`NODE_SCALE`).
    leaf_radii : (M,) or None; where > 0, the node is drawn as its own disc ``r²(I − m mᵀ)``.
    """
    m = np.asarray(normals, np.float64)
    Pm = np.eye(3)[None] - np.einsum("mi,mj->mij", m, m)
    R = 4.0 * float(scale) * np.einsum("mij,mjk,mkl->mil", Pm, np.asarray(cov, np.float64), Pm)
    if leaf_radii is not None:
        r = np.asarray(leaf_radii, np.float64)
        R = np.where((r > 0)[:, None, None], r[:, None, None] ** 2 * Pm, R)
    iu = np.triu_indices(3)
    return R[:, iu[0], iu[1]]


# ----------------------------------------------------------------------------- codebooks


@dataclass(frozen=True)
class Codebook:
    """k-means codebook of log-spreads. ``centres`` (K, d) float32 hold log σ."""

    centres: np.ndarray

    def encode(self, sigma: np.ndarray, *, floor: float) -> np.ndarray:
        """(n,) uint16 index of the nearest centre to log(max(σ, floor))."""
        from scipy.spatial import KDTree

        x = np.log(np.maximum(np.asarray(sigma, np.float64), floor))
        _, idx = KDTree(self.centres.astype(np.float64)).query(x)
        return np.asarray(idx, np.uint16)

    def decode(self, idx: np.ndarray) -> np.ndarray:
        """(n, d) σ of the indices."""
        return np.exp(self.centres[np.asarray(idx, np.int64)].astype(np.float64))


def fit_codebook(sigma: np.ndarray, *, size: int, floor: float, train: int = 16384, seed: int = 0) -> Codebook:
    """k-means (``scipy.cluster.vq.kmeans2``, 8 Lloyd iterations) on ``log max(σ, floor)``.

    Parameters
    ----------
    sigma : (n, d) spreads.  size : centres (≤ 65536; fewer when there are fewer distinct values).
    train : at most this many spreads (a seeded sample) train the centres.
    """
    from scipy.cluster.vq import kmeans2

    x = np.log(np.maximum(np.asarray(sigma, np.float64), floor))
    if x.ndim != 2 or len(x) == 0:
        raise InputError(f"fit_codebook: expected (n, d) spreads with n ≥ 1, got {x.shape}")
    uniq = np.unique(np.round(x, 9), axis=0)
    if len(uniq) <= size:
        return Codebook(uniq.astype(np.float32))
    rng = np.random.default_rng(seed)
    sample = x if len(x) <= train else x[rng.choice(len(x), train, replace=False)]
    k = min(size, len(np.unique(np.round(sample, 9), axis=0)))
    # initial centres: distinct sample points (scipy's "++" start is O(k²n) in Python:
    # 2 minutes for 1024 centres over 9000 spreads); an emptied cluster keeps its centre
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        centres, _ = kmeans2(sample, k, iter=8, minit="points", rng=np.random.default_rng(seed))
    return Codebook(np.asarray(centres, np.float32))


# ----------------------------------------------------------------------------- packing


def oct_encode(n: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Octahedral map of unit vectors (Meyer et al. 2010) to two ``bits``-bit integers."""
    n = np.asarray(n, np.float64)
    n = n / np.maximum(np.abs(n).sum(-1, keepdims=True), 1e-30)
    x, y = n[..., 0], n[..., 1]
    neg = n[..., 2] < 0
    sx = np.where(x >= 0, 1.0, -1.0)
    sy = np.where(y >= 0, 1.0, -1.0)
    x, y = np.where(neg, (1 - np.abs(n[..., 1])) * sx, x), np.where(neg, (1 - np.abs(n[..., 0])) * sy, y)
    q = (1 << bits) - 1
    u = np.clip(np.round((x * 0.5 + 0.5) * q), 0, q).astype(np.uint32)
    v = np.clip(np.round((y * 0.5 + 0.5) * q), 0, q).astype(np.uint32)
    return u, v


def oct_decode(u: np.ndarray, v: np.ndarray, bits: int) -> np.ndarray:
    """Inverse of :func:`oct_encode`: (..., 3) unit vectors."""
    q = (1 << bits) - 1
    x = np.asarray(u, np.float64) / q * 2 - 1
    y = np.asarray(v, np.float64) / q * 2 - 1
    z = 1 - np.abs(x) - np.abs(y)
    t = np.maximum(-z, 0.0)
    x = x - np.where(x >= 0, t, -t)
    y = y - np.where(y >= 0, t, -t)
    n = np.stack([x, y, z], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


NODE_DTYPE = np.dtype(
    [
        ("mean", "<u4"),  # 11-11-10 bits on the bundle's box (10 on its thinnest axis)
        ("fp", "u1", 3),  # f_p³ octahedral 8 + 8 bits, f_p¹'s angle about it 8 bits
        ("fn", "u1", 3),  # mean normal octahedral 8 + 8 bits, f_n x's angle about it 8 bits
        ("sig", "u1", 3),  # σ_p codebook index (12 bits) | σ_n index (12 bits) << 12
        ("r_min", "u1"),  # error code (see ``error_codes``)
        ("r_max", "u1"),
        ("vis", "<u2"),  # visibility dictionary index
    ]
)
"""Inner-node record, 17 bytes (the paper's 13 bytes of geometry + LOD interval + visibility index)."""

LEAF_DTYPE = np.dtype(
    [
        ("nrm", "u1", 3),  # octahedral 12 + 12 bits
        ("radius", "u1"),  # log code over the leaves' radius range
        ("area", "u1"),  # log code over the leaves' area range
        ("r_max", "u1"),  # error code of the parent's error
        ("vis", "<u2"),
    ]
)
"""Leaf record, 8 bytes (position from the octree code)."""

ERROR_LEVELS = 253


def _log_codes(x: np.ndarray, lo: float, hi: float, levels: int) -> np.ndarray:
    """Monotone log code 1..levels+1 of x in [lo, hi] (0 for x ≤ 0, levels+2 for +inf)."""
    x = np.asarray(x, np.float64)
    ratio = max(hi / lo, 1.0 + 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = 1 + np.round(levels * np.log(np.maximum(x, lo) / lo) / np.log(ratio))
    k = np.clip(np.nan_to_num(k, nan=1.0, posinf=levels + 1), 1, levels + 1)
    k = np.where(x > 0, k, 0)
    return np.where(np.isinf(x), levels + 2, k).astype(np.uint8)


def _log_values(k: np.ndarray, lo: float, hi: float, levels: int) -> np.ndarray:
    k = np.asarray(k, np.float64)
    ratio = max(hi / lo, 1.0 + 1e-12)
    v = lo * ratio ** ((k - 1) / levels)
    return np.where(k == 0, 0.0, np.where(k == levels + 2, np.inf, v))


@dataclass(frozen=True)
class PackedNodes:
    """A point tree with statistical inner nodes, packed (the bundle's records).

    ``header`` holds every constant the decoder needs (JSON-able); ``order`` maps packed
    inner record i to tree node ``inner_ids[i]`` (and leaves likewise)."""

    header: dict
    inner: np.ndarray  # NODE_DTYPE records
    leaves: np.ndarray  # LEAF_DTYPE records
    inner_ids: np.ndarray
    leaf_ids: np.ndarray
    codebook_p: Codebook
    codebook_n: Codebook
    vis_dict: np.ndarray  # (D, ceil(V/8)) uint8

    def nbytes(self) -> dict:
        return {
            "inner": int(self.inner.nbytes),
            "leaves": int(self.leaves.nbytes),
            "codebooks": int(self.codebook_p.centres.nbytes + self.codebook_n.centres.nbytes),
            "visibility_dictionary": int(self.vis_dict.nbytes),
        }


def _angle_code(axis: np.ndarray, z: np.ndarray) -> np.ndarray:
    bx, by = tangent_basis(z)
    psi = np.mod(np.arctan2((axis * by).sum(-1), (axis * bx).sum(-1)), np.pi)
    return (np.round(psi / np.pi * 256).astype(np.int64) % 256).astype(np.uint8)


def _angle_axis(code: np.ndarray, z: np.ndarray) -> np.ndarray:
    bx, by = tangent_basis(z)
    psi = np.asarray(code, np.float64) / 256 * np.pi
    return np.cos(psi)[:, None] * bx + np.sin(psi)[:, None] * by


def pack_nodes(
    tree: PointTree,
    stats: NodeStats,
    *,
    codebook_p: int | None = None,
    codebook_n: int | None = None,
    seed: int = 0,
) -> PackedNodes:
    """Quantise ``tree`` (inner nodes with ``stats``) into :data:`NODE_DTYPE` and
    :data:`LEAF_DTYPE` records, k-means codebooks and a visibility dictionary.

    Parameters
    ----------
    codebook_p, codebook_n : centres of the σ_p (3-D) and σ_n (2-D) codebooks (≤ 4096: 12-bit
        indices); default one per 32 inner nodes, 64 … 4096 (the paper: 1500 and 800 for
        1.34 M nodes), so that the codebooks cost ≤ 0.6 bytes per inner node.
    """
    n_inner = int((~tree.is_leaf).sum())
    auto = int(np.clip(n_inner // 32, 64, 4096))
    codebook_p = auto if codebook_p is None else int(codebook_p)
    codebook_n = auto if codebook_n is None else int(codebook_n)
    if not (1 <= codebook_p <= 4096 and 1 <= codebook_n <= 4096):
        raise InputError(f"codebook sizes {codebook_p}, {codebook_n}: expected 1..4096 (12-bit indices)")
    leaf = tree.is_leaf
    inner_ids = np.flatnonzero(~leaf)
    leaf_ids = np.flatnonzero(leaf)
    P = tree.positions.astype(np.float64)
    lo = P.min(axis=0)
    hi = P.max(axis=0)
    ext = np.maximum(hi - lo, 1e-12)
    thin = int(np.argmin(ext))
    axes = [a for a in range(3) if a != thin] + [thin]  # bits 11, 11, 10
    bits = [11, 11, 10]
    span_floor = SIGMA_FLOOR_REL * float(ext.max())
    # visibility dictionary (lossless)
    vis_dict, vis_idx = np.unique(tree.visibility, axis=0, return_inverse=True)
    vis_idx = vis_idx.reshape(-1)
    if len(vis_dict) > 65536:
        raise InputError(
            f"pack_nodes: {len(vis_dict)} distinct visibility patterns; the 16-bit dictionary index holds 65536"
        )
    # errors: one monotone log code for r_min and r_max, so r_max(child) = r_min(parent) stays exact
    e = tree.r_min.astype(np.float64)
    pos_e = e[e > 0]
    e_lo = float(pos_e.min()) if pos_e.size else 1.0
    e_hi = float(pos_e.max()) if pos_e.size else 1.0
    rec = np.zeros(len(inner_ids), NODE_DTYPE)
    if len(inner_ids):
        mu = stats.mean[inner_ids]
        q = 0
        for sh, a, b in zip((0, 11, 22), axes, bits, strict=True):
            s = (1 << b) - 1
            c = np.clip(np.round((mu[:, a] - lo[a]) / ext[a] * s), 0, s).astype(np.uint32)
            q = q | (c << np.uint32(sh))
        rec["mean"] = q
        fp = stats.frame_p[inner_ids]
        u, v = oct_encode(fp[:, 2], 8)
        z = oct_decode(u, v, 8)
        rec["fp"][:, 0], rec["fp"][:, 1] = u, v
        rec["fp"][:, 2] = _angle_code(fp[:, 0], z)
        fn = stats.frame_n[inner_ids]
        u, v = oct_encode(fn[:, 2], 8)
        z = oct_decode(u, v, 8)
        rec["fn"][:, 0], rec["fn"][:, 1] = u, v
        rec["fn"][:, 2] = _angle_code(fn[:, 0], z)
        cbp = fit_codebook(stats.sigma_p[inner_ids], size=codebook_p, floor=span_floor, seed=seed)
        cbn = fit_codebook(stats.sigma_n[inner_ids], size=codebook_n, floor=SIGMA_N_FLOOR, seed=seed)
        ip = cbp.encode(stats.sigma_p[inner_ids], floor=span_floor).astype(np.uint32)
        inn = cbn.encode(stats.sigma_n[inner_ids], floor=SIGMA_N_FLOOR).astype(np.uint32)
        packed = ip | (inn << np.uint32(12))
        for j in range(3):
            rec["sig"][:, j] = (packed >> np.uint32(8 * j)) & np.uint32(255)
        rec["r_min"] = _log_codes(e[inner_ids], e_lo, e_hi, ERROR_LEVELS)
        rec["r_max"] = _log_codes(tree.r_max[inner_ids], e_lo, e_hi, ERROR_LEVELS)
        rec["vis"] = vis_idx[inner_ids]
    else:
        cbp = Codebook(np.zeros((1, 3), np.float32))
        cbn = Codebook(np.zeros((1, 2), np.float32))
    lrec = np.zeros(len(leaf_ids), LEAF_DTYPE)
    r = tree.radii[leaf_ids].astype(np.float64)
    ar = tree.areas[leaf_ids].astype(np.float64)
    r_lo, r_hi = float(np.min(r[r > 0])) if (r > 0).any() else 1.0, float(np.max(r)) if len(r) else 1.0
    a_lo, a_hi = float(np.min(ar[ar > 0])) if (ar > 0).any() else 1.0, float(np.max(ar)) if len(ar) else 1.0
    u, v = oct_encode(tree.normals[leaf_ids], 12)
    w = u | (v << np.uint32(12))
    for j in range(3):
        lrec["nrm"][:, j] = (w >> np.uint32(8 * j)) & np.uint32(255)
    lrec["radius"] = _log_codes(r, r_lo, r_hi, 254)
    lrec["area"] = _log_codes(ar, a_lo, a_hi, 254)
    lrec["r_max"] = _log_codes(tree.r_max[leaf_ids], e_lo, e_hi, ERROR_LEVELS)
    lrec["vis"] = vis_idx[leaf_ids]
    header = {
        "box_min": lo.tolist(),
        "box_size": ext.tolist(),
        "mean_axes": axes,
        "mean_bits": bits,
        "error_range": [e_lo, e_hi],
        "error_levels": ERROR_LEVELS,
        "radius_range": [r_lo, r_hi],
        "area_range": [a_lo, a_hi],
        "kappa": disc_over_area(tree),
        "sigma_p_floor": span_floor,
        "sigma_n_floor": SIGMA_N_FLOOR,
        "n_views": int(tree.n_views),
    }
    return PackedNodes(header, rec, lrec, inner_ids, leaf_ids, cbp, cbn, vis_dict.astype(np.uint8))


def unpack_nodes(packed: PackedNodes, *, leaf_positions: np.ndarray | None = None) -> tuple[PointTree, NodeStats]:
    """The tree and statistics the packed records stand for (node order of the tree
    they were packed from; parent links are not stored and come back as −1).

    Parameters
    ----------
    leaf_positions : (n_leaves, 3) positions of the leaves in ``packed.leaf_ids`` order
        (in the bundle: the octree code's); None leaves them at the box's corner.
    """
    h = packed.header
    ni, nl = len(packed.inner), len(packed.leaves)
    M = ni + nl
    if packed.vis_dict.ndim != 2:
        raise FormatError("unpack_nodes: visibility dictionary is not a 2-D byte table")
    lo = np.asarray(h["box_min"], np.float64)
    ext = np.asarray(h["box_size"], np.float64)
    e_lo, e_hi = h["error_range"]
    L = int(h["error_levels"])
    pos = np.zeros((M, 3))
    nrm = np.zeros((M, 3))
    rad = np.zeros(M)
    area = np.zeros(M)
    r_min = np.zeros(M)
    r_max = np.zeros(M)
    vis_idx = np.zeros(M, np.int64)
    frame_p = np.zeros((M, 3, 3))
    frame_n = np.zeros((M, 3, 3))
    sigma_p = np.zeros((M, 3))
    sigma_n = np.zeros((M, 2))
    ii, li = packed.inner_ids, packed.leaf_ids
    rec = packed.inner
    if ni:
        q = rec["mean"].astype(np.uint32)
        for sh, a, b in zip((0, 11, 22), h["mean_axes"], h["mean_bits"], strict=True):
            s = (1 << b) - 1
            pos[ii, a] = lo[a] + ((q >> np.uint32(sh)) & np.uint32(s)) / s * ext[a]
        z = oct_decode(rec["fp"][:, 0], rec["fp"][:, 1], 8)
        x = _angle_axis(rec["fp"][:, 2], z)
        frame_p[ii] = np.stack([x, np.cross(z, x), z], 1)
        z = oct_decode(rec["fn"][:, 0], rec["fn"][:, 1], 8)
        x = _angle_axis(rec["fn"][:, 2], z)
        frame_n[ii] = np.stack([x, np.cross(z, x), z], 1)
        sg = rec["sig"].astype(np.uint32)
        packed_idx = sg[:, 0] | (sg[:, 1] << np.uint32(8)) | (sg[:, 2] << np.uint32(16))
        sigma_p[ii] = packed.codebook_p.decode(packed_idx & np.uint32(4095))
        sigma_n[ii] = packed.codebook_n.decode(packed_idx >> np.uint32(12))
        nrm[ii] = z
        r_min[ii] = _log_values(rec["r_min"], e_lo, e_hi, L)
        r_max[ii] = _log_values(rec["r_max"], e_lo, e_hi, L)
        vis_idx[ii] = rec["vis"]
    lr = packed.leaves
    if nl:
        w = lr["nrm"].astype(np.uint32)
        w = w[:, 0] | (w[:, 1] << np.uint32(8)) | (w[:, 2] << np.uint32(16))
        nrm[li] = oct_decode(w & np.uint32(4095), w >> np.uint32(12), 12)
        rad[li] = _log_values(lr["radius"], h["radius_range"][0], h["radius_range"][1], 254)
        area[li] = _log_values(lr["area"], h["area_range"][0], h["area_range"][1], 254)
        r_max[li] = _log_values(lr["r_max"], e_lo, e_hi, L)
        vis_idx[li] = lr["vis"]
        pos[li] = lo if leaf_positions is None else np.asarray(leaf_positions, np.float64)
        # a leaf's statistics are its disc
        t1, t2 = tangent_basis(nrm[li])
        frame_p[li] = np.stack([t1, t2, nrm[li]], 1)
        s = np.sqrt(area[li] / (4 * np.pi))
        sigma_p[li] = np.stack([s, s, np.full_like(s, h["sigma_p_floor"])], 1)
        frame_n[li] = frame_p[li]
    stats = NodeStats(mean=pos, frame_p=frame_p, sigma_p=sigma_p, frame_n=frame_n, sigma_n=sigma_n, area=area)
    if ni:
        # a node's coverage area is its ellipse's: π·(2σ₁)(2σ₂) of the tangent projection
        C = stats.covariance()[ii]
        m = nrm[ii]
        Pm = np.eye(3)[None] - np.einsum("mi,mj->mij", m, m)
        Ct = np.einsum("mij,mjk,mkl->mil", Pm, C, Pm)
        ev = np.linalg.eigvalsh(Ct)
        area[ii] = 4 * np.pi * np.sqrt(np.maximum(ev[:, 2] * ev[:, 1], 0.0))
        rad[ii] = np.sqrt(h["kappa"] * area[ii] / np.pi)
        stats = NodeStats(mean=pos, frame_p=frame_p, sigma_p=sigma_p, frame_n=frame_n, sigma_n=sigma_n, area=area)
    vis = packed.vis_dict[vis_idx]
    tree = PointTree(
        positions=pos.astype(np.float32),
        normals=nrm.astype(np.float32),
        radii=rad.astype(np.float32),
        areas=area.astype(np.float32),
        visibility=np.ascontiguousarray(vis),
        r_min=r_min.astype(np.float32),
        r_max=r_max.astype(np.float32),
        parent=np.full(M, -1, np.int64),
        is_leaf=np.isin(np.arange(M), li),
        leaf_index=np.where(np.isin(np.arange(M), li), 0, -1),
        n_views=int(h["n_views"]),
    )
    return tree, stats


def statistical_cut(
    tree: PointTree, stats: NodeStats, mask: np.ndarray, *, scale: float = NODE_SCALE
) -> tuple[Surfels, np.ndarray, np.ndarray]:
    """A cut of ``tree`` as statistical splats: (surfels, areas (n,), radius tensors (n, 6)).

    Inner nodes are drawn at their mean with their mean normal and the ellipse of their
    position PCA (:func:`radius_tensors`); leaves as their own discs. Pass the tensors to
    :func:`~opacityhull.render.renderer.render_image` as ``splat_cov``."""
    idx = np.flatnonzero(np.asarray(mask, bool))
    leaf = tree.is_leaf[idx]
    pos = np.where(leaf[:, None], tree.positions[idx], stats.mean[idx])
    nrm = np.where(leaf[:, None], tree.normals[idx], stats.normal[idx])
    cov = radius_tensors(stats.covariance()[idx], nrm, scale=scale, leaf_radii=np.where(leaf, tree.radii[idx], 0.0))
    s = Surfels(pos, nrm, tree.radii[idx], tree.visibility[idx], tree.n_views)
    return s, tree.areas[idx].astype(np.float32), cov
