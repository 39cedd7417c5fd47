"""The analytic paper-scale session writer (opacityhull.acquire.synthetic): the paper's
layout, a session that `session verify` accepts, mattes equal to the true coverage,
one-light images that are Lambertian, and a session `build` turns into a model."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from opacityhull.acquire.synthetic import SyntheticSessionConfig, write_synthetic_session
from opacityhull.errors import InputError

TINY = dict(n_cameras=2, n_table=4, width_px=40, height_px=30)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "session"
    info = write_synthetic_session(root, SyntheticSessionConfig(**TINY, n_light_dirs=8, noise=0.0))
    return root, info


def test_defaults_are_the_paper_layout():
    cfg = SyntheticSessionConfig()
    assert (cfg.n_cameras, cfg.n_table, cfg.n_views) == (6, 72, 432)
    n_lights, arrays = SyntheticSessionConfig(n_light_dirs=60).light_layout()
    assert (n_lights, len(arrays)) == (4, 15)  # the paper's 4 lights x 15 array angles
    assert SyntheticSessionConfig(n_light_dirs=6).light_layout() == (6, [0.0])


@pytest.mark.parametrize(
    "bad", [dict(n_cameras=0), dict(width_px=2.5), dict(n_light_dirs=-1), dict(noise=float("nan"))]
)
def test_bad_config_names_the_field(bad):
    with pytest.raises(InputError, match=next(iter(bad))):
        SyntheticSessionConfig(**bad)


def test_writes_every_phase_and_session_verify_accepts_it(tiny):
    root, info = tiny
    assert len(info["views"]) == 8
    # per view: 1 pair x (with, without object) x 2 patterns + lightfield + 8 one-light images
    assert info["n_images"] == 8 * (4 + 1 + 8)
    for cam in ("cam0", "cam1"):
        assert (root / "calibration" / f"{cam}.yaml").is_file()
    r = subprocess.run(
        [str(Path(sys.executable).with_name("opacityhull")), "session", "verify", str(root), "--json"],
        capture_output=True,
        text=True,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["ok"] is True
    assert out["per_phase"] == {"matting": 32, "lightfield": 8, "reflectance": 64}


def test_noise_free_matte_equals_the_true_coverage(tiny):
    from opacityhull.imageio import read_exr
    from opacityhull.reconstruct.perview import matte_view, view_tasks

    root, _ = tiny
    for t in view_tasks(root)[:3]:
        a = matte_view(t)
        true = read_exr(root / "groundtruth" / "alpha" / f"{t.view}.exr")[..., 0]
        assert set(np.unique(true)) <= {0.0, 1.0} and true.sum() > 10  # 1 ray per pixel: binary
        assert np.abs(a - true).max() < 1e-3


def test_one_light_images_are_lambertian(tiny):
    """Radiance under light l is albedo * 0.85 * max(n.l, 0): it scales with the cosine, so
    on the sphere's lit side the ratio of two lights' images equals the ratio of cosines."""
    from opacityhull.acquire.synthetic import CENTRE_M, CORE_R_M, pixel_rays, sphere_hit_t
    from opacityhull.riggeometry import RigGeometry
    from opacityhull.session import Session

    root, info = tiny
    s = Session.open(root)
    geo = info["geometry"]
    c, a = info["views"][1]
    recs = {(r.light, r.lights_deg): r for r in s.select(phase="reflectance", camera=c, table_deg=a)}
    assert len(recs) == 8
    cam = RigGeometry.view_camera(geo.nominal_cameras()[c], a)
    o, d = pixel_rays(cam, 1)
    t = sphere_hit_t(o, d, CENTRE_M, CORE_R_M)
    hit = np.isfinite(t)
    n = (o + t[hit, None] * d[hit] - CENTRE_M) / CORE_R_M
    (k0, r0), (k1, r1) = sorted(recs.items())[:2]
    cos0 = n @ geo.light_direction_object(k0[0], a, k0[1])
    cos1 = n @ geo.light_direction_object(k1[0], a, k1[1])
    i0 = s.load_image(r0).reshape(-1, 3)[hit]
    i1 = s.load_image(r1).reshape(-1, 3)[hit]
    both = (cos0 > 0.2) & (cos1 > 0.2)
    assert both.sum() > 5
    np.testing.assert_allclose(i1[both] / i0[both], np.repeat((cos1 / cos0)[both, None], 3, axis=1), rtol=1e-3)
    assert np.all(i0.reshape(-1, 3)[cos0 < 0] == 0)  # no light from behind
    assert np.all(s.load_image(r0).reshape(-1, 3)[~hit] == 0)  # displays dark


def test_refuses_a_non_empty_folder(tmp_path):
    (tmp_path / "x").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        write_synthetic_session(tmp_path, SyntheticSessionConfig(**TINY))


def test_builds_into_a_model(tiny, tmp_path):
    from opacityhull.model import OpacityHullModel
    from opacityhull.reconstruct.build import BuildConfig, build_model

    root, info = tiny
    rep = build_model(root, tmp_path / "model", config=BuildConfig(hull_res=32, pictures=False))
    assert rep.camera_source.startswith("calibration/")
    assert rep.backdrop_source == "object-absent captures"
    m = OpacityHullModel.open(tmp_path / "model")
    assert len(m.views) == 8
    assert m.surfels.positions.shape[0] > 100
    # a visual hull contains the object: no surfel inside the sphere by more than about a
    # voxel of the 32^3 grid (~3 mm); 8 views carve loosely, so the median sits outside
    from opacityhull.acquire.synthetic import CENTRE_M, CORE_R_M

    r = np.linalg.norm(np.asarray(m.surfels.positions) - CENTRE_M, axis=1)
    assert r.min() > CORE_R_M - 0.004
    assert 0.0 < np.median(r - CORE_R_M) < 0.25 * CORE_R_M
    assert len(m.light_samples) == 8
    # the per-view task the executor runs is the build's matting step, bit for bit
    from opacityhull.reconstruct.perview import matte_view, view_tasks

    for t in view_tasks(root)[:3]:
        assert np.array_equal(m.load_view_rgba(m.view_index(t.view))[..., 3], matte_view(t))


def test_same_session_whatever_the_writer_threads(tmp_path):
    from opacityhull.session import Session

    cfg = dict(n_cameras=1, n_table=3, width_px=24, height_px=18, n_light_dirs=4)
    for th in (1, 3):
        write_synthetic_session(tmp_path / f"t{th}", SyntheticSessionConfig(**cfg, threads=th, groundtruth=False))
    recs = [[(r.id, r.path, r.sha256) for r in Session.open(tmp_path / f"t{th}").records] for th in (1, 3)]
    assert len(recs[0]) == 3 * (4 + 1 + 4) and recs[0] == recs[1]
