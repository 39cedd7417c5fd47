"""Enttec DMX USB Pro wire protocol (API 1.44): pure framing encode/parse, no I/O.

Every message, both ways, is framed as::

    0x7E  label  len_lsb  len_msb  data[len]  0xE7

with ``len`` in 0..600. Labels used here: 3 *Get Widget Parameters* (request: 2 bytes,
user-configuration size LSB/MSB; reply: firmware version LSB, MSB, DMX break time and
mark-after-break time in 10.67 µs units, output rate in packets/s, then the requested
user-configuration bytes), 4 *Set Widget Parameters*, 6 *Output Only Send DMX Packet*
(data = start code — 0 for dimmer data — followed by 24..512 channel levels, channel 1
first) and 10 *Get Widget Serial Number* (reply: 4 bytes, BCD, least significant first).
The widget ignores messages it does not support and never acknowledges a DMX packet: the
protocol has no checksum and DMX output is fire-and-forget.

:class:`FrameParser` decodes a byte stream incrementally, skips noise, reports bad
frames and re-synchronises: when a candidate frame turns out bad (length over 600, wrong
end byte) it rescans from the byte after that candidate's start, so a valid frame hidden
inside a corrupt one is still found. Without a checksum, noise that itself contains a
start byte, a plausible header and an end byte at just the right distance is
indistinguishable from a frame; noise without a 0x7E byte can never hide a valid frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from ..errors import InputError
from .transport import ProtocolError

log = logging.getLogger(__name__)

__all__ = [
    "START",
    "END",
    "MAX_DATA",
    "LABEL_GET_PARAMS",
    "LABEL_SET_PARAMS",
    "LABEL_RECEIVED_DMX",
    "LABEL_SEND_DMX",
    "LABEL_GET_SERIAL",
    "LABEL_NAMES",
    "DMX_CHANNELS",
    "MIN_DMX_CHANNELS",
    "TIME_UNIT_US",
    "Frame",
    "BadFrame",
    "WidgetParameters",
    "encode",
    "encode_send_dmx",
    "encode_get_widget_parameters",
    "encode_widget_parameters_reply",
    "encode_set_widget_parameters",
    "encode_get_serial",
    "encode_serial_reply",
    "parse_widget_parameters",
    "parse_serial",
    "decode_one",
    "FrameParser",
]

START = 0x7E
END = 0xE7
MAX_DATA = 600
LABEL_GET_PARAMS = 3
LABEL_SET_PARAMS = 4
LABEL_RECEIVED_DMX = 5
LABEL_SEND_DMX = 6
LABEL_GET_SERIAL = 10
LABEL_NAMES = {
    1: "Reprogram Firmware",
    2: "Program Flash Page",
    3: "Get Widget Parameters",
    4: "Set Widget Parameters",
    5: "Received DMX Packet",
    6: "Output Only Send DMX Packet",
    7: "Send RDM Packet",
    8: "Receive DMX on Change",
    9: "Received DMX Change Of State",
    10: "Get Widget Serial Number",
    11: "Send RDM Discovery Request",
}
#: Channels in one DMX512 universe.
DMX_CHANNELS = 512
#: Shortest DMX packet the widget accepts (label 6 data length 25..513 with the start code).
MIN_DMX_CHANNELS = 24
#: Unit of the break and mark-after-break times, microseconds.
TIME_UNIT_US = 10.67


@dataclass(frozen=True)
class Frame:
    """One well-formed message."""

    label: int
    data: bytes

    @property
    def label_name(self) -> str:
        return LABEL_NAMES.get(self.label, f"label {self.label}")


@dataclass(frozen=True)
class BadFrame:
    """Bytes the parser rejected, and why (``noise``: no start byte; ``length``: header
    claims more than 600 bytes; ``end``: no 0xE7 where the length says it must be)."""

    reason: str
    data: bytes


@dataclass(frozen=True)
class WidgetParameters:
    """Reply to Get Widget Parameters (label 3).

    Attributes
    ----------
    firmware : (msb, lsb); msb 1 = normal DMX firmware, 2 = RDM, 3 = RDM sniffer.
    break_time : DMX break, 10.67 µs units (9..127).
    mab_time : mark after break, 10.67 µs units (1..127).
    rate_hz : DMX output rate, packets/s (1..40; 0 = as fast as possible).
    user_config : the user configuration bytes requested.
    """

    firmware: tuple[int, int]
    break_time: int
    mab_time: int
    rate_hz: int
    user_config: bytes = b""

    @property
    def firmware_version(self) -> str:
        return f"{self.firmware[0]}.{self.firmware[1]}"

    @property
    def break_us(self) -> float:
        return self.break_time * TIME_UNIT_US

    @property
    def mab_us(self) -> float:
        return self.mab_time * TIME_UNIT_US


def _u8(name: str, v, lo: int = 0, hi: int = 255) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise InputError(f"{name} = {v!r}, expected an integer {lo}..{hi}")
    return v


def encode(label: int, data: bytes = b"") -> bytes:
    """``0x7E label len_lsb len_msb data 0xE7``."""
    _u8("Enttec label", label)
    data = bytes(data)
    if len(data) > MAX_DATA:
        raise InputError(f"Enttec message data is {len(data)} bytes, at most {MAX_DATA} allowed")
    n = len(data)
    return bytes((START, label, n & 0xFF, n >> 8)) + data + bytes((END,))


def encode_send_dmx(levels: bytes, *, start_code: int = 0, min_channels: int = MIN_DMX_CHANNELS) -> bytes:
    """Label 6 with ``start_code`` then the channel levels (channel 1 first), zero-padded to
    ``min_channels`` (the widget ignores shorter packets)."""
    _u8("DMX start code", start_code)
    try:
        levels = bytes(levels)
    except (TypeError, ValueError):
        raise InputError("DMX levels must be bytes or integers 0..255") from None
    if len(levels) > DMX_CHANNELS:
        raise InputError(f"{len(levels)} DMX channels given; a universe has {DMX_CHANNELS}")
    if len(levels) < min_channels:
        levels = levels + bytes(min_channels - len(levels))
    return encode(LABEL_SEND_DMX, bytes((start_code,)) + levels)


def encode_get_widget_parameters(user_config_size: int = 0) -> bytes:
    """Label 3 request: 2-byte size (LSB, MSB) of the user configuration to return (0..508)."""
    _u8("user configuration size", user_config_size, 0, 508)
    return encode(LABEL_GET_PARAMS, bytes((user_config_size & 0xFF, user_config_size >> 8)))


def encode_widget_parameters_reply(p: WidgetParameters) -> bytes:
    """Label 3 reply (what the widget — or the emulator — sends)."""
    msb, lsb = p.firmware
    data = bytes(
        (
            _u8("firmware lsb", lsb),
            _u8("firmware msb", msb),
            _u8("break time", p.break_time),
            _u8("MAB time", p.mab_time),
            _u8("rate", p.rate_hz),
        )
    ) + bytes(p.user_config)
    return encode(LABEL_GET_PARAMS, data)


def encode_set_widget_parameters(
    break_time: int = 9, mab_time: int = 1, rate_hz: int = 40, user_config: bytes = b""
) -> bytes:
    """Label 4: user-config size LSB/MSB, break time, MAB time, rate, user config."""
    _u8("break time", break_time, 9, 127)
    _u8("MAB time", mab_time, 1, 127)
    _u8("rate", rate_hz, 0, 40)
    n = len(user_config)
    return encode(LABEL_SET_PARAMS, bytes((n & 0xFF, n >> 8, break_time, mab_time, rate_hz)) + bytes(user_config))


def encode_get_serial() -> bytes:
    """Label 10 request (no data)."""
    return encode(LABEL_GET_SERIAL)


def encode_serial_reply(serial_bcd: int) -> bytes:
    """Label 10 reply for a serial such as 0x12345678 (BCD digits "12345678")."""
    if isinstance(serial_bcd, bool) or not isinstance(serial_bcd, int) or not 0 <= serial_bcd <= 0xFFFFFFFF:
        raise InputError(f"serial number {serial_bcd!r} must fit in 4 bytes")
    return encode(LABEL_GET_SERIAL, serial_bcd.to_bytes(4, "little"))


def parse_widget_parameters(frame: Frame) -> WidgetParameters:
    """Decode a label-3 reply; :class:`ProtocolError` quoting the bytes if it is not one."""
    if frame.label != LABEL_GET_PARAMS or len(frame.data) < 5:
        raise ProtocolError(
            f"not a Get Widget Parameters reply: label {frame.label}, data {frame.data!r} "
            "(expected label 3 with at least 5 bytes)"
        )
    d = frame.data
    return WidgetParameters(
        firmware=(d[1], d[0]), break_time=d[2], mab_time=d[3], rate_hz=d[4], user_config=bytes(d[5:])
    )


def parse_serial(frame: Frame) -> str:
    """Decode a label-10 reply to its printed form (BCD, most significant digit first)."""
    if frame.label != LABEL_GET_SERIAL or len(frame.data) != 4:
        raise ProtocolError(
            f"not a Get Widget Serial Number reply: label {frame.label}, data {frame.data!r} "
            "(expected label 10 with 4 bytes)"
        )
    return "".join(f"{b:02x}" for b in reversed(frame.data))


def decode_one(data: bytes) -> Frame:
    """Exactly one frame and nothing else, or :class:`ProtocolError`."""
    p = FrameParser()
    frames = p.feed(data)
    if len(frames) != 1 or p.bad or p.pending:
        raise ProtocolError(
            f"{bytes(data)[:40]!r} is not exactly one Enttec frame "
            f"({len(frames)} frames, {len(p.bad)} bad, {p.pending} bytes pending)"
        )
    return frames[0]


class FrameParser:
    """Incremental Enttec frame decoder that re-synchronises on garbage.

    :meth:`feed` returns the complete frames found so far; rejected bytes go to
    :attr:`bad` (a bounded list) and are counted in :attr:`bad_count`. A frame whose
    bytes have not all arrived stays :attr:`pending`; :meth:`abandon` gives up on it (a
    reader that timed out) and rescans what was buffered.
    """

    def __init__(self, *, max_bad: int = 256):
        self._buf = bytearray()
        self.bad: list[BadFrame] = []
        self.bad_count = 0
        self.frames_count = 0
        self._max_bad = max_bad

    @property
    def pending(self) -> int:
        """Bytes buffered for an incomplete frame."""
        return len(self._buf)

    def _reject(self, reason: str, data: bytes | bytearray) -> None:
        self.bad_count += 1
        if len(self.bad) < self._max_bad:
            self.bad.append(BadFrame(reason, bytes(data)))

    def feed(self, data: bytes) -> list[Frame]:
        self._buf += data
        return self._scan(final=False)

    def abandon(self) -> list[Frame]:
        """Treat the buffered incomplete frame as bad and rescan after its start byte."""
        return self._scan(final=True)

    def _scan(self, *, final: bool) -> list[Frame]:
        out: list[Frame] = []
        buf = self._buf
        while buf:
            i = buf.find(START)
            if i < 0:
                self._reject("noise", buf)
                buf.clear()
                break
            if i > 0:
                self._reject("noise", buf[:i])
                del buf[:i]
            if len(buf) < 4:
                if final:
                    self._reject("end", buf[:1])
                    del buf[:1]
                    continue
                break
            n = buf[2] | (buf[3] << 8)
            if n > MAX_DATA:
                self._reject("length", buf[:4])
                del buf[:1]
                continue
            if len(buf) < n + 5:
                if final:
                    self._reject("end", buf[: n + 5])
                    del buf[:1]
                    continue
                break
            if buf[n + 4] != END:
                self._reject("end", buf[: n + 5])
                del buf[:1]  # a real frame may start inside this one
                continue
            out.append(Frame(buf[1], bytes(buf[4 : n + 4])))
            self.frames_count += 1
            del buf[: n + 5]
        return out
