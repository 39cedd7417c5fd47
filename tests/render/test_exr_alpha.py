"""One EXR convention (#33): every RGBA EXR the renderer and the model write holds
premultiplied colour and says so in its header; compositing the file as a compositor
does (OpenEXR, ``RGB + (1 - A) B``) gives the PNG of the same render."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from exrkit import over_premultiplied, read_rgba_openexr, srgb8
from opacityhull.cli import app
from opacityhull.imageio import ALPHA_CUTOFF, read_png, straight_from_premul

BG = np.array([0.2, 0.5, 0.8], np.float32)


def test_render_exr_composites_like_its_png(sphere_dir, tmp_path):
    root, _ = sphere_dir
    for name in ("v.exr", "v.png"):
        r = CliRunner().invoke(app, ["render", str(root), "--out", str(tmp_path / name), "--view", "1,30"])
        assert r.exit_code == 0, r.output
    png = read_png(tmp_path / "v.png")  # straight sRGB RGBA
    a = png[..., 3:4]
    want = png[..., :3] * a + (1.0 - a) * BG
    got = over_premultiplied(tmp_path / "v.exr", BG)
    # the PNG's 8-bit colour and alpha: at most a code or two apart in sRGB
    assert np.abs(srgb8(got) - srgb8(want)).max() <= 2
    rgba, _ = read_rgba_openexr(tmp_path / "v.exr")
    edge = (rgba[..., 3] > 0.05) & (rgba[..., 3] < 0.95)
    assert edge.any()  # the test sees partial coverage, where straight and premultiplied differ
    assert np.all(rgba[..., :3] <= rgba[..., 3:4] + 1e-6)  # premultiplied: colour ≤ alpha for albedo ≤ 1


def test_orbit_exr_frames_say_premultiplied(sphere_dir, tmp_path):
    root, _ = sphere_dir
    r = CliRunner().invoke(app, ["render", str(root), "--out", str(tmp_path / "o.exr"), "--orbit", "2"])
    assert r.exit_code == 0, r.output
    for k in range(2):
        _, header = read_rgba_openexr(tmp_path / f"o_{k:03d}.exr")
        assert header["opacityhull:alpha"] == "premultiplied"


def test_model_views_are_premultiplied_and_say_so(sphere_dir):
    root, m = sphere_dir
    for i, v in enumerate(m.views[:6]):
        straight = np.asarray(m.view_rgba[i], np.float32)
        want = straight[..., :3] * straight[..., 3:4] + (1.0 - straight[..., 3:4]) * BG
        np.testing.assert_allclose(over_premultiplied(root / "views" / f"{v.id}.exr", BG), want, atol=1e-5)


def test_one_straight_from_premultiplied_with_one_cutoff():
    rgba = np.array([[[0.5, 0.25, 0.0, 0.5], [1e-5, 1e-5, 1e-5, 1e-4], [0.3, 0.3, 0.3, 1.2], [1, 1, 1, 0]]], np.float32)
    s = straight_from_premul(rgba)
    np.testing.assert_allclose(s[0, 0], [1.0, 0.5, 0.0, 0.5])
    assert 1e-4 < ALPHA_CUTOFF and np.all(s[0, 1, :3] == 0)  # below the cut-off: no colour
    np.testing.assert_allclose(s[0, 2], [0.3, 0.3, 0.3, 1.0])  # alpha clipped to 1
    assert np.all(s[0, 3, :3] == 0)
    # the renderer, the relighter and the model reader use this one function
    import inspect

    from opacityhull.model import OpacityHullModel
    from opacityhull.relight import runner as relight_runner
    from opacityhull.render import renderer

    assert renderer.straight_from_premul is straight_from_premul and renderer.ALPHA_MIN == ALPHA_CUTOFF
    assert "straight_from_premul" in inspect.getsource(OpacityHullModel.load_view_rgba)
    assert relight_runner.straight_from_premul is straight_from_premul
