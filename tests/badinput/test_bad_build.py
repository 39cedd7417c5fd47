"""Bad inputs of ``build``: every one is refused before the build runs (the issue's
FileExistsError came after a whole build), with nothing written and the session intact."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from badkit import Case, run_case


def _make_file(rel: str):
    def setup(root: Path):
        p = root.parent / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("not a model folder\n")

    return setup


def _set_white_level(value: str):
    def setup(root: Path):
        p = root / "session.toml"
        p.write_text(re.sub(r"(?m)^white_level = .*$", f"white_level = {value}", p.read_text()))

    return setup


M = "{T}/m"
WHITE_LEVEL = r"session.toml: \[session\] white_level = {}, expected a finite number > 0"


def _bad_white_level(case_id: str, toml_value: str, shown: str) -> Case:
    """``white_level = TOML_VALUE`` in session.toml: exit 4 and no model.toml written."""
    argv = ("build", "{S}", "--out", M, "--no-pictures")
    setup = _set_white_level(toml_value)
    return Case(case_id, argv, 4, WHITE_LEVEL.format(shown), setup=setup, must_not_exist=(f"{M}/model.toml",))


def _bad_flag(case_id: str, flags: tuple, message: str) -> Case:
    """``build {S} --out M FLAGS``: exit 2 and no model folder created."""
    return Case(case_id, ("build", "{S}", "--out", M, *flags), 2, message, must_not_exist=(M,))


CASES = [
    Case(
        "out-is-a-file",
        ("build", "{S}", "--out", "{T}/model.txt"),
        2,
        r"--out .*model.txt: is an existing file, expected a model folder",
        setup=_make_file("model.txt"),
    ),
    Case("out-is-the-session", ("build", "{S}", "--out", "{S}"), 2, r"--out .*S: is the session folder"),
    Case(
        "out-inside-the-session",
        ("build", "{S}", "--out", "{S}/model"),
        2,
        r"--out .*S/model: is inside the session folder",
        must_not_exist=("{S}/model",),
    ),
    Case("out-contains-the-session", ("build", "{S}", "--out", "{T}"), 2, r"contains the session folder"),
    Case(
        "session-missing",
        ("build", "{T}/nosuch", "--out", M),
        2,
        r"nosuch: no such session folder",
        must_not_exist=(M,),
    ),
    _bad_white_level("white-level-text", '"bright"', r"\"bright\""),
    _bad_white_level("white-level-zero", "0", "0"),
    _bad_flag("bounds-not-numbers", ("--bounds", "a,b"), r"--bounds 'a,b': expected six numbers"),
    _bad_flag("refine-unknown", ("--refine", "deep"), r"--refine 'deep': expected shading, surfels or none"),
    # the train/test split (#29): a selection of no view, of every view, or out of range
    _bad_flag("hold-out-every-view", ("--hold-out", "every:1"), r"--hold-out 'every:1': holds out all 6 views"),
    _bad_flag("hold-out-every-0", ("--hold-out", "every:0"), r"--hold-out 'every:0': every:N needs a whole number"),
    _bad_flag("hold-out-all-listed", ("--hold-out", "0,1,2,3,4,5"), r"holds out all 6 views"),
    _bad_flag("hold-out-no-view", ("--hold-out", ","), r"--hold-out ',': names no view"),
    _bad_flag("hold-out-unknown-id", ("--hold-out", "c9_t000.000"), r"no view 'c9_t000.000' in the session"),
    _bad_flag("hold-out-out-of-range", ("--hold-out", "2,99"), r"view index 99 is out of range \[0, 6\)"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_build_input(case, session_dir, tmp_path):
    run_case(case, inputs={"S": session_dir}, tmp_path=tmp_path)


def test_build_progress_starts_each_step_with_its_own_count(monkeypatch, session_dir, tmp_path):
    """The bar's count is the step's: after "matting 6/6", the next step must not keep
    showing a stale count (the issue: "0/24" through every step)."""
    import rich.progress

    import opacityhull.reconstruct.build as build_mod
    from badkit import invoke

    seen = []

    class Report:
        notes = []

        def summary(self):
            return {
                "model": str(tmp_path / "m"),
                "views": 6,
                "surfels": 0,
                "seconds": {},
                "metrics": {},
                "camera_source": "x",
                "backdrop_source": "y",
            }

    def fake_build(session, out, *, config, ground_truth, progress, on_step, **_):
        on_step("matting")
        for i in range(6):
            progress(i + 1, 6)
        on_step("hull")
        seen.append([(t.description, t.completed, t.total) for t in bar_ref[0].tasks if t.visible])
        return Report()

    bar_ref = []
    real_progress = rich.progress.Progress

    class Spy(real_progress):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            bar_ref.append(self)

    monkeypatch.setattr(build_mod, "build_model", fake_build)
    monkeypatch.setattr(rich.progress, "Progress", Spy)
    r = invoke(["build", session_dir, "--out", tmp_path / "m"])
    assert r.exit_code == 0, r.output
    assert seen == [[("hull", 0, None)]]
