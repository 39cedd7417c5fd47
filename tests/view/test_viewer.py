"""The browser viewer: bundle layout read back in NumPy, and the page in a real headless
Chromium (software WebGL2) against the CPU renderer."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import urllib.request

import numpy as np
import pytest
from helpers import copy_without, load_viewer, viewer_error

from opacityhull.imageio import srgb_decode, srgb_encode
from opacityhull.model import OpacityHullModel
from opacityhull.view.bundle import VIEWER_FORMAT, read_bundle, write_bundle
from opacityhull.view.server import BundleServer


def test_bundle_layout_reads_back(view_model, bundle):
    from scipy.spatial import KDTree  # (cKDTree is untyped: no stub for the C module)

    from opacityhull.render.spg import LEAF_DTYPE, NODE_DTYPE

    root, m = view_model
    out, summary = bundle
    man, pos, rec = read_bundle(out)
    assert man["format"] == VIEWER_FORMAT and man["n_surfels"] == len(m.surfels) and man["n_views"] == len(m.views)
    assert len(man["chunks"]) > 2 and man["chunks"][0]["count"] == 500
    assert [c["first"] for c in man["chunks"]] == list(np.cumsum([0] + [c["count"] for c in man["chunks"]])[:-1])
    assert len(rec) == len(pos) == man["n_nodes"] > len(m.surfels)
    nf = man["n_float"]  # the packed inner nodes come first, coarse first; every leaf is octree-coded
    assert np.all(np.diff(rec["r_max"][:nf]) <= 0) and np.all(rec["r_min"][:nf] > 0)
    L, H, S = man["leaves"], man["positions"], man["spg"]
    assert L["first"] == nf and L["count"] == man["n_nodes"] - nf == len(m.surfels)
    assert np.all(rec["r_min"][nf:] == 0) and np.all(rec["r_max"][nf:] <= L["r_max_max"])
    # a chunk prefix is a complete cut above its r_max_last: each node's parent (the node
    # whose r_min is the node's r_max) is earlier in the stream
    assert all(c["r_max_last"] >= rec["r_max"][c["first"] + c["count"] - 1] for c in man["chunks"])
    # match leaves to surfels by their normals (on the sphere a normal is its surfel: 3° apart,
    # quantised to < 0.06° by the 12-bit octahedral code)
    leaf = rec["r_min"] == 0
    ang_d, idx = KDTree(m.surfels.normals).query(rec["nrm"][leaf], 1)
    np.testing.assert_array_equal(np.sort(idx), np.arange(len(m.surfels)))
    assert np.degrees(ang_d.max()) < 0.06
    # positions: within half a cell diagonal (octree cell + normal offset)
    h = H["cell_m"]
    assert np.linalg.norm(pos[leaf] - m.surfels.positions[idx], axis=1).max() <= np.sqrt(3) * h
    # radii within a log step, visibility exact (lossless dictionary)
    np.testing.assert_allclose(rec["radius"][leaf], m.surfels.radii[idx], rtol=1e-5)
    vis = np.unpackbits(rec["vis"][leaf].view(np.uint8).reshape(leaf.sum(), -1), axis=1, bitorder="little")
    np.testing.assert_array_equal(vis[:, : len(m.views)].astype(bool), m.surfels.visible_bool()[idx])
    assert not vis[:, len(m.views) :].any()
    # inner nodes: anisotropic radius tensors (symmetric, positive semi-definite, flat along the normal)
    cov = rec["cov"][:nf].astype(np.float64)
    R = cov[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    ev = np.linalg.eigvalsh(R)  # ascending; float32 storage: relative to each node's largest
    assert np.all(ev[:, 0] > -1e-5 * ev[:, 2]) and np.all(ev[:, 1] > 0)
    n = rec["nrm"][:nf].astype(np.float64)
    assert np.all(np.abs(np.einsum("mi,mij,mj->m", n, R, n)) < 1e-5 * ev[:, 2])
    assert not rec["cov"][nf:].any()
    # the budget table: t = 0 draws exactly the leaves, larger t fewer splats
    assert man["lod"]["t"][0] == 0 and man["lod"]["splats"][0] == len(m.surfels)
    assert np.all(np.diff(man["lod"]["splats"]) <= 0) and man["lod"]["splats"][-1] == 1
    V = man["views"]
    tex = np.frombuffer((out / V["file"]).read_bytes(), np.uint8).reshape(
        len(m.views), V["layer_height"], V["layer_width"], 4
    )
    for v in (0, 11):
        rgba = m.view_rgba[v]
        np.testing.assert_allclose(tex[v, ..., 3] / 255, rgba[..., 3], atol=0.5 / 255 + 1e-6)
        pre = srgb_decode(tex[v, ..., :3] / 255.0)
        assert np.abs(pre - rgba[..., :3] * rgba[..., 3:4]).max() < 0.01
        np.testing.assert_allclose(V["layers"][v]["world_from_cam"], m.views[v].camera.world_from_cam.ravel())
    model_bytes = (
        sum(c["bytes"] for c in man["chunks"])
        + S["codebooks"]["bytes"]
        + S["visibility"]["bytes"]
        + L["bytes"]
        + H["codes_bytes"]
        + H["counts_bytes"]
        + H["offsets_bytes"]
    )
    assert summary["bytes_per_surfel"] == pytest.approx(model_bytes / man["n_surfels"])
    assert sum(c["bytes"] for c in man["chunks"]) == nf * NODE_DTYPE.itemsize == nf * 17
    assert L["bytes"] == L["count"] * LEAF_DTYPE.itemsize == L["count"] * 8
    assert summary["bytes_per_surfel"] < 35  # the 44-byte records and float positions of format 2: 70


def test_bundle_refuses_to_replace_other_folders(view_model, tmp_path):
    from opacityhull.errors import FormatError, InputError

    root, _ = view_model
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="replaces only an earlier `view` output.*notes.txt"):
        write_bundle(root, keep)
    assert (keep / "notes.txt").read_text() == "mine"
    with pytest.raises(FormatError, match="model.toml"):
        write_bundle(tmp_path / "nothing", tmp_path / "b")
    with pytest.raises(InputError, match="k in"):
        write_bundle(root, tmp_path / "b", k=9)
    with pytest.raises(InputError, match="--offset-bits 9"):
        write_bundle(root, tmp_path / "b", offset_bits=9)
    with pytest.raises(InputError, match="--position-cell-m"):
        write_bundle(root, tmp_path / "b", position_cell_m=float("nan"))
    assert not (tmp_path / "b").exists()


def test_cli_out_alone_writes_bundle_and_bad_model_exits_4(view_model, tmp_path):
    root, _ = view_model
    exe = [sys.executable, "-m", "opacityhull.cli", "view"]
    r = subprocess.run(exe + [str(root), "--out", str(tmp_path / "b"), "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["surfels"] == 4000 and (tmp_path / "b" / "index.html").is_file() and "url" not in s
    (tmp_path / "empty").mkdir()  # a folder, but not a model (an --out inside it is refused first, #35)
    r = subprocess.run(exe + [str(tmp_path / "empty"), "--out", str(tmp_path / "c")], capture_output=True, text=True)
    err = " ".join(r.stderr.split())  # rich wraps long lines
    assert r.returncode == 4 and "is not a model" in err and "model.toml not found" in err and "Traceback" not in err


def test_server_serves_bundle(bundle):
    out, _ = bundle
    with BundleServer(out) as srv:
        assert srv.url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(srv.url + "manifest.json", timeout=10) as r:
            assert json.loads(r.read())["format"] == VIEWER_FORMAT
        with urllib.request.urlopen(srv.url + "viewer.js", timeout=10) as r:
            assert "javascript" in r.headers["Content-Type"]


# --------------------------------------------------------------------------- in the browser


def test_browser_matches_cpu_renderer(browser, view_model, bundle):
    """A captured camera set through the JS hook: PSNR ≥ 30 dB inside the mask against
    render_model; frames/s of an orbit are printed, not asserted (software GL)."""
    from opacityhull.render.config import RenderConfig
    from opacityhull.render.renderer import render_model
    from opacityhull.view.browser import canvas_rgb

    root, m = view_model
    out, _ = bundle
    model = OpacityHullModel.open(root)
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        assert (
            browser.execute_script("return window.opacityhull.viewer.loaded")
            == json.loads((out / "manifest.json").read_text())["n_nodes"]
        )
        # the page's octree decoder (with the normal offsets) gives the NumPy reference's positions
        man, pos, _ = read_bundle(out)
        js = np.array(browser.execute_script("return window.opacityhull.leafPositions()"), np.float64).reshape(-1, 3)
        assert js.shape == (man["leaves"]["count"], 3)
        np.testing.assert_allclose(js, pos[man["n_float"] :], rtol=0, atol=2e-7 * man["positions"]["size"])
        lv = browser.execute_script("return window.opacityhull.octree.levels")
        assert len(lv) == man["positions"]["depth"] + 1 and lv[-1] == man["positions"]["n_cells"] and lv[0] == 1
        # The page draws the bundle's surfels (octree-coded leaf positions) with per-surfel
        # ULR: against the CPU renderer of the same surfels in its surfel shading mode it must
        # agree closely; against the exact model (CPU default, pixel shading) the figure
        # includes the position coding's loss (cell = surfel spacing, 3 offset bits).
        from opacityhull.render.renderer import prepare_model_views, render_image
        from opacityhull.view.bundle import decoded_surfels

        decoded = decoded_surfels(out, n_views=len(m.views))
        pv = prepare_model_views(model)
        cams = [v.camera for v in model.views]
        # the bundle's background (18 % grey by default) around the model, 8-bit sRGB exactly;
        # the comparisons below are premultiplied, i.e. over black
        browser.execute_script("return window.opacityhull.setCamera(2)")
        corner = srgb_decode(canvas_rgb(browser)[:2, :2].astype(np.float32) / 255.0)
        bg8 = srgb_decode(np.round(srgb_encode(np.asarray(man["background"], np.float32)) * 255) / 255)
        assert man["background"] == [0.18, 0.18, 0.18] and np.abs(corner - bg8).max() < 1e-6
        browser.execute_script("return window.opacityhull.setBackground([0, 0, 0])")
        for vi in (2, 13):
            browser.execute_script(f"return window.opacityhull.setCamera({vi})")
            gpu = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
            cpu = render_model(model, m.views[vi].camera, config=RenderConfig(k=4, threads=1))
            same = render_image(decoded, cams, pv, cams[vi], config=RenderConfig(k=4, threads=1, shading="surfel"))
            pre = cpu.rgba[..., :3] * cpu.rgba[..., 3:4]
            mask = cpu.rgba[..., 3] > 0.01
            assert mask.sum() > 300
            psnr = 10 * np.log10(1.0 / np.mean((gpu - pre)[mask] ** 2))
            psnr_same = 10 * np.log10(1.0 / np.mean((gpu - same.rgba[..., :3] * same.rgba[..., 3:4])[mask] ** 2))
            print(
                f"view {vi}: browser vs CPU PSNR inside the mask: {psnr_same:.1f} dB (same surfels), "
                f"{psnr:.1f} dB (exact model)"
            )
            assert psnr_same >= 35.0
            assert psnr >= 27.0
            # outside the silhouette the page shows the background (black) exactly
            far = ~(np.abs(cpu.rgba[..., 3]) > 0) & (cpu.weight == 0) & (same.weight == 0)
            assert np.abs(gpu[far]).max() < 1e-6
        # a quarter of the splats: a coarser cut of the point tree, close to the full picture
        full = canvas_rgb(browser).astype(np.float32) / 255.0
        browser.execute_script(f"return window.opacityhull.setBudget({len(m.surfels) // 4})")
        quarter = canvas_rgb(browser).astype(np.float32) / 255.0
        browser.execute_script("return window.opacityhull.setBudget(null)")
        again = canvas_rgb(browser).astype(np.float32) / 255.0
        np.testing.assert_array_equal(again, full)
        d = np.mean((srgb_decode(quarter) - srgb_decode(full))[mask] ** 2)
        print(f"budget N/4 vs full in the browser: {10 * np.log10(1 / d):.1f} dB")
        assert 0 < d < 10 ** (-2.0)
        ms = browser.execute_script("return window.opacityhull.benchmark(10)")
        print(f"orbit: {ms:.1f} ms/frame ({1000 / ms:.1f} frames/s, software GL, 4000 surfels, 64x48)")
        # k and background through the hook change the picture
        browser.execute_script("window.opacityhull.setBackground([1, 1, 1]); return window.opacityhull.setCamera(13)")
        white = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
        far = (cpu.weight == 0) & (same.weight == 0)  # the page draws the decoded surfels
        assert np.all(white[far] > 0.99)


def test_browser_missing_chunk_shows_error(browser, bundle, tmp_path):
    out, _ = bundle
    text = viewer_error(browser, copy_without(out, tmp_path / "broken", "nodes_002.bin"))
    assert "nodes_002.bin" in text and "HTTP 404" in text and "incomplete" in text


def test_browser_corrupt_octree_code_shows_error(browser, bundle, tmp_path):
    """A truncated deflate stream and a stream one level short: readable errors naming the file."""
    import zlib

    out, _ = bundle
    man = json.loads((out / "manifest.json").read_text())
    H = man["positions"]
    broken = tmp_path / "oct"
    shutil.copytree(out, broken)
    p = broken / H["codes_file"]
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    text = viewer_error(browser, broken)
    assert "positions.oct" in text and ("truncated" in text or "inflated" in text)
    codes = zlib.decompress((out / H["codes_file"]).read_bytes())
    short = zlib.compress(codes[:-5], 9)
    p.write_bytes(short)
    man["positions"]["codes_bytes"] = len(short)
    (broken / "manifest.json").write_text(json.dumps(man))
    text = viewer_error(browser, broken)
    assert "octree position code" in text and "ends at level" in text


def test_browser_truncated_chunk_and_not_a_bundle(browser, bundle, tmp_path):
    out, _ = bundle
    broken = tmp_path / "trunc"
    shutil.copytree(out, broken)
    p = broken / "nodes_001.bin"
    p.write_bytes(p.read_bytes()[:-48])
    assert "truncated" in viewer_error(browser, broken)
    empty = tmp_path / "empty"
    empty.mkdir()
    for f in ("index.html", "viewer.js"):
        shutil.copyfile(out / f, empty / f)
    assert "not an opacityhull viewer bundle" in viewer_error(browser, empty)


def test_browser_environment_map_background(browser, view_model, tmp_path):
    """--envmap: the page composites over the same equirectangular lookup as the CPU
    renderer (render/background.py), yaw included."""
    from opacityhull.relight.envmap import resolve_envmap_path
    from opacityhull.render.background import load_background
    from opacityhull.render.config import RenderConfig
    from opacityhull.render.renderer import render_model
    from opacityhull.view.browser import canvas_rgb

    root, m = view_model
    out = tmp_path / "env"
    s = write_bundle(root, out, envmap="builtin:uffizi", env_yaw_deg=150.0)
    assert s["envmap"]["yaw_deg"] == 150.0 and (out / "envmap.bin").stat().st_size == s["envmap"]["bytes"]
    env = load_background(str(resolve_envmap_path("builtin:uffizi")), yaw_deg=150.0, kind="envmap")
    model = OpacityHullModel.open(root)
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        browser.execute_script("window.opacityhull.setCamera(7); return window.opacityhull.setBackground('envmap')")
        gpu = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
        cpu = render_model(model, m.views[7].camera, config=RenderConfig(threads=1))
        ref = np.clip(cpu.over(env), 0, 1)
        bg = cpu.weight == 0
        assert bg.mean() > 0.5
        assert 10 * np.log10(1 / np.mean((gpu - ref)[bg] ** 2)) > 45  # 8-bit sRGB output
        assert 10 * np.log10(1 / np.mean((gpu - ref) ** 2)) > 30
        # turning the map changes the background
        browser.execute_script("return window.opacityhull.setEnvYaw(60)")
        turned = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
        assert np.mean(np.abs(turned - gpu)[bg]) > 0.01


def test_cli_serves_until_terminated(view_model):
    """Without --out: a temporary bundle served on 127.0.0.1, URL in the JSON, removed on SIGTERM."""
    import signal
    from pathlib import Path

    root, _ = view_model
    p = subprocess.Popen(
        [sys.executable, "-m", "opacityhull.cli", "view", str(root), "--port", "0", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert p.stdout is not None
        s = json.loads(p.stdout.readline())
        assert s["url"].startswith("http://127.0.0.1:")
        with urllib.request.urlopen(s["url"], timeout=10) as r:
            assert b"viewer.js" in r.read()
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=20) == 0
        assert not Path(s["out"]).exists()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_browser_draws_statistical_nodes_as_the_cpu_renderer(browser, view_model, bundle):
    """At a budget of N/16 the page draws the packed inner nodes as anisotropic EWA splats
    from their radius tensors: against the CPU renderer of the same cut (read_bundle's
    decoder, ``render_image(splat_cov=)``, per-surfel shading) the pictures agree."""
    from opacityhull.render.config import RenderConfig
    from opacityhull.render.renderer import prepare_model_views, render_image
    from opacityhull.render.runner import _seed_surfel_areas
    from opacityhull.view.browser import canvas_rgb
    from opacityhull.view.bundle import bundle_cut

    root, m = view_model
    out, _ = bundle
    model = OpacityHullModel.open(root)
    pv = prepare_model_views(model)
    cams = [v.camera for v in model.views]
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        browser.execute_script("return window.opacityhull.setBackground([0, 0, 0])")
        for vi in (2, 13):
            browser.execute_script(f"window.opacityhull.setCamera({vi}); return window.opacityhull.setBudget(250)")
            gpu = srgb_decode(canvas_rgb(browser).astype(np.float32) / 255.0)
            tau = browser.execute_script("return window.opacityhull.viewer.lastTau")
            s, areas, cov = bundle_cut(out, tau, cams[vi].centre_world, n_views=len(m.views))
            assert (cov.any(axis=1) & (areas > 0)).sum() > 0 and len(s) < 400  # a coarse cut of inner nodes
            _seed_surfel_areas(s, areas)
            cpu = render_image(
                s, cams, pv, cams[vi], config=RenderConfig(k=4, threads=1, shading="surfel"), splat_cov=cov
            )
            pre = cpu.rgba[..., :3] * cpu.rgba[..., 3:4]
            mask = (cpu.rgba[..., 3] > 0.01) | (gpu.max(axis=2) > 0.01)
            psnr = 10 * np.log10(1.0 / np.mean((gpu - pre)[mask] ** 2))
            print(f"view {vi}: {len(s)} statistical splats, browser vs CPU {psnr:.1f} dB")
            assert psnr >= 35.0
        browser.execute_script("return window.opacityhull.setBudget(null)")
