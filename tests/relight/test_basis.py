"""Light basis: directions per table angle, integration of maps onto the lights
(partition of unity, total preserved, no aliasing of a sun), poles and seams,
calibration, and the --lights parser."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import ConfigError, InputError
from opacityhull.model import OpacityHullModel
from opacityhull.relight.basis import (
    KernelConfig,
    LightSet,
    angular_spacing,
    directional_light_weights,
    integrate_envmap,
    integrate_envmap_reference,
    light_set_from_model,
    parse_lights,
    partition_weights,
)
from opacityhull.envmap import EnvironmentMap, direction_to_uv, latlong_directions
from opacityhull.relight.envmap import sun_envmap


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def dir_el_az(el_deg, az_deg):
    el, az = math.radians(el_deg), math.radians(az_deg)
    return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])


def test_light_directions_match_the_model_for_every_view(sphere_model):
    m = OpacityHullModel.open(sphere_model)
    ls = light_set_from_model(m)
    assert len(ls) == 60 and len(set(ls.keys)) == 60
    for i in (0, 3, 5, 7):
        want = np.array([m.light_direction(i, s) for s in m.light_samples])
        np.testing.assert_allclose(ls.directions_object(m.views[i].table_deg), want, atol=1e-12)
    # turning the table by +a turns the lights by -a in the object frame
    d0 = ls.directions_object(0.0)
    d90 = ls.directions_object(90.0)
    np.testing.assert_allclose(d90[:, 0], -d0[:, 2], atol=1e-12)
    np.testing.assert_allclose(d90[:, 2], d0[:, 0], atol=1e-12)
    # calibration is intensity x colour of each light
    g = m.geometry
    for k, s in enumerate(m.light_samples):
        L = g.light(s.light_id)
        np.testing.assert_allclose(ls.output_rgb[k], L.intensity * np.asarray(L.colour))


def _random_lights(seed, k):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(k, 3))
    d[:, 1] = np.abs(d[:, 1])  # an overhead array
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    k=st.integers(1, 12),
    kind=st.sampled_from(["vmf", "linear", "voronoi"]),
    lower=st.sampled_from(["drop", "nearest"]),
    width=st.floats(0.2, 1.5),
    h=st.sampled_from([4, 5, 9, 16]),
)
def test_weights_sum_to_the_integral_over_the_covered_domain(seed, k, kind, lower, width, h):
    rng = np.random.default_rng(seed + 1)
    img = rng.gamma(0.5, 1.0, size=(h, 2 * h, 3)).astype(np.float32)
    img[rng.integers(h), rng.integers(2 * h)] *= 1e4  # a sun somewhere
    env = EnvironmentMap(img)
    cfg = KernelConfig(kind=kind, lower_hemisphere=lower, width=width)
    W = integrate_envmap(env, _random_lights(seed, k), config=cfg)
    assert np.all(W >= 0)
    np.testing.assert_allclose(W.sum(0), env.integral(upper_only=(lower == "drop")), rtol=1e-9)


@pytest.mark.parametrize("kind", ["vmf", "linear", "voronoi"])
@pytest.mark.parametrize("lower", ["drop", "nearest"])
def test_fast_integration_matches_the_texel_loop(kind, lower):
    rng = np.random.default_rng(3)
    env = EnvironmentMap(rng.random((9, 18, 3)).astype(np.float32))
    L = _random_lights(5, 7)
    cfg = KernelConfig(kind=kind, lower_hemisphere=lower, width=0.7, chunk=13)  # chunks cut rows
    np.testing.assert_allclose(
        integrate_envmap(env, L, config=cfg), integrate_envmap_reference(env, L, config=cfg), rtol=1e-10, atol=1e-12
    )


def test_voronoi_cells_of_a_constant_map_are_scipys_spherical_voronoi_areas():
    from scipy.spatial import SphericalVoronoi

    rng = np.random.default_rng(11)
    L = rng.normal(size=(20, 3))
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    env = EnvironmentMap(np.ones((256, 512, 3), np.float32))
    W = integrate_envmap(env, L, config=KernelConfig(kind="voronoi", lower_hemisphere="nearest"))
    areas = SphericalVoronoi(L).calculate_areas()
    np.testing.assert_allclose(W[:, 0], areas, rtol=0.02, atol=2e-3)


def test_an_all_zero_map_gives_zero_weights():
    env = EnvironmentMap(np.zeros((16, 32, 3), np.float32))
    for kind in ("vmf", "voronoi"):
        W = integrate_envmap(env, _random_lights(0, 6), config=KernelConfig(kind=kind))
        assert W.shape == (6, 3) and np.all(W == 0)


def test_a_sun_between_two_lights_splits_smoothly_and_keeps_its_power():
    a, b = dir_el_az(30, -12), dir_el_az(30, 12)  # two lights 24 deg apart (the paper's array step)
    far = dir_el_az(80, 180)
    L = np.array([a, b, far])
    H, W = 512, 1024  # fine texels so the sun can be placed within 0.35 deg
    cfg = KernelConfig(kind="vmf", width=0.5)
    total = None
    split = []
    for az in np.linspace(-9, 9, 13):  # across the bisector (azimuth 0), 1.5 deg steps
        env = sun_envmap(H, W, dir_el_az(30, az), [1e5, 1e5, 1e5])
        w = integrate_envmap(env, L, config=cfg)[:, 0]
        tot = env.integral()[0]
        assert w.sum() == pytest.approx(tot, rel=1e-9)  # total preserved
        assert w[2] < 1e-6 * tot  # nothing leaks to the far light
        split.append(w[1] / tot)
        total = tot
    split = np.array(split)
    # at the bisector the sun is shared equally (to the texel the sun snaps to)
    assert split[6] == pytest.approx(0.5, abs=0.03)
    # the hand-over is monotonic and gradual: no 1.5 deg step carries more than 15 % of
    # the sun (the logistic width is width^2 x spacing = 5 deg here)
    assert np.all(np.diff(split) >= 0) and np.max(np.diff(split)) < 0.15
    assert split[0] < 0.2 and split[-1] > 0.8
    # Voronoi aliases: the whole sun jumps from one light to the other at the bisector
    vor = [
        integrate_envmap(sun_envmap(H, W, dir_el_az(30, az), [1e5] * 3), L, config=KernelConfig(kind="voronoi"))[1, 0]
        / total
        for az in (-0.5, 0.5)
    ]
    assert vor[0] < 1e-9 and vor[1] > 1 - 1e-9


def test_lights_exactly_at_the_pole_and_on_the_seam():
    L = np.array([[0, 1.0, 0], [0, 0.0, -1], unit([1, 0.3, 0]), unit([-1, 0.3, 0.2])])
    H, W = 64, 128
    for kind in ("vmf", "voronoi"):
        cfg = KernelConfig(kind=kind, lower_hemisphere="nearest")
        # a uniform sky: total preserved, every weight finite and > 0
        w = integrate_envmap(EnvironmentMap(np.ones((H, W, 3), np.float32)), L, config=cfg)
        assert np.all(np.isfinite(w)) and np.all(w > 0)
        np.testing.assert_allclose(w.sum(0), 4 * math.pi, rtol=1e-9)
        # a sun next to the pole goes to the pole light, a sun on the seam to the seam light
        for k, d in ((0, [1e-3, 1, 0]), (1, [0, 0, -1])):
            env = sun_envmap(H, W, d, [1.0, 2.0, 3.0])
            w = integrate_envmap(env, L, config=cfg)
            share = w[:, 2] / env.integral()[2]
            assert np.argmax(share) == k and share.sum() == pytest.approx(1.0, rel=1e-9)
            # wide vMF cells (these 4 lights are ~80 deg apart) still give it the most
            assert share[k] > (0.999 if kind == "voronoi" else 0.6)
    # the texel containing the seam direction is column 0 (u = 0)
    assert direction_to_uv([0, 0, -1])[0] == 0.0


def test_the_seam_light_collects_both_edges_of_the_map():
    L = np.array([[0, 0.2, -1.0], [0, 0.2, 1.0]])
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    img = np.zeros((16, 32, 3), np.float32)
    img[6:10, 0] = 1.0  # left edge
    img[6:10, -1] = 1.0  # right edge: the same neighbourhood of -Z
    for cfg in (
        KernelConfig(kind="vmf", width=0.1, lower_hemisphere="nearest"),
        KernelConfig(kind="voronoi", lower_hemisphere="nearest"),
    ):
        w = integrate_envmap(EnvironmentMap(img), L, config=cfg)
        assert w[0, 0] / w[:, 0].sum() > 0.999
        np.testing.assert_allclose(w[:, 0].sum(), EnvironmentMap(img).integral()[0], rtol=1e-12)


def test_vmf_tends_to_voronoi_as_the_width_shrinks():
    L = _random_lights(2, 8)
    Q = latlong_directions(32, 64).reshape(-1, 3)
    vor = partition_weights(L, Q, kind="voronoi")
    sharp = partition_weights(L, Q, kind="vmf", sigma_rad=0.01)
    assert np.mean(np.abs(sharp - vor).sum(1) > 1e-3) < 0.02  # only texels on the bisectors differ
    soft = partition_weights(L, Q, kind="vmf", sigma_rad=0.5)
    np.testing.assert_allclose(soft.sum(1), 1.0, rtol=1e-12)
    assert np.all(np.isfinite(partition_weights(L, Q, kind="vmf", sigma_rad=1e-6)))  # no overflow


def test_spacing_of_the_paper_array():
    from opacityhull.relight.synthetic import sphere_rig
    from opacityhull.riggeometry import RigGeometry

    rig, positions = sphere_rig(n_lights=4, n_positions=15, calibrated=False)
    g = RigGeometry.from_dict(rig)
    d = np.array([g.light_direction_object(L.id, 0.0, b) for b in positions for L in g.lights])
    sp = math.degrees(angular_spacing(d))
    assert 10 < sp < 25  # 24 deg array steps, shrinking towards the zenith


def test_directional_lights_use_the_same_partition():
    L = _random_lights(4, 10)
    cfg = KernelConfig(kind="vmf", width=0.5, lower_hemisphere="nearest")
    d = unit([0.3, 0.5, 0.2])
    w = directional_light_weights(L, [d], [[1.0, 2.0, 3.0]], config=cfg)
    np.testing.assert_allclose(w.sum(0), [1, 2, 3], rtol=1e-12)
    # the limit of a tiny sun of the same irradiance in that direction
    H, W = 1024, 2048
    env = sun_envmap(H, W, d, [1.0, 1.0, 1.0])
    ws = integrate_envmap(
        env, L, config=KernelConfig(kind="vmf", width=0.5, lower_hemisphere="nearest", max_map_width=4096)
    )
    np.testing.assert_allclose(ws[:, 0] / ws[:, 0].sum(), w[:, 0] / w[:, 0].sum(), atol=0.02)
    # a light below the table is dropped by default
    assert np.all(directional_light_weights(L, [[0, -1, 0]], [[1, 1, 1]]) == 0)
    # exactly on a captured direction with Voronoi cells: all to that light
    w = directional_light_weights(
        L, L[3:4], [[1, 1, 1]], config=KernelConfig(kind="voronoi", lower_hemisphere="nearest")
    )
    assert w[3, 0] == 1.0 and w.sum() == 3.0


@pytest.mark.parametrize("kind", ["vmf", "linear", "voronoi"])
def test_coincident_lights_share_their_cell(kind):
    """A light on the array axis (the zenith) is at the same place at every array
    angle: its duplicates split the cell equally, nothing else changes."""
    ring = [dir_el_az(40, az) for az in range(0, 360, 45)]
    zen = [[0, 1.0, 0]] * 6
    L = np.array(ring + zen)
    rng = np.random.default_rng(2)
    env = EnvironmentMap(rng.random((16, 32, 3)).astype(np.float32))
    cfg = KernelConfig(kind=kind)
    w = integrate_envmap(env, L, config=cfg)
    single = integrate_envmap(env, np.array(ring + zen[:1]), config=cfg)
    np.testing.assert_allclose(w[:8], single[:8], rtol=1e-12)
    np.testing.assert_allclose(w[8:], np.repeat(single[8:] / 6, 6, axis=0), rtol=1e-12)
    np.testing.assert_allclose(w.sum(0), env.integral(upper_only=True), rtol=1e-9)
    d = directional_light_weights(L, [[0, 1, 0]], [[6.0, 6.0, 6.0]], config=cfg)
    np.testing.assert_allclose(d[8:], 1.0, rtol=1e-5)  # vMF leaks 1e-6 to the ring
    np.testing.assert_allclose(d.sum(0), 6.0, rtol=1e-12)


def test_parse_lights():
    d, e = parse_lights("0,1,0,1,1,1; 1,0,0,0.5,0.2,0.1;point:0,2,0,4,4,4")
    np.testing.assert_allclose(d, [[0, 1, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_allclose(e, [[1, 1, 1], [0.5, 0.2, 0.1], [1, 1, 1]])  # 4 / 2^2
    with pytest.raises(InputError, match=r"--lights: light 2 '1,2' has 2 values"):
        parse_lights("0,1,0,1,1,1;1,2")
    with pytest.raises(InputError, match="zero direction"):
        parse_lights("0,0,0,1,1,1")
    with pytest.raises(InputError, match="negative"):
        parse_lights("0,1,0,-1,1,1")
    with pytest.raises(InputError, match="not six numbers"):
        parse_lights("a,b,c,d,e,f")
    with pytest.raises(InputError, match="no lights"):
        parse_lights(" ; ")


def test_light_set_and_config_validation():
    with pytest.raises(ConfigError, match="channel B <= 0"):
        LightSet(("a",), [0], [0.0], [[0, 1, 0]], [[1.0, 1.0, 0.0]])
    with pytest.raises(ConfigError, match="kind"):
        KernelConfig(kind="gauss")
    with pytest.raises(ConfigError, match="width"):
        KernelConfig(width=0)
    with pytest.raises(ConfigError, match="lower_hemisphere"):
        KernelConfig(lower_hemisphere="up")
