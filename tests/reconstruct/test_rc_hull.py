"""Visual hull: octree == dense == NumPy reference, conservative rules, bounds, hard cases."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.errors import InputError
from opacityhull.reconstruct.hull import (
    EmptyHullError,
    HullGrid,
    carve_dense,
    carve_octree,
    carve_reference,
    hull_bounds,
    point_in_hull,
    silhouette_from_alpha,
    undistort_silhouette,
)

CENTRE = np.array([0.0, 0.05, 0.0])
R = 0.05


def ring_cameras(n, *, W=64, H=48, dist=0.6, el_deg=(10.0, 40.0), f=70.0, target=CENTRE, seed=None):
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        el = math.radians(el_deg[i % len(el_deg)])
        az = 2 * math.pi * i / n + (0 if seed is None else rng.uniform(-0.2, 0.2))
        eye = target + dist * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
        cams.append(Camera(K=K, width=W, height=H, world_from_cam=look_at_world_from_cam(eye, target), name=f"v{i}"))
    return cams


def sphere_silhouette(cam, c=CENTRE, r=R):
    o, d = cam.pixel_rays()
    oc = o - c
    b = d @ oc
    return b * b - (oc @ oc - r * r) >= 0


def box_silhouette(cam, lo, hi):
    """Silhouette of an axis-aligned box by ray-slab intersection at pixel centres."""
    o, d = cam.pixel_rays()
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (np.asarray(lo) - o) / d
        t1 = (np.asarray(hi) - o) / d
    tn = np.nanmax(np.minimum(t0, t1), axis=-1)
    tf = np.nanmin(np.maximum(t0, t1), axis=-1)
    return (tf >= tn) & (tf > 0)


def scene_silhouettes(cams):
    return [sphere_silhouette(c) | box_silhouette(c, (0.03, 0.0, -0.02), (0.08, 0.03, 0.02)) for c in cams]


@pytest.fixture(scope="module")
def ring():
    cams = ring_cameras(12, seed=1)
    return cams, scene_silhouettes(cams)


@pytest.mark.parametrize("res,root", [(17, 4), (33, 8), (40, 32)])
def test_octree_equals_dense_equals_reference(ring, res, root):
    cams, sils = ring
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), res)
    ref = carve_reference(sils, cams, grid)
    dense = carve_dense(sils, cams, grid)
    octo, stats = carve_octree(sils, cams, grid, root_cell=root, return_stats=True)
    assert ref.sum() > 100
    np.testing.assert_array_equal(dense, ref)
    np.testing.assert_array_equal(octo, ref)  # not a voxel fatter than centre sampling
    assert stats.tests < ref.size * len(cams)  # and it did less work than testing every voxel


def test_hull_contains_object_and_is_bounded_by_silhouettes(ring):
    cams, sils = ring
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), 48)
    occ = carve_octree(sils, cams, grid)
    c = grid.all_centres()
    inside = np.linalg.norm(c - CENTRE, axis=-1) < R - 1.5 * grid.voxel_m
    assert np.all(occ[inside])
    far = np.linalg.norm(c - CENTRE, axis=-1) > 0.15
    assert not np.any(occ & far)


def test_many_views_and_mixed_image_sizes():
    cams = ring_cameras(70, W=40, H=30, f=45.0)
    cams = [c if i % 3 else c.scaled(1.5) for i, c in enumerate(cams)]
    sils = [sphere_silhouette(c) for c in cams]
    grid = HullGrid.from_bounds(CENTRE - 0.07, CENTRE + 0.07, 24)
    np.testing.assert_array_equal(carve_octree(sils, cams, grid, root_cell=8), carve_reference(sils, cams, grid))


def test_silhouette_touching_the_border_is_not_carved_outside():
    """A close camera whose silhouette runs off the image: voxels projecting outside the
    image are not carved by it (they may be part of the object)."""
    far = ring_cameras(8)
    close = ring_cameras(1, dist=0.12, f=100.0, el_deg=(5.0,))  # the sphere fills and overflows it
    sil_close = sphere_silhouette(close[0])
    assert sil_close.all()  # the silhouette is the whole image: it touches every border
    cams = far + close
    sils = [sphere_silhouette(c) for c in cams]
    grid = HullGrid.from_bounds(CENTRE - 0.07, CENTRE + 0.07, 32)
    occ = carve_octree(sils, cams, grid)
    np.testing.assert_array_equal(occ, carve_reference(sils, cams, grid))
    base = carve_octree(sils[:-1], cams[:-1], grid)
    uv, z = close[0].project(grid.all_centres().reshape(-1, 3))
    outside = ~close[0].in_image(uv).reshape(grid.shape)
    assert outside.sum() > 1000
    np.testing.assert_array_equal(occ, base)  # a full silhouette carves nothing, off-image or not
    c = grid.all_centres()
    inside = np.linalg.norm(c - CENTRE, axis=-1) < R - 1.5 * grid.voxel_m
    assert np.all(occ[inside])


def _inner_camera(eye) -> Camera:
    """A 40 x 30 px camera (f = 30 px) at ``eye`` looking along +x."""
    K = np.array([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]])
    T = look_at_world_from_cam(eye, eye + np.array([1.0, 0.0, 0.0]))
    return Camera(K=K, width=40, height=30, world_from_cam=T, name="inner")


def test_camera_centre_inside_the_bounding_volume():
    """A camera inside the grid (looking outwards) carves only in front of it; voxels
    behind it and on its plane stay, and the three carvers still agree."""
    cams = ring_cameras(8)
    eye = CENTRE + np.array([0.0, 0.0, 0.0])
    inner = _inner_camera(eye)
    sil_inner = np.zeros((30, 40), bool)  # sees nothing of the object in front of it
    grid = HullGrid.from_bounds(CENTRE - 0.07, CENTRE + 0.07, 28)
    sils = [sphere_silhouette(c) for c in cams] + [sil_inner]
    allc = cams + [inner]
    occ = carve_octree(sils, allc, grid, root_cell=4)
    np.testing.assert_array_equal(occ, carve_reference(sils, allc, grid))
    np.testing.assert_array_equal(occ, carve_dense(sils, allc, grid))
    base = carve_octree(sils[:-1], cams, grid)
    c = grid.all_centres()
    behind = (c[..., 0] - eye[0]) <= 0.0
    np.testing.assert_array_equal(occ[behind], base[behind])  # untouched behind the camera
    in_view = (c[..., 0] - eye[0]) > 0.01
    rel = c - eye
    with np.errstate(divide="ignore", invalid="ignore"):
        seen = in_view & (np.abs(rel[..., 2] / rel[..., 0]) * 30 < 19) & (np.abs(rel[..., 1] / rel[..., 0]) * 30 < 14)
    assert not np.any(occ & seen)  # carved where it sees (empty silhouette)


def test_empty_silhouette_carves_everything_in_view_and_bounds_refuse():
    cams = ring_cameras(6)
    sils = [sphere_silhouette(c) for c in cams]
    sils[2] = np.zeros_like(sils[2])
    grid = HullGrid.from_bounds(CENTRE - 0.07, CENTRE + 0.07, 20)
    assert not carve_octree(sils, cams, grid).any()
    with pytest.raises(EmptyHullError, match="v2"):
        hull_bounds(sils, cams)


def test_hull_bounds_contain_the_hull_and_are_tight():
    cams = ring_cameras(12)
    sils = [sphere_silhouette(c) for c in cams]
    lo, hi = hull_bounds(sils, cams, margin_px=0.0)
    assert np.all(lo <= CENTRE - R + 1e-3) and np.all(hi >= CENTRE + R - 1e-3)
    assert np.all(lo > CENTRE - R - 0.02) and np.all(hi < CENTRE + R + 0.02)
    grid = HullGrid.from_bounds(lo - 0.02, hi + 0.02, 40)
    occ = carve_octree(sils, cams, grid)
    c = grid.all_centres()[occ]
    assert np.all(c >= lo - grid.voxel_m) and np.all(c <= hi + grid.voxel_m)


def test_hull_bounds_drop_a_camera_inside_and_need_a_fallback_when_unbounded():
    cams = ring_cameras(8)
    sils = [sphere_silhouette(c) for c in cams]
    inner = _inner_camera(CENTRE)
    s_in = np.zeros((30, 40), bool)
    s_in[10:20, 10:20] = True
    lo, hi = hull_bounds(sils + [s_in], cams + [inner])
    lo0, hi0 = hull_bounds(sils, cams)
    np.testing.assert_allclose(lo, lo0, atol=1e-9)
    np.testing.assert_allclose(hi, hi0, atol=1e-9)
    # a single view whose silhouette fills the image: unbounded
    full = [np.ones((48, 64), bool)]
    with pytest.raises(InputError, match="unbounded"):
        hull_bounds(full, cams[:1])
    lo2, hi2 = hull_bounds(full, cams[:1], fallback=((-1, -1, -1), (1, 1, 1)))
    assert np.all(lo2 >= -1) and np.all(hi2 <= 1)


def test_silhouette_from_alpha_threshold_dilation_nan():
    a = np.zeros((21, 21), np.float32)
    a[10, 10] = 0.8
    a[0, 0] = np.nan
    s = silhouette_from_alpha(a, threshold=0.5)
    assert s.sum() == 1 and not s[0, 0]
    s2 = silhouette_from_alpha(a, threshold=0.5, dilate_px=2.3)  # rounds up to a radius-3 disc
    yy, xx = np.mgrid[0:21, 0:21]
    assert s2[10, 13] and s2[13, 10] and not s2[10, 14] and not s2[12, 13]
    assert not silhouette_from_alpha(a, threshold=0.85).any()
    with pytest.raises(InputError, match="threshold"):
        silhouette_from_alpha(a, threshold=1.0)


def test_distorted_camera_silhouette_is_resampled_conservatively():
    cams = ring_cameras(10, W=160, H=120, f=220.0)  # sphere radius ~18 px
    dist_cams = [dataclasses.replace(c, dist=(-0.15, 0.03, 0.001, -0.001, 0.0)) for c in cams]
    sils_d = []
    for c in dist_cams:  # silhouette as the distorted camera sees it
        uv = np.stack(np.meshgrid(np.arange(c.width), np.arange(c.height)), -1).reshape(-1, 2).astype(float)
        o, d = c.pixel_rays(uv)
        oc = o - CENTRE
        b = d @ oc
        sils_d.append((b * b - (oc @ oc - R * R) >= 0).reshape(c.height, c.width))
    pin = [undistort_silhouette(s, c) for s, c in zip(sils_d, dist_cams, strict=True)]
    grid = HullGrid.from_bounds(CENTRE - 0.07, CENTRE + 0.07, 32)
    occ = carve_octree([p[0] for p in pin], [p[1] for p in pin], grid)
    # reference: project every centre through the distorted cameras
    pts = grid.all_centres().reshape(-1, 3)
    keep = np.ones(len(pts), bool)
    for s, c in zip(sils_d, dist_cams, strict=True):
        uv, z = c.project(pts)
        px = np.floor(uv + 0.5)
        ok = (z > 0) & c.in_image(uv)
        carved = np.zeros_like(keep)
        idx = np.nonzero(ok)[0]
        carved[idx] = ~s[px[idx, 1].astype(int).clip(0, c.height - 1), px[idx, 0].astype(int).clip(0, c.width - 1)]
        keep &= ~carved
    keep = keep.reshape(grid.shape)
    assert np.all(occ[keep])  # conservative: never cuts what the distorted test keeps
    assert occ.sum() <= 1.3 * keep.sum()  # and only a little fatter (1 px dilation)
    with pytest.raises(InputError, match="distortion"):
        carve_octree(sils_d, dist_cams, grid)


def test_point_in_hull_matches_voxels(ring):
    cams, sils = ring
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), 20)
    occ = carve_octree(sils, cams, grid)
    np.testing.assert_array_equal(point_in_hull(grid.all_centres().reshape(-1, 3), sils, cams).reshape(grid.shape), occ)


def test_grid_validation():
    with pytest.raises(InputError):
        HullGrid.from_bounds((0, 0, 0), (0, 1, 1), 10)
    with pytest.raises(InputError):
        HullGrid((0, 0, 0), -1.0, (2, 2, 2))
    g = HullGrid.from_bounds((0, 0, 0), (2.0, 1.0, 0.5), 10)
    assert g.shape == (10, 5, 3) and g.voxel_m == pytest.approx(0.2)
    with pytest.raises(InputError, match="power of two"):
        carve_octree([np.ones((4, 4), bool)], ring_cameras(1, W=4, H=4), g, root_cell=6)


# --------------------------------------------------------------------------- robust carving


def _holed(sils, rng, holes=3, r_px=4):
    """Punch dark-shadow holes (discs) into the silhouettes, as thresholded real masks have."""
    out = []
    for s in sils:
        s = s.copy()
        ys, xs = np.nonzero(s)
        for _ in range(holes):
            i = rng.integers(len(ys))
            yy, xx = np.mgrid[: s.shape[0], : s.shape[1]]
            s[(yy - ys[i]) ** 2 + (xx - xs[i]) ** 2 <= r_px * r_px] = False
        out.append(s)
    return out


@pytest.mark.parametrize("tol", [1, 2])
@pytest.mark.parametrize("res,root", [(17, 4), (33, 8)])
def test_tolerant_octree_equals_dense_equals_reference(ring, tol, res, root):
    cams, sils = ring
    sils = _holed(sils, np.random.default_rng(res + tol))
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), res)
    ref = carve_reference(sils, cams, grid, tolerance=tol)
    np.testing.assert_array_equal(carve_dense(sils, cams, grid, tolerance=tol), ref)
    np.testing.assert_array_equal(carve_octree(sils, cams, grid, root_cell=root, tolerance=tol), ref)
    pts = grid.all_centres().reshape(-1, 3)
    np.testing.assert_array_equal(point_in_hull(pts, sils, cams, tolerance=tol).reshape(grid.shape), ref)
    # monotone: tolerating more rejections never removes a voxel
    assert np.all(ref >= carve_reference(sils, cams, grid, tolerance=tol - 1))


def test_tolerance_one_closes_a_shadow_tunnel(ring):
    """A hole in one view's mask tunnels through the classical hull; with tolerance 1
    the other views keep those voxels, and the hull returns to the unholed one inside."""
    cams, sils = ring
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), 40)
    clean = carve_octree(sils, cams, grid)
    bad = list(sils)
    bad[3] = _holed([sils[3]], np.random.default_rng(0), holes=4, r_px=5)[0]
    classical = carve_octree(bad, cams, grid)
    robust = carve_octree(bad, cams, grid, tolerance=1)
    lost = clean & ~classical
    assert lost.sum() > 50  # the holes did cut tunnels
    assert not np.any(clean & ~robust)  # tolerance 1 repairs all of them
    # and does not inflate the hull much: extra voxels only where a single view carved alone
    assert (robust & ~clean).sum() < 0.25 * clean.sum()
    from opacityhull.reconstruct.hull import view_rejections

    rej = view_rejections(grid.centres(np.argwhere(robust)), bad, cams)
    per_view = rej.sum(0)
    assert int(np.argmax(per_view)) == 3  # the holed view is the one that disagrees most


def test_tolerance_is_validated(ring):
    cams, sils = ring
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), 8)
    for bad in (-1, 1.5, len(cams)):
        with pytest.raises(InputError, match="tolerance"):
            carve_octree(sils, cams, grid, tolerance=bad)
