"""The demo's relit-glass step, without Mitsuba: its plan and its switch.

The step itself (capture → build → relight → eval against Mitsuba) is what
``tests/relight/test_natural_eval_relight.py`` and ``tests/e2e/test_natural_glass.py``
run on a smaller plan; here only what the demo adds is checked: the plan is a valid
natural-illumination plan with two illumination domains whose patterns do not fit the
display controller's 64 slots at once (so it relies on upload-as-shown), and
``opacityhull demo --no-glass`` exists and is the only way to skip the step.
"""

from __future__ import annotations

import tomllib

from typer.testing import CliRunner

from opacityhull.acquire.patterns import plan_patterns
from opacityhull.acquire.plan import parse_plan
from opacityhull.acquire.schedule import expected_counts, schedule
from opacityhull.demo_runner import GLASS_PLAN, GLASS_RIG, run_demo


def _geometry():
    from opacityhull.sim.simrig import open_sim_rig

    rig = open_sim_rig(GLASS_RIG, open=False)
    return rig.geometry


def test_glass_plan_is_two_domains_beyond_the_slots():
    plan = parse_plan(tomllib.loads(GLASS_PLAN), where="demo glass plan")
    nat = plan.natural
    assert nat is not None and nat.count >= nat.kernels == 25
    assert nat.displays == ("back", "bottom")
    geo = _geometry()
    pats = plan_patterns(plan, geo)
    assert len(pats) * len(geo.displays) > 64  # more slots than the OHDC-2 stores
    counts = expected_counts(schedule(plan, geo))
    # 2 cameras x 1 table angle x 2 displays x N natural images
    assert counts["envmatte"] == 2 * 1 * 2 * nat.count
    assert "calibration" not in counts  # the step builds with the simulator's true cameras


def test_demo_cli_has_the_glass_switch():
    import inspect

    from opacityhull.cli import app

    res = CliRunner().invoke(app, ["demo", "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "--with-glass" in res.output and "--no-glass" in res.output
    assert inspect.signature(run_demo).parameters["with_glass"].default is True


def test_glass_plans_say_which_viewpoints_they_relight():
    from opacityhull.acquire.plan import load_plan
    from opacityhull.acquire.schedule import natural_view_note

    demo = natural_view_note(parse_plan(tomllib.loads(GLASS_PLAN), where="demo glass plan", source="demo:glass"))
    assert demo is not None and "captured viewpoints only (one table angle)" in demo
    shipped = natural_view_note(load_plan("builtin:natural"))
    assert shipped is not None and "up to 180 deg apart" in shipped and "0.83 at 6 deg" in shipped
    assert natural_view_note(load_plan("builtin:demo")) is None  # no natural phase
