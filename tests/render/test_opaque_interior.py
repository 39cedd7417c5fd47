"""Interior opacity of the per-pixel shading (``RenderConfig.opaque_interior``): inside
the hull's projection α is what the views' mattes say once the carve's silhouette
dilation is allowed for, and the outline is left alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from opacityhull.camera import look_at_world_from_cam
from opacityhull.errors import InputError
from opacityhull.evaluate.loo import region_masks
from opacityhull.render.renderer import RenderConfig, dilated_matte_views, hull_interior, render_image
from opacityhull.render.synthetic import make_sphere_model
from opacityhull.render.views import prepare_views


def test_hull_interior_closes_seams_and_keeps_off_the_outline():
    cov = np.zeros((40, 50), np.float32)
    cov[5:35, 8:44] = 1.0
    cov[8:32, 20] = 0.2  # a 1-px sampling seam inside the projection
    cov[10:12, 30:32] = 0.0  # a pinhole
    winner = np.where(cov > 0, 7, -1)
    got = hull_interior(cov, winner, erode_px=2, close_px=2)
    # independent reference: the true projection (seam and pinhole closed) eroded by the
    # 5×5 digital disc
    full = np.zeros_like(got)
    full[5:35, 8:44] = True
    disc = np.array([[0, 0, 1, 0, 0], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1], [0, 0, 1, 0, 0]], bool)
    ref = ndimage.binary_erosion(full, structure=disc, border_value=0)
    assert np.array_equal(got, ref)
    assert got[8:32, 20].all() and got[10:12, 30:32].all()
    assert not hull_interior(cov, np.full_like(winner, -1)).any()  # no surfel: no interior


def test_dilated_matte_views_dilate_alpha_per_view():
    rng = np.random.default_rng(0)
    m = make_sphere_model(500, width=16, height=12, table_step_deg=120.0, elevations_deg=(20.0,))
    imgs = [v.copy() for v in m.views_premul()]
    for im in imgs:
        im[..., 3] = (rng.random(im.shape[:2]) > 0.97).astype(np.float32)
        im[6, 8, 3] = 0.5  # fractional (fur, glass): not dilated
    pv = prepare_views(m.cameras, imgs)
    d = dilated_matte_views(pv, 1)
    cross = ndimage.generate_binary_structure(2, 1)
    for v, im in enumerate(imgs):
        want = np.maximum(im[..., 3], ndimage.binary_dilation(im[..., 3] >= 0.99, structure=cross))
        got = d.image(v)
        assert np.array_equal(got[..., 3], want) and np.array_equal(got[..., 0], want)
        assert got[6, 8, 3] == 0.5 or want[6, 8] == 1.0
    assert dilated_matte_views(pv, 1) is d  # cached for the same views
    assert np.array_equal(dilated_matte_views(pv, 0).image(1)[..., 3], imgs[1][..., 3])


def test_dilated_matte_views_of_mapped_views_are_mapped_and_equal(tmp_path):
    """Memory-mapped views (the renderer's default) give the same dilated mattes, in a
    mapped file too, and the source's pages are handed back (RSS flat in the views)."""
    import mmap

    from opacityhull.model import OpacityHullModel, write_model
    from opacityhull.render.renderer import prepare_model_views

    rng = np.random.default_rng(1)
    m = make_sphere_model(500, width=40, height=30, table_step_deg=60.0, elevations_deg=(20.0,))
    imgs = [np.array(v, np.float32) for v in m.view_rgba]
    for im in imgs:
        im[..., 3] = np.where(rng.random(im.shape[:2]) > 0.9, 1.0, im[..., 3] * 0.5).astype(np.float32)
    write_model(tmp_path / "m", views=m.views, surfels=m.surfels, view_rgba=imgs, storage="float")
    model = OpacityHullModel.open(tmp_path / "m")
    mapped = prepare_model_views(model, mapped=True)
    held = prepare_model_views(model, mapped=False)
    assert isinstance(mapped.texels.base, mmap.mmap)
    a, b = dilated_matte_views(mapped, 1), dilated_matte_views(held, 1)
    assert isinstance(a.texels.base, mmap.mmap) and not isinstance(b.texels.base, mmap.mmap)
    assert np.array_equal(np.asarray(a.texels), b.texels)
    assert np.array_equal(np.asarray(mapped.texels), held.texels)  # the source is unchanged


@pytest.fixture(scope="module")
def cracked_sphere():
    """The analytic sphere whose every matte has a 1-px transparent crack (row 24) and a
    7×7 transparent hole: a crack is what the carve's 1-px silhouette dilation forgives,
    the hole is not."""
    m = make_sphere_model(8000, width=64, height=48)
    imgs = []
    for im in m.views_premul():
        im = im.copy()
        im[24, :, :] = 0.0
        im[10:17, 28:35, :] = 0.0
        imgs.append(im)
    cam = m.cameras[4].with_pose(look_at_world_from_cam((0.12, 0.32, 0.42), m.scene.centre))
    return m, prepare_views(m.cameras, imgs), cam


def _render(m, pv, cam, **kw):
    return render_image(m.surfels, m.cameras, pv, cam, config=RenderConfig(shading="pixel", align="none", **kw))


def test_interior_alpha_is_one_where_the_mattes_say_opaque(cracked_sphere):
    m, pv, cam = cracked_sphere
    truth = m.scene.render(cam)
    opaque = region_masks(truth[..., 3])["opaque"]
    off = _render(m, pv, cam, opaque_interior=False)
    on = _render(m, pv, cam)  # the default
    assert on.config.opaque_interior
    # the crack shows in the plain blend (measured: mean 0.913, 48 % of the opaque
    # pixels below 0.999, min 0)
    assert off.alpha[opaque].mean() < 0.95
    # with the views' mattes dilated by the tolerance it is gone (measured: mean 0.984,
    # 18 % below 0.999), except where the 7×7 holes, wider than the tolerance, project
    assert on.alpha[opaque].mean() > 0.975
    assert (on.alpha[opaque] < 0.999).mean() < 0.5 * (off.alpha[opaque] < 0.999).mean()
    # the colour where α was raised is the blend's straight colour, not darkened
    raised = opaque & (on.alpha > off.alpha + 0.05) & (off.alpha > 0.1)
    assert raised.sum() > 20
    assert np.allclose(on.rgba[raised, :3], off.rgba[raised, :3], atol=1e-5)


def test_opaque_interior_keeps_the_outline(cracked_sphere):
    m, pv, cam = cracked_sphere
    truth = m.scene.render(cam)
    off = _render(m, pv, cam, opaque_interior=False)
    on = _render(m, pv, cam)
    inner = hull_interior(on.coverage, np.where(on.coverage > 0, 0, -1))
    # outside the hull's interior nothing changes
    assert np.array_equal(on.rgba[~inner], off.rgba[~inner])
    # nothing is drawn outside the true silhouette dilated by 1 px
    assert not np.any(on.alpha[~ndimage.binary_dilation(truth[..., 3] > 0, iterations=1)] > 1e-3)
    a, b, c = truth[..., 3] > 0.5, on.alpha > 0.5, off.alpha > 0.5
    # measured IoU 0.924 with, 0.902 without (the crack cut the silhouette in two)
    assert (a & b).sum() / (a | b).sum() >= (a & c).sum() / (a | c).sum() + 0.01


def test_config_rejects_bad_interior_options():
    with pytest.raises(InputError, match="interior_px"):
        RenderConfig(interior_px=-1)
    with pytest.raises(InputError, match="matte_tolerance_px"):
        RenderConfig(matte_tolerance_px=1.5)  # type: ignore[arg-type]
