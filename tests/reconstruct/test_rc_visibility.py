"""The visibility kernel against its NumPy twin beyond the default options: the
z-buffers themselves, and every option reaching both (they share one signature)."""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.reconstruct.visibility import surfel_visibility, surfel_visibility_reference

from test_rc_hull import CENTRE, R, ring_cameras


@pytest.fixture(scope="module")
def sphere_surfels():
    rng = np.random.default_rng(4)
    d = rng.normal(size=(1500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pos = CENTRE + R * d
    rad = rng.uniform(0.003, 0.006, size=len(pos))
    cams = ring_cameras(5, W=48, H=40, f=60.0, el_deg=(-10.0, 30.0))
    cams[2] = ring_cameras(5, W=40, H=32, f=50.0)[2]  # views of different sizes: padded z-buffers
    return pos, d, rad, cams


@pytest.mark.parametrize(
    "options",
    [{}, {"depth_tol_m": 0.0}, {"depth_tol_m": 0.01, "slope_px": 0.0}, {"facing_cos": 0.3, "slope_px": 3.0}],
)
def test_reference_twin_matches_kernel_with_depths(sphere_surfels, options):
    pos, nrm, rad, cams = sphere_surfels
    vis, zb = surfel_visibility(pos, nrm, rad, cams, return_depth=True, **options)
    vis_r, zb_r = surfel_visibility_reference(pos, nrm, rad, cams, return_depth=True, **options)
    np.testing.assert_array_equal(vis, vis_r)
    assert zb.shape == zb_r.shape == (len(cams), 40, 48)
    np.testing.assert_array_equal(np.isinf(zb), np.isinf(zb_r))
    fin = np.isfinite(zb)
    np.testing.assert_allclose(zb[fin], zb_r[fin], rtol=1e-12)
    assert np.isinf(zb[2, 32:]).all() and np.isinf(zb[2, :, 40:]).all()  # padding of the smaller view
    assert 0.2 < vis.mean() < 0.6


def test_reference_twin_without_surfels_or_views(sphere_surfels):
    pos, nrm, rad, cams = sphere_surfels
    assert surfel_visibility_reference(pos[:0], nrm[:0], rad[:0], cams).shape == (0, len(cams))
    assert surfel_visibility_reference(pos, nrm, rad, []).shape == (len(pos), 0)
