"""Fixtures of the bad-input suite (helpers and the case table format: badkit.py).

Analytic and fast (no Mitsuba): ``tests/reconstruct/rcsynth.py`` sessions,
``opacityhull.render.synthetic`` / ``opacityhull.relight.synthetic`` models.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # badkit
sys.path.insert(0, str(HERE.parent / "reconstruct"))  # rcsynth
sys.path.insert(0, str(HERE.parent / "acquire"))  # rigkit


@pytest.fixture(scope="session")
def session_dir(tmp_path_factory) -> Path:
    """A tiny analytic session: 2 cameras x 3 table angles of 32x24, one pattern pair,
    object-absent backdrops, two one-light images per view (about 0.5 s)."""
    import rcsynth

    root = tmp_path_factory.mktemp("badinput") / "session"
    rcsynth.make_session(root, n_cams=2, n_angles=3, width=32, height=24, n_patterns=1, ss=1)
    return root


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory) -> Path:
    """A tiny analytic model (500 surfels, 12 views of 24x18)."""
    from opacityhull.render.synthetic import write_sphere_model

    root = tmp_path_factory.mktemp("badinput") / "model"
    write_sphere_model(root, n_surfels=500, width=24, height=18, table_step_deg=90.0)
    return root


@pytest.fixture(scope="session")
def relight_model_dir(tmp_path_factory) -> Path:
    """A tiny model with reflectance (one-light images), about 0.1 s."""
    from opacityhull.relight.synthetic import write_sphere_model

    root = tmp_path_factory.mktemp("badinput") / "relight_model"
    write_sphere_model(root, width=16, height=12, table_degs=(0.0, 90.0), n_positions=5, n_surfels=500)
    return root
