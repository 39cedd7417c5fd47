"""Natural-illumination reflectance fields of the glass, end to end on the simulated rig:
capture (``[phases.natural]`` through the real display driver and the emulators,
Mitsuba rendering), build (simulator's true cameras), estimation
(``reconstruct/natural_field.py``), relighting, and the paper's three tests against
Mitsuba (``evaluate/natural.py``):

(a) held-out natural images never used in the estimate, per pixel;
(b) the moving white bar (1/8 of the back display's width, 16 positions);
(c) a new viewpoint under an environment map: the captured views relit under
    ``builtin:uffizi`` and blended by ULR into a camera between them, against Mitsuba
    under the map restricted to the displays' solid angles (what the field covers).

Plan: 2 cameras × 1 table angle at half resolution (100 × 75), N = 30 images on the back
display (64 × 36 domain), K = 25 — N = 30 keeps the capture and estimate within the CI
budget (the display controller's 64 pattern slots no longer cap it: the runner uploads
patterns as they are shown, least recently used first); the paper's N = 200 is measured
by ``benchmarks/natural.py --sim``.

Thresholds (measured on this plan, contended machine, seeds fixed; PSNR over the
field's pixels, peak = the truth's brightest pixel there):
(a) measured 26.7 / 30.3 / 34.9 / 32.8 dB on this plan: require a mean ≥ 27 dB and every
    image ≥ 22 dB (~5 dB below the lowest measured; the renders' seeds are fixed).
(b) measured 28.4–33.7 dB over the 16 positions: require every position ≥ 22 dB (the
    issue's goal, 25 dB at N = 200, is met at N = 200 by ``benchmarks/natural.py --sim``:
    28.3 dB worst).
(c) truth: Mitsuba with the back display showing ``builtin:uffizi`` as the object centre
    sees it there (8-bit, scaled to its peak). At a captured viewpoint the field measured
    26.8 dB: require ≥ 25 dB and half the error of the environment turned upside
    down. At the new viewpoint (camera 2, ULR of the two relit views) measured 18.1 dB,
    relative error 1.27: ULR blends per-surfel colours of two views 15° apart, which a
    refracting object does not have — require only ≥ 15 dB and a relative error < 2
    (a sanity bound: this is the weak part, see the report).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import simcache

pytestmark = pytest.mark.slow

SCALE = 0.5
PLAN = (Path(__file__).parent / "natural_e2e_plan.toml").read_text()  # the capture plan, as `acquire` reads it


@pytest.fixture(scope="module")
def glass():
    from opacityhull.model import OpacityHullModel
    from opacityhull.reconstruct.natural_field import estimate_session_natural
    from opacityhull.session import Session

    plan = simcache.root() / "natural_e2e_plan.toml"
    if not plan.is_file() or plan.read_text() != PLAN:
        plan.write_text(PLAN)
    model_dir = simcache.built("glass", plan, SCALE, hull_res=64, cameras="groundtruth")
    sess = Session.open(simcache.captured("glass", plan, SCALE))
    model = OpacityHullModel.open(model_dir)
    views = [(v.camera_index, v.table_deg) for v in model.views]
    alphas = [model.load_view_rgba(i)[..., 3] for i in range(len(views))]
    out = simcache.root() / f"natural_e2e_fields_{model_dir.parent.name}"
    rep = estimate_session_natural(sess, views, [v.camera for v in model.views], alphas, out, n_kernels=25)
    return sess, model, out, rep


def _view(glass, i=0):
    from opacityhull.reconstruct import natural as nt
    from opacityhull.evaluate import natural as ne

    sess, model, out, rep = glass
    rig = ne.sim_rig_for_session(sess)
    v = model.views[i]
    f = nt.load_view_fields(out, v.id)["back"]
    mask = np.zeros(f.image_hw, bool)
    mask.reshape(-1)[f.pixel_index] = True
    return rig, v, f, mask


def _psnr_of(rig, v, f, mask, pat):
    from opacityhull.reconstruct import natural as nt
    from opacityhull.evaluate import natural as ne

    back = rig.geometry.display("back")
    tru = ne.render_display_image(rig, v.camera_index, v.table_deg, "back", pat, seed=3)
    est = nt.scatter_pixels(f, nt.relight_natural(f, pat.astype(np.float64) / 255 * back.max_radiance))
    return ne.compare(est, tru, mask)["psnr"]


def test_fields_written_and_reported(glass):
    sess, model, out, rep = glass
    assert rep["displays"] == {"back": {"domain_hw": [36, 64], "images": 30}}
    assert rep["pixels"] > 500 and 1 <= rep["kernels_mean"] <= 25
    assert len(rep["files"]) == len(model.views)


def test_a_held_out_natural_images(glass):
    from opacityhull.evaluate import natural as ne

    rig, v, f, mask = _view(glass)
    psnr = [_psnr_of(rig, v, f, mask, p) for p in ne.held_out_images(rig.geometry.display("back"), 4)]
    print("held-out PSNR", psnr)
    assert np.mean(psnr) >= 27 and min(psnr) >= 22, psnr


def test_b_moving_white_bar(glass):
    from opacityhull.evaluate import natural as ne

    rig, v, f, mask = _view(glass)
    psnr = [_psnr_of(rig, v, f, mask, p) for p in ne.bar_patterns(rig.geometry.display("back"), 16)]
    print("bar PSNR", psnr)
    assert len(psnr) == 16 and min(psnr) >= 22, psnr


def test_c_new_viewpoint_under_an_envmap(glass):
    from opacityhull.render import prepare_views, render_image
    from opacityhull.render.renderer import model_surfels
    from opacityhull.reconstruct import natural as nt
    from opacityhull.evaluate import natural as ne
    from opacityhull.relight.envmap import default_yaw_deg, load_envmap
    from opacityhull.riggeometry import RigGeometry

    sess, model, out, rep = glass
    rig = ne.sim_rig_for_session(sess)
    env = load_envmap("builtin:uffizi", yaw_deg=default_yaw_deg("builtin:uffizi"))
    surfels = model_surfels(model)
    centre = surfels.positions.mean(axis=0)
    cams = [v.camera for v in model.views]
    a = model.views[0].table_deg
    back = rig.geometry.display("back")
    # Truth: Mitsuba with the back display showing the environment as seen from the object
    # centre (8 bits, scaled to its peak), from camera 2 — between the captured cameras 1 and 3.
    L_env = nt.envmap_display_image(env, back, a, centre_m=centre)
    scale = 255.0 / L_env.max()
    pat = np.clip(np.round(L_env * scale), 0, 255).astype(np.uint8)
    truth = ne.render_display_image(rig, 2, a, "back", pat, seed=7) / scale * 255.0 / back.max_radiance
    new_cam = RigGeometry.view_camera(rig.true_cameras[2], a, name="new")

    def novel(image):
        relit = []
        for i, v in enumerate(model.views):
            f = nt.load_view_fields(out, v.id)["back"]
            part = nt.scatter_pixels(f, nt.relight_natural(f, image))
            alpha = model.load_view_rgba(i)[..., 3]
            relit.append(np.concatenate([part, alpha[..., None]], axis=-1).astype(np.float32))
        res = render_image(surfels, cams, prepare_views(cams, relit), new_cam)
        return res.rgba[..., :3] * res.rgba[..., 3:4]

    from opacityhull.sim.groundtruth import render_ground_truth

    cover = render_ground_truth(rig.scene, new_cam, spp=16, renderer=rig.renderer)["alpha"]
    mask = cover >= 0.99
    shown = pat.astype(np.float64) / scale  # the quantised environment, what the truth's display showed
    good = ne.compare(novel(shown), truth, mask)
    print("new viewpoint", good)
    assert mask.sum() > 100
    assert good["psnr"] >= 15 and good["rel_err"] < 2.0, good
    # the same environment at a captured viewpoint (no ULR): the field itself
    v = model.views[0]
    f = nt.load_view_fields(out, v.id)["back"]
    t0 = ne.render_display_image(rig, v.camera_index, a, "back", pat, seed=8) / scale * 255.0 / back.max_radiance
    m0 = np.zeros(f.image_hw, bool)
    m0.reshape(-1)[f.pixel_index] = True
    cap = ne.compare(nt.scatter_pixels(f, nt.relight_natural(f, shown)), t0, m0)
    upside = ne.compare(nt.scatter_pixels(f, nt.relight_natural(f, shown[::-1, ::-1])), t0, m0)
    print("captured viewpoint", cap, "upside down", upside)
    assert cap["psnr"] >= 25 and cap["rel_err"] < 0.5 * upside["rel_err"], (cap, upside)


def test_d_build_attaches_the_field_and_relight_uses_it(glass, tmp_path):
    """`build` estimates the field itself (a [natural] table in model.toml, files under
    natural/), and `relight` adds the display-domain part to the relit views: the glass,
    exactly black under the light array alone (delta paths), is no longer black."""
    from opacityhull.relight.runner import builtin_envmap, relight_model

    sess, model, out, rep = glass
    nat = model.meta.get("natural", {})
    assert nat.get("present") and nat["n_kernels"] == 25 and "back" in nat["displays"]
    assert (model.root / "natural" / model.views[0].id / "back.npz").is_file()
    s = relight_model(model.root, out=tmp_path / "relit", envmap=builtin_envmap("uffizi"))
    assert "natural_field_s" in s
    from opacityhull.imageio import read_exr

    img = read_exr(tmp_path / "relit" / "views" / f"{model.views[0].id}.exr")
    a = img[..., 3] > 0.5
    assert a.sum() > 100 and float(img[..., :3][a].mean()) > 1e-3
