"""Bright extensions (hull.bright_extensions, build.bright_extension_masks): thick bright
parts just outside an imported mask's outline — a shadowed part that sticks out past it,
which the threshold lost — are doubted by a tolerant carve like shadow holes, while the
thin glow around every outline is not. Checked against a SciPy twin, on synthetic
outlines, through the carve, in the report and the geometry holdout's file, and that
rig sessions never use the rule."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from opacityhull.errors import ConfigError, InputError, ShapeError
from opacityhull.reconstruct.build import (
    BuildConfig,
    _extensions_apply,
    bright_extension_masks,
    default_carve_tolerance,
    default_dilate_base_px,
)
from opacityhull.reconstruct.hull import HullGrid, bright_extensions, carve_octree, carve_robust, enclosed_holes

REAL = Path(__file__).resolve().parents[1] / "data" / "real"


def _disc(r: int) -> np.ndarray:
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    # OpenCV's MORPH_ELLIPSE of size 2r+1 for the radii used here (checked below)
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)).astype(bool) | (yy == 0) & (xx == 0)


def _twin(sil, lum, *, reach_px, open_px=3, margin=0.2, ring_px=15, median_px=5):
    """The same rule with SciPy's morphology: dilation for the reach and the ring,
    components by label, opening by erosion then dilation."""
    filled = ndimage.binary_fill_holes(sil)
    reach = ndimage.binary_dilation(filled, structure=_disc(reach_px))
    ring = ndimage.binary_dilation(reach, structure=np.ones((2 * ring_px + 1,) * 2, bool)) & ~reach
    if not ring.any():  # the object fills the frame: no backdrop to judge by
        return np.zeros_like(sil)
    bg, fg = np.median(lum[ring]), np.median(lum[sil])
    sm = ndimage.median_filter(lum, size=median_px, mode="nearest")
    cand = (sm > bg + margin * max(fg - bg, 0.0)) & reach & ~filled
    lab, _ = ndimage.label(cand | filled, structure=np.ones((3, 3), bool))
    grown = np.isin(lab, np.unique(lab[filled])) & cand  # filled pixels are never label 0
    opened = ndimage.binary_opening(grown, structure=_disc(open_px), border_value=0)
    return opened & ~filled


def _outline(H=80, W=100, *, plate=True, glow=True, seed=0):
    """A bright disc object on a dark backdrop, a 2-px glow band around it, and a
    shadowed plate (mid-grey, 9 px thick) that the mask lost at the top."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W]
    obj = (yy - 45) ** 2 + (xx - 50) ** 2 <= 22**2
    lum = 0.02 + 0.01 * rng.random((H, W))
    lum[obj] = 0.8
    plate_m = (np.abs(xx - 50) <= 4) & (yy >= 12) & (yy < 24)
    if glow:
        band = ndimage.binary_dilation(obj, iterations=2) & ~obj
        lum[band] = 0.4
    if plate:
        lum[plate_m] = 0.3
    return obj, lum.astype(np.float32), plate_m & ~obj


def test_a_thick_shadowed_plate_is_doubted_the_glow_band_is_not():
    sil, lum, plate = _outline()
    got = bright_extensions(sil, lum, reach_px=15)
    assert got[plate].mean() > 0.7  # the plate, minus the opening's rounded corners
    glow = ndimage.binary_dilation(sil, iterations=2) & ~sil & ~ndimage.binary_dilation(plate, iterations=4)
    assert not (got & glow).any()  # 2 px of glow: thinner than the 3-px opening
    assert not (got & sil).any()
    # nothing to find without the plate; nothing beyond the reach
    assert not bright_extensions(*_outline(plate=False)[:2], reach_px=15).any()
    assert not bright_extensions(sil, lum, reach_px=5)[:15].any()
    # a plate as dark as the backdrop is backdrop
    dark = lum.copy()
    dark[plate] = 0.03
    assert not bright_extensions(sil, dark, reach_px=15).any()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_equals_the_scipy_twin_on_random_blobs(seed):
    """A random object in the middle of the frame, random bright patches around it (some
    touching it, some thick, some thin) on a noisy dark backdrop."""
    rng = np.random.default_rng(seed)
    H, W = 90, 120
    yy, xx = np.mgrid[:H, :W]
    centre = ((yy - 45) / 25.0) ** 2 + ((xx - 60) / 30.0) ** 2 <= 1.0
    blob = (ndimage.gaussian_filter(rng.random((H, W)), 3) > 0.47) & centre
    patches = ndimage.gaussian_filter(rng.random((H, W)), 2) > 0.55
    lum = (0.03 + 0.02 * rng.random((H, W))).astype(np.float32)
    lum[patches] = 0.35
    lum[blob] = 0.8 + 0.1 * rng.random(int(blob.sum()))
    found = 0
    for reach, op, margin in ((9, 3, 0.2), (12, 2, 0.1), (6, 1, 0.3)):
        got = bright_extensions(blob, lum, reach_px=reach, open_px=op, margin=margin)
        np.testing.assert_array_equal(got, _twin(blob, lum, reach_px=reach, open_px=op, margin=margin))
        found += int(got.sum())
    assert found > 0


def test_nan_and_checks():
    sil, lum, plate = _outline()
    nan = lum.copy()
    nan[plate] = np.nan
    assert not bright_extensions(sil, nan, reach_px=15)[plate].any()  # unknown is never bright
    assert not bright_extensions(sil, lum, reach_px=0).any()
    assert not bright_extensions(np.zeros_like(sil), lum, reach_px=15).any()
    with pytest.raises(InputError, match="must match"):
        bright_extensions(sil, lum[:-1], reach_px=15)
    with pytest.raises(ShapeError, match=r"expected \(H, W\)"):
        bright_extensions(sil[None], lum[None], reach_px=15)
    with pytest.raises(InputError, match="median_px 4 odd"):
        bright_extensions(sil, lum, reach_px=15, median_px=4)
    with pytest.raises(InputError, match="reach_frac"):
        bright_extension_masks(sil.astype(np.float32), np.repeat(lum[..., None], 3, 2), reach_frac=-1.0)


def test_masks_read_linear_rgb_and_size_the_reach_by_the_object():
    sil, lum, _ = _outline()
    rgb = np.repeat((lum**2.2)[..., None], 3, axis=2)  # linear, as the build loads photographs
    r = int(np.ceil(0.2 * np.sqrt(enclosed_holes(sil).sum())))
    np.testing.assert_array_equal(
        bright_extension_masks(sil.astype(np.float32), rgb, reach_frac=0.2),
        bright_extensions(sil, lum, reach_px=r),
    )


def test_a_doubted_protrusion_needs_the_tolerant_count_to_carve():
    """One view's mask loses a part at its outline: trusted, that view alone carves it
    off the hull; doubted, only a second rejection does."""
    from test_rc_hull import ring_cameras, scene_silhouettes

    cams = ring_cameras(10, W=160, H=120, f=175.0, seed=3)
    sils = scene_silhouettes(cams)
    ys, xs = np.nonzero(sils[3])
    lost = np.zeros_like(sils[3])
    lost[: int(ys.mean()) - 5, int(xs.mean()) - 4 : int(xs.mean()) + 5] = True
    lost &= sils[3]
    sils[3] = sils[3] & ~lost
    assert lost.sum() > 60
    grid = HullGrid.from_bounds((-0.07, -0.01, -0.07), (0.1, 0.11, 0.07), 32)
    trusted, _ = carve_robust(sils, cams, grid, tolerance=1)
    strong = [enclosed_holes(s) | (lost if i == 3 else False) for i, s in enumerate(sils)]
    doubted, _ = carve_robust(sils, cams, grid, tolerance=1, strong_silhouettes=strong)
    assert doubted.sum() > trusted.sum() and np.all(doubted >= trusted)
    restored = [s | (lost if i == 3 else False) for i, s in enumerate(sils)]
    np.testing.assert_array_equal(
        doubted, carve_robust(restored, cams, grid, tolerance=1)[0] & carve_octree(sils, cams, grid, tolerance=1)
    )


def test_rule_applies_only_to_tolerant_carves_of_imported_masks():
    on = BuildConfig()
    assert on.doubt_bright_extensions and _extensions_apply(on, True, True)
    assert not _extensions_apply(on, False, True)  # rig default: tolerance 0
    assert not _extensions_apply(on, True, False)  # triangulation mattes
    assert not _extensions_apply(BuildConfig(doubt_bright_extensions=False), True, True)


def test_default_carve_tolerance_grows_with_the_imported_views():
    """One rule for the carve, the hole filling and the bright extensions (they used to
    disagree under 8 views: the carve was classical while holes were filled)."""
    cfg = BuildConfig()
    got = [default_carve_tolerance(cfg, rig_session=False, n_views=v) for v in (1, 7, 8, 15, 16, 100)]
    assert got == [0, 0, 1, 1, 2, 2]
    assert default_carve_tolerance(cfg, rig_session=True, n_views=400) == 0  # triangulation mattes
    for tol in (0, 3):  # an explicit tolerance wins either way
        assert default_carve_tolerance(BuildConfig(carve_tolerance=tol), rig_session=True, n_views=4) == tol
        assert default_carve_tolerance(BuildConfig(carve_tolerance=tol), rig_session=False, n_views=50) == tol


def test_imported_masks_are_not_dilated_by_default():
    """Half a pixel (one, rounded up) for a rig's mattes thresholded at ½; none for the
    masks of other tools, whose threshold already reaches past the edge."""
    cfg = BuildConfig()
    assert cfg.dilate_base_px is None
    assert default_dilate_base_px(cfg, rig_session=True) == 0.5
    assert default_dilate_base_px(cfg, rig_session=False) == 0.0
    for d in (0.0, 1.5):  # an explicit value wins either way
        for rig in (True, False):
            assert default_dilate_base_px(BuildConfig(dilate_base_px=d), rig_session=rig) == d
    with pytest.raises(ConfigError, match="dilate_base_px"):
        BuildConfig(dilate_base_px=-0.5)


def test_rig_sessions_never_use_the_rule(tmp_path):
    from opacityhull.acquire.synthetic import SyntheticSessionConfig, write_synthetic_session
    from opacityhull.model import BRIGHT_EXTENSIONS, read_surfels_ply
    from opacityhull.reconstruct.build import build_model

    s = tmp_path / "s"
    write_synthetic_session(
        s, SyntheticSessionConfig(n_table=2, width_px=40, height_px=30, groundtruth=False, threads=1)
    )
    cfg = BuildConfig(pictures=False, reflectance=False, natural=False, optimize="none")  # the hull alone
    on = build_model(s, tmp_path / "on", config=cfg)
    build_model(s, tmp_path / "off", config=replace(cfg, doubt_bright_extensions=False))
    assert on.hull["carve_tolerance"] == 0 and on.hull["bright_extensions"] == {"views": 0, "px": 0}
    assert not (tmp_path / "on" / "build" / BRIGHT_EXTENSIONS).exists()
    a, b = read_surfels_ply(tmp_path / "on" / "surfels.ply"), read_surfels_ply(tmp_path / "off" / "surfels.ply")
    np.testing.assert_array_equal(a.positions, b.positions)


def test_imported_build_records_what_it_doubted_and_the_holdout_reads_it(tmp_path):
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.model import BRIGHT_EXTENSIONS, read_hole_masks
    from opacityhull.reconstruct.build import build_model

    src = REAL / "dinoSR"
    import_colmap(src / "sparse", src / "images", tmp_path / "s", masks_dir=src / "masks")
    # the hull's carving alone: no fit (the default --optimize fast took ~140 s of this test)
    cfg = BuildConfig(hull_res=48, refine="none", pictures=False, reflectance=False, natural=False, optimize="none")
    on = build_model(tmp_path / "s", tmp_path / "on", config=cfg)
    ext = read_hole_masks(tmp_path / "on" / "build" / BRIGHT_EXTENSIONS)
    assert on.hull["carve_tolerance"] == 2 and len(ext) == 16  # 16 imported views
    assert 0 < on.hull["bright_extensions"]["px"] <= sum(int(m.sum()) for m in ext.values())
    assert on.hull["bright_extensions"]["views"] >= 5  # measured 9 of 16 at full resolution
    off = build_model(tmp_path / "s", tmp_path / "off", config=replace(cfg, doubt_bright_extensions=False))
    assert off.hull["bright_extensions"] == {"views": 0, "px": 0}
    assert not (tmp_path / "off" / "build" / BRIGHT_EXTENSIONS).exists()
    assert on.hull["occupied_voxels"] > off.hull["occupied_voxels"]
