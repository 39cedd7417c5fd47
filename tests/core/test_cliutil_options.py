"""cliutil.option_group: options declared once land in one dict, keep their place in
--help, and are validated by typer (a bad value exits 2)."""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from opacityhull.cliutil import option_group, scheduler_options

OPTS = {
    "k": (int, typer.Option(4, "--k", min=1, max=16, help="ULR neighbourhood.")),
    "shading": (str, typer.Option("pixel", "--shading", help="pixel or surfel.")),
}


def _app(build=None):
    app = typer.Typer()
    seen = {}

    @app.command()
    @option_group(OPTS, into="render", before="out", build=build)
    def render(model: str, out: str = typer.Option("o", "--out", help="Output folder."), *, render):
        seen["model"], seen["out"], seen["render"] = model, out, render

    @app.command()
    @option_group(scheduler_options("what runs there", workers=True), into="sched")
    def other(model: str, *, sched):
        seen["sched"] = sched

    return app, seen


def test_values_arrive_as_one_dict_with_defaults():
    app, seen = _app()
    r = CliRunner().invoke(app, ["render", "M", "--k", "7"])
    assert r.exit_code == 0, r.output
    assert seen == {"model": "M", "out": "o", "render": {"k": 7, "shading": "pixel"}}
    r = CliRunner().invoke(app, ["other", "M", "--scheduler", "threads", "--workers", "2"])
    assert r.exit_code == 0, r.output
    assert seen["sched"] == {"scheduler": "threads", "timeout_s": 10.0, "workers": 2}


def test_build_converts_the_dict():
    app, seen = _app(build=lambda **v: (v["k"], v["shading"]))
    assert CliRunner().invoke(app, ["render", "M", "--shading", "surfel"]).exit_code == 0
    assert seen["render"] == (4, "surfel")


def test_help_order_and_bad_value():
    app, _ = _app()
    r = CliRunner().invoke(app, ["render", "--help"], env={"COLUMNS": "200", "NO_COLOR": "1"})
    text = re.sub(r"\x1b\[[0-9;]*m", "", r.output)
    assert text.index("--k") < text.index("--shading") < text.index("--out")  # placed before --out
    bad = CliRunner().invoke(app, ["render", "M", "--k", "0"])
    assert bad.exit_code == 2 and "--k" in re.sub(r"\x1b\[[0-9;]*m", "", bad.output)


def test_missing_target_parameter_is_a_programming_error():
    with pytest.raises(TypeError, match="keyword-only parameter 'render'"):

        @option_group(OPTS, into="render")
        def f(model: str):  # no `render` parameter
            return model
