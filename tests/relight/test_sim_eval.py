"""Relighting on the simulated rig end to end: `opacityhull capture` (reflectance
phase) → build → `opacityhull eval relight` against Mitsuba's direct render of the
same object under the same probe, for builtin:diffuse and builtin:glossy.

CI size: one camera (27° elevation), four table angles, the rig's 4 lights at 6 array
angles (24 one-light images per view; the zenith light repeats, 19 directions), 64×48
pixels. See THRESHOLDS for what the errors measure and why the limits are where they
are; benchmarks/relight.py and the report give the demo-plan figures.
"""

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from opacityhull.cli import app

pytestmark = pytest.mark.slow

# Relative L2 error (premultiplied RGB over the object's interior, mean over the four
# views) of relit captured views against Mitsuba's render under the probe, with the
# default near-light correction. Measured at this CI size (64×48, truth at 32 spp):
#   diffuse: grace 0.21, uffizi 0.20;   glossy: grace 0.43, uffizi 0.26
# (at 100×75 and 64 spp: 0.18 / 0.22 and 0.35 / 0.25; with 4 × 15 = 60 lights the
# diffuse figures stay at 0.20 / 0.19 — the light count is not what limits them).
# What remains is physics a one-light-at-a-time capture with lights at 1 m cannot
# represent, not noise: seen from a point of a 15 cm object a light comes from up to
# ~6° off its nominal direction (parallax; only its 1/r² is corrected), the windows of
# grace are small suns between lights 25–60° apart (on the glossy object their
# highlights land between the captured ones: hence 0.43), light cells are cut by the
# dark backdrop panels differently from the truth's occlusion, and the one-camera CI
# hull is loose (it places the near-light factor). A wrong light direction, table
# rotation, calibration or map orientation costs 0.5–2.0 (measured: the map turned by
# the table angle gives 0.97–2.0), so the limits — ~1.4–1.6× the measured values —
# separate "working" from "broken" without flaking on Monte-Carlo noise.
THRESHOLDS = {
    ("diffuse", "grace"): 0.32,
    ("diffuse", "uffizi"): 0.32,
    ("glossy", "grace"): 0.60,
    ("glossy", "uffizi"): 0.40,
}

PLAN = (Path(__file__).parent / "relight_ci_plan.toml").read_text()  # the capture plan, as `acquire` reads it


def _small_rig(tmp, width=64, height=48):
    from opacityhull.sim.scenes import DATA_DIR

    text = (DATA_DIR / "rig.toml").read_text()
    text = re.sub(r"(?m)^width = \d+", f"width = {width}", text)
    text = re.sub(r"(?m)^height = \d+", f"height = {height}", text)
    p = tmp / "rig.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module", params=["diffuse", "glossy"])
def sim_model(request, tmp_path_factory):
    pytest.importorskip("mitsuba")
    from opacityhull.reconstruct.build import BuildConfig, build_model

    scene = request.param
    tmp = tmp_path_factory.mktemp(f"sim_{scene}")
    rig = _small_rig(tmp)
    (tmp / "plan.toml").write_text(PLAN)
    r = CliRunner().invoke(
        app,
        [
            "capture",
            "--rig",
            f"sim:builtin:{scene}@{rig}",
            "--plan",
            str(tmp / "plan.toml"),
            "--out",
            str(tmp / "session"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    # the cameras are the simulator's true ones (a debug source, recorded in the
    # model): this test is about relighting, not calibration
    build_model(tmp / "session", tmp / "model", config=BuildConfig(cameras="groundtruth", hull_res=64, pictures=False))
    return scene, tmp / "model"


@pytest.mark.parametrize("probe", ["grace", "uffizi"])
def test_eval_relight_against_mitsuba(sim_model, probe, tmp_path):
    scene, model = sim_model
    r = CliRunner().invoke(
        app,
        [
            "eval",
            "relight",
            str(model),
            "--envmap",
            f"builtin:{probe}",
            "--spp",
            "32",
            "--out",
            str(tmp_path / "e"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["truth"].startswith(f"mitsuba render_under_envmap (scene builtin:{scene}")
    assert len(s["per_view"]) == 4 and all(v["pixels"] > 100 for v in s["per_view"])
    assert s["n_lights_captured"] == 24 and s["config"]["near_light"] is True
    print(scene, probe, "rel_err_mean", s["rel_err_mean"], "psnr_mean", s["psnr_mean"])
    assert s["rel_err_mean"] < THRESHOLDS[(scene, probe)], s["per_view"]
    # every table angle, not just the unturned one: the map stays in the object frame
    assert s["rel_err_max"] < 1.5 * THRESHOLDS[(scene, probe)]
    assert (tmp_path / "e" / "eval_relight.png").stat().st_size > 0
