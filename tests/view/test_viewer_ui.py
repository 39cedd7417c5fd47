"""The page as a user meets it (#33): the canvas fills the window at the device pixel
ratio with the camera's aspect, a neutral grey background with black and white one click
away, the rotation slider's angle, and `?` for the controls — in headless Chromium."""

from __future__ import annotations

import numpy as np
from helpers import load_viewer

from opacityhull.view.browser import canvas_rgb
from opacityhull.view.server import BundleServer


def _frames(drv, n: int = 3) -> None:
    """Let the page's frame loop run ``n`` animation frames."""
    drv.execute_async_script(
        "const done = arguments[arguments.length - 1]; let k = arguments[0];"
        "const f = () => (--k <= 0 ? done(null) : requestAnimationFrame(f)); requestAnimationFrame(f);",
        n,
    )


def _layout(drv) -> dict:
    return drv.execute_script(
        "const c = document.getElementById('canvas'), r = c.getBoundingClientRect();"
        "return {w: c.width, h: c.height, cssW: r.width, cssH: r.height, innerW: window.innerWidth,"
        " innerH: window.innerHeight, bar: document.getElementById('bar').getBoundingClientRect().height,"
        " dpr: window.devicePixelRatio, cam: window.opacityhull.viewer.baseCam};"
    )


def _check_fills(L: dict) -> None:
    aspect = L["cam"]["width"] / L["cam"]["height"]
    css_w = min(L["innerW"], (L["innerH"] - L["bar"]) * aspect)
    assert abs(L["cssW"] - css_w) <= 1.0 and L["cssW"] <= L["innerW"] + 0.5
    assert L["cssH"] <= L["innerH"] - L["bar"] + 1.0
    # backing store at the device pixel ratio, the camera's aspect kept to the pixel
    assert abs(L["w"] - L["cssW"] * L["dpr"]) <= 1.0
    assert abs(L["w"] / L["h"] - aspect) <= aspect / L["h"]
    assert L["w"] > 4 * L["cam"]["width"]  # far more than the 64x48 capture


def test_canvas_fills_the_window_at_the_device_pixel_ratio(browser, bundle):
    out, _ = bundle
    try:
        for dpr in (1, 2):
            browser.execute_cdp_cmd(
                "Emulation.setDeviceMetricsOverride",
                {"width": 1000, "height": 700, "deviceScaleFactor": dpr, "mobile": False},
            )
            with BundleServer(out) as srv:
                r = load_viewer(browser, srv.url)
                assert r["ok"], r["error"]
                L = _layout(browser)
                assert L["dpr"] == dpr and L["innerW"] == 1000 and L["innerH"] == 700
                _check_fills(L)
                # the drawn camera is the captured one scaled: same field of view
                cam = browser.execute_script("return window.opacityhull.viewer.cam")
                base = L["cam"]
                assert abs(cam["fx"] / cam["width"] - base["fx"] / base["width"]) < 1e-6 * base["fx"]
                # a window resize refits
                browser.execute_cdp_cmd(
                    "Emulation.setDeviceMetricsOverride",
                    {"width": 600, "height": 900, "deviceScaleFactor": dpr, "mobile": False},
                )
                _frames(browser)
                L2 = _layout(browser)
                assert L2["innerW"] == 600
                _check_fills(L2)
                # the API's captured camera draws at the capture's own size (tests compare pixels)
                browser.execute_script("return window.opacityhull.setCamera(0)")
                assert _layout(browser)["w"] == base["width"]
    finally:
        browser.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})


def test_background_is_grey_with_black_and_white_one_click_away(browser, bundle):
    out, _ = bundle
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        _frames(browser)
        img = canvas_rgb(browser)
        corner = img[:3, :3].reshape(-1, 3)  # outside the sphere
        # 18 % linear grey, sRGB-encoded: 118
        np.testing.assert_array_equal(corner, np.full_like(corner, 118))
        assert browser.execute_script("return document.getElementById('bg').value") == "0.18,0.18,0.18"
        for title, want in (("black", 0), ("white", 255), ("grey", 118)):
            browser.find_element("css selector", f"#bgbuttons button[title='{title}']").click()
            _frames(browser)
            c = canvas_rgb(browser)[:3, :3]
            assert np.all(c == want), (title, c[0, 0])
        # the sphere itself is drawn over it
        mid = canvas_rgb(browser)[img.shape[0] // 2, img.shape[1] // 2]
        assert np.abs(mid.astype(int) - 118).max() > 10


def test_rotation_slider_shows_its_angle_and_question_mark_shows_the_controls(browser, view_model, tmp_path):
    from opacityhull.view.bundle import write_bundle

    root, _ = view_model
    out = tmp_path / "env"
    write_bundle(root, out, envmap="builtin:grace", env_yaw_deg=30.0, relight=False)
    with BundleServer(out) as srv:
        r = load_viewer(browser, srv.url)
        assert r["ok"], r["error"]
        assert browser.execute_script("return document.getElementById('yawval').textContent") == "30°"
        browser.execute_script(
            "const y = document.getElementById('yaw'); y.value = '-45'; y.dispatchEvent(new Event('input'));"
        )
        assert browser.execute_script("return document.getElementById('yawval').textContent") == "-45°"
        assert browser.execute_script("return window.opacityhull.viewer.envYawDeg") == -45
        help_hidden = "return document.getElementById('help').hidden"
        assert browser.execute_script(help_hidden) is True
        body = browser.find_element("tag name", "body")
        body.send_keys("?")
        assert browser.execute_script(help_hidden) is False
        text = browser.find_element("id", "help").text
        assert "drag" in text and "wheel" in text and "background" in text
        body.send_keys("?")
        assert browser.execute_script(help_hidden) is True
        browser.find_element("id", "helpbutton").click()
        assert browser.execute_script(help_hidden) is False
