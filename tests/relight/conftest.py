"""Shared fixtures: analytic Lambertian-sphere models (exact one-light images and an
exact relit ground truth, see opacityhull.relight.synthetic) and the real probes."""

from pathlib import Path

import pytest

from opacityhull.data import PROBES_DIR as PROBES  # the probes shipped with the package


@pytest.fixture(scope="session")
def probes_dir() -> Path:
    if not (PROBES / "grace.hdr").is_file():
        pytest.skip(f"light probes not found in {PROBES}")
    return PROBES


@pytest.fixture(scope="session")
def sphere_model(tmp_path_factory):
    """4 table angles x 2 cameras, 4 x 15 lights of unequal calibrated output and tint."""
    from opacityhull.relight.synthetic import write_sphere_model

    return write_sphere_model(tmp_path_factory.mktemp("sphere") / "model", width=40, height=32)


@pytest.fixture(scope="session")
def sphere_model_missing(tmp_path_factory):
    """The same sphere with one one-light image of view 1 lost."""
    from opacityhull.model import light_key
    from opacityhull.relight.synthetic import write_sphere_model

    root = tmp_path_factory.mktemp("sphere_missing") / "model"
    lost = (1, light_key(2, 72.0))
    return write_sphere_model(root, width=16, height=12, table_degs=(0.0, 90.0), n_positions=5, drop_light=lost)
