"""Test helpers for code that talks to the rig: byte-exchange checks and a stateful lab rig.

* :class:`ExpectedExchangeTransport` is a real :class:`~opacityhull.rigs.transport.Transport`
  over a script of ``(bytes_out, bytes_in)`` pairs: every write must be the next expected
  bytes (one pair may arrive over several writes), is answered with the paired reply, and
  :meth:`~ExpectedExchangeTransport.verify` asserts every pair was used.
  :func:`expected_exchange` builds a driver on it (pymeasure's ``expected_protocol``, for
  this package's drivers)::

      with expected_exchange(GrblController, [(b"?", b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\\r\\n"),
                                              ...], serial=replace(GRBL_SERIAL, timeout_s=0.2)) as grbl:
          grbl.open()

  A pair ``(None, reply)`` is a message the device sends unasked: it arrives as soon as
  the pair before it has been used (at once, when it is the first). ``(bytes_out, b"")``
  is a write the device does not answer (a DMX packet, a real-time byte).

* :class:`LabRig` is a small laboratory rig: the real drivers over ptys to the real
  emulators (:func:`~opacityhull.rigs.emulators.launch.start_emulators`), cameras
  (:class:`SynthCamera`) that synthesise their image from the emulators' state, a scene
  (object or calibration board on the table) that the operator steps change, and a
  ground-truth writer like a simulated rig's. A capture of a few hundred images takes
  seconds (no Mitsuba).
"""

from __future__ import annotations

import json
import logging
import math
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from ..errors import DeviceError
from ..riggeometry import back_display, bottom_display
from .config import emulated_axis
from .interfaces import CameraInfo, DeviceInfo
from .transport import Transport

log = logging.getLogger(__name__)

__all__ = [
    "ExpectedExchangeTransport",
    "expected_exchange",
    "LabRig",
    "SynthCamera",
    "LAB_GEOMETRY",
    "LAB_RIG_CONFIG",
    "lab_video_rig_config",
    "read_xwd",
    "xvfb",
]

Pair = tuple[bytes | None, bytes | None]
D = TypeVar("D")


def _show(data: bytes | None, limit: int = 80) -> str:
    if data is None:
        return "None"
    text = repr(bytes(data))
    return text if len(text) <= limit else f"{text[:limit]}... ({len(data)} bytes)"


class ExpectedExchangeTransport(Transport):
    """An in-memory transport that checks every byte a driver writes against a script.

    Parameters
    ----------
    pairs : sequence of (bytes_out or None, bytes_in or None)
        What the driver must write, in order, and what the device answers to each.
        ``bytes_out = None``: the device speaks unasked (after the previous pair).
        ``bytes_in = None`` or ``b""``: no answer.
    name, url : str
        As named in the driver's messages.
    timeout_s : float
        Default read timeout; a read the script does not answer waits this long (real
        time: keep it short in tests that expect a timeout).

    Notes
    -----
    A write that differs from the script raises :class:`AssertionError` at once and is
    also kept in :attr:`mismatch`, so a driver that swallows errors (``stop()`` never
    raises) cannot hide it: :meth:`verify` raises it again.
    """

    def __init__(
        self,
        pairs: Sequence[Pair],
        *,
        name: str = "device",
        url: str = "memory://expected",
        baudrate: int = 115200,
        timeout_s: float = 0.5,
        write_timeout_s: float = 0.5,
    ):
        super().__init__(url, name=name, baudrate=baudrate, timeout_s=timeout_s, write_timeout_s=write_timeout_s)
        self.pairs: list[tuple[bytes | None, bytes]] = []
        for k, pair in enumerate(pairs):
            if not (isinstance(pair, tuple) and len(pair) == 2):
                raise TypeError(f"expected_exchange: pair #{k} must be (bytes_out, bytes_in), got {pair!r}")
            out, reply = pair
            if out is not None and not isinstance(out, (bytes, bytearray)):
                raise TypeError(f"expected_exchange: pair #{k}: bytes_out must be bytes or None, got {out!r}")
            if reply is not None and not isinstance(reply, (bytes, bytearray)):
                raise TypeError(f"expected_exchange: pair #{k}: bytes_in must be bytes or None, got {reply!r}")
            if out is None and not reply:
                raise TypeError(f"expected_exchange: pair #{k} is (None, {reply!r}): nothing written, nothing read")
            self.pairs.append((None if out is None else bytes(out), bytes(reply or b"")))
        self.used = 0  # pairs completely written (and answered)
        self.written: list[bytes] = []  # every write, as the driver made it
        self.mismatch: AssertionError | None = None
        self.opens = 0
        self._partial = bytearray()  # bytes of the current pair written so far
        self._inbox = bytearray()
        self._is_open = False
        self._deliver_unsolicited()

    # ---- the script
    def _deliver_unsolicited(self) -> None:
        while self.used < len(self.pairs) and self.pairs[self.used][0] is None:
            self._inbox += self.pairs[self.used][1]
            self.used += 1

    def _fail(self, message: str) -> AssertionError:
        err = AssertionError(f"{self.name}: {message}")
        if self.mismatch is None:
            self.mismatch = err
        return err

    def verify(self) -> None:
        """Raise :class:`AssertionError` for the first write that differed from the script,
        or naming the first pair that was never (completely) written."""
        if self.mismatch is not None:
            raise self.mismatch
        if self.used < len(self.pairs):
            out, reply = self.pairs[self.used]
            got = (
                f"; {len(self._partial)} byte(s) of it were written: {_show(bytes(self._partial))}"
                if self._partial
                else ""
            )
            raise AssertionError(
                f"{self.name}: pair #{self.used} of {len(self.pairs)} was never used: ({_show(out)}, {_show(reply)})"
                f"{got}; writes so far: {[_show(w, 40) for w in self.written[-5:]]}"
            )

    # ---- Transport primitives
    @property
    def is_open(self) -> bool:
        return self._is_open

    def _open_raw(self) -> None:
        self._is_open = True
        self.opens += 1

    def _close_raw(self) -> None:
        self._is_open = False

    def _write_raw(self, data: bytes) -> None:
        data = bytes(data)
        self.written.append(data)
        if self.mismatch is not None:
            raise self.mismatch
        rest = data
        while rest:
            if self.used >= len(self.pairs):
                raise self._fail(
                    f"unexpected write {_show(data)}: all {len(self.pairs)} expected pairs were already used"
                )
            expected = self.pairs[self.used][0]
            assert expected is not None  # leading (None, reply) pairs are delivered before this
            want = expected[len(self._partial) :]
            take = rest[: len(want)]
            if not want.startswith(take):
                raise self._fail(
                    f"write {_show(data)} differs from pair #{self.used}: expected {_show(expected)}"
                    + (f" (of which {_show(bytes(self._partial))} was already written)" if self._partial else "")
                )
            self._partial += take
            rest = rest[len(take) :]
            if bytes(self._partial) == expected:
                self._inbox += self.pairs[self.used][1]
                self._partial.clear()
                self.used += 1
                self._deliver_unsolicited()

    def _read_raw(self) -> bytes:
        out = bytes(self._inbox)
        self._inbox.clear()
        return out

    def _wait_raw(self, wait_s: float) -> None:
        # nothing arrives between writes in a script: only the clock moves
        if not self._inbox and wait_s > 0:
            time.sleep(wait_s)


@contextmanager
def expected_exchange(
    driver: Callable[..., D],
    pairs: Sequence[Pair],
    *,
    name: str | None = None,
    transport_timeout_s: float = 0.5,
    **driver_kwargs: Any,
) -> Iterator[D]:
    """``with expected_exchange(Driver, [(bytes_out, bytes_in), ...], **kw) as dev:``

    Builds ``driver(transport, **kw)`` on an :class:`ExpectedExchangeTransport` (``driver``
    is a class or any factory taking the transport first) and, when the block ends without
    an exception, asserts that every pair was used. A mismatched write raises inside the
    block; if the driver swallowed it, it is raised at the end (and chained to whatever
    the block raised).

    Parameters
    ----------
    driver : callable(transport, **driver_kwargs) -> driver
    pairs : sequence of (bytes_out or None, bytes_in or None)
        See :class:`ExpectedExchangeTransport`.
    name : str, optional
        Device name of the transport (and, through it, of the driver by default).
    transport_timeout_s : float
        The transport's default read and write timeout.

    Yields
    ------
    The driver; its transport is ``dev.transport`` for drivers that keep it.
    """
    transport = ExpectedExchangeTransport(
        pairs, name=name or "device", timeout_s=transport_timeout_s, write_timeout_s=transport_timeout_s
    )
    dev = driver(transport, **driver_kwargs)
    try:
        yield dev
    except BaseException as e:
        if transport.mismatch is not None and transport.mismatch is not e:
            raise transport.mismatch from e
        raise
    finally:
        transport.close()
    transport.verify()


# --------------------------------------------------------------------------- the lab rig

LAB_GEOMETRY: dict[str, Any] = {
    "target_m": [0.0, 0.08, 0.0],
    "cameras": [
        {
            "name": f"cam{i}",
            "width": 24,
            "height": 18,
            "distance_m": 1.0,
            "elevation_deg": 10.0 + 15 * i,
            "azimuth_deg": 0.0,
            "fov_y_deg": 30.0,
            "gain": 1.0,
        }
        for i in range(3)
    ],
    "lights": [{"id": i, "elevation_deg": 45.0, "azimuth_deg": 90.0 * i, "distance_m": 1.2} for i in range(4)],
    "displays": [
        bottom_display([0.6, 0.6], [16, 16]),
        back_display([0.0, 0.3, -0.4], [0.8, 0.6], [16, 12], rotates_with_table=False),
    ],
}

LAB_RIG_CONFIG: dict[str, Any] = {
    "rig": {"name": "lab rig (tests)"},
    "devices": {
        "turntable": emulated_axis("X", max_rate_deg_s=90.0, accel_deg_s2=180.0),
        "light_array": {
            "url": "emulator:enttec",
            "timeout_s": 2.0,
            "rotation": emulated_axis("Y", max_rate_deg_s=45.0, accel_deg_s2=90.0),
            "channels": {"0": 1, "1": 2, "2": 3, "3": 4},
        },
        "backdrops": {"url": "emulator:display", "timeout_s": 1.0, "outputs": {"bottom": 0, "back": 1}},
        "cameras": [{"name": f"cam{i}", "driver": "sim"} for i in range(3)],
    },
    "geometry": LAB_GEOMETRY,
}


def lab_video_rig_config(
    monitors: dict[str, str] | None = None, *, x_display: str | None = None, response_ms: float = 5.0
) -> dict[str, Any]:
    """:data:`LAB_RIG_CONFIG` with video-output backdrops (``bottom`` on ``screen@1``,
    ``back`` on ``screen@0``: the two X screens of :func:`xvfb`) and an emulated Samsung
    MDC control port per panel (MDC ids 1 and 2, the emulator's dynamic-contrast command)."""
    import copy

    from .emulators.mdc import EMU_DYNAMIC_CONTRAST_CMD

    cfg = copy.deepcopy(LAB_RIG_CONFIG)
    bd: dict[str, Any] = {
        "driver": "video",
        "response_ms": response_ms,
        "monitors": monitors or {"bottom": "screen@1", "back": "screen@0"},
    }
    if x_display is not None:
        bd["x_display"] = x_display
    cfg["devices"]["backdrops"] = bd
    cfg["devices"]["panels"] = {
        name: {
            "url": f"emulator:mdc#{name}",
            "id": i + 1,
            "timeout_s": 1.0,
            "input": "hdmi1",
            "brightness": 100,
            "contrast": 100,
            "dynamic_contrast_cmd": EMU_DYNAMIC_CONTRAST_CMD,
        }
        for i, name in enumerate(("bottom", "back"))
    }
    return cfg


class SynthCamera:
    """Image from the lab rig's state: the bottom display as its emulator shows it, a lit
    disk when the object is on the table, a checkerboard when the board is.

    ``value = gain * exposure_s * L`` clipped to [0, 1] (white level 1), float32 (H, W, 3).
    """

    def __init__(self, rig: LabRig, index: int):
        self.rig = rig
        self.index = index
        spec = rig.geometry.cameras[index]
        self.name = spec.name
        self.width, self.height = spec.width, spec.height
        self.captures = 0
        #: hook(camera) called before every capture (tests: fill the disk, pull a plug)
        self.before_capture: Callable[[SynthCamera], object] | None = None

    def info(self) -> CameraInfo:
        return CameraInfo(
            name=self.name, width=self.width, height=self.height, model="synth", white_level=1.0, linear=True
        )

    def radiance(self) -> np.ndarray:
        """Linear radiance (H, W, 3) float32 of what the camera sees now."""
        rig = self.rig
        h, w = self.height, self.width
        back = rig.bottom_display(w, h).astype(np.float32) / 255.0  # nearest-scaled, black if blank
        L = back.copy()
        yy, xx = np.mgrid[0:h, 0:w]
        light = sum(rig.dmx_levels().values()) / 255.0
        table = math.radians(rig.table_deg())
        if rig.scene["object"]:
            r = 0.3 * h
            inside = (xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2 <= r * r
            albedo = np.array([0.6, 0.4 + 0.1 * math.cos(table), 0.2 + 0.05 * self.index], np.float32)
            L[inside] = albedo * (0.05 + 0.5 * light)
        if rig.scene["board"]:
            board = ((xx // 3 + yy // 3) % 2).astype(np.float32)[..., None] * (0.1 + 0.4 * light)
            L = np.where((yy > h // 2)[..., None], board, L)
        return L.astype(np.float32)

    def capture(self, exposure_s: float) -> np.ndarray:
        if self.before_capture is not None:
            self.before_capture(self)
        self.rig.settle()
        self.captures += 1
        gain = self.rig.geometry.cameras[self.index].gain
        return np.clip(self.radiance() * gain * exposure_s, 0.0, 1.0).astype(np.float32)


class LabRig:
    """A stateful fake rig: implements :class:`~opacityhull.rigs.interfaces.Rig` (and
    :class:`~opacityhull.rigs.interfaces.GroundTruthSource`) with the real drivers over
    ptys to the real emulators, and :class:`SynthCamera` cameras.

    Parameters
    ----------
    config : dict, optional
        Rig TOML content with ``emulator:KIND`` URLs (default :data:`LAB_RIG_CONFIG`:
        a GRBL with the turntable on X and the light-array rotation on Y, an Enttec
        widget with 4 lights, a display controller with two displays, 3 cameras).

    Attributes
    ----------
    emulators : the running emulators (``by_device``, ``servers``).
    grbl, enttec, display_emulator : the emulated devices (their state is the truth).
    hw : the :class:`~opacityhull.rigs.rig.HardwareRig` doing the real work.
    scene : ``{"board": bool, "object": bool}``, changed by :meth:`operator`.
    operator_log, ground_truth_calls : what was asked of the rig.
    """

    def __init__(self, config: dict[str, Any] | None = None):
        from .config import parse_rig_config
        from .emulators.launch import start_emulators
        from .rig import build_rig

        cfg = parse_rig_config(LAB_RIG_CONFIG if config is None else config, source="lab-rig")
        self.emulators = start_emulators(cfg)
        by = self.emulators.by_device
        self.grbl: Any = by["turntable"]
        self.enttec: Any = by["light_array"]
        # an OHDC-2 controller's emulator, or None: video-output backdrops (the picture is
        # what the DisplayOutput last drew) with MDC panels (``panel_emulators``)
        self.display_emulator: Any = by.get("backdrops")
        self.display_server = self.emulators.servers.get("emulator:display")
        self.panel_emulators: dict[str, Any] = {p.display: by[p.name] for p in cfg.panels if p.name in by}
        self.grbl_server = self.emulators.servers["emulator:grbl"]
        self.geometry = cfg.geometry
        self.cameras = [SynthCamera(self, i) for i in range(len(self.geometry.cameras))]
        self.hw = build_rig(
            self.emulators.config,
            cameras=self.cameras,
            interactive=False,
            assume_ready=True,
            reconnect_attempts=1,
            reconnect_delay_s=0.01,
        )
        self.turntable = self.hw.turntable
        self.light_array = self.hw.light_array
        self.backdrops = self.hw.backdrops
        self.channels = dict(cfg.light_array.channel_map) if cfg.light_array is not None else {}
        self.scene = {"board": False, "object": True}
        self.operator_log: list[str] = []
        self.ground_truth_calls: list[list[tuple[int, float]]] = []

    # state as the emulators hold it (what a physical camera would see)
    def table_deg(self) -> float:
        return self.grbl.position_deg("X")

    def bottom_display(self, width: int, height: int) -> np.ndarray:
        """What the bottom display emits, nearest-scaled to ``width x height`` (uint8)."""
        from .display_protocol import nearest_resize

        if self.display_emulator is not None:
            return self.display_emulator.displayed(0, width, height)
        bd: Any = self.hw.backdrops
        img = bd.current("bottom") if bd is not None else None
        if img is None:
            return np.zeros((height, width, 3), np.uint8)
        return nearest_resize(img, width, height)

    def dmx_levels(self) -> dict[int, int]:
        return {lid: self.enttec.level(ch) for lid, ch in self.channels.items()}

    def settle(self, timeout_s: float = 2.0) -> None:
        """Wait until the lights output what the driver last sent (DMX packets are not
        acknowledged: the bytes may still be in the pty when the shutter opens, as a real
        lamp may still be warming up). A real rig waits a settle time instead."""
        if self.light_array is None:
            return
        want = {lid: int(v) for lid, v in self.light_array.levels().items()}
        deadline = time.monotonic() + timeout_s
        while self.dmx_levels() != want and time.monotonic() < deadline:
            time.sleep(0.001)

    def open(self) -> LabRig:
        self.hw.open()
        return self

    def close(self) -> None:
        try:
            self.hw.close()
        finally:
            self.emulators.stop()

    def __enter__(self) -> LabRig:
        return self.open()

    def __exit__(self, *exc: object) -> bool:
        self.close()
        return False

    def safe(self):
        return self.hw.safe()

    def check(self) -> list[DeviceInfo]:
        return self.hw.check()

    def describe(self) -> dict[str, Any]:
        return self.hw.describe()

    def operator(self, action: str, **details: Any) -> None:
        self.operator_log.append(action)
        if action == "place_board":
            self.scene["board"] = True
            self.scene["object"] = False
        elif action == "remove_board":
            self.scene["board"] = False
        elif action == "remove_object":
            self.scene["object"] = False
        elif action == "place_object":
            self.scene["object"] = True
        else:
            raise DeviceError(f"lab rig: unknown operator action {action!r}")

    def ground_truth(self, root: Path, views: Sequence[tuple[int, float]]) -> Path:
        """Record the views asked for in ``root/groundtruth/views.json``."""
        self.ground_truth_calls.append(list(views))
        d = Path(root) / "groundtruth"
        d.mkdir(exist_ok=True)
        (d / "views.json").write_text(json.dumps([list(v) for v in views]))
        return d


# --------------------------------------------------------------------------- a virtual display server


def read_xwd(path) -> np.ndarray:
    """The screen an Xvfb ``-fbdir`` file holds (XWD format, 24/32-bit TrueColor) as
    uint8 (rows, cols, 3) RGB: a screenshot of the virtual display, read at any moment."""
    import struct

    b = Path(path).read_bytes()
    hs = struct.unpack(">25I", b[:100])
    header_size, width, height, byte_order = hs[0], hs[4], hs[5], hs[7]
    bpp, bpl, ncolors = hs[11], hs[12], hs[19]
    masks = hs[14:17]
    if bpp != 32 or masks != (0xFF0000, 0xFF00, 0xFF):
        raise ValueError(f"{path}: XWD with {bpp} bits per pixel and masks {masks} (expected 32, RGB888)")
    off = header_size + 12 * ncolors
    rows = np.frombuffer(b, np.uint8, count=height * bpl, offset=off).reshape(height, bpl)
    px = rows[:, : 4 * width].reshape(height, width, 4)
    return px[..., 2::-1].copy() if byte_order == 0 else px[..., 1:].copy()


@contextmanager
def xvfb(screens: Sequence[tuple[int, int]] = ((320, 240),), *, timeout_s: float = 10.0) -> Iterator[tuple[str, Path]]:
    """A private Xvfb server with one X screen per ``(width, height)``, each a monitor.

    Yields ``(display, fbdir)``: the display name (``":N"``, a free number Xvfb chose)
    and the folder where Xvfb keeps each screen's framebuffer as ``Xvfb_screenK``
    (:func:`read_xwd` reads it). Raises :class:`FileNotFoundError` when Xvfb is not
    installed (``apt-get install xvfb``).
    """
    import os
    import shutil
    import subprocess
    import tempfile

    exe = shutil.which("Xvfb")
    if exe is None:
        raise FileNotFoundError("Xvfb is not installed (apt-get install xvfb; `make system-deps` does it)")
    fbdir = Path(tempfile.mkdtemp(prefix="ohxvfb-"))
    rfd, wfd = os.pipe()
    args = [exe, "-displayfd", str(wfd), "-nolisten", "tcp", "-fbdir", str(fbdir), "-noreset"]
    for i, (w, h) in enumerate(screens):
        args += ["-screen", str(i), f"{int(w)}x{int(h)}x24"]
    proc = subprocess.Popen(args, pass_fds=(wfd,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(wfd)
    try:
        number = b""
        deadline = time.monotonic() + timeout_s
        while not number.endswith(b"\n"):
            import select

            r, _, _ = select.select([rfd], [], [], max(0.0, deadline - time.monotonic()))
            chunk = os.read(rfd, 16) if r else b""
            if not chunk:
                err = (
                    proc.stderr.read().decode(errors="replace")[-400:]
                    if proc.poll() is not None and proc.stderr
                    else ""
                )
                raise RuntimeError(f"Xvfb did not start within {timeout_s} s: {err}")
            number += chunk
        yield f":{int(number)}", fbdir
    finally:
        os.close(rfd)
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(fbdir, ignore_errors=True)
