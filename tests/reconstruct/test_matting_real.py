"""Two-backdrop matting of real photographs with photometric drift correction, the drift
estimate against synthetic ground truth, and ``opacityhull matte``.

Real data: tests/data/real/matting-flowers (a bouquet in a glass vase in front of a light
and a dark cloth, the cloths alone; JPEG, downscaled to 640×960, see SOURCE.txt).
Without correction the backdrop shots drift against the object shots (exposure ×0.95,
white balance ×(0.82, 0.96, 1.28), varying over the frame by ±10 %): only 53 % of the
pure-backdrop band (left quarter, top 60 %) gets alpha < 0.05 and 40 % of the frame is
fractional. Measured with ``drift="field"`` (default of ``opacityhull matte``; figures
from ``benchmarks/matting_real.py``, ``benchmarks/out/matting_real.md``):

=========================  ===========  ===========  ==============
                           640×960      640×960      no correction
                           field+flow   field only
band alpha < 0.05          99.04 %      98.90 %      53 %
band minus the leaf tip    99.95 %      99.80 %      55 %
band alpha p99             0.05         0.05         0.23
frame fractional           9.9 %        10.2 %       40 %
=========================  ===========  ===========  ==============

The band is not pure backdrop at the vendored framing: the tip of the leftmost leaf
(rows 527-552, columns 91-159 at 640×960) reaches into it and is rightly opaque (829
pixels at alpha >= 0.05, connected to opaque ones), which caps the raw band statistic at
99.10 %. What the gain field alone leaves (183 pixels outside the leaf box; 278 with
the field of before, ``field_sigma_rel`` 0.004: 98.79 %) lies along a cloth fold near
the left edge that moved between backdrop shot A and object shot A: the non-rigid
registration (``DriftOptions.flow``) takes the motion and the finer field the changed
shading, leaving 47. The test asserts >= 99 % on the raw band. The margin, measured
under one-at-a-time perturbations of the parameters around the default (field_sigma_rel
0.0025 / 0.0035, flow_sigma_px 0.7 / 1.5, flow_prior 0.5 / 2, flow_iters 10, rounds 4,
object_margin_rel 0.003 / 0.006): 99.012 - 99.047 %, i.e. 11 to 43 pixels to spare; the
band minus the leaf tip stays >= 99.92 % (asserted >= 99.9 %). Global per-channel gain or 3×3 + offset models
reach only 64 % / 69 % of the band (the drift varies over the frame: the lighting changed
the fold shading), which is why ``opacityhull matte`` defaults to the gain field.

Opaque regions, chosen by inspection of the photographs: a stem inside the vase (seen
through glass and water, so the matte there is a little below 1), the white
chrysanthemum's head and the pink gerbera's petals; and the opaque pixels of the leaf tip in the band. Their
medians and 5th percentiles must stay high, and the drift correction must not move them
by more than 0.02 (it only changes the backdrop estimate, to which opaque pixels are
insensitive).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from opacityhull.cli import app
from opacityhull.errors import InputError, ShapeError
from opacityhull.imageio import read_png
from opacityhull.reconstruct.matting import (
    DriftOptions,
    MattingOptions,
    correct_photometric_drift,
    estimate_backdrop_flow,
    object_support,
    shift_image,
    solve_matte,
    warp_image,
)

DATA = Path(__file__).resolve().parents[1] / "data" / "real" / "matting-flowers"
PAIRS = [("flowers-compA.jpg", "flowers-backA.jpg"), ("flowers-compB.jpg", "flowers-backB.jpg")]

# regions at 640x960 (rows y0:y1, columns x0:x1), by inspection
LEAF_TIP = (520, 560, 85, 160)
OPAQUE = {
    "stem_in_vase": ((710, 864, 374, 386), 0.90, 0.85),
    "chrysanthemum": ((212, 242, 355, 420), 0.95, 0.85),
    "gerbera": ((282, 308, 318, 352), 0.90, 0.75),
}


@pytest.fixture(scope="module")
def flowers():
    C = np.stack([read_png(DATA / c) for c, _ in PAIRS])
    B = np.stack([read_png(DATA / b) for _, b in PAIRS])
    assert C.shape == (2, 960, 640, 3)
    return C, B


@pytest.fixture(scope="module")
def mattes(flowers):
    C, B = flowers
    return {
        "field": solve_matte(C, B, options=MattingOptions(drift="field")),
        "noflow": solve_matte(C, B, options=MattingOptions(drift="field", drift_options=DriftOptions(flow=False))),
        "none": solve_matte(C, B),
    }


def _band(a):
    H, W = a.shape
    return a[: int(0.6 * H), : W // 4]


def _band_minus_leaf(a):
    keep = np.ones(a.shape, bool)
    y0, y1, x0, x1 = LEAF_TIP
    keep[y0:y1, x0:x1] = False
    return _band(a)[_band(keep)]


def test_real_backdrop_band_is_clear(mattes):
    a, a0 = mattes["field"].alpha, mattes["none"].alpha
    # the drift is real: uncorrected, about half of the band shows the cloth
    assert np.mean(_band(a0) < 0.05) < 0.6
    # the moved cloth fold: the gain field alone stays under 99 %, the flow clears it
    assert np.mean(_band(mattes["noflow"].alpha) < 0.05) < 0.99 <= np.mean(_band(a) < 0.05)
    clean = _band_minus_leaf(a)
    assert np.mean(clean < 0.05) >= 0.999
    assert np.percentile(clean, 99) < 0.05
    fractional = np.mean((a >= 0.05) & (a <= 0.95))
    assert fractional < 0.15 < np.mean((a0 >= 0.05) & (a0 <= 0.95))


@pytest.mark.parametrize("name", sorted(OPAQUE))
def test_real_petals_and_stems_stay_opaque(mattes, name):
    (y0, y1, x0, x1), min_median, min_p5 = OPAQUE[name]
    r = mattes["field"].alpha[y0:y1, x0:x1]
    r0 = mattes["none"].alpha[y0:y1, x0:x1]
    assert np.median(r) > min_median
    assert np.percentile(r, 5) > min_p5
    assert abs(np.median(r) - np.median(r0)) < 0.02
    assert abs(np.median(r) - np.median(mattes["noflow"].alpha[y0:y1, x0:x1])) < 0.01


def test_real_leaf_tip_in_the_band_stays_opaque(mattes):
    """The thin serrated leaf tip fills only part of its box: count its opaque pixels."""
    y0, y1, x0, x1 = LEAF_TIP
    r, r0 = mattes["field"].alpha[y0:y1, x0:x1], mattes["none"].alpha[y0:y1, x0:x1]
    assert np.sum(r > 0.9) > 400 and np.sum(r > 0.9) >= 0.9 * np.sum(r0 > 0.9)
    assert np.median(r[r > 0.5]) > 0.93


def test_real_drift_report(mattes):
    rep = mattes["field"].drift
    assert rep is not None and rep.mode == "field" and len(rep.shots) == 2
    g0, g1 = np.array(rep.shots[0].gain), np.array(rep.shots[1].gain)
    # pair A: an exposure change of ~5 %, nearly neutral
    assert 0.93 < g0.mean() < 0.97 and np.ptp(g0) < 0.02
    # pair B: a white-balance change, blue up and red down
    assert g1[2] / g1[0] > 1.4 and 0.95 < g1[1] < 1.0
    for s in rep.shots:
        assert s.residual_after < 0.5 * s.residual_before
        assert s.shift_px is not None and np.hypot(*s.shift_px) < 0.5 and not s.shift_applied
        assert 0.5 < s.fit_fraction < 0.95
        # the flow is sub-pixel where it matters and clipped at flow_max_px
        assert 0.1 < s.flow_px_p50 < 1.0 and s.flow_px_p99 <= 2.0 + 1e-6
    assert mattes["noflow"].drift.shots[0].flow_px_p50 is None
    json.dumps(rep.to_dict())  # plain data for report.json


# --------------------------------------------------------------------------- synthetic


def _scene(H=48, W=64, seed=0):
    """Two smooth, different backdrops (analytic, so shifts are exact), an opaque disk
    and a ring of alpha 0.5; returns (alpha, F, backdrop function)."""
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * np.pi, (2, 3))

    def backdrop(k, dx=0.0, dy=0.0):
        y, x = np.mgrid[0:H, 0:W].astype(np.float64)
        x, y = x - dx, y - dy
        base = 0.6 if k == 0 else 0.1
        # a different frequency per channel, so the channels (and 1) are independent
        return np.stack(
            [base + 0.25 * base * np.sin((0.31 + 0.07 * c) * x + (0.23 - 0.05 * c) * y + ph[k, c]) for c in range(3)],
            -1,
        )

    y, x = np.mgrid[0:H, 0:W]
    r = np.hypot(x - W * 0.6, y - H * 0.5)
    alpha = np.where(r < 0.18 * H, 1.0, np.where(r < 0.24 * H, 0.5, 0.0))
    F = np.broadcast_to(np.array([0.8, 0.3, 0.2]), (H, W, 3))
    return alpha, F, backdrop


def _observe(alpha, F, Bk):
    return (alpha[..., None] * F + (1 - alpha[..., None]) * Bk).astype(np.float32)


FAST = DriftOptions(rounds=2, register=False)


@settings(max_examples=12, deadline=None)
@given(g=st.tuples(*[st.floats(0.7, 1.4)] * 3), h=st.tuples(*[st.floats(0.7, 1.4)] * 3))
def test_gain_recovered_for_any_drift(g, h):
    alpha, F, bd = _scene()
    B = np.stack([bd(0), bd(1)]).astype(np.float32)
    # the object shots see the backdrops with drifted gains: C_k = aF + (1-a) g_k B_k
    gains = np.array([g, h])
    C = np.stack([_observe(alpha, F, gains[k] * B[k]) for k in range(2)])
    Bc, rep = correct_photometric_drift(C, B, mode="gain", options=FAST)
    for k in range(2):
        np.testing.assert_allclose(rep.shots[k].gain, gains[k], rtol=2e-3)
    r = solve_matte(C, Bc)
    np.testing.assert_allclose(r.alpha, alpha, atol=0.01)


def test_affine_recovers_matrix_and_offset():
    alpha, F, bd = _scene(seed=1)
    B = np.stack([bd(0), bd(1)]).astype(np.float32)
    M = np.array([[0.9, 0.05, 0.0], [0.02, 1.05, -0.03], [0.0, 0.1, 1.25]])
    o = np.array([0.01, -0.005, 0.002])
    C = np.stack([_observe(alpha, F, B[0]), _observe(alpha, F, B[1] @ M.T + o)])
    Bc, rep = correct_photometric_drift(C, B, mode="affine", options=FAST)
    np.testing.assert_allclose(rep.shots[1].matrix, M, atol=2e-3)
    np.testing.assert_allclose(rep.shots[1].offset, o, atol=5e-4)
    np.testing.assert_allclose(rep.shots[0].matrix, np.eye(3), atol=2e-3)
    np.testing.assert_allclose(solve_matte(C, Bc).alpha, alpha, atol=0.01)


def test_field_follows_drift_that_varies_over_the_frame():
    H, W = 96, 128
    alpha, F, bd = _scene(H, W, seed=2)
    B = np.stack([bd(0), bd(1)]).astype(np.float32)
    x = np.linspace(-1, 1, W)[None, :, None]
    y = np.linspace(-1, 1, H)[:, None, None]
    field = 1.0 + 0.12 * x - 0.08 * y * x + np.array([0.0, 0.03, -0.05])  # smooth, per channel
    C = np.stack([_observe(alpha, F, B[0] * field), _observe(alpha, F, B[1])])
    a_none = solve_matte(C, B).alpha
    r = solve_matte(C, B, options=MattingOptions(drift="field", drift_options=DriftOptions(register=False)))
    back = alpha == 0
    assert np.mean(a_none[back] < 0.02) < 0.7  # the drift matters
    assert np.mean(r.alpha[back] < 0.02) > 0.99
    assert np.all(r.alpha[alpha == 1] > 0.97)
    np.testing.assert_allclose(r.alpha[alpha == 0.5], 0.5, atol=0.05)
    # global models cannot follow it
    g = solve_matte(C, B, options=MattingOptions(drift="gain", drift_options=FAST)).alpha
    assert np.mean(g[back] < 0.02) < 0.9


@pytest.mark.parametrize("d", [(0.8, -0.6), (-0.3, 0.2)])
def test_registration_recovers_subpixel_shift(d):
    alpha, F, bd = _scene(96, 128, seed=3)
    truth = np.stack([bd(0), bd(1)])
    C = np.stack([_observe(alpha, F, truth[k]) for k in range(2)])
    # backdrop 0 was shot with its content displaced by d: B(x) = truth(x - d)
    B = np.stack([bd(0, *d), bd(1)]).astype(np.float32)
    Bc, rep = correct_photometric_drift(C, B, mode="gain", options=DriftOptions(rounds=2, apply_shift_px=0.5))
    s0, s1 = rep.shots
    np.testing.assert_allclose(s0.shift_px, d, atol=0.01)
    np.testing.assert_allclose(s1.shift_px, (0, 0), atol=0.01)
    assert s0.shift_applied == (np.hypot(*d) >= 0.5) and not s1.shift_applied
    if s0.shift_applied:
        inner = (slice(4, -4), slice(4, -4))
        assert np.abs(Bc[0] - truth[0])[inner].max() < 0.01


def _bend(H, W):
    """A smooth non-rigid displacement (px) like a cloth fold that moved: up to 0.9 px."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    return 0.9 * np.sin(x / 17.0) * np.cos(y / 23.0), 0.5 * np.cos(x / 29.0 + y / 19.0)


def _cloth(H, W, fx=0.0, fy=0.0):
    """A texture with structure in every direction (one channel varies along x, one along
    y, one diagonally), seen through the displacement ``(fx, fy)``: the value at x is the
    texture at ``x - f``."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = x - fx, y - fy
    return np.stack(
        [0.4 + 0.1 * np.sin(0.4 * x), 0.4 + 0.1 * np.sin(0.37 * y + 1.0), 0.4 + 0.1 * np.sin(0.3 * (x + y))], -1
    )


def test_flow_recovers_a_non_rigid_displacement():
    H, W = 96, 128
    alpha, F, _ = _scene(H, W, seed=6)
    dx, dy = _bend(H, W)
    truth = _cloth(H, W)
    moved = _cloth(H, W, dx, dy)
    # the flow f with moved(x + f(x)) = truth(x) solves f = d(x + f): a fixed point
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    fx, fy = np.zeros((H, W)), np.zeros((H, W))
    for _ in range(30):
        fx = 0.9 * np.sin((x + fx) / 17.0) * np.cos((y + fy) / 23.0)
        fy = 0.5 * np.cos((x + fx) / 29.0 + (y + fy) / 19.0)
    C = _observe(alpha, F, truth)
    w = (alpha == 0).astype(float)
    flow = estimate_backdrop_flow(C, moved, w, sigma_px=2.0, iters=8)
    inner = np.zeros((H, W), bool)
    inner[6:-6, 6:-6] = True
    sel = inner & (w > 0)
    err = np.hypot(flow[..., 0] - fx, flow[..., 1] - fy)[sel]
    assert np.median(err) < 0.02 and np.percentile(err, 95) < 0.05
    back = np.abs(warp_image(moved, flow) - truth)[sel]
    assert back.max() < 0.1 * np.abs(moved - truth)[sel].max()


def test_flow_stays_near_zero_on_noise_and_without_texture():
    rng = np.random.default_rng(7)
    H, W = 64, 80
    flat = np.full((H, W, 3), 0.4)
    C = flat + rng.normal(0, 0.01, flat.shape)
    B = flat + rng.normal(0, 0.01, flat.shape)
    f = estimate_backdrop_flow(C, B, np.ones((H, W)))
    # the Tikhonov weight is the residual's noise variance: noise moves nothing much
    assert np.percentile(np.hypot(f[..., 0], f[..., 1]), 95) < 0.25
    assert np.all(np.isfinite(f)) and np.abs(f).max() <= 2.0 + 1e-6
    # nothing to register on: zeros
    assert not estimate_backdrop_flow(C, B, np.zeros((H, W))).any()


def test_field_with_flow_clears_a_moved_backdrop():
    """The backdrop shot of pair 0 moved non-rigidly and drifted in gain: the gain field
    alone leaves the moved texture in the matte; with the flow the backdrop clears, and
    the opaque disk and the alpha-0.5 ring are kept."""
    H, W = 96, 128
    alpha, F, bd = _scene(H, W, seed=8)
    dx, dy = _bend(H, W)
    C = np.stack([_observe(alpha, F, 0.9 * _cloth(H, W)), _observe(alpha, F, bd(1))])
    B = np.stack([_cloth(H, W, dx, dy), bd(1)]).astype(np.float32)
    res = {}
    for flow in (False, True):
        opts = DriftOptions(register=False, flow=flow, flow_sigma_px=2.0)
        res[flow] = solve_matte(C, B, options=MattingOptions(drift="field", drift_options=opts))
    a0, a1 = res[False].alpha, res[True].alpha
    # the backdrop away from the object's margin and the frame's edge
    far = cv2.erode((alpha == 0).astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    far[:6] = far[-6:] = False
    far[:, :6] = far[:, -6:] = False
    # the flow is fitted against the backdrop under the fine gain field of the round
    # before, which has already taken part of this smooth motion as gain (on the
    # flowers a wider reference does worse): it removes a good part of what is left,
    # not all (0.027 -> 0.016 at the 99th percentile)
    p0, p1 = np.percentile(a0[far], 99), np.percentile(a1[far], 99)
    assert p0 > 0.02 and p1 < 0.7 * p0
    assert np.mean(a1[far]) < 0.7 * np.mean(a0[far])
    assert np.all(a1[alpha == 1] > 0.97)
    np.testing.assert_allclose(np.median(a1[alpha == 0.5]), 0.5, atol=0.03)
    s = res[True].drift.shots
    assert s[0].flow_px_p99 > 0.3 and res[False].drift.shots[0].flow_px_p50 is None


def test_warp_image_convention_matches_shift_image():
    _, _, bd = _scene(seed=9)
    img = bd(0).astype(np.float32)
    H, W = img.shape[:2]
    flow = np.broadcast_to(np.array([0.3, -0.6], np.float32), (H, W, 2))
    inner = (slice(3, -3), slice(3, -3))
    np.testing.assert_allclose(warp_image(img, flow)[inner], shift_image(img, (0.3, -0.6))[inner], atol=2e-3)
    with pytest.raises(ShapeError):
        warp_image(img, flow[:, :-1])


def test_shift_image_convention():
    img = np.zeros((5, 7, 1), np.float32)
    img[2, 3] = 1.0
    out = shift_image(img, (1.0, 0.0))  # output (x, y) = input (x + 1, y)
    assert out[2, 2, 0] == pytest.approx(1.0) and out[2, 3, 0] == pytest.approx(0.0)


def test_object_support_hysteresis():
    a = np.zeros((20, 20))
    a[2:6, 2:6] = 0.3  # a speck of spurious alpha, never above the seed level: not object
    a[10:15, 10:15] = 0.3
    a[12, 12] = 1.0  # a blob with an opaque core: object, low part included
    m = object_support(a, seed=0.9, low=0.1)
    assert not m[2:6, 2:6].any() and m[10:15, 10:15].all() and m.sum() == 25
    assert object_support(a, seed=0.9, low=0.1, margin_px=1).sum() == 49
    assert not object_support(np.zeros((4, 4))).any()


def test_drift_with_no_object_and_with_object_everywhere():
    alpha, F, bd = _scene(seed=5)
    B = np.stack([bd(0), bd(1)]).astype(np.float32)
    none = np.zeros_like(alpha)
    C = np.stack([_observe(none, F, 1.1 * B[0]), _observe(none, F, B[1])])
    r = solve_matte(C, B, options=MattingOptions(drift="field"))
    assert r.alpha.max() < 0.02 and r.drift.shots[0].fit_fraction > 0.95
    np.testing.assert_allclose(r.drift.shots[0].gain, 1.1, rtol=2e-3)
    # an opaque object filling the frame: no backdrop pixels after round 0; the round-0
    # estimate is kept, with a note, and the matte stays opaque
    full = np.ones_like(alpha)
    C = np.stack([_observe(full, F, B[0]), _observe(full, F, B[1])])
    r = solve_matte(C, B, options=MattingOptions(drift="field", drift_options=FAST))
    assert any("backdrop pixels" in n for n in r.drift.notes)
    assert np.all(np.isfinite(r.alpha)) and r.alpha.min() > 0.99


def test_drift_none_is_identity_and_options_validate():
    alpha, F, bd = _scene()
    B = np.stack([bd(0), bd(1)]).astype(np.float32)
    C = np.stack([_observe(alpha, F, B[k]) for k in range(2)])
    Bc, rep = correct_photometric_drift(C, B, mode="none")
    np.testing.assert_array_equal(Bc, B)
    assert rep.shots[0].gain == (1.0, 1.0, 1.0)
    assert solve_matte(C, B).drift is None
    with pytest.raises(InputError, match="drift must be one of"):
        MattingOptions(drift="exposure")
    with pytest.raises(InputError, match="drift mode must be one of"):
        correct_photometric_drift(C, B, mode="curves")
    with pytest.raises(InputError, match="object_low"):
        DriftOptions(object_low=0.95, object_seed=0.9)
    with pytest.raises(InputError, match="rounds"):
        DriftOptions(rounds=0)
    # the build config round-trips MattingOptions through asdict
    o = MattingOptions(drift="field", drift_options=DriftOptions(rounds=2))
    assert MattingOptions(**asdict(o)) == o


def test_drift_correction_with_nan_and_saturated_samples():
    alpha, F, bd = _scene(seed=4)
    B = np.stack([bd(0), bd(1)]).astype(np.float32)
    C = np.stack([_observe(alpha, F, 0.9 * B[0]), _observe(alpha, F, B[1])])
    C[0, 0, :5] = np.nan
    B[1, 1, :5] = np.inf
    C[1, 2, :5] = 5.0
    Bc, rep = correct_photometric_drift(C, B, mode="gain", options=FAST, c_saturation=2.0)
    np.testing.assert_allclose(rep.shots[0].gain, 0.9, rtol=2e-3)
    assert np.isinf(Bc[1, 1, :5]).all()  # dropped samples stay dropped, never invented
    assert np.all(np.isfinite(solve_matte(C, Bc, c_saturation=2.0).alpha))


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def small_set(tmp_path_factory):
    """The flowers set at 160×240 (fast), plus odd files for the error cases."""
    d = tmp_path_factory.mktemp("flowers-small")
    for name in ["flowers-compA", "flowers-compB", "flowers-backA", "flowers-backB", "window"]:
        im = cv2.imread(str(DATA / f"{name}.jpg"))
        cv2.imwrite(str(d / f"{name}.png"), cv2.resize(im, (160, 240), interpolation=cv2.INTER_AREA))
    cv2.imwrite(str(d / "other-size.png"), np.zeros((10, 12, 3), np.uint8))
    (d / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    return d


def _args(d, obj, back, out, *extra):
    return [
        "matte",
        "--object",
        *[str(d / o) for o in obj],
        "--backdrop",
        *[str(d / b) for b in back],
        "--out",
        str(out),
        *extra,
    ]


def test_cli_matte_writes_files_and_json(small_set, tmp_path):
    d, out = small_set, tmp_path / "m"
    res = CliRunner().invoke(
        app,
        _args(
            d,
            ["flowers-compA.png", "flowers-compB.png"],
            ["flowers-backA.png", "flowers-backB.png"],
            out,
            "--over",
            str(d / "window.png"),
            "--json",
        ),
    )
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    alpha = cv2.imread(str(out / "alpha.png"), cv2.IMREAD_UNCHANGED)
    assert alpha.dtype == np.uint16 and alpha.shape == (240, 160)
    a = alpha / 65535.0
    assert summary["clear_fraction"] == pytest.approx(np.mean(a < 0.05), abs=2e-3)
    assert summary["opaque_fraction"] == pytest.approx(np.mean(a > 0.95), abs=2e-3)
    assert summary["clear_fraction"] > 0.75 and summary["fractional_fraction"] < 0.2
    assert json.loads((out / "matte.json").read_text())["clear_fraction"] == summary["clear_fraction"]
    assert len(summary["drift"]["shots"]) == 2 and len(summary["registration_px"]) == 2
    assert all(s["flow_px_p50"] is not None for s in summary["drift"]["shots"])  # the flow is on by default
    fg = cv2.imread(str(out / "foreground_premul.png"), cv2.IMREAD_UNCHANGED)
    comp = cv2.imread(str(out / "composite.png"))
    win = cv2.imread(str(d / "window.png"))
    assert fg.shape == (240, 160, 3) and fg.dtype == np.uint16 and (out / "foreground_premul.exr").is_file()
    # where the matte is clear the composite is the new background, where opaque it is not
    clear = a < 0.01
    assert np.abs(comp.astype(int) - win.astype(int))[clear].mean() < 2.0
    assert np.abs(comp.astype(int) - win.astype(int))[a > 0.99].mean() > 20.0


def test_cli_matte_repeated_flags_and_human_output(small_set, tmp_path):
    d = small_set
    res = CliRunner().invoke(
        app,
        [
            "matte",
            "--object",
            str(d / "flowers-compA.png"),
            "--backdrop",
            str(d / "flowers-backA.png"),
            "--object",
            str(d / "flowers-compB.png"),
            "--backdrop",
            str(d / "flowers-backB.png"),
            "--out",
            str(tmp_path / "m"),
            "--drift",
            "none",
        ],
    )
    assert res.exit_code == 0, res.output
    assert res.stdout.strip() == "" and "clear" in res.stderr
    assert json.loads((tmp_path / "m" / "matte.json").read_text())["drift"] is None


@pytest.mark.parametrize(
    "obj,back,extra,match",
    [
        (["flowers-compA.png", "flowers-compB.png"], ["flowers-backA.png"], [], "counts must match"),
        (["flowers-compA.png"], ["flowers-backA.png"], [], "at least 2"),
        (["flowers-compA.png", "other-size.png"], ["flowers-backA.png", "flowers-backB.png"], [], "differs from"),
        (["flowers-compA.png", "broken.jpg"], ["flowers-backA.png", "flowers-backB.png"], [], "not a readable image"),
        (["flowers-compA.png", "missing.png"], ["flowers-backA.png", "flowers-backB.png"], [], "no such file"),
        (["flowers-compA.png", "flowers-compB.png"], ["flowers-backA.png", "flowers-backA.png"], [], "identical"),
        (
            ["flowers-compA.png", "flowers-compB.png"],
            ["flowers-backA.png", "flowers-backB.png"],
            ["--drift", "x"],
            "drift must be one of",
        ),
        (
            ["flowers-compA.png", "flowers-compB.png"],
            ["flowers-backA.png", "flowers-backB.png"],
            ["--bogus"],
            "unknown option",
        ),
    ],
)
def test_cli_matte_bad_input_exit_2(small_set, tmp_path, obj, back, extra, match):
    out = tmp_path / "m"
    res = CliRunner().invoke(app, _args(small_set, obj, back, out, *extra))
    assert res.exit_code == 2, res.output
    # the console wraps long messages at a space: undo that, whatever the tmp path's length
    assert match in " ".join(res.stderr.split())
    assert "Traceback" not in res.output and res.stdout.strip() == ""
    assert not out.exists()  # nothing half-written


def test_simulated_views_without_drift_do_not_get_worse():
    """The rcsynth ray caster (fuzzy sphere: core alpha 1, halo 0.35, display backdrops,
    noise 0.002): with no drift the field correction keeps the alpha error of the plain
    solve; with a drift of the backdrop shots it removes the error the drift causes."""
    from rcsynth import _rays, render_view, rig_dict

    from opacityhull.riggeometry import RigGeometry

    rng = np.random.default_rng(0)
    geo = RigGeometry.from_dict(rig_dict(3, 64, 48))
    cams = geo.nominal_cameras()
    err = {"none": [], "field": [], "none_drift": [], "field_drift": []}
    drift = np.array([[0.95, 0.95, 0.95], [0.82, 0.97, 1.3]])
    for c, a in [(0, 0.0), (1, 60.0), (2, 120.0)]:
        cam = RigGeometry.view_camera(cams[c], a)
        rays = _rays(cam, 3)
        base = {d.name: rng.uniform(0.05, 0.95, (d.resolution[1], d.resolution[0], 3)) for d in geo.displays}
        C, B = [], []
        for p in (base, {n: 1 - x for n, x in base.items()}):
            col, alpha = render_view(cam, a, geo, kind="fuzzy", patterns=p, rays=rays)
            bk, _ = render_view(cam, a, geo, kind="fuzzy", patterns=p, rays=rays, hide_object=True)
            C.append(col + rng.normal(0, 0.002, col.shape))
            B.append(bk + rng.normal(0, 0.002, bk.shape))
        C, B = np.array(C, np.float32), np.array(B, np.float32)
        Bd = (B / drift[:, None, None, :]).astype(np.float32)
        for mode in ("none", "field"):
            opts = MattingOptions(drift=mode)
            err[mode].append(np.abs(solve_matte(C, B, options=opts).alpha - alpha).mean())
            err[mode + "_drift"].append(np.abs(solve_matte(C, Bd, options=opts).alpha - alpha).mean())
    e = {k: float(np.mean(v)) for k, v in err.items()}
    assert e["field"] <= 1.05 * e["none"] < 0.005  # measured 0.0029 vs 0.0030
    assert e["none_drift"] > 0.04  # measured 0.062
    assert e["field_drift"] <= 1.05 * e["none"]  # measured 0.0029
