"""Wire protocol of the plasma-display controller (pure encode/parse, no I/O).

The controller sits on RS-232 (115200 8N1) and drives up to 255 panel outputs. It
stores small RGB8 patterns (e.g. 64×36) which each panel scales to its native
resolution with nearest-neighbour sampling; the software generates the patterns,
uploads them once and then only switches between stored ids. The full description,
with byte-level examples, is ``docs/display-protocol.md``; this module is its
executable form and is shared by the driver (:mod:`opacityhull.rigs.backdrops`) and
the emulator (:mod:`opacityhull.rigs.emulators.display`).

Framing (both directions) is asynchronous HDLC as in PPP (RFC 1662)::

    0x7E | escape( SEQ | CMD | PAYLOAD... | CRC16_hi | CRC16_lo ) | 0x7E

* ``0x7E`` is the flag that delimits frames; inside a frame ``0x7E`` and ``0x7D``
  are sent as ``0x7D, byte ^ 0x20``. A receiver that loses sync (line noise, a
  truncated frame) resynchronises at the next flag — no length field to misread.
* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR; check
  value ``0x29B1`` for ``b"123456789"``) over ``SEQ | CMD | PAYLOAD``, big-endian.
* ``SEQ`` (1..254) is chosen by the host per command and echoed by the controller.
  A retried command keeps its ``SEQ``; every command is idempotent (absolute state:
  "show pattern 5 on output 1", "these bytes at this offset"), so a late reply to an
  earlier attempt of the same command is as good as the reply to the retry.
* Every command is answered by exactly one ``ACK`` (0x06: ``cmd, data...``) or
  ``NAK`` (0x15: ``cmd, reason``). A frame that fails its CRC is answered by a ``NAK``
  with reason :data:`NAK_BAD_FRAME` and ``SEQ``/``cmd`` as received (possibly
  corrupt), which the host treats as "resend".

Integers are big-endian. Pattern ids are u16 in ``0..0xFFFE``; ``0xFFFF`` means "none"
(in state replies) or "all" (in ``DELETE``).
"""

from __future__ import annotations

import binascii
import logging
import struct
import zlib
from dataclasses import dataclass
from collections.abc import Iterator

import numpy as np

from ..errors import InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = [
    "FLAG",
    "ESC",
    "MAX_PAYLOAD",
    "MAX_CHUNK",
    "NO_PATTERN",
    "ALL_OUTPUTS",
    "CMD_IDENTIFY",
    "CMD_STATE",
    "CMD_POWER",
    "CMD_SHOW",
    "CMD_BLANK",
    "CMD_UPLOAD_BEGIN",
    "CMD_UPLOAD_DATA",
    "CMD_UPLOAD_END",
    "CMD_PATTERN_INFO",
    "CMD_DELETE",
    "ACK",
    "NAK",
    "COMMAND_NAMES",
    "NAK_REASONS",
    "RETRYABLE_NAKS",
    "NAK_BAD_FRAME",
    "NAK_BAD_LENGTH",
    "NAK_UNKNOWN_CMD",
    "NAK_BAD_OUTPUT",
    "NAK_NO_PATTERN",
    "NAK_OUT_OF_RANGE",
    "NAK_NO_UPLOAD",
    "NAK_BUSY",
    "NAK_STORAGE_FULL",
    "NAK_INCOMPLETE",
    "NAK_IMAGE_CRC",
    "NAK_TOO_LARGE",
    "crc16_ccitt",
    "image_crc32",
    "encode_frame",
    "Frame",
    "FrameError",
    "FrameDecoder",
    "ControllerState",
    "PatternInfo",
    "identify",
    "parse_identity_slots",
    "query_state",
    "power",
    "show",
    "blank",
    "upload_begin",
    "upload_data",
    "upload_end",
    "pattern_info",
    "delete",
    "ack",
    "nak",
    "parse_state",
    "encode_state",
    "parse_pattern_info",
    "encode_pattern_info",
    "parse_nak",
    "pattern_bytes",
    "pattern_chunks",
    "nearest_resize",
]

FLAG = 0x7E
ESC = 0x7D
_ESC_XOR = 0x20

#: Largest unescaped payload a frame may carry (an UPLOAD_DATA header of 6 bytes + 1024 data bytes).
MAX_CHUNK = 1024
MAX_PAYLOAD = MAX_CHUNK + 6
NO_PATTERN = 0xFFFF
ALL_OUTPUTS = 0xFF

CMD_IDENTIFY = 0x01
CMD_STATE = 0x02
CMD_POWER = 0x10
CMD_SHOW = 0x11
CMD_BLANK = 0x12
CMD_UPLOAD_BEGIN = 0x20
CMD_UPLOAD_DATA = 0x21
CMD_UPLOAD_END = 0x22
CMD_PATTERN_INFO = 0x23
CMD_DELETE = 0x24
ACK = 0x06
NAK = 0x15

COMMAND_NAMES = {
    CMD_IDENTIFY: "IDENTIFY",
    CMD_STATE: "STATE",
    CMD_POWER: "POWER",
    CMD_SHOW: "SHOW",
    CMD_BLANK: "BLANK",
    CMD_UPLOAD_BEGIN: "UPLOAD_BEGIN",
    CMD_UPLOAD_DATA: "UPLOAD_DATA",
    CMD_UPLOAD_END: "UPLOAD_END",
    CMD_PATTERN_INFO: "PATTERN_INFO",
    CMD_DELETE: "DELETE",
    ACK: "ACK",
    NAK: "NAK",
}

NAK_BAD_FRAME = 0x01  # CRC mismatch or framing error: resend
NAK_BAD_LENGTH = 0x02  # payload length wrong for the command
NAK_UNKNOWN_CMD = 0x03
NAK_BAD_OUTPUT = 0x04  # output index not present on this controller
NAK_NO_PATTERN = 0x05  # pattern id not stored
NAK_OUT_OF_RANGE = 0x06  # chunk beyond the pattern's size, or bad dimensions
NAK_NO_UPLOAD = 0x07  # UPLOAD_DATA/END without a matching UPLOAD_BEGIN (e.g. after a power cycle)
NAK_BUSY = 0x08  # controller busy (panel switching): resend
NAK_STORAGE_FULL = 0x09
NAK_INCOMPLETE = 0x0A  # UPLOAD_END before every byte arrived
NAK_IMAGE_CRC = 0x0B  # UPLOAD_END: CRC-32 of the received image differs
NAK_TOO_LARGE = 0x0C  # pattern larger than the controller's maximum

NAK_REASONS = {
    NAK_BAD_FRAME: "bad frame (checksum)",
    NAK_BAD_LENGTH: "bad payload length",
    NAK_UNKNOWN_CMD: "unknown command",
    NAK_BAD_OUTPUT: "no such output",
    NAK_NO_PATTERN: "no such stored pattern",
    NAK_OUT_OF_RANGE: "out of range",
    NAK_NO_UPLOAD: "no upload in progress for this pattern",
    NAK_BUSY: "busy",
    NAK_STORAGE_FULL: "pattern storage full",
    NAK_INCOMPLETE: "upload incomplete",
    NAK_IMAGE_CRC: "image CRC mismatch",
    NAK_TOO_LARGE: "pattern too large",
}
#: NAK reasons after which resending the same frame can succeed.
RETRYABLE_NAKS = frozenset({NAK_BAD_FRAME, NAK_BUSY})


# --------------------------------------------------------------------------- checksums


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value 0x29B1 for ``b"123456789"``):
    ``binascii.crc_hqx`` is this CRC (poly 0x1021, MSB first) from the given start value."""
    return binascii.crc_hqx(data, crc)


def image_crc32(data: bytes) -> int:
    """CRC-32 (zlib/IEEE 802.3) of a pattern's RGB8 bytes, row-major; identifies a stored pattern."""
    return zlib.crc32(data) & 0xFFFFFFFF


# --------------------------------------------------------------------------- framing


def _escape(body: bytes) -> bytes:
    out = bytearray()
    for b in body:
        if b in (FLAG, ESC):
            out += bytes((ESC, b ^ _ESC_XOR))
        else:
            out.append(b)
    return bytes(out)


def encode_frame(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    """One frame on the wire: flag, escaped ``seq cmd payload crc16``, flag."""
    if not 0 <= seq <= 255 or not 0 <= cmd <= 255:
        raise InputError(f"frame seq/cmd must be bytes, got seq={seq}, cmd={cmd}")
    if len(payload) > MAX_PAYLOAD:
        raise InputError(f"frame payload of {len(payload)} bytes exceeds the maximum {MAX_PAYLOAD}")
    body = bytes((seq, cmd)) + bytes(payload)
    return bytes((FLAG,)) + _escape(body + struct.pack(">H", crc16_ccitt(body))) + bytes((FLAG,))


@dataclass(frozen=True)
class Frame:
    """A frame that passed its CRC."""

    seq: int
    cmd: int
    payload: bytes

    @property
    def name(self) -> str:
        return COMMAND_NAMES.get(self.cmd, f"0x{self.cmd:02X}")


@dataclass(frozen=True)
class FrameError:
    """Bytes between two flags that are not a valid frame (bad CRC, bad escape, too long/short).

    ``seq`` and ``cmd`` are the raw first bytes if present (unreliable: the frame is corrupt).
    """

    reason: str
    raw: bytes
    seq: int | None = None
    cmd: int | None = None


class FrameDecoder:
    """Incremental frame decoder: :meth:`feed` bytes as they arrive, get frames and errors.

    Everything between two flags is a frame candidate; empty candidates (back-to-back
    flags) are ignored. Candidates longer than the largest legal frame are reported
    once and the rest is skipped up to the next flag, so a stream of garbage cannot
    grow memory without bound.
    """

    _MAX_RAW = 2 * (MAX_PAYLOAD + 4) + 16

    def __init__(self):
        self._buf = bytearray()
        self._overflow = False

    def reset(self) -> None:
        """Forget a partial frame (used after a timeout, before a resend)."""
        self._buf.clear()
        self._overflow = False

    @property
    def pending(self) -> bytes:
        """Bytes of the frame currently being received."""
        return bytes(self._buf)

    def feed(self, data: bytes) -> list[Frame | FrameError]:
        out: list[Frame | FrameError] = []
        for b in data:
            if b == FLAG:
                if self._overflow:
                    self._overflow = False
                elif self._buf:
                    out.append(_decode_body(bytes(self._buf)))
                self._buf.clear()
                continue
            if self._overflow:
                continue
            self._buf.append(b)
            if len(self._buf) > self._MAX_RAW:
                out.append(FrameError("frame too long (missing flag?)", bytes(self._buf[:32])))
                self._buf.clear()
                self._overflow = True
        return out


def _decode_body(raw: bytes) -> Frame | FrameError:
    body = bytearray()
    it = iter(raw)
    for b in it:
        if b == ESC:
            nxt = next(it, None)
            if nxt is None or (nxt ^ _ESC_XOR) not in (FLAG, ESC):
                return FrameError("bad escape sequence", raw, *_peek(raw))
            body.append(nxt ^ _ESC_XOR)
        else:
            body.append(b)
    if len(body) < 4:
        return FrameError(f"frame too short ({len(body)} bytes)", raw, *_peek(raw))
    data, crc = bytes(body[:-2]), struct.unpack(">H", body[-2:])[0]
    if crc16_ccitt(data) != crc:
        return FrameError("checksum mismatch", raw, data[0], data[1])
    if len(data) - 2 > MAX_PAYLOAD:
        return FrameError("payload too long", raw, data[0], data[1])
    return Frame(seq=data[0], cmd=data[1], payload=data[2:])


def _peek(raw: bytes) -> tuple[int | None, int | None]:
    return (raw[0] if len(raw) > 0 else None, raw[1] if len(raw) > 1 else None)


# --------------------------------------------------------------------------- payloads (host → controller)


def _u8(name: str, v: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) <= 0xFF:
        raise InputError(f"{name} must be an integer in 0..255, got {v!r}")
    return int(v)


def _pid(v: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) < NO_PATTERN:
        raise InputError(f"pattern id must be an integer in 0..{NO_PATTERN - 1}, got {v!r}")
    return int(v)


def identify() -> tuple[int, bytes]:
    return CMD_IDENTIFY, b""


def parse_identity_slots(identity: str) -> int | None:
    """The pattern capacity ``M`` of an IDENTIFY reply (``model;fw=X.Y.Z;outputs=N;slots=M;max=WxH``),
    None when it names none (or a non-positive one)."""
    import re

    m = re.search(r"(?:^|;)slots=(\d+)(?:;|$)", str(identity))
    return int(m.group(1)) if m and int(m.group(1)) > 0 else None


def query_state() -> tuple[int, bytes]:
    return CMD_STATE, b""


def power(output: int, on: bool) -> tuple[int, bytes]:
    return CMD_POWER, bytes((_u8("output", output), 1 if on else 0))


def show(output: int, pattern_id: int) -> tuple[int, bytes]:
    return CMD_SHOW, struct.pack(">BH", _u8("output", output), _pid(pattern_id))


def blank(output: int = ALL_OUTPUTS) -> tuple[int, bytes]:
    return CMD_BLANK, bytes((_u8("output", output),))


def upload_begin(pattern_id: int, width: int, height: int) -> tuple[int, bytes]:
    if not (1 <= width <= 0xFFFF and 1 <= height <= 0xFFFF):
        raise InputError(f"pattern size must be 1..65535 pixels per side, got {width}x{height}")
    return CMD_UPLOAD_BEGIN, struct.pack(">HHH", _pid(pattern_id), width, height)


def upload_data(pattern_id: int, offset: int, data: bytes) -> tuple[int, bytes]:
    if len(data) == 0 or len(data) > MAX_CHUNK:
        raise InputError(f"upload chunk must hold 1..{MAX_CHUNK} bytes, got {len(data)}")
    return CMD_UPLOAD_DATA, struct.pack(">HI", _pid(pattern_id), offset) + bytes(data)


def upload_end(pattern_id: int, crc32: int) -> tuple[int, bytes]:
    return CMD_UPLOAD_END, struct.pack(">HI", _pid(pattern_id), crc32 & 0xFFFFFFFF)


def pattern_info(pattern_id: int) -> tuple[int, bytes]:
    return CMD_PATTERN_INFO, struct.pack(">H", _pid(pattern_id))


def delete(pattern_id: int | None = None) -> tuple[int, bytes]:
    """Delete one stored pattern, or all of them (``None``)."""
    return CMD_DELETE, struct.pack(">H", NO_PATTERN if pattern_id is None else _pid(pattern_id))


# --------------------------------------------------------------------------- replies (controller → host)


def ack(cmd: int, data: bytes = b"") -> tuple[int, bytes]:
    return ACK, bytes((cmd,)) + bytes(data)


def nak(cmd: int, reason: int) -> tuple[int, bytes]:
    return NAK, bytes((cmd & 0xFF, reason & 0xFF))


def parse_nak(payload: bytes) -> tuple[int, int]:
    """``(cmd, reason)`` of a NAK payload; raises :class:`InputError` when malformed."""
    if len(payload) != 2:
        raise InputError(f"NAK payload must be 2 bytes, got {len(payload)}")
    return payload[0], payload[1]


@dataclass(frozen=True)
class ControllerState:
    """Reply to STATE: per output (index order) power and shown pattern; stored pattern ids."""

    power: tuple[bool, ...]
    shown: tuple[int | None, ...]
    stored: tuple[int, ...]


def encode_state(state: ControllerState) -> bytes:
    if len(state.power) != len(state.shown):
        raise InputError("state: power and shown must have one entry per output")
    out = bytearray((len(state.power),))
    for p, s in zip(state.power, state.shown, strict=True):
        out += struct.pack(">BH", 1 if p else 0, NO_PATTERN if s is None else s)
    out += struct.pack(">H", len(state.stored))
    for pid in state.stored:
        out += struct.pack(">H", pid)
    return bytes(out)


def parse_state(data: bytes) -> ControllerState:
    """Parse the data of an ACK to STATE; raises :class:`InputError` when malformed."""
    try:
        n = data[0]
        pos = 1
        powers, shown = [], []
        for _ in range(n):
            p, s = struct.unpack_from(">BH", data, pos)
            pos += 3
            if p not in (0, 1):
                raise InputError(f"state: power flag {p} is not 0 or 1")
            powers.append(bool(p))
            shown.append(None if s == NO_PATTERN else s)
        (m,) = struct.unpack_from(">H", data, pos)
        pos += 2
        stored = struct.unpack_from(f">{m}H", data, pos)
        pos += 2 * m
    except (IndexError, struct.error):
        raise InputError(f"state reply of {len(data)} bytes is truncated") from None
    if pos != len(data):
        raise InputError(f"state reply has {len(data) - pos} trailing bytes")
    return ControllerState(power=tuple(powers), shown=tuple(shown), stored=tuple(stored))


@dataclass(frozen=True)
class PatternInfo:
    """Reply to PATTERN_INFO: size in pixels and CRC-32 of the stored RGB8 bytes."""

    width: int
    height: int
    crc32: int


def encode_pattern_info(info: PatternInfo) -> bytes:
    return struct.pack(">HHI", info.width, info.height, info.crc32)


def parse_pattern_info(data: bytes) -> PatternInfo:
    if len(data) != 8:
        raise InputError(f"pattern info reply must be 8 bytes, got {len(data)}")
    return PatternInfo(*struct.unpack(">HHI", data))


# --------------------------------------------------------------------------- patterns


def pattern_bytes(image_rgb8) -> tuple[int, int, bytes]:
    """Validate a pattern image and return ``(width, height, row-major RGB bytes)``.

    Parameters
    ----------
    image_rgb8 : array (rows, cols, 3), uint8
    """
    a = np.asarray(image_rgb8)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ShapeError(f"pattern has shape {a.shape}, expected (rows, cols, 3)")
    if a.dtype != np.uint8:
        raise ShapeError(f"pattern has dtype {a.dtype}, expected uint8 (RGB8)")
    return int(a.shape[1]), int(a.shape[0]), np.ascontiguousarray(a).tobytes()


def pattern_chunks(nbytes: int, chunk: int) -> Iterator[tuple[int, int]]:
    """``(offset, length)`` of the chunks covering ``nbytes`` bytes."""
    if not 1 <= chunk <= MAX_CHUNK:
        raise InputError(f"chunk size must be 1..{MAX_CHUNK} bytes, got {chunk}")
    for off in range(0, nbytes, chunk):
        yield off, min(chunk, nbytes - off)


def nearest_resize(image, width: int, height: int) -> np.ndarray:
    """Scale an (rows, cols, C) image to (height, width, C) by nearest neighbour, as the
    panel does: output pixel ``j`` samples input ``floor((j + 0.5) * cols / width)``."""
    a = np.asarray(image)
    rows, cols = a.shape[:2]
    yi = np.minimum(((np.arange(height) + 0.5) * rows / height).astype(np.int64), rows - 1)
    xi = np.minimum(((np.arange(width) + 0.5) * cols / width).astype(np.int64), cols - 1)
    return a[yi][:, xi]
