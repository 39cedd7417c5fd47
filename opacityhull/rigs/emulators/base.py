"""Serve a device emulator over a pty pair or a TCP socket, with fault injection.

An :class:`EmulatedDevice` is a pure state machine: :meth:`~EmulatedDevice.receive`
takes bytes from the host and returns the replies (with optional delays). An
:class:`EmulatorServer` runs it in a background thread behind a real pty
(``os.openpty``; the driver opens the slave path like any serial port) or a TCP socket
on 127.0.0.1 (the driver uses ``socket://127.0.0.1:PORT``). Replies pass through a
:class:`Faults` object first, so tests can drop, garble, delay, silence or cut the
line, or make the device vanish (the pty master closes: the driver sees EIO; the
socket closes: the driver sees EOF) and come back (:meth:`EmulatorServer.reappear`).
"""

from __future__ import annotations

import heapq
import logging
import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass, field
from collections.abc import Iterable

from ...interrupts import signals_off_this_thread

log = logging.getLogger(__name__)

__all__ = ["Reply", "Faults", "EmulatedDevice", "EmulatorServer", "noise"]


@dataclass
class Reply:
    """Bytes to send back, after ``delay_s`` seconds of emulator time.

    Replies leave in order: a delayed reply holds back the ones queued after it (one
    serial line), unless it is ``independent`` — then later replies may overtake it (as
    GRBL's real-time status report overtakes the ``ok`` of a line still being planned).
    """

    data: bytes
    delay_s: float = 0.0
    independent: bool = False


@dataclass
class Faults:
    """Fault injection for the next replies. Counters decrement as faults fire.

    Attributes
    ----------
    drop : number of next replies silently discarded.
    garble : number of next replies with bytes corrupted (every even byte XOR 0x5A; a
        trailing ``\r\n`` is kept, so the receiver gets a complete but garbled line).
    truncate : number of next replies cut to half (the terminator is lost).
    late : number of next replies delivered ``late_s`` seconds late; later replies
        overtake them.
    late_s : the delay for ``late`` replies.
    match : when set, the four counters above only fire on replies whose bytes start
        with ``match`` (``b"ok"``, ``b"<"``, ``b"\\x7e\\x03"`` ...); others pass untouched.
    delay_s : extra delay added to every reply while > 0.
    silent : when True, nothing is answered at all (device hung).
    babble : while > 0, the device sends this many bytes per second of noise that never
        parses in any of the rig's protocols (bytes 0x80-0xFD, never the frame flags
        0x7E/0x7D, with a ``\r\n`` every 40 bytes), and its replies become noise of
        the same length: a wrong baud rate or a babbling device.
    log : what fired, as ``(kind, original bytes)``.
    """

    drop: int = 0
    garble: int = 0
    truncate: int = 0
    late: int = 0
    late_s: float = 0.0
    match: bytes | None = None
    delay_s: float = 0.0
    silent: bool = False
    babble: float = 0.0
    log: list = field(default_factory=list)

    def apply(self, reply: Reply) -> Reply | None:
        if self.silent:
            self.log.append(("silent", reply.data))
            return None
        if self.babble > 0:  # a wrong baud rate: the real replies are noise too
            self.log.append(("babble", reply.data))
            return Reply(noise(len(reply.data), len(self.log)), reply.delay_s + self.delay_s, reply.independent)
        targeted = self.match is None or reply.data.startswith(self.match)
        if targeted and self.drop > 0:
            self.drop -= 1
            self.log.append(("drop", reply.data))
            return None
        data = reply.data
        delay = reply.delay_s + self.delay_s
        independent = reply.independent
        if targeted and self.garble > 0:
            self.garble -= 1
            body = data.rstrip(b"\r\n")
            data = bytes((b ^ 0x5A) if i % 2 == 0 else b for i, b in enumerate(body)) + data[len(body) :]
            self.log.append(("garble", reply.data))
        if targeted and self.truncate > 0:
            self.truncate -= 1
            data = data[: max(1, len(data) // 2)]
            self.log.append(("truncate", reply.data))
        if targeted and self.late > 0:
            self.late -= 1
            delay += self.late_s
            independent = True
            self.log.append(("late", reply.data))
        return Reply(data, delay, independent)


_NOISE = bytes(range(0x80, 0xFE))


def noise(n: int, offset: int = 0) -> bytes:
    """``n`` bytes of :attr:`Faults.babble` noise (deterministic, starting at ``offset``)."""
    out = bytearray()
    for i in range(offset, offset + n):
        out += b"\r\n" if i % 40 == 39 else _NOISE[(i * 37) % len(_NOISE)].to_bytes(1, "big")
    return bytes(out)


class EmulatedDevice:
    """Base class of device emulators: override :meth:`receive`.

    ``time_scale`` multiplies every physical duration (moves, settling): 0 makes them
    instant, 1 is real time. Subclasses read :meth:`now` for their own clock. The server
    calls :meth:`receive` and :meth:`tick` with :attr:`lock` held; public accessors of
    subclasses take it too, so tests and the simulator can read state from any thread.
    """

    name = "device"

    def __init__(self, *, time_scale: float = 0.0):
        if not time_scale >= 0.0:
            raise ValueError(f"time_scale must be >= 0, got {time_scale!r}")
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
        self._url: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self._lsock: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._pending: list[tuple[float, int, bytes]] = []  # heap of (due, seq, data)
        self._ordered_due = 0.0  # due time of the last in-order reply
        self._seq = 0
        self._pending_lock = threading.Lock()
        self._gone = False
        self.connections = 0
        self._babble_t: float | None = None
        self._babble_sent = 0

    @property
    def url(self) -> str:
        """What a driver opens: the pty's device path, or ``socket://127.0.0.1:PORT``."""
        if self._url is None:
            raise RuntimeError(
                f"emulator {self.device.name}: not serving yet; use it as a context manager or call start()"
            )
        return self._url

    # ---- lifecycle
    def _open_endpoint(self) -> str:
        if self.kind == "pty":
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)  # no echo, no line discipline before the driver opens it
            tty.setraw(self._master)
            return os.ttyname(self._slave)
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._lsock.bind(("127.0.0.1", self._port))
        self._lsock.listen(1)
        self._port = self._lsock.getsockname()[1]  # keep it: reappear() binds the same port
        return f"socket://127.0.0.1:{self._port}"

    def start(self) -> str:
        self._stop.clear()
        self._gone = False
        self._url = url = self._open_endpoint()
        self._thread = threading.Thread(target=self._run, name=f"emu-{self.device.name}", daemon=True)
        self._thread.start()
        return url

    def _join(self) -> None:
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def stop(self) -> None:
        self._stop.set()
        self._join()
        self._close_all()

    def __enter__(self) -> EmulatorServer:
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()
        return False

    def vanish(self) -> None:
        """Simulate unplugging: close our end so the driver's next read fails (EIO / EOF).

        The serving thread is joined before the descriptors close, so it can never
        touch a descriptor number the OS hands out again afterwards.
        """
        self._gone = True
        self._join()
        self._close_all()
        with self._pending_lock:
            self._pending.clear()

    def reappear(self) -> str:
        """Plug back in after :meth:`vanish`: serve again (same TCP port; a new pty path).

        The device state is kept (a controller with its own power supply whose USB cable
        was pulled). Returns the URL to reconnect to.
        """
        if not self._gone:
            raise RuntimeError("reappear() without vanish()")
        self._join()
        self._close_all()
        return self.start()

    @property
    def vanished(self) -> bool:
        return self._gone

    @property
    def backlog(self) -> int:
        """Replies queued but not yet sent (delayed or late ones)."""
        with self._pending_lock:
            return len(self._pending)

    def _close_all(self) -> None:
        for attr in ("_master", "_slave"):
            fd = getattr(self, attr)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError as e:  # already closed by the other side: nothing left to free
                    log.debug("%s: closing %s: %s", self.device.name, attr, e)
                setattr(self, attr, None)
        for attr in ("_conn", "_lsock"):
            s = getattr(self, attr)
            if s is not None:
                try:
                    s.close()
                except OSError as e:
                    log.debug("%s: closing %s: %s", self.device.name, attr, e)
                setattr(self, attr, None)

    # ---- I/O loop
    def _send_now(self, data: bytes) -> None:
        try:
            if self.kind == "pty" and self._master is not None:
                view = memoryview(data)
                while view:
                    n = os.write(self._master, view)
                    view = view[n:]
            elif self.kind == "tcp" and self._conn is not None:
                self._conn.sendall(data)
        except OSError as e:  # the client went away: its replies have nowhere to go, as on a real line
            log.debug("%s: reply of %d byte(s) dropped: %s", self.device.name, len(data), e)

    def _queue(self, replies: Iterable[Reply]) -> None:
        now = time.monotonic()
        for r in replies:
            r2 = self.device.faults.apply(r)
            if r2 is None or not r2.data:
                continue
            with self._pending_lock:
                if r2.independent:
                    due = now + r2.delay_s
                else:
                    due = max(now + r2.delay_s, self._ordered_due)  # one line: keep order
                    self._ordered_due = due
                    if due <= now:
                        self._send_now(r2.data)
                        continue
                self._seq += 1
                heapq.heappush(self._pending, (due, self._seq, r2.data))

    def _babble(self) -> None:
        rate = self.device.faults.babble
        now = time.monotonic()
        if rate <= 0:
            self._babble_t = None
            return
        if self._babble_t is None:
            self._babble_t = now
            return
        n = int((now - self._babble_t) * rate)
        if n <= 0:
            return
        self._babble_t += n / rate
        # a babbling device does not wait for its reader: send only what the line takes
        # now (a blocked write would stall the emulator, and a reconnect after it)
        fd = self._master if self.kind == "pty" else (self._conn.fileno() if self._conn is not None else None)
        if fd is None:
            return
        try:
            _, w, _ = select.select([], [fd], [], 0)
            if not w:
                return
            chunk = noise(min(n, 4096), self._babble_sent)
            conn = self._conn
            if self.kind == "pty":
                sent = os.write(fd, chunk)
            elif conn is not None:
                sent = conn.send(chunk)
            else:
                return
        except (OSError, ValueError, AttributeError):
            return
        self._babble_sent += sent

    def _flush_due(self) -> None:
        now = time.monotonic()
        with self._pending_lock:
            while self._pending and self._pending[0][0] <= now:
                _, _, data = heapq.heappop(self._pending)
                self._send_now(data)

    def _run(self) -> None:
        signals_off_this_thread()
        while not self._stop.is_set() and not self._gone:
            fd = None
            if self.kind == "pty":
                fd = self._master
            else:
                if self._conn is None:
                    if self._lsock is None:
                        return
                    try:
                        r, _, _ = select.select([self._lsock], [], [], 0.02)
                    except (OSError, ValueError):
                        return
                    if r and not self._gone:
                        try:
                            self._conn, _ = self._lsock.accept()
                        except OSError:
                            return
                        self._conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                        self.connections += 1
                    with self.device.lock:
                        self._queue(self.device.tick())
                    self._flush_due()
                    continue
                fd = self._conn.fileno()
            if fd is None:
                return
            with self._pending_lock:
                timeout = 0.005 if self._pending or self.device.faults.babble > 0 else 0.02
            try:
                r, _, _ = select.select([fd], [], [], timeout)
            except (OSError, ValueError):
                return
            if self._gone or self._stop.is_set():
                return
            if r:
                try:
                    if self.kind == "pty":
                        data = os.read(fd, 65536)
                    else:
                        conn = self._conn
                        data = conn.recv(65536) if conn is not None else b""
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
                        except OSError as e:
                            log.debug("%s: closing the client socket: %s", self.device.name, e)
                        self._conn = None
                        with self._pending_lock:
                            self._pending.clear()
                        continue
                    time.sleep(0.01)  # pty slave closed by the driver; keep serving
                    continue
                with self.device.lock:
                    self.device.received += data
                    self._queue(self.device.receive(data))
            with self.device.lock:
                self._queue(self.device.tick())
            self._flush_due()
            self._babble()
