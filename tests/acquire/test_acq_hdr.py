"""HDR merging: synthetic radiance with known values, clipped highlights, the slow
oracle, Debevec response recovery, and the session step."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.acquire.hdr import hdr_session, merge_debevec, merge_linear, merge_linear_reference, recover_response
from opacityhull.errors import InputError, ShapeError
from opacityhull.session import Session, SessionWriter

TIMES = [0.01, 0.04, 0.16, 0.64]


def _radiance(h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    # log-uniform over three decades (all unclipped at t = 0.01, gain <= 2), plus a highlight
    L = np.exp(rng.uniform(np.log(0.05), np.log(45.0), size=(h, w, 3))).astype(np.float32)
    L[2:6, 2:6] = [40.0, 30.0, 36.0]  # clips at t >= 0.04 with gain 2: only the shortest sees it
    return L


def _expose(L, t, gain=1.0, white=1.0, noise=0.0, rng=None):
    v = gain * t * L
    if noise:
        v = v + noise * rng.standard_normal(v.shape) * np.sqrt(np.maximum(v, 0) * white)
    return np.clip(v, 0.0, white).astype(np.float32)


def test_linear_merge_recovers_known_radiance():
    L = _radiance()
    imgs = [_expose(L, t, gain=2.0) for t in TIMES]
    out, flag = merge_linear(imgs, TIMES, gain=2.0)
    # every pixel below white*0.98 in the shortest exposure is recovered exactly (no noise)
    ok = 2.0 * 0.01 * L.max(axis=-1) < 0.98
    np.testing.assert_allclose(out[ok], L[ok], rtol=1e-5)
    # the highlight patch clips in every exposure but the shortest: recovered from it
    np.testing.assert_allclose(out[2:6, 2:6], L[2:6, 2:6], rtol=1e-5)
    assert not flag[ok].any() and flag[~ok].all()


def test_all_saturated_uses_shortest_and_flags():
    L = _radiance()
    L[10:12, 10:12] = 1e6  # too bright for every exposure
    imgs = [_expose(L, t) for t in TIMES]
    out, flag = merge_linear(imgs, TIMES)
    assert flag[10:12, 10:12].all() and flag.sum() == 4
    np.testing.assert_allclose(out[10:12, 10:12], 1.0 / 0.01)  # white / (gain * t_min): a lower bound
    # black pixels: radiance 0 everywhere -> 0, not NaN
    L[0, 0] = 0.0
    out, _ = merge_linear([_expose(L, t) for t in TIMES], TIMES)
    assert np.all(np.isfinite(out)) and np.all(out[0, 0] == 0)


def test_noisy_merge_beats_any_single_exposure():
    rng = np.random.default_rng(5)
    L = np.full((64, 64, 3), 3.0, np.float32)
    imgs = [_expose(L, t, noise=0.01, rng=rng) for t in TIMES]
    out, _ = merge_linear(imgs, TIMES)
    err_merge = np.sqrt(np.mean((out - L) ** 2))
    singles = [np.sqrt(np.mean((im / t - L) ** 2)) for im, t in zip(imgs, TIMES, strict=True) if (3.0 * t) < 0.98]
    assert err_merge < min(singles)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), sat=st.floats(0.5, 1.0), gain=st.floats(0.5, 4.0))
def test_vectorised_merge_matches_slow_oracle(seed, sat, gain):
    rng = np.random.default_rng(seed)
    L = np.exp(rng.uniform(-3, 8, size=(5, 6, 3))).astype(np.float32)
    L[0, 0] = 0.0
    times = sorted(rng.choice([0.001, 0.01, 0.03, 0.1, 0.3, 1.0], size=3, replace=False).tolist())
    imgs = [_expose(L, t, gain=gain) for t in times]
    a, fa = merge_linear(imgs, times, saturation=sat, gain=gain)
    b, fb = merge_linear_reference(imgs, times, saturation=sat, gain=gain)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    assert np.array_equal(fa, fb)


def test_merge_input_errors():
    with pytest.raises(InputError):
        merge_linear([np.zeros((2, 2, 3))], [0.1, 0.2])
    with pytest.raises(ShapeError):
        merge_linear([np.zeros((2, 2, 3)), np.zeros((2, 3, 3))], [0.1, 0.2])
    with pytest.raises(InputError):
        merge_linear([np.zeros((2, 2, 3))] * 2, [0.1, -0.2])


def _gamma_camera(L, t):
    """An 8-bit camera with a non-linear (gamma 1/2.2) response, as float code/255."""
    x = np.clip(t * L, 0.0, 1.0) ** (1 / 2.2)
    return (np.round(x * 255) / 255).astype(np.float32)


def test_debevec_recovers_response_and_radiance():
    rng = np.random.default_rng(2)
    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w]
    L = np.exp(np.log(0.5) + (np.log(200.0) - np.log(0.5)) * (xx / (w - 1)))[..., None] * np.array([1.0, 0.8, 0.6])
    L = (L * (1 + 0.05 * rng.random((h, w, 1)))).astype(np.float32)
    times = [1 / 256, 1 / 64, 1 / 16, 1 / 4, 1.0]
    imgs = [_gamma_camera(L, t) for t in times]
    resp = recover_response([imgs], times)
    assert resp.shape == (256, 3)
    assert np.all(np.diff(resp[5:250], axis=0) > 0)  # monotone
    # recovered response ~ true inverse response (code/255)^2.2 up to scale
    codes = np.arange(30, 240)
    true = (codes / 255.0) ** 2.2
    for c in range(3):
        k = np.exp(np.median(np.log(resp[codes, c]) - np.log(true)))
        rel = np.abs(resp[codes, c] / (k * true) - 1)
        assert np.median(rel) < 0.05, (c, np.median(rel))
    E = merge_debevec(imgs, times, resp)
    valid = np.isfinite(E).all(-1)
    k = np.exp(np.median(np.log(E[valid]) - np.log(L[valid])))
    rel = np.abs(E[valid] / (k * L[valid]) - 1)
    assert np.median(rel) < 0.08, np.median(rel)


def _add_bracket(w, img, shot, k, t, *, light, **kw):
    """Bracket ``k`` (exposure ``t`` s) of reflectance shot ``shot`` (camera 0, light ``light``)."""
    w.add_image(
        img,
        id=f"{shot}/e{k}",
        shot=shot,
        phase="reflectance",
        camera=0,
        table_deg=0.0,
        rel_path=f"images/{shot}_e{k}.exr",
        exposure_s=t,
        lights_deg=0.0,
        light=light,
        **kw,
    )


def _bracketed_session(tmp_path, L, times, *, linear=True, gain=1.0):
    geo = {
        "target_m": [0, 0, 0],
        "cameras": [{"name": "c", "width": L.shape[1], "height": L.shape[0], "distance_m": 1.0, "gain": gain}],
    }
    meta = {
        "rig": geo,
        "session": {"white_level": 1.0},
        "camera_info": [{"index": 0, "name": "c", "white_level": 1.0, "linear": linear}],
    }
    root = tmp_path / "s"
    with SessionWriter(root).create(meta) as w:
        for shot_i, scale in enumerate((1.0, 0.5)):
            shot = f"reflectance/c0_t000.000/a000.000_l{shot_i}"
            for k, t in enumerate(times):
                img = _expose(L * scale, t, gain=gain) if linear else _gamma_camera(L * scale, t)
                _add_bracket(w, img, shot, k, t, light=shot_i)
    return root


def test_hdr_session_step(tmp_path):
    L = _radiance(12, 16)
    root = _bracketed_session(tmp_path, L, TIMES, gain=2.0)
    rep = hdr_session(root)
    assert rep["merged"] == 2 and rep["shots"] == 2 and rep["methods"] == {"0": "linear"}
    s = Session.open(root)
    h = s.select(kind="hdr")
    assert len(h) == 2 and all(len(r.sources) == 4 for r in h)
    rad = s.load_radiance("reflectance/c0_t000.000/a000.000_l0")
    np.testing.assert_allclose(rad, L, rtol=1e-5)  # highlight patch included (from the short exposure)
    assert len(s.select(kind="raw")) == 8  # raw brackets stay
    rep2 = hdr_session(root)
    assert rep2["merged"] == 0 and rep2["skipped"] == 2
    from opacityhull.acquire.verify import verify_session

    v = verify_session(root)
    assert v["ok"] and v["hdr"] == 2


def test_hdr_session_debevec_for_nonlinear_camera(tmp_path):
    h, w = 20, 40
    xx = np.mgrid[0:h, 0:w][1]
    L = np.exp(np.log(0.5) + (np.log(200.0) - np.log(0.5)) * (xx / (w - 1)))[..., None] * np.ones(3)
    times = [1 / 256, 1 / 64, 1 / 16, 1 / 4, 1.0]
    root = _bracketed_session(tmp_path, L.astype(np.float32), times, linear=False)
    rep = hdr_session(root)
    assert rep["methods"] == {"0": "debevec"} and rep["merged"] == 2
    assert (root / rep["responses"]["0"]).is_file()
    s = Session.open(root)
    a = s.load_radiance("reflectance/c0_t000.000/a000.000_l0")
    b = s.load_radiance("reflectance/c0_t000.000/a000.000_l1")
    # the second shot had half the radiance: the ratio survives the unknown response
    assert np.median(b / a) == pytest.approx(0.5, rel=0.08)


def test_hdr_remerges_when_a_bracket_was_reshot(tmp_path):
    L = _radiance(12, 16)
    root = _bracketed_session(tmp_path, L, TIMES)
    assert hdr_session(root)["merged"] == 2
    shot = "reflectance/c0_t000.000/a000.000_l1"
    with SessionWriter(root).resume() as w:  # a re-shoot of bracket 1 (e.g. its file was corrupt)
        _add_bracket(w, _expose(L, TIMES[1]), shot, 1, TIMES[1], light=1, replace=True)
    rep = hdr_session(root)
    assert rep["merged"] == 1 and rep["skipped"] == 1
    s = Session.open(root)
    h = [r for r in s.records if r.kind == "hdr" and r.shot == shot][0]
    assert h.extra["sources_sha256"][1] == [r for r in s.records if r.id == f"{shot}/e1"][0].sha256
