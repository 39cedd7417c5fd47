"""Ground-truth metrics: mesh voxelisation (numba vs NumPy reference vs analytic), IoU,
alpha MAE in the dilated object region."""

from __future__ import annotations

import numpy as np
import pytest

import rcsynth
from opacityhull.errors import FormatError, ShapeError
from opacityhull.reconstruct.hull import HullGrid
from opacityhull.reconstruct.metrics import (
    alpha_mae,
    hull_iou,
    object_region,
    read_mesh_ply,
    voxelize_mesh,
    voxelize_mesh_reference,
)


def two_overlapping_spheres():
    V1, F1 = rcsynth.uv_sphere(np.array([0.0, 0.05, 0.0]), 0.04, seg=32, rings=16)
    V2, F2 = rcsynth.uv_sphere(np.array([0.03, 0.05, 0.01]), 0.025, seg=24, rings=12)
    return np.concatenate([V1, V2]), np.concatenate([F1, F2 + len(V1)])


def test_voxelize_numba_matches_reference_and_is_the_union():
    V, F = two_overlapping_spheres()
    grid = HullGrid.from_bounds(V.min(0) - 0.005, V.max(0) + 0.005, 30)
    fast = voxelize_mesh(V, F, grid)
    ref = voxelize_mesh_reference(V, F, grid)
    np.testing.assert_array_equal(fast, ref)
    c = grid.all_centres()
    # analytic union of the two spheres, away from the facetted surface (1 voxel band)
    d1 = np.linalg.norm(c - [0.0, 0.05, 0.0], axis=-1) - 0.04
    d2 = np.linalg.norm(c - [0.03, 0.05, 0.01], axis=-1) - 0.025
    d = np.minimum(d1, d2)
    clear = np.abs(d) > grid.voxel_m
    np.testing.assert_array_equal(fast[clear], (d < 0)[clear])  # union, not XOR (parity)


def test_voxelize_flipped_orientation_and_empty_mesh():
    V, F = rcsynth.uv_sphere(np.zeros(3), 0.05, seg=24, rings=12)
    grid = HullGrid.from_bounds((-0.06,) * 3, (0.06,) * 3, 20)
    a = voxelize_mesh(V, F, grid)
    b = voxelize_mesh(V, F[:, ::-1], grid)  # inward-facing: winding -1 inside, still != 0
    np.testing.assert_array_equal(a, b)
    assert not voxelize_mesh(V, np.zeros((0, 3), np.int64), grid).any()
    with pytest.raises(ShapeError):
        voxelize_mesh(V[:, :2], F, grid)


def test_read_mesh_ply_roundtrip_and_errors(tmp_path):
    V, F = rcsynth.uv_sphere(np.zeros(3), 0.05, seg=12, rings=6)
    rcsynth.write_ply(tmp_path / "m.ply", V, F)
    V2, F2 = read_mesh_ply(tmp_path / "m.ply")
    np.testing.assert_allclose(V2, V, atol=1e-7)
    np.testing.assert_array_equal(F2, F)
    with pytest.raises(FormatError, match="not found"):
        read_mesh_ply(tmp_path / "nope.ply")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat garbage\n")
    with pytest.raises(FormatError, match="bad.ply"):
        read_mesh_ply(tmp_path / "bad.ply")


def test_hull_iou_values():
    a = np.zeros((4, 4, 4), bool)
    b = np.zeros((4, 4, 4), bool)
    a[:2] = True
    b[1:3] = True
    r = hull_iou(a, b)
    assert r["iou"] == pytest.approx(1 / 3)
    assert r["object_in_hull"] == pytest.approx(0.5)
    with pytest.raises(ShapeError):
        hull_iou(a, b[:3])


def test_alpha_mae_region_and_fractional():
    t = np.zeros((40, 40), np.float32)
    t[10:20, 10:20] = 1.0
    t[20:22, 10:20] = 0.5
    a = t.copy()
    a[15, 15] = 0.8  # error 0.2 inside
    a[0, 0] = 1.0  # far background: outside the dilated region, not counted
    region = object_region(t, dilate_px=3)
    assert region[9, 9] and region[24, 15] and not region[0, 0] and not region[30, 30]
    r = alpha_mae(a, t, dilate_px=3)
    assert r["mae"] == pytest.approx(0.2 / region.sum())
    assert r["fractional_pixels"] == 20 and r["fractional_recovered"] == 1.0 and r["mae_fractional"] == 0.0
    binary = np.where(t > 0.4, 1.0, 0.0)
    assert alpha_mae(binary, t)["fractional_recovered"] == 0.0  # a binary mask is caught
