"""GRBL motion drivers: one :class:`GrblController` per serial port, one :class:`GrblAxis`
per rotary axis on it (turntable on X, light-array rotation on Y of the same board).

Reliability rules this driver follows (each is a test in ``tests/rigs/test_grbl_driver.py``):

* **Absolute moves only** (``G90 G0 X...``): sending a move twice ends at the same
  place, so a retry is safe.
* **Ask before re-sending.** When the ``ok`` for a move does not come (timeout) or comes
  garbled, the driver queries the position with ``?`` first. At the target and idle: done,
  nothing is re-sent. Moving: the line got through, wait for it. Idle elsewhere: the line
  was lost on the way in, send it again (``retries`` times at most).
* **Late replies are never taken for new answers.** Status reports (``<...>``) and line
  replies (``ok``/``error:N``) are told apart by their form. A line reply that timed out
  leaves the stream "dirty": before the next line the driver sends ``$G`` and discards
  everything up to its ``[GC:...]`` — GRBL answers lines in order, so any late reply to an
  earlier line comes before it. A status query that timed out makes the next
  :meth:`GrblController.status` ask twice and keep the second report.
* **Push messages are not thrown away.** Before every transaction the driver reads what
  arrived unasked; an ``ALARM:N`` or a welcome banner (the board reset) that arrives
  during a move turns into :class:`GrblAlarm` / :class:`GrblInterrupted`.
* Moves wait for ``Idle`` at the target by polling ``?`` with a deadline from the
  trapezoid move time (distance, rate, acceleration) plus a margin; ``Hold``, ``Door``,
  ``Alarm`` during a move raise.
* :meth:`GrblAxis.stop` / :meth:`GrblController.stop` send the real-time feed hold
  ``!`` without taking the driver lock (real-time bytes may interleave with anything)
  and never raise, even on a dead port: :func:`Rig.safe` relies on it.

Angles: G-code units are degrees (``$100`` steps/degree, ``$110`` degrees/min, ``$120``
degrees/s²). A *continuous* axis (the turntable; default when no ``soft_limits_deg``)
accepts any angle and takes the **short way** to it: the controller coordinate is
``current + wrap180(angle - current)``, so ``move_to(350)`` from 0 turns -10 degrees, and
``move_to`` returns the reached angle expressed near the request (≈350). Its
:meth:`~GrblAxis.position_deg` is wrapped to [0, 360). An axis with ``soft_limits_deg``
(cables that must not wind up) is not wrapped: targets outside the range are rejected
before anything is sent.

Backlash: with ``backlash_deg > 0`` every target is approached moving in the +
direction: a move in the - direction goes to ``target - backlash_deg`` first and then up
to the target, so the gear train always rests against the same flank.

Thread safety: every transaction holds the controller's lock (axes on one controller
move one at a time); :meth:`~GrblController.stop` and :meth:`~GrblController.close` do
not take it.
"""

from __future__ import annotations

import logging
import math
import numbers
import threading
import time
from collections import deque
from typing import Any

from ..errors import ConfigError, DeviceError, InputError
from . import grbl_protocol as gp
from .interfaces import DeviceInfo, check_opened
from .transport import DeviceGone, DeviceTimeout, OverTransport, ProtocolError, Transport, driver_name
from .transport import SerialSettings, SerialTransport, reopen

log = logging.getLogger(__name__)

__all__ = [
    "GRBL_SERIAL",
    "GrblController",
    "GrblAxis",
    "GrblCommandError",
    "GrblAlarm",
    "GrblInterrupted",
    "move_duration_s",
]


#: GRBL 1.1 talks at 115200 baud; a lost move line is re-sent once; :meth:`GrblController.reconnect`
#: tries 5 times, 0.5 s apart.
GRBL_SERIAL = SerialSettings(baudrate=115200, timeout_s=2.0, retries=1, reconnect_attempts=5, reconnect_delay_s=0.5)


class GrblCommandError(DeviceError):
    """GRBL rejected a line with ``error:N`` (nothing in that line was executed)."""

    def __init__(self, message: str, *, code: int, meaning: str, line: str):
        super().__init__(message)
        self.code = code
        self.meaning = meaning
        self.line = line


class GrblAlarm(DeviceError):
    """GRBL is in the alarm state (``ALARM:N``); motion is locked until reset/``$X``/``$H``."""

    def __init__(
        self, message: str, *, code: int | None, meaning: str, position_deg: float | None = None, critical: bool = False
    ):
        super().__init__(message)
        self.code = code
        self.meaning = meaning
        self.position_deg = position_deg
        self.critical = critical


class GrblInterrupted(DeviceError):
    """A move was interrupted without an alarm: feed hold, safety door, sleep, check mode
    or an unexpected controller reset."""

    def __init__(self, message: str, *, state: str, substate: int | None = None):
        super().__init__(message)
        self.state = state
        self.substate = substate


def move_duration_s(distance_deg: float, rate_deg_s: float, accel_deg_s2: float) -> float:
    """Time of a trapezoid (or triangle) velocity profile from rest to rest.

    Parameters
    ----------
    distance_deg : path length, degrees (>= 0).
    rate_deg_s : cruise speed, degrees/s (> 0).
    accel_deg_s2 : acceleration and deceleration, degrees/s² (> 0).
    """
    d = abs(float(distance_deg))
    if d == 0.0:
        return 0.0
    v, a = float(rate_deg_s), float(accel_deg_s2)
    if d >= v * v / a:
        return d / v + v / a
    return 2.0 * math.sqrt(d / a)


class GrblController(OverTransport):
    """One GRBL 1.1 board on one serial port, shared by its axes.

    Parameters
    ----------
    transport : the byte transport (a :class:`~opacityhull.rigs.transport.SerialTransport`
        from :meth:`from_url`, or the in-memory one of :mod:`opacityhull.rigs.testing`).
    name : device name in messages (default: the transport's).
    serial : :class:`~opacityhull.rigs.transport.SerialSettings` (default
        :data:`GRBL_SERIAL`): ``timeout_s`` per reply (a move adds its travel time on
        top), ``retries`` the default of the axes, ``reconnect_attempts`` and
        ``reconnect_delay_s`` those of :meth:`reconnect`; ``baudrate`` is the
        transport's (:meth:`from_url` opens the port at it).
    poll_s : interval between ``?`` polls while waiting for a move.
    boot_timeout_s : how long :meth:`open` keeps asking ``?`` for a first answer (an
        Arduino resets when the port opens and takes 1-2 s to boot); then it sends a soft
        reset and waits ``timeout_s`` for the banner. Default ``max(1, 1.5 * timeout_s)``.

    No I/O happens in ``__init__``. Use as a context manager or :meth:`open`/:meth:`close`.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        name: str | None = None,
        serial: SerialSettings = GRBL_SERIAL,
        poll_s: float = 0.02,
        boot_timeout_s: float | None = None,
    ):
        name = driver_name(transport, name, driver="GrblController", fallback="grbl")
        self.name = name
        self.timeout_s = float(serial.timeout_s)
        self.retries = serial.retries
        self.reconnect_attempts = serial.reconnect_attempts
        self.reconnect_delay_s = float(serial.reconnect_delay_s)
        self.poll_s = float(poll_s)
        self.boot_timeout_s = max(1.0, 1.5 * self.timeout_s) if boot_timeout_s is None else float(boot_timeout_s)
        self.transport = transport
        self.lock = threading.RLock()
        self._axes: dict[str, GrblAxis] = {}
        self._line_dirty = False
        self._status_stale = False
        self.settings: dict[int, float] = {}
        self.version: str | None = None
        self.build: str | None = None
        self.options: str = ""
        self.last_alarm: gp.Alarm | None = None
        self.alarm_seq = 0
        self.halted = False  # a critical alarm arrived and no reset since: GRBL answers nothing
        self.resets_seen = 0
        self.last_status: gp.Status | None = None
        self._wco: dict[str, float] = {}
        self.messages: deque = deque(maxlen=64)
        self.discarded: deque = deque(maxlen=64)  # late replies and garbage skipped, for diagnosis
        self.last_stop_error: Exception | None = None

    @classmethod
    def from_url(
        cls,
        url: str,
        *,
        name: str = "grbl",
        serial: SerialSettings = GRBL_SERIAL,
        poll_s: float = 0.02,
        boot_timeout_s: float | None = None,
    ) -> GrblController:
        """A controller on a serial URL (``/dev/ttyUSB0``, ``socket://host:port``, a pty
        path); ``serial.timeout_s`` bounds every reply and every write."""
        transport = SerialTransport.from_settings(url, serial, name=name)
        return cls(transport, name=name, serial=serial, poll_s=poll_s, boot_timeout_s=boot_timeout_s)

    # ------------------------------------------------------------------ lifecycle
    @property
    def baudrate(self) -> int:
        return self.transport.baudrate

    @property
    def axes(self) -> dict:
        """Axis letter -> :class:`GrblAxis` registered on this controller."""
        return dict(self._axes)

    @property
    def single_axis_homing(self) -> bool:
        """The firmware was built with ``$HX`` single-axis homing (``[OPT:]`` has ``H``)."""
        return "H" in self.options

    def stop_time_s(self) -> float:
        """Longest time any axis on this controller needs to decelerate from full speed
        (at most 5 s; 0.5 s with no axis): how long a feed hold takes to reach ``Hold:0``."""
        axes = self._axes.values()
        return min(5.0, max([a.max_rate_deg_s / (a.accel_deg_s2 or 10.0) for a in axes] or [0.5]))

    def _register(self, axis: GrblAxis) -> None:
        if axis.axis in self._axes and self._axes[axis.axis] is not axis:
            raise ConfigError(
                f"{self.name}: axis {axis.axis} on {self.url} is already used by "
                f"{self._axes[axis.axis].name!r}; give {axis.name!r} another axis letter"
            )
        self._axes[axis.axis] = axis

    def open(self, *, unlock: bool = False, reset: bool = False) -> GrblController:
        """Open the port, make sure a GRBL answers, read ``$I`` and ``$$``, and write
        ``$100/$110/$120`` for the registered axes where they differ.

        Parameters
        ----------
        unlock : send ``$X`` if the controller is in alarm (position not re-established:
            prefer homing when a home switch is fitted).
        reset : start with a soft reset (clears a feed hold; loses position if moving).
        """
        with self.lock:
            if self.is_open:
                return self
            self.transport.open()
            self._line_dirty = False
            self._status_stale = False
            self.halted = False  # re-learnt from what the controller says now
            try:
                self._handshake(reset=reset)
                try:
                    pushes = self.send_line(gp.build_info())
                except GrblCommandError:
                    pushes = []
                for r in pushes:
                    if isinstance(r, gp.Message) and r.kind == "VER":
                        self.build = r.text.split(":")[0]  # "1.1h.20190830"
                        head, _, date = self.build.rpartition(".")
                        self.version = self.version or (head if date.isdigit() and head else self.build)
                    elif isinstance(r, gp.Message) and r.kind == "OPT":
                        self.options = r.text.split(",")[0]
                st = self.status()
                if st.state == "Alarm" and unlock:
                    self.unlock()
                elif st.state == "Hold" and st.substate == 0:
                    raise GrblInterrupted(
                        f"{self.name}: controller on {self.url} is in a completed feed hold (Hold:0: stopped, "
                        "as a capture's safe stop leaves it); resume it with ~ or open with reset=True",
                        state=st.state,
                        substate=0,
                    )
                elif st.state in ("Run", "Jog", "Home", "Hold", "Door", "Sleep", "Check"):
                    raise GrblInterrupted(
                        f"{self.name}: controller on {self.url} is busy (state {st.state}) — another program may "
                        "be driving it; stop it, or open with reset=True (a soft reset: cancels motion, wakes it "
                        "from sleep, leaves check mode)",
                        state=st.state,
                    )
                self.read_settings()
                if int(self.settings.get(13, 0)) == 1:  # inch reports would scale our degrees by 1/25.4
                    self.write_setting(13, 0)
                for ax in self._axes.values():
                    ax._configured = False
                    ax._last_dir = None
                    ax._apply_settings()
            except BaseException:
                self.transport.close()
                raise
        return self

    def close(self) -> None:
        """Close the port (no lock: may be called while another thread is blocked in a move)."""
        self.transport.close()

    def reconnect(
        self,
        max_attempts: int | None = None,
        delay_s: float | None = None,
        *,
        url: str | None = None,
        unlock: bool = False,
    ) -> GrblController:
        """Reopen the port after :class:`DeviceGone` and re-read state and settings.

        Tries ``max_attempts`` times (default :attr:`reconnect_attempts`), ``delay_s``
        apart (default :attr:`reconnect_delay_s`); ``url`` replaces the port (a
        re-enumerated USB device). Raises :class:`DeviceGone` naming the last error.
        """
        if max_attempts is not None and max_attempts < 1:
            raise InputError(f"{self.name}: max_attempts must be >= 1, got {max_attempts}")

        def once(_attempt: int) -> GrblController:
            self.close()
            if url is not None:
                self.transport.url = url
            return self.open(unlock=unlock)

        def gave_up(tries: int, last: BaseException | None) -> DeviceGone:
            return DeviceGone(
                f"{self.name}: could not reconnect to {self.url} after {tries} attempts "
                f"({last}) — check the USB cable and the controller's power, then reconnect"
            )

        return reopen(
            once,
            attempts=self.reconnect_attempts if max_attempts is None else max_attempts,
            delay_s=self.reconnect_delay_s if delay_s is None else delay_s,
            catch=DeviceError,
            gave_up=gave_up,
        )

    def _require_open(self) -> None:
        if not self.is_open:
            raise DeviceGone(f"{self.name}: port {self.url} is not open — call open() (or reconnect())")

    # ------------------------------------------------------------------ line I/O
    def _readline(self, deadline: float, what: str) -> bytes:
        while True:
            raw = self.transport.read_until(b"\n", timeout_s=max(0.0, deadline - time.monotonic()), what=what)
            if raw.strip(b"\r\n \t"):
                return raw

    def _parse_or_discard(self, raw: bytes):
        """The parsed line, or None for a garbled one (kept in :attr:`discarded`)."""
        try:
            return gp.parse_response(raw)
        except ProtocolError:
            self.discarded.append(raw.rstrip(b"\r\n"))
            return None

    def _next_response(self, deadline: float, what: str) -> tuple[bytes, Any]:
        """The next line before ``deadline`` and its parse (None for a garbled one); a timeout is explained."""
        try:
            raw = self._readline(deadline, what)
        except DeviceTimeout as e:
            raise self._explain_timeout(e) from None
        return raw, self._parse_or_discard(raw)

    def _note(self, r) -> None:
        if isinstance(r, gp.Alarm):
            log.warning("%s: ALARM:%s (%s)", self.name, r.code, r.meaning)
            self.last_alarm = r
            self.alarm_seq += 1
            self.halted = self.halted or r.critical
        elif isinstance(r, gp.Banner):
            log.info("%s: controller reset (banner %r)", self.name, r.text)
            self.resets_seen += 1
            self.halted = False
            self.version = r.version
            self._line_dirty = False  # a reset flushed GRBL's buffers: no earlier reply will come
        elif isinstance(r, gp.Status):
            self.last_status = r
            if r.wco is not None:
                self._wco = dict(r.wco)
        elif isinstance(r, (gp.Message, gp.StartupLine)):
            self.messages.append(r)

    def _take(self, lines, *, tolerant: bool) -> None:
        for raw in lines:
            if not raw.strip(b"\r\n \t"):
                continue
            r = self._parse_or_discard(raw)
            if r is None:
                continue
            if isinstance(r, (gp.Ok, gp.GrblError)):
                self.discarded.append(raw.rstrip(b"\r\n"))
                if not tolerant:
                    self._line_dirty = True  # a reply nobody waited for: the stream is out of step
            elif isinstance(r, gp.Status):
                self.discarded.append(raw.rstrip(b"\r\n"))
                self._status_stale = False
                self._note(r)
            else:
                self._note(r)

    def _service(self) -> None:
        """Take in what arrived unasked (alarms, banners, late replies) before a transaction."""
        if self._line_dirty or self._status_stale:
            raw = self.transport.flush_input()  # partial tails of a failed exchange go too
            self._take(raw.split(b"\n")[:-1], tolerant=True)  # the last piece is partial or empty
        else:
            self._take(self.transport.pending_lines(), tolerant=False)

    def _resync(self) -> None:
        """Send ``$G`` and discard everything before its ``[GC:...]`` + ``ok``."""
        log.debug("%s: resynchronising the line stream with $G", self.name)
        self.transport.write(gp.parser_state())
        deadline = time.monotonic() + self.timeout_s
        seen_gc = False
        while True:
            raw, r = self._next_response(deadline, "reply to $G (resynchronising after a lost reply)")
            if r is None:
                continue
            if isinstance(r, gp.Message) and r.kind == "GC":
                seen_gc = True
            elif isinstance(r, (gp.Ok, gp.GrblError)):
                if seen_gc:
                    self._line_dirty = False
                    return
                self.discarded.append(raw.rstrip(b"\r\n"))
            else:
                self._note(r)

    def _explain_timeout(self, e: DeviceTimeout) -> DeviceError:
        if self.halted:
            return self._alarm_error(self.last_alarm, requery=False)
        return DeviceTimeout(
            f"{e} [GRBL at {self.baudrate} baud; check the USB cable, the controller's power "
            "and that no other program holds the port]"
        )

    def send_line(self, line: str | bytes, *, timeout_s: float | None = None) -> list:
        """Send one line and wait for its ``ok``; return the push messages that came with it
        (``$$`` settings, ``[GC:...]``, ``[MSG:...]``).

        Raises
        ------
        InputError
            The line is not sendable (before any byte).
        GrblCommandError
            ``error:N`` — message names the code, its meaning and what to check.
        GrblAlarm
            ``ALARM:N`` arrived instead.
        GrblInterrupted
            The controller reset (banner) while the line was pending.
        DeviceTimeout, ProtocolError, DeviceGone
            No reply / garbled reply / port vanished.
        """
        data = gp.encode_line(line)
        text = data.decode("ascii").strip()
        with self.lock:
            self._require_open()
            self._service()
            if self.halted:
                raise self._alarm_error(self.last_alarm, doing=f"sending {text!r}", requery=False)
            if self._line_dirty:
                self._resync()
            self.transport.write(data)
            self._line_dirty = True
            pushes: list = []
            t_line = self.timeout_s if timeout_s is None else float(timeout_s)
            deadline = time.monotonic() + t_line
            with self.transport.exchange(t_line, f"reply to {text!r}"):
                return self._await_ok(text, deadline, pushes)

    def _await_ok(self, text: str, deadline: float, pushes: list) -> list:
        """The rest of :meth:`send_line`: lines until its ``ok`` (inside its exchange)."""
        while True:
            try:
                raw = self._readline(deadline, f"reply to {text!r}")
            except DeviceTimeout as e:
                raise self._explain_timeout(e) from None
            try:
                r = gp.parse_response(raw)
            except ProtocolError:
                raise ProtocolError(
                    f"{self.name}: garbled reply {raw!r} to {text!r} on {self.url} — check the baud rate "
                    f"({self.baudrate}), the USB cable and the grounding of the stepper supply"
                ) from None
            if isinstance(r, gp.Ok):
                self._line_dirty = False
                return pushes
            if isinstance(r, gp.GrblError):
                self._line_dirty = False
                raise GrblCommandError(
                    f"{self.name}: {text!r} rejected with error:{r.code} ({r.meaning}) — {r.hint}",
                    code=r.code,
                    meaning=r.meaning,
                    line=text,
                )
            if isinstance(r, gp.Alarm):
                self._note(r)
                raise self._alarm_error(r, doing=f"sending {text!r}")
            if isinstance(r, gp.Banner):
                self._note(r)
                raise GrblInterrupted(
                    f"{self.name}: the controller reset while {text!r} was pending (got {r.text!r}) — the line "
                    "was discarded and the position may be lost; check its power supply and reset wiring",
                    state="reset",
                )
            if isinstance(r, gp.Status):
                self._note(r)
                self._status_stale = False
                self.discarded.append(raw.rstrip(b"\r\n"))
                continue
            self._note(r)
            pushes.append(r)

    def _alarm_error(
        self, a: gp.Alarm | None, *, doing: str = "", axis: str | None = None, requery: bool = True
    ) -> GrblAlarm:
        """A :class:`GrblAlarm` for ``a``, with the position re-queried when GRBL still answers."""
        pos = None
        if requery and axis is not None and not (a is not None and a.critical):
            try:
                st = self.status()
                pos = st.position(self._wco).get(axis)
            except DeviceError:
                pos = None
        where = f" (axis {axis} now at {pos:.3f} deg)" if pos is not None else ""
        ctx = f" while {doing}" if doing else ""
        if a is None:
            return GrblAlarm(
                f"{self.name}: controller is in ALARM{ctx}{where} — home ($H) or unlock ($X) after checking the axis",
                code=None,
                meaning="alarm state",
                position_deg=pos,
            )
        short = gp.ALARM_CODES.get(a.code, ("alarm", "", ""))[0].lower()
        halt = " GRBL now ignores everything until a soft reset (reset())." if a.critical and self.halted else ""
        return GrblAlarm(
            f"{self.name}: ALARM:{a.code} {short}{ctx} — {a.meaning}; {a.hint}{where}.{halt}",
            code=a.code,
            meaning=a.meaning,
            position_deg=pos,
            critical=a.critical,
        )

    # ------------------------------------------------------------------ status
    def status(self, *, timeout_s: float | None = None) -> gp.Status:
        """Ask ``?`` and return the report (late replies waiting in the buffer are
        taken in first and never returned as this answer)."""
        with self.lock:
            self._require_open()
            self._service()
            if self.halted:  # GRBL does not answer '?' in a critical alarm: do not wait for nothing
                raise self._alarm_error(self.last_alarm, requery=False)
            deadline = time.monotonic() + (self.timeout_s if timeout_s is None else float(timeout_s))
            if self._status_stale:  # an earlier '?' may still be answered: ask twice, keep the second
                self.transport.write(gp.STATUS_QUERY)
                self._read_status(deadline)
            self.transport.write(gp.STATUS_QUERY)
            st = self._read_status(deadline)
            self._status_stale = False
            return st

    def _read_status(self, deadline: float) -> gp.Status:
        while True:
            try:
                raw = self._readline(deadline, "status report (answer to '?')")
            except DeviceTimeout as e:
                self._status_stale = True
                raise self._explain_timeout(e) from None
            try:
                r = gp.parse_response(raw)
            except ProtocolError:
                if self._status_stale or self._line_dirty:
                    self.discarded.append(raw.rstrip(b"\r\n"))
                    continue
                self._status_stale = True
                raise ProtocolError(
                    f"{self.name}: garbled status report {raw!r} on {self.url} — check the baud rate "
                    f"({self.baudrate}), the USB cable and the grounding of the stepper supply"
                ) from None
            if isinstance(r, gp.Status):
                self._note(r)
                return r
            if isinstance(r, (gp.Ok, gp.GrblError)):
                self.discarded.append(raw.rstrip(b"\r\n"))  # a late line reply: not ours
                self._line_dirty = True
                continue
            self._note(r)

    def position(self, axis: str) -> float:
        """Work position of ``axis`` from a fresh status report (degrees, unwrapped)."""
        return self.status().position(self._wco)[axis.upper()]

    # ------------------------------------------------------------------ commands
    def _handshake(self, *, reset: bool) -> None:
        mark = self.transport.mark()
        # one overall deadline: a port that keeps sending lines (a babbling device, a
        # wrong baud rate) cannot keep the handshake going
        with self.transport.exchange(self.boot_timeout_s + self.timeout_s, "GRBL handshake"):
            self._handshake_once(reset=reset, mark=mark)

    def _handshake_once(self, *, reset: bool, mark) -> None:
        if not reset:
            deadline = time.monotonic() + self.boot_timeout_s
            asked = 0
            self.transport.flush_input()
            while time.monotonic() < deadline:
                self.transport.write(gp.STATUS_QUERY)
                asked += 1
                until = min(deadline, time.monotonic() + 0.3)
                while True:
                    try:
                        raw = self._readline(until, "answer to '?'")
                    except DeviceTimeout:
                        break
                    r = self._parse_or_discard(raw)
                    if r is None:
                        continue
                    self._note(r)
                    if isinstance(r, gp.Status):
                        self._status_stale = asked > 1  # an earlier '?' may still be answered
                        return
        # nothing answered '?': provoke the welcome banner
        self.transport.write(gp.SOFT_RESET)
        deadline = time.monotonic() + self.timeout_s
        while True:
            try:
                raw = self._readline(deadline, "GRBL welcome banner after a soft reset")
            except DeviceTimeout:
                raise DeviceTimeout(
                    f"{self.name}: no answer to '?' nor a welcome banner after a soft reset on {self.url}; "
                    f"{self.transport.heard_since(mark)} — check that the controller is powered, runs GRBL 1.1 at "
                    f"{self.baudrate} baud, and that no other program holds the port"
                ) from None
            r = self._parse_or_discard(raw)
            if r is None:
                continue
            self._note(r)
            if isinstance(r, gp.Banner):
                self._status_stale = True
                return

    def read_settings(self) -> dict[int, float]:
        """``$$`` -> ``{number: value}`` (also kept in :attr:`settings`)."""
        pushes = self.send_line(gp.get_settings())
        settings = gp.parse_settings(pushes)
        if not settings:
            raise ProtocolError(f"{self.name}: '$$' on {self.url} returned no settings — is this a GRBL 1.1?")
        self.settings = settings
        return dict(settings)

    def write_setting(self, number: int, value: float) -> None:
        """``$N=value`` (EEPROM); :attr:`settings` follows."""
        self.send_line(gp.set_setting(number, value))
        self.settings[number] = float(value)

    def unlock(self) -> None:
        """``$X``: clear the alarm lock without homing (check the axis position yourself)."""
        self.send_line(gp.unlock())

    def home(self, axes: str = "", *, timeout_s: float = 120.0) -> None:
        """``$H`` (all axes) or ``$H<axis>``; returns when homing finished (``ok``)."""
        self.send_line(gp.home(axes), timeout_s=timeout_s)
        for ax in self._axes.values():
            ax._last_dir = None

    def reset(self) -> list:
        """Soft reset (Ctrl-X) and wait for the banner; returns the pushes seen (e.g. ``ALARM:3``
        when it stopped a move). Motion and queued lines are discarded."""
        with self.lock:
            self._require_open()
            self._service()
            self.transport.write(gp.SOFT_RESET)
            deadline = time.monotonic() + self.timeout_s
            pushes = []
            while True:
                _, r = self._next_response(deadline, "welcome banner after a soft reset")
                if r is None:
                    continue
                self._note(r)
                pushes.append(r)
                if isinstance(r, gp.Banner):
                    self._line_dirty = False
                    self._status_stale = False  # "a soft-reset clears the last status report query"
                    for ax in self._axes.values():
                        ax._last_dir = None
                    return pushes

    def resume(self) -> None:
        """Cycle start ``~``: resume after a feed hold (or a closed safety door)."""
        with self.lock:
            self._require_open()
            self.transport.write(gp.CYCLE_START)

    def stop(self) -> None:
        """Feed hold ``!`` now. Never raises (a dead port is recorded in :attr:`last_stop_error`)."""
        try:
            if self.transport.is_open:
                self.transport.write(gp.FEED_HOLD)
            self.last_stop_error = None
        except Exception as e:  # noqa: BLE001 - used from Rig.safe: must not mask the real error
            self.last_stop_error = e

    def cancel_motion(self) -> None:
        """Stop and forget the rest of the motion without losing position: feed hold, wait
        for ``Hold:0`` (decelerated), then soft reset."""
        with self.lock:
            self.stop()
            deadline = time.monotonic() + max(self.timeout_s, 10.0)
            while time.monotonic() < deadline:
                st = self.status()
                if st.state != "Hold" or st.substate == 0:
                    break
                time.sleep(self.poll_s)
            self.reset()

    def check(self) -> DeviceInfo:
        """Controller identity and state; never raises."""
        return check_opened(self, self._probe)

    def _probe(self) -> DeviceInfo:
        st = self.status()
        ok = st.state in ("Idle", "Run", "Jog", "Home")
        alarm = f" ALARM:{self.last_alarm.code}" if st.state == "Alarm" and self.last_alarm else ""
        return DeviceInfo(
            self.name,
            ok,
            f"{st.state}{alarm} on {self.url}",
            identity=f"Grbl {self.version or '?'} ({self.build or 'build ?'})",
            state={"state": st.state, "position": st.position(self._wco), "url": self.url},
        )


class GrblAxis:
    """One rotary axis of a :class:`GrblController`; implements ``RotaryAxis``/``Turntable``.

    Parameters
    ----------
    controller : the board (shared with the other axes on it).
    axis : GRBL axis letter.
    steps_per_deg : written to ``$10x`` when it differs.
    max_rate_deg_s : written to ``$11x`` (degrees/min = 60 x this).
    accel_deg_s2 : written to ``$12x``; None = keep the controller's value.
    backlash_deg : approach every target moving + by at least this much.
    soft_limits_deg : (min, max) allowed angles; None = continuous axis.
    name : device name in messages.
    continuous : wrap angles and take the short way; default: ``soft_limits_deg is None``.
    tolerance_deg : |reported - target| accepted as arrived; default half a step (at least
        the 0.0005 degree print resolution of GRBL's reports).
    retries : how often a move line that provably never arrived is re-sent; default the
        controller's (``serial.retries``).
    homing_timeout_s : how long ``$H`` may take.

    No I/O in ``__init__``; the controller's :meth:`~GrblController.open` applies the
    settings.
    """

    def __init__(
        self,
        controller: GrblController,
        *,
        axis: str = "X",
        steps_per_deg: float,
        max_rate_deg_s: float,
        accel_deg_s2: float | None = None,
        backlash_deg: float = 0.0,
        soft_limits_deg: tuple[float, float] | None = None,
        name: str | None = None,
        continuous: bool | None = None,
        tolerance_deg: float | None = None,
        retries: int | None = None,
        homing_timeout_s: float = 120.0,
    ):
        self.name = name or f"{controller.name}.{axis}"
        if not isinstance(axis, str) or axis.upper() not in gp.AXES or len(axis) != 1:
            raise ConfigError(f"{self.name}: axis = {axis!r} is not a GRBL axis letter ({', '.join(gp.AXES)})")
        self.axis = axis.upper()

        def positive(key, v):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"{self.name}: {key} = {v!r}, expected a finite number > 0")
            return float(v)

        self.steps_per_deg = positive("steps_per_deg", steps_per_deg)
        self.max_rate_deg_s = positive("max_rate_deg_s", max_rate_deg_s)
        self.accel_deg_s2 = None if accel_deg_s2 is None else positive("accel_deg_s2", accel_deg_s2)
        if self.steps_per_deg * self.max_rate_deg_s > 30000.0:
            raise ConfigError(
                f"{self.name}: steps_per_deg x max_rate_deg_s = "
                f"{self.steps_per_deg * self.max_rate_deg_s:.0f} steps/s exceeds GRBL's 30 kHz"
            )
        if (
            isinstance(backlash_deg, bool)
            or not isinstance(backlash_deg, (int, float))
            or not math.isfinite(backlash_deg)
            or not 0 <= backlash_deg < 90
        ):
            raise ConfigError(f"{self.name}: backlash_deg = {backlash_deg!r}, expected 0 <= value < 90")
        self.backlash_deg = float(backlash_deg)
        if soft_limits_deg is not None:
            try:
                lo, hi = (float(v) for v in soft_limits_deg)
            except (TypeError, ValueError):
                raise ConfigError(f"{self.name}: soft_limits_deg = {soft_limits_deg!r}, expected [min, max]") from None
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ConfigError(f"{self.name}: soft_limits_deg = {soft_limits_deg!r}, expected finite min < max")
            soft_limits_deg = (lo, hi)
        self.soft_limits_deg = soft_limits_deg
        self.continuous = (soft_limits_deg is None) if continuous is None else bool(continuous)
        res = max(0.5 / self.steps_per_deg, 0.0005) + 1e-9
        self.tolerance_deg = res if tolerance_deg is None else float(tolerance_deg)
        retries = controller.retries if retries is None else retries
        if not isinstance(retries, int) or retries < 0:
            raise ConfigError(f"{self.name}: retries = {retries!r}, expected an integer >= 0")
        self.retries = retries
        self.homing_timeout_s = float(homing_timeout_s)
        self.controller = controller
        self._configured = False
        self._last_dir: int | None = None
        self.moves = 0  # legs commanded, for diagnostics
        controller._register(self)

    # ------------------------------------------------------------------ settings
    def _apply_settings(self) -> None:
        c = self.controller
        k = gp.AXES.index(self.axis)
        want = {100 + k: self.steps_per_deg, 110 + k: self.max_rate_deg_s * 60.0}
        if self.accel_deg_s2 is not None:
            want[120 + k] = self.accel_deg_s2
        for n, v in want.items():
            have = c.settings.get(n)
            if have is None:
                raise DeviceError(
                    f"{c.name}: controller on {c.url} has no setting ${n} — is axis {self.axis} "
                    "enabled in this GRBL build?"
                )
            if abs(have - v) > 5e-4 + 1e-7 * abs(v):
                c.write_setting(n, v)
        self._configured = True

    def _ensure_configured(self) -> None:
        if not self._configured:
            self._apply_settings()

    def _rate_accel(self) -> tuple[float, float]:
        k = gp.AXES.index(self.axis)
        rate = self.max_rate_deg_s
        acc = self.accel_deg_s2 or float(self.controller.settings.get(120 + k, 10.0))
        return rate, acc

    # ------------------------------------------------------------------ helpers
    def _check_angle(self, angle_deg) -> float:
        if isinstance(angle_deg, bool) or not isinstance(angle_deg, numbers.Real):
            raise InputError(f"{self.name}: angle {angle_deg!r} is not a number of degrees")
        a = float(angle_deg)
        if not math.isfinite(a):
            raise InputError(f"{self.name}: angle {angle_deg!r} is not a finite number of degrees")
        if abs(a) > gp.MAX_ABS_COORD:
            raise InputError(f"{self.name}: angle {a:g} deg is beyond +-{gp.MAX_ABS_COORD:g} deg")
        if not self.continuous:
            self._check_limits(a, requested=a)
        return a

    def _check_limits(self, target: float, *, requested: float) -> None:
        if self.soft_limits_deg is not None:
            lo, hi = self.soft_limits_deg
            if not lo - 1e-9 <= target <= hi + 1e-9:
                raise InputError(
                    f"{self.name}: angle {requested:g} deg is outside soft_limits_deg "
                    f"[{lo:g}, {hi:g}] (controller target {target:g} deg)"
                )

    def _pos(self, st: gp.Status) -> float:
        try:
            return st.position(self.controller._wco)[self.axis]
        except KeyError:
            raise ProtocolError(
                f"{self.controller.name}: status {st.raw!r} has no position for axis {self.axis} "
                "— is that axis enabled in the firmware?"
            ) from None

    def _at(self, pos: float, target: float) -> bool:
        return abs(pos - target) <= self.tolerance_deg

    def _check_interrupts(self, st: gp.Status | None, mark: tuple[int, int], doing: str) -> None:
        c = self.controller
        if c.alarm_seq > mark[0]:
            raise c._alarm_error(c.last_alarm, doing=doing, axis=self.axis)
        if c.resets_seen > mark[1]:
            raise GrblInterrupted(
                f"{self.name}: the controller reset while {doing} — the move was discarded and "
                "the position may be lost; home or check the angle",
                state="reset",
            )
        if st is None:
            return
        if st.state == "Alarm":
            raise c._alarm_error(c.last_alarm, doing=doing, axis=self.axis)
        if st.state in ("Hold", "Door", "Sleep", "Check"):
            what = {
                "Hold": "a feed hold (stop() or the hold button) — resume() continues, reset() cancels",
                "Door": "the safety door is open — close it and resume()",
                "Sleep": "the controller is asleep ($SLP) — reset() it",
                "Check": "the controller is in check mode ($C): nothing moves — send $C again",
            }[st.state]
            raise GrblInterrupted(
                f"{self.name}: {doing} interrupted by {what} (state {st.state}"
                f"{'' if st.substate is None else ':' + str(st.substate)}, "
                f"at {self._pos(st):.3f} deg)",
                state=st.state,
            )

    # ------------------------------------------------------------------ RotaryAxis
    def move_to(self, angle_deg: float, *, timeout_s: float | None = None) -> float:
        """Absolute move; blocks until idle at the target; returns the reached angle
        (within ``tolerance_deg`` of the request, expressed near the request on a continuous
        axis).

        Raises
        ------
        InputError : non-finite angle or outside the soft limits (nothing sent).
        GrblAlarm, GrblInterrupted, GrblCommandError, DeviceTimeout, DeviceGone, ProtocolError
        """
        a = self._check_angle(angle_deg)
        c = self.controller
        with c.lock:
            c._require_open()
            self._ensure_configured()
            doing = f"moving {self.name} to {a:g} deg"
            st = c.status()
            self._check_interrupts(st, (c.alarm_seq, c.resets_seen), doing)
            if st.state in ("Run", "Jog", "Home"):
                st = self._wait_idle(
                    self._pos(st),
                    time.monotonic() + max(c.timeout_s * 5, 30.0),
                    (c.alarm_seq, c.resets_seen),
                    doing,
                    settle_only=True,
                )
            cur = self._pos(st)
            # nearest angle congruent to a (mod 360): a itself when no turn is involved, exactly
            target = a - 360.0 * math.floor((a - cur) / 360.0 + 0.5) if self.continuous else a
            self._check_limits(target, requested=a)
            legs = [target]
            b = self.backlash_deg
            if b > 0 and not self._at(cur, target) and (target < cur or (target - cur < b and self._last_dir != 1)):
                pre = target - b
                if self.soft_limits_deg is not None:
                    pre = max(pre, self.soft_limits_deg[0])
                legs = [pre, target]
            reached = cur
            start = time.monotonic()
            for leg in legs:
                budget = None if timeout_s is None else max(0.0, timeout_s - (time.monotonic() - start))
                before = reached
                reached = self._move_leg(leg, before, budget, doing)
                if not self._at(before, leg):
                    self._last_dir = 1 if leg > before else -1
            return a + (reached - target)

    def _move_leg(self, target: float, start: float, timeout_s: float | None, doing: str) -> float:
        c = self.controller
        line = gp.move_abs({self.axis: target})
        mark = (c.alarm_seq, c.resets_seen)
        rate, acc = self._rate_accel()
        t_move = move_duration_s(target - start, rate, acc)
        budget = timeout_s if timeout_s is not None else 1.5 * t_move + c.timeout_s + 1.0
        deadline = time.monotonic() + budget
        if self._at(start, target):
            return start
        attempts = 0
        while True:
            attempts += 1
            self.moves += 1
            try:
                c.send_line(line)
            except (DeviceTimeout, ProtocolError) as e:
                # Did the line arrive? Ask where the axis is before anything is re-sent.
                log.info("%s: %s: no valid reply to %r (%s); asking the position", self.name, doing, line, e)
                st = c.status()
                self._check_interrupts(st, mark, doing)
                pos = self._pos(st)
                if st.state == "Idle":
                    if self._at(pos, target):
                        return pos
                    if attempts > self.retries:
                        raise DeviceTimeout(
                            f"{self.name}: {doing}: {e} — the controller is idle at {pos:.3f} deg, "
                            f"so the line never arrived ({attempts} attempts)"
                        ) from None
                    continue  # it never arrived: the absolute move is safe to send again
                # Run/Jog: the line got through and is executing; wait for it below
            st = self._wait_idle(target, deadline, mark, doing)
            pos = self._pos(st)
            if self._at(pos, target):
                return pos
            raise DeviceError(
                f"{self.name}: {doing}: the controller stopped at {pos:.3f} deg instead of "
                f"{target:.3f} deg without an alarm — was the motion cancelled (jog cancel, reset)?"
            )

    def _wait_idle(self, target: float, deadline: float, mark, doing: str, *, settle_only: bool = False):
        c = self.controller
        failures = 0
        idle_since = None
        while True:
            try:
                st = c.status()
                failures = 0
            except GrblAlarm:
                self._check_interrupts(None, mark, doing)
                raise
            except (DeviceTimeout, ProtocolError):
                self._check_interrupts(None, mark, doing)
                failures += 1
                if failures > 2 or time.monotonic() > deadline:
                    raise
                continue
            self._check_interrupts(st, mark, doing)
            if st.state == "Idle":
                if settle_only or self._at(self._pos(st), target):
                    return st
                # GRBL can report Idle for a moment between 'ok' and the start of the cycle
                idle_since = idle_since or time.monotonic()
                if time.monotonic() - idle_since > max(0.25, 5 * c.poll_s):
                    return st
            else:
                idle_since = None
            if time.monotonic() > deadline:
                raise DeviceTimeout(
                    f"{self.name}: {doing}: not finished by the deadline (state {st.state}, at "
                    f"{self._pos(st):.3f} deg, target {target:.3f} deg) on {c.url} — is the axis stalled, or "
                    f"slower than max_rate_deg_s = {self.max_rate_deg_s:g}?"
                )
            time.sleep(c.poll_s)

    def position_deg(self) -> float:
        """Current angle from a fresh status report (wrapped to [0, 360) on a continuous axis)."""
        c = self.controller
        with c.lock:
            c._require_open()
            pos = self._pos(c.status())
        if self.continuous:
            pos = pos % 360.0
            if pos >= 360.0 - 1e-9:
                pos = 0.0
        return pos

    def home(self) -> None:
        """``$H<axis>`` (single-axis homing builds) or ``$H`` (homes every axis of the
        board); angle 0 afterwards."""
        c = self.controller
        with c.lock:
            c._require_open()
            self._ensure_configured()
            c.home(self.axis if c.single_axis_homing else "", timeout_s=self.homing_timeout_s)

    def stop(self) -> None:
        """Feed hold now; never raises (safe on a dead port, from any thread)."""
        self.controller.stop()

    def check(self) -> DeviceInfo:
        """Identity, state and angle; never raises."""
        c = self.controller
        try:
            c._require_open()
            st = c.status()
            pos = self._pos(st) % 360.0 if self.continuous else self._pos(st)
            ok = st.state in ("Idle", "Run", "Jog")
            alarm = ""
            if st.state == "Alarm":
                a = c.last_alarm
                alarm = f" ALARM:{a.code} ({a.meaning}) — {a.hint}" if a else " — home() or unlock"
            return DeviceInfo(
                self.name,
                ok,
                f"{st.state}{alarm}; axis {self.axis} at {pos:.3f} deg on {c.url}",
                identity=f"Grbl {c.version or '?'} ({c.build or 'build ?'}) axis {self.axis}",
                state={
                    "state": st.state,
                    "substate": st.substate,
                    "position_deg": pos,
                    "axis": self.axis,
                    "url": c.url,
                    "alarm": c.last_alarm.code if c.last_alarm and st.state == "Alarm" else None,
                },
            )
        except DeviceError as e:
            return DeviceInfo(self.name, False, str(e), state={"axis": self.axis, "url": c.url})
