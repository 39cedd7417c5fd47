"""`opacityhull relight` and `opacityhull eval relight` end to end on the analytic
sphere model (the real CLI in a subprocess-free typer runner)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from opacityhull.cli import app
from opacityhull.imageio import read_exr, write_exr


def run(*args):
    r = CliRunner().invoke(app, [str(a) for a in args])
    r.text = " ".join(r.output.split())  # rich wraps long messages
    return r


def run_ok(*args) -> dict:
    """``run(*args, "--json")``: asserts exit 0 and returns the summary (the last stdout line)."""
    r = run(*args, "--json")
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_relight_envmap_writes_views_and_summary(sphere_model, probes_dir, tmp_path):
    uffizi = ("--envmap", probes_dir / "uffizi.hdr", "--yaw-deg", 180)
    s = run_ok("relight", sphere_model, *uffizi, "--out", tmp_path / "o")
    assert s["n_views"] == 8 and s["n_lights_captured"] == 60
    assert s["lighting"]["envmap"]["source"] == "uffizi.hdr yaw 180"
    rgba = read_exr(tmp_path / "o" / "views" / "c0_t000.000.exr")
    assert rgba.shape == (32, 40, 4) and rgba[..., :3].max() > 0
    assert (tmp_path / "o" / "views.png").stat().st_size > 0
    assert json.loads((tmp_path / "o" / "relight.json").read_text())["n_views"] == 8


def test_builtin_probe_gets_its_yaw_by_default(sphere_model, tmp_path):
    grace = ("relight", sphere_model, "--envmap", "builtin:grace", "--out", tmp_path / "o", "--no-views")
    assert run_ok(*grace)["lighting"]["envmap"]["source"] == "grace.hdr yaw 180"
    assert run_ok(*grace, "--yaw-deg", 0)["lighting"]["envmap"]["source"] == "grace.hdr"
    r = run("relight", sphere_model, "--envmap", "builtin:sun", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "unknown built-in probe" in r.text


def test_relight_with_lights_and_pca(sphere_model, tmp_path):
    lights = "0,1,0.2,1,1,1;point:1,1,0,2,0,0"
    s = run_ok("relight", sphere_model, "--lights", lights, "--pca-rank", 9, "--out", tmp_path / "o", "--no-views")
    assert s["lighting"]["envmap"] is None and len(s["lighting"]["lights"]) == 2
    np.testing.assert_allclose(s["lighting"]["lights"][1]["irradiance_rgb"], [1.0, 0, 0])  # 2 / |(1,1,0)|^2
    assert s["pca"]["rank"] == 9 and 0 < s["pca"]["reflectance_rel_error_mean"] < 0.05
    assert not (tmp_path / "o" / "views").exists()


def test_relight_orbit_and_view_render_through_ulr(sphere_model, probes_dir, tmp_path):
    pisa = ("--envmap", probes_dir / "pisa.hdr", "--yaw-deg", 180)
    orbit = ("--orbit", 3, "--fps", 5, "--view", "1,45")
    s = run_ok("relight", sphere_model, *pisa, *orbit, "--out", tmp_path / "o", "--no-views")
    assert s["orbit"]["frames"] == 3
    from PIL import Image

    with Image.open(tmp_path / "o" / "orbit.gif") as gif:  # 5 fps: 200 ms a frame, not 0 (the old bug)
        assert gif.n_frames == 3 and gif.info["duration"] == 200
    f = read_exr(tmp_path / "o" / "orbit" / "frame_001.exr")
    assert f.shape == (32, 40, 4) and f[..., 3].max() > 0.9  # the sphere is in frame
    assert (tmp_path / "o" / "view_c1_t045.000.png").is_file()


def test_relight_bad_inputs_exit_nonzero_with_a_clear_message(sphere_model, tmp_path):
    bad = np.ones((8, 16, 3), np.float32)
    bad[3, 4, 0] = np.nan
    write_exr(tmp_path / "nan.exr", bad)
    r = run("relight", sphere_model, "--envmap", tmp_path / "nan.exr", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "nan.exr" in r.text and "1 NaN" in r.text
    r = run("relight", sphere_model, "--out", tmp_path / "o")
    assert r.exit_code == 2 and "--envmap" in r.text
    r = run("relight", tmp_path / "nope", "--lights", "0,1,0,1,1,1", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "no such model folder" in r.text
    r = run("relight", sphere_model, "--lights", "0,1,0,1,1", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "--lights" in r.text
    r = run("relight", sphere_model, "--lights", "0,1,0,1,1,1", "--view", "9,0", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "no captured camera 9" in r.text


def test_eval_relight_on_the_analytic_sphere(sphere_model, probes_dir, tmp_path):
    uffizi = ("--envmap", probes_dir / "uffizi.hdr", "--yaw-deg", 180)
    s = run_ok("eval", "relight", sphere_model, *uffizi, "--max-views", 3, "--out", tmp_path / "e")
    assert {"psnr_mean", "rel_err_mean", "per_view"} <= set(s)
    assert len(s["per_view"]) == 3 and s["truth"] == "analytic quadrature"
    assert s["rel_err_mean"] < 0.03 and s["psnr_mean"] > 30
    assert (tmp_path / "e" / "eval_relight.png").stat().st_size > 0


def test_eval_relight_refuses_a_model_of_a_real_rig(sphere_model, tmp_path, probes_dir):
    """A model whose session was captured on hardware has no ground truth to compare with."""
    import shutil
    import tomllib

    from opacityhull.session import SESSION_FORMAT
    from opacityhull.tomlio import toml_dumps

    m = tmp_path / "m"
    shutil.copytree(sphere_model, m)
    sess = tmp_path / "sess"
    sess.mkdir()
    (sess / "session.toml").write_text(
        toml_dumps({"session": {"format": SESSION_FORMAT, "rig_source": "rigs/lab.toml"}})
    )
    (sess / "manifest.jsonl").write_text("")
    meta = tomllib.loads((m / "model.toml").read_text())
    meta["provenance"] = {"session": str(sess)}
    (m / "model.toml").write_text(toml_dumps(meta))
    r = run("eval", "relight", m, "--envmap", probes_dir / "uffizi.hdr", "--json")
    assert r.exit_code == 2 and "not a simulated rig" in r.text and "rigs/lab.toml" in r.text


def test_metrics_and_scene_lookup():
    from opacityhull.evaluate.relight import _scene_of, relight_metrics

    a = np.ones((4, 5, 3), np.float32)
    m = np.zeros((4, 5), bool)
    m[1:3, 1:4] = True
    r = relight_metrics(a, a, m)
    assert r["psnr"] == float("inf") and r["rel_err"] == 0 and r["pixels"] == 6
    r = relight_metrics(a * 1.1, a, m)
    assert r["rel_err"] == pytest.approx(0.1, rel=1e-5) and r["psnr"] == pytest.approx(20.0, abs=1e-3)
    assert np.isnan(relight_metrics(a, a, np.zeros_like(m))["rel_err"])
    assert _scene_of("sim:builtin:glossy") == "builtin:glossy"
    assert _scene_of("sim:builtin:diffuse@/tmp/small/rig.toml") == "builtin:diffuse"
    assert _scene_of("sim:glossy?scale=0.5") == "builtin:glossy"


def test_all_zero_envmap_is_refused_and_nothing_written(sphere_model, tmp_path):
    write_exr(tmp_path / "black.exr", np.zeros((8, 16, 3), np.float32))
    for cmd in (("relight",), ("eval", "relight")):
        out = tmp_path / ("o_" + "_".join(cmd))
        r = run(*cmd, sphere_model, "--envmap", tmp_path / "black.exr", "--out", out)
        text = " ".join(r.output.split())
        assert r.exit_code == 2 and "black.exr" in text and "all zero" in text, r.output
        assert not out.exists()


def test_mean_normalised_psnr():
    """psnr_norm divides by the truth's mean: a uniform 10 % error scores
    10 log10(1 / 0.01) = 20 dB whatever the brightness, and one bright highlight in the
    truth leaves it unchanged where the peak PSNR rises."""
    from opacityhull.evaluate.metrics import relight_metrics

    rng = np.random.default_rng(3)
    t = rng.uniform(0.5, 1.5, (16, 16, 3))
    m = np.ones((16, 16), bool)
    for scale in (1e-3, 1.0, 1e3):
        r = relight_metrics(scale * t * 1.1, scale * t, m)
        expect = 10 * np.log10(np.mean(t) ** 2 / np.mean((0.1 * t) ** 2))
        assert r["psnr_norm"] == pytest.approx(expect, abs=1e-6)
        assert r["rel_err"] == pytest.approx(0.1, rel=1e-9)
    e = np.zeros_like(t)
    e[2, 3] = 0.5  # one wrong pixel, then one bright highlight both images share
    h = t.copy()
    h[9, 9] = 200.0
    a, b = relight_metrics(t + e, t, m), relight_metrics(h + e, h, m)
    assert b["psnr"] > a["psnr"] + 40  # the peak PSNR is flattered by the highlight
    assert abs(b["psnr_norm"] - a["psnr_norm"]) < abs(b["psnr"] - a["psnr"]) / 2
