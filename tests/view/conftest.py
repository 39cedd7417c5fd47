"""Fixtures of the viewer tests: an analytic sphere model, its bundle, and a headless Chromium."""

from __future__ import annotations

import pytest

from opacityhull.render.synthetic import write_sphere_model


@pytest.fixture(scope="session")
def view_model(tmp_path_factory):
    """4000 surfels, 24 views of 64×48 with a highlight (view-dependent colour)."""
    return write_sphere_model(
        tmp_path_factory.mktemp("view") / "sphere", n_surfels=4000, width=64, height=48, table_step_deg=45.0
    )


@pytest.fixture(scope="session")
def bundle(view_model, tmp_path_factory):
    from opacityhull.view.bundle import write_bundle

    root, _ = view_model
    out = tmp_path_factory.mktemp("bundle") / "b"
    summary = write_bundle(root, out, first_chunk=500)  # several chunks: progressive loading is exercised
    return out, summary


@pytest.fixture(scope="module")
def browser():
    from opacityhull.view.browser import close_browser, find_chromium, open_browser

    b, d, why = find_chromium()
    if b is None:
        pytest.skip(f"headless browser tests need Chromium: {why}")
    drv = open_browser()
    yield drv
    close_browser(drv)


@pytest.fixture(scope="session")
def relit_model(tmp_path_factory):
    """The analytic Lambertian sphere with reflectance (relight/synthetic.py): 4 table
    angles × 2 cameras of 48×40, 4 × 15 directional lights, 4000 surfels."""
    from opacityhull.relight.synthetic import write_sphere_model as write_relit_sphere

    return write_relit_sphere(tmp_path_factory.mktemp("relit") / "sphere", width=48, height=40, n_surfels=4000)


@pytest.fixture(scope="session")
def relit_bundle(relit_model, tmp_path_factory):
    """Its bundle, relightable under two probes, weights every 15° (24 yaw steps: the
    default 72 costs 3× the bundle time in Relighter.weights)."""
    from opacityhull.view.bundle import write_bundle

    out = tmp_path_factory.mktemp("relit_bundle") / "b"
    summary = write_bundle(relit_model, out, first_chunk=500, probes=["grace", "uffizi"], yaw_steps=24)
    return out, summary
