"""Effect selection: which integrator, depth, emitters and samples each scene and phase gets."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from opacityhull.cli import app
from opacityhull.errors import ConfigError
from opacityhull.sim.effects import PHASES, reference_effects, select_effects
from opacityhull.sim.render import SimState, phase_for_state
from opacityhull.sim.scenes import builtin_names, load_scene

CAPTURE_PHASES = ("matting", "lightfield", "reflectance", "envmatte")


@pytest.fixture(scope="module")
def scenes():
    return {n: load_scene(f"builtin:{n}") for n in builtin_names()}


def test_diffuse_under_lights_is_direct_lighting_only(scenes):
    for name in ("diffuse", "sphere"):
        for phase in ("reflectance", "lightfield"):
            cfg = select_effects(scenes[name], phase)
            assert cfg.integrator == "direct" and cfg.max_depth == 2


@pytest.mark.parametrize("phase", CAPTURE_PHASES)
def test_glass_is_deeper_than_diffuse(scenes, phase):
    glass = select_effects(scenes["glass"], phase)
    diffuse = select_effects(scenes["diffuse"], phase)
    assert glass.integrator == "path"
    assert glass.max_depth >= 3, "PITFALLS: direct lighting leaves glass black"
    assert glass.max_depth > diffuse.max_depth


@pytest.mark.parametrize("phase", ("reflectance", "lightfield", "envmatte"))
def test_glossy_gets_a_few_bounces(scenes, phase):
    g = select_effects(scenes["glossy"], phase)
    d = select_effects(scenes["diffuse"], phase)
    assert g.integrator == "path" and 3 <= g.max_depth < select_effects(scenes["glass"], phase).max_depth
    assert g.max_depth > d.max_depth


def test_matting_has_no_light_array_emitters(scenes):
    for name, s in scenes.items():
        for phase in ("matting", "envmatte"):
            cfg = select_effects(s, phase)
            assert "light_array" not in cfg.emitters and "displays" in cfg.emitters, (name, phase)


def test_light_phases_have_no_display_emitters_but_keep_the_panels(scenes):
    for name, s in scenes.items():
        for phase in ("lightfield", "reflectance"):
            cfg = select_effects(s, phase)
            assert "displays" not in cfg.emitters and "displays" in cfg.shapes
            if name == "glass":  # smooth glass on black panels: point lights show nothing
                assert cfg.emitters == () and cfg.skipped == ("light_array",)
            else:
                assert cfg.emitters == ("light_array",) and cfg.skipped == ()


def test_delta_only_objects_skip_the_light_array_and_the_reference_checks_it(scenes, tmp_path):
    """Smooth glass and polished metal alone: no light pass; the reference still renders
    the lights (to measure that claim); a rough or diffuse part brings them back."""
    assert scenes["glass"].delta_only and not scenes["glossy"].delta_only
    ref = reference_effects(scenes["glass"], "lightfield", spp=16)
    assert ref.emitters == ("light_array",) and ref.skipped == ()
    p = tmp_path / "mirror_and_clay.toml"
    body = ('[materials.mirror]\ntype = "conductor"\n[materials.clay]\ntype = "diffuse"\n'
            '[[objects]]\nname = "a"\nshape = "sphere"\nmaterial = "mirror"\nradius_m = 0.05\n')
    p.write_text(body)
    assert select_effects(load_scene(p), "reflectance").emitters == ()
    p.write_text(body + '[[objects]]\nname = "b"\nshape = "disk"\nmaterial = "clay"\nradius_m = 0.1\n')
    assert select_effects(load_scene(p), "reflectance").emitters == ("light_array",)


def test_groundtruth_is_object_only_aov(scenes):
    for s in scenes.values():
        cfg = select_effects(s, "groundtruth")
        assert cfg.integrator == "aov" and cfg.emitters == () and cfg.shapes == ("object",)
        assert cfg.sampler == "stratified"


def test_calibration_renders_the_board_directly(scenes):
    for s in scenes.values():
        cfg = select_effects(s, "calibration")
        assert cfg.integrator == "direct" and "board" in cfg.shapes and cfg.error_metric == "corner_px"


def test_every_selection_explains_itself_and_states_a_bound(scenes):
    for s in scenes.values():
        for phase in PHASES:
            cfg = select_effects(s, phase)
            assert cfg.reasons and all(isinstance(r, str) and r for r in cfg.reasons)
            assert cfg.error_bound > 0 and cfg.phase == phase
            if cfg.sampler == "stratified":
                assert round(cfg.spp ** 0.5) ** 2 == cfg.spp, "stratified spp must be a square"


def test_reference_is_full_path_tracing(scenes):
    ref = reference_effects(scenes["glass"], "matting", spp=128)
    assert (ref.integrator, ref.max_depth, ref.spp) == ("path", 16, 128)
    assert ref.emitters == select_effects(scenes["glass"], "matting").emitters


def test_overrides_apply_and_are_recorded(scenes):
    cfg = select_effects(scenes["diffuse"], "reflectance", overrides={"spp": 1, "integrator": "path", "max_depth": 5})
    assert (cfg.spp, cfg.integrator, cfg.max_depth) == (1, "path", 5)
    assert any("override" in r and "spp" in r for r in cfg.reasons)
    assert select_effects(scenes["glass"], "matting", overrides={"integrator": "direct"}).max_depth == 2


@pytest.mark.parametrize("overrides,needle", [
    ({"bounces": 3}, "bounces"),
    ({"integrator": "bdpt"}, "bdpt"),
    ({"spp": 0}, "spp"),
    ({"resolution_scale": -1}, "resolution_scale"),
])
def test_bad_overrides_raise(scenes, overrides, needle):
    with pytest.raises(ConfigError, match=needle):
        select_effects(scenes["diffuse"], "matting", overrides=overrides)


def test_unknown_phase_raises(scenes):
    with pytest.raises(ConfigError, match="phase 'olat'"):
        select_effects(scenes["diffuse"], "olat")


def test_phase_is_inferred_from_the_rig_state():
    pat = np.full((4, 4, 3), 200, np.uint8)
    black = np.zeros((4, 4, 3), np.uint8)
    assert phase_for_state(SimState(content="board", light_levels={0: 255})) == "calibration"
    assert phase_for_state(SimState(displays={"back": pat})) == "matting"
    assert phase_for_state(SimState(light_levels={1: 255})) == "reflectance"
    assert phase_for_state(SimState(light_levels={1: 255, 2: 10})) == "lightfield"
    assert phase_for_state(SimState(light_levels={1: 255}, displays={"back": pat})) == "lightfield"
    assert phase_for_state(SimState(light_levels={1: 255}, displays={"back": black})) == "reflectance"
    assert phase_for_state(SimState(light_levels={1: 0})) == "matting"


def test_cli_explain_json():
    r = CliRunner().invoke(app, ["sim", "explain", "--scene", "builtin:glass", "--phase", "matting", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout.strip().splitlines()[-1])
    assert {"integrator", "max_depth", "spp", "emitters", "reasons"} <= set(d)
    assert d["integrator"] == "path" and d["max_depth"] >= 3 and d["emitters"] == ["displays"]
    r2 = CliRunner().invoke(app, ["sim", "explain", "--scene", "builtin:diffuse", "--phase", "reflectance", "--json"])
    d2 = json.loads(r2.stdout.strip().splitlines()[-1])
    assert d2["integrator"] == "direct" and d2["max_depth"] < d["max_depth"]
    assert d2["emitters"] == ["light_array"]


def test_cli_explain_bad_phase_exits_2():
    r = CliRunner().invoke(app, ["sim", "explain", "--scene", "builtin:glass", "--phase", "nap"])
    assert r.exit_code == 2
    assert "nap" in r.output


def test_non_square_spp_override_switches_to_independent_samples(scenes):
    cfg = select_effects(scenes["sphere"], "reflectance", overrides={"spp": 5})
    assert cfg.spp == 5 and cfg.sampler == "independent"
    assert select_effects(scenes["sphere"], "reflectance", overrides={"spp": 9}).sampler == "stratified"


def test_cli_explain_reports_expected_cost_and_variant(monkeypatch):
    from opacityhull.sim import variants as V

    monkeypatch.setenv(V.ENV_VARIANT, "scalar_rgb")  # no probe; the report says where the choice came from
    r = CliRunner().invoke(app, ["sim", "explain", "--scene", "builtin:diffuse", "--phase", "matting", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout.strip().splitlines()[-1])
    assert d["variant"]["variant"] == "scalar_rgb" and d["variant"]["gpu"] is False
    assert "environment" in d["variant"]["source"]
    assert d["crop"] is True and d["backdrop_spp"] == 16
    assert set(d["expected_cost"]) == {"vs_reference", "measured"}
    if d["expected_cost"]["vs_reference"] is not None:
        assert 0 < d["expected_cost"]["vs_reference"] < 1


def test_measured_cost_table_matches_the_scene_kinds(scenes):
    """Every measured (scene, phase) names a built-in whose kind is recorded correctly, so
    a custom scene of the same kind inherits the right figure."""
    from opacityhull.sim.effects import _BUILTIN_KIND, MEASURED_COST, expected_cost, scene_kind

    for (name, phase), ratio in MEASURED_COST.items():
        sc = load_scene(f"builtin:{name}")
        assert _BUILTIN_KIND[(name, phase)] == scene_kind(sc, phase)
        assert expected_cost(sc, phase)["vs_reference"] == ratio
    assert scene_kind(scenes["glass"], "matting") == "transmissive"
    assert scene_kind(scenes["glass"], "calibration") == "board"


def test_backdrop_shots_use_fewer_samples_but_the_reference_keeps_its_own(scenes):
    from opacityhull.sim.effects import BACKDROP_SPP, backdrop_only_effects

    sel = select_effects(scenes["diffuse"], "matting")
    b = backdrop_only_effects(sel)
    assert (b.integrator, b.max_depth, b.spp, b.crop) == ("path", 1, BACKDROP_SPP, False)
    ref = reference_effects(scenes["diffuse"], "matting", spp=256)
    assert backdrop_only_effects(ref).spp == 256
    low = select_effects(scenes["diffuse"], "matting", overrides={"spp": 4})
    assert backdrop_only_effects(low).spp == 4  # never more than the shot itself
