"""Fitting on a small analytic scene: the fit beats its own start (the hull-like model)
on held-out views, is deterministic, resumes from its checkpoint to the same bytes,
and refuses another model's checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from opacityhull.model import Surfels, write_model
from opacityhull.optimize.config import FitConfig
from opacityhull.optimize.data import load_fit_data
from opacityhull.optimize.fit import OPTIMIZED_DIR, SPLATS_PLY, CheckpointError, fit_model, render_fitted, render_params
from opacityhull.optimize.surfelparams import start_params
from opacityhull.evaluate.loo import loo_metrics
from opacityhull.render.synthetic import make_sphere_model

TEST_VIEWS = (3, 8)
# a short schedule (150 steps, ~19 epochs of 8 views) with densification twice; the
# position rate is 3x the default's, as this hull is 10 % too large (2 px at 64x48)
CFG = FitConfig(
    lr_position=1e-2,
    lr_position_final=1e-4,
    iterations=150,
    densify_from=40,
    densify_until=120,
    densify_every=40,
    sh_degree_every=50,
    checkpoint_every=0,
)


def _scene(root: Path, *, inflate: float = 1.1, texture_freq: float = 1.0, width: int = 64, n_surfels: int = 3000):
    """An analytic textured sphere seen by 10 views on a ring (36° apart), its surfels on
    a sphere ``inflate`` times too large — a visual hull's error — and their radii with it."""
    m = make_sphere_model(
        n_surfels,
        width=width,
        height=width * 3 // 4,
        table_step_deg=36,
        elevations_deg=(20.0,),
        texture_freq=texture_freq,
    )
    c = np.asarray(m.scene.centre)
    s = m.surfels
    sf = Surfels(c + (s.positions - c) * inflate, s.normals, s.radii * inflate, s.visibility, s.n_views)
    write_model(root, views=m.views, surfels=sf, view_rgba=m.view_rgba, rig=m.rig)
    return m


def _train(m):
    return [i for i in range(len(m.views)) if i not in TEST_VIEWS]


def _test_psnr(m, render) -> float:
    return float(np.mean([loo_metrics(m.view_rgba[i], render(m.views[i].camera))["psnr"] for i in TEST_VIEWS]))


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit") / "sphere"
    return root, _scene(root)


def test_fit_beats_the_start_on_held_out_views(sphere):
    root, m = sphere
    train = _train(m)
    d = load_fit_data(root, train)
    p0 = start_params(d.surfels.positions, d.surfels.normals, d.surfels.radii, d.sh_dc, sh_degree=0)
    start = _test_psnr(m, lambda cam: render_params(p0, cam))
    rep = fit_model(root, train_views=train, config=CFG)
    fitted = _test_psnr(m, lambda cam: render_fitted(root, cam))
    # measured (seeds 0-3, this scene): start 12.1 dB, fitted 20.5-21.7 dB (a gain of
    # 8.5-9.7 dB); the margin is half the smallest gain
    assert fitted > start + 4.0, (start, fitted)
    assert len(rep.loss) == CFG.iterations and np.all(np.isfinite(rep.loss))
    assert np.mean(rep.loss[-20:]) < np.mean(rep.loss[:20])
    assert (root / OPTIMIZED_DIR / SPLATS_PLY).is_file() and (root / OPTIMIZED_DIR / "fit.json").is_file()


def test_fit_is_deterministic_and_resumes_to_the_same_bytes(sphere, tmp_path):
    root, m = sphere
    train = _train(m)
    cfg = FitConfig(iterations=40, densify_from=10, densify_until=30, densify_every=10, checkpoint_every=15)
    fit_model(root, train_views=train, config=cfg)
    first = (root / OPTIMIZED_DIR / SPLATS_PLY).read_bytes()
    fit_model(root, train_views=train, config=cfg)
    assert (root / OPTIMIZED_DIR / SPLATS_PLY).read_bytes() == first

    class Stop(Exception):
        pass

    def stop_at_20(p):
        if p.iteration == 20:
            raise Stop

    ck = tmp_path / "ck"
    ck.mkdir()
    with pytest.raises(Stop):
        fit_model(root, train_views=train, config=cfg, progress=stop_at_20, checkpoint_dir=ck)
    assert (ck / "fit_checkpoint.npz").is_file()
    rep = fit_model(root, train_views=train, config=cfg, checkpoint_dir=ck)
    assert rep.resumed_from == 15
    assert (root / OPTIMIZED_DIR / SPLATS_PLY).read_bytes() == first


def test_a_checkpoint_of_another_model_is_refused(sphere, tmp_path):
    root, m = sphere
    train = _train(m)
    cfg = FitConfig(iterations=10, densify_from=100, checkpoint_every=5)
    ck = tmp_path / "ck"
    ck.mkdir()
    fit_model(root, train_views=train, config=cfg, checkpoint_dir=ck)
    other = tmp_path / "other"
    _scene(other, inflate=1.05)
    with pytest.raises(CheckpointError, match="another model"):
        fit_model(other, train_views=train, config=cfg, checkpoint_dir=ck)
    assert not (other / OPTIMIZED_DIR).exists()
    with pytest.raises(CheckpointError, match="other train views"):
        fit_model(root, train_views=train[:-1], config=cfg, checkpoint_dir=ck)


def test_mode_none_writes_nothing(sphere, tmp_path):
    m = _scene(tmp_path / "m")
    rep = fit_model(tmp_path / "m", train_views=_train(m), config=FitConfig(mode="none", iterations=0))
    assert rep.iterations == 0 and not (tmp_path / "m" / OPTIMIZED_DIR).exists()


def test_a_thinned_start_densifies_and_stays_finite(sphere):
    root, m = sphere
    cfg = FitConfig(
        iterations=12,
        max_start_surfels=1000,
        densify_from=4,
        densify_until=10,
        densify_every=4,
        densify_grad_threshold=0.0,
        checkpoint_every=0,
    )
    rep = fit_model(root, train_views=_train(m), config=cfg)
    assert rep.n_surfels_start == 1000 and rep.n_surfels_end > 1000
    assert np.all(np.isfinite(rep.loss))


def test_a_time_budget_stops_the_fit_and_still_writes(sphere):
    root, m = sphere
    cfg = FitConfig(iterations=100_000, time_budget_s=0.5, densify_from=10**6, checkpoint_every=0)
    rep = fit_model(root, train_views=_train(m), config=cfg)
    assert rep.stopped_by == "time_budget" and 0 < rep.iterations < 100_000
    assert (root / OPTIMIZED_DIR / SPLATS_PLY).is_file()
