"""Shared fixtures for the rig driver tests: emulators served over a real pty AND over TCP.

Every driver test that takes ``kind`` runs twice, once per transport. Fixtures build a
fresh emulator + server + driver per test (milliseconds) and tear them down, so a test
may break its device (vanish, alarms) freely.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from types import SimpleNamespace

import pytest

from opacityhull.rigs.emulators.base import EmulatorServer
from opacityhull.rigs.emulators.enttec import EnttecEmulator
from opacityhull.rigs.emulators.grbl import GrblEmulator
from opacityhull.rigs.lights import DMX_SERIAL, DmxLightArray, EnttecDmx
from opacityhull.rigs.motion import GRBL_SERIAL, GrblAxis, GrblController
from opacityhull.rigs.transport import DeviceTimeout


@pytest.fixture(params=["pty", "tcp"])
def kind(request) -> str:
    """Transport of the emulator server."""
    return request.param


def _wait_for(predicate, timeout_s: float = 5.0, what: str = "condition"):
    """Poll ``predicate`` until true (waiting on state, not on time); fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = predicate()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.002)


@pytest.fixture
def wait_for():
    return _wait_for


def _open_silent(kit, port) -> str:
    """Open ``port`` while ``kit.emu`` answers nothing: it must raise
    :class:`DeviceTimeout` naming ``kit.server.url`` and stay closed. Returns the message."""
    kit.emu.faults.silent = True
    with pytest.raises(DeviceTimeout) as ei:
        port.open()
    msg = str(ei.value)
    assert kit.server.url in msg, msg
    assert not port.is_open
    return msg


@pytest.fixture
def open_silent():
    """``msg = open_silent(kit, port)``: see :func:`_open_silent`."""
    return _open_silent


@pytest.fixture
def background():
    """Run a blocking driver call in a thread: ``fut = background(fn, *args)``."""
    pool = ThreadPoolExecutor(max_workers=2)
    yield pool.submit
    pool.shutdown(wait=True, cancel_futures=True)


@pytest.fixture
def grbl(kind):
    """Factory: ``g = grbl(emu_kw={...}, timeout_s=0.5)`` -> namespace with ``server``,
    ``emu`` (GrblEmulator), ``ctl`` (GrblController, opened unless ``open=False``),
    ``turntable`` (axis X, continuous) and ``lights`` (axis Y, soft limits ±180°, backlash
    from ``backlash_deg``)."""
    made = []

    def make(
        *,
        emu_kw=None,
        timeout_s: float = 0.5,
        open: bool = True,
        backlash_deg: float = 0.0,
        boot_timeout_s: float = 0.5,
        unlock: bool = False,
        **ctl_kw,
    ):
        emu = GrblEmulator(**(emu_kw or {}))
        srv = EmulatorServer(emu, kind=kind)
        srv.start()
        ctl = GrblController.from_url(
            srv.url,
            name="grbl",
            serial=replace(GRBL_SERIAL, timeout_s=timeout_s),
            boot_timeout_s=boot_timeout_s,
            **ctl_kw,
        )
        made.append((srv, ctl))
        tt = GrblAxis(ctl, axis="X", steps_per_deg=80.0, max_rate_deg_s=30.0, accel_deg_s2=60.0, name="turntable")
        la = GrblAxis(
            ctl,
            axis="Y",
            steps_per_deg=80.0,
            max_rate_deg_s=30.0,
            accel_deg_s2=60.0,
            backlash_deg=backlash_deg,
            soft_limits_deg=(-180.0, 180.0),
            name="light_rotation",
        )
        if open:
            ctl.open(unlock=unlock)
        return SimpleNamespace(server=srv, emu=emu, ctl=ctl, turntable=tt, lights=la, kind=kind)

    yield make
    for srv, ctl in made:
        ctl.close()
        srv.stop()


@pytest.fixture
def enttec(kind):
    """Factory: ``e = enttec(channels={0: 1, ...})`` -> namespace with ``server``, ``emu``
    (EnttecEmulator), ``dmx`` (EnttecDmx, opened unless ``open=False``) and ``array``
    (DmxLightArray)."""
    made = []

    def make(*, emu_kw=None, channels=None, timeout_s: float = 0.3, open: bool = True, rotation=None):
        emu = EnttecEmulator(**(emu_kw or {}))
        srv = EmulatorServer(emu, kind=kind)
        srv.start()
        dmx = EnttecDmx.from_url(srv.url, name="dmx", serial=replace(DMX_SERIAL, timeout_s=timeout_s))
        made.append((srv, dmx))
        arr = DmxLightArray(dmx, channels=channels or {0: 1, 1: 2, 2: 3, 3: 4}, rotation=rotation, name="light_array")
        if open:
            dmx.open()
        return SimpleNamespace(server=srv, emu=emu, dmx=dmx, array=arr, kind=kind)

    yield make
    for srv, dmx in made:
        dmx.close()
        srv.stop()
