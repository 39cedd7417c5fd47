"""Bad inputs of ``render`` and ``eval loo``: refused before anything is rendered or
written, naming the flag, the value and what is expected."""

from __future__ import annotations

import json

import pytest

from badkit import Case, invoke, run_case

OUT = "{T}/out.png"
NOTHING = ("{T}/out.png", "{T}/out_000.png", "{T}/out.gif")


def _render(case_id: str, flags: tuple, message: str, *, model: str = "{M}") -> Case:
    """``render MODEL --out OUT FLAGS``: exit 2 and no image written."""
    return Case(case_id, ("render", model, "--out", OUT, *flags), 2, message, must_not_exist=NOTHING)


EXCLUDE_ALL = sum((("--exclude-view", str(i)) for i in range(12)), ())
EXCLUDE_ALL_OLD_FLAG = sum((("--exclude", str(i)) for i in range(12)), ())
HUGE = r"--width/--height: 100000 x 75000 = 7500 Mpx is more than the 67 Mpx limit \(MAX_RENDER_PIXELS\)"
CASES = [
    _render("width-zero", ("--width", "0"), r"--width 0: expected a positive number"),
    _render("height-zero", ("--height", "0"), r"--height 0: expected a positive"),
    _render("width-negative", ("--width", "-5"), r"--width -5: expected a positive"),
    _render("width-huge", ("--width", "100000"), HUGE),
    _render("width-height-huge", ("--width", "9000", "--height", "9000"), r"9000 x 9000 = 81 Mpx is more than"),
    _render("fps-zero", ("--orbit", "2", "--fps", "0"), r"--fps 0.0: expected a frame rate > 0"),
    _render("fps-negative", ("--orbit", "2", "--fps", "-3"), r"--fps -3.0"),
    _render("orbit-zero", ("--orbit", "0"), r"--orbit 0: expected at least 1 frame"),
    _render(
        "background-kind-bogus",
        ("--background", "black", "--background-kind", "bogus"),
        r"--background-kind 'bogus': expected one of auto, image, envmap",
    ),
    _render("every-view-excluded", EXCLUDE_ALL, r"--exclude-view: all 12 views of .* are excluded"),
    _render("every-view-excluded-old-flag", EXCLUDE_ALL_OLD_FLAG, r"all 12 views"),
    _render("unknown-view-excluded", ("--exclude-view", "c9_t000.000"), r"view 'c9_t000.000' not in model"),
    _render("model-missing", (), r"nosuch: no such model folder", model="{T}/nosuch"),
    _render("model-is-a-file", (), r"model.toml is a file, expected a model folder", model="{M}/model.toml"),
    Case("loo-model-missing", ("eval", "loo", "{T}/nosuch"), 2, r"nosuch: no such model folder"),
    Case(
        "loo-twins-unknown",
        ("eval", "loo", "{M}", "--twins", "drop", "--out", "{T}/loo"),
        2,
        r"--twins.*drop.*expected together or keep",
    ),
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


def test_eval_loo_writes_under_the_model_by_default_and_names_the_holdout_on_the_sheet(
    model_dir, tmp_path, monkeypatch
):
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
    assert (m / "eval" / "loo" / "loo.json").is_file() and not any(work.iterdir())
    after = {k: v for k, v in tree_digest(m).items() if not k.startswith("eval/")}
    assert after == before  # nothing of the model itself touched
    # the sheet's render column names the holdout mode
    import numpy as np

    from opacityhull.evaluate.loo import contact_sheet

    rgba = np.zeros((8, 8, 4), np.float32)
    plain = contact_sheet([("v", rgba, rgba, "")], tmp_path / "a.png")
    named = contact_sheet([("v", rgba, rgba, "")], tmp_path / "b.png", holdout="geometry")
    assert plain.read_bytes() != named.read_bytes()
