"""Headless Chromium for tests and benchmarks (Selenium + Debian's chromium/chromium-driver).

:func:`find_chromium` says why the browser cannot be used (for ``pytest.skip``), and
:func:`open_browser` launches it with software WebGL2 (SwiftShader through ANGLE).
"""

from __future__ import annotations

import base64
import shutil
import tempfile

import numpy as np

__all__ = ["find_chromium", "open_browser", "close_browser", "canvas_rgb", "wait_ready"]

CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-dev-shm-usage",
    "--window-size=800,600",
)


def find_chromium() -> tuple[str | None, str | None, str]:
    """(browser path, driver path, reason) — the paths are None with a reason when missing."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return None, None, "selenium is not installed (pip install 'selenium>=4.30,<5')"
    b = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    d = shutil.which("chromedriver")
    if not b or not d:
        return None, None, "chromium and chromium-driver are not installed (apt-get install chromium chromium-driver)"
    return b, d, ""


def open_browser():
    """A Selenium Chrome driver on headless Chromium; the caller quits it (use ``with``-less try/finally)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    b, d, why = find_chromium()
    if b is None:
        raise RuntimeError(why)
    opts = webdriver.ChromeOptions()
    opts.binary_location = b
    profile = tempfile.mkdtemp(prefix="opacityhull-chromium-")
    for f in CHROMIUM_FLAGS:
        opts.add_argument(f)
    opts.add_argument(f"--user-data-dir={profile}")
    drv = webdriver.Chrome(service=Service(d), options=opts)
    setattr(drv, "_opacityhull_profile", profile)  # noqa: B010  removed by close_browser; WebDriver declares no such attribute
    return drv


def close_browser(drv) -> None:
    try:
        drv.quit()
    finally:
        shutil.rmtree(getattr(drv, "_opacityhull_profile", ""), ignore_errors=True)


def wait_ready(drv, timeout_s: float = 60.0) -> dict:
    """Wait for ``window.opacityhull.ready``; returns ``{"ok": bool, "error": str|None}``."""
    drv.set_script_timeout(timeout_s)
    return drv.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "const t = () => { if (!window.opacityhull) return setTimeout(t, 20);"
        " window.opacityhull.ready.then(() => done({ok: true, error: null}),"
        " (e) => done({ok: false, error: String(e && e.message || e)})); }; t();"
    )


def canvas_rgb(drv) -> np.ndarray:
    """(H, W, 3) uint8 sRGB pixels of the viewer's canvas (lossless PNG through toDataURL)."""
    import cv2

    url = drv.execute_script("return document.getElementById('canvas').toDataURL('image/png');")
    raw = base64.b64decode(url.split(",", 1)[1])
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise RuntimeError("the viewer canvas did not give a decodable PNG")
    return img[:, :, ::-1].copy()
