"""Umbrella triangulation of the surfels (PMR, Dey & Hudson 2002, §2).

Per octree leaf (at most ``max_points`` surfels, with the points of a margin around it so
that the Voronoi cells of its own points are complete), Qhull's 3-D Delaunay
triangulation (``scipy.spatial.Delaunay``) gives the Voronoi diagram: a cell's vertices
are the circumcentres of the tetrahedra around its point, and the Voronoi edge dual to a
Delaunay triangle joins the circumcentres of the two tetrahedra that share it. For a
surfel p with normal n (the hull's; the paper estimates it from the pole):

* the **umbrella** of p: the Delaunay triangles incident to p whose dual Voronoi edge
  crosses p's tangent plane (the plane through p ⟂ n) — for dense samples these lie flat
  on the surface;
* the **tangent polygon** is that plane's section of the cell; its vertices are those
  crossings, and the cell's **radius** r is the farthest of them from p;
* the cell's **height** h is the distance from p to its farthest Voronoi vertex (the
  pole), the local feature size; the paper's **feature measure** is r / h (small: a long
  skinny cell, a redundant point; the paper decimates below a threshold);
* the **umbrella radius**: the largest distance from p to a vertex of its umbrella — PMR
  draws the umbrella where twice that exceeds a pixel and the point elsewhere.

The mesh is the triangles that lie in the umbrellas of all three of their vertices (the
paper notes a triangle in one umbrella is very likely in the other two; requiring all
three keeps the surface a 2-manifold where the sampling is good), oriented by the
surfels' normals. Each triangle is kept by the leaf that holds its first vertex.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["Umbrellas", "umbrella_triangulation", "circumcentres", "octree_leaves", "mesh_quality", "sample_faces"]


@dataclass(frozen=True)
class Umbrellas:
    """Result of :func:`umbrella_triangulation` (surfel order of the input).

    Attributes
    ----------
    triangles : (T, 3) int64 surfel indices, counter-clockwise seen from outside.
    umbrella_radius : (N,) float64 m (0 without an umbrella).
    height, radius : (N,) float64 m: pole distance and tangent-polygon radius of the
        Voronoi cell (inf / nan where the cell is unbounded or the plane misses it).
    feature : (N,) float64 r / h.
    umbrella_size : (N,) int64 triangles in each umbrella.
    leaves : octree leaves triangulated.
    """

    triangles: np.ndarray
    umbrella_radius: np.ndarray
    height: np.ndarray
    radius: np.ndarray
    feature: np.ndarray
    umbrella_size: np.ndarray
    leaves: int


def circumcentres(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """(T, 3) circumcentres of tetrahedra (NaN for flat ones)."""
    P = np.asarray(points, np.float64)[simplices]
    a = P[:, 0]
    A = P[:, 1:] - a[:, None]
    b = 0.5 * (A**2).sum(axis=2)
    det = np.linalg.det(A)
    scale = np.abs(A).max(axis=(1, 2)) ** 3
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    out = np.full((len(P), 3), np.nan)
    if ok.any():
        out[ok] = a[ok] + np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return out


def octree_leaves(points: np.ndarray, max_points: int) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Octree leaves of at most ``max_points`` points: [(point indices, cell min corner, cell edge)]."""
    P = np.asarray(points, np.float64)
    lo = P.min(axis=0)
    size = float((P.max(axis=0) - lo).max()) * (1 + 1e-9) or 1.0
    out = []
    stack = [(np.arange(len(P)), lo, size, 0)]
    while stack:
        idx, c, s, depth = stack.pop()
        if len(idx) <= max_points or depth >= 20:
            if len(idx):
                out.append((idx, c, s))
            continue
        h = 0.5 * s
        o = ((P[idx] - c) >= h).astype(np.int64)
        key = o[:, 0] + 2 * o[:, 1] + 4 * o[:, 2]
        for k in range(8):
            sub = idx[key == k]
            if len(sub):
                stack.append((sub, c + h * np.array([k & 1, (k >> 1) & 1, (k >> 2) & 1]), h, depth + 1))
    return out


def umbrella_triangulation(
    positions: np.ndarray,
    normals: np.ndarray,
    *,
    max_points: int = 10000,
    margin: float | None = None,
    agree: int = 3,
) -> Umbrellas:
    """The umbrellas, feature measure and umbrella mesh of oriented points.

    Parameters
    ----------
    positions : (N, 3) m.  normals : (N, 3) unit, outward.
    max_points : surfels per octree leaf (the paper: 8 000–12 000).
    margin : points within this distance (m) of a leaf's cell join its triangulation;
        default 4 × the median nearest-neighbour spacing.
    agree : a triangle is in the mesh when it lies in the umbrellas of at least this many
        of its vertices (3: all).
    """
    from scipy.spatial import Delaunay, KDTree

    P = np.asarray(positions, np.float64)
    Nrm = np.asarray(normals, np.float64)
    N = len(P)
    if N < 4 or P.shape != (N, 3) or Nrm.shape != (N, 3):
        raise InputError(f"umbrella_triangulation: expected ≥ 4 points with normals, got {P.shape} and {Nrm.shape}")
    if not (np.isfinite(P).all() and np.isfinite(Nrm).all()):
        raise InputError("umbrella_triangulation: non-finite positions or normals")
    Nrm = Nrm / np.maximum(np.linalg.norm(Nrm, axis=1, keepdims=True), 1e-30)
    if margin is None:
        d, _ = KDTree(P).query(P, k=2)
        margin = 4.0 * float(np.median(d[:, 1]))
    height = np.full(N, np.inf)
    radius = np.full(N, np.nan)
    uradius = np.zeros(N)
    usize = np.zeros(N, np.int64)
    tris = []
    leaves = octree_leaves(P, max_points)
    for own, c, s in leaves:
        inside = np.all((P >= c - margin) & (P <= c + s + margin), axis=1)
        ids = np.flatnonzero(inside)
        owned = np.zeros(N, bool)
        owned[own] = True
        if len(ids) < 5:
            continue
        dl = Delaunay(P[ids])
        simp = dl.simplices
        cc = circumcentres(P[ids], simp)
        # height: the farthest (finite) Voronoi vertex of each own point's cell, the pole
        v = simp.ravel()
        t = np.repeat(np.arange(len(simp)), 4)
        dist = np.nan_to_num(np.linalg.norm(cc[t] - P[ids][v], axis=1), nan=0.0)
        h = np.zeros(len(ids))
        np.maximum.at(h, v, dist)
        sel = owned[ids]
        height[ids[sel]] = np.where(h[sel] > 0, h[sel], np.inf)
        # faces: tetra t, opposite vertex i; each interior face once (t < neighbour); a
        # face on the hull is dual to a ray from t's circumcentre, outward along its normal
        nb = dl.neighbors
        T = np.repeat(np.arange(len(simp)), 4)
        OPP = np.tile(np.arange(4), len(simp))
        NB = nb.ravel()
        keep = ((NB > T) | (NB < 0)) & np.isfinite(cc[T]).all(axis=1) & np.isfinite(cc[np.maximum(NB, 0)]).all(axis=1)
        T, OPP, NB = T[keep], OPP[keep], NB[keep]
        fv = np.stack([simp[T, (OPP + k) % 4] for k in (1, 2, 3)], 1)  # local ids of the face's vertices
        Q = P[ids]
        c1 = cc[T]
        c2 = cc[np.maximum(NB, 0)].copy()
        ray = NB < 0
        if ray.any():
            fa, fb, fc = Q[fv[ray, 0]], Q[fv[ray, 1]], Q[fv[ray, 2]]
            d = np.cross(fb - fa, fc - fa)
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
            opp = Q[simp[T[ray], OPP[ray]]]
            d = np.where(((opp - fa) * d).sum(1, keepdims=True) > 0, -d, d)
            reach = 10.0 * float(np.ptp(Q, axis=0).max() + 1.0)
            c2[ray] = c1[ray] + reach * d
        inu = np.zeros(fv.shape, bool)
        for k in range(3):
            p = P[ids][fv[:, k]]
            n = Nrm[ids][fv[:, k]]
            s1 = ((c1 - p) * n).sum(1)
            s2 = ((c2 - p) * n).sum(1)
            cross = (s1 * s2) <= 0.0
            inu[:, k] = cross
            # tangent-polygon vertex: the crossing point of the dual edge
            tt = np.where(cross, s1 / np.where(s1 != s2, s1 - s2, 1.0), 0.0)
            x = c1 + tt[:, None] * (c2 - c1)
            rr = np.where(cross, np.linalg.norm(x - p, axis=1), -np.inf)
            gid = ids[fv[:, k]]
            mine = owned[gid] & cross
            r_acc = np.full(N, -np.inf)
            np.maximum.at(r_acc, gid[mine], rr[mine])
            got = r_acc > -np.inf
            radius[got] = np.fmax(np.nan_to_num(radius[got], nan=-np.inf), r_acc[got])
            # umbrella radius: farthest umbrella vertex
            far = np.zeros(len(fv))
            for j in range(3):
                far = np.maximum(far, np.linalg.norm(P[ids][fv[:, j]] - p, axis=1))
            np.maximum.at(uradius, gid[mine], far[mine])
            np.add.at(usize, gid[mine], 1)
        full = inu.sum(axis=1) >= agree
        g = ids[fv[full]]
        first = g.min(axis=1)
        g = g[owned[first]]
        tris.append(g)
    tri = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    if len(tri):
        tri = np.unique(np.sort(tri, axis=1), axis=0)
        a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
        fn = np.cross(b - a, c - a)
        flip = (fn * (Nrm[tri[:, 0]] + Nrm[tri[:, 1]] + Nrm[tri[:, 2]])).sum(1) < 0
        tri[flip] = tri[flip][:, [0, 2, 1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        feature = radius / height
    return Umbrellas(
        triangles=tri.astype(np.int64),
        umbrella_radius=uradius,
        height=height,
        radius=radius,
        feature=feature,
        umbrella_size=usize,
        leaves=len(leaves),
    )


def mesh_quality(vertices: np.ndarray, faces: np.ndarray, surfels: np.ndarray, *, voxel_m: float) -> dict:
    """Manifold edges, holes and the Chamfer distance to the surfels of a triangle mesh.

    Returns
    -------
    ``manifold_edge_fraction`` (edges with exactly two faces), ``boundary_edges``,
    ``nonmanifold_edges`` (> 2 faces), ``holes`` (boundary loops: connected components of
    the boundary edges), ``chamfer_voxels`` (mean of the two mean nearest distances,
    surfels → mesh samples and mesh samples → surfels, in ``voxel_m``; the mesh sampled
    on a barycentric grid of 15 points a triangle), and the counts.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import KDTree

    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    ue, cnt = np.unique(e, axis=0, return_counts=True)
    bnd = ue[cnt == 1]
    holes = 0
    if len(bnd):
        nodes, inv = np.unique(bnd.ravel(), return_inverse=True)
        inv = inv.reshape(-1, 2)
        g = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(nodes), len(nodes)))
        holes = int(connected_components(g, directed=False)[0])
    # Chamfer: the mesh sampled on a barycentric grid (15 points a triangle) against the surfels
    S = np.asarray(surfels, np.float64)
    samples = sample_faces(V, F) if len(F) else V
    d1, _ = KDTree(samples).query(S)
    d2, _ = KDTree(S).query(samples)
    return {
        "vertices": int(len(V)),
        "faces": int(len(F)),
        "edges": int(len(ue)),
        "manifold_edge_fraction": float((cnt == 2).mean()) if len(ue) else 0.0,
        "boundary_edges": int((cnt == 1).sum()),
        "nonmanifold_edges": int((cnt > 2).sum()),
        "holes": holes,
        "chamfer_voxels": float(0.5 * (d1.mean() + d2.mean()) / voxel_m),
        "surfels_to_mesh_voxels": float(d1.mean() / voxel_m),
        "mesh_to_surfels_voxels": float(d2.mean() / voxel_m),
    }


def sample_faces(vertices: np.ndarray, faces: np.ndarray, *, k: int = 4) -> np.ndarray:
    """Points of every triangle on the barycentric grid (i/k, j/k), i + j ≤ k."""
    ij = np.array([(i, j) for i in range(k + 1) for j in range(k + 1 - i)], np.float64) / k
    w = np.c_[1 - ij.sum(1), ij]
    T = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]  # (F, 3, 3)
    return np.einsum("sk,fkd->fsd", w, T).reshape(-1, 3)
