"""Backdrop patterns through a video output: a full-screen window per display.

Each backdrop display is a monitor of the capture computer (a panel on an HDMI or
DisplayPort output); :class:`DisplayOutput` opens a borderless full-screen window on
each named monitor with pyglet (OpenGL, no X11 code here) and shows a pattern as it is
— no upload, no pattern slots — scaled to the panel by nearest neighbour (native column
``j`` shows pattern column ``floor((j + 0.5) * width / W)``, the rule of the OHDC-2
controller, so both kinds of panel show the same picture).

Latency: :meth:`DisplayOutput.show_image` draws, swaps and waits for the swap to finish
(``glFinish`` after the buffer swap: with vsync the swap completes at the vertical
blank, after which the frame is scanned out), then waits the panel's response time
(``response_ms`` in the rig TOML) before it returns, so the camera never exposes a
frame in transition. Every show is timed (:class:`ShowTiming`).

Monitors (:func:`list_monitors`) are what pyglet enumerates on every X screen of the
display server: RandR outputs by their names (``HDMI-1``, ``DP-2``); a name that occurs
on several X screens (Xvfb calls each screen's output ``screen``) is qualified by the
screen: ``screen@0``, ``screen@1``. The optional RS-232 control of the same panels
(Samsung MDC, :mod:`opacityhull.rigs.panels`) is held here too, so that the backdrops
device locks and reports its panels.
"""

from __future__ import annotations

import logging
import os
import re
import time
from dataclasses import dataclass
from typing import Any
from collections.abc import Mapping

import numpy as np

from ..errors import ConfigError, DeviceError, InputError, ShapeError
from .interfaces import DeviceInfo
from .transport import OpenClose

log = logging.getLogger(__name__)

__all__ = [
    "Monitor",
    "ShowTiming",
    "DisplayOutput",
    "NoDisplayServer",
    "UnknownMonitor",
    "list_monitors",
    "x_display_name",
    "disconnect",
]


class NoDisplayServer(DeviceError):
    """No X display to open windows on (DISPLAY unset or unreachable, or pyglet missing)."""


class UnknownMonitor(ConfigError):
    """A rig TOML names a monitor the display server does not have."""


@dataclass(frozen=True)
class Monitor:
    """One monitor as the windowing library enumerates it.

    ``name`` is unique on the server (what the rig TOML uses); ``output`` the library's
    name for it; ``x_screen`` the X screen; ``x, y, width, height`` its area, pixels.
    """

    name: str
    output: str
    x_screen: int
    x: int
    y: int
    width: int
    height: int

    def __str__(self) -> str:
        return f"{self.name} ({self.width}x{self.height}+{self.x}+{self.y})"


@dataclass(frozen=True)
class ShowTiming:
    """When a pattern was asked for, when its buffer swap finished and when the panel
    is taken to show it (swap + response time); ``time.monotonic`` seconds."""

    display: str
    requested: float
    swapped: float
    ready: float


_HINT = (
    "run on the rig computer's desktop session, or start a virtual display server: "
    "`Xvfb :99 -screen 0 1920x1080x24 &` then `export DISPLAY=:99` (or `xvfb-run opacityhull ...`)"
)


def x_display_name(display: str | None = None) -> str:
    """The X display to use (``display``, else ``$DISPLAY``) without its screen suffix:
    ``":99.1"`` -> ``":99"``. :class:`NoDisplayServer` when there is none."""
    name = display if display is not None else os.environ.get("DISPLAY", "")
    if not name:
        raise NoDisplayServer(f"video output: no display server — DISPLAY is not set; {_HINT}")
    m = re.fullmatch(r"(.*:\d+)(?:\.\d+)?", name)
    if m is None:
        raise NoDisplayServer(f"video output: DISPLAY={name!r} is not an X display name like ':0' or 'host:0.0'")
    return m.group(1)


def _pyglet():
    try:
        import pyglet
    except ImportError:
        raise NoDisplayServer(
            "video output: pyglet is not installed — pip install 'opacityhull[video]' (and a system OpenGL: "
            "libgl1-mesa-dri on Debian/Ubuntu)"
        ) from None
    # No hidden shadow window: it would open on $DISPLAY at import time, and every
    # window here has its own context on its own X screen.
    pyglet.options["shadow_window"] = False
    return pyglet


_DISPLAYS: dict[str, Any] = {}  # "host:N.S" -> pyglet Display (one connection per X screen)


def _x_display(base: str, screen: int):
    key = f"{base}.{screen}"
    d = _DISPLAYS.get(key)
    if d is None:
        _pyglet()
        try:
            import importlib

            Display: Any = importlib.import_module("pyglet.display").Display
        except Exception as e:  # noqa: BLE001  pyglet found no libGL / libX11 (ImportError, OSError or its own)
            raise NoDisplayServer(f"video output: pyglet cannot load its X11/OpenGL libraries ({e}); {_HINT}") from None
        try:
            # the screen suffix makes XRandR enumerate that screen's outputs
            d = Display(name=key, x_screen=screen)
        except Exception as e:  # noqa: BLE001  pyglet's NoSuchDisplayException and X errors: named below
            raise NoDisplayServer(
                f"video output: cannot connect to the display server {key!r} ({type(e).__name__}: {e}); {_HINT}"
            ) from None
        _DISPLAYS[key] = d
    return d


def disconnect(display: str | None = None) -> None:
    """Close this process's connections to the display server (before it goes away: a
    dead connection makes Xlib exit the process at its next call). Windows on it must be
    closed first (:meth:`DisplayOutput.close`)."""
    import importlib

    from pyglet import app

    xlib: Any = importlib.import_module("pyglet.libs.x11.xlib")
    loop: Any = app.platform_event_loop
    base = x_display_name(display)
    for key in [k for k in _DISPLAYS if k.rsplit(".", 1)[0] == base]:
        d = _DISPLAYS.pop(key)
        loop.select_devices.discard(d)
        xlib.XCloseDisplay(d._display)


def _screen_count(base: str) -> int:
    import importlib

    xlib: Any = importlib.import_module("pyglet.libs.x11.xlib")

    d = _x_display(base, 0)
    return int(xlib.XScreenCount(d._display))


def _enumerate(base: str) -> list[tuple[Monitor, Any]]:
    raw: list[tuple[str, int, Any]] = []
    for s in range(_screen_count(base)):
        for i, scr in enumerate(_x_display(base, s).get_screens()):
            out = str(scr.get_monitor_name())
            raw.append((f"monitor{i}" if out == "Unknown" else out, s, scr))
    counts: dict[str, int] = {}
    for out, _, _ in raw:
        counts[out] = counts.get(out, 0) + 1
    found = []
    for out, s, scr in raw:
        name = out if counts[out] == 1 else f"{out}@{s}"
        found.append((Monitor(name, out, s, int(scr.x), int(scr.y), int(scr.width), int(scr.height)), scr))
    return found


def list_monitors(display: str | None = None) -> list[Monitor]:
    """Every monitor of the display server (``display`` or ``$DISPLAY``), X screen by X
    screen; :class:`NoDisplayServer` when there is no server to ask."""
    return [m for m, _ in _enumerate(x_display_name(display))]


class _Window:
    """One full-screen window and the texture it shows."""

    def __init__(self, display: str, monitor: Monitor, screen, *, vsync: bool):
        from pyglet import gl
        from pyglet.window import Window

        config = screen.get_best_config(gl.Config(double_buffer=True))
        context = config.create_context(None)  # no sharing: one context per X screen
        self.window = Window(
            fullscreen=True, screen=screen, vsync=vsync, context=context, caption=f"opacityhull backdrop {display}"
        )
        self.window.set_mouse_visible(False)
        self.monitor = monitor
        self.texture = None

    def draw(self, image: np.ndarray) -> None:
        import pyglet
        from pyglet import gl

        w = self.window
        w.switch_to()
        w.dispatch_events()
        rows, cols = image.shape[:2]
        # pyglet's rows run bottom to top
        data = pyglet.image.ImageData(cols, rows, "RGB", np.ascontiguousarray(image[::-1]).tobytes(), pitch=3 * cols)
        old, self.texture = self.texture, data.get_texture()
        if old is not None:
            old.delete()
        tex = self.texture
        gl.glBindTexture(tex.target, tex.id)
        gl.glTexParameteri(tex.target, gl.GL_TEXTURE_MAG_FILTER, gl.GL_NEAREST)
        gl.glTexParameteri(tex.target, gl.GL_TEXTURE_MIN_FILTER, gl.GL_NEAREST)
        w.clear()
        tex.blit(0, 0, width=w.width, height=w.height)
        w.flip()
        gl.glFinish()  # the swap has happened when this returns

    def close(self) -> None:
        try:
            self.window.close()
        except Exception as e:  # noqa: BLE001  closing must not mask the error being handled
            log.debug("closing window on %s: %s", self.monitor.name, e)


def _check_image(display: str, image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ShapeError(
            f"video output {display}: expected a uint8 (rows, cols, 3) RGB pattern, got {a.dtype} {a.shape}"
        )
    return a


class DisplayOutput(OpenClose):
    """The backdrops as monitors of this computer (implements
    :class:`~opacityhull.rigs.interfaces.Backdrops` and :class:`~opacityhull.rigs.interfaces.Port`).

    Parameters
    ----------
    monitors : mapping display name -> monitor name
        E.g. ``{"bottom": "HDMI-1", "back": "DP-1"}`` (names as :func:`list_monitors` gives).
    response_s : float
        Panel response time waited after each swap, seconds (``response_ms`` / 1000).
    name : str
    x_display : str, optional
        X display (default ``$DISPLAY`` when opened).
    panels : mapping display name -> :class:`~opacityhull.rigs.panels.MdcPanel`, optional
        The panels' RS-232 control, locked by :meth:`lock_panels` (each is a port of its
        own: the rig opens and closes it).
    vsync : bool
        Swap at the vertical blank (real panels); a virtual server has none.

    No window opens in ``__init__``; :meth:`open` resolves the monitors and opens one
    full-screen black window per display.
    """

    def __init__(
        self,
        *,
        monitors: Mapping[str, str],
        response_s: float = 0.0,
        name: str = "backdrops",
        x_display: str | None = None,
        panels: Mapping[str, Any] | None = None,
        vsync: bool = True,
    ):
        if not monitors:
            raise ConfigError(f"{name}: at least one display -> monitor is required")
        if not (isinstance(response_s, (int, float)) and 0 <= response_s < 10):
            raise ConfigError(f"{name}: response time must be 0..10 s, got {response_s!r}")
        self.name = name
        self.monitors = dict(monitors)
        self.response_s = float(response_s)
        self.x_display = x_display
        self.panels = dict(panels or {})
        self.vsync = bool(vsync)
        self.timings: list[ShowTiming] = []
        self.last_error: str | None = None
        self._windows: dict[str, _Window] = {}
        self._patterns: dict[int, np.ndarray] = {}
        self._shown: dict[str, int | None] = {d: None for d in self.monitors}
        self._images: dict[str, np.ndarray | None] = {d: None for d in self.monitors}

    # ---- Port
    @property
    def url(self) -> str:
        return f"x11:{self.x_display or os.environ.get('DISPLAY', '')}"

    @property
    def is_open(self) -> bool:
        return bool(self._windows)

    def resolve(self) -> dict[str, tuple[Monitor, Any]]:
        """Display name -> its monitor; :class:`UnknownMonitor` naming the missing one
        and listing the monitors there are."""
        found = _enumerate(x_display_name(self.x_display))
        by_name = {m.name: (m, s) for m, s in found}
        by_output: dict[str, list[tuple[Monitor, Any]]] = {}
        for m, s in found:
            by_output.setdefault(m.output, []).append((m, s))
        out = {}
        for disp, mon in self.monitors.items():
            hit = by_name.get(mon)
            if hit is None and len(by_output.get(mon, [])) == 1:
                hit = by_output[mon][0]
            if hit is None:
                have = ", ".join(str(m) for m, _ in found) or "none"
                raise UnknownMonitor(
                    f"{self.name}: display {disp!r} is on monitor {mon!r}, which {self.url[4:]} does not have "
                    f"(monitors: {have}) — fix devices.backdrops.monitors in the rig TOML"
                )
            out[disp] = hit
        used = [m.name for m, _ in out.values()]
        if len(set(used)) != len(used):
            raise ConfigError(f"{self.name}: two displays on one monitor: {self.monitors}")
        return out

    def open(self) -> DisplayOutput:
        if self._windows:
            return self
        resolved = self.resolve()
        try:
            for disp, (mon, scr) in resolved.items():
                self._windows[disp] = _Window(disp, mon, scr, vsync=self.vsync)
                log.info("%s: display %s on monitor %s", self.name, disp, mon)
            for disp in self._windows:
                self._draw(disp, np.zeros((1, 1, 3), np.uint8), None)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        wins, self._windows = self._windows, {}
        for w in wins.values():
            w.close()

    # ---- showing
    def _window(self, display: str) -> _Window:
        if display not in self.monitors:
            raise InputError(f"{self.name}: no display named {display!r} (displays: {sorted(self.monitors)})")
        w = self._windows.get(display)
        if w is None:
            raise DeviceError(f"{self.name}: not open — call open() first (display {display!r})")
        return w

    def _draw(self, display: str, image: np.ndarray, pattern_id: int | None) -> ShowTiming:
        w = self._window(display)
        requested = time.monotonic()
        try:
            w.draw(image)
        except Exception as e:  # noqa: BLE001  an X error, a lost server: re-raised as DeviceError
            raise DeviceError(
                f"{self.name}: drawing on monitor {w.monitor.name} failed ({type(e).__name__}: {e}) — is the "
                f"display server {self.url[4:]} still running?"
            ) from None
        swapped = time.monotonic()
        if self.response_s > 0:
            time.sleep(self.response_s)  # the panel's pixels are still changing
        t = ShowTiming(display, requested, swapped, time.monotonic())
        self.timings.append(t)
        del self.timings[:-1000]
        self._shown[display] = pattern_id
        self._images[display] = image if pattern_id is not None or image.any() else None
        return t

    def show_image(self, display: str, image_rgb8: np.ndarray, *, pattern_id: int | None = -1) -> ShowTiming:
        """Show ``image_rgb8`` (uint8 (rows, cols, 3)) full-screen on ``display``; returns
        once the swap is done and the panel's response time has passed."""
        return self._draw(display, _check_image(display, image_rgb8), pattern_id)

    @property
    def displays(self) -> list[str]:
        return list(self.monitors)

    def upload(self, display: str, pattern_id: int, image_rgb8: np.ndarray) -> bool:
        """Keep ``image_rgb8`` as pattern ``pattern_id`` (nothing is sent anywhere: a
        video output shows images as they are); returns False."""
        if display not in self.monitors:
            raise InputError(f"{self.name}: no display named {display!r} (displays: {sorted(self.monitors)})")
        self._patterns[int(pattern_id)] = _check_image(display, image_rgb8)
        return False

    def show(self, display: str, pattern_id: int) -> None:
        img = self._patterns.get(int(pattern_id))
        if img is None:
            raise InputError(f"{self.name}: pattern {pattern_id} was never given (upload() or show_image() it)")
        self._draw(display, img, int(pattern_id))

    def blank(self, display: str | None = None) -> None:
        """Black on one display or all; never raises (used by ``Rig.safe``)."""
        try:
            for d in [display] if display is not None else list(self._windows):
                self._draw(d, np.zeros((1, 1, 3), np.uint8), None)
            self.last_error = None
        except (DeviceError, InputError, OSError) as e:
            self.last_error = str(e)

    def shown(self) -> dict[str, int | None]:
        return dict(self._shown)

    def current(self, display: str) -> np.ndarray | None:
        """The image ``display`` shows now (None: black)."""
        return self._images[display]

    # ---- panels
    def lock_panels(self) -> dict[str, Any]:
        """Lock every panel's radiance settings (:meth:`MdcPanel.lock`); their states."""
        return {d: p.lock() for d, p in self.panels.items()}

    def drift(self) -> dict[str, list[str]]:
        """Per display, what lets its panel change its own radiance (empty: locked)."""
        out = {}
        for d, p in self.panels.items():
            st = p.state()
            if st.drift:
                out[d] = list(st.drift)
        return out

    def check(self) -> DeviceInfo:
        """Which monitor each display is on; never raises."""
        try:
            resolved = self.resolve()
        except (DeviceError, ConfigError) as e:
            return DeviceInfo(self.name, False, str(e), state={"url": self.url})
        text = ", ".join(f"{d} on {m}" for d, (m, _) in resolved.items())
        state = {"monitors": {d: m.name for d, (m, _) in resolved.items()}, "url": self.url}
        return DeviceInfo(self.name, True, f"video output {self.url[4:]}: {text}", "video output", state)
