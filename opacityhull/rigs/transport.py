"""Byte transport for every serial device: pyserial ``serial_for_url`` with timeouts.

A URL is a device path (``/dev/ttyUSB0``, a pty slave such as ``/dev/pts/5``),
``socket://host:port`` or ``loop://``. No I/O happens in ``__init__``; :meth:`open`
opens the port (exclusively where the platform supports it). Every read and write has
a timeout, and every failure becomes a :class:`~opacityhull.errors.DeviceError`
subclass whose message names the device and the URL and says what to check.

pyserial facts this module is built around (PITFALLS.md): a read that times out
returns ``b''`` or a partial line and never raises; ``readline`` splits on ``\\n``
only; late replies stay in the input buffer (so :meth:`query` flushes first); when the
other end of a pty goes away, reads raise ``OSError(EIO)``.
"""

from __future__ import annotations

import time
from typing import Callable

from ..errors import DeviceError

try:  # termios.error is not an OSError; a hung-up pty raises it from tcdrain()
    import termios

    _PORT_ERRORS: tuple = (OSError, termios.error)
except ImportError:  # pragma: no cover - Windows
    _PORT_ERRORS = (OSError,)

__all__ = [
    "DeviceTimeout",
    "DeviceGone",
    "ProtocolError",
    "SerialTransport",
    "URL_SCHEMES",
    "check_url",
]

URL_SCHEMES = ("socket://", "loop://", "rfc2217://", "/dev/", "COM")


class DeviceTimeout(DeviceError):
    """The device did not answer (completely) within the timeout."""


class DeviceGone(DeviceError):
    """The port vanished (unplugged, emulator killed, pty hung up)."""


class ProtocolError(DeviceError):
    """The device answered something that is not valid in its protocol."""


def check_url(url: str, *, where: str = "url") -> str:
    """Validate a transport URL; raise :class:`~opacityhull.errors.ConfigError` naming ``where``."""
    from ..errors import ConfigError

    if not isinstance(url, str) or not url:
        raise ConfigError(f"{where}: expected a serial URL string, got {url!r}")
    if url.startswith(URL_SCHEMES) or url.startswith("emulator:"):
        return url
    scheme = url.split("://")[0] + "://" if "://" in url else url
    raise ConfigError(
        f"{where}: unknown URL scheme in {url!r} (expected a device path like /dev/ttyUSB0, "
        "socket://HOST:PORT, loop://, or emulator:KIND)"
    )


class SerialTransport:
    """A serial port with timeouts on every operation.

    Parameters
    ----------
    url : str
        Device path, ``socket://host:port`` or ``loop://``.
    name : str
        Device name used in error messages (``turntable``).
    baudrate : int
    timeout_s : float
        Default read timeout for :meth:`read_until` / :meth:`read_exact`.
    write_timeout_s : float
    exclusive : bool
        Request exclusive access (POSIX ports only; ignored for sockets).
    """

    def __init__(self, url: str, *, name: str = "device", baudrate: int = 115200, timeout_s: float = 2.0,
                 write_timeout_s: float = 2.0, exclusive: bool = True):
        self.url = url
        self.name = name
        self.baudrate = baudrate
        self.timeout_s = float(timeout_s)
        self.write_timeout_s = float(write_timeout_s)
        self.exclusive = exclusive
        self._port = None
        self._rxbuf = bytearray()

    # ---- lifecycle
    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> "SerialTransport":
        import serial

        if self.is_open:
            return self
        kw = dict(baudrate=self.baudrate, timeout=0.05, write_timeout=self.write_timeout_s)
        if self.exclusive and self.url.startswith("/dev/"):
            kw["exclusive"] = True
        try:
            self._port = serial.serial_for_url(self.url, **kw)
        except (serial.SerialException, OSError, ValueError) as e:
            raise DeviceGone(
                f"{self.name}: cannot open {self.url} ({e}) — is it plugged in, powered, and not in use by "
                "another program?"
            ) from None
        self._rxbuf.clear()
        return self

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # closing a dead port must never mask the real error
                pass

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()
        return False

    def _require_open(self):
        if not self.is_open:
            raise DeviceGone(f"{self.name}: port {self.url} is not open")
        return self._port

    def _gone(self, e: Exception) -> DeviceGone:
        self.close()
        return DeviceGone(f"{self.name}: lost the connection on {self.url} ({e}) — was it unplugged or powered off?")

    # ---- writing
    def write(self, data: bytes) -> None:
        import serial

        port = self._require_open()
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
            raise DeviceTimeout(f"{self.name}: wrote {n} of {len(data)} bytes to {self.url}")

    # ---- reading
    def _fill(self, deadline: float) -> bool:
        """Read whatever is available (waiting at most until ``deadline``); True if bytes came."""
        import serial

        port = self._require_open()
        try:
            waiting = port.in_waiting
            chunk = port.read(max(1, waiting))
        except (serial.SerialException, *_PORT_ERRORS) as e:
            raise self._gone(e) from None
        if chunk:
            self._rxbuf += chunk
            return True
        return False

    def read_until(self, terminator: bytes = b"\n", *, timeout_s: float | None = None, what: str = "reply") -> bytes:
        """Bytes up to and including ``terminator``; raises :class:`DeviceTimeout` (with the
        partial data in the message) when it does not arrive in time."""
        t = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + t
        while True:
            i = self._rxbuf.find(terminator)
            if i >= 0:
                out = bytes(self._rxbuf[: i + len(terminator)])
                del self._rxbuf[: i + len(terminator)]
                return out
            if time.monotonic() >= deadline:
                partial = bytes(self._rxbuf)
                raise DeviceTimeout(
                    f"{self.name}: no {what} within {t:.1f} s on {self.url}"
                    + (f" (partial: {partial[:40]!r})" if partial else "")
                    + " — is it powered and connected?"
                )
            self._fill(deadline)

    def read_exact(self, n: int, *, timeout_s: float | None = None, what: str = "reply") -> bytes:
        t = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + t
        while len(self._rxbuf) < n:
            if time.monotonic() >= deadline:
                raise DeviceTimeout(
                    f"{self.name}: {what}: got {len(self._rxbuf)} of {n} bytes within {t:.1f} s on {self.url}"
                    " — is it powered and connected?"
                )
            self._fill(deadline)
        out = bytes(self._rxbuf[:n])
        del self._rxbuf[:n]
        return out

    def read_available(self) -> bytes:
        """Everything already received (no waiting)."""
        import serial

        port = self._require_open()
        try:
            while port.in_waiting:
                self._rxbuf += port.read(port.in_waiting)
        except (serial.SerialException, *_PORT_ERRORS) as e:
            raise self._gone(e) from None
        out = bytes(self._rxbuf)
        self._rxbuf.clear()
        return out

    def flush_input(self) -> bytes:
        """Discard (and return) late replies waiting in the input buffer."""
        return self.read_available()

    def query(self, data: bytes, *, terminator: bytes = b"\n", timeout_s: float | None = None,
              what: str = "reply", accept: Callable[[bytes], bool] | None = None) -> bytes:
        """Flush input, send ``data``, return the first line ``accept`` takes (default: any)."""
        self.flush_input()
        self.write(data)
        t = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + t
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            line = self.read_until(terminator, timeout_s=remaining, what=what)
            if accept is None or accept(line):
                return line
