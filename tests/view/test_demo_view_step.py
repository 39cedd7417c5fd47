"""The demo's last step: the viewer bundle of the model and the command that serves it."""

from __future__ import annotations

import json
import shlex

from typer.testing import CliRunner

from opacityhull.cli import app
from opacityhull.demo_runner import VIEW_PORT, print_view_summary, view_step
from opacityhull.view.bundle import VIEWER_FORMAT


def test_demo_view_step_writes_the_bundle_and_a_working_command(view_model, tmp_path, capsys):
    root, m = view_model
    web = tmp_path / "demo" / "web"
    s = view_step(root, web)
    man = json.loads((web / "manifest.json").read_text())
    assert man["format"] == VIEWER_FORMAT and man["n_surfels"] == len(m.surfels) == s["surfels"]
    assert (web / "index.html").is_file() and s["index"] == str(web / "index.html")
    assert s["serve"] == f"opacityhull view {root} --port {VIEW_PORT}"
    assert s["url"] == f"http://127.0.0.1:{VIEW_PORT}/" and f"-d {web} {VIEW_PORT}" in s["serve_static"]
    print_view_summary(s)
    err = " ".join(capsys.readouterr().err.split())
    assert s["serve"] in err and str(web) in err and s["url"] in err
    # a second demo run replaces its own earlier bundle
    (web / "manifest.json").write_text(json.dumps({**man, "n_surfels": -1}))
    view_step(root, web)
    assert json.loads((web / "manifest.json").read_text())["n_surfels"] == len(m.surfels)
    # the printed command is one the CLI accepts (with --out instead of serving forever)
    argv = shlex.split(s["serve"])
    assert argv[:2] == ["opacityhull", "view"]
    args = argv[2:]
    args[args.index("--port") :] = ["--out", str(tmp_path / "b2")]
    res = CliRunner().invoke(app, ["view", *args])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "b2" / "manifest.json").read_text())["n_surfels"] == len(m.surfels)
