"""Environment maps: convention, solid angles, orientation (yaw, ICT probes), probe
formats, and rejection of bad radiance (NaN, Inf, negative, half overflow)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import InputError
from opacityhull.imageio import read_hdr, write_exr, write_hdr
from opacityhull.envmap import (
    EnvironmentMap,
    direction_to_uv,
    latlong_directions,
    latlong_solid_angles,
    rotate_latlong_yaw,
)
from opacityhull.relight.envmap import (
    angular_to_latlong,
    downsample_latlong,
    latlong_to_angular,
    load_envmap,
    mirrorball_to_latlong,
)


def smooth_map(h=32, w=64):
    d = latlong_directions(h, w)
    r = 1.0 + 0.5 * d[..., 0] + 0.3 * d[..., 1] ** 2
    g = 1.0 + 0.4 * d[..., 2]
    b = 0.5 + 0.5 * np.abs(d[..., 1])
    return np.stack([r, g, b], -1).astype(np.float32)


def test_texel_directions_follow_the_project_convention():
    H, W = 64, 128
    d = latlong_directions(H, W)
    # the centre column looks along +Z, a quarter to the left of it along +X (u = 0.25),
    # the seam along -Z, row 0 at the zenith
    centre = d[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].sum((0, 1))
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [0, 0, 1], atol=1e-12)
    assert d[H // 2, W // 4][0] > 0.99
    assert d[H // 2, 0][2] < -0.99 and d[H // 2, W - 1][2] < -0.99
    assert d[0, 0][1] > 0.99 and d[-1, 0][1] < -0.99
    # same formula as OpenEXR's LatLongMap::direction (written out independently)
    r, c = np.mgrid[0:H, 0:W] + 0.5
    lat = -np.pi * (r / H - 0.5)
    lon = -2 * np.pi * (c / W - 0.5)
    exr = np.stack([np.sin(lon) * np.cos(lat), np.sin(lat), np.cos(lon) * np.cos(lat)], -1)
    np.testing.assert_allclose(d, exr, atol=1e-12)


def test_convention_agrees_with_the_renderer_background():
    from opacityhull.render.background import direction_to_equirect

    d = np.random.default_rng(0).normal(size=(500, 3))
    u, v = direction_to_uv(d)
    u2, v2 = direction_to_equirect(d)
    np.testing.assert_allclose(np.c_[u, v], np.c_[u2, v2], atol=1e-12)


def test_solid_angles_are_exact_and_sum_to_4pi():
    for H, W in [(1, 2), (7, 14), (128, 256)]:
        sa = latlong_solid_angles(H, W)
        assert sa.sum() * W == pytest.approx(4 * math.pi, rel=1e-12)
    # close to the sin-theta rule for fine rows, as they should be
    H, W = 256, 512
    theta = (np.arange(H) + 0.5) * math.pi / H
    np.testing.assert_allclose(latlong_solid_angles(H, W), np.sin(theta) * (math.pi / H) * (2 * math.pi / W), rtol=1e-4)


@settings(max_examples=40, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))
def test_uv_round_trip(x, y, z):
    d = np.array([x, y, z])
    if np.linalg.norm(d) < 1e-3:
        return
    u, v = direction_to_uv(d)
    assert 0 <= u < 1 and 0 <= v <= 1
    phi, theta = 2 * np.pi * u, np.pi * v
    back = np.array([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)])
    np.testing.assert_allclose(back, d / np.linalg.norm(d), atol=1e-9)


def test_lookup_at_the_poles_and_across_the_seam():
    H, W = 8, 16
    img = np.zeros((H, W, 3), np.float32)
    img[0] = 5.0  # top row
    img[-1] = 7.0
    img[:, 0, 1] = 2.0  # first and last column meet at the seam (-Z)
    img[:, -1, 1] = 4.0
    env = EnvironmentMap(img)
    np.testing.assert_allclose(env.lookup([0, 1, 0])[0], 5.0)
    np.testing.assert_allclose(env.lookup([0, -1, 0])[0], 7.0)
    # exactly on the seam: halfway between column W-1 and column 0
    np.testing.assert_allclose(env.lookup([0, 0, -1])[1], 3.0, atol=1e-6)
    np.testing.assert_allclose(env.lookup([1e-9, 0, -1])[1], 3.0, atol=1e-5)
    np.testing.assert_allclose(env.lookup([-1e-9, 0, -1])[1], 3.0, atol=1e-5)
    assert np.all(np.isfinite(env.lookup(latlong_directions(3, 6))))
    with pytest.raises(InputError, match="zero"):
        env.lookup([0, 0, 0])


def test_whole_texel_yaw_is_exact_and_turns_plus_z_towards_plus_x():
    img = smooth_map()
    env = EnvironmentMap(img)
    rot = env.rotated(90.0)
    d = latlong_directions(32, 64).reshape(-1, 3)
    R = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float)  # R_y(90): +Z -> +X
    np.testing.assert_allclose(
        rot.lookup(d @ R.T, interpolation="nearest"), env.lookup(d, interpolation="nearest"), atol=0
    )
    np.testing.assert_allclose(rotate_latlong_yaw(img, 360.0), img)


def test_fractional_yaw_keeps_row_integrals():
    img = smooth_map()
    img[10, 5] = 1e5
    out = rotate_latlong_yaw(img, 13.7)
    np.testing.assert_allclose(out.sum(axis=1), img.sum(axis=1), rtol=1e-5)


def test_ict_probe_centre_moves_to_minus_z_with_yaw_180(probes_dir):
    raw = read_hdr(probes_dir / "grace.hdr")
    env = load_envmap(probes_dir / "grace.hdr", yaw_deg=180)
    H, W = raw.shape[:2]
    d = latlong_directions(H, W)
    # the raw image's centre column (its -Z) now sits at -Z of the project frame
    r = H // 2
    assert d[r, W // 2][2] > 0.99  # the file's centre column, +Z when read as-is
    np.testing.assert_array_equal(env.lookup([0, d[r, W // 2][1], -1], interpolation="nearest"), raw[r, W // 2])
    # every texel moved by R_y(180) exactly
    rd = d * np.array([-1, 1, -1])
    np.testing.assert_array_equal(env.lookup(rd.reshape(-1, 3), interpolation="nearest"), raw.reshape(-1, 3))
    # HDR survives: the window is ~1e5 x the median
    s = env.stats()
    assert s["dynamic_range"] > 5e4 and s["max"] == raw.max()


def test_hdr_and_float_exr_keep_a_sun_of_1e5_times_the_median(tmp_path):
    img = np.full((16, 32, 3), 1.0, np.float32)
    img[3, 7] = 1e5
    write_exr(tmp_path / "sun.exr", img)
    env = load_envmap(tmp_path / "sun.exr")
    assert env.radiance.dtype == np.float32 and env.radiance[3, 7, 0] == 1e5
    total = env.integral()
    expect = latlong_solid_angles(16, 32).sum() * 32 + (1e5 - 1) * latlong_solid_angles(16, 32)[3]
    np.testing.assert_allclose(total, expect, rtol=1e-6)
    write_hdr(tmp_path / "sun.hdr", img)
    env2 = load_envmap(tmp_path / "sun.hdr")
    assert env2.radiance[3, 7, 0] == pytest.approx(1e5, rel=1e-2)  # RGBE: 8-bit mantissa


def test_half_float_values_near_65504_load_exactly(tmp_path):
    img = np.full((8, 16, 3), 0.5, np.float32)
    img[2, 3] = 65504.0
    img[4, 4] = 65000.0
    write_exr(tmp_path / "half.exr", img, half=True)
    env = load_envmap(tmp_path / "half.exr")
    assert env.radiance[2, 3, 0] == 65504.0 and env.radiance[4, 4, 1] == float(np.float16(65000.0))
    assert np.isfinite(env.integral()).all()


def test_half_exr_with_overflow_inf_is_rejected_clearly(tmp_path):
    import OpenEXR

    a = np.full((8, 16), 1.0, np.float16)
    a[1, 2] = np.inf
    chans = {c: a.copy() for c in "RGB"}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans) as f:
        f.write(str(tmp_path / "over.exr"))
    with pytest.raises(InputError, match=r"over\.exr.*half-float.*3 Inf.*row 1, column 2.*65504"):
        load_envmap(tmp_path / "over.exr")


@pytest.mark.parametrize(
    "bad,match",
    [
        (np.nan, r"1 NaN and 0 Inf.*row 2, column 5, channel G"),
        (np.inf, r"0 NaN and 1 Inf.*row 2, column 5"),
        (-0.25, r"1 negative radiance.*-0\.25.*row 2, column 5"),
    ],
)
def test_nan_inf_and_negative_radiance_are_rejected_naming_the_file(tmp_path, bad, match):
    img = np.ones((8, 16, 3), np.float32)
    img[2, 5, 1] = bad
    write_exr(tmp_path / "bad.exr", img)
    with pytest.raises(InputError, match=r"bad\.exr.*" + match):
        load_envmap(tmp_path / "bad.exr")
    with pytest.raises(InputError, match=match):
        EnvironmentMap(img)


def test_bad_files_and_options(tmp_path):
    write_exr(tmp_path / "square.exr", np.ones((8, 8, 3), np.float32))
    with pytest.raises(InputError, match="2:1"):
        load_envmap(tmp_path / "square.exr")
    with pytest.raises(InputError, match="probe format .cube., expected one of"):
        load_envmap(tmp_path / "square.exr", probe_format="cube")
    (tmp_path / "x.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"\.exr or \.hdr"):
        load_envmap(tmp_path / "x.png")


def test_flip_u_mirrors_left_right(tmp_path):
    img = smooth_map()
    write_exr(tmp_path / "m.exr", img[:, ::-1])
    env = load_envmap(tmp_path / "m.exr", flip_u=True)
    np.testing.assert_array_equal(env.radiance, img)


def test_angular_probe_round_trip_and_debevec_axes():
    img = smooth_map(64, 128)
    ang = latlong_to_angular(img, 128)
    # Debevec's formula: the centre shows +Z, halfway to the right edge +X, to the top +Y
    env = EnvironmentMap(img)
    np.testing.assert_allclose(ang[63:65, 63:65].mean((0, 1)), env.lookup([0, 0, 1]), rtol=0.02)
    np.testing.assert_allclose(ang[63:65, 95:97].mean((0, 1)), env.lookup([1, 0, 0]), rtol=0.02)
    np.testing.assert_allclose(ang[31:33, 63:65].mean((0, 1)), env.lookup([0, 1, 0]), rtol=0.02)
    back = angular_to_latlong(ang, width=128)
    d = latlong_directions(64, 128)
    far_from_rim = d[..., 2] > -0.8  # the rim circle is the single direction -Z
    err = np.abs(back - img)[far_from_rim].max() / img.max()
    assert err < 0.02
    np.testing.assert_allclose(EnvironmentMap(back).integral(), env.integral(), rtol=0.02)


def test_mirror_ball_matches_a_physically_reflected_ball():
    img = smooth_map(64, 128)
    env = EnvironmentMap(img)
    S = 256
    c = (np.arange(S) + 0.5) / S * 2 - 1
    u, v = np.meshgrid(c, -c)
    r2 = u * u + v * v
    inside = r2 < 1
    n = np.stack([u, v, np.sqrt(np.clip(1 - r2, 0, 1))], -1)
    # camera on +Z looking down -Z: the view ray (0, 0, -1) reflects about the normal
    i = np.array([0, 0, -1.0])
    refl = i - 2 * (n @ i)[..., None] * n
    ball = np.where(inside[..., None], env.lookup(refl.reshape(-1, 3)).reshape(S, S, 3), 0).astype(np.float32)
    back = mirrorball_to_latlong(ball, width=128)
    d = latlong_directions(64, 128)
    ok = d[..., 2] > -0.5  # mirror balls resolve the back hemisphere poorly
    assert np.abs(back - img)[ok].max() / img.max() < 0.02


def test_downsampling_preserves_the_integral_exactly():
    img = smooth_map(64, 128)
    img[7, 9] = 3e4
    for f in (2, 4, 8):
        small = downsample_latlong(img, f)
        np.testing.assert_allclose(EnvironmentMap(small).integral(), EnvironmentMap(img).integral(), rtol=1e-6)
    with pytest.raises(InputError, match="divide"):
        downsample_latlong(img, 3)


def test_upper_hemisphere_integral_of_a_constant_map_is_2pi():
    for H in (8, 9, 33):
        env = EnvironmentMap(np.ones((H, 2 * H, 3), np.float32))
        np.testing.assert_allclose(env.integral(upper_only=True), 2 * math.pi, rtol=1e-9)
        np.testing.assert_allclose(env.integral(), 4 * math.pi, rtol=1e-9)
