"""GRBL 1.1h emulator: the same bytes as a real controller, with motion in (scaled) time.

What it models, following GRBL 1.1's documented interface:

* Real-time bytes picked out of the stream anywhere: ``?`` status report, ``!`` feed
  hold, ``~`` cycle start, ``0x18`` soft reset, ``0x85`` jog cancel (override bytes
  0x90-0xA5 are accepted and ignored).
* Lines end at ``\\n`` or ``\\r``; whitespace and ``( )``/``;`` comments are removed and
  letters upper-cased; an empty line answers ``ok`` (so a host sending ``\\r\\n`` gets
  two ``ok`` — as real GRBL does); lines of 80+ characters answer ``error:11``.
* G-code: G0, G1 (needs a feed: ``error:22``), G4 dwell, G17-19, G20/G21 (inches are
  converted), G53, G54-G59 (all offsets zero), G80, G90/G91, G94, M0-M9/M30, F, N, P,
  S, T and axis words for the configured axes. Unknown codes or letters ``error:20``,
  a second code of one modal group ``error:21``, repeated words ``error:25``, a missing
  letter ``error:1``, malformed numbers ``error:2``, negative F/P/N ``error:4``. Arcs
  (G2/G3), probing, G10/G28/G30/G92 are not emulated (``error:20``).
* ``$`` commands: ``$`` help, ``$$``, ``$#``, ``$G``, ``$I``, ``$N``, ``$x=val`` (with the
  checks for error:2/3/4/6/8/10/12), ``$X``, ``$H`` and ``$HX`` (single-axis homing, build
  option ``H``), ``$C`` check mode, ``$SLP``, ``$RST=``, ``$J=`` jogging.
* States Idle, Run, Hold:1 → Hold:0 (deceleration takes v/a), Jog, Home, Alarm, Door,
  Check, Sleep. Moves follow a trapezoid velocity profile limited per axis by $110 and
  $120; positions are integer steps ($100). ``time_scale`` = 0 makes every move, dwell
  and homing instant.
* Soft reset while moving (Run/Jog/Hold:1) → ``ALARM:3`` (during homing ``ALARM:6``),
  then the banner and ``[MSG:'$H'|'$X' to unlock]``; the step counters keep the
  position where the pulses stopped. A reset from Hold:0 cancels the motion without an
  alarm. With ``$22=1`` the controller powers up locked in Alarm (HOMING_INIT_LOCK).
* Critical alarms (hard limit ALARM:1, soft limit ALARM:2) block everything, status
  reports included, until a soft reset. ``$20=1`` soft limits check targets against
  [0, $13x] (homing sets the origin at the switch, HOMING_FORCE_SET_ORIGIN style).
* During homing status queries are ignored and later lines wait in the serial buffer;
  ``$H`` answers ``ok`` when homing ends. Lines sent while a dwell runs wait too.

Not modelled: the 128-byte serial buffer and planner back-pressure (every motion line is
answered ``ok`` at once), spindle/coolant, overrides, probing, arcs, work offsets.

Fault knobs beyond :class:`~opacityhull.rigs.emulators.base.Faults`:
:meth:`inject_alarm`, :meth:`reset_mid_move`, :meth:`open_door` / :meth:`close_door`,
:meth:`power_cycle`, :attr:`lose_lines` (next N lines vanish in transit),
:attr:`force_errors` (the next lines are answered with these ``error:N`` codes, as a
firmware variant might) and :attr:`fail_homing` (next homing ends in that alarm); plus
the server's ``vanish()``.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field

from ..grbl_protocol import AXES, format_number
from .base import EmulatedDevice, Reply

log = logging.getLogger(__name__)

__all__ = ["GrblEmulator"]

VERSION = "1.1h"
BUILD_DATE = "20190830"

# GRBL 1.1 defaults (defaults.h, DEFAULTS_GENERIC), in our units (degrees).
_DEFAULTS = {
    0: 10,
    1: 25,
    2: 0,
    3: 0,
    4: 0,
    5: 0,
    6: 0,
    10: 1,
    11: 0.010,
    12: 0.002,
    13: 0,
    20: 0,
    21: 0,
    22: 0,
    23: 0,
    24: 25.0,
    25: 500.0,
    26: 250,
    27: 1.0,
    30: 1000,
    31: 0,
    32: 0,
}
_AXIS_DEFAULTS = {100: 250.0, 110: 500.0, 120: 10.0, 130: 200.0}
_INT_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}
_BOOL_SETTINGS = {4, 5, 6, 13, 20, 21, 22, 32}
MAX_STEP_RATE_HZ = 30000.0
_NUM = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)")
_LINE_MAX = 80

_MODAL_GROUPS = {
    0: "motion",
    1: "motion",
    2: "motion",
    3: "motion",
    80: "motion",
    38: "motion",
    17: "plane",
    18: "plane",
    19: "plane",
    20: "units",
    21: "units",
    90: "distance",
    91: "distance",
    93: "feedmode",
    94: "feedmode",
    54: "wcs",
    55: "wcs",
    56: "wcs",
    57: "wcs",
    58: "wcs",
    59: "wcs",
    4: "nonmodal",
    10: "nonmodal",
    28: "nonmodal",
    30: "nonmodal",
    53: "nonmodal",
    92: "nonmodal",
}
_SUPPORTED_G = {0, 1, 4, 17, 18, 19, 20, 21, 53, 54, 55, 56, 57, 58, 59, 80, 90, 91, 94}
_M_GROUPS = {
    0: "stop",
    1: "stop",
    2: "stop",
    30: "stop",
    3: "spindle",
    4: "spindle",
    5: "spindle",
    7: "coolant",
    8: "coolant",
    9: "coolant",
}


class _LineError(Exception):
    def __init__(self, code: int):
        self.code = code


def _modal_group(code: int, group_of: dict, used: dict) -> str:
    """The modal group of G/M ``code``: error 20 when the table ``group_of`` does not know
    it, 21 when the block already has a word of that group (a key of ``used``)."""
    if code not in group_of:
        raise _LineError(20)
    g = group_of[code]
    if g in used:
        raise _LineError(21)
    return g


@dataclass
class _Motion:
    """One planned straight move (or homing) and its timing."""

    kind: str  # "line" | "jog" | "home"
    start: dict  # axis -> degrees
    target: dict  # axis -> degrees (already quantised to steps)
    rate_deg_s: float  # requested speed along the path (before axis limits)
    t0: float = 0.0
    T: float = 0.0  # physical duration, s
    L: float = 0.0
    v: float = 0.0
    a: float = 1.0
    ta: float = 0.0
    tc: float = 0.0
    unit: dict = field(default_factory=dict)


class GrblEmulator(EmulatedDevice):
    """A GRBL 1.1h controller with rotary axes in degrees.

    Parameters
    ----------
    axes : axis letters fitted (reported in X, Y, Z, A, B, C order).
    steps_per_deg : $100.. per axis: one number for all axes or {axis: value}; None =
        GRBL's default 250.
    time_scale : real seconds per physical second of motion (0 = instant).
    banner : print the welcome banner at power-up (a soft reset always prints it).
    homing : $22 homing enabled (the controller then powers up locked in Alarm).
    options : ``[OPT:]`` build-option letters; ``H`` enables ``$HX`` single-axis homing.
    """

    name = "grbl"

    def __init__(
        self,
        *,
        axes=("X", "Y"),
        steps_per_deg=None,
        time_scale: float = 0.0,
        banner: bool = True,
        homing: bool = False,
        options: str = "VH",
    ):
        super().__init__(time_scale=time_scale)
        axes = tuple(a.upper() for a in axes)
        if not axes or any(a not in AXES for a in axes) or len(set(axes)) != len(axes):
            raise ValueError(f"axes must be distinct letters of {AXES}, got {axes!r}")
        self.axes = tuple(sorted(axes, key=AXES.index))
        self.options = options
        self._banner_at_power_up = banner
        self._defaults = dict(_DEFAULTS)
        self._defaults[22] = 1 if homing else 0
        for a in self.axes:
            k = AXES.index(a)
            for base, v in _AXIS_DEFAULTS.items():
                self._defaults[base + k] = v
            if steps_per_deg is not None:
                spd = steps_per_deg[a] if isinstance(steps_per_deg, dict) else steps_per_deg
                self._defaults[100 + k] = float(spd)
        self.settings: dict[int, float] = dict(self._defaults)
        # logs (public, read by tests)
        self.lines: list[str] = []  # every complete line received, as sent
        self.realtime: list[bytes] = []  # every real-time byte received
        # fault knobs
        self.lose_lines = 0
        self.force_errors: list[int] = []
        self.fail_homing: int | None = None
        self.build_info_text = ""
        self.startup_lines = ["", ""]
        self._power_up()

    # ------------------------------------------------------------------ public state
    @property
    def state(self) -> str:
        """Machine state name (``Idle``, ``Run``, ``Hold``, ``Alarm`` ...), without substate."""
        with self.lock:
            self._update(self.now())
            return self._state

    @property
    def substate(self) -> int | None:
        with self.lock:
            self._update(self.now())
            return self._sub

    @property
    def critical(self) -> bool:
        """True while a critical alarm (hard/soft limit) blocks everything until a reset."""
        with self.lock:
            return self._critical

    @property
    def is_moving(self) -> bool:
        with self.lock:
            self._update(self.now())
            return self._active is not None and self._state in ("Run", "Jog", "Home")

    def position_deg(self, axis: str) -> float:
        """Where the axis is now (degrees, machine coordinates, whole steps)."""
        with self.lock:
            self._update(self.now())
            return self._pos_now(self.now())[axis.upper()]

    def positions(self) -> dict[str, float]:
        with self.lock:
            self._update(self.now())
            return dict(self._pos_now(self.now()))

    def status_line(self) -> str:
        """The status report ``?`` would produce now (without counting as a report)."""
        with self.lock:
            self._update(self.now())
            return self._status(count=False).decode().strip()

    # ------------------------------------------------------------------ fault knobs
    def inject_alarm(self, code: int) -> None:
        """Raise ``ALARM:code`` now, as the firmware would (motion stops where it is).
        Codes 1 (hard limit) and 2 (soft limit) are critical: nothing is answered until a
        soft reset."""
        with self.lock:
            now = self.now()
            self._update(now)
            self._alarm(code, now)

    def reset_mid_move(self) -> bool:
        """Soft reset from outside the host link (reset button, EMI): during motion the
        position is no longer trusted and ALARM:3 follows. Returns whether it was moving."""
        with self.lock:
            now = self.now()
            self._update(now)
            moving = self._active is not None and self._state in ("Run", "Jog", "Home", "Hold")
            self._out += self._soft_reset(now)
            return moving

    def open_door(self) -> None:
        """Safety door opens: motion holds and the state becomes Door:1."""
        with self.lock:
            now = self.now()
            self._update(now)
            if self._state in ("Run", "Jog", "Hold"):
                self._freeze(now, keep_remaining=self._state != "Jog")
            if self._state not in ("Alarm", "Sleep"):
                self._state, self._sub = "Door", 1
            self._out.append(self._line("[MSG:Check Door]"))

    def close_door(self) -> None:
        """Safety door closes: Door:0, ready to resume with ``~``."""
        with self.lock:
            if self._state == "Door":
                self._sub = 0
                self._out.append(self._line("[MSG:Check Door]"))

    def power_cycle(self) -> None:
        """Power off and on: position zero, parser reset, banner (if enabled)."""
        with self.lock:
            self._power_up()

    # ------------------------------------------------------------------ internals: setup
    def _power_up(self) -> None:
        self._pos = {a: 0.0 for a in self.axes}
        self._active: _Motion | None = None
        self._queue: list[_Motion] = []
        self._state = "Alarm" if int(self.settings.get(22, 0)) else "Idle"
        self._sub: int | None = None
        self._critical = False
        self._hold_done_at = 0.0
        self._blocking: list | None = None  # ["home"] | ["dwell", seconds, due time or None, received]
        self._motion_end = 0.0
        self._waiting_lines: list[str] = []
        self._buf = bytearray()
        self._out: list[Reply] = []
        self._reports = 0
        self._reset_parser()
        if self._banner_at_power_up:
            self._out += self._banner()

    def _reset_parser(self) -> None:
        self._motion_mode = 0
        self._absolute = True
        self._inches = False
        self._feed = 0.0
        self._wcs = 54
        self._plane = 17
        self._spindle = 5
        self._coolant = 9
        self._tool = 0
        self._spindle_speed = 0.0

    @staticmethod
    def _line(text: str) -> Reply:
        return Reply(text.encode("ascii") + b"\r\n")

    def _banner(self) -> list[Reply]:
        out = [Reply(f"\r\nGrbl {VERSION} ['$' for help]\r\n".encode("ascii"))]
        if self._state == "Alarm":
            out.append(self._line("[MSG:'$H'|'$X' to unlock]"))
        return out

    def _spd(self, axis: str) -> float:
        return float(self.settings[100 + AXES.index(axis)])

    def _quantise(self, axis: str, deg: float) -> float:
        spd = self._spd(axis)
        return round(deg * spd) / spd

    # ------------------------------------------------------------------ internals: motion
    def _plan(self, m: _Motion, now: float) -> None:
        d = {a: m.target[a] - m.start[a] for a in self.axes}
        L = math.sqrt(sum(v * v for v in d.values()))
        m.L = L
        m.t0 = now
        if L <= 0.0:
            m.T = 0.0
            return
        m.unit = {a: d[a] / L for a in self.axes}
        v = m.rate_deg_s
        acc = math.inf
        for a in self.axes:
            u = abs(m.unit[a])
            if u > 0:
                k = AXES.index(a)
                v = min(v, float(self.settings[110 + k]) / 60.0 / u)
                acc = min(acc, float(self.settings[120 + k]) / u)
        v = max(v, 1e-6)
        acc = max(acc, 1e-6)
        ta = v / acc
        da = 0.5 * acc * ta * ta
        if 2 * da >= L:
            ta = math.sqrt(L / acc)
            v = acc * ta
            tc = 0.0
        else:
            tc = (L - 2 * da) / v
        m.v, m.a, m.ta, m.tc = v, acc, ta, tc
        m.T = 2 * ta + tc

    def _s_at(self, m: _Motion, tau: float) -> tuple[float, float]:
        """Distance along the path and speed, ``tau`` physical seconds after the start."""
        if tau >= m.T or m.L <= 0:
            return m.L, 0.0
        if tau <= 0:
            return 0.0, 0.0
        if tau < m.ta:
            return 0.5 * m.a * tau * tau, m.a * tau
        if tau < m.ta + m.tc:
            return 0.5 * m.a * m.ta * m.ta + m.v * (tau - m.ta), m.v
        rest = m.T - tau
        return m.L - 0.5 * m.a * rest * rest, m.a * rest

    def _tau(self, m: _Motion, now: float) -> float:
        if self.time_scale <= 0:
            return m.T
        return (now - m.t0) / self.time_scale

    def _end_time(self, m: _Motion) -> float:
        return m.t0 + m.T * self.time_scale

    def _pos_now(self, now: float) -> dict:
        m = self._active
        if m is None or self._state not in ("Run", "Jog", "Home"):
            return dict(self._pos)
        if m.kind == "home":
            f = 1.0 if m.T <= 0 else min(1.0, self._tau(m, now) / m.T)
            return {a: self._quantise(a, m.start[a] + (m.target[a] - m.start[a]) * f) for a in self.axes}
        s, _ = self._s_at(m, self._tau(m, now))
        return {a: self._quantise(a, m.start[a] + m.unit.get(a, 0.0) * s) for a in self.axes}

    def _speed_now(self, now: float) -> float:
        m = self._active
        if m is None or self._state not in ("Run", "Jog") or m.kind == "home":
            return 0.0
        return self._s_at(m, self._tau(m, now))[1]

    def _start_next(self, t0: float) -> None:
        if self._active is None and self._queue:
            m = self._queue.pop(0)
            m.start = dict(self._pos)
            self._plan(m, t0)
            self._active = m

    def _update(self, now: float) -> None:
        """Advance time: finish moves, homing, dwells and holds that are due."""
        for _ in range(100000):
            if self._state == "Hold" and self._sub == 1 and now >= self._hold_done_at:
                self._sub = 0
            if self._state in ("Run", "Jog", "Home"):
                if self._active is None:
                    self._start_next(now)
                m = self._active
                if m is None:
                    self._state, self._sub = "Idle", None
                    continue
                end = self._end_time(m)
                if now >= end:
                    self._pos = dict(m.target)
                    self._active = None
                    if m.kind == "home":
                        self._finish_homing(now)
                        continue
                    if self._queue:  # the next block starts when this one ended, not when we looked
                        self._start_next(end if self.time_scale > 0 else now)
                        continue
                    self._motion_end = end
                    self._state, self._sub = "Idle", None
                    continue
            b = self._blocking
            if b is not None and b[0] == "dwell" and self._state not in ("Run", "Jog", "Hold", "Door"):
                if b[2] is None:  # the dwell starts once the planner has emptied
                    b[2] = max(b[3], self._motion_end) + b[1] * self.time_scale
                if now >= b[2]:
                    self._blocking = None
                    self._out.append(self._line("ok"))
                    self._drain_waiting(now)
                    continue
            break

    def _finish_homing(self, now: float) -> None:
        self._blocking = None
        if self.fail_homing is not None:
            code, self.fail_homing = self.fail_homing, None
            self._state, self._sub = "Alarm", None
            self._out.append(self._line(f"ALARM:{code}"))
            self._waiting_lines.clear()
            return
        self._state, self._sub = "Idle", None
        self._out.append(self._line("ok"))
        self._drain_waiting(now)

    def _drain_waiting(self, now: float) -> None:
        while self._waiting_lines and self._blocking is None and not self._critical:
            self._out += self._exec_line(self._waiting_lines.pop(0), now)

    def _freeze(self, now: float, *, keep_remaining: bool) -> float:
        """Stop where the pulses are now; return the speed at that instant. With
        ``keep_remaining`` the rest of the current move stays first in the queue."""
        speed = self._speed_now(now)
        self._pos = self._pos_now(now)
        m = self._active
        self._active = None
        if m is not None and keep_remaining and m.kind != "home":
            self._queue.insert(0, _Motion(m.kind, dict(self._pos), dict(m.target), m.rate_deg_s))
        if not keep_remaining:
            self._queue.clear()
        return speed

    def _drop_motion(self, now: float) -> None:
        """Stop where the axes are now and forget every queued, active or waiting line."""
        if self._state in ("Run", "Jog", "Home", "Hold", "Door"):
            self._freeze(now, keep_remaining=False)
        self._queue.clear()
        self._active = None
        self._blocking = None
        self._waiting_lines.clear()

    def _alarm(self, code: int, now: float) -> None:
        self._drop_motion(now)
        self._state, self._sub = "Alarm", None
        self._out.append(self._line(f"ALARM:{code}"))
        if code in (1, 2):
            self._critical = True
            self._out.append(self._line("[MSG:Reset to continue]"))

    def _soft_reset(self, now: float) -> list[Reply]:
        out: list[Reply] = []
        moving = (
            (self._state in ("Run", "Jog", "Home") and self._active is not None)
            or (self._state == "Hold" and self._sub == 1)
            or (self._state == "Door" and self._sub in (2, 3))
        )
        was_home = self._state == "Home"
        self._drop_motion(now)
        self._buf.clear()
        self._critical = False
        if moving:
            code = 6 if was_home else 3
            self._state, self._sub = "Alarm", None
            out.append(self._line(f"ALARM:{code}"))
        elif self._state == "Sleep":
            self._state, self._sub = "Alarm", None
        elif self._state != "Alarm":
            self._state, self._sub = "Idle", None
        self._reset_parser()
        self._reports = 0
        out += self._banner()
        return out

    # ------------------------------------------------------------------ bytes in
    def receive(self, data: bytes):
        # Every handler appends to self._out in the order things happen (including what
        # _update emits when a move or homing ends), so replies keep GRBL's order.
        now = self.now()
        self._update(now)
        for b in data:
            c = bytes([b])
            if c in (b"?", b"!", b"~", b"\x18", b"\x85") or 0x90 <= b <= 0xA5:
                self.realtime.append(c)
                self._out += self._realtime(c, now)
                continue
            if b in (0x0A, 0x0D):
                text = self._buf.decode("ascii", "replace")
                self._buf.clear()
                self.lines.append(text)
                self._out += self._dispatch_line(text, now)
                continue
            if b >= 0x80:
                continue  # GRBL drops other extended-ASCII bytes
            self._buf.append(b)
        out, self._out = self._out, []
        return out

    def tick(self):
        with self.lock:
            self._update(self.now())
            out, self._out = self._out, []
            return out

    def _realtime(self, c: bytes, now: float) -> list[Reply]:
        if c == b"\x18":
            return self._soft_reset(now)
        if self._critical:
            return []  # blocked until reset, status reports included
        self._update(now)
        if c == b"?":
            if self._state == "Home":
                return []  # GRBL does not report during a homing cycle
            return [Reply(self._status())]
        if c == b"!":
            if self._state in ("Run", "Jog"):
                jog = self._state == "Jog"
                speed = self._freeze(now, keep_remaining=not jog)
                decel = speed / max(self._accel_limit(), 1e-9)
                self._hold_done_at = now + decel * self.time_scale
                if jog:  # a feed hold cancels a jog
                    self._state, self._sub = "Idle", None
                else:
                    self._state, self._sub = "Hold", 1 if decel * self.time_scale > 0 else 0
            return []
        if c == b"~":
            if (self._state == "Hold" and self._sub in (0, 1)) or (self._state == "Door" and self._sub == 0):
                if self._queue:
                    self._state, self._sub = "Run", None
                    self._start_next(now)
                else:
                    self._state, self._sub = "Idle", None
                self._update(now)
            return []
        if c == b"\x85":
            if self._state == "Jog":
                self._freeze(now, keep_remaining=False)
                self._state, self._sub = "Idle", None
            return []
        return []  # overrides: accepted, not modelled

    def _accel_limit(self) -> float:
        return min(float(self.settings[120 + AXES.index(a)]) for a in self.axes)

    def _status(self, *, count: bool = True) -> bytes:
        now = self.now()
        pos = self._pos_now(now)
        state = self._state if self._sub is None else f"{self._state}:{self._sub}"
        vals = ",".join(format_number(pos[a]) for a in self.axes)
        feed = self._speed_now(now) * 60.0
        parts = [state, f"MPos:{vals}", f"FS:{feed:.0f},0"]
        if self._reports == 0:
            parts.append("WCO:" + ",".join(format_number(0.0) for _ in self.axes))
        elif self._reports == 1:
            parts.append("Ov:100,100,100")
        if count:
            self._reports = (self._reports + 1) % 30
        return ("<" + "|".join(parts) + ">\r\n").encode("ascii")

    # ------------------------------------------------------------------ lines
    def _dispatch_line(self, raw: str, now: float) -> list[Reply]:
        if self._critical or self._state == "Sleep":
            return []
        if self.lose_lines > 0:
            self.lose_lines -= 1
            return []
        if self.force_errors:
            return [self._line(f"error:{self.force_errors.pop(0)}")]
        if self._blocking is not None:
            self._waiting_lines.append(raw)  # sits in the serial buffer until the dwell/homing ends
            return []
        return self._exec_line(raw, now)

    @staticmethod
    def _clean(raw: str) -> str:
        out = []
        depth = 0
        for ch in raw:
            if depth:
                if ch == ")":
                    depth = 0
                continue
            if ch == "(":
                depth = 1
                continue
            if ch == ";":
                break
            if ch.isspace():
                continue
            out.append(ch.upper() if "a" <= ch <= "z" else ch)
        return "".join(out)

    def _exec_line(self, raw: str, now: float) -> list[Reply]:
        if len(raw) >= _LINE_MAX:
            return [self._line("error:11")]
        text = self._clean(raw)
        try:
            if not text:
                return [self._line("ok")]
            if text.startswith("$"):
                return self._system(raw.strip(), text, now)
            if self._state in ("Alarm", "Jog"):
                raise _LineError(9)
            return self._gcode(text, now)
        except _LineError as e:
            return [self._line(f"error:{e.code}")]

    # ---- G-code
    def _words(self, text: str) -> list[tuple[str, float, str]]:
        words = []
        i = 0
        while i < len(text):
            letter = text[i]
            if not ("A" <= letter <= "Z"):
                raise _LineError(1)
            m = _NUM.match(text, i + 1)
            if not m:
                raise _LineError(2)
            words.append((letter, float(m.group(0)), m.group(0)))
            i = m.end()
        return words

    def _gcode(self, text: str, now: float, *, jog: bool = False) -> list[Reply]:
        words = self._words(text)
        groups: dict[str, float] = {}
        mgroups: dict[str, int] = {}
        seen: set[str] = set()
        axis_words: dict[str, float] = {}
        feed = None
        dwell = None
        for letter, value, _txt in words:
            if letter == "G":
                code = round(value * 10) / 10
                if code != int(code):
                    raise _LineError(29 if int(code) == 59 else 20)
                code = int(code)
                g = _modal_group(code, _MODAL_GROUPS, groups)
                if code not in _SUPPORTED_G:
                    raise _LineError(20)
                if jog and code not in (20, 21, 90, 91, 53):
                    raise _LineError(16)
                groups[g] = code
                continue
            if letter == "M":
                if jog:
                    raise _LineError(16)
                if value != int(value):
                    raise _LineError(23)
                code = int(value)
                mgroups[_modal_group(code, _M_GROUPS, mgroups)] = code
                continue
            if letter in seen:
                raise _LineError(25)
            seen.add(letter)
            if letter in self.axes:
                axis_words[letter] = value
            elif letter == "F":
                if value < 0:
                    raise _LineError(4)
                feed = value
            elif letter == "N":
                if jog:
                    raise _LineError(16)
                if value < 0:
                    raise _LineError(4)
                if value != int(value) or not 1 <= value <= 9999999:
                    raise _LineError(27)
            elif letter == "P":
                if value < 0:
                    raise _LineError(4)
                dwell = value
            elif letter in "ST" and not jog:
                if value < 0:
                    raise _LineError(4)
                if letter == "T":
                    if value != int(value):
                        raise _LineError(23)
                    if value > 255:
                        raise _LineError(38)
                    self._tool = int(value)
                else:
                    self._spindle_speed = value
            elif letter in "IJKRLQ" and not jog:
                raise _LineError(36)
            else:
                raise _LineError(20)
        # modal updates (GRBL applies them in this order; the line is atomic: validate first)
        units_inch = self._inches if "units" not in groups else groups["units"] == 20
        absolute = self._absolute if "distance" not in groups else groups["distance"] == 90
        motion = groups.get("motion", self._motion_mode)
        nonmodal = groups.get("nonmodal")
        scale = 25.4 if units_inch else 1.0
        if jog:
            if feed is None:
                raise _LineError(22)
            if not axis_words:
                raise _LineError(26)
        if nonmodal == 4:
            if dwell is None:
                raise _LineError(28)
            if axis_words:
                raise _LineError(24)
        if nonmodal == 53 and motion not in (0, 1) and not jog:
            raise _LineError(30)
        if axis_words and motion == 80 and nonmodal is None and not jog:
            raise _LineError(31)
        new_feed = self._feed if feed is None else feed * scale
        if not jog and motion == 1 and axis_words and new_feed <= 0:
            raise _LineError(22)
        # everything valid: commit modal state
        if not jog:
            self._inches, self._absolute, self._motion_mode = units_inch, absolute, motion
            self._feed = new_feed
            if "wcs" in groups:
                self._wcs = groups["wcs"]
            if "plane" in groups:
                self._plane = groups["plane"]
            if "spindle" in mgroups:
                self._spindle = mgroups["spindle"]
            if "coolant" in mgroups:
                self._coolant = mgroups["coolant"]
        out: list[Reply] = []
        if self._state == "Check":
            return [self._line("ok")]
        if nonmodal == 4:
            self._blocking = ["dwell", dwell, None, now]
            self._update(now)
            return out  # ok when the planner has emptied and the dwell ran
        if axis_words:
            base = self._planned_end()
            target = dict(base)
            for a, v in axis_words.items():
                v = v * scale
                target[a] = v if absolute else base[a] + v
            target = {a: self._quantise(a, target[a]) for a in self.axes}
            if int(self.settings.get(20, 0)):
                for a in self.axes:
                    travel = float(self.settings[130 + AXES.index(a)])
                    if not -1e-9 <= target[a] <= travel + 1e-9:
                        self._alarm(2, now)
                        return []
            if jog:
                assert feed is not None  # a jog without F was refused above (error:22)
                rate = feed * scale / 60.0
                kind = "jog"
            elif motion == 0:
                rate = math.inf
                kind = "line"
            else:
                rate = new_feed / 60.0
                kind = "line"
            self._queue.append(_Motion(kind, dict(base), target, rate))
            if self._state == "Idle":
                self._state = "Jog" if jog else "Run"
                self._sub = None
                self._start_next(now)
            self._update(now)
        if mgroups.get("stop") in (2, 30):
            self._reset_parser()
            out.append(self._line("[MSG:Pgm End]"))
        out.append(self._line("ok"))
        return out

    def _planned_end(self) -> dict:
        if self._queue:
            return dict(self._queue[-1].target)
        if self._active is not None and self._state in ("Run", "Jog"):
            return dict(self._active.target)
        return dict(self._pos)

    # ---- $ commands
    def _system(self, raw: str, text: str, now: float) -> list[Reply]:
        ok = self._line("ok")
        st = self._state
        idle_or_alarm = st in ("Idle", "Alarm")
        if text == "$":
            return [self._line("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"), ok]
        if text.startswith("$J="):
            if st not in ("Idle", "Jog"):
                raise _LineError(8)
            body = text[3:]
            if not body:
                raise _LineError(16)
            return self._gcode(body, now, jog=True)
        if text == "$$":
            if st in ("Run", "Hold", "Jog", "Home"):
                raise _LineError(8)
            return [self._line(f"${n}={self._fmt_setting(n)}") for n in sorted(self.settings)] + [ok]
        if text == "$G":
            gc = (
                f"[GC:G{self._motion_mode} G{self._wcs} G{self._plane} G{20 if self._inches else 21} "
                f"G{90 if self._absolute else 91} G94 M{self._spindle} M{self._coolant} T{self._tool} "
                f"F{self._feed:g} S{self._spindle_speed:g}]"
            )
            return [self._line(gc), ok]
        if text == "$C":
            if st == "Check":
                out = [self._line("[MSG:Disabled]"), ok]
                return out + self._soft_reset(now)
            if st != "Idle":
                raise _LineError(8)
            self._state, self._sub = "Check", None
            return [self._line("[MSG:Enabled]"), ok]
        if text == "$X":
            if st == "Alarm":
                self._state, self._sub = "Idle", None
                return [self._line("[MSG:Caution: Unlocked]"), ok]
            return [ok]
        # the rest needs Idle or Alarm
        if not idle_or_alarm:
            raise _LineError(8)
        if text.startswith("$H"):
            rest = text[2:]
            if not int(self.settings.get(22, 0)):
                raise _LineError(5)
            if rest and ("H" not in self.options or len(rest) != 1 or rest not in self.axes):
                raise _LineError(3)
            homed = (rest,) if rest else self.axes
            self._start_homing(homed, now)
            return []  # ok when homing completes
        if text == "$#":
            z = ",".join(format_number(0.0) for _ in self.axes)
            lines = [f"[G{n}:{z}]" for n in (54, 55, 56, 57, 58, 59)] + [
                f"[G28:{z}]",
                f"[G30:{z}]",
                f"[G92:{z}]",
                "[TLO:0.000]",
                f"[PRB:{z}:0]",
            ]
            return [self._line(x) for x in lines] + [ok]
        if text == "$I":
            return [
                self._line(f"[VER:{VERSION}.{BUILD_DATE}:{self.build_info_text}]"),
                self._line(f"[OPT:{self.options},15,128]"),
                ok,
            ]
        if text.startswith("$I="):
            self.build_info_text = raw.strip()[3:]
            return [ok]
        if text == "$N":
            return [self._line(f"$N{i}={s}") for i, s in enumerate(self.startup_lines)] + [ok]
        if re.fullmatch(r"\$N[01]=.*", text):
            self.startup_lines[int(text[2])] = text[4:]
            return [ok]
        if text == "$SLP":
            self._state, self._sub = "Sleep", None
            return [self._line("[MSG:Sleeping]"), ok]
        if text.startswith("$RST="):
            what = text[5:]
            if what not in ("$", "#", "*"):
                raise _LineError(3)
            if what in ("$", "*"):
                self.settings = dict(self._defaults)
            return [self._line("[MSG:Restoring defaults]"), ok]
        m = re.fullmatch(r"\$(\d+)=(.*)", text)
        if m:
            return self._write_setting(int(m.group(1)), m.group(2))
        raise _LineError(3)

    def _fmt_setting(self, n: int) -> str:
        v = self.settings[n]
        return str(int(v)) if n in _INT_SETTINGS else format_number(float(v))

    def _write_setting(self, n: int, value_text: str) -> list[Reply]:
        if n not in self.settings:
            raise _LineError(3)
        if not _NUM.fullmatch(value_text):
            raise _LineError(2)
        v = float(value_text)
        if v < 0:
            raise _LineError(4)
        if n == 0 and v < 3:
            raise _LineError(6)
        if n in _BOOL_SETTINGS:
            v = 1 if v else 0
        elif n in _INT_SETTINGS:
            v = int(v)
        if n == 20 and v and not int(self.settings.get(22, 0)):
            raise _LineError(10)
        if 100 <= n < 120:
            k = n % 10
            spd = v if n < 110 else float(self.settings[100 + k])
            rate = v if n >= 110 else float(self.settings[110 + k])
            if spd * rate / 60.0 > MAX_STEP_RATE_HZ:
                raise _LineError(12)
            if n < 110 and v <= 0:
                raise _LineError(4)
        self.settings[n] = v
        return [self._line("ok")]

    def _start_homing(self, homed, now: float) -> None:
        seek = float(self.settings[25]) / 60.0
        locate = max(float(self.settings[24]) / 60.0, 1e-6)
        pull = float(self.settings[27])
        far = max(abs(self._pos[a]) for a in homed)
        T = far / max(seek, 1e-6) + 2.0 * pull / locate
        target = dict(self._pos)
        for a in homed:
            target[a] = 0.0
        m = _Motion("home", dict(self._pos), target, seek, t0=now, T=T, L=far)
        self._queue.clear()
        self._active = m
        self._state, self._sub = "Home", None
        self._blocking = ["home"]
        self._update(now)
