"""Shared fixtures of the renderer tests: analytic sphere models with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.render.synthetic import make_sphere_model, write_sphere_model


@pytest.fixture(scope="session")
def sphere_small():
    """3000 surfels, 24 views (8 table angles × 3 elevations) of 48×36 px, in memory."""
    return make_sphere_model(3000, width=48, height=36, table_step_deg=45.0)


@pytest.fixture(scope="session")
def sphere_views_premul(sphere_small):
    return sphere_small.views_premul()


@pytest.fixture(scope="session")
def sphere_dir(tmp_path_factory):
    """A written analytic model folder (diffuse + highlight), 8000 surfels, 36 views of 64×48."""
    root, m = write_sphere_model(tmp_path_factory.mktemp("render") / "sphere", n_surfels=8000, width=64, height=48)
    return root, m


def premul(rgba: np.ndarray) -> np.ndarray:
    out = np.asarray(rgba, np.float32).copy()
    out[..., :3] *= out[..., 3:4]
    return out


def psnr_premul(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB, peak 1) of premultiplied linear RGBA, optionally inside a mask."""
    d = premul(a) - premul(b)
    if mask is not None:
        d = d[mask]
    mse = float(np.mean(d**2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)
