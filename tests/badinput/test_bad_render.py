"""Bad inputs of ``render`` and ``eval loo``: refused before anything is rendered or
written, naming the flag, the value and what is expected."""

from __future__ import annotations

import json

import pytest

from badkit import Case, invoke, run_case

OUT = "{T}/out.png"
NOTHING = ("{T}/out.png", "{T}/out_000.png", "{T}/out.gif")

CASES = [
    Case(
        "width-zero",
        ("render", "{M}", "--out", OUT, "--width", "0"),
        2,
        r"--width 0: expected a positive number",
        must_not_exist=NOTHING,
    ),
    Case(
        "height-zero",
        ("render", "{M}", "--out", OUT, "--height", "0"),
        2,
        r"--height 0: expected a positive",
        must_not_exist=NOTHING,
    ),
    Case(
        "width-negative",
        ("render", "{M}", "--out", OUT, "--width", "-5"),
        2,
        r"--width -5: expected a positive",
        must_not_exist=NOTHING,
    ),
    Case(
        "width-huge",
        ("render", "{M}", "--out", OUT, "--width", "100000"),
        2,
        r"--width/--height: 100000 x 75000 = 7500 Mpx is more than the 67 Mpx limit \(MAX_RENDER_PIXELS\)",
        must_not_exist=NOTHING,
    ),
    Case(
        "width-height-huge",
        ("render", "{M}", "--out", OUT, "--width", "9000", "--height", "9000"),
        2,
        r"9000 x 9000 = 81 Mpx is more than",
        must_not_exist=NOTHING,
    ),
    Case(
        "fps-zero",
        ("render", "{M}", "--out", OUT, "--orbit", "2", "--fps", "0"),
        2,
        r"--fps 0.0: expected a frame rate > 0",
        must_not_exist=NOTHING,
    ),
    Case(
        "fps-negative",
        ("render", "{M}", "--out", OUT, "--orbit", "2", "--fps", "-3"),
        2,
        r"--fps -3.0",
        must_not_exist=NOTHING,
    ),
    Case(
        "orbit-zero",
        ("render", "{M}", "--out", OUT, "--orbit", "0"),
        2,
        r"--orbit 0: expected at least 1 frame",
        must_not_exist=NOTHING,
    ),
    Case(
        "background-kind-bogus",
        ("render", "{M}", "--out", OUT, "--background", "black", "--background-kind", "bogus"),
        2,
        r"--background-kind 'bogus': expected one of auto, image, envmap",
        must_not_exist=NOTHING,
    ),
    Case(
        "every-view-excluded",
        ("render", "{M}", "--out", OUT, *sum((("--exclude-view", str(i)) for i in range(12)), ())),
        2,
        r"--exclude-view: all 12 views of .* are excluded",
        must_not_exist=NOTHING,
    ),
    Case(
        "every-view-excluded-old-flag",
        ("render", "{M}", "--out", OUT, *sum((("--exclude", str(i)) for i in range(12)), ())),
        2,
        r"all 12 views",
        must_not_exist=NOTHING,
    ),
    Case(
        "unknown-view-excluded",
        ("render", "{M}", "--out", OUT, "--exclude-view", "c9_t000.000"),
        2,
        r"view 'c9_t000.000' not in model",
        must_not_exist=NOTHING,
    ),
    Case(
        "model-missing",
        ("render", "{T}/nosuch", "--out", OUT),
        2,
        r"nosuch: no such model folder",
        must_not_exist=NOTHING,
    ),
    Case(
        "model-is-a-file",
        ("render", "{M}/model.toml", "--out", OUT),
        2,
        r"model.toml is a file, expected a model folder",
        must_not_exist=NOTHING,
    ),
    Case("loo-model-missing", ("eval", "loo", "{T}/nosuch"), 2, r"nosuch: no such model folder"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_render_input(case, model_dir, tmp_path):
    run_case(case, inputs={"M": model_dir}, tmp_path=tmp_path)


def test_old_flag_names_still_work_and_are_hidden(model_dir, tmp_path):
    r = invoke(["render", model_dir, "--out", tmp_path / "a.png", "--exclude", "0", "--yaw-deg", "0", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["frames"] == 1 and (tmp_path / "a.png").is_file()
    h = invoke(
        ["render", "--help"],
    )
    assert "--exclude-view" in h.stdout and "--env-yaw-deg" in h.stdout
    assert "--yaw-deg " not in h.stdout and "--exclude " not in h.stdout


def test_eval_loo_writes_outside_the_model_by_default(model_dir, tmp_path, monkeypatch):
    import shutil

    from badkit import tree_digest

    m = tmp_path / "mymodel"
    shutil.copytree(model_dir, m)
    before = tree_digest(m)
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    r = invoke(["eval", "loo", m, "--views", "0", "--json"])
    assert r.exit_code == 0, r.output
    assert (work / "mymodel_loo" / "loo.json").is_file()
    assert tree_digest(m) == before  # nothing written into the model
