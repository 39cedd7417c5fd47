"""GRBL 1.1 wire protocol: pure encoders and parsers, no I/O.

GRBL talks in lines terminated by ``\\r\\n``. The host sends G-code blocks and ``$``
system commands, one per line, and waits for one *response* per line — ``ok`` or
``error:N``. Everything else GRBL prints is a *push message* that may come at any time:
status reports ``<Idle|MPos:0.000,0.000,0.000|FS:0,0>`` (answers to the real-time
``?``), ``ALARM:N``, the welcome banner ``Grbl 1.1h ['$' for help]`` (after power-up or
a soft reset), ``$N=value`` settings (answer to ``$$``), and bracketed feedback such as
``[MSG:Caution: Unlocked]``, ``[GC:...]`` (``$G``), ``[VER:...]``/``[OPT:...]`` (``$I``).
Real-time commands are single bytes that GRBL picks out of the stream at once, even in
the middle of a line: ``?`` status, ``!`` feed hold, ``~`` cycle start/resume, ``0x18``
(Ctrl-X) soft reset, ``0x85`` jog cancel.

In opacityhull the G-code unit is the degree: ``$100`` is steps per degree, ``$110``
the maximum rate in degrees per minute, ``$120`` the acceleration in degrees/s².

Every parser raises :class:`~opacityhull.rigs.transport.ProtocolError` quoting the
offending bytes; every encoder validates its inputs and raises
:class:`~opacityhull.errors.InputError` before producing a byte.
"""

from __future__ import annotations

import logging
import math
import numbers
import re
from dataclasses import dataclass, field
from collections.abc import Mapping

from ..errors import InputError
from .transport import ProtocolError

log = logging.getLogger(__name__)

__all__ = [
    "AXES",
    "STATES",
    "ERROR_CODES",
    "ALARM_CODES",
    "CRITICAL_ALARMS",
    "STATUS_QUERY",
    "FEED_HOLD",
    "CYCLE_START",
    "SOFT_RESET",
    "JOG_CANCEL",
    "LINE_BUFFER_SIZE",
    "MAX_ABS_COORD",
    "Ok",
    "GrblError",
    "Alarm",
    "Banner",
    "Message",
    "Setting",
    "StartupLine",
    "Status",
    "error_meaning",
    "alarm_meaning",
    "encode_line",
    "move_abs",
    "unlock",
    "home",
    "get_settings",
    "set_setting",
    "build_info",
    "parser_state",
    "format_number",
    "parse_response",
    "parse_status",
    "parse_settings",
]

#: Axis letters in the order GRBL reports positions.
AXES = "XYZABC"
#: Machine states of a GRBL 1.1 status report.
STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")

STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
SOFT_RESET = b"\x18"
JOG_CANCEL = b"\x85"

#: GRBL's serial line buffer; longer lines are rejected with error:11.
LINE_BUFFER_SIZE = 80
#: Largest coordinate we send. GRBL parses numbers into 32-bit floats; beyond ~1e5 the
#: 0.001° resolution of a status report is no longer representable.
MAX_ABS_COORD = 1.0e5

# Code -> (short name, description, what to check). The first two columns follow
# grbl/doc/csv/error_codes_en_US.csv and alarm_codes_en_US.csv (GRBL 1.1); ALARM:10 is
# the dual-axis homing alarm of 1.1g+; the hints are ours, for a rotary rig.
ERROR_CODES: dict[int, tuple[str, str, str]] = {
    1: (
        "Expected command letter",
        "G-code words consist of a letter and a value; the letter was not found",
        "the line sent is not G-code — check what the driver wrote",
    ),
    2: (
        "Bad number format",
        "missing the expected G-code word value or the numeric format is not valid",
        "a number in the line is malformed (e.g. 'X1.2.3' or 'X'); check the value sent",
    ),
    3: (
        "Invalid statement",
        "GRBL '$' system command was not recognized or supported",
        "the '$' command or setting number is not supported by this firmware",
    ),
    4: (
        "Value < 0",
        "negative value received for an expected positive value",
        "settings such as steps per degree, rates and accelerations must be positive",
    ),
    5: (
        "Setting disabled",
        "homing cycle is not enabled via settings",
        "enable homing with $22=1 (and fit a home switch) or do not call home()",
    ),
    6: ("Value < 3 usec", "minimum step pulse time must be greater than 3 microseconds", "set $0 to 3 or more"),
    7: (
        "EEPROM read fail",
        "an EEPROM read failed; settings were restored to defaults",
        "the controller lost its settings: re-apply them ($$) and check its power supply",
    ),
    8: (
        "Not idle",
        "GRBL '$' command cannot be used unless GRBL is IDLE",
        "wait for the move to finish (or stop and reset) before changing settings or homing",
    ),
    9: (
        "G-code lock",
        "G-code commands are locked out during alarm or jog state",
        "clear the alarm first: home() ($H) or unlock ($X)",
    ),
    10: ("Homing not enabled", "soft limits cannot be enabled without homing also enabled", "set $22=1 before $20=1"),
    11: (
        "Line overflow",
        "max characters per line exceeded; the line was not executed",
        f"keep lines under {LINE_BUFFER_SIZE} characters",
    ),
    12: (
        "Step rate > 30kHz",
        "the '$' setting value makes the step rate exceed the maximum supported",
        "lower steps_per_deg x max_rate_deg_s below 30000 steps/s",
    ),
    13: (
        "Check Door",
        "safety door detected as opened and door state initiated",
        "close the enclosure door and resume",
    ),
    14: (
        "Line length exceeded",
        "build info or startup line exceeded the EEPROM line length limit",
        "shorten the stored line",
    ),
    15: (
        "Travel exceeded",
        "jog target exceeds machine travel; the command was ignored",
        "check the jog target against $130-$132",
    ),
    16: (
        "Invalid jog command",
        "jog command has no '=' or contains prohibited g-code",
        "jog lines look like '$J=G91 X10 F600'",
    ),
    17: (
        "Setting disabled",
        "laser mode requires PWM output",
        "this firmware build has no variable spindle; leave $32=0",
    ),
    20: (
        "Unsupported command",
        "unsupported or invalid g-code command found in block",
        "the controller does not know this G/M code or axis letter; check the axis configured for this device",
    ),
    21: (
        "Modal group violation",
        "more than one g-code command from the same modal group found in block",
        "send one motion mode (G0/G1) per line",
    ),
    22: ("Undefined feed rate", "feed rate has not yet been set or is undefined", "G1 needs an F word"),
    23: ("Invalid gcode ID:23", "g-code command in block requires an integer value", "check the G/M number"),
    24: (
        "Invalid gcode ID:24",
        "more than one g-code command that requires axis words found in block",
        "split the line",
    ),
    25: ("Invalid gcode ID:25", "repeated g-code word found in block", "each word once per line"),
    26: (
        "Invalid gcode ID:26",
        "no axis words found in block for g-code command or current modal state which requires them",
        "add the axis word",
    ),
    27: ("Invalid gcode ID:27", "line number value is invalid", "N must be 1..9999999"),
    28: ("Invalid gcode ID:28", "g-code command is missing a required value word", "e.g. G4 needs P"),
    29: ("Invalid gcode ID:29", "G59.x work coordinate systems are not supported", "use G54-G59"),
    30: ("Invalid gcode ID:30", "G53 only allowed with G0 and G1 motion modes", "use G53 with G0/G1"),
    31: (
        "Invalid gcode ID:31",
        "axis words found in block when no command or current modal state uses them",
        "G80 is active: give a motion mode",
    ),
    32: ("Invalid gcode ID:32", "G2 and G3 arcs require at least one in-plane axis word", "fix the arc"),
    33: ("Invalid gcode ID:33", "motion command target is invalid", "fix the arc or probe target"),
    34: ("Invalid gcode ID:34", "arc radius value is invalid", "fix the arc"),
    35: ("Invalid gcode ID:35", "G2 and G3 arcs require at least one in-plane offset word", "fix the arc"),
    36: ("Invalid gcode ID:36", "unused value words found in block", "remove the extra words"),
    37: (
        "Invalid gcode ID:37",
        "G43.1 dynamic tool length offset is not assigned to the configured tool length axis",
        "not used by a rotary rig",
    ),
    38: ("Invalid gcode ID:38", "tool number greater than max supported value", "not used by a rotary rig"),
}

ALARM_CODES: dict[int, tuple[str, str, str]] = {
    1: (
        "Hard limit",
        "hard limit triggered; machine position is likely lost due to the sudden halt",
        "check the limit switch and its wiring (is something blocking the table?), then reset() and "
        "re-home ($H) or unlock ($X)",
    ),
    2: (
        "Soft limit",
        "G-code motion target exceeds machine travel; machine position retained",
        "check the commanded angle against soft_limits_deg and $130-$132, then reset() and unlock ($X)",
    ),
    3: (
        "Abort during cycle",
        "reset while in motion; machine position is likely lost",
        "something sent a soft reset (or the reset button was pressed) during a move: re-home ($H), or unlock "
        "($X) and verify the angle",
    ),
    4: (
        "Probe fail",
        "probe is not in the expected initial state before starting the probe cycle",
        "the rig does not probe: check what sent G38",
    ),
    5: (
        "Probe fail",
        "probe did not contact the workpiece within the programmed travel",
        "the rig does not probe: check what sent G38",
    ),
    6: ("Homing fail", "the active homing cycle was reset", "do not reset during homing; run $H again"),
    7: ("Homing fail", "safety door was opened during the homing cycle", "close the door and run $H again"),
    8: (
        "Homing fail",
        "pull-off travel failed to clear the limit switch",
        "increase the pull-off $27 or check the home switch wiring",
    ),
    9: (
        "Homing fail",
        "could not find the limit switch within the search distance",
        "check the home switch and its wiring, the seek rate $25 and the max travel $130-$132",
    ),
    10: (
        "Homing fail",
        "on dual-axis machines, could not find the second limit switch for self-squaring",
        "check the second home switch",
    ),
}

#: Alarms after which GRBL ignores everything (status queries included) until a soft reset.
CRITICAL_ALARMS = frozenset({1, 2})


def error_meaning(code: int) -> str:
    """``"Bad number format: missing the expected ..."`` for an ``error:N`` code."""
    if code in ERROR_CODES:
        short, desc, _ = ERROR_CODES[code]
        return f"{short}: {desc}"
    return f"unknown error code {code} (not a GRBL 1.1 code)"


def alarm_meaning(code: int) -> str:
    """``"Hard limit: hard limit triggered ..."`` for an ``ALARM:N`` code."""
    if code in ALARM_CODES:
        short, desc, _ = ALARM_CODES[code]
        return f"{short}: {desc}"
    return f"unknown alarm code {code} (not a GRBL 1.1 code)"


# ---------------------------------------------------------------------------- responses


@dataclass(frozen=True)
class Ok:
    """``ok``: the line was parsed and executed (or queued for execution)."""


@dataclass(frozen=True)
class GrblError:
    """``error:N``: the line was rejected and nothing in it was executed."""

    code: int
    meaning: str
    hint: str = ""


@dataclass(frozen=True)
class Alarm:
    """``ALARM:N`` push message: GRBL is now in the alarm state."""

    code: int
    meaning: str
    hint: str = ""

    @property
    def critical(self) -> bool:
        return self.code in CRITICAL_ALARMS


@dataclass(frozen=True)
class Banner:
    """Welcome message ``Grbl 1.1h ['$' for help]``: GRBL (re)initialised."""

    version: str
    text: str


@dataclass(frozen=True)
class Message:
    """Bracketed feedback ``[KIND:text]`` (``MSG``, ``GC``, ``VER``, ``OPT``, ``HLP``, ``G54`` ...)."""

    kind: str
    text: str


@dataclass(frozen=True)
class Setting:
    """``$N=value`` line of a ``$$`` print-out."""

    number: int
    value: float


@dataclass(frozen=True)
class StartupLine:
    """``>G54G20:ok``: a stored startup line ran (``ok``) or failed (``error:N``)."""

    line: str
    result: str


@dataclass(frozen=True)
class Status:
    """A real-time status report.

    Attributes
    ----------
    state : one of :data:`STATES`.
    substate : ``Hold:0``/``Door:1`` code, else None.
    mpos, wpos : axis letter -> position in G-code units (degrees here); GRBL sends
        exactly one of them (``$10`` bit 0).
    feed : current feed rate (units/min), or None when absent.
    spindle : spindle speed, or None.
    wco : work coordinate offset (``WPos = MPos - WCO``), when this report carries it.
    fields : every ``type:value`` field as text, for the rest (``Bf``, ``Ln``, ``Pn``, ``Ov``, ``A``).
    raw : the report line.
    """

    state: str
    substate: int | None
    mpos: dict | None
    wpos: dict | None
    feed: float | None = None
    spindle: float | None = None
    wco: dict | None = None
    fields: dict = field(default_factory=dict)
    raw: str = ""

    def position(self, wco: Mapping[str, float] | None = None, *, work: bool = True) -> dict:
        """Work (default) or machine position per axis, using this report's WCO or ``wco``."""
        off = self.wco if self.wco is not None else (wco or {})
        if self.mpos is None and self.wpos is None:
            raise ProtocolError(f"GRBL status {self.raw!r} has neither MPos nor WPos")
        if work:
            if self.wpos is not None:
                return dict(self.wpos)
            assert self.mpos is not None
            return {a: v - off.get(a, 0.0) for a, v in self.mpos.items()}
        if self.mpos is not None:
            return dict(self.mpos)
        assert self.wpos is not None
        return {a: v + off.get(a, 0.0) for a, v in self.wpos.items()}


# ---------------------------------------------------------------------------- encoders


def format_number(value: float, *, decimals: int = 3) -> str:
    """Fixed-point text GRBL's ``read_float`` accepts (no exponent, no ``-0.000``)."""
    text = f"{value:.{decimals}f}"
    if float(text) == 0.0:
        text = f"{0.0:.{decimals}f}"
    return text


def encode_line(line: str | bytes) -> bytes:
    """One command line as bytes with ``\\n``; rejects control characters, real-time bytes
    and lines GRBL would overflow on."""
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError:
            raise InputError(f"GRBL line {line!r} is not ASCII") from None
    if not isinstance(line, str):
        raise InputError(f"GRBL line must be a str, got {type(line).__name__}")
    line = line.rstrip("\r\n")
    bad = [c for c in line if ord(c) < 0x20 or ord(c) > 0x7E or c in "?!~"]
    if bad:
        raise InputError(
            f"GRBL line {line!r} contains {bad[0]!r}: control characters and the real-time bytes ? ! ~ "
            "would be executed by GRBL immediately, not as part of the line"
        )
    if len(line) >= LINE_BUFFER_SIZE:
        raise InputError(f"GRBL line {line!r} is {len(line)} characters; GRBL accepts at most {LINE_BUFFER_SIZE - 1}")
    return line.encode("ascii") + b"\n"


def _check_axis(axis: str) -> str:
    if not isinstance(axis, str) or len(axis) != 1 or axis.upper() not in AXES:
        raise InputError(f"GRBL axis {axis!r} is not one of {', '.join(AXES)}")
    return axis.upper()


def _check_coord(axis: str, value, limits: Mapping[str, tuple[float, float]] | None) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"axis {axis}: angle {value!r} is not a number of degrees")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"axis {axis}: angle {value!r} is not a finite number of degrees")
    if abs(v) > MAX_ABS_COORD:
        raise InputError(
            f"axis {axis}: angle {v} deg is beyond +-{MAX_ABS_COORD:g} deg, which GRBL cannot represent to 0.001 deg"
        )
    if limits is not None and axis in limits:
        lo, hi = limits[axis]
        if not lo <= v <= hi:
            raise InputError(f"axis {axis}: angle {v:g} deg is outside the soft range [{lo:g}, {hi:g}] deg")
    return v


def move_abs(
    axis_deg: Mapping[str, float],
    feed_deg_min: float | None = None,
    *,
    limits: Mapping[str, tuple[float, float]] | None = None,
    decimals: int = 3,
) -> bytes:
    """Absolute move ``G90 G0 X12.500`` (rapid, at ``$110``) or ``G90 G1 X12.500 F600.0``.

    Absolute moves make a retried command idempotent. Every angle is validated (finite,
    within ``limits`` [deg] per axis, within :data:`MAX_ABS_COORD`) before a byte exists.

    Parameters
    ----------
    axis_deg : axis letter -> target angle, degrees.
    feed_deg_min : feed rate for a G1 move, degrees per minute; None = rapid G0.
    limits : axis letter -> (min, max) degrees.
    """
    if not isinstance(axis_deg, Mapping) or not axis_deg:
        raise InputError(f"move_abs needs a non-empty mapping axis -> degrees, got {axis_deg!r}")
    words = []
    for axis in sorted(axis_deg, key=lambda a: AXES.index(_check_axis(a))):
        a = _check_axis(axis)
        v = _check_coord(a, axis_deg[axis], limits)
        words.append(f"{a}{format_number(v, decimals=decimals)}")
    if feed_deg_min is None:
        return encode_line("G90 G0 " + " ".join(words))
    if isinstance(feed_deg_min, bool) or not isinstance(feed_deg_min, numbers.Real):
        raise InputError(f"feed rate {feed_deg_min!r} is not a number of degrees/min")
    f = float(feed_deg_min)
    if not (math.isfinite(f) and f > 0):
        raise InputError(f"feed rate {feed_deg_min!r} must be a finite number > 0 degrees/min")
    return encode_line("G90 G1 " + " ".join(words) + f" F{format_number(f, decimals=1)}")


def unlock() -> bytes:
    """``$X``: kill the alarm lock (position is not re-established)."""
    return b"$X\n"


def home(axes: str = "") -> bytes:
    """``$H`` homing cycle (all axes), or ``$HX`` for one axis on builds with single-axis homing."""
    if axes:
        for a in axes:
            _check_axis(a)
        if len(axes) != 1:
            raise InputError(f"single-axis homing takes one axis letter, got {axes!r}")
    return f"$H{axes.upper()}\n".encode("ascii")


def get_settings() -> bytes:
    """``$$``: print every setting as ``$N=value`` lines, then ``ok``."""
    return b"$$\n"


def set_setting(number: int, value: float) -> bytes:
    """``$N=value`` (stored in EEPROM)."""
    if isinstance(number, bool) or not isinstance(number, int) or not 0 <= number <= 255:
        raise InputError(f"GRBL setting number {number!r} must be an integer 0..255")
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"GRBL setting ${number} value {value!r} is not a number")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"GRBL setting ${number} value {value!r} is not finite")
    return encode_line(f"${number}={format_number(v)}")


def build_info() -> bytes:
    """``$I``: ``[VER:...]`` and ``[OPT:...]`` then ``ok``."""
    return b"$I\n"


def parser_state() -> bytes:
    """``$G``: ``[GC:...]`` then ``ok``. Allowed in every state, so also used to resynchronise."""
    return b"$G\n"


# ---------------------------------------------------------------------------- parsers

_BANNER = re.compile(r"^Grbl(?:HAL)? (\S+) \[.*help\]$")
_NUMBER = re.compile(r"^[+-]?(?:\d+\.?\d*|\.\d+)$")


def _text(line: bytes | str) -> str:
    if isinstance(line, (bytes, bytearray)):
        try:
            text = bytes(line).decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError(f"GRBL reply {bytes(line)!r} is not ASCII — wrong baud rate or line noise?") from None
    else:
        text = line
    return text.strip("\r\n")


def _number(text: str, line) -> float:
    if not _NUMBER.match(text):
        raise ProtocolError(f"bad number {text!r} in GRBL reply {line!r}")
    return float(text)


def _code(text: str, line) -> int:
    if not text.isdigit() or len(text) > 3:
        raise ProtocolError(f"bad code {text!r} in GRBL reply {line!r}")
    return int(text)


def _vector(text: str, line) -> dict:
    parts = text.split(",")
    if not 1 <= len(parts) <= len(AXES):
        raise ProtocolError(f"position {text!r} in GRBL status {line!r} has {len(parts)} values, expected 1-6")
    return {AXES[i]: _number(p, line) for i, p in enumerate(parts)}


def parse_status(line: bytes | str) -> Status:
    """Parse ``<Idle|MPos:0.000,0.000,0.000|FS:0,0>`` into a :class:`Status`.

    Machine state and one position (``MPos`` or ``WPos``) are mandatory and come first;
    any other field may be present in any order.
    """
    text = _text(line)
    if not (text.startswith("<") and text.endswith(">")) or len(text) < 3:
        raise ProtocolError(f"GRBL status report {line!r} is not enclosed in <>")
    parts = text[1:-1].split("|")
    state, _, sub = parts[0].partition(":")
    if state not in STATES:
        raise ProtocolError(f"unknown machine state {parts[0]!r} in GRBL status {line!r}")
    substate = _code(sub, line) if sub else None
    mpos = wpos = wco = None
    feed = spindle = None
    fields: dict[str, str] = {}
    for part in parts[1:]:
        kind, sep, value = part.partition(":")
        if not sep or not kind:
            raise ProtocolError(f"field {part!r} of GRBL status {line!r} is not type:value")
        if kind in fields:
            raise ProtocolError(f"field {kind!r} repeated in GRBL status {line!r}")
        fields[kind] = value
        if kind == "MPos":
            mpos = _vector(value, line)
        elif kind == "WPos":
            wpos = _vector(value, line)
        elif kind == "WCO":
            wco = _vector(value, line)
        elif kind == "FS":
            fs = value.split(",")
            if len(fs) != 2:
                raise ProtocolError(f"FS field {value!r} of GRBL status {line!r} needs feed,speed")
            feed, spindle = _number(fs[0], line), _number(fs[1], line)
        elif kind == "F":
            feed = _number(value, line)
        elif kind in ("Bf", "Ov"):
            for v in value.split(","):
                _number(v, line)
        elif kind == "Ln":
            _number(value, line)
    if (mpos is None) == (wpos is None):
        raise ProtocolError(f"GRBL status {line!r} must carry exactly one of MPos/WPos")
    first = parts[1].partition(":")[0] if len(parts) > 1 else ""
    if first not in ("MPos", "WPos"):
        raise ProtocolError(f"GRBL status {line!r}: the position must be the second field")
    return Status(state, substate, mpos, wpos, feed, spindle, wco, fields, text)


def parse_response(line: bytes | str):
    """Classify one line GRBL sent.

    Returns
    -------
    Ok | GrblError | Alarm | Banner | Message | Setting | StartupLine | Status

    Raises
    ------
    ProtocolError
        Empty, non-ASCII or unrecognised lines (quoting the bytes).
    """
    text = _text(line)
    if not text:
        raise ProtocolError(f"empty GRBL reply {line!r}")
    if text == "ok":
        return Ok()
    if text.startswith("error:"):
        code = _code(text[6:], line)
        hint = ERROR_CODES.get(code, ("", "", ""))[2]
        return GrblError(code, error_meaning(code), hint)
    if text.startswith("ALARM:"):
        code = _code(text[6:], line)
        hint = ALARM_CODES.get(code, ("", "", ""))[2]
        return Alarm(code, alarm_meaning(code), hint)
    if text.startswith("<"):
        return parse_status(text)
    if text.startswith("[") and text.endswith("]"):
        kind, sep, body = text[1:-1].partition(":")
        if not sep or not kind or not kind.replace(".", "").replace("_", "").isalnum():
            raise ProtocolError(f"GRBL feedback message {line!r} is not [TYPE:text]")
        return Message(kind, body)
    if text.startswith("$"):
        key, sep, value = text[1:].partition("=")
        if sep and key.isdigit():
            return Setting(int(key), _number(value, line))
        if sep and key.startswith("N") and key[1:].isdigit():
            return Message(key, value)
        raise ProtocolError(f"GRBL setting line {line!r} is not $N=value")
    if text.startswith(">"):
        body, sep, result = text[1:].rpartition(":")
        if result == "ok":
            return StartupLine(body, "ok")
        body2, sep2, code = text[1:].rpartition(":error:")
        if sep2 and code.isdigit():
            return StartupLine(body2, f"error:{code}")
        raise ProtocolError(f"GRBL startup-line report {line!r} does not end in :ok or :error:N")
    m = _BANNER.match(text)
    if m:
        return Banner(m.group(1), text)
    raise ProtocolError(f"unrecognised GRBL reply {line!r}")


def parse_settings(lines) -> dict[int, float]:
    """``$$`` output (Setting objects or raw lines) -> ``{number: value}``; other lines are ignored."""
    out: dict[int, float] = {}
    for item in lines:
        r = item if isinstance(item, (Setting, Message, Ok)) else parse_response(item)
        if isinstance(r, Setting):
            out[r.number] = r.value
    return out
