"""`opacityhull render` and `opacityhull eval loo` on a written analytic model."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import opacityhull
from opacityhull.cli import app
from opacityhull.imageio import read_exr, read_png
from opacityhull.model import OpacityHullModel
from opacityhull.render.renderer import render_model

runner = CliRunner()


#: A shipped HDR probe (the same bytes as shared/data/probes/grace.hdr), so the tests need no ../shared.
GRACE = Path(opacityhull.__file__).parent / "data" / "probes" / "grace.hdr"


def run(*args):
    res = runner.invoke(app, [str(a) for a in args])
    res.flat = " ".join(res.output.split()).replace("\n", "")  # rich wraps long messages
    return res


def run_json(*args):
    res = run(*args, "--json")
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_render_captured_view_png_and_exr(sphere_dir, tmp_path):
    root, m = sphere_dir
    s = run_json("render", root, "--out", tmp_path / "v.exr", "--view", "1,30")
    assert s["frames"] == 1 and s["width"] == 64 and s["height"] == 48 and s["k"] == 4
    img = read_exr(tmp_path / "v.exr")
    assert img.shape == (48, 64, 4)
    ref = render_model(OpacityHullModel.open(root), m.cameras[4])
    np.testing.assert_allclose(img, ref.premul, atol=1e-6)  # the CLI renders what the API renders (premultiplied)
    s = run_json("render", root, "--out", tmp_path / "v.png", "--view", "1,15", "--width", "128")
    png = read_png(tmp_path / "v.png")
    assert png.shape == (96, 128, 4) and png[..., 3].max() > 0.99 and png[0, 0, 3] == 0


def test_render_orbit_writes_frames_and_gif(sphere_dir, tmp_path):
    import imageio.v2 as iio

    root, _ = sphere_dir
    s = run_json("render", root, "--out", tmp_path / "orb.png", "--orbit", 4, "--background", "grey")
    assert s["frames"] == 4 and len(s["paths"]) == 4 and s["ms_per_frame"] > 0
    frames = iio.mimread(s["gif"])
    assert len(frames) == 4 and frames[0].shape[:2] == (48, 64)
    from PIL import Image

    with Image.open(s["gif"]) as gif:  # default --fps 12: 8 cs (GIF's unit) a frame
        assert gif.info["duration"] == 80
    first = read_png(tmp_path / "orb_000.png")
    assert first.shape == (48, 64, 3)  # composited over the background: no alpha
    assert not np.allclose(read_png(tmp_path / "orb_000.png"), read_png(tmp_path / "orb_002.png"))


def test_render_look_at_over_environment_map(sphere_dir, tmp_path):
    root, _ = sphere_dir
    s = run_json(
        "render",
        root,
        "--out",
        tmp_path / "la.exr",
        "--look-at",
        "0,0.3,0.5,0,0.1,0,30",
        "--background",
        str(GRACE),
        "--env-yaw-deg",
        "180",
        "--k",
        "3",
    )
    assert s["background"] == "envmap"
    img = read_exr(tmp_path / "la.exr")
    assert img.shape == (48, 64, 3) and np.all(np.isfinite(img))
    from opacityhull.envmap import EnvironmentMap
    from opacityhull.render.background import envmap_background, load_background
    from opacityhull.render.runner import choose_cameras

    from opacityhull.render.cameras import parse_look_at

    cam = choose_cameras(OpacityHullModel.open(root), look_at=parse_look_at("0,0.3,0.5,0,0.1,0,30"))[0]
    env = load_background(str(GRACE), yaw_deg=180)
    assert isinstance(env, EnvironmentMap)
    bg = envmap_background(env, cam)
    np.testing.assert_allclose(img[0], bg[0], rtol=1e-5)  # the top row is all environment
    assert np.abs(img[24, 32] - bg[24, 32]).max() > 0.05  # the object covers the centre


@pytest.mark.parametrize(
    "args,code,msg",
    [
        (["--view", "0,0", "--orbit", "3"], 2, "only one of"),
        (["--view", "zero"], 2, "--view"),
        (["--view", "9,0"], 2, "no captured camera 9"),
        (["--look-at", "1,2,3"], 2, "--look-at"),
        (["--k", "0"], 2, "--k = 0"),  # the flag, not the field (#35)
        (["--background", "nonsense.png"], 2, "neither a colour"),
    ],
)
def test_render_bad_input_exits_nonzero_with_a_message(sphere_dir, tmp_path, args, code, msg):
    root, _ = sphere_dir
    res = run("render", root, "--out", tmp_path / "x.png", *args)
    assert res.exit_code == code
    assert msg in res.flat


def test_render_missing_model_and_bad_output(tmp_path, sphere_dir):
    res = run("render", tmp_path / "nothing", "--out", tmp_path / "x.png")
    assert res.exit_code == 2 and "no such model folder" in res.flat  # a missing path is bad input
    res = run("render", sphere_dir[0], "--out", tmp_path / "x.jpg")
    assert res.exit_code == 2 and ".png or .exr" in res.flat


def test_eval_loo_json_and_contact_sheet(sphere_dir, tmp_path):
    root, _ = sphere_dir
    s = run_json("eval", "loo", root, "--views", "every:6", "--out", tmp_path)
    assert set(s) >= {"views", "psnr_mean", "ssim_mean", "alpha_mae", "per_view"}
    assert len(s["views"]) == 6 and len(s["per_view"]) == 6
    assert s["psnr_mean"] > 21 and s["ssim_mean"] > 0.93 and s["alpha_mae"] < 0.1
    sheet = read_png(s["sheet"])
    assert sheet.shape[1] >= 3 * 64 and sheet.shape[0] >= 6 * 48
    saved = json.loads((tmp_path / "loo.json").read_text())
    assert saved["psnr_mean"] == pytest.approx(s["psnr_mean"])
    res = run("eval", "loo", root, "--views", "c9_t000.000")
    assert res.exit_code == 2 and "c9_t000.000" in res.flat


def test_render_background_takes_builtin_probes_as_relight_does(sphere_dir, tmp_path):
    """``render --background builtin:grace`` was refused though ``relight`` takes it (#33):
    one resolver (``opacityhull.envmap``), with the shipped probes' default yaw of 180°."""
    from opacityhull.data import probe_path

    root, _ = sphere_dir
    a = run_json("render", root, "--out", tmp_path / "a.exr", "--view", "0,0", "--background", "builtin:grace")
    b = run_json(
        "render", root, "--out", tmp_path / "b.exr", "--view", "0,0", "--background", probe_path("grace"),
        "--env-yaw-deg", "180",
    )  # fmt: skip
    assert a["background"] == b["background"] == "envmap"
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "b.exr"))
    run_json("render", root, "--out", tmp_path / "c.exr", "--view", "0,0", "--background", probe_path("grace"))
    assert not np.allclose(read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "c.exr"))  # a path's yaw stays 0
    r = run("render", root, "--out", tmp_path / "d.exr", "--background", "builtin:nowhere")
    assert r.exit_code == 2 and "nowhere" in r.flat and "grace" in r.flat


def test_frame_timings_leave_the_warm_up_out(sphere_dir, tmp_path):
    """``render --view`` reported 15 s "per frame", numba's compile included (#33): one
    small warm-up render per opened model is timed apart (``ms_warmup``), the frames'
    ``ms_per_frame`` are warm, and the pixels do not change."""
    from opacityhull.render.runner import _FrameState, _render_chunk, choose_cameras

    root, _ = sphere_dir
    s = run_json("render", root, "--out", tmp_path / "w.exr", "--view", "0,0")
    assert s["ms_warmup"] > 0 and s["ms_per_frame"] > 0 and "warm-up" not in s  # reported apart, not mixed in
    model = OpacityHullModel.open(root)
    st = _FrameState(root, model)
    cams = choose_cameras(model, orbit=2)
    from opacityhull.render.renderer import RenderConfig

    a = _render_chunk(st, cams, config=RenderConfig(), exclude=[], budget=None,
                      paths=[str(tmp_path / f"f{i}.exr") for i in range(2)], background=None, anim_background=None)  # fmt: skip
    b = _render_chunk(st, cams, config=RenderConfig(), exclude=[], budget=None,
                      paths=[str(tmp_path / f"g{i}.exr") for i in range(2)], background=None, anim_background=None)  # fmt: skip
    assert a["ms_warmup"] > 0 and b["ms_warmup"] == 0.0  # once per opened model
    for i in range(2):
        np.testing.assert_array_equal(read_exr(tmp_path / f"f{i}.exr"), read_exr(tmp_path / f"g{i}.exr"))
    ref = render_model(model, cams[0])
    np.testing.assert_array_equal(read_exr(tmp_path / "f0.exr"), ref.premul)
