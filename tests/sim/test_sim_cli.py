"""``opacityhull sim render`` and ``sim scenes`` through the real CLI app."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from opacityhull.cli import app
from opacityhull.imageio import read_exr


def _json(result):
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_render_writes_exr_and_preview(tmp_path):
    out = tmp_path / "img.exr"
    r = CliRunner().invoke(
        app,
        [
            "sim",
            "render",
            "--scene",
            "builtin:sphere",
            "--camera",
            "cam2",
            "--table-deg",
            "30",
            "--light",
            "1",
            "--scale",
            "0.4",
            "--out",
            str(out),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    d = _json(r)
    img = read_exr(out)
    assert img.shape == (60, 80, 3) and d["width"] == 80 and d["lights"] == [1]
    assert d["effects"]["integrator"] == "direct" and d["effects"]["phase"] == "reflectance"
    assert (tmp_path / "img.png").is_file()
    assert np.isclose(img.mean(), d["mean_radiance"], rtol=1e-5)


def test_render_pattern_with_lights_off(tmp_path):
    r = CliRunner().invoke(
        app,
        [
            "sim",
            "render",
            "--scene",
            "builtin:diffuse",
            "--camera",
            "0",
            "--lights-off",
            "--pattern",
            "black",
            "--scale",
            "0.3",
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    assert _json(r)["max_radiance"] == 0.0  # an all-black pattern and no lights: black


def test_render_bad_input_exits_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[materials.m]\ntype = "unobtainium"\n[[objects]]\nshape = "sphere"\nmaterial = "m"\n')
    r = CliRunner().invoke(app, ["sim", "render", "--scene", str(bad)])
    assert r.exit_code == 2 and "materials.m.type" in r.output
    r = CliRunner().invoke(app, ["sim", "render", "--scene", "builtin:sphere", "--light", "1", "--lights-off"])
    assert r.exit_code == 2
    r = CliRunner().invoke(app, ["sim", "render", "--scene", "builtin:sphere", "--camera", "cam9"])
    assert r.exit_code == 2 and "cam9" in r.output
    r = CliRunner().invoke(app, ["sim", "render", "--scene", "builtin:sphere", "--pattern", "plaid"])
    assert r.exit_code == 2 and "plaid" in r.output


def test_scenes_lists_the_builtins():
    r = CliRunner().invoke(app, ["sim", "scenes", "--json"])
    assert r.exit_code == 0
    names = {s["name"] for s in _json(r)["scenes"]}
    assert {"builtin:diffuse", "builtin:glossy", "builtin:fuzzy", "builtin:glass", "builtin:charuco"} <= names


def test_scenes_and_explain_print_their_text_on_stdout():
    """``sim scenes | less`` showed nothing: the list went to stderr (#33)."""
    r = CliRunner().invoke(app, ["sim", "scenes"])
    assert r.exit_code == 0, r.output
    assert "builtin:diffuse" in r.stdout and "builtin:diffuse" not in r.stderr
    assert "stdout is for --json" not in r.stderr
    r = CliRunner().invoke(app, ["sim", "explain", "--scene", "builtin:diffuse", "--phase", "matting"])
    assert r.exit_code == 0, r.output
    assert "expected cost" in r.stdout and "expected cost" not in r.stderr
