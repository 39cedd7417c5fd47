"""One EXR convention (#33): relight's ``--view`` / ``--orbit`` EXRs held straight colour
and its ``views/`` premultiplied, with nothing to tell them apart. Every one is now
premultiplied and says so; over the environment, at the run's exposure, each file
gives its PNG."""

from __future__ import annotations

import numpy as np

from exrkit import over_premultiplied, srgb8
from opacityhull.imageio import read_png


def test_relight_exrs_composite_like_their_pngs(sphere_model, tmp_path):
    from opacityhull.model import OpacityHullModel
    from opacityhull.relight.envmap import default_yaw_deg, load_envmap
    from opacityhull.relight.runner import orbit_cameras, relight_model, view_camera
    from opacityhull.render.background import envmap_background

    env = load_envmap("builtin:pisa", yaw_deg=default_yaw_deg("builtin:pisa"))
    out = tmp_path / "o"
    s = relight_model(sphere_model, out=out, envmap=env, view=(1, 45.0), orbit=2)
    model = OpacityHullModel.open(sphere_model)
    exposure = s["exposure"]
    pairs = [(out / f"view_{view_camera(model, 1, 45.0).name}", view_camera(model, 1, 45.0))]
    pairs += [(out / "orbit" / f"frame_{k:03d}", cam) for k, cam in enumerate(orbit_cameras(model, 2))]
    pairs += [(out / "views" / v.id, v.camera) for v in model.views[:3]]
    for stem, cam in pairs:
        got = over_premultiplied(f"{stem}.exr", envmap_background(env, cam)) * exposure
        png = read_png(f"{stem}.png")[..., :3]
        assert np.abs(srgb8(got) - srgb8(png)).max() <= 1, stem
