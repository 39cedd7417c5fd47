"""Pictures say what they show (#33): legends for the colours drawn on tiles, and the
command's warnings printed on the sheet they concern."""

from __future__ import annotations

import numpy as np

from opacityhull.pictures import WARNING_RGB, contact_sheet


def _has(img: np.ndarray, rgb) -> bool:
    return bool(np.any(np.all(img == np.asarray(rgb, np.uint8), axis=-1)))


def test_legend_and_notes_strips():
    tiles = [np.full((20, 30, 3), 90, np.uint8)] * 2
    plain = contact_sheet(tiles, background=40)
    legend = [((0, 255, 0), "silhouette"), ((255, 0, 0), "surfels")]
    both = contact_sheet(tiles, background=40, legend=legend, notes=["only 2 lights captured"])
    assert both.shape[1] == plain.shape[1] and both.shape[0] > plain.shape[0] + 20
    top = both[: both.shape[0] - plain.shape[0]]
    assert _has(both, (0, 255, 0)) and _has(both, (255, 0, 0)) and not _has(plain, (0, 255, 0))
    # warning text near the top, in the warning colour (anti-aliased: the exact colour at the strokes' cores)
    assert _has(top, WARNING_RGB)


def test_hull_overlay_has_a_legend(tmp_path):
    from opacityhull.imageio import read_png
    from opacityhull.reconstruct.pictures import HULL_OVERLAY_LEGEND, hull_overlays

    img = np.zeros((40, 60, 3), np.float32) + 0.3
    sil = np.zeros((40, 60), bool)
    sil[10:30, 20:40] = True
    sm = np.zeros_like(sil)
    sm[12:28, 22:38] = True
    p = hull_overlays([img], [sil], [sm], ["c0_t000.000"], tmp_path / "hull_overlay.png", thumb_h=40)
    sheet = np.round(read_png(p, linear=True) * 255).astype(np.uint8)
    bottom = sheet[40 + 2 * 2 :]  # below the one row of 40-px tiles and its gaps
    for colour, text in HULL_OVERLAY_LEGEND:
        assert _has(bottom, colour), text  # each outline colour has its swatch under the tiles
    assert "silhouette" in HULL_OVERLAY_LEGEND[0][1] and "surfels" in HULL_OVERLAY_LEGEND[1][1]


def test_eval_relight_sheet_carries_the_few_lights_warning(tmp_path):
    from opacityhull.imageio import read_png
    from opacityhull.relight.envmap import default_yaw_deg, load_envmap
    from opacityhull.evaluate.relight import eval_relight
    from opacityhull.relight.synthetic import write_sphere_model

    root = write_sphere_model(
        tmp_path / "m", width=24, height=20, n_lights=1, n_positions=2, table_degs=(0.0, 180.0), n_surfels=800
    )
    env = load_envmap("builtin:grace", yaw_deg=default_yaw_deg("builtin:grace"))
    s = eval_relight(root, envmap=env, out=tmp_path / "e")
    assert s["n_lights_captured"] == 2 and "only 2 captured light direction(s)" in s["warnings"][0]
    sheet = np.round(read_png(s["sheet"], linear=True) * 255).astype(np.uint8)
    assert _has(sheet[:40], WARNING_RGB)  # on the picture, above the tiles
