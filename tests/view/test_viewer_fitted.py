"""The viewer of a model built with ``--optimize`` (#29 item 4): the bundle carries the
fitted splats (``splats.bin``, the manifest's ``splats``; the format stays
``opacityhull-viewer/3``: the key is optional, so bundles without it load as before) and
the page draws them, in headless Chromium, as the CPU draws them
(:class:`opacityhull.render.splats.FittedSplats`, the fitting's own forward pass)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import load_viewer

import fitted
from opacityhull.errors import FormatError, InputError
from opacityhull.imageio import srgb_decode
from opacityhull.model import OpacityHullModel
from opacityhull.optimize.fit import load_fitted
from opacityhull.view.bundle import VIEWER_FORMAT, write_bundle
from opacityhull.view.server import BundleServer
from opacityhull.view.splats import SPLAT_HEAD, read_splats


@pytest.fixture(scope="module")
def fitted_bundle(tmp_path_factory):
    root = fitted.sphere(tmp_path_factory)
    out = tmp_path_factory.mktemp("fitted_bundle") / "b"
    return root, out, write_bundle(root, out, first_chunk=500)


def test_bundle_holds_the_fitted_splats(fitted_bundle, tmp_path):
    root, out, summary = fitted_bundle
    p = load_fitted(root)
    N, B = p["sh"].shape[:2]
    meta, rec = read_splats(out)
    man = json.loads((out / "manifest.json").read_text())
    assert man["format"] == VIEWER_FORMAT and summary["renderer"] == "fitted" and meta["count"] == N == len(rec)
    assert meta["sh_degree"] == 1 and rec.shape[1] == 4 * meta["texels"] >= SPLAT_HEAD + 3 * B
    np.testing.assert_array_equal(rec[:, :3], p["means"])
    np.testing.assert_allclose(rec[:, 3], 1 / (1 + np.exp(-p["opacity_logits"].astype(np.float64))), rtol=1e-6)
    # the scaled tangent axes: lengths the std-devs, orthogonal, spanning the plane of the fitted normal
    u, v = rec[:, 4:7].astype(np.float64), rec[:, 7:10].astype(np.float64)
    s = np.exp(p["log_scales"].astype(np.float64))
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), s[:, 0], rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), s[:, 1], rtol=1e-5)
    assert np.abs(np.einsum("ni,ni->n", u, v)).max() < 1e-5 * (s[:, 0] * s[:, 1]).max()
    from scipy.spatial.transform import Rotation

    n = Rotation.from_quat(p["quats"].astype(np.float64), scalar_first=True).as_matrix()[:, :, 2]
    nn = np.cross(u, v) / (s[:, :1] * s[:, 1:2])
    np.testing.assert_allclose(nn, n, atol=1e-5)
    np.testing.assert_array_equal(rec[:, SPLAT_HEAD : SPLAT_HEAD + 3 * B], p["sh"].reshape(N, 3 * B))
    # --renderer ulr leaves them out; an unfitted model has none; fitted without a fit is bad input
    plain = write_bundle(root, tmp_path / "u", renderer="ulr")
    assert plain["renderer"] == "ulr" and "splats" not in json.loads((tmp_path / "u" / "manifest.json").read_text())
    with pytest.raises(FormatError, match="no fitted splats"):
        read_splats(tmp_path / "u")
    with pytest.raises(InputError, match="--renderer 'nerf'"):
        write_bundle(root, tmp_path / "x", renderer="nerf")
    assert not (tmp_path / "x").exists()


def test_cli_fitted_renderer_on_an_unfitted_model_exits_2(view_model, tmp_path):
    import subprocess
    import sys

    root, _ = view_model
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "opacityhull.cli",
            "view",
            str(root),
            "--out",
            str(tmp_path / "b"),
            "--renderer",
            "fitted",
        ],
        capture_output=True,
        text=True,
    )
    err = " ".join(r.stderr.split())
    assert r.returncode == 2 and "--renderer fitted" in err and "--optimize" in err and "Traceback" not in err
    assert not (tmp_path / "b").exists()


def test_browser_draws_the_fitted_splats_as_the_cpu(browser, fitted_bundle):
    from opacityhull.render.splats import FittedSplats
    from opacityhull.view.browser import canvas_rgb

    root, out, _ = fitted_bundle
    m = OpacityHullModel.open(root)
    fs = FittedSplats.load(root)
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        assert browser.execute_script("return window.opacityhull.viewer.renderer") == "fitted"
        assert browser.execute_script("return window.opacityhull.viewer.splatsReady")
        for bg in ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]):
            browser.execute_script(f"return window.opacityhull.setBackground({bg})")
            for vi in (2, 13):
                browser.execute_script(f"return window.opacityhull.setCamera({vi})")
                gpu = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
                res = fs.render(m.views[vi].camera)
                cpu = res.over(np.asarray(bg, np.float32))
                mask = res.rgba[..., 3] > 0.01
                assert mask.sum() > 300
                d = gpu - cpu
                psnr = 10 * np.log10(1.0 / np.mean(d**2))
                psnr_in = 10 * np.log10(1.0 / np.mean(d[mask] ** 2))
                print(
                    f"view {vi} on {bg}: browser vs CPU fitted splats {psnr:.1f} dB whole image, {psnr_in:.1f} dB inside"
                )
                # measured (SwiftShader): 55.8-58.9 dB inside, 62-65 dB whole, about the 8-bit
                # canvas's own floor; the same splats without their degree-1 SH band score
                # 52.7-53.1 dB inside, shifted by one pixel 20-21 dB
                assert psnr_in >= 54.0
                assert psnr >= 58.0
        # the page still draws the captured views by ULR on request, and back
        browser.execute_script("return window.opacityhull.setRenderer('ulr')")
        ulr = canvas_rgb(browser).astype(np.float32)
        browser.execute_script("return window.opacityhull.setRenderer('fitted')")
        assert np.abs(canvas_rgb(browser).astype(np.float32) - ulr).mean() > 0.5
