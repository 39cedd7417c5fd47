"""The glass relit under a whole environment (#30), end to end on the simulated rig:
capture with the shipped plan's light array (lamps of 0.2 m radius, 4 x 15 array angles)
and two display domains, build, and ``eval relight`` against Mitsuba under uffizi — the
display fields for the directions the displays cover, the one-light images for the rest
(the sphere split).

Thresholds: see the constants (measured on this plan, seeds fixed, CI scale 0.5; 2 min
under a load of 20 on the 2-core machine, hence ``slow``).
"""

from __future__ import annotations

from pathlib import Path

import pytest

import simcache

pytestmark = pytest.mark.slow

SCALE = 0.5
PLAN = (Path(__file__).parent / "glass_relit_plan.toml").read_text()

#: uffizi on this plan measured 0.43 (views 0 and 90 degrees; the display half 0.30 with the
#: field grown into low-α glass at the outline, 0.33 before; the array half 0.51). The full builtin:natural plan's 4 views spread 0.22-0.44 about their
#: mean 0.32 (benchmarks/out/glass.md): allow that spread, +0.12, above the figure here.
REL_ERR_MAX = 0.55
#: the light-array half against the truth outside the displays: black (point lamps) is
#: exactly 1.0 and 2.5 cm lamps measured 1.64 (a cell's light in a sparkle); measured 0.51
#: with the plan's 0.2 m lamps — require it well below black.
ARRAY_REL_ERR_MAX = 0.7


@pytest.fixture(scope="module")
def evaluated():
    from opacityhull.evaluate.relight import eval_relight
    from opacityhull.relight.runner import builtin_envmap

    plan = simcache.root() / "glass_relit_plan.toml"
    if not plan.is_file() or plan.read_text() != PLAN:
        plan.write_text(PLAN)
    model = simcache.built("glass", plan, SCALE, hull_res=64, cameras="groundtruth", optimize="none")
    return eval_relight(model, envmap=builtin_envmap("uffizi"), spp=32, write_images=False)


def test_glass_relit_under_uffizi(evaluated):
    ev = evaluated
    nat = ev["natural"]
    assert ev["n_lights_captured"] == 60
    assert ev["rel_err_mean"] <= REL_ERR_MAX
    assert nat["array_part_rel_err_mean"] <= ARRAY_REL_ERR_MAX
