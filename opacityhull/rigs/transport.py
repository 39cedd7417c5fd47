"""Byte transport for every serial device: :class:`Transport` (buffering, deadlines,
DEBUG logging of every byte) and :class:`SerialTransport` (pyserial ``serial_for_url``).

Drivers take a :class:`Transport` in their constructor (``from_url`` builds a
:class:`SerialTransport`), so a test can hand them the in-memory transport of
:mod:`opacityhull.rigs.testing` and check every byte they exchange.

A URL is a device path (``/dev/ttyUSB0``, a pty slave such as ``/dev/pts/5``),
``socket://host:port`` or ``loop://``. No I/O happens in ``__init__``; :meth:`open`
opens the port (exclusively where the platform supports it). Every read and write has
a timeout, and every failure becomes a :class:`~opacityhull.errors.DeviceError`
subclass whose message names the device and the URL and says what to check.

pyserial facts this module is built around (docs/pitfalls.md, "pyserial"): a read that times out
returns ``b''`` or a partial line and never raises; ``readline`` splits on ``\\n``
only; late replies stay in the input buffer (so :meth:`query` flushes first); when the
other end of a pty goes away, reads raise ``OSError(EIO)``; a TCP peer that closed
shows up as a readable socket whose ``recv`` returns ``b''`` (pyserial raises
``SerialException('socket disconnected')``).

The port is opened non-blocking (``timeout=0``) and waits happen in ``select`` on its
file descriptor, so one read call drains everything available (pyserial's socket
handler otherwise reads a TCP stream one byte per system call).
"""

from __future__ import annotations

import logging
import math
import select
import socket
import time
from contextlib import suppress
from dataclasses import dataclass
from typing import Any, Self, TypeVar
from collections.abc import Callable

from ..errors import ConfigError, DeviceError

try:  # termios.error is not an OSError; a hung-up pty raises it from tcdrain()
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)
except ImportError:  # pragma: no cover - Windows
    _PORT_ERRORS = (OSError,)

log = logging.getLogger(__name__)

__all__ = [
    "Transport",
    "DeviceTimeout",
    "DeviceGone",
    "ProtocolError",
    "SerialTransport",
    "SerialSettings",
    "URL_SCHEMES",
    "check_url",
    "reopen",
]

URL_SCHEMES = ("socket://", "loop://", "rfc2217://", "/dev/", "COM")

#: Longest single wait inside a read loop; bounds how late a deadline is noticed.
_POLL_S = 0.05

#: Most bytes kept unread in the receive buffer. A babbling port (wrong baud rate)
#: would otherwise grow it without bound, and every terminator search with it.
_MAX_RXBUF = 1 << 16


class DeviceTimeout(DeviceError):
    """The device did not answer (completely) within the timeout."""


class DeviceGone(DeviceError):
    """The port vanished (unplugged, emulator killed, pty hung up)."""


class ProtocolError(DeviceError):
    """The device answered something that is not valid in its protocol."""


T = TypeVar("T")


def _count(v: object, lo: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _seconds(v: object, *, positive: bool) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return False
    return v > 0 if positive else v >= 0


@dataclass(frozen=True, kw_only=True)
class SerialSettings:
    """How a driver talks over its serial link: line speed, reply and write timeout, and
    how hard it tries again. Every field is required: start from the driver's defaults
    (``replace(GRBL_SERIAL, timeout_s=0.5)``; ``GRBL_SERIAL`` in
    :mod:`~opacityhull.rigs.motion`, ``DMX_SERIAL`` in :mod:`~opacityhull.rigs.lights`,
    ``DISPLAY_SERIAL`` in :mod:`~opacityhull.rigs.backdrops`), which differ.

    Attributes
    ----------
    baudrate : int
        Line speed, bit/s (8N1); also named in the "garbled" diagnosis. The Enttec
        widget's virtual COM port ignores it.
    timeout_s : float
        Seconds allowed for each reply and for each write (> 0).
    retries : int
        Resends of one command whose reply did not come or came garbled (>= 0): a
        display command; a GRBL move line that provably never arrived (the default of
        the controller's axes). DMX is never acknowledged: the Enttec driver has
        nothing to resend.
    reconnect_attempts : int
        Re-opens of a vanished port before the error names the device (>= 0). The
        Enttec widget is re-opened by the rig (:class:`~opacityhull.rigs.rig.HardwareRig`).
    reconnect_delay_s : float
        Seconds between two re-opens (>= 0): a re-plugged USB adapter needs time to
        enumerate.

    Raises
    ------
    ConfigError
        A field of the wrong type or out of range (it names the field, the value and
        what was expected).
    """

    baudrate: int
    timeout_s: float
    retries: int
    reconnect_attempts: int
    reconnect_delay_s: float

    def __post_init__(self) -> None:
        checks = {
            "baudrate": (_count(self.baudrate, 1), "an integer > 0 (bit/s)"),
            "timeout_s": (_seconds(self.timeout_s, positive=True), "a number of seconds > 0"),
            "retries": (_count(self.retries, 0), "an integer >= 0"),
            "reconnect_attempts": (_count(self.reconnect_attempts, 0), "an integer >= 0"),
            "reconnect_delay_s": (_seconds(self.reconnect_delay_s, positive=False), "a number of seconds >= 0"),
        }
        for key, (ok, expected) in checks.items():
            if not ok:
                raise ConfigError(f"SerialSettings: {key} = {getattr(self, key)!r}, expected {expected}")


def reopen(
    open_once: Callable[[int], T],
    *,
    attempts: int,
    delay_s: float,
    catch: type[BaseException] | tuple[type[BaseException], ...] = DeviceGone,
    gave_up: Callable[[int, BaseException | None], DeviceError],
) -> T:
    """``open_once(attempt)`` (``attempt`` = 1, 2, ...) until it returns, at most
    ``max(1, attempts)`` times, ``delay_s`` seconds apart (a re-plugged USB adapter needs
    time to enumerate); only ``catch`` failures are retried. Then raises
    ``gave_up(tries, last_error)``: the one loop behind every driver's and the rig's
    reconnect."""
    tries = max(1, attempts)
    last: BaseException | None = None
    for i in range(tries):
        if i:
            time.sleep(delay_s)
        try:
            return open_once(i + 1)
        except catch as e:
            last = e
    raise gave_up(tries, last) from None


def check_url(url: str, *, where: str = "url") -> str:
    """Validate a transport URL; raise :class:`~opacityhull.errors.ConfigError` naming ``where``."""
    if not isinstance(url, str) or not url:
        raise ConfigError(f"{where}: expected a serial URL string, got {url!r}")
    if url.startswith(URL_SCHEMES) or url.startswith("emulator:"):
        return url
    raise ConfigError(
        f"{where}: unknown URL scheme in {url!r} (expected a device path like /dev/ttyUSB0, "
        "socket://HOST:PORT, loop://, or emulator:KIND)"
    )


def driver_name(transport: Any, name: str | None, *, driver: str, fallback: str) -> str:
    """The device name a driver over ``transport`` goes by: ``name``, else the transport's.

    Raises :class:`~opacityhull.errors.ConfigError` (naming ``driver``'s ``from_url``) when
    ``transport`` is not a :class:`Transport`, e.g. a URL string passed by mistake.
    """
    if not isinstance(transport, Transport):
        raise ConfigError(
            f"{name or fallback}: expected a Transport, got {type(transport).__name__} "
            f"(use {driver}.from_url({transport!r}, ...) for a serial URL)"
        )
    return transport.name if name is None else name


class OpenClose:
    """``with device:`` opens it and closes it on the way out, whatever happened inside."""

    def open(self) -> Self:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> bool:
        self.close()
        return False


class OverTransport(OpenClose):
    """A driver talking over ``self.transport``: its URL and open state are the transport's."""

    transport: Transport

    @property
    def url(self) -> str:
        return self.transport.url

    @property
    def is_open(self) -> bool:
        return self.transport.is_open


class Transport(OpenClose):
    """Bytes to and from one device, with a timeout on every operation.

    The base class holds everything a driver relies on — the receive buffer, the
    overall deadline of an exchange (:meth:`exchange`), terminator and length reads,
    the garbled/silent diagnosis (:meth:`heard_since`), DEBUG logging of every byte —
    over five primitives a subclass provides: :meth:`_open_raw`, :meth:`_close_raw`,
    :meth:`_write_raw`, :meth:`_read_raw` (non-blocking) and :meth:`_wait_raw`.
    :class:`SerialTransport` implements them over pyserial; the in-memory transport
    of :mod:`opacityhull.rigs.testing` implements them over a script of expected bytes.

    Parameters
    ----------
    url : str
        Where the device is (named in every message).
    name : str
        Device name used in messages and logs (``turntable``).
    baudrate : int
        Named in the "garbled" diagnosis.
    timeout_s : float
        Default read timeout for :meth:`read_until` / :meth:`read_exact`, seconds.
    write_timeout_s : float
        Seconds a write may take to leave.

    Notes
    -----
    Not thread-safe for concurrent reads; device drivers serialise transactions with
    their own lock. A single-byte :meth:`write` from another thread (a GRBL feed hold)
    is safe: it is one ``write(2)`` call.
    """

    def __init__(
        self,
        url: str,
        *,
        name: str = "device",
        baudrate: int = 115200,
        timeout_s: float = 2.0,
        write_timeout_s: float = 2.0,
    ):
        self.url = url
        self.name = name
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.write_timeout_s = float(write_timeout_s)
        self._rxbuf = bytearray()
        self.bytes_written = 0
        self.bytes_read = 0
        self._deadline: float | None = None  # of the current exchange (see exchange())
        self._deadline_what = ""
        self._deadline_mark: tuple[int, float] = (0, 0.0)

    # ---- primitives (subclasses)
    @property
    def is_open(self) -> bool:
        raise NotImplementedError

    def _open_raw(self) -> None:
        """Open the device; :class:`DeviceGone` naming it when it is not there."""
        raise NotImplementedError

    def _close_raw(self) -> None:
        """Close the device; never raises."""
        raise NotImplementedError

    def _write_raw(self, data: bytes) -> None:
        """Write all of ``data``; :class:`DeviceTimeout` / :class:`DeviceGone`."""
        raise NotImplementedError

    def _read_raw(self) -> bytes:
        """Everything available now, without waiting (``b''`` if nothing); :class:`DeviceGone`."""
        raise NotImplementedError

    def _wait_raw(self, wait_s: float) -> None:
        """Wait at most ``wait_s`` seconds for bytes to become readable."""
        raise NotImplementedError

    # ---- lifecycle
    def open(self) -> Transport:
        if self.is_open:
            return self
        self._open_raw()
        self._rxbuf.clear()
        log.debug("%s: opened %s", self.name, self.url)
        return self

    def close(self) -> None:
        self._close_raw()

    def _gone(self, e: BaseException) -> DeviceGone:
        self.close()
        log.debug("%s: lost %s (%s)", self.name, self.url, e)
        return DeviceGone(f"{self.name}: lost the connection on {self.url} ({e}) — was it unplugged or powered off?")

    def _not_open(self) -> DeviceGone:
        return DeviceGone(f"{self.name}: port {self.url} is not open — call open() first (or reconnect)")

    # ---- writing
    def write(self, data: bytes) -> None:
        """Write all of ``data``; :class:`DeviceTimeout` if it does not leave within the write timeout,
        :class:`DeviceGone` if the port is dead."""
        if not self.is_open:
            raise self._not_open()
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s > %r", self.name, bytes(data))
        self._write_raw(data)
        self.bytes_written += len(data)

    # ---- exchanges: one overall deadline
    def exchange(self, timeout_s: float, what: str = "exchange") -> _Exchange:
        """``with transport.exchange(T, "reply to $I"):`` — every read inside ends by
        ``T`` seconds from now, whatever its own timeout and however many lines arrive,
        so no stream of bytes (a babbling device, a wrong baud rate) can hold a command
        past it. Nested exchanges keep the earliest deadline."""
        return _Exchange(self, float(timeout_s), what)

    def _clamp(self, deadline: float) -> float:
        d = self._deadline
        return deadline if d is None else min(deadline, d)

    def mark(self) -> tuple[int, float]:
        """A point to measure :meth:`heard_since` from."""
        return (self.bytes_read, time.monotonic())

    def heard_since(self, mark: tuple[int, float]) -> str:
        """How to read a failed exchange: bytes came that never parsed (a wrong baud
        rate, a babbling device, noise on the line) — or not a single byte (silent:
        power, cable, wrong port)."""
        n = self.bytes_read - mark[0]
        dt = time.monotonic() - mark[1]
        if n > 0:
            return (
                f"{n} byte(s) arrived in {dt:.2f} s but none formed a valid reply: garbled — check the baud "
                f"rate ({self.baudrate}), the cable and for electrical noise"
            )
        return f"not a single byte arrived in {dt:.2f} s: silent — is it powered, connected and on this port?"

    # ---- reading
    def _read_now(self) -> bytes:
        """Everything the OS has for us right now (non-blocking)."""
        if not self.is_open:
            raise self._not_open()
        chunk = self._read_raw()
        if chunk:
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s < %r", self.name, chunk)
            self._rxbuf += chunk
            self.bytes_read += len(chunk)
            if len(self._rxbuf) > _MAX_RXBUF:  # keep the newest: a reply ends the buffer
                del self._rxbuf[: len(self._rxbuf) - _MAX_RXBUF]
        return chunk

    def _fill(self, deadline: float) -> bool:
        """Wait (at most until ``deadline``, in slices of ``_POLL_S``) for bytes; True if some came."""
        if self._read_now():
            return True
        self._wait_raw(min(_POLL_S, max(0.0, deadline - time.monotonic())))
        return bool(self._read_now())

    def _drain(self) -> None:
        """Take in what is waiting — but not for ever: a device that sends as fast as we
        read (a babbling port) would otherwise hold this loop as long as it babbles."""
        end = self._clamp(time.monotonic() + _POLL_S)
        got = 0
        while True:
            chunk = self._read_now()
            got += len(chunk)
            if not chunk or got >= _MAX_RXBUF or time.monotonic() >= end:
                return

    def read_some(self, *, timeout_s: float | None = None) -> bytes:
        """Whatever arrives first (at least one byte), or ``b''`` when nothing came within the timeout."""
        t = self.timeout_s if timeout_s is None else timeout_s
        deadline = self._clamp(time.monotonic() + t)
        while not self._rxbuf:
            self._fill(deadline)
            if self._rxbuf or time.monotonic() >= deadline:
                break
        out = bytes(self._rxbuf)
        self._rxbuf.clear()
        return out

    def read_until(self, terminator: bytes = b"\n", *, timeout_s: float | None = None, what: str = "reply") -> bytes:
        """Bytes up to and including ``terminator``; raises :class:`DeviceTimeout` (with the
        partial data in the message) when it does not arrive in time."""
        t = self.timeout_s if timeout_s is None else timeout_s
        start = time.monotonic()
        deadline = self._clamp(start + t)
        mark = self.mark()
        last_look = False
        while True:
            i = self._rxbuf.find(terminator)
            if i >= 0:
                out = bytes(self._rxbuf[: i + len(terminator)])
                del self._rxbuf[: i + len(terminator)]
                return out
            if last_look:
                partial = bytes(self._rxbuf)
                clamped = deadline < start + t
                raise DeviceTimeout(
                    f"{self.name}: no {what} within {deadline - start:.2f} s on {self.url}"
                    + (f" (the overall deadline of {self._deadline_what})" if clamped else "")
                    + (f" (partial: {partial[-40:]!r})" if partial else "")
                    # over a whole exchange, every line that came and was refused counts
                    + f" — {self.heard_since(self._deadline_mark if clamped else mark)}"
                )
            if time.monotonic() >= deadline:
                self._read_now()  # what arrived while we were busy still counts
                last_look = True
                continue
            self._fill(deadline)

    def read_exact(self, n: int, *, timeout_s: float | None = None, what: str = "reply") -> bytes:
        t = self.timeout_s if timeout_s is None else timeout_s
        deadline = self._clamp(time.monotonic() + t)
        while len(self._rxbuf) < n:
            if time.monotonic() >= deadline:
                self._read_now()
                if len(self._rxbuf) >= n:
                    break
                raise DeviceTimeout(
                    f"{self.name}: {what}: got {len(self._rxbuf)} of {n} bytes within {t:.2f} s on {self.url}"
                    " — is it powered and connected?"
                )
            self._fill(deadline)
        out = bytes(self._rxbuf[:n])
        del self._rxbuf[:n]
        return out

    def read_available(self) -> bytes:
        """Everything already received, partial lines included (no waiting).

        Also how a vanished port is noticed without writing: a closed TCP peer or a
        hung-up pty raises :class:`DeviceGone` here.
        """
        self._drain()
        out = bytes(self._rxbuf)
        self._rxbuf.clear()
        return out

    def pending_lines(self, terminator: bytes = b"\n") -> list[bytes]:
        """Complete lines already received (no waiting); a partial line stays buffered."""
        self._drain()
        lines = []
        while True:
            i = self._rxbuf.find(terminator)
            if i < 0:
                return lines
            lines.append(bytes(self._rxbuf[: i + len(terminator)]))
            del self._rxbuf[: i + len(terminator)]

    def flush_input(self) -> bytes:
        """Discard (and return) late replies waiting in the input buffer."""
        out = self.read_available()
        if out:
            log.debug("%s: discarded %d late byte(s)", self.name, len(out))
        return out

    def query(
        self,
        data: bytes,
        *,
        terminator: bytes = b"\n",
        timeout_s: float | None = None,
        what: str = "reply",
        accept: Callable[[bytes], bool] | None = None,
    ) -> bytes:
        """Flush input, send ``data``, return the first line ``accept`` takes (default: any)."""
        self.flush_input()
        self.write(data)
        t = self.timeout_s if timeout_s is None else timeout_s
        with self.exchange(t, what):  # lines that accept() refuses cannot extend it
            while True:
                line = self.read_until(terminator, timeout_s=t, what=what)
                if accept is None or accept(line):
                    return line


class SerialTransport(Transport):
    """A serial port (pyserial ``serial_for_url``) with timeouts on every operation.

    Takes the parameters of :class:`Transport` (``url``: a device path,
    ``socket://host:port`` or ``loop://``); :meth:`from_settings` builds one from a
    driver's :class:`SerialSettings`.

    Attributes
    ----------
    exclusive : bool
        Request exclusive access when opening (POSIX device paths only; sockets ignore
        it). Set it before :meth:`open`.
    """

    exclusive = True
    _port: Any = None
    _fd: int | None = None

    @classmethod
    def from_settings(cls, url: str, serial: SerialSettings, *, name: str) -> SerialTransport:
        """The port at ``url`` at ``serial.baudrate``, with ``serial.timeout_s`` for every read and write."""
        return cls(
            url, name=name, baudrate=serial.baudrate, timeout_s=serial.timeout_s, write_timeout_s=serial.timeout_s
        )

    @property
    def is_open(self) -> bool:
        port = self._port
        return port is not None and port.is_open

    def _open_raw(self) -> None:
        import serial

        kw: dict[str, Any] = dict(baudrate=self.baudrate, timeout=0, write_timeout=self.write_timeout_s)
        if self.exclusive and self.url.startswith("/dev/"):
            kw["exclusive"] = True
        try:
            port = serial.serial_for_url(self.url, **kw)
        except (serial.SerialException, OSError, ValueError) as e:
            raise DeviceGone(
                f"{self.name}: cannot open {self.url} ({e}) — is it plugged in, powered, and not in use by "
                "another program?"
            ) from None
        try:
            self._fd = port.fileno()
        except (
            AttributeError,
            OSError,
        ):  # loop:// and rfc2217:// have no descriptor (io.UnsupportedOperation): poll instead
            self._fd = None
        self._port = port

    def _close_raw(self) -> None:
        port, self._port = self._port, None
        self._fd = None
        if port is None:
            return
        try:
            sock = getattr(port, "_socket", None) if self.url.startswith("socket://") else None
            if sock is not None:
                # pyserial's socket close() sleeps 0.3 s "for quick reconnects"; a rig with
                # three TCP devices would pay it on every close and reconnect attempt.
                with suppress(OSError):  # the peer may already be gone; close() below still frees the socket
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
                port._socket = None
                port.is_open = False
            else:
                port.close()
        except Exception as e:  # noqa: BLE001  closing a dead port must never mask the real error
            log.debug("%s: error while closing %s: %s", self.name, self.url, e)

    def _write_raw(self, data: bytes) -> None:
        import serial

        port = self._port
        try:
            n = port.write(data)
            port.flush()
        except serial.SerialTimeoutException:
            raise DeviceTimeout(
                f"{self.name}: write of {len(data)} bytes to {self.url} did not finish within "
                f"{self.write_timeout_s} s — is flow control stuck or the device hung?"
            ) from None
        except (serial.SerialException, *_PORT_ERRORS) as e:
            raise self._gone(e) from None
        if n is not None and n != len(data):
            raise DeviceTimeout(f"{self.name}: wrote {n} of {len(data)} bytes to {self.url} — is the device hung?")

    def _read_raw(self) -> bytes:
        import serial

        try:
            return self._port.read(65536)
        except (serial.SerialException, *_PORT_ERRORS) as e:
            raise self._gone(e) from None

    def _wait_raw(self, wait_s: float) -> None:
        if self._fd is not None:
            try:
                select.select([self._fd], [], [], wait_s)
            except (OSError, ValueError) as e:
                raise self._gone(e) from None
        else:
            time.sleep(min(wait_s, 0.002))


class _Exchange:
    """Context manager of :meth:`Transport.exchange`."""

    def __init__(self, transport: Transport, timeout_s: float, what: str):
        self.t = transport
        self.timeout_s = timeout_s
        self.what = what
        self._saved: tuple[float | None, str, tuple[int, float]] = (None, "", (0, 0.0))

    def __enter__(self) -> _Exchange:
        t = self.t
        self._saved = (t._deadline, t._deadline_what, t._deadline_mark)
        d = time.monotonic() + self.timeout_s
        if t._deadline is None or d < t._deadline:
            t._deadline, t._deadline_what = d, f"{self.what} ({self.timeout_s:g} s)"
            t._deadline_mark = t.mark()
        return self

    def __exit__(self, *exc):
        self.t._deadline, self.t._deadline_what, self.t._deadline_mark = self._saved
        return False
