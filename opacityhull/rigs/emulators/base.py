"""Serve a device emulator over a pty pair or a TCP socket, with fault injection.

An :class:`EmulatedDevice` is a pure state machine: :meth:`~EmulatedDevice.receive`
takes bytes from the host and returns the replies (with optional delays). An
:class:`EmulatorServer` runs it in a background thread behind a real pty
(``os.openpty``; the driver opens the slave path like any serial port) or a TCP socket
on 127.0.0.1 (the driver uses ``socket://127.0.0.1:PORT``). Replies pass through a
:class:`Faults` object first, so tests can drop, garble, delay, silence or cut the
line, or make the device vanish (the pty master closes: the driver sees EIO).
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Iterable

__all__ = ["Reply", "Faults", "EmulatedDevice", "EmulatorServer"]


@dataclass
class Reply:
    """Bytes to send back, after ``delay_s`` seconds of emulator time."""

    data: bytes
    delay_s: float = 0.0


@dataclass
class Faults:
    """Fault injection for the next replies. Counters decrement as faults fire.

    Attributes
    ----------
    drop : number of next replies silently discarded.
    garble : number of next replies with bytes corrupted.
    truncate : number of next replies cut to half (no terminator).
    delay_s : extra delay added to every reply while > 0.
    silent : when True, nothing is answered at all (device hung).
    """

    drop: int = 0
    garble: int = 0
    truncate: int = 0
    delay_s: float = 0.0
    silent: bool = False
    log: list = field(default_factory=list)

    def apply(self, reply: Reply) -> Reply | None:
        if self.silent:
            self.log.append(("silent", reply.data))
            return None
        if self.drop > 0:
            self.drop -= 1
            self.log.append(("drop", reply.data))
            return None
        data = reply.data
        if self.garble > 0:
            self.garble -= 1
            data = bytes((b ^ 0x5A) if i % 2 == 0 else b for i, b in enumerate(data))
            self.log.append(("garble", reply.data))
        if self.truncate > 0:
            self.truncate -= 1
            data = data[: max(1, len(data) // 2)]
            self.log.append(("truncate", reply.data))
        return Reply(data, reply.delay_s + self.delay_s)


class EmulatedDevice:
    """Base class of device emulators: override :meth:`receive`.

    ``time_scale`` multiplies every physical duration (moves, settling): 0 makes them
    instant, 1 is real time. Subclasses read :meth:`now` for their own clock.
    """

    name = "device"

    def __init__(self, *, time_scale: float = 0.0):
        self.time_scale = float(time_scale)
        self.faults = Faults()
        self.lock = threading.RLock()
        self.received = bytearray()

    def now(self) -> float:
        return time.monotonic()

    def receive(self, data: bytes) -> Iterable[Reply]:
        """Consume bytes from the host; return replies to send."""
        raise NotImplementedError

    def tick(self) -> Iterable[Reply]:
        """Called periodically by the server; spontaneous output (e.g. GRBL ALARM on a limit)."""
        return ()


class EmulatorServer:
    """Run an :class:`EmulatedDevice` behind a pty or a TCP socket.

    Parameters
    ----------
    device : EmulatedDevice
    kind : "pty" or "tcp"
    port : TCP port (0 = any free port), for ``kind="tcp"``.

    Use as a context manager or call :meth:`start` / :meth:`stop`. :attr:`url` is what
    a driver passes to ``serial_for_url``.
    """

    def __init__(self, device: EmulatedDevice, *, kind: str = "pty", port: int = 0):
        if kind not in ("pty", "tcp"):
            raise ValueError(f"emulator kind must be 'pty' or 'tcp', got {kind!r}")
        self.device = device
        self.kind = kind
        self._port = port
        self.url: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self._lsock: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._pending: list[tuple[float, bytes]] = []
        self._gone = False

    # ---- lifecycle
    def start(self) -> str:
        if self.kind == "pty":
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)  # no echo, no line discipline before the driver opens it
            tty.setraw(self._master)
            self.url = os.ttyname(self._slave)
        else:
            self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._lsock.bind(("127.0.0.1", self._port))
            self._lsock.listen(1)
            self.url = f"socket://127.0.0.1:{self._lsock.getsockname()[1]}"
        self._thread = threading.Thread(target=self._run, name=f"emu-{self.device.name}", daemon=True)
        self._thread.start()
        return self.url

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_all()

    def __enter__(self) -> "EmulatorServer":
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()
        return False

    def vanish(self) -> None:
        """Simulate unplugging: close our end so the driver's next read fails (EIO / EOF)."""
        self._gone = True
        self._close_all()

    def _close_all(self) -> None:
        for attr in ("_master", "_slave"):
            fd = getattr(self, attr)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, attr, None)
        for attr in ("_conn", "_lsock"):
            s = getattr(self, attr)
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
                setattr(self, attr, None)

    # ---- I/O loop
    def _send_now(self, data: bytes) -> None:
        try:
            if self.kind == "pty" and self._master is not None:
                os.write(self._master, data)
            elif self.kind == "tcp" and self._conn is not None:
                self._conn.sendall(data)
        except OSError:
            pass

    def _queue(self, replies: Iterable[Reply]) -> None:
        now = time.monotonic()
        for r in replies:
            r2 = self.device.faults.apply(r)
            if r2 is None or not r2.data:
                continue
            if r2.delay_s <= 0 and not self._pending:
                self._send_now(r2.data)
            else:
                due = max([now + r2.delay_s] + [d for d, _ in self._pending])  # keep order
                self._pending.append((due, r2.data))

    def _flush_due(self) -> None:
        now = time.monotonic()
        while self._pending and self._pending[0][0] <= now:
            _, data = self._pending.pop(0)
            self._send_now(data)

    def _run(self) -> None:
        while not self._stop.is_set() and not self._gone:
            fd = None
            if self.kind == "pty":
                fd = self._master
            else:
                if self._conn is None:
                    if self._lsock is None:
                        return
                    r, _, _ = select.select([self._lsock], [], [], 0.02)
                    if r:
                        self._conn, _ = self._lsock.accept()
                        self._conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    with self.device.lock:
                        self._queue(self.device.tick())
                    self._flush_due()
                    continue
                fd = self._conn.fileno()
            if fd is None:
                return
            timeout = 0.01 if self._pending else 0.02
            try:
                r, _, _ = select.select([fd], [], [], timeout)
            except (OSError, ValueError):
                return
            if r:
                try:
                    if self.kind == "pty":
                        data = os.read(fd, 4096)
                    else:
                        conn = self._conn
                        data = conn.recv(4096) if conn is not None else b""
                except (OSError, AttributeError):
                    if self._gone or self._stop.is_set():
                        return
                    data = b""
                if not data:
                    if self._gone or self._stop.is_set():
                        return
                    if self.kind == "tcp":  # client went away: wait for the next one
                        try:
                            if self._conn is not None:
                                self._conn.close()
                        except OSError:
                            pass
                        self._conn = None
                        continue
                    time.sleep(0.01)  # pty slave closed by the driver; keep serving
                    continue
                with self.device.lock:
                    self.device.received += data
                    self._queue(self.device.receive(data))
            with self.device.lock:
                self._queue(self.device.tick())
            self._flush_due()
