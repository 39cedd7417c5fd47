"""Emulator of the plasma-display controller: the same bytes as the real one.

Holds the stored patterns, per-output power and shown pattern, and an upload in
progress; answers every frame of :mod:`opacityhull.rigs.display_protocol` with an
ACK or NAK. Served over a pty or TCP by
:class:`~opacityhull.rigs.emulators.base.EmulatorServer`.

Faults, on top of the reply faults of :class:`~opacityhull.rigs.emulators.base.Faults`
(``drop``, ``garble``, ``truncate``, ``delay_s``, ``silent``) and the server's
``vanish()``:

* ``corrupt_rx`` — the next N received frames are treated as failing their checksum
  (as if the line corrupted them), so the controller answers ``NAK bad frame``;
* ``busy`` — the next N commands are answered ``NAK busy``;
* ``on_command`` — a callback ``f(frame)`` run for every valid frame before it is
  handled (tests use it to pull the plug at a precise point of an upload).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Iterable

import numpy as np

from .. import display_protocol as dp
from .base import EmulatedDevice, Reply

log = logging.getLogger(__name__)

__all__ = ["DisplayEmulator"]


class DisplayEmulator(EmulatedDevice):
    """A plasma-display controller with ``outputs`` panel outputs.

    Parameters
    ----------
    outputs : int
        Number of panel outputs (indices ``0..outputs-1``).
    slots : int
        How many patterns it can store.
    max_width, max_height : int
        Largest pattern it accepts, in pixels.
    switch_s : float
        Time the panel takes to switch pattern or power (scaled by ``time_scale``).
    time_scale : float
        0 = instant replies, 1 = real time.
    """

    name = "display"
    model = "OHDC-2 plasma display controller (emulated)"
    firmware = "1.3.0"

    def __init__(
        self,
        *,
        outputs: int = 2,
        slots: int = 64,
        max_width: int = 512,
        max_height: int = 512,
        switch_s: float = 0.05,
        time_scale: float = 0.0,
    ):
        super().__init__(time_scale=time_scale)
        if not 1 <= outputs <= 254:
            raise ValueError(f"outputs must be 1..254, got {outputs}")
        self.outputs = int(outputs)
        self.slots = int(slots)
        self.max_width = int(max_width)
        self.max_height = int(max_height)
        self.switch_s = float(switch_s)
        self._power = [False] * self.outputs
        self._shown: list[int | None] = [None] * self.outputs
        self._patterns: dict[int, tuple[int, int, bytes]] = {}
        self._upload: dict | None = None
        self._decoder = dp.FrameDecoder()
        self.corrupt_rx = 0
        self.busy = 0
        self.on_command: Callable[[dp.Frame], None] | None = None
        self.history: list[tuple[str, bytes]] = []  # (command name, payload) of every valid frame

    # ---- public state accessors (thread-safe; the simulator reads these)
    def shown(self, output: int) -> int | None:
        """Pattern id selected on ``output`` (None = blank)."""
        with self.lock:
            return self._shown[self._out(output)]

    def powered(self, output: int) -> bool:
        with self.lock:
            return self._power[self._out(output)]

    def stored_ids(self) -> list[int]:
        with self.lock:
            return sorted(self._patterns)

    def pattern(self, pattern_id: int) -> np.ndarray:
        """Stored pattern as uint8 (rows, cols, 3); KeyError if not stored."""
        with self.lock:
            if pattern_id not in self._patterns:
                raise KeyError(f"pattern {pattern_id} is not stored (stored: {sorted(self._patterns)})")
            w, h, data = self._patterns[pattern_id]
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3).copy()

    def displayed(self, output: int, width: int | None = None, height: int | None = None) -> np.ndarray:
        """What the panel emits: the shown pattern (black when blank or powered off),
        scaled to ``width × height`` with nearest neighbour if given. uint8 (rows, cols, 3)."""
        with self.lock:
            out = self._out(output)
            pid = self._shown[out] if self._power[out] else None
            img = self.pattern(pid) if pid is not None else None
        if img is None:
            img = np.zeros((height or 1, width or 1, 3), np.uint8)
        if width is not None and height is not None:
            img = dp.nearest_resize(img, width, height)
        return img

    def is_lit(self) -> bool:
        """True if any powered output shows a pattern."""
        with self.lock:
            return any(p and s is not None for p, s in zip(self._power, self._shown, strict=True))

    def _out(self, output: int) -> int:
        if not 0 <= output < self.outputs:
            raise IndexError(f"output {output} not in 0..{self.outputs - 1}")
        return output

    # ---- wire side
    def receive(self, data: bytes) -> Iterable[Reply]:
        replies: list[Reply] = []
        for item in self._decoder.feed(data):
            if isinstance(item, dp.FrameError):
                seq = item.seq if item.seq is not None else 0
                cmd = item.cmd if item.cmd is not None else 0
                replies.append(self._reply(seq, *dp.nak(cmd, dp.NAK_BAD_FRAME)))
                continue
            if self.corrupt_rx > 0:
                self.corrupt_rx -= 1
                self.history.append(("corrupted", item.payload))
                replies.append(self._reply(item.seq, *dp.nak(item.cmd, dp.NAK_BAD_FRAME)))
                continue
            self.history.append((item.name, item.payload))
            if self.on_command is not None:
                self.on_command(item)
            if self.busy > 0:
                self.busy -= 1
                replies.append(self._reply(item.seq, *dp.nak(item.cmd, dp.NAK_BUSY)))
                continue
            cmd, payload, delay = self._handle(item)
            replies.append(self._reply(item.seq, cmd, payload, delay))
        return replies

    def _reply(self, seq: int, cmd: int, payload: bytes, delay_s: float = 0.0) -> Reply:
        return Reply(dp.encode_frame(seq, cmd, payload), delay_s * self.time_scale)

    def _handle(self, f: dp.Frame) -> tuple[int, bytes, float]:
        c, p = f.cmd, f.payload

        def bad(reason):
            return (*dp.nak(c, reason), 0.0)

        def ok(data=b"", delay=0.0):
            return (*dp.ack(c, data), delay)

        if c == dp.CMD_IDENTIFY:
            if p:
                return bad(dp.NAK_BAD_LENGTH)
            ident = (
                f"{self.model};fw={self.firmware};outputs={self.outputs};slots={self.slots};"
                f"max={self.max_width}x{self.max_height}"
            )
            return ok(ident.encode("ascii"))
        if c == dp.CMD_STATE:
            if p:
                return bad(dp.NAK_BAD_LENGTH)
            st = dp.ControllerState(
                power=tuple(self._power), shown=tuple(self._shown), stored=tuple(sorted(self._patterns))
            )
            return ok(dp.encode_state(st))
        if c == dp.CMD_POWER:
            if len(p) != 2:
                return bad(dp.NAK_BAD_LENGTH)
            out, on = p
            if out >= self.outputs or on not in (0, 1):
                return bad(dp.NAK_BAD_OUTPUT if out >= self.outputs else dp.NAK_OUT_OF_RANGE)
            changed = self._power[out] != bool(on)
            self._power[out] = bool(on)
            return ok(delay=self.switch_s if changed else 0.0)
        if c == dp.CMD_SHOW:
            if len(p) != 3:
                return bad(dp.NAK_BAD_LENGTH)
            out, pid = struct.unpack(">BH", p)
            if out >= self.outputs:
                return bad(dp.NAK_BAD_OUTPUT)
            if pid not in self._patterns:
                return bad(dp.NAK_NO_PATTERN)
            self._shown[out] = pid
            return ok(delay=self.switch_s)
        if c == dp.CMD_BLANK:
            if len(p) != 1:
                return bad(dp.NAK_BAD_LENGTH)
            out = p[0]
            if out == dp.ALL_OUTPUTS:
                self._shown = [None] * self.outputs
            elif out < self.outputs:
                self._shown[out] = None
            else:
                return bad(dp.NAK_BAD_OUTPUT)
            return ok(delay=self.switch_s)
        if c == dp.CMD_UPLOAD_BEGIN:
            if len(p) != 6:
                return bad(dp.NAK_BAD_LENGTH)
            pid, w, h = struct.unpack(">HHH", p)
            if pid == dp.NO_PATTERN or w < 1 or h < 1:
                return bad(dp.NAK_OUT_OF_RANGE)
            if w > self.max_width or h > self.max_height:
                return bad(dp.NAK_TOO_LARGE)
            if pid not in self._patterns and len(self._patterns) >= self.slots:
                return bad(dp.NAK_STORAGE_FULL)
            n = w * h * 3
            self._upload = {"id": pid, "w": w, "h": h, "buf": bytearray(n), "got": np.zeros(n, bool)}
            return ok()
        if c == dp.CMD_UPLOAD_DATA:
            if len(p) < 7:
                return bad(dp.NAK_BAD_LENGTH)
            pid, off = struct.unpack(">HI", p[:6])
            data = p[6:]
            u = self._upload
            if u is None or u["id"] != pid:
                return bad(dp.NAK_NO_UPLOAD)
            if off + len(data) > len(u["buf"]):
                return bad(dp.NAK_OUT_OF_RANGE)
            u["buf"][off : off + len(data)] = data
            u["got"][off : off + len(data)] = True
            return ok(struct.pack(">I", off))
        if c == dp.CMD_UPLOAD_END:
            if len(p) != 6:
                return bad(dp.NAK_BAD_LENGTH)
            pid, crc = struct.unpack(">HI", p)
            u = self._upload
            if u is None or u["id"] != pid:
                return bad(dp.NAK_NO_UPLOAD)
            if not u["got"].all():
                return bad(dp.NAK_INCOMPLETE)
            if dp.image_crc32(bytes(u["buf"])) != crc:
                self._upload = None
                return bad(dp.NAK_IMAGE_CRC)
            self._patterns[pid] = (u["w"], u["h"], bytes(u["buf"]))
            self._upload = None
            return ok()
        if c == dp.CMD_PATTERN_INFO:
            if len(p) != 2:
                return bad(dp.NAK_BAD_LENGTH)
            (pid,) = struct.unpack(">H", p)
            if pid not in self._patterns:
                return bad(dp.NAK_NO_PATTERN)
            w, h, data = self._patterns[pid]
            return ok(dp.encode_pattern_info(dp.PatternInfo(w, h, dp.image_crc32(data))))
        if c == dp.CMD_DELETE:
            if len(p) != 2:
                return bad(dp.NAK_BAD_LENGTH)
            (pid,) = struct.unpack(">H", p)
            if pid == dp.NO_PATTERN:
                self._patterns.clear()
                self._shown = [None] * self.outputs
            elif pid in self._patterns:
                del self._patterns[pid]
                self._shown = [None if s == pid else s for s in self._shown]
            else:
                return bad(dp.NAK_NO_PATTERN)
            return ok()
        return bad(dp.NAK_UNKNOWN_CMD)
