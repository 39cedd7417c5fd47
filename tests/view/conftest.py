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
