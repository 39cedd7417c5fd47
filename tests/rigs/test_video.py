"""The video output under Xvfb: patterns shown full-screen on named monitors, read back
from the virtual display's framebuffer (Xvfb ``-fbdir``: a screenshot of each X screen),
two X screens as two monitors. Skipped, saying so, where Xvfb or pyglet is missing
(``make system-deps`` installs Xvfb and Mesa's OpenGL)."""

from __future__ import annotations

import importlib.util
import shutil

import numpy as np
import pytest

from opacityhull.rigs.testing import read_xwd, xvfb

if shutil.which("Xvfb") is None:
    pytest.skip("Xvfb is not installed (apt-get install xvfb, or `make system-deps`)", allow_module_level=True)
if importlib.util.find_spec("pyglet") is None:
    pytest.skip("pyglet is not installed (pip install 'opacityhull[video]')", allow_module_level=True)

from opacityhull.rigs import video  # noqa: E402
from opacityhull.rigs.video import DisplayOutput, NoDisplayServer, UnknownMonitor  # noqa: E402

SCREENS = ((320, 240), (200, 150))


@pytest.fixture(scope="module")
def server():
    with xvfb(SCREENS) as (display, fbdir):
        yield display, fbdir
        video.disconnect(display)


def nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """The OHDC-2 scaling rule written out: native pixel j shows floor((j + 0.5) * w / W)."""
    rows = ((np.arange(height) + 0.5) * image.shape[0] / height).astype(int)
    cols = ((np.arange(width) + 0.5) * image.shape[1] / width).astype(int)
    return image[rows][:, cols]


def test_two_x_screens_are_two_named_monitors(server):
    display, _ = server
    mons = video.list_monitors(display)
    assert [(m.name, m.x_screen, m.width, m.height) for m in mons] == [
        ("screen@0", 0, 320, 240),
        ("screen@1", 1, 200, 150),
    ]


def test_patterns_land_on_the_chosen_monitor_scaled_by_nearest_neighbour(server):
    display, fbdir = server
    rng = np.random.default_rng(3)
    back = rng.integers(0, 256, (9, 16, 3), dtype=np.uint8)
    bottom = rng.integers(0, 256, (7, 7, 3), dtype=np.uint8)
    out = DisplayOutput(monitors={"bottom": "screen@1", "back": "screen@0"}, x_display=display, response_s=0.02)
    with out:
        assert read_xwd(fbdir / "Xvfb_screen0").max() == 0  # opened black
        t_back = out.show_image("back", back, pattern_id=4)
        t_bottom = out.show_image("bottom", bottom, pattern_id=5)
        np.testing.assert_array_equal(read_xwd(fbdir / "Xvfb_screen0"), nearest(back, 320, 240))
        np.testing.assert_array_equal(read_xwd(fbdir / "Xvfb_screen1"), nearest(bottom, 200, 150))
        assert out.shown() == {"bottom": 5, "back": 4}
        # timing: asked, swapped, then the panel's response time, then the next show
        for t in (t_back, t_bottom):
            assert t.requested <= t.swapped and t.ready - t.swapped >= 0.02
        assert t_back.ready <= t_bottom.requested
        out.blank("back")
        assert read_xwd(fbdir / "Xvfb_screen0").max() == 0
        np.testing.assert_array_equal(read_xwd(fbdir / "Xvfb_screen1"), nearest(bottom, 200, 150))
        assert out.shown() == {"bottom": 5, "back": None} and out.current("back") is None
        info = out.check()
        assert info.ok and info.state["monitors"] == {"bottom": "screen@1", "back": "screen@0"}
    assert not out.is_open


def test_an_unknown_monitor_lists_the_ones_there_are(server):
    display, _ = server
    out = DisplayOutput(monitors={"back": "HDMI-1"}, x_display=display)
    with pytest.raises(UnknownMonitor, match=r"'HDMI-1'.*monitors: screen@0 \(320x240\+0\+0\), screen@1"):
        out.open()
    assert not out.check().ok


def test_no_display_server_says_what_to_do(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(NoDisplayServer, match="DISPLAY is not set.*Xvfb"):
        DisplayOutput(monitors={"back": "HDMI-1"}).open()
    with pytest.raises(NoDisplayServer, match="cannot connect to the display server"):
        video.list_monitors(":987")


def test_rig_monitors_cli(server):
    import json
    import os
    import subprocess
    import sys

    display, _ = server
    cli = [sys.executable, "-m", "opacityhull.cli", "rig", "monitors", "--json"]
    r = subprocess.run([*cli, "--display", display], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert [m["name"] for m in json.loads(r.stdout)["monitors"]] == ["screen@0", "screen@1"]
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    r = subprocess.run(cli, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 3 and "DISPLAY is not set" in " ".join(r.stderr.split()) and "Traceback" not in r.stderr
