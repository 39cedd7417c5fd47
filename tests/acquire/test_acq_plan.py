"""Plans: parsing, errors naming the key, built-ins, the schedule and its estimate."""

from __future__ import annotations

import copy
import math
from itertools import pairwise

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.acquire.plan import load_plan, parse_plan
from opacityhull.acquire.schedule import MotionRates, estimate, expected_counts, move_time_s, schedule, select_cameras
from opacityhull.errors import ConfigError
from opacityhull.riggeometry import RigGeometry

from rigkit import GEOMETRY, TINY_PLAN

PAPER_GEOMETRY = {
    "target_m": [0.0, 0.1, 0.0],
    "cameras": [
        {
            "name": f"cam{i}",
            "width": 1300,
            "height": 1030,
            "distance_m": 1.2,
            "elevation_deg": 10.0 * i,
            "azimuth_deg": 0.0,
            "fov_y_deg": 30.0,
        }
        for i in range(6)
    ],
    "lights": [{"id": i, "elevation_deg": 40.0, "azimuth_deg": 90.0 * i, "distance_m": 1.5} for i in range(4)],
    "displays": GEOMETRY["displays"],
}


def _plan(mod=None):
    d = copy.deepcopy(TINY_PLAN)
    if mod:
        mod(d)
    return parse_plan(d, where="test.toml")


def test_tiny_lab_plan_counts():
    plan = _plan()
    geo = RigGeometry.from_dict(GEOMETRY)
    counts = expected_counts(schedule(plan, geo))
    # 3 cameras; calibration 2 angles; 4 table angles; 2 pattern pairs
    assert counts == {
        "calibration": 3 * 2,
        "matting": 3 * 4 * (4 + 1) + 3 * 4 * 4,
        "lightfield": 3 * 4,
        "reflectance": 3 * 4 * 2 * 2 * 2,
    }


@pytest.mark.parametrize(
    "mod, key",
    [
        (lambda d: d["phases"].__setitem__("holography", {}), "phases.holography"),
        (lambda d: d["table"].__setitem__("steps", -4), "[table].steps"),
        (lambda d: d["table"].update({"step_deg": -5.0}) or d["table"].pop("steps"), "[table].step_deg"),
        (lambda d: d["exposures"].__setitem__("default_s", []), "[exposures].default_s"),
        (lambda d: d["phases"]["reflectance"].__setitem__("exposures_s", []), "[phases.reflectance].exposures_s"),
        (lambda d: d["phases"]["reflectance"].__setitem__("array_steps", 0), "[phases.reflectance].array_steps"),
        (lambda d: d["phases"]["matting"].__setitem__("patterns", 0), "[phases.matting].patterns"),
        (lambda d: d["phases"]["matting"].__setitem__("colour", 1), "[phases.matting]"),
        (lambda d: d["phases"]["lightfield"].__setitem__("level", 300), "[phases.lightfield].level"),
        (lambda d: d["exposures"].__setitem__("default_s", [0.1, -0.1]), "[exposures].default_s[1]"),
        (lambda d: d["phases"]["calibration"]["charuco"].__setitem__("marker_m", 0.5), "marker_m"),
        (lambda d: d["plan"].__setitem__("seed", "x"), "[plan].seed"),
        (lambda d: d.__setitem__("extras", {}), "extras"),
        (lambda d: d["plan"].__setitem__("exr_compression", "lzma"), "[plan].exr_compression"),
        (lambda d: d["phases"]["reflectance"].__setitem__("level", 0), "[phases.reflectance].level"),
    ],
)
def test_bad_plans_name_the_key(mod, key):
    with pytest.raises(ConfigError) as e:
        _plan(mod)
    assert key in str(e.value), str(e.value)
    assert "test.toml" in str(e.value) or "charuco" in str(e.value)


def test_plan_file_errors_name_the_file(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text("[plan]\nname = 'x'\n[table]\nsteps = -3\n[phases.lightfield]\n")
    with pytest.raises(ConfigError, match=r"p\.toml.*\[table\]\.steps.*> 0"):
        load_plan(p)
    p.write_text("[plan\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_plan(p)
    with pytest.raises(ConfigError, match="builtin:tiny"):
        load_plan("builtin:huge")


def test_plan_does_not_fit_rig():
    geo = RigGeometry.from_dict(GEOMETRY)
    with pytest.raises(ConfigError, match=r"\[plan\]\.cameras.*5"):
        schedule(_plan(lambda d: d["plan"].__setitem__("cameras", [0, 5])), geo)
    with pytest.raises(ConfigError, match=r"lights.*\[9\]"):
        schedule(_plan(lambda d: d["phases"]["reflectance"].__setitem__("lights", [0, 9])), geo)
    nodisp = dict(GEOMETRY, displays=[])
    with pytest.raises(ConfigError, match="matting.*displays"):
        schedule(_plan(), RigGeometry.from_dict(nodisp))


def test_schedule_order_and_stages():
    plan = _plan()
    geo = RigGeometry.from_dict(GEOMETRY)
    stages = schedule(plan, geo)
    assert [s.scene for s in stages] == ["board", "empty", "object"]
    obj = stages[2].shots
    # within a phase: table outermost, then array, then light/pattern, then camera
    refl = [s for s in obj if s.phase == "reflectance"]
    tables = [s.table_deg for s in refl]
    changes = sum(1 for a, b in pairwise(tables) if a != b)
    assert changes == len(plan.table_deg) - 1
    first_view = [s for s in refl if s.table_deg == refl[0].table_deg]
    arrays = [s.lights_deg for s in first_view]
    assert sum(1 for a, b in pairwise(arrays) if a != b) == len(plan.reflectance.array_deg) - 1
    cams = [s.camera for s in first_view[:3]]
    assert cams == [0, 1, 2]
    # consecutive sweeps alternate direction: no full return move between phases
    phases = []
    for s in obj:
        if not phases or phases[-1][0] != s.phase:
            phases.append((s.phase, []))
        if not phases[-1][1] or phases[-1][1][-1] != s.table_deg:
            phases[-1][1].append(s.table_deg)
    for (p1, a1), (p2, a2) in pairwise(phases):
        assert a1[-1] == a2[0], (p1, p2, a1, a2)
    # lightfield: lights rotate with the object
    assert all(s.lights_deg == s.table_deg for s in obj if s.phase == "lightfield")
    # keys unique, brackets of reflectance have two exposures
    keys = [s.key for st_ in stages for s in st_.shots]
    assert len(keys) == len(set(keys))
    assert all(len(s.exposures_s) == 2 for s in refl)


def test_builtins_parse_and_paper_counts():
    for name in ("tiny", "demo", "paper"):
        load_plan(f"builtin:{name}")
    paper = load_plan("builtin:paper")
    geo = RigGeometry.from_dict(PAPER_GEOMETRY)
    counts = expected_counts(schedule(paper, geo))
    views = 6 * 72
    assert counts["reflectance"] == views * 4 * 15 * 4
    assert counts["matting"] == views * (3 * 2 + 1) + views * 3 * 2
    assert counts["lightfield"] == views
    assert sum(counts.values()) > 100_000
    est = estimate(paper, geo, MotionRates())
    assert est.total_images == sum(counts.values())
    assert est.total_bytes >= est.total_images * 1300 * 1030 * 3 * 4
    # exposure time alone: every reflectance shot runs the whole bracket
    assert est.exposure_s >= views * 60 * sum(paper.reflectance.exposures_s)
    assert est.total_s > est.exposure_s + est.overhead_s


def test_tiny_on_a_six_camera_rig_uses_three_spread_cameras():
    geo = RigGeometry.from_dict(PAPER_GEOMETRY)
    assert select_cameras(load_plan("builtin:tiny"), geo) == (0, 2, 4)


def test_move_time_against_integration():
    # The fastest move under |v| <= vmax, |acc| <= a covers exactly d in T:
    # integrate the velocity profile min(a t, vmax, a (T - t)) numerically.
    import numpy as np

    for d, v, a in [(5.0, 30.0, 60.0), (90.0, 30.0, 60.0), (1.0, 30.0, 60.0), (360.0, 10.0, 5.0)]:
        T = move_time_s(d, v, a)
        t = np.linspace(0.0, T, 200_001)
        vel = np.minimum(np.minimum(a * t, v), a * (T - t))
        assert np.trapezoid(vel, t) == pytest.approx(d, rel=1e-6), (d, v, a)
        # and it is the fastest: the peak speed is the limit (trapezoid) or accel-bound (triangle)
        assert vel.max() <= v + 1e-9
    assert move_time_s(0.0, 30, 60) == 0.0


@settings(max_examples=40, deadline=None)
@given(steps=st.integers(1, 72), start=st.floats(0, 359))
def test_table_steps_even_and_distinct(steps, start):
    p = _plan(lambda d: d["table"].update({"steps": steps, "start_deg": start}))
    a = sorted(p.table_deg)
    assert len(a) == steps
    gaps = [(b - c) for c, b in pairwise(a)] + [a[0] + 360 - a[-1]]
    assert all(math.isclose(g, 360 / steps, abs_tol=1e-5) for g in gaps)


def test_step_deg_not_dividing_360():
    p = _plan(lambda d: d["table"].update({"step_deg": 100.0}) or d["table"].pop("steps"))
    assert p.table_deg == (0.0, 100.0, 200.0, 300.0)


# --------------------------------------------------------------------------- natural phase


def _natural(ph: dict, **plan):
    return parse_plan({"plan": {"name": "n", **plan}, "phases": {"natural": ph}}, where="n.toml")


def test_natural_phase_is_envmatte_one_display_at_a_time():
    from opacityhull.acquire.schedule import natural_pattern_ids

    geo = RigGeometry.from_dict(GEOMETRY)
    plan = _natural({"images": 4, "kernels": 3})
    assert plan.natural is plan.envmatte and plan.phases == ("envmatte",) and plan.name == "n"
    names = [d.name for d in geo.displays]
    ids = natural_pattern_ids(plan, geo)
    assert list(ids) == names and [len(v) for v in ids.values()] == [4] * len(names)
    shots = [s for st_ in schedule(plan, geo) for s in st_.shots]
    ncam = len(geo.cameras)
    assert len(shots) == len(plan.table_deg) * len(names) * 4 * ncam
    # the patterns of one domain are contiguous: one display's sweep, then the next
    first = [s.pattern for s in shots if s.camera == 0]
    assert first == sorted(first)
    # the older name gives the same schedule
    old = parse_plan({"plan": {"name": "n"}, "phases": {"envmatte": {"images": 4, "kernels": 3}}}, where="n.toml")
    assert [s.key for st_ in schedule(old, geo) for s in st_.shots] == [s.key for s in shots]
    # one display only
    one = _natural({"images": 4, "kernels": 3, "displays": [names[-1]]})
    assert list(natural_pattern_ids(one, geo)) == [names[-1]]
    # the dry run prices it: one upload per id on the lit display, and one black shared by
    # the ids on each other display (they all fit in the controller's 64 slots)
    from opacityhull.acquire.schedule import upload_wire_bytes

    est = estimate(one, geo, MotionRates())
    assert est.images["envmatte"] == len(plan.table_deg) * 4 * ncam
    res = {d.name: tuple(d.resolution) for d in geo.displays}
    wire = 4 * upload_wire_bytes(*res[names[-1]]) + sum(upload_wire_bytes(*res[n]) for n in names[:-1])
    assert est.uploads == 4 + len(names) - 1
    assert est.upload_s == pytest.approx(round(wire) / MotionRates().serial_bytes_s)


@pytest.mark.parametrize(
    "ph, match",
    [
        ({"images": 10}, r"\[phases\.natural\].*images = 10.*kernels = 25.*N >= K"),
        ({"images": 30, "kernels": 40}, r"kernels = 40"),
        ({"images": 30, "sources": ["sky"]}, r"\[phases\.natural\]\.sources.*'sky'"),
        ({"images": 30, "sources": ["user"]}, r"user_images"),
        ({"images": 30, "user_images": ["x.png"]}, r"user_images.*not in sources"),
        ({"images": 30, "displays": "back"}, r"\[phases\.natural\]\.displays"),
        ({"images": 30, "resolution": 3}, r"unknown key"),
    ],
)
def test_bad_natural_phases_name_the_key(ph, match):
    with pytest.raises(ConfigError, match=match) as e:
        _natural(ph)
    assert "n.toml" in str(e.value)


def test_natural_user_image_that_is_not_an_image(tmp_path):
    (tmp_path / "notes.png").write_text("not a picture")
    with pytest.raises(ConfigError, match=r"user_images\[0\].*notes\.png.*not an image"):
        parse_plan(
            {
                "plan": {"name": "n"},
                "phases": {"natural": {"images": 30, "sources": ["user", "noise"], "user_images": ["notes.png"]}},
            },
            where="n.toml",
            base_dir=tmp_path,
        )
    with pytest.raises(ConfigError, match=r"images\[0\].*missing\.png.*not found"):
        parse_plan(
            {"plan": {"name": "n"}, "phases": {"envmatte": {"images": ["missing.png"]}}},
            where="n.toml",
            base_dir=tmp_path,
        )


def test_natural_phase_on_a_rig_without_displays_or_unknown_display():
    plan = _natural({"images": 25})
    with pytest.raises(ConfigError, match=r"\[phases\.natural\] needs backdrop displays.*none"):
        schedule(plan, RigGeometry.from_dict(dict(GEOMETRY, displays=[])))
    with pytest.raises(ConfigError, match=r"\[phases\.natural\]\.displays: \['side'\] not in the rig"):
        schedule(_natural({"images": 25, "displays": ["side"]}), RigGeometry.from_dict(GEOMETRY))


def test_builtin_natural_plan():
    plan = load_plan("builtin:natural")
    assert plan.natural is not None and plan.natural.count >= plan.natural.kernels == 25
    assert plan.matting is not None and plan.lightfield is not None
