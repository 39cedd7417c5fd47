"""Surfels on the hull (LDC sampling, bisection, normals, hole-free radii) and their
depth-tested visibility."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from opacityhull.errors import InputError, ShapeError
from opacityhull.reconstruct.hull import HullGrid, carve_octree, point_in_hull
from opacityhull.reconstruct.surfels import hull_normals, hull_normals_reference, sample_hull_surfels
from opacityhull.reconstruct.visibility import depth_maps, surfel_visibility, surfel_visibility_reference

from test_rc_hull import CENTRE, R, ring_cameras, sphere_silhouette


@pytest.fixture(scope="module")
def sphere_hull():
    cams = ring_cameras(24, W=128, H=96, f=150.0, el_deg=(-20.0, 15.0, 50.0))
    sils = [sphere_silhouette(c) for c in cams]
    grid = HullGrid.from_bounds(CENTRE - 0.065, CENTRE + 0.065, 48)
    occ = carve_octree(sils, cams, grid)
    footprint = 0.6 / 150.0
    sample = sample_hull_surfels(occ, grid, sils, cams, bisection_iters=12, normal_scale_vox=footprint / grid.voxel_m)
    return cams, sils, grid, occ, sample


def test_surfels_lie_on_the_image_based_hull(sphere_hull):
    """Each surfel is within voxel / 2**iters of the exact (silhouette-tested) hull
    boundary along its LDC axis: a step inwards is inside, a step outwards outside."""
    cams, sils, grid, occ, s = sphere_hull
    e = np.eye(3)[s.axis]
    sign = np.sign(s.normals[np.arange(len(s)), s.axis])
    step = 2.0 * grid.voxel_m / 2**12
    inside = point_in_hull(s.positions - sign[:, None] * step * e, sils, cams)
    outside = ~point_in_hull(s.positions + sign[:, None] * step * e, sils, cams)
    assert inside.mean() > 0.99 and outside.mean() > 0.99
    r = np.linalg.norm(s.positions - CENTRE, axis=1)
    assert r.min() > R - 0.004 and r.max() < R + 0.01  # on the (fattened) sphere


def test_surfel_normals_and_reduction(sphere_hull):
    cams, sils, grid, occ, s = sphere_hull
    radial = (s.positions - CENTRE) / np.linalg.norm(s.positions - CENTRE, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip((radial * s.normals).sum(1), -1, 1)))
    # the hull of 8 azimuths per ring is faceted (facets up to ~22 deg apart): the
    # normals follow the facets, so they differ from the sphere's by a few degrees
    assert np.median(ang) < 8.0 and np.percentile(ang, 99) < 30.0
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-5)
    an = np.abs(s.normals)
    nax = an[np.arange(len(s)), s.axis]
    assert np.all(nax >= 0.85 * an.max(axis=1) - 1e-6)  # 3-to-1 reduction (+ seam overlap 0.15)
    dominant = np.argmax(an, axis=1) == s.axis
    assert 0.7 < dominant.mean() < 0.95
    np.testing.assert_allclose(s.radii, s.spacing_m / (math.sqrt(2) * np.maximum(nax, 0.85 / math.sqrt(3))), rtol=1e-5)
    # density: the dominant axis samples |n_a| / spacing^2 per unit area, ~0.8 on average
    # over a sphere, plus the seam overlap (the hull is a slightly fattened sphere)
    area = 4 * math.pi * np.median(np.linalg.norm(s.positions - CENTRE, axis=1)) ** 2
    density = len(s) * s.spacing_m**2 / area
    assert 0.8 < density < 1.2


def test_surfel_discs_cover_the_hull_without_holes(sphere_hull):
    """Random points of the hull surface (found by bisection along random rays from the
    centre) each lie on some surfel disc."""
    cams, sils, grid, occ, s = sphere_hull
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo = np.zeros(len(d))
    hi = np.full(len(d), 0.06)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        ins = point_in_hull(CENTRE + mid[:, None] * d, sils, cams)
        lo = np.where(ins, mid, lo)
        hi = np.where(ins, hi, mid)
    pts = CENTRE + lo[:, None] * d
    tree = cKDTree(s.positions)
    _, idx = tree.query(pts, k=12)
    rel = pts[:, None, :] - s.positions[idx]
    n = s.normals[idx]
    off = np.abs((rel * n).sum(-1))
    inplane = np.sqrt(np.maximum((rel**2).sum(-1) - off**2, 0))
    covered = np.any((inplane <= s.radii[idx]) & (off <= 2 * s.spacing_m), axis=1)
    assert covered.mean() == 1.0


def test_normals_kernel_matches_reference(sphere_hull):
    cams, sils, grid, occ, s = sphere_hull
    pts = s.positions[::97]
    np.testing.assert_allclose(
        hull_normals(occ, grid, pts, sigma_vox=1.3, radius_vox=3),
        hull_normals_reference(occ, grid, pts, sigma_vox=1.3, radius_vox=3),
        atol=1e-9,
    )


def test_oversampling_and_empty_hull(sphere_hull):
    cams, sils, grid, occ, s = sphere_hull
    s2 = sample_hull_surfels(occ, grid, sils, cams, oversample=2, normal_scale_vox=1.0)
    assert 3.0 < len(s2) / len(s) < 5.0
    assert s2.spacing_m == pytest.approx(grid.voxel_m / 2)
    e = sample_hull_surfels(np.zeros(grid.shape, bool), grid, sils, cams)
    assert len(e) == 0 and e.positions.shape == (0, 3)
    with pytest.raises(InputError):
        sample_hull_surfels(occ[:-1], grid, sils, cams)


# --------------------------------------------------------------------------- visibility


def test_visibility_kernel_matches_reference(sphere_hull):
    cams, sils, grid, occ, s = sphere_hull
    sub = slice(None, None, 7)
    few = cams[::4]
    a = surfel_visibility(s.positions[sub], s.normals[sub], s.radii[sub], few)
    b = surfel_visibility_reference(s.positions[sub], s.normals[sub], s.radii[sub], few)
    np.testing.assert_array_equal(a, b)


def test_sphere_visibility_is_the_facing_hemisphere(sphere_hull):
    """Convex object: a surfel is visible where it faces the camera (beyond a band
    around the rim), and never where the segment to the camera runs through the hull —
    a depth test, not just the frustum. Occlusion is checked independently by sampling
    the segment with the silhouette point test."""
    cams, sils, grid, occ, s = sphere_hull
    vis = surfel_visibility(s.positions, s.normals, s.radii, cams)
    radial = (s.positions - CENTRE) / np.linalg.norm(s.positions - CENTRE, axis=1, keepdims=True)
    C = np.array([c.centre_world for c in cams])
    to_cam = C[None] - s.positions[:, None]
    dist = np.linalg.norm(to_cam, axis=-1)
    cosang = (radial[:, None] * to_cam).sum(-1) / dist
    assert vis[cosang > 0.2].mean() > 0.995
    # occluded: some point 3 voxels or more along the segment to the camera is in the hull
    sub = np.arange(0, len(s), 5)
    u = to_cam[sub] / dist[sub][..., None]  # (n, V, 3)
    ts = np.linspace(3 * grid.voxel_m, 2.3 * R, 24)
    pts = s.positions[sub][:, None, None, :] + ts[None, None, :, None] * u[:, :, None, :]
    occluded = point_in_hull(pts.reshape(-1, 3), sils, cams).reshape(len(sub), len(cams), len(ts)).any(axis=2)
    assert occluded.mean() > 0.3
    # away from the rim the depth test agrees with the segment test exactly; at grazing
    # angles (|cos| < 0.3 between hull normal and view ray: 73 deg, given normal errors of
    # up to ~15 deg at the hull's creases) either answer is defensible
    cos_n = (s.normals[sub][:, None, :] * to_cam[sub]).sum(-1) / dist[sub]
    clear = np.abs(cos_n) >= 0.3
    assert not np.any((vis[sub] & occluded)[clear])
    assert (vis[sub] & occluded).sum() < 0.05 * vis[sub].sum()


def test_occluded_surfels_are_not_visible():
    """Two spheres on a line with the camera: the far sphere's facing cap is hidden."""
    rng = np.random.default_rng(1)

    def sphere_pts(c, r, n):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return c + r * d, d

    c1, c2 = np.array([0.0, 0.05, 0.1]), np.array([0.06, 0.05, -0.1])  # far one half hidden
    p1, n1 = sphere_pts(c1, 0.05, 20000)
    p2, n2 = sphere_pts(c2, 0.05, 20000)
    P = np.concatenate([p1, p2])
    N = np.concatenate([n1, n2])
    rad = np.full(len(P), 0.0015)
    cam = ring_cameras(1, W=96, H=72, f=120.0, dist=0.8, el_deg=(0.0,), target=np.array([0.0, 0.05, 0.0]))[0]
    assert cam.centre_world[2] > 0.5  # looking along -z: sphere 1 in front of sphere 2
    vis = surfel_visibility(P, N, rad, [cam])[:, 0]
    # far sphere, facing the camera, behind the near sphere (its ray passes within the
    # near sphere's radius minus a margin)
    o = cam.centre_world
    d2 = p2 - o
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    t = ((c1 - o) * d2).sum(1)
    miss = np.linalg.norm(o + t[:, None] * d2 - c1, axis=1)
    facing = (n2 * (o - p2)).sum(1) > 0
    hidden = facing & (miss < 0.045)
    assert hidden.sum() > 500
    assert not vis[len(p1) :][hidden].any()
    exposed = facing & (miss > 0.055) & ((n2 * (o - p2)).sum(1) / np.linalg.norm(o - p2, axis=1) > 0.3)
    assert exposed.sum() > 100 and vis[len(p1) :][exposed].mean() > 0.99
    near_front = (n1 * (o - p1)).sum(1) / np.linalg.norm(o - p1, axis=1) > 0.3
    assert vis[: len(p1)][near_front].mean() > 0.99


def test_depth_maps_and_input_checks(sphere_hull):
    cams, sils, grid, occ, s = sphere_hull
    zb = depth_maps(s.positions, s.radii, cams[:2])
    assert zb.shape == (2, 96, 128)
    assert np.isinf(zb[0, 0, 0])  # corner: background
    c = cams[0]
    uv, z = c.project(CENTRE[None])
    px = np.floor(uv[0] + 0.5).astype(int)
    assert zb[0, px[1], px[0]] == pytest.approx(z[0] - R, abs=0.006)  # the sphere's near point
    with pytest.raises(ShapeError):
        surfel_visibility(s.positions, s.normals[:-1], s.radii, cams)
    bad = s.positions.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        surfel_visibility(bad, s.normals, s.radii, cams)


def test_packed_bisection_stacks_answer_as_the_unpacked_silhouettes():
    """The bisection reads bit-packed silhouettes and a block-pooled distance floor: the
    point test equals the carvers' on the unpacked stack for random points and odd
    widths, the floor is a lower bound of the exact distance, and nothing (V, H, W) is
    held (0.31 B a pixel a view)."""
    from numba import njit

    from opacityhull.reconstruct.hull import _centre_carves, _stack_silhouettes, projection_matrices
    from opacityhull.reconstruct.surfels import (
        EDT_BLOCK,
        _centre_carves_bits,
        packed_bisection_stacks,
        silhouette_distance,
    )

    @njit(cache=False)
    def both(P, sil, bits, sizes, pts, out):
        for v in range(P.shape[0]):
            for k in range(pts.shape[0]):
                x, y, z = pts[k, 0], pts[k, 1], pts[k, 2]
                out[v, k, 0] = _centre_carves(P, sil, sizes, v, x, y, z)
                out[v, k, 1] = _centre_carves_bits(P, bits, sizes, v, x, y, z)

    rng = np.random.default_rng(5)
    cams = ring_cameras(5, W=61, H=43, f=70.0, el_deg=(-10.0, 30.0))
    sils = [sphere_silhouette(c) for c in cams]
    for s in sils:  # a few specks and holes, so that pixel-exact addressing matters
        s[rng.integers(0, 43, 30), rng.integers(0, 61, 30)] ^= True
    bits, strong, sizes, edt = packed_bisection_stacks(sils, cams)
    assert strong is bits and bits.shape == (5, 43, 8) and edt.shape == (5, 11, 16)
    assert bits.nbytes + edt.nbytes < 0.2 * 5 * 43 * 61
    sil, sizes_ref = _stack_silhouettes(sils, cams)
    np.testing.assert_array_equal(sizes, sizes_ref)
    pts = CENTRE + rng.uniform(-1.5 * R, 1.5 * R, (4000, 3))
    out = np.zeros((5, len(pts), 2), np.bool_)
    both(projection_matrices(cams), sil, bits, sizes, pts, out)
    assert out[..., 0].any() and not out[..., 0].all()
    np.testing.assert_array_equal(out[..., 0], out[..., 1])
    exact = silhouette_distance(sils)
    for v in range(5):
        lower = np.repeat(np.repeat(edt[v], EDT_BLOCK, 0), EDT_BLOCK, 1)[:43, :61]
        assert np.all(lower <= np.floor(exact[v])) and lower.max() > 0
    with pytest.raises(InputError, match="superset"):
        packed_bisection_stacks(sils, cams, [np.zeros_like(s) for s in sils])
    with pytest.raises(ShapeError, match=r"expected \(43, 61\)"):
        packed_bisection_stacks([s[:, :-1] for s in sils], cams)
