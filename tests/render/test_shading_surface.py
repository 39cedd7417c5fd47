"""Shading on the photo-consistent surface (``Surfels.depth_m``, ``RenderConfig.shading_surface``):
surfels on an inflated "hull" around the analytic sphere, with the true surface δ inside.
The colour must come from the true surface while coverage stays the hull's."""

from __future__ import annotations

import math

import numpy as np
import pytest
from plyfile import PlyData
from scipy import ndimage

from opacityhull.camera import look_at_world_from_cam
from opacityhull.errors import ConfigError, FormatError, InputError, ShapeError
from opacityhull.model import Surfels, read_surfels_ply, write_surfels_ply
from opacityhull.render.renderer import RenderConfig, render_image
from opacityhull.render.synthetic import make_sphere_model
from opacityhull.render.views import prepare_views

DELTA_REL = 0.15  # the hull lies 15 % of the radius outside the sphere


@pytest.fixture(scope="module")
def inflated():
    m = make_sphere_model(8000, width=64, height=48, table_step_deg=45.0)
    pv = prepare_views(m.cameras, m.views_premul())
    s = m.surfels
    c = np.asarray(m.scene.centre, np.float32)
    d = DELTA_REL * m.scene.radius
    n = (s.positions - c) / np.linalg.norm(s.positions - c, axis=1, keepdims=True)
    hull = Surfels(
        c + n * (m.scene.radius + d),
        n,
        s.radii * (1 + DELTA_REL),
        s.visibility,
        s.n_views,
        np.full(len(s), d, np.float32),
    )
    return m, pv, hull, d


def _novel(m):
    return m.cameras[3].with_pose(look_at_world_from_cam((0.2, 0.3, 0.38), m.scene.centre))


def _psnr(a, b, sel):
    mse = float(np.mean((a[sel][..., :3] - b[sel][..., :3]) ** 2))
    return 10 * math.log10(1 / mse)


def test_refined_surface_fetches_the_true_colours(inflated):
    m, pv, hull, _ = inflated
    cam = _novel(m)
    truth = m.scene.render(cam)
    inside = ndimage.binary_erosion(truth[..., 3] >= 0.999, iterations=2)
    ref = render_image(hull, m.cameras, pv, cam, config=RenderConfig(shading_surface="refined"))
    on_hull = render_image(hull, m.cameras, pv, cam, config=RenderConfig(shading_surface="hull"))
    assert ref.stats["shading_surface"] == "refined" and on_hull.stats["shading_surface"] == "hull"
    p_ref, p_hull = _psnr(ref.rgba, truth, inside), _psnr(on_hull.rgba, truth, inside)
    # measured 30.7 vs 23.9 dB (surfels on the true sphere: 30.7 dB): colours fetched 15 %
    # of a radius off the surface ghost
    assert p_ref > p_hull + 4.0, (p_ref, p_hull)
    assert p_ref > 28.0
    # coverage is the hull's in both: the same pixels are drawn
    assert np.array_equal(ref.coverage, on_hull.coverage)


def test_shading_depth_lies_behind_the_hull_by_delta_along_the_axis(inflated):
    m, pv, hull, d = inflated
    cam = _novel(m)
    a = render_image(hull, m.cameras, pv, cam, config=RenderConfig(shading_surface="hull"))
    # the displaced surfels alone, drawn as geometry: the sphere's own depth
    true = render_image(
        Surfels(hull.shading_positions(), hull.normals, hull.radii, hull.visibility, hull.n_views),
        m.cameras,
        pv,
        cam,
        config=RenderConfig(),
    )
    cx, cy = int(round(cam.K[0, 2])), int(round(cam.K[1, 2]))
    # on the optical axis through the centre the ray meets both spheres head on
    assert true.depth[cy, cx] - a.depth[cy, cx] == pytest.approx(d, rel=0.1)


def test_zero_depth_renders_exactly_the_hull(inflated):
    m, pv, hull, _ = inflated
    cam = _novel(m)
    zero = Surfels(
        hull.positions, hull.normals, hull.radii, hull.visibility, hull.n_views, np.zeros(len(hull), np.float32)
    )
    none = Surfels(hull.positions, hull.normals, hull.radii, hull.visibility, hull.n_views)
    a = render_image(zero, m.cameras, pv, cam, config=RenderConfig())
    b = render_image(none, m.cameras, pv, cam, config=RenderConfig())
    assert np.array_equal(a.rgba, b.rgba)
    assert a.stats["shading_surface"] == "refined" and b.stats["shading_surface"] == "hull"


def test_surfel_shading_ignores_depth(inflated):
    m, pv, hull, _ = inflated
    cam = _novel(m)
    none = Surfels(hull.positions, hull.normals, hull.radii, hull.visibility, hull.n_views)
    a = render_image(hull, m.cameras, pv, cam, config=RenderConfig(shading="surfel"))
    b = render_image(none, m.cameras, pv, cam, config=RenderConfig(shading="surfel"))
    assert np.array_equal(a.rgba, b.rgba)


def test_depth_round_trips_through_the_ply(tmp_path, inflated):
    _, _, hull, d = inflated
    p = tmp_path / "surfels.ply"
    write_surfels_ply(p, hull.subset(np.arange(100)))
    ply = PlyData.read(str(p))
    assert "depth" in ply["vertex"].data.dtype.names
    np.testing.assert_array_equal(ply["vertex"]["depth"], np.full(100, d, np.float32))
    back = read_surfels_ply(p)
    assert back.depth_m is not None and np.array_equal(back.depth_m, hull.depth_m[:100])
    # a PLY without the property is a hull-only model
    write_surfels_ply(
        p, Surfels(hull.positions[:5], hull.normals[:5], hull.radii[:5], hull.visibility[:5], hull.n_views)
    )
    assert read_surfels_ply(p).depth_m is None


def test_bad_depths_are_named(tmp_path, inflated):
    _, _, hull, _ = inflated
    s = hull.subset(np.arange(10))
    with pytest.raises(ShapeError, match="depth_m"):
        Surfels(s.positions, s.normals, s.radii, s.visibility, s.n_views, np.full(10, -1.0))
    with pytest.raises(ShapeError, match="depth_m"):
        Surfels(s.positions, s.normals, s.radii, s.visibility, s.n_views, np.full(9, 0.0))
    good, bad = tmp_path / "good.ply", tmp_path / "bad.ply"
    write_surfels_ply(good, s)
    ply = PlyData.read(str(good), mmap=False)
    data = ply["vertex"].data.copy()
    data["depth"][3] = np.nan
    ply["vertex"].data = data
    ply.write(str(bad))
    with pytest.raises(FormatError, match="depth"):
        read_surfels_ply(bad)


def test_config_values():
    from opacityhull.reconstruct.build import BuildConfig

    with pytest.raises(InputError, match="shading_surface"):
        RenderConfig(shading_surface="mesh")
    assert BuildConfig().refine == "shading"
    assert BuildConfig(refine=True).refine == "surfels" and BuildConfig(refine=False).refine == "none"
    with pytest.raises(ConfigError, match="refine"):
        BuildConfig(refine="deep")
