"""Relit models in the viewer: the relighting chunks read back against the CPU relighter
(weights, PCA rank, quantisation), and the page in headless Chromium against
``Relighter`` + ``render_image`` / ``relight_model`` under the same map and yaw."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from helpers import copy_without, load_viewer, viewer_error

from opacityhull.errors import FormatError, InputError
from opacityhull.imageio import srgb_decode
from opacityhull.model import OpacityHullModel
from opacityhull.relight.envmap import load_envmap
from opacityhull.relight.relit import Relighter, compress_reflectance, compress_reflectance_reference
from opacityhull.view.bundle import decoded_surfels, write_bundle
from opacityhull.view.relit import (
    choose_rank,
    quantize_basis,
    read_relight,
    relit_error_by_rank,
    relit_views_from_bundle,
)
from opacityhull.view.server import BundleServer

SPECS = ("builtin:grace", "builtin:uffizi")


def test_bundled_weights_are_the_relighters(relit_model, relit_bundle):
    """The page's weight table is Relighter.weights of load_envmap(spec, yaw_deg=yaw)."""
    out, summary = relit_bundle
    rl, _, _, weights = read_relight(out)
    assert [e["source"] for e in rl["envmaps"]] == list(SPECS) and summary["relight"]["envmaps"] == ["grace", "uffizi"]
    S = rl["yaw_steps"]
    assert S == 24 and rl["table_deg"] == [0.0, 90.0, 180.0, 270.0]
    R = Relighter(OpacityHullModel.open(relit_model))
    assert rl["n_lights"] == len(R.lights) == 60 and rl["light_keys"] == list(R.lights.keys)
    for n, spec in enumerate(SPECS):
        assert weights[n].shape == (S, 4, 60, 3)
        for s in (0, 1, 13, 23):
            env = load_envmap(spec, yaw_deg=360.0 * s / S)
            for t, a in enumerate(rl["table_deg"]):
                w = R.weights(a, envmap=env)
                np.testing.assert_allclose(weights[n][s, t], w, rtol=1e-6, atol=1e-7 * np.abs(w).max())
        # a quarter turn of the map moves the light between the table angles' weights
        assert np.abs(weights[n][6, 0] - weights[n][0, 0]).max() > 0.05 * np.abs(weights[n][0, 0]).max()


def test_bundled_relighting_matches_exact_relighting(relit_model, relit_bundle):
    """PCA at the chosen rank plus 8-bit eigen-images: the relit views the page computes
    (NumPy mirror) against Relighter's exact relit views; the rank is the smallest
    whose relit error meets the target."""
    out, summary = relit_bundle
    rl = json.loads((out / "manifest.json").read_text())["relight"]
    r, errs, tgt = rl["rank"], rl["relit_rel_error_by_rank"], rl["rel_error_target"]
    assert errs[r - 1] <= tgt and (r == 1 or errs[r - 2] > tgt)
    assert np.all(np.diff(errs) <= 1e-12)  # more components never relight worse (on the judged lightings)
    assert summary["relight"]["rank"] == r and 1 < r < 16
    model = OpacityHullModel.open(relit_model)
    R = Relighter(model)
    for yaw in (180.0, 60.0, 67.5):  # two table rows, and halfway between rows (interpolated)
        env = load_envmap("builtin:grace", yaw_deg=yaw)
        exact = [R.relight_view(i, envmap=env) for i in range(len(model.views))]
        page = relit_views_from_bundle(out, 0, yaw, [e.shape[:2] for e in exact])
        num = sum(float(np.sum((p - e[..., :3]) ** 2)) for p, e in zip(page, exact, strict=True))
        den = sum(float(np.sum(e[..., :3] ** 2)) for e in exact)
        rel = np.sqrt(num / den)
        print(f"yaw {yaw:g}: bundled relighting vs exact, relative RMS {100 * rel:.2f} % (rank {r})")
        assert rel < 2 * tgt  # PCA truncation (≤ target on the judged yaws) plus byte quantisation
        # outside the matte the relit colour is exactly 0, as in relight_view
        for p, e in zip(page, exact, strict=True):
            assert not p[e[..., 3] == 0].any()
    # yaw 0 and 360 are the same table row
    a, b = (relit_views_from_bundle(out, 1, y, [e.shape[:2] for e in exact]) for y in (0.0, 360.0))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    # file sizes are what the manifest says: the bytes reported per view
    assert (out / "basis.bin").stat().st_size == rl["basis"]["bytes"]
    per_view = (rl["basis"]["bytes"] + rl["coeffs"]["bytes"]) / len(model.views)
    assert summary["relight"]["bytes_per_view"] == pytest.approx(per_view)


def test_quantize_and_rank_choice_hard_cases():
    rng = np.random.default_rng(3)
    b = rng.normal(size=(3, 5, 7, 3))
    b[1] *= 1e-6
    b[2] = 0.0  # an all-zero component (a black view)
    q, sc = quantize_basis(b)
    assert q.dtype == np.int8 and sc[2] == 0 and not q[2].any() and np.abs(q).max() == 127
    err = np.abs(q * (sc / 127.0)[:, None, None, None] - b)
    assert np.all(err <= (sc / 254.0)[:, None, None, None] * (1 + 1e-9))
    assert choose_rank(np.array([4.0, 1.0, 0.25]), 100.0, target=0.1) == (2, [0.2, 0.1, 0.05])
    assert choose_rank(np.array([4.0, 1.0, 0.25]), 100.0, target=0.01)[0] == 3  # never met: the largest
    assert choose_rank(np.zeros(4), 0.0, target=0.01)[0] == 1  # black views: any rank is exact
    # the per-rank relit error against SVD truncation (numpy.linalg.svd oracle)
    s = rng.random((6, 4, 5, 3)).astype(np.float32)
    s[5] = s[0] + s[1]  # rank-deficient: the last component carries nothing
    w = rng.random((2, 6, 3))
    comp = compress_reflectance(s, 6)
    err2, tot2 = relit_error_by_rank(comp, s, w)
    exact = np.einsum("khwc,mkc->mhwc", s.astype(np.float64), w)
    assert tot2 == pytest.approx(float(np.sum(exact**2)))
    for r in (1, 3, 5):
        ref = np.einsum("khwc,mkc->mhwc", compress_reflectance_reference(s, r).astype(np.float64), w)
        assert err2[r - 1] == pytest.approx(float(np.sum((exact - ref) ** 2)), rel=1e-3, abs=1e-9 * tot2)
    assert err2[4] < 1e-9 * tot2


def test_relight_options_checked_before_writing(relit_model, bundle, tmp_path):
    out = tmp_path / "b"
    cases: tuple[tuple[dict, str], ...] = (
        ({"probes": ["grace", "nope"]}, "unknown probe 'nope'"),
        ({"relight_rank": 17}, "--relight-rank 17"),
        ({"relight_error": 0.0}, "--relight-error"),
        ({"yaw_steps": 0}, "--yaw-steps 0"),
    )
    for kw, msg in cases:
        with pytest.raises(InputError, match=msg):
            write_bundle(relit_model, out, **kw)
        assert not out.exists()
    # a model without reflectance: no relighting block, and the reader says so
    b, summary = bundle
    assert "relight" not in json.loads((b / "manifest.json").read_text()) and "relight" not in summary
    with pytest.raises(FormatError, match="no relighting data"):
        read_relight(b)


def test_cli_relight_options(relit_model, tmp_path):
    exe = [sys.executable, "-m", "opacityhull.cli", "view", str(relit_model), "--out"]
    r = subprocess.run(exe + [str(tmp_path / "x"), "--probes", "sunset"], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown probe 'sunset'" in " ".join(r.stderr.split()) and "Traceback" not in r.stderr
    r = subprocess.run(
        exe + [str(tmp_path / "b"), "--probes", "wells", "--relight-rank", "3", "--yaw-steps", "8", "--json"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)["relight"]
    assert s["rank"] == 3 and s["envmaps"] == ["wells"]
    rl, basis, coeffs, weights = read_relight(tmp_path / "b")
    assert basis.shape[1] == 3 and coeffs.shape == (8, 60, 3) and weights[0].shape == (8, 4, 60, 3)


# --------------------------------------------------------------------------- in the browser


def _decoded_surfels(bundle_dir, model):
    return decoded_surfels(bundle_dir, n_views=len(model.views))


def test_browser_relit_matches_cpu_relighter(browser, relit_model, relit_bundle, tmp_path):
    """The page relit under grace at a captured camera vs the CPU: Relighter's exact relit
    views blended by render_image on the bundle's surfels (surfel shading, as the page),
    and relight_model's own picture of the exact model; both over the same rotated map
    with the page's exposure.

    Measured (software GL; view 2 at yaw 180, a table row, and view 5 at yaw 67.5, halfway
    between two 15° rows, i.e. interpolated weights): 44.5–46.7 dB against the same
    surfels, 33.6–35.5 dB against relight_model (which adds the octree position coding
    and per-pixel shading, as in test_browser_matches_cpu_renderer). Thresholds: 40 dB
    and the issue's 30 dB."""
    from opacityhull.imageio import read_image
    from opacityhull.relight.runner import relight_model
    from opacityhull.render.background import composite_over, resolve_background
    from opacityhull.render.config import RenderConfig
    from opacityhull.render.renderer import render_image
    from opacityhull.render.views import prepare_views
    from opacityhull.view.browser import canvas_rgb

    out, _ = relit_bundle
    model = OpacityHullModel.open(relit_model)
    man = json.loads((out / "manifest.json").read_text())
    dec = _decoded_surfels(out, model)
    cams = [v.camera for v in model.views]
    R = Relighter(model)
    expo = man["relight"]["envmaps"][0]["exposure"]
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        for yaw, vi in ((180.0, 2), (67.5, 5)):
            env = load_envmap("builtin:grace", yaw_deg=yaw)
            bg = env
            pv = prepare_views(cams, [R.relight_view(i, envmap=env) for i in range(len(cams))])
            browser.execute_script(
                f"window.opacityhull.setCamera({vi}); return window.opacityhull.setRelight('grace', {yaw})"
            )
            gpu = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
            same = render_image(dec, cams, pv, cams[vi], config=RenderConfig(k=4, threads=1, shading="surfel"))
            ref_same = np.clip(expo * same.over(bg), 0, 1)
            v = model.views[vi]
            s = relight_model(
                relit_model,
                out=tmp_path / f"cpu{vi}",
                envmap=env,
                view=(v.camera_index, v.table_deg),
                write_views=False,
                exposure=expo,
                render_config=RenderConfig(k=4, threads=1),
            )
            full = read_image(s["view"]["exr"])
            ref_full = np.clip(expo * composite_over(full, resolve_background(bg, cams[vi])), 0, 1)
            mask = same.rgba[..., 3] > 0.01
            assert mask.sum() > 300
            p_same = 10 * np.log10(1 / np.mean((gpu - ref_same)[mask] ** 2))
            p_full = 10 * np.log10(1 / np.mean((gpu - ref_full)[mask] ** 2))
            print(
                f"relit yaw {yaw:g} view {vi}: browser vs CPU {p_same:.1f} dB (same surfels), {p_full:.1f} dB (relight_model)"
            )
            assert p_same >= 40.0
            assert p_full >= 30.0


def _frame(drv):
    """The canvas after the page's frame loop has drawn (two animation frames)."""
    from opacityhull.view.browser import canvas_rgb

    drv.execute_async_script(
        "const done = arguments[arguments.length - 1]; requestAnimationFrame(() => requestAnimationFrame(() => done()));"
    )
    return srgb_decode(canvas_rgb(drv).astype(np.float32) / 255.0)


def test_browser_relit_controls(browser, relit_bundle, bundle):
    """The picker and the slider (their DOM events, as a user moves them) change the
    picture; yaw 0 and 360 give the same frame; a model without reflectance has neither."""
    out, _ = relit_bundle
    ui = (
        "const [id, v, ev] = arguments; const e = document.getElementById(id); e.value = v;"
        " e.dispatchEvent(new Event(ev));"
    )
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        assert browser.find_element("id", "lightlabel").is_displayed()
        opts = browser.execute_script("return Array.from(document.getElementById('light').options).map(o => o.text)")
        assert opts == ["as captured", "relit: grace", "relit: uffizi"]
        browser.execute_script("return window.opacityhull.setCamera(3)")
        captured = _frame(browser)
        browser.execute_script(ui, "light", "0", "change")
        grace = _frame(browser)
        assert browser.execute_script("return document.getElementById('yaw').value") == "180"
        assert browser.execute_script("return window.opacityhull.viewer.lighting") == 0
        assert np.mean(np.abs(grace - captured)) > 0.02
        frames = {}
        for yaw in ("0", "360", "90"):
            browser.execute_script(ui, "yaw", yaw, "input")
            frames[yaw] = _frame(browser)
        np.testing.assert_array_equal(frames["0"], frames["360"])
        assert np.mean(np.abs(frames["90"] - frames["0"])) > 0.01
        browser.execute_script(ui, "light", "1", "change")
        assert np.mean(np.abs(_frame(browser) - frames["0"])) > 0.01
        browser.execute_script(ui, "light", "", "change")
        np.testing.assert_array_equal(_frame(browser), captured)  # back to the captured views, black background
    b, _ = bundle
    with BundleServer(b) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        assert not browser.find_element("id", "lightlabel").is_displayed()
        with pytest.raises(Exception, match="no relighting data"):
            browser.execute_script("return window.opacityhull.setRelight('grace', 0)")


def test_browser_relit_missing_or_truncated_chunk(browser, relit_bundle, tmp_path):
    out, _ = relit_bundle
    broken = copy_without(out, tmp_path / "nobasis", "basis.bin")
    text = viewer_error(browser, broken)
    assert "relighting PCA basis" in text and "basis.bin" in text and "HTTP 404" in text
    p = broken / "weights_01.bin"
    shutil.copyfile(out / "basis.bin", broken / "basis.bin")
    p.write_bytes(p.read_bytes()[:-12])
    text = viewer_error(browser, broken)
    assert "weights_01.bin" in text and "uffizi" in text and "truncated" in text


def test_browser_envmap_option_is_a_relighting_map(browser, relit_model, tmp_path):
    """--envmap naming a bundled probe: one entry, its yaw the default, the image shared
    with envmap.bin (loaded once by the page)."""
    out = tmp_path / "b"
    write_bundle(relit_model, out, probes=["grace"], envmap="builtin:grace", env_yaw_deg=150.0, yaw_steps=8)
    rl = json.loads((out / "manifest.json").read_text())["relight"]
    assert len(rl["envmaps"]) == 1 and rl["envmaps"][0]["image"]["file"] == "envmap.bin"
    assert rl["envmaps"][0]["default_yaw_deg"] == 150.0 and not list(out.glob("relight_env_*.bin"))
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        browser.execute_script("return window.opacityhull.setRelight('grace')")
        assert browser.execute_script("return window.opacityhull.viewer.envYawDeg") == 150
        with pytest.raises(Exception, match="no bundled environment map"):
            browser.execute_script("return window.opacityhull.setRelight('wells')")
