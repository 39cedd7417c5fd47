"""``render`` of a model built with ``--optimize`` (#29 item 4): the fitted splats draw
by default (``--renderer auto|fitted|ulr``, as ``eval test``), through the fitting's own
forward pass, into the same outputs as the ULR renderer (EXR premultiplied and saying
so, PNG, ``--background``, orbits with their GIF, ``--scheduler``); options of the ULR
renderer and ``--renderer fitted`` on an unfitted model are bad input (exit 2, nothing
written)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

import fitted
from exrkit import over_premultiplied, read_rgba_openexr, srgb8
from opacityhull.cli import app
from opacityhull.imageio import read_png
from opacityhull.model import OpacityHullModel
from opacityhull.optimize.fit import load_fitted, render_params


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "4000"})


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return fitted.sphere(tmp_path_factory)


def _premul(rgba):
    out = rgba.copy()
    out[..., :3] *= out[..., 3:4]
    return out


def test_view_exr_is_the_fitted_forward_pass_premultiplied(model, tmp_path):
    r = run("render", model, "--view", "1,45", "--out", tmp_path / "v.exr", "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["renderer"] == "fitted" and s["surfels"] == len(load_fitted(model)["means"])
    m = OpacityHullModel.open(model)
    cam = next(v.camera for v in m.views if v.camera_index == 1 and abs(v.table_deg - 45) < 1e-9)
    want = render_params(load_fitted(model), cam)  # the fitting's own picture of that camera
    assert want[..., 3].max() > 0.9 and (want[..., 3] == 0).any()
    got, header = read_rgba_openexr(tmp_path / "v.exr")
    assert header["opacityhull:alpha"] == "premultiplied"
    np.testing.assert_allclose(got, _premul(want), rtol=0, atol=1e-6)


def test_png_and_background_composite_like_the_exr(model, tmp_path):
    for name, extra in (("v.png", ()), ("w.png", ("--background", "white")), ("v.exr", ())):
        r = run("render", model, "--view", "2,90", "--out", tmp_path / name, *extra)
        assert r.exit_code == 0, r.output
    png = read_png(tmp_path / "v.png")  # straight sRGB RGBA
    a = png[..., 3:4]
    bg = np.array([0.2, 0.5, 0.8], np.float32)
    exr = over_premultiplied(tmp_path / "v.exr", bg)
    assert np.abs(srgb8(png[..., :3] * a + (1 - a) * bg) - srgb8(exr)).max() <= 2
    white = read_png(tmp_path / "w.png")
    assert white.shape[2] == 3 and np.abs(srgb8(white) - srgb8(over_premultiplied(tmp_path / "v.exr", 1.0))).max() <= 1


def test_renderer_ulr_still_renders_the_hull(model, tmp_path):
    from opacityhull.render.renderer import render_model

    r = run("render", model, "--view", "1,45", "--out", tmp_path / "u.exr", "--renderer", "ulr", "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["renderer"] == "ulr"
    m = OpacityHullModel.open(model)
    cam = next(v.camera for v in m.views if v.camera_index == 1 and abs(v.table_deg - 45) < 1e-9)
    got, _ = read_rgba_openexr(tmp_path / "u.exr")
    np.testing.assert_allclose(got, render_model(m, cam).premul, atol=1e-6)


def test_orbit_with_threads_writes_the_serial_frames(model, tmp_path):
    outs = {}
    for sched in ("serial", "threads"):
        d = tmp_path / sched
        r = run("render", model, "--orbit", "3", "--out", d / "o.png", "--scheduler", sched, "--json")
        assert r.exit_code == 0, r.output
        s = json.loads(r.stdout)
        assert s["renderer"] == "fitted" and s["frames"] == 3 and (d / "o.gif").is_file()
        outs[sched] = [(d / f"o_{i:03d}.png").read_bytes() for i in range(3)]
    assert outs["serial"] == outs["threads"]


def test_bad_renderer_input_exits_2_and_writes_nothing(model, tmp_path):
    plain = tmp_path / "plain"
    shutil.copytree(model, plain)
    shutil.rmtree(plain / "optimized")
    stale = tmp_path / "stale"
    shutil.copytree(model, stale)
    fit = json.loads((stale / "optimized" / "fit.json").read_text())
    (stale / "optimized" / "fit.json").write_text(json.dumps({**fit, "model": "0" * 64}))
    cases = [
        ((plain, "--renderer", "fitted"), ("--renderer fitted", "are missing", "--optimize")),
        ((stale, "--renderer", "fitted"), ("--renderer fitted", "earlier build", "--optimize")),
        ((model, "--renderer", "nerf"), ("--renderer 'nerf'", "auto, fitted, ulr")),
        ((model, "--budget", "100"), ("--budget", "--renderer ulr")),
        ((model, "--exclude-view", "0"), ("--exclude-view", "--renderer ulr")),
    ]
    for args, words in cases:
        out = tmp_path / "out" / "x.png"
        r = run("render", *args, "--view", "0,0", "--out", out)
        err = " ".join(r.stderr.split())
        assert r.exit_code == 2, (args, r.output)
        assert all(w in err for w in words), (args, err)
        assert "Traceback" not in err and not out.parent.exists()
    # auto on the unfitted and the stale model: the hull by ULR
    for m in (plain, stale):
        r = run("render", m, "--view", "0,0", "--out", tmp_path / f"{m.name}.png", "--json")
        assert r.exit_code == 0 and json.loads(r.stdout)["renderer"] == "ulr"


def test_ulr_surfel_colours_at_a_captured_camera_sample_that_view(model):
    """At a captured camera the ULR weights are one-hot on that view: each surfel it sees
    gets the view's texel at its projection (OpenCV's bilinear remap as the reference)."""
    import cv2

    from opacityhull.render.renderer import model_surfels
    from opacityhull.render.splats import ulr_surfel_colours

    m = OpacityHullModel.open(model)
    s = model_surfels(m)
    cams = [v.camera for v in m.views]
    images = [_premul(m.load_view_rgba(i)) for i in range(len(m.views))]
    v = 5
    rgba, count = ulr_surfel_colours(s, cams, images, cams[v].centre_world, k=4)
    seen = s.visible_bool()[:, v]
    assert seen.sum() > 500 and np.all(count[seen] > 0)
    uv = np.asarray(cams[v].project(s.positions[seen].astype(np.float64))[0], np.float32)
    ref = cv2.remap(images[v], uv[:, 0], uv[:, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    np.testing.assert_allclose(rgba[seen], ref.reshape(-1, 4), atol=2e-3)
