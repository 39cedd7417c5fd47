"""Relighting a model built with ``--optimize`` (#29 item 4): ``relight --view/--orbit``
draws the fitted splats, each with the relit views' Unstructured-Lumigraph colour sampled
where the splat projects (``FittedSplats.render_relit``); on the analytic Lambertian
sphere (exact relit truth) novel views relit that way are no worse than the hull's.
``eval relight`` scores the relit captured views, which no surfel touches: the same for a
fitted model and its unfitted build (``benchmarks/relight_fitted.py`` measures the
held-out views of a simulated session against Mitsuba)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

import fitted
from exrkit import read_rgba_openexr
from opacityhull.cli import app
from opacityhull.model import OpacityHullModel


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "4000"})


@pytest.fixture(scope="module")
def fitted_sphere(tmp_path_factory):
    """The analytic relit sphere (4 table angles × 2 cameras of 48×40, 4 × 15 lights),
    its surfels fitted to the 8 views (tests/fitted.py's 60-step schedule)."""
    from opacityhull.optimize.config import fit_preset
    from opacityhull.optimize.fit import fit_model
    from opacityhull.relight.synthetic import write_sphere_model

    root = tmp_path_factory.mktemp("relit_fitted") / "sphere"
    write_sphere_model(root, width=48, height=40, n_surfels=4000)
    V = len(OpacityHullModel.open(root).views)
    fit_model(root, train_views=list(range(V)), config=replace(fit_preset("fast"), **fitted.FIT))
    return root


def test_novel_views_relit_on_the_fitted_splats_are_no_worse_than_the_hull(fitted_sphere):
    from opacityhull.evaluate.metrics import relight_metrics
    from opacityhull.evaluate.relight import MASK_ALPHA, _truth_renderer, find_scene
    from opacityhull.relight.envmap import load_envmap
    from opacityhull.relight.relit import Relighter
    from opacityhull.render import RenderConfig, prepare_views, render_image
    from opacityhull.render.renderer import model_surfels
    from opacityhull.render.splats import FittedSplats

    m = OpacityHullModel.open(fitted_sphere)
    env = load_envmap("builtin:grace")
    kind, ref = find_scene(m)
    assert kind == "analytic"
    truth_fn = _truth_renderer(m, kind, ref, spp=16)
    R = Relighter(m)
    relit = [R.relight_view(i, envmap=env) for i in range(len(m.views))]
    cams = [v.camera for v in m.views]
    surfels = model_surfels(m)
    pv = prepare_views(cams, relit)
    fs = FittedSplats.load(fitted_sphere)
    ulr, fit = [], []
    for i in range(len(m.views)):  # each view left out of the blend: a novel view of the other 7
        truth, cover = truth_fn(i, env)
        mask = cover >= MASK_ALPHA
        u = render_image(surfels, cams, pv, cams[i], config=RenderConfig(), exclude_views=[i]).premul
        f = fs.render_relit(cams[i], surfels, cams, relit, exclude_views=[i]).premul
        assert np.isfinite(f).all() and f[..., 3].max() > 0.9
        ulr.append(relight_metrics(u[..., :3], truth, mask)["rel_err"])
        fit.append(relight_metrics(f[..., :3], truth, mask)["rel_err"])
    print(f"relit novel views, mean relative error: hull by ULR {np.mean(ulr):.4f}, fitted splats {np.mean(fit):.4f}")
    # measured: hull 0.125 (0.026-0.255 per view), fitted 0.100 (0.068-0.143)
    assert np.mean(fit) <= np.mean(ulr)


def test_relight_view_draws_the_fitted_splats_and_bad_renderer_exits_2(fitted_sphere, tmp_path):
    from opacityhull.relight.envmap import load_envmap
    from opacityhull.relight.relit import Relighter
    from opacityhull.relight.runner import view_camera
    from opacityhull.render.renderer import model_surfels
    from opacityhull.render.splats import FittedSplats

    r = run("relight", fitted_sphere, "--envmap", "builtin:grace", "--view", "1,45", "--out", tmp_path / "r", "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["renderer"] == "fitted"
    got, header = read_rgba_openexr(s["view"]["exr"])
    assert header["opacityhull:alpha"] == "premultiplied"
    m = OpacityHullModel.open(fitted_sphere)
    R = Relighter(m)
    env = load_envmap("builtin:grace", yaw_deg=180.0)  # the CLI's default yaw for builtin: probes
    relit = [R.relight_view(i, envmap=env) for i in range(len(m.views))]
    cams = [v.camera for v in m.views]
    want = FittedSplats.load(fitted_sphere).render_relit(view_camera(m, 1, 45.0), model_surfels(m), cams, relit)
    np.testing.assert_allclose(got, want.premul, rtol=1e-5, atol=1e-6)
    plain = tmp_path / "plain"
    shutil.copytree(fitted_sphere, plain)
    shutil.rmtree(plain / "optimized")
    out = tmp_path / "x"
    r = run("relight", plain, "--envmap", "builtin:grace", "--view", "1,45", "--out", out, "--renderer", "fitted")
    err = " ".join(r.stderr.split())
    assert r.exit_code == 2 and "--renderer fitted" in err and "--optimize" in err and not out.exists()
    r = run("relight", plain, "--envmap", "builtin:grace", "--view", "1,45", "--out", tmp_path / "u", "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["renderer"] == "ulr"
