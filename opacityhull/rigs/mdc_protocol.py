"""Samsung MDC (Multiple Display Control) wire protocol: pure encode/parse, no I/O.

The control port of signage displays (RS-232C, 9600 8N1, or TCP port 1515). Source:
*Multiple Display Control Protocol*, Samsung Electronics (SEC-VD-DSW), Ver. 13.7c,
2016-02-23, section 1.2.1 and the per-command pages; ``docs/mdc-protocol.md`` lists the
facts used here and where each comes from. Frames, both directions::

    host -> panel   0xAA  CMD   ID  LEN  DATA[LEN]                  CHECKSUM
    panel -> host   0xAA  0xFF  ID  LEN  'A'|'N'  r-CMD  VAL[LEN-2]  CHECKSUM

``CHECKSUM`` is the sum of every byte after the header, modulo 256 (the document's
example: Power On to ID 0xFE is ``AA 11 FE 01 01`` and ``11+FE+01+01 = 111`` gives the
checksum ``11``). An ACK (``'A'`` = 0x41) echoes the command and carries its values; a
NAK (``'N'`` = 0x4E) carries one error byte. ID 0xFE addresses every panel on the
daisy chain, and no panel answers it — a driver that must know the command arrived
never uses it. A GET is the command with no data; a SET carries the new value(s) and
is acknowledged with the value now in force.

The protocol has no sequence numbers: every command here states an absolute value
(power on, brightness 50), so resending after a lost reply is safe.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "HEADER",
    "REPLY_CMD",
    "ACK",
    "NAK",
    "BROADCAST_ID",
    "MAX_DISPLAY_ID",
    "CMD_STATUS",
    "CMD_VIDEO",
    "CMD_SERIAL",
    "CMD_ERROR_STATUS",
    "CMD_SW_VERSION",
    "CMD_MODEL_NUMBER",
    "CMD_POWER",
    "CMD_INPUT",
    "CMD_CONTRAST",
    "CMD_BRIGHTNESS",
    "CMD_AUTO_LAMP",
    "CMD_MANUAL_LAMP",
    "CMD_SAFETY_LOCK",
    "CMD_MODEL_NAME",
    "CMD_ENERGY_SAVING",
    "COMMAND_NAMES",
    "INPUT_SOURCES",
    "ENERGY_SAVING",
    "Command",
    "Reply",
    "BadFrame",
    "ErrorStatus",
    "checksum",
    "check_display_id",
    "encode_command",
    "encode_reply",
    "FrameParser",
    "parse_error_status",
]

HEADER = 0xAA
REPLY_CMD = 0xFF
ACK = ord("A")
NAK = ord("N")
#: Every panel of the chain obeys; none answers.
BROADCAST_ID = 0xFE
#: Highest ID a single panel can be addressed by (0xFE is the broadcast; old models
#: answer ID 0 as 0xFF, which this driver does not use).
MAX_DISPLAY_ID = 0xFD

CMD_STATUS = 0x00
CMD_VIDEO = 0x04
CMD_SERIAL = 0x0B
CMD_ERROR_STATUS = 0x0D
CMD_SW_VERSION = 0x0E
CMD_MODEL_NUMBER = 0x10
CMD_POWER = 0x11
CMD_INPUT = 0x14
CMD_CONTRAST = 0x24
CMD_BRIGHTNESS = 0x25
CMD_AUTO_LAMP = 0x57
CMD_MANUAL_LAMP = 0x58
CMD_SAFETY_LOCK = 0x5D
CMD_MODEL_NAME = 0x8A
CMD_ENERGY_SAVING = 0x92

COMMAND_NAMES = {
    CMD_STATUS: "STATUS",
    CMD_VIDEO: "VIDEO",
    CMD_SERIAL: "SERIAL NUMBER",
    CMD_ERROR_STATUS: "DISPLAY STATUS",
    CMD_SW_VERSION: "SW VERSION",
    CMD_MODEL_NUMBER: "MODEL NUMBER",
    CMD_POWER: "POWER",
    CMD_INPUT: "INPUT SOURCE",
    CMD_CONTRAST: "CONTRAST",
    CMD_BRIGHTNESS: "BRIGHTNESS",
    CMD_AUTO_LAMP: "AUTO LAMP",
    CMD_MANUAL_LAMP: "MANUAL LAMP",
    CMD_SAFETY_LOCK: "SAFETY LOCK",
    CMD_MODEL_NAME: "MODEL NAME",
    CMD_ENERGY_SAVING: "ENERGY SAVING",
}

#: Input source codes (name as in the rig TOML -> code).
INPUT_SOURCES = {
    "pc": 0x14,
    "dvi": 0x18,
    "hdmi1": 0x21,
    "hdmi1_pc": 0x22,
    "hdmi2": 0x23,
    "hdmi2_pc": 0x24,
    "displayport1": 0x25,
    "displayport2": 0x26,
    "hdmi3": 0x31,
    "hdmi3_pc": 0x32,
    "hdmi4": 0x33,
    "hdmi4_pc": 0x34,
}

#: Energy saving (the panel dims itself with the ambient light or on a schedule):
#: anything but ``off`` changes the backdrop's radiance between shots.
ENERGY_SAVING = {"off": 0x00, "low": 0x01, "medium": 0x02, "high": 0x03, "picture_off": 0x04}


@dataclass(frozen=True)
class Command:
    """A host -> panel frame."""

    cmd: int
    display_id: int
    data: bytes = b""

    @property
    def name(self) -> str:
        return COMMAND_NAMES.get(self.cmd, f"command 0x{self.cmd:02X}")


@dataclass(frozen=True)
class Reply:
    """A panel -> host frame: ``ack`` True for 'A'; ``data`` the values (ACK) or the
    error byte (NAK)."""

    display_id: int
    ack: bool
    rcmd: int
    data: bytes = b""


@dataclass(frozen=True)
class BadFrame:
    """Bytes the parser rejected: ``noise`` (no header), ``checksum``, ``reply`` (an
    0xFF frame too short for 'A'/'N' and r-CMD, or neither 'A' nor 'N')."""

    reason: str
    data: bytes


def checksum(body: bytes | bytearray) -> int:
    """Sum of ``body`` (every byte after the 0xAA header) modulo 256."""
    return sum(body) & 0xFF


def check_display_id(display_id: object, *, where: str = "display id") -> int:
    """The ID of one panel, 0..0xFD; :class:`InputError` naming ``where`` otherwise
    (0xFE is the broadcast ID, which no panel acknowledges)."""
    if isinstance(display_id, bool) or not isinstance(display_id, int) or not 0 <= display_id <= MAX_DISPLAY_ID:
        extra = " (0xFE = 254 is the broadcast ID: no panel answers it)" if display_id == BROADCAST_ID else ""
        raise InputError(f"{where}: MDC display id must be an integer 0..{MAX_DISPLAY_ID}, got {display_id!r}{extra}")
    return display_id


def _u8(what: str, v: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
        raise InputError(f"MDC {what}: expected a byte 0..255, got {v!r}")
    return v


def encode_command(cmd: int, display_id: int, data: bytes = b"") -> bytes:
    """``AA CMD ID LEN DATA CHECKSUM`` (``display_id`` may be the broadcast 0xFE here)."""
    _u8("command", cmd)
    _u8("display id", display_id)
    if len(data) > 255:
        raise InputError(f"MDC {COMMAND_NAMES.get(cmd, hex(cmd))}: {len(data)} data bytes, at most 255")
    body = bytes((cmd, display_id, len(data))) + bytes(data)
    return bytes((HEADER,)) + body + bytes((checksum(body),))


def encode_reply(display_id: int, rcmd: int, data: bytes = b"", *, ack: bool = True) -> bytes:
    """``AA FF ID LEN 'A'|'N' r-CMD DATA CHECKSUM`` (the emulator's side)."""
    payload = bytes((ACK if ack else NAK, _u8("r-CMD", rcmd))) + bytes(data)
    return encode_command(REPLY_CMD, display_id, payload)


class FrameParser:
    """Incremental decoder of MDC frames (either direction).

    ``feed(bytes)`` returns the :class:`Command`, :class:`Reply` and :class:`BadFrame`
    items complete so far; a partial frame stays buffered. A frame that fails its
    checksum is reported and scanning restarts at the byte after its header, so a
    valid frame hidden behind noise that contains 0xAA is still found.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def reset(self) -> None:
        self._buf.clear()

    def _complete_frame_after(self, start: int) -> int | None:
        buf = self._buf
        j = buf.find(HEADER, start + 1)
        while j >= 0:
            if len(buf) - j >= 5 and len(buf) - j >= 5 + buf[j + 3]:
                end = j + 5 + buf[j + 3]
                if checksum(buf[j + 1 : end - 1]) == buf[end - 1]:
                    return j
            j = buf.find(HEADER, j + 1)
        return None

    def feed(self, data: bytes) -> list[Command | Reply | BadFrame]:
        self._buf += data
        out: list[Command | Reply | BadFrame] = []
        buf = self._buf
        while buf:
            start = buf.find(HEADER)
            if start < 0:
                out.append(BadFrame("noise", bytes(buf)))
                buf.clear()
                break
            if start > 0:
                out.append(BadFrame("noise", bytes(buf[:start])))
                del buf[:start]
            if len(buf) < 4 or len(buf) < 5 + buf[3]:
                # A header in noise can claim a length that is not there yet; a complete,
                # valid frame further on wins over waiting for it.
                later = self._complete_frame_after(0)
                if later is None:
                    break
                out.append(BadFrame("noise", bytes(buf[:later])))
                del buf[:later]
                continue
            n = buf[3]
            raw = bytes(buf[: 5 + n])
            if checksum(raw[1:-1]) != raw[-1]:
                out.append(BadFrame("checksum", raw))
                del buf[:1]
                continue
            del buf[: 5 + n]
            cmd, did, payload = raw[1], raw[2], raw[4:-1]
            if cmd != REPLY_CMD:
                out.append(Command(cmd, did, payload))
            elif len(payload) < 2 or payload[0] not in (ACK, NAK):
                out.append(BadFrame("reply", raw))
            else:
                out.append(Reply(did, payload[0] == ACK, payload[1], payload[2:]))
        return out


@dataclass(frozen=True)
class ErrorStatus:
    """Reply of DISPLAY STATUS (0x0D): error flags and the panel temperature.

    Attributes
    ----------
    lamp_error, temperature_error : bool
    brightness_sensor : str
        ``none`` (the panel has no ambient-light sensor), ``error`` or ``normal``.
    no_sync : bool
        The input has no signal or an unsupported resolution (a video output that is
        not running, or the wrong input source).
    temperature_c : int
        Panel temperature, °C.
    fan : str
        ``normal``, ``error`` or ``none`` (no fan).
    """

    lamp_error: bool
    temperature_error: bool
    brightness_sensor: str
    no_sync: bool
    temperature_c: int
    fan: str

    def encode(self) -> bytes:
        sensor = {"none": 0, "error": 1, "normal": 2}[self.brightness_sensor]
        fan = {"normal": 0, "error": 1, "none": 2}[self.fan]
        return bytes(
            (int(self.lamp_error), int(self.temperature_error), sensor, int(self.no_sync), self.temperature_c, fan)
        )


def parse_error_status(data: bytes) -> ErrorStatus:
    """:class:`ErrorStatus` from the 6 values of a DISPLAY STATUS ACK."""
    if len(data) < 6:
        raise InputError(f"MDC DISPLAY STATUS: expected 6 values, got {len(data)} ({data.hex(' ')})")
    sensor = {0: "none", 1: "error", 2: "normal"}.get(data[2], f"0x{data[2]:02X}")
    fan = {0: "normal", 1: "error", 2: "none"}.get(data[5], f"0x{data[5]:02X}")
    return ErrorStatus(
        lamp_error=data[0] == 1,
        temperature_error=data[1] == 1,
        brightness_sensor=sensor,
        no_sync=data[3] == 1,
        temperature_c=data[4],
        fan=fan,
    )
