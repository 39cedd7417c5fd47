"""The matte's ``foreground_premul.exr`` had RGB and no A channel (#33): now RGBA,
premultiplied and saying so; over the ``--over`` backdrop it gives ``composite.png``."""

from __future__ import annotations

import numpy as np

from exrkit import over_premultiplied, srgb8
from opacityhull.imageio import read_png, write_exr


def test_matte_foreground_exr_has_alpha_and_composites_like_composite_png(tmp_path):
    from opacityhull.reconstruct.matte_files import matte_files

    H, W = 24, 32
    rng = np.random.default_rng(0)
    alpha = np.clip(np.linspace(-0.2, 1.2, W, dtype=np.float32)[None, :].repeat(H, 0), 0, 1)
    F = rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float32)
    objs, backs = [], []
    for k, B in enumerate([np.full((H, W, 3), 0.9, np.float32), rng.uniform(0.0, 0.4, (H, W, 3)).astype(np.float32)]):
        C = alpha[..., None] * F + (1 - alpha[..., None]) * B
        write_exr(tmp_path / f"o{k}.exr", C)
        write_exr(tmp_path / f"b{k}.exr", B)
        objs.append(tmp_path / f"o{k}.exr")
        backs.append(tmp_path / f"b{k}.exr")
    over = np.full((H, W, 3), [0.1, 0.6, 0.3], np.float32)
    write_exr(tmp_path / "over.exr", over)
    matte_files(objs, backs, tmp_path / "m", over=tmp_path / "over.exr", drift="none")
    got = over_premultiplied(tmp_path / "m" / "foreground_premul.exr", over)
    assert np.abs(srgb8(got) - srgb8(read_png(tmp_path / "m" / "composite.png"))).max() <= 1
    np.testing.assert_allclose(got, alpha[..., None] * F + (1 - alpha[..., None]) * over, atol=2e-3)
