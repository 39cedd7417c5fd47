"""A plan's light array against the sphere split (#30): a plan whose one-light shots
light no direction outside its natural phase's displays is refused (named error, exit 2,
nothing written); a plan's ``lamp_radius_m`` is fitted by the simulator and must already
be in a physical rig's TOML."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from helpers import invoke_cli as invoke

from opacityhull.acquire.plan import load_plan, parse_plan
from opacityhull.acquire.schedule import array_coverage, lamps_for_plan, require_array_coverage, schedule
from opacityhull.errors import ConfigError
from opacityhull.riggeometry import RigGeometry
from opacityhull.sim.simrig import sim_rig_config


def flat(text: str) -> str:
    return " ".join(text.split())


@pytest.fixture(scope="module")
def geometry():
    return RigGeometry.from_dict(sim_rig_config(None)["geometry"])


def _plan(*, array_deg, lights=(0,), displays=("back",), steps=1, radius=None):
    refl = {"array_deg": list(array_deg), "lights": list(lights), "level": 255}
    if radius is not None:
        refl["lamp_radius_m"] = radius
    return parse_plan(
        {
            "plan": {"name": "cover", "seed": 1, "cameras": [1]},
            "table": {"steps": steps},
            "exposures": {"default_s": [0.8]},
            "phases": {
                "reflectance": refl,
                "natural": {"images": 4, "kernels": 4, "sources": ["noise"], "displays": list(displays)},
            },
        },
        where="cover.toml",
    )


def _hits_back(geometry, direction) -> bool:
    """Independent test of the back panel: the ray from the aim point meets the plane
    z = centre_z within the rectangle (the back panel is fixed and faces +z)."""
    d = geometry.display("back")
    o = np.asarray(geometry.target_m, float)
    t = (d.centre_m[2] - o[2]) / direction[2]
    p = o + t * direction
    w, h = d.size_m
    return bool(t > 0 and abs(p[0] - d.centre_m[0]) <= w / 2 and abs(p[1] - d.centre_m[1]) <= h / 2)


def test_coverage_matches_a_direct_ray_test_of_the_back_panel(geometry):
    # light 0 (elevation 30 on the +X arc) swept round the array: inside the back panel
    # around array angle 90 (the lamp is then behind the panel), outside elsewhere
    angles = [float(a) for a in range(0, 360, 15)]
    cov = array_coverage(_plan(array_deg=angles), geometry)
    assert cov is not None and cov.displays == ("back",) and len(cov.shots) == len(angles)
    o = np.asarray(geometry.target_m, float)
    want = []
    for _, ad, _ in cov.shots:
        v = geometry.light(0).position_rig(ad) - o
        want.append(not _hits_back(geometry, v / np.linalg.norm(v)))
    assert list(cov.outside) == want
    assert 0 < cov.n_covering < len(angles)  # both cases occur


def test_no_coverage_without_both_phases(geometry):
    nat_only = parse_plan(
        {"plan": {"name": "n"}, "phases": {"natural": {"images": 4, "kernels": 4, "displays": ["back"]}}}, where="n"
    )
    assert array_coverage(nat_only, geometry) is None
    assert array_coverage(load_plan("builtin:demo"), geometry) is None  # no natural phase


def test_a_light_array_inside_the_displays_is_refused(geometry):
    plan = _plan(array_deg=[90.0])
    with pytest.raises(ConfigError, match=r"covers no direction of the light array's share.*\['back'\]"):
        require_array_coverage(plan, geometry)
    with pytest.raises(ConfigError, match="covers no direction"):
        schedule(plan, geometry)
    # a 20 cm lamp there (12 degrees across) is still wholly inside the panel
    with pytest.raises(ConfigError, match="covers no direction"):
        schedule(
            _plan(array_deg=[90.0], radius=0.2),
            lamps_for_plan(_plan(array_deg=[90.0], radius=0.2), geometry, can_fit=True),
        )
    # one position outside is enough
    cov = require_array_coverage(_plan(array_deg=[0.0, 90.0]), geometry)
    assert cov is not None and cov.n_covering == 1
    # the shipped natural plan: the two lowest lamps are behind the back panel at 4 and 2
    # of its 15 array angles (x 2 table angles); every other position lights the share
    cov = require_array_coverage(load_plan("builtin:natural"), geometry)
    assert cov is not None and len(cov.shots) == 120 and cov.n_covering == 108


def test_a_lamp_with_area_covers_the_share_from_its_rim(geometry):
    # a lamp just outside the back panel's top edge as a point; big enough, its disc
    # still pokes out, and pushed inside the panel, only its rim does
    o = np.asarray(geometry.target_m, float)
    back = geometry.display("back")
    top = back.centre_m + np.array([0.0, back.size_m[1] / 2, 0.0])
    v = top - o
    el_top = math.degrees(math.atan2(v[1], -v[2]))
    raw = geometry.to_dict()
    for el, radius, outside in ((el_top - 3.0, None, False), (el_top - 3.0, 0.2, True)):
        g = RigGeometry.from_dict(
            {
                **raw,
                "lights": [
                    {"id": 0, "elevation_deg": el, "azimuth_deg": 180.0, "distance_m": 1.0}
                    | ({} if radius is None else {"radius_m": radius})
                ],
            }
        )
        cov = array_coverage(_plan(array_deg=[0.0]), g)
        assert cov is not None and cov.outside == (outside,), (el, radius)


def test_lamp_radius_is_parsed_and_fitted(geometry):
    plan = _plan(array_deg=[0.0], radius=0.2)
    assert plan.reflectance is not None and plan.reflectance.lamp_radius_m == 0.2
    fitted = lamps_for_plan(plan, geometry, can_fit=True)
    assert all(L.radius_m == 0.2 for L in fitted.lights)
    assert all(L["radius_m"] == 0.2 for L in fitted.to_dict()["lights"])  # what the session records
    assert [c.name for c in fitted.cameras] == [c.name for c in geometry.cameras]
    assert lamps_for_plan(plan, fitted, can_fit=False) is fitted  # the TOML already says it
    assert lamps_for_plan(_plan(array_deg=[0.0]), geometry, can_fit=False) is geometry
    with pytest.raises(ConfigError, match=r"lamp_radius_m = 0.2 m but the rig's lamps are points \(no radius_m\)"):
        lamps_for_plan(plan, geometry, can_fit=False)
    for bad in (0.0, -0.1, float("nan"), float("inf"), "big"):
        with pytest.raises(ConfigError, match=r"\[phases.reflectance\].lamp_radius_m"):
            _plan(array_deg=[0.0], radius=bad)


PLAN_INSIDE = """
[plan]
name = "inside"
cameras = [1]
[table]
steps = 1
[exposures]
default_s = [0.8]
[phases.reflectance]
array_deg = [90.0]
lights = [0]
{extra}
[phases.natural]
images = 4
kernels = 4
sources = ["noise"]
displays = ["back"]
"""


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("", r"covers no direction of the light array's share"),
        ("lamp_radius_m = 0.2", r"covers no direction of the light array's share"),
        ("lamp_radius_m = nan", r"\[phases.reflectance\].lamp_radius_m: expected a finite number"),
        ("lamp_radius_m = 0.0", r"\[phases.reflectance\].lamp_radius_m: expected a lamp radius > 0"),
    ],
    ids=["points", "area", "nan", "zero"],
)
@pytest.mark.parametrize("dry", [False, True], ids=["capture", "dry-run"])
def test_cli_refuses_a_light_array_that_covers_nothing(tmp_path, extra, message, dry):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN_INSIDE.format(extra=extra))
    out = tmp_path / "S"
    argv = ["capture", "--rig", "sim:builtin:glass", "--plan", str(plan)] + (
        ["--dry-run"] if dry else ["--out", str(out)]
    )
    r = invoke(argv)
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert "plan.toml" in flat(r.stderr)
    assert re.search(message, flat(r.stderr)), r.stderr
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("lights = 0", r"\[phases.reflectance\].lights: a light count must be > 0"),
        ("lights = []", r"\[phases.reflectance\].lights: expected \"all\" or a non-empty list"),
        ("array_deg = []", r"\[phases.reflectance\].array_deg: expected a non-empty list"),
        ("array_steps = 0", r"\[phases.reflectance\].array_steps: must be > 0"),
    ],
    ids=["zero-lights", "empty-lights", "no-array-angles", "zero-array-steps"],
)
def test_cli_refuses_zero_lights_or_array_positions(tmp_path, line, message):
    key = line.split()[0]
    body = PLAN_INSIDE.format(extra="").replace("array_deg = [90.0]\nlights = [0]\n", line + "\n")
    if key == "array_deg" or key == "array_steps":
        body = body.replace(line + "\n", line + "\nlights = [0]\n")
    plan = tmp_path / "plan.toml"
    plan.write_text(body)
    r = invoke(["capture", "--rig", "sim:builtin:glass", "--plan", str(plan), "--out", str(tmp_path / "S")])
    assert r.exit_code == 2, r.output
    assert re.search(message, flat(r.stderr)), r.stderr
    assert not (tmp_path / "S").exists()
