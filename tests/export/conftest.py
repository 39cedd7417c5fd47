"""Small analytic sphere models written as model folders (exact ground truth, no Mitsuba)."""

from __future__ import annotations

import pytest

from opacityhull.render.synthetic import write_sphere_model

SPHERE = {"n_surfels": 2000, "table_step_deg": 45.0}  # what both models share


@pytest.fixture(scope="session")
def diffuse_model(tmp_path_factory):
    """2000 surfels, 24 views of 96×72, smooth view-independent colour (no highlight), so that
    a pixel's colour is close to the colour at the point it images."""
    root = tmp_path_factory.mktemp("export") / "diffuse"
    return write_sphere_model(root, **SPHERE, width=96, height=72, specular=0.0, texture_freq=0.5)


@pytest.fixture(scope="session")
def glossy_model(tmp_path_factory):
    """As ``diffuse_model`` with a Blinn-Phong highlight (view-dependent colour)."""
    root = tmp_path_factory.mktemp("export") / "glossy"
    return write_sphere_model(root, **SPHERE, width=48, height=36, specular=0.25)
