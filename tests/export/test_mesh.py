"""PMR umbrella mesh (seed 004) and ``export --format mesh``: the triangles are Delaunay
triangles (scipy.spatial.Delaunay on the same points), octree leaves agree with one
global triangulation, and the PLY / OBJ read back with trimesh and plyfile."""

from __future__ import annotations

import json

import numpy as np
import pytest

from opacityhull.render.pmr import circumcentres, mesh_quality, octree_leaves, umbrella_triangulation
from opacityhull.render.synthetic import fibonacci_sphere


def _faces_of(simplices: np.ndarray) -> set:
    out = set()
    for t in simplices:
        for i in range(4):
            out.add(tuple(sorted(np.delete(t, i).tolist())))
    return out


def _bumpy(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A jittered ellipsoid-like closed surface with outward normals (not cospherical)."""
    rng = np.random.default_rng(seed)
    d = fibonacci_sphere(n)
    r = 0.1 * (1 + 0.15 * np.sin(3 * d[:, 0]) * np.cos(2 * d[:, 1]))
    P = d * r[:, None] * np.array([1.0, 0.8, 1.2]) + rng.normal(scale=1e-4, size=(n, 3))
    # normals of the implicit shape by finite differences of the radial map
    eps = 1e-4
    t1 = np.cross(d, [0.0, 0.0, 1.0])
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-9)
    t2 = np.cross(d, t1)

    def surf(u):
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        rr = 0.1 * (1 + 0.15 * np.sin(3 * u[:, 0]) * np.cos(2 * u[:, 1]))
        return u * rr[:, None] * np.array([1.0, 0.8, 1.2])

    nrm = np.cross(surf(d + eps * t1) - surf(d - eps * t1), surf(d + eps * t2) - surf(d - eps * t2))
    nrm *= np.sign((nrm * d).sum(1, keepdims=True))
    return P, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def test_umbrella_triangles_are_delaunay_triangles_and_close_a_sphere():
    from scipy.spatial import Delaunay

    P, N = _bumpy(1500, 1)
    u = umbrella_triangulation(P, N, max_points=100_000)
    assert u.leaves == 1 and len(u.triangles) > 0
    dl = Delaunay(P)
    faces = _faces_of(dl.simplices)
    assert all(tuple(sorted(t)) in faces for t in u.triangles.tolist())
    # a closed, well-sampled surface: the umbrella mesh is a closed 2-manifold (Euler: F = 2V − 4)
    q = mesh_quality(P, u.triangles, P, voxel_m=0.005)
    assert q["manifold_edge_fraction"] > 0.99 and q["holes"] <= 2
    # outward orientation: the signed volume is positive
    a, b, c = P[u.triangles].transpose(1, 0, 2)
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() > 0
    # feature measure: finite, small on a dense sample (long skinny cells), umbrellas of ~6
    assert np.nanmedian(u.feature) < 0.3 and 4 <= np.median(u.umbrella_size) <= 8


def test_octree_leaves_agree_with_one_triangulation():
    P, N = _bumpy(3000, 2)
    one = umbrella_triangulation(P, N, max_points=100_000)
    many = umbrella_triangulation(P, N, max_points=500)
    assert many.leaves > 4
    a = {tuple(t) for t in np.sort(one.triangles, axis=1).tolist()}
    b = {tuple(t) for t in np.sort(many.triangles, axis=1).tolist()}
    assert len(a ^ b) <= 0.01 * len(a)
    leaves = octree_leaves(P, 500)
    assert sorted(np.concatenate([i for i, _, _ in leaves]).tolist()) == list(range(len(P)))


def test_circumcentres_are_equidistant():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(40, 3))
    from scipy.spatial import Delaunay

    s = Delaunay(P).simplices
    c = circumcentres(P, s)
    d = np.linalg.norm(P[s] - c[:, None], axis=2)
    np.testing.assert_allclose(d, np.repeat(d[:, :1], 4, axis=1), rtol=1e-8)


@pytest.fixture(scope="module")
def sphere_model(tmp_path_factory):
    from opacityhull.render.synthetic import write_sphere_model

    return write_sphere_model(tmp_path_factory.mktemp("mesh") / "sphere", n_surfels=3000, width=48, height=36)


@pytest.mark.parametrize("method", ["umbrella", "marching-cubes"])
def test_mesh_export_reads_back_with_trimesh_and_plyfile(sphere_model, tmp_path, method):
    trimesh = pytest.importorskip("trimesh")
    from helpers import invoke_cli
    from plyfile import PlyData

    root, m = sphere_model
    out = tmp_path / "m"
    r = invoke_cli(["export", root, "--format", "mesh", "--mesh-method", method, "--out", out, "--json"])
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["format"] == "mesh" and s["method"] == method
    assert s["manifold_edge_fraction"] > 0.99 and s["holes"] == 0 and s["chamfer_voxels"] < 0.5
    ply = PlyData.read(str(out / "mesh.ply"))
    v, f = ply["vertex"].data, ply["face"].data
    V = np.c_[v["x"], v["y"], v["z"]]
    assert len(f) == s["faces"]
    if method == "umbrella":  # the vertices are the surfels
        np.testing.assert_allclose(V, m.surfels.positions, atol=1e-7)
    faces = np.stack(f["vertex_indices"])
    assert faces.shape == (s["faces"], 3) and faces.min() >= 0 and faces.max() < len(v)
    # vertex colours: the sphere's texture, not black
    assert np.mean(v["red"].astype(float) + v["green"] + v["blue"]) > 60
    for name in ("mesh.ply", "mesh.obj"):
        tm = trimesh.load(str(out / name), process=False)
        assert len(tm.vertices) == len(v) and len(tm.faces) == s["faces"]
        np.testing.assert_allclose(tm.vertices, V, atol=1e-6)
        np.testing.assert_array_equal(tm.faces, faces)
        assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
        c = np.asarray(tm.visual.vertex_colors)[:, :3].astype(int)
        np.testing.assert_allclose(c, np.c_[v["red"], v["green"], v["blue"]], atol=1)
        # the enclosed volume is the sphere's (radius 0.08 m) within the sampling's loss
        assert tm.volume == pytest.approx(4 / 3 * np.pi * 0.08**3, rel=0.03)
