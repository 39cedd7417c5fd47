"""Level of detail: a sequential point tree over the surfels (Dachsbacher, Vogelgsang &
Stamminger 2003).

The hierarchy is an octree over the Morton-sorted surfels, with single-child cells
collapsed. Each node is a disc that stands for its subtree: area-weighted mean position
and normal, the summed area, the OR of the visibility bits, a render radius that keeps the
subtree's total disc area (√Σr²), and a geometric error ``e`` = the radius of the sphere
that encloses every child disc (0 for leaves). Node ``i`` covers the error interval
``[r_min, r_max) = [e_i, e_parent(i))`` (the root's r_max is +∞): along every leaf-to-root
path the intervals partition [0, ∞), so for any threshold t exactly one node per path has
``r_min ≤ t < r_max`` — the cut is a partition of the surface, with no holes and no double
cover. With the view-dependent threshold ``t = τ · distance`` the cut adapts to the view.

The flat array is sorted by r_max, largest first ("sequential"): every node whose
``r_max > t_min`` lies in a prefix, so a renderer takes the prefix for the nearest
distance and tests the interval per node (on the GPU: in the vertex shader).
:func:`select_cut` picks τ for a splat budget on the CPU; :func:`cut_surfels` returns the
cut as :class:`~opacityhull.model.Surfels` that the CPU renderer draws unchanged.

It lives in ``render`` because both ``render --budget`` and the viewer bundle
(``opacityhull.view``, which may import ``render`` but not the other way round) use it;
``opacityhull.view.lod`` re-exports it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..model import Surfels
from .morton import morton_codes

log = logging.getLogger(__name__)

__all__ = ["PointTree", "build_point_tree", "select_cut", "cut_mask", "cut_surfels"]


@dataclass(frozen=True)
class PointTree:
    """Sequential point tree (flat arrays, sorted by ``r_max`` descending).

    Attributes
    ----------
    positions, normals : (M, 3) float32.  radii : (M,) float32 render radius (m).
    areas : (M,) float32 surface area the node stands for (m²).
    visibility : (M, ceil(V/8)) uint8 packed bits (OR over the subtree).
    r_min, r_max : (M,) float32 error interval (m); r_max = inf for the root.
    parent : (M,) int64 index of the parent node (−1 for the root).
    is_leaf : (M,) bool (leaves are the model's surfels). leaf_index : (M,) int64 surfel
        index of a leaf, −1 for internal nodes.
    n_views : V.
    """

    positions: np.ndarray
    normals: np.ndarray
    radii: np.ndarray
    areas: np.ndarray
    visibility: np.ndarray
    r_min: np.ndarray
    r_max: np.ndarray
    parent: np.ndarray
    is_leaf: np.ndarray
    leaf_index: np.ndarray
    n_views: int

    def __len__(self) -> int:
        return self.positions.shape[0]


def build_point_tree(surfels: Surfels, areas: np.ndarray | None = None, *, depth: int = 16) -> PointTree:
    """Build the sequential point tree of ``surfels``.

    Parameters
    ----------
    surfels : the model's surfels (finite positions).
    areas : (N,) area per surfel (m²); default π r².
    depth : octree levels of the Morton grid (≤ 21).
    """
    N = len(surfels)
    if N == 0:
        raise InputError("build_point_tree: no surfels")
    P = surfels.positions.astype(np.float64)
    if not np.all(np.isfinite(P)):
        raise InputError(
            f"build_point_tree: {int((~np.isfinite(P).all(axis=1)).sum())} surfels have non-finite positions"
        )
    if not 1 <= depth <= 21:
        raise InputError(f"build_point_tree: depth {depth}, expected 1..21")
    A = (np.pi * surfels.radii.astype(np.float64) ** 2) if areas is None else np.asarray(areas, np.float64)
    code = morton_codes(P, bits=depth)  # the renderer's Morton order
    order = np.argsort(code, kind="stable")
    # node storage (appended level by level); leaves first
    pos: list[np.ndarray] = [P[order]]
    nrm: list[np.ndarray] = [surfels.normals.astype(np.float64)[order]]
    rad: list[np.ndarray] = [surfels.radii.astype(np.float64)[order]]
    area: list[np.ndarray] = [A[order]]
    vis: list[np.ndarray] = [surfels.visibility[order]]
    err: list[np.ndarray] = [np.zeros(N)]
    leaf_idx: list[np.ndarray] = [order.astype(np.int64)]
    n_nodes = N
    parent_chunks = []  # (child node ids, parent node ids)
    cur = np.arange(N)  # node ids of the current frontier, in Morton order
    cur_code = code[order]
    cur_pos, cur_nrm, cur_rad, cur_area, cur_vis, cur_err = pos[0], nrm[0], rad[0], area[0], vis[0], err[0]
    for _level in range(depth):
        pcode = cur_code >> np.uint64(3)
        starts = np.flatnonzero(np.r_[True, pcode[1:] != pcode[:-1]])
        counts = np.diff(np.r_[starts, len(pcode)])
        multi = counts > 1
        if not multi.any():
            cur_code = pcode
            if len(cur) == 1:
                break
            continue
        grp = np.repeat(np.arange(len(starts)), counts)  # group of each frontier node
        w = cur_area
        wsum = np.bincount(grp, w)
        wsafe = np.where(wsum > 0, wsum, 1.0)
        gpos = np.stack([np.bincount(grp, w * cur_pos[:, j]) for j in range(3)], 1) / wsafe[:, None]
        cnt = np.bincount(grp).astype(float)
        zero_w = wsum <= 0
        if zero_w.any():
            gpos[zero_w] = np.stack([np.bincount(grp, cur_pos[:, j]) for j in range(3)], 1)[zero_w] / cnt[zero_w, None]
        gn = np.stack([np.bincount(grp, np.maximum(w, 1e-30) * cur_nrm[:, j]) for j in range(3)], 1)
        gnn = np.linalg.norm(gn, axis=1, keepdims=True)
        gn = np.where(gnn > 1e-12, gn / np.maximum(gnn, 1e-30), [0.0, 0.0, 0.0])
        enclose = np.linalg.norm(cur_pos - gpos[grp], axis=1) + np.maximum(cur_rad, cur_err)
        gerr = np.zeros(len(starts))
        np.maximum.at(gerr, grp, enclose)
        grad = np.sqrt(np.bincount(grp, cur_rad**2))
        gvis = np.bitwise_or.reduceat(cur_vis, starts, axis=0) if cur_vis.shape[1] else cur_vis[starts]
        # groups of one pass their node through; groups of several get a new node
        new_ids = np.full(len(starts), -1, np.int64)
        k = int(multi.sum())
        new_ids[multi] = n_nodes + np.arange(k)
        n_nodes += k
        child_multi = multi[grp]
        parent_chunks.append((cur[child_multi], new_ids[grp[child_multi]]))
        pos.append(gpos[multi])
        nrm.append(gn[multi])
        rad.append(grad[multi])
        area.append(wsum[multi])
        vis.append(gvis[multi])
        err.append(gerr[multi])
        leaf_idx.append(np.full(k, -1, np.int64))
        nxt = np.where(multi, new_ids, cur[starts])
        cur = nxt
        cur_code = pcode[starts]
        cur_pos = np.where(multi[:, None], gpos, cur_pos[starts])
        cur_nrm = np.where(multi[:, None], gn, cur_nrm[starts])
        cur_rad = np.where(multi, grad, cur_rad[starts])
        cur_area = np.where(multi, wsum, cur_area[starts])
        cur_vis = np.where(multi[:, None], gvis, cur_vis[starts])
        cur_err = np.where(multi, gerr, cur_err[starts])
        if len(cur) == 1:
            break
    if len(cur) > 1:  # several top cells left (depth exhausted): one root over them
        grp = np.zeros(len(cur), np.int64)
        w = np.maximum(cur_area, 1e-30)
        rp = (w[:, None] * cur_pos).sum(0) / w.sum()
        rn = (w[:, None] * cur_nrm).sum(0)
        rn = rn / (np.linalg.norm(rn) or 1.0)
        pos.append(rp[None])
        nrm.append(rn[None])
        rad.append(np.sqrt([np.sum(cur_rad**2)]))
        area.append(np.array([cur_area.sum()]))
        vis.append(np.bitwise_or.reduce(cur_vis, axis=0)[None])
        err.append(np.array([np.max(np.linalg.norm(cur_pos - rp, axis=1) + np.maximum(cur_rad, cur_err))]))
        leaf_idx.append(np.array([-1]))
        parent_chunks.append((cur, np.full(len(cur), n_nodes)))
        n_nodes += 1
    parent = np.full(n_nodes, -1, np.int64)
    for c, p in parent_chunks:
        parent[c] = p
    e = np.concatenate(err)
    r_max = np.where(parent >= 0, e[np.maximum(parent, 0)], np.inf)
    srt = np.argsort(-r_max, kind="stable")
    inv = np.empty_like(srt)
    inv[srt] = np.arange(n_nodes)
    par = np.where(parent[srt] >= 0, inv[np.maximum(parent[srt], 0)], -1)
    li = np.concatenate(leaf_idx)[srt]
    return PointTree(
        positions=np.concatenate(pos)[srt].astype(np.float32),
        normals=np.concatenate(nrm)[srt].astype(np.float32),
        radii=np.concatenate(rad)[srt].astype(np.float32),
        areas=np.concatenate(area)[srt].astype(np.float32),
        visibility=np.ascontiguousarray(np.concatenate(vis)[srt]).astype(np.uint8),
        r_min=e[srt].astype(np.float32),
        r_max=r_max[srt].astype(np.float32),
        parent=par,
        is_leaf=li >= 0,
        leaf_index=li,
        n_views=surfels.n_views,
    )


def _distances(tree: PointTree, eye) -> np.ndarray:
    """(M,) float32 distance of every node from ``eye`` (one expression for the cut and
    its selection, so both see the same rounding; float32 is 3x faster and its 1e-7
    relative error is far below any error interval)."""
    D = tree.positions - np.asarray(eye, np.float32).reshape(1, 3)
    return np.sqrt(np.einsum("ij,ij->i", D, D))


def _in_cut(tree: PointTree, tau: float, d: np.ndarray) -> np.ndarray:
    t = float(tau) * d
    return (tree.r_min <= t) & (t < tree.r_max)


def cut_mask(tree: PointTree, tau: float, eye) -> np.ndarray:
    """(M,) bool: nodes with ``r_min ≤ τ·d < r_max``, d = distance from ``eye`` (τ = 0: the leaves)."""
    return _in_cut(tree, tau, _distances(tree, eye))


def select_cut(tree: PointTree, eye, budget: int, *, iterations: int = 40) -> tuple[float, np.ndarray]:
    """The finest view-dependent cut with at most ``budget`` nodes.

    Parameters
    ----------
    tree : :class:`PointTree`.  eye : (3,) camera centre (object frame, m).
    budget : splats allowed (≥ 1); ≥ the number of leaves gives the full model.

    Returns
    -------
    (τ, mask): the error per unit distance chosen by bisection, and the (M,) node mask
    (1 ≤ mask.sum() ≤ budget).
    """
    if int(budget) < 1:
        raise InputError(f"--budget {budget}: expected >= 1")
    n_leaves = int(tree.is_leaf.sum())
    if budget >= n_leaves:
        return 0.0, tree.is_leaf.copy()
    d = _distances(tree, eye)
    # node i is in the cut for τ in [r_min/d, r_max/d): with both ends sorted once, the
    # count at any τ is two binary searches instead of a pass over the tree
    dd = np.maximum(d, np.float32(1e-12))
    lo_i = np.sort(tree.r_min / dd)
    hi_i = np.sort(tree.r_max / dd)  # +inf for the root

    def count(tau):
        t = lo_i.dtype.type(tau)  # a float64 key would convert the whole float32 array per search
        return int(np.searchsorted(lo_i, t, side="right")) - int(np.searchsorted(hi_i, t, side="right"))

    # start from a τ at which only the root qualifies (τ·d ≥ r_max for every other node,
    # and ≥ the root's r_min), so a cut within the budget always exists: with t = τ·d
    # varying per node, the count at τ = max(r_min / d) can exceed the budget (a parent
    # and a nearer child both pass)
    fin = np.isfinite(hi_i)
    hi = max(float(hi_i[fin][-1]) if fin.any() else 0.0, float(lo_i[-1])) * (1 + 1e-6) + 1e-9
    lo, best, root_only = 0.0, hi, hi
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if 1 <= count(mid) <= budget:  # (never an empty cut)
            best, hi = mid, mid
        else:
            lo = mid
    mask = _in_cut(tree, best, d)
    n = int(np.count_nonzero(mask))
    if not 1 <= n <= budget:  # a node on the rounding edge of τ·d vs r/d: walk to a safe τ
        for tau in best * (1 + np.geomspace(1e-9, 1e-3, 13)):
            mask = _in_cut(tree, float(tau), d)
            if 1 <= int(np.count_nonzero(mask)) <= budget:
                return float(tau), mask
        return root_only, _in_cut(tree, root_only, d)
    return best, mask


def cut_surfels(tree: PointTree, mask: np.ndarray) -> tuple[Surfels, np.ndarray]:
    """The cut as renderable :class:`Surfels` and their areas (for edge coverage)."""
    m = np.asarray(mask, bool)
    s = Surfels(tree.positions[m], tree.normals[m], tree.radii[m], tree.visibility[m], tree.n_views)
    return s, tree.areas[m]
