"""Driver of the plasma-display controller (implements :class:`~opacityhull.rigs.interfaces.Backdrops`
and :class:`~opacityhull.rigs.interfaces.PatternStore`).

Transport: any :class:`~opacityhull.rigs.transport.Transport` (``from_url``: a serial one); wire protocol:
:mod:`opacityhull.rigs.display_protocol` (documented in ``docs/display-protocol.md``).
This module holds the device logic: one command at a time, each answered by ACK or
NAK; timeouts, garbled or truncated replies and ``NAK bad frame``/``NAK busy`` resend
the same frame (same sequence number — every command is idempotent) up to
``retries`` times; a vanished port is re-opened up to ``reconnect_attempts`` times
before the error names the device and says what to check (both from the driver's
:class:`~opacityhull.rigs.transport.SerialSettings`, default :data:`DISPLAY_SERIAL`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping

import numpy as np

from ..errors import ConfigError, DeviceError, InputError
from . import display_protocol as dp
from .interfaces import DeviceInfo, PatternMissing, StorageFull
from .transport import DeviceGone, DeviceTimeout, OverTransport, ProtocolError, Transport, driver_name
from .transport import SerialSettings, SerialTransport, reopen

log = logging.getLogger(__name__)

__all__ = ["DISPLAY_SERIAL", "DisplayController", "DisplayNak", "DisplayPatternMissing", "DisplayStorageFull"]

#: 115200 baud RS-232; a command is resent 3 times, a vanished port re-opened twice, 0.2 s apart.
DISPLAY_SERIAL = SerialSettings(baudrate=115200, timeout_s=2.0, retries=3, reconnect_attempts=2, reconnect_delay_s=0.2)


class DisplayNak(ProtocolError):
    """The controller refused a command (the reason is in the message and :attr:`reason`)."""

    def __init__(self, message: str, reason: int):
        super().__init__(message)
        self.reason = reason


class DisplayPatternMissing(DisplayNak, PatternMissing):
    """NAK no such stored pattern (:data:`~.display_protocol.NAK_NO_PATTERN`)."""


class DisplayStorageFull(DisplayNak, StorageFull):
    """NAK pattern storage full (:data:`~.display_protocol.NAK_STORAGE_FULL`)."""


def display_nak(message: str, reason: int) -> DisplayNak:
    """The NAK error of ``reason``: typed (:class:`PatternMissing`, :class:`StorageFull`)
    where the pattern-store protocol names it."""
    cls = {dp.NAK_NO_PATTERN: DisplayPatternMissing, dp.NAK_STORAGE_FULL: DisplayStorageFull}.get(reason, DisplayNak)
    return cls(message, reason)


def _check_display_options(name: str, outputs: Mapping[str, int], chunk_bytes: int) -> None:
    if not outputs:
        raise ConfigError(f"{name}: at least one display output is required")
    for disp, idx in outputs.items():
        if isinstance(idx, bool) or not isinstance(idx, int) or not 0 <= idx < dp.ALL_OUTPUTS:
            raise ConfigError(f"{name}: output index of display {disp!r} must be an integer in 0..254, got {idx!r}")
    if len(set(outputs.values())) != len(outputs):
        raise ConfigError(f"{name}: two displays share one controller output: {dict(outputs)}")
    if not 1 <= chunk_bytes <= dp.MAX_CHUNK:
        raise ConfigError(f"{name}: chunk_bytes must be 1..{dp.MAX_CHUNK}, got {chunk_bytes}")


class DisplayController(OverTransport):
    """The display controller behind the backdrops.

    Parameters
    ----------
    transport : Transport
        The byte transport (:meth:`from_url` builds a serial one on ``/dev/ttyUSB1``,
        ``socket://host:port`` or a pty path).
    outputs : mapping display name → controller output index
        E.g. ``{"bottom": 0, "back": 1}`` (names as in ``geometry.displays``).
    name : str, optional
        Device name used in messages (default: the transport's).
    serial : SerialSettings
        Default :data:`DISPLAY_SERIAL`. ``timeout_s`` per reply; ``retries``: resends of
        one frame after a timeout, a garbled reply or a retryable NAK;
        ``reconnect_attempts``, ``reconnect_delay_s``: re-opens of a vanished port before
        giving up; ``baudrate`` is the transport's (:meth:`from_url` opens the port at it).
    chunk_bytes : int
        Pattern upload chunk size (1..1024); each chunk is acknowledged.

    No I/O happens in ``__init__``; the port opens in :meth:`open` (or on first use).
    """

    def __init__(
        self,
        transport: Transport,
        *,
        outputs: Mapping[str, int],
        name: str | None = None,
        serial: SerialSettings = DISPLAY_SERIAL,
        chunk_bytes: int = 512,
    ):
        name = driver_name(transport, name, driver="DisplayController", fallback="backdrops")
        _check_display_options(name, outputs, chunk_bytes)
        self.name = name
        self.outputs = dict(outputs)
        self.timeout_s = float(serial.timeout_s)
        self.retries = serial.retries
        self.chunk_bytes = int(chunk_bytes)
        self.reconnect_attempts = serial.reconnect_attempts
        self.reconnect_delay_s = float(serial.reconnect_delay_s)
        self.transport = transport
        self._decoder = dp.FrameDecoder()
        self._seq = 0
        self.stats = {"frames": 0, "resends": 0, "reconnects": 0, "naks": 0}
        self.last_error: str | None = None

    @classmethod
    def from_url(
        cls,
        url: str,
        *,
        outputs: Mapping[str, int],
        name: str = "backdrops",
        serial: SerialSettings = DISPLAY_SERIAL,
        chunk_bytes: int = 512,
    ) -> DisplayController:
        """A controller on a serial URL; ``serial.timeout_s`` bounds every reply and every write."""
        transport = SerialTransport.from_settings(url, serial, name=name)
        return cls(transport, outputs=outputs, name=name, serial=serial, chunk_bytes=chunk_bytes)

    # ---- lifecycle
    def open(self) -> DisplayController:
        self.transport.open()
        self._decoder.reset()
        return self

    def close(self) -> None:
        self.transport.close()

    def reconnect(self, max_attempts: int | None = None, delay_s: float | None = None) -> None:
        """Close and re-open the port, up to ``max_attempts`` times; raise :class:`DeviceGone`
        naming the device if it never comes back."""
        n = self.reconnect_attempts if max_attempts is None else int(max_attempts)
        d = self.reconnect_delay_s if delay_s is None else float(delay_s)

        def once(attempt: int) -> None:
            self.transport.close()
            self.open()
            self.stats["reconnects"] += 1
            log.info("%s: reconnected to %s (attempt %d)", self.name, self.url, attempt)

        def gave_up(tries: int, last: BaseException | None) -> DeviceGone:
            return DeviceGone(
                f"{self.name}: port {self.url} did not come back after {tries} attempt(s) ({last}) — "
                "check the cable and that the controller is powered"
            )

        reopen(once, attempts=n, delay_s=d, gave_up=gave_up)

    # ---- protocol core
    def _next_seq(self) -> int:
        self._seq = self._seq % 254 + 1
        return self._seq

    def _transact(self, cmd: int, payload: bytes = b"", *, what: str = "") -> bytes:
        """Send one command, return the ACK data; resend on timeouts/garbage/retryable NAKs."""
        what = what or dp.COMMAND_NAMES.get(cmd, hex(cmd))
        seq = self._next_seq()
        frame = dp.encode_frame(seq, cmd, payload)
        problems: list[str] = []
        mark = self.transport.mark()
        # one overall deadline: however many garbled frames a babbling line delivers, a
        # command ends within timeout x attempts
        with self.transport.exchange(self.timeout_s * (self.retries + 1), what):
            return self._transact_loop(cmd, frame, seq, what, problems, mark)

    def _transact_loop(self, cmd, frame, seq, what, problems, mark) -> bytes:
        reconnects = 0
        attempt = 0
        while attempt <= self.retries:
            if problems:
                log.info(
                    "%s: %s: resending (attempt %d of %d) after %s",
                    self.name,
                    what,
                    attempt + 1,
                    self.retries + 1,
                    problems[-1],
                )
            try:
                if not self.transport.is_open:
                    self.open()
                self.transport.flush_input()
                self._decoder.reset()
                self.transport.write(frame)
                self.stats["frames"] += 1
                reply = self._await_reply(seq, cmd)
            except DeviceGone:
                if reconnects >= self.reconnect_attempts:
                    raise
                reconnects += 1
                self.reconnect()  # up to reconnect_attempts re-opens; raises DeviceGone naming the device
                continue
            except DeviceTimeout:
                problems.append(f"no reply within {self.timeout_s:g} s")
                attempt += 1
                self.stats["resends"] += 1
                continue
            if isinstance(reply, dp.FrameError):
                problems.append(f"garbled reply ({reply.reason}: {reply.raw[:16]!r})")
                attempt += 1
                self.stats["resends"] += 1
                continue
            if reply.cmd == dp.ACK:
                if not reply.payload or reply.payload[0] != cmd:
                    problems.append(f"ACK for command 0x{reply.payload[:1].hex() or '??'}")
                    attempt += 1
                    continue
                return reply.payload[1:]
            if reply.cmd == dp.NAK:
                try:
                    _, reason = dp.parse_nak(reply.payload)
                except InputError:
                    problems.append("malformed NAK")
                    attempt += 1
                    continue
                self.stats["naks"] += 1
                text = dp.NAK_REASONS.get(reason, f"reason 0x{reason:02X}")
                if reason in dp.RETRYABLE_NAKS:
                    problems.append(f"NAK {text}")
                    attempt += 1
                    self.stats["resends"] += 1
                    continue
                raise display_nak(f"{self.name}: controller refused {what}: {text}", reason)
            problems.append(f"unexpected reply {reply.name}")
            attempt += 1
        self.last_error = problems[-1] if problems else "no reply"
        summary = "; ".join(dict.fromkeys(problems))
        raise DeviceTimeout(
            f"{self.name}: no valid reply to {what} after {self.retries + 1} attempt(s) on {self.url} ({summary}); "
            f"{self.transport.heard_since(mark)} — check the RS-232 cable, baud rate and that the display "
            "controller is powered"
        )

    def _await_reply(self, seq: int, cmd: int) -> dp.Frame | dp.FrameError:
        """Next frame answering ``seq`` (frames for other sequence numbers are late replies
        to earlier commands and are skipped), or the first garbled frame."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = min(deadline, self.transport._clamp(deadline)) - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"{self.name}: no reply within {self.timeout_s:.1f} s on {self.url}")
            chunk = self.transport.read_until(bytes((dp.FLAG,)), timeout_s=remaining, what="reply frame")
            for item in self._decoder.feed(chunk):
                if isinstance(item, dp.FrameError):
                    # A NAK for a frame the controller could not read carries a corrupt seq:
                    # a corrupt reply, whatever it was, means "resend".
                    return item
                if item.seq == seq or (item.cmd == dp.NAK and item.payload[-1:] == bytes((dp.NAK_BAD_FRAME,))):
                    return item

    # ---- helpers
    def _output(self, display: str) -> int:
        try:
            return self.outputs[display]
        except KeyError:
            raise InputError(f"{self.name}: no display named {display!r} (displays: {sorted(self.outputs)})") from None

    def _display_of(self, output: int) -> str | None:
        for k, v in self.outputs.items():
            if v == output:
                return k
        return None

    # ---- Backdrops protocol
    @property
    def displays(self) -> list[str]:
        return list(self.outputs)

    def identity(self) -> str:
        return self._transact(*dp.identify()).decode("ascii", "replace")

    def state(self) -> dp.ControllerState:
        try:
            return dp.parse_state(self._transact(*dp.query_state()))
        except InputError as e:
            raise ProtocolError(f"{self.name}: malformed STATE reply ({e})") from None

    def power(self, display: str, on: bool) -> None:
        self._transact(*dp.power(self._output(display), on), what=f"POWER {display} {'on' if on else 'off'}")

    def pattern_info(self, pattern_id: int) -> dp.PatternInfo | None:
        """Size and CRC-32 of a stored pattern, or None if the id is not stored."""
        try:
            data = self._transact(*dp.pattern_info(pattern_id), what=f"PATTERN_INFO {pattern_id}")
        except DisplayNak as e:
            if e.reason == dp.NAK_NO_PATTERN:
                return None
            raise
        try:
            return dp.parse_pattern_info(data)
        except InputError as e:
            raise ProtocolError(f"{self.name}: malformed PATTERN_INFO reply ({e})") from None

    def upload(
        self,
        display: str,
        pattern_id: int,
        image_rgb8: np.ndarray,
        *,
        skip_if_stored: bool = True,
        progress: Callable[[int, int], None] | None = None,
    ) -> bool:
        """Store ``image_rgb8`` (uint8 (rows, cols, 3)) as pattern ``pattern_id``.

        Patterns are stored in the controller, not per output; ``display`` only checks
        that the display exists. With ``skip_if_stored`` an identical pattern (same size
        and CRC-32) already stored is not sent again. Returns True if bytes were sent.
        ``progress(done_bytes, total_bytes)`` is called after every acknowledged chunk.
        """
        self._output(display)
        w, h, data = dp.pattern_bytes(image_rgb8)
        crc = dp.image_crc32(data)
        if skip_if_stored:
            info = self.pattern_info(pattern_id)
            if info is not None and (info.width, info.height, info.crc32) == (w, h, crc):
                return False
        for restart in range(2):
            try:
                self._upload_once(pattern_id, w, h, data, crc, progress)
                return True
            except DisplayNak as e:
                # The controller lost the upload (power cycle, reconnect): start it over once.
                if restart == 0 and e.reason in (dp.NAK_NO_UPLOAD, dp.NAK_INCOMPLETE, dp.NAK_IMAGE_CRC):
                    continue
                raise
        return True  # pragma: no cover

    def _upload_once(self, pid, w, h, data, crc, progress) -> None:
        self._transact(*dp.upload_begin(pid, w, h), what=f"UPLOAD_BEGIN {pid} ({w}x{h})")
        total = len(data)
        for off, n in dp.pattern_chunks(total, self.chunk_bytes):
            self._transact(*dp.upload_data(pid, off, data[off : off + n]), what=f"UPLOAD_DATA {pid} @{off}")
            if progress is not None:
                progress(off + n, total)
        self._transact(*dp.upload_end(pid, crc), what=f"UPLOAD_END {pid}")

    def show(self, display: str, pattern_id: int) -> None:
        """Power the panel on (if needed) and show stored pattern ``pattern_id``."""
        out = self._output(display)
        self._transact(*dp.power(out, True), what=f"POWER {display} on")
        try:
            self._transact(*dp.show(out, pattern_id), what=f"SHOW {pattern_id} on {display}")
        except DisplayNak as e:
            if e.reason == dp.NAK_NO_PATTERN:
                raise DisplayPatternMissing(
                    f"{self.name}: pattern {pattern_id} is not stored in the controller — upload it first", e.reason
                ) from None
            raise

    def blank(self, display: str | None = None) -> None:
        """Show black on one display or all. Never raises on a dead port (used by ``Rig.safe``):
        failures are recorded in :attr:`last_error`."""
        try:
            if display is None:
                self._transact(*dp.blank(dp.ALL_OUTPUTS), what="BLANK all")
            else:
                self._transact(*dp.blank(self._output(display)), what=f"BLANK {display}")
            self.last_error = None
        except (DeviceError, OSError) as e:
            self.last_error = str(e)

    def shown(self) -> dict[str, int | None]:
        """Pattern id shown per display (None = blank or panel off), queried from the controller."""
        st = self.state()
        out = {}
        for disp, idx in self.outputs.items():
            if idx >= len(st.shown):
                raise ProtocolError(
                    f"{self.name}: controller reports {len(st.shown)} outputs, "
                    f"display {disp!r} is configured on output {idx}"
                )
            out[disp] = st.shown[idx] if st.power[idx] else None
        return out

    # ---- PatternStore protocol
    def stored(self) -> list[int]:
        return list(self.state().stored)

    def slots(self) -> int | None:
        """The controller's pattern capacity, from its IDENTIFY reply (None: not reported)."""
        return dp.parse_identity_slots(self.identity())

    def delete(self, pattern_id: int | None = None) -> None:
        """Delete one stored pattern (or all with None)."""
        self._transact(*dp.delete(pattern_id), what="DELETE")

    def check(self) -> DeviceInfo:
        """Identity and state; never raises (``ok=False`` with the reason instead)."""
        try:
            ident = self.identity()
            st = self.state()
        except (DeviceError, OSError) as e:
            return DeviceInfo(name=self.name, ok=False, detail=str(e))
        missing = [d for d, i in self.outputs.items() if i >= len(st.power)]
        state = {
            "power": {d: st.power[i] for d, i in self.outputs.items() if i < len(st.power)},
            "shown": {d: st.shown[i] for d, i in self.outputs.items() if i < len(st.shown)},
            "stored": list(st.stored),
            "url": self.url,
        }
        if missing:
            return DeviceInfo(
                self.name,
                False,
                f"controller has {len(st.power)} outputs; configured displays {missing} are beyond that",
                ident,
                state,
            )
        return DeviceInfo(self.name, True, f"{ident}; {len(st.stored)} stored pattern(s)", ident, state)
