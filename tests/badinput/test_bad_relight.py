"""Bad inputs of ``relight`` and ``eval relight``: refused before any image is relit or
written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from badkit import Case, invoke, run_case

OUT = "{T}/relit"

GRACE = ("--envmap", "builtin:grace")


def _relight(case_id: str, flags: tuple, message: str, *, model: str = "{M}") -> Case:
    """``relight MODEL --out OUT --envmap builtin:grace FLAGS``: exit 2, nothing written."""
    return Case(case_id, ("relight", model, "--out", OUT, *GRACE, *flags), 2, message, must_not_exist=(OUT,))


def _eval(case_id: str, flags: tuple, message: str) -> Case:
    """``eval relight {M} --envmap builtin:grace FLAGS --out OUT``: exit 2, nothing written."""
    return Case(case_id, ("eval", "relight", "{M}", *GRACE, *flags, "--out", OUT), 2, message, must_not_exist=(OUT,))


CASES = [
    _relight("exposure-negative", ("--exposure", "-1"), r"--exposure -1.0: expected a multiplier > 0"),
    _relight("exposure-zero", ("--exposure", "0"), r"--exposure 0.0: expected a multiplier > 0"),
    _relight("exposure-nan", ("--exposure", "nan"), r"--exposure nan"),
    _relight("orbit-zero", ("--orbit", "0"), r"--orbit 0: expected at least 1 frame"),
    _relight("model-missing", (), r"nosuch: no such model folder", model="{T}/nosuch"),
    _eval("eval-spp-zero", ("--spp", "0"), r"--spp 0: expected at least 1 sample per pixel"),
    _eval("eval-max-views-zero", ("--max-views", "0"), r"--max-views 0: expected at least 1"),
    Case("eval-model-missing", ("eval", "relight", "{T}/nosuch", *GRACE), 2, r"nosuch: no such model folder"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_relight_input(case, relight_model_dir, tmp_path):
    run_case(case, inputs={"M": relight_model_dir}, tmp_path=tmp_path)


def test_eval_relight_default_out_is_model_eval_relight_and_old_yaw_flag_works(
    relight_model_dir, tmp_path, monkeypatch
):
    import opacityhull.evaluate.relight as ev

    got = {}

    def fake(model, **kw):
        got.update(kw)
        return {"per_view": [], "psnr_mean": 0.0, "rel_err_mean": 0.0, "sheet": ""}

    monkeypatch.setattr(ev, "eval_relight", fake)
    monkeypatch.chdir(tmp_path)
    r = invoke(["eval", "relight", relight_model_dir, "--envmap", "builtin:grace", "--yaw-deg", "33", "--json"])
    assert r.exit_code == 0, r.output
    from opacityhull.relight.envmap import load_envmap

    # the command loads the map turned by the old flag's yaw and hands the runner the map itself
    np.testing.assert_array_equal(got["envmap"].radiance, load_envmap("builtin:grace", yaw_deg=33.0).radiance)
    assert Path(got["out"]) == Path(relight_model_dir) / "eval" / "relight"  # beside the model's own pictures
    r = invoke(["eval", "relight", relight_model_dir, "--envmap", "builtin:grace", "--env-yaw-deg", "12", "--json"])
    assert r.exit_code == 0
    np.testing.assert_array_equal(got["envmap"].radiance, load_envmap("builtin:grace", yaw_deg=12.0).radiance)


def test_eval_relight_warns_when_few_lights_were_captured(relight_model_dir, tmp_path, monkeypatch):
    import json

    import opacityhull.evaluate.relight as ev
    from badkit import flat

    def fake(model, **kw):
        return {"per_view": [], "psnr_mean": 10.0, "rel_err_mean": 0.7, "sheet": "s.png", "n_lights_captured": 2}

    monkeypatch.setattr(ev, "eval_relight", fake)
    r = invoke(["eval", "relight", relight_model_dir, "--envmap", "builtin:grace", "--out", tmp_path / "e"])
    assert r.exit_code == 0 and "warning: only 2 captured light direction(s)" in flat(r.stderr)
    r = invoke(["eval", "relight", relight_model_dir, "--envmap", "builtin:grace", "--out", tmp_path / "e", "--json"])
    assert "only 2 captured" in json.loads(r.stdout)["warnings"][0]
