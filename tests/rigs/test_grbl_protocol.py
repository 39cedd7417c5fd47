"""GRBL 1.1 wire protocol: encoders and parsers (pure, no I/O)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import InputError
from opacityhull.rigs import grbl_protocol as gp
from opacityhull.rigs.transport import ProtocolError

# GRBL 1.1 documents error codes 1-17 and 20-38 and alarm codes 1-9 (1.1g+ adds 10).
ERROR_CODES = [*range(1, 18), *range(20, 39)]
ALARM_CODES = list(range(1, 11))


def test_code_tables_are_complete():
    assert sorted(gp.ERROR_CODES) == ERROR_CODES
    assert sorted(gp.ALARM_CODES) == ALARM_CODES
    for table in (gp.ERROR_CODES, gp.ALARM_CODES):
        for code, (short, desc, hint) in table.items():
            assert short and len(desc) > 15 and hint, code


@pytest.mark.parametrize("code", ERROR_CODES)
def test_every_error_code_parses_with_its_meaning(code):
    r = gp.parse_response(f"error:{code}\r\n".encode())
    assert isinstance(r, gp.GrblError) and r.code == code
    assert r.meaning.startswith(gp.ERROR_CODES[code][0]) and gp.ERROR_CODES[code][1] in r.meaning
    assert r.hint == gp.ERROR_CODES[code][2]


def test_known_error_meanings_match_the_grbl_documentation():
    assert "Bad number format" in gp.error_meaning(2)
    assert "Homing" in gp.ERROR_CODES[5][1] or "homing" in gp.ERROR_CODES[5][1]
    assert "alarm or jog" in gp.error_meaning(9)
    assert "Unsupported" in gp.error_meaning(20)
    assert "unknown" in gp.error_meaning(99)


@pytest.mark.parametrize("code", ALARM_CODES)
def test_every_alarm_code_parses_with_its_meaning(code):
    r = gp.parse_response(f"ALARM:{code}\r\n".encode())
    assert isinstance(r, gp.Alarm) and r.code == code
    assert gp.ALARM_CODES[code][1] in r.meaning
    assert r.critical == (code in (1, 2))


def test_alarm_meanings_match_the_grbl_documentation():
    assert "Hard limit" in gp.alarm_meaning(1) and "limit switch" in gp.ALARM_CODES[1][2]
    assert "Soft limit" in gp.alarm_meaning(2)
    assert "reset while in motion" in gp.alarm_meaning(3).lower()
    assert "could not find the limit switch" in gp.alarm_meaning(9).lower()


@pytest.mark.parametrize(
    "line,expected",
    [
        (b"ok\r\n", gp.Ok()),
        (b"Grbl 1.1h ['$' for help]\r\n", gp.Banner("1.1h", "Grbl 1.1h ['$' for help]")),
        (b"[MSG:'$H'|'$X' to unlock]\r\n", gp.Message("MSG", "'$H'|'$X' to unlock")),
        (b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\n", gp.Message("GC", "G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0")),
        (b"[VER:1.1h.20190830:]\r\n", gp.Message("VER", "1.1h.20190830:")),
        (b"[OPT:VH,15,128]\r\n", gp.Message("OPT", "VH,15,128")),
        (b"[PRB:0.000,0.000,0.000:0]\r\n", gp.Message("PRB", "0.000,0.000,0.000:0")),
        (b"$100=80.000\r\n", gp.Setting(100, 80.0)),
        (b"$0=10\r\n", gp.Setting(0, 10.0)),
        (b"$N0=G54\r\n", gp.Message("N0", "G54")),
        (b">G54G20:ok\r\n", gp.StartupLine("G54G20", "ok")),
        (b">G54G20:error:20\r\n", gp.StartupLine("G54G20", "error:20")),
    ],
)
def test_push_messages(line, expected):
    assert gp.parse_response(line) == expected


@pytest.mark.parametrize(
    "line",
    [
        b"",
        b"\r\n",
        b"okk\r\n",
        b"error:\r\n",
        b"error:x1\r\n",
        b"ALARM:abc\r\n",
        b"\xff\xfe\r\n",
        b"5\x1bk\r\n",
        b"[MSG\r\n",
        b"$abc=1\r\n",
        b"$100=1.2.3\r\n",
        b"Grbl\r\n",
        b">G54:maybe\r\n",
        bytes(b ^ 0x5A if i % 2 == 0 else b for i, b in enumerate(b"ok\r\n")),
    ],
)
def test_garbage_raises_protocol_error_quoting_the_bytes(line):
    with pytest.raises(ProtocolError) as ei:
        gp.parse_response(line)
    assert repr(line.strip(b"\r\n"))[2:-1][:8] in str(ei.value) or repr(line)[2:-1][:8] in str(ei.value)


def test_status_idle_mpos_fs():
    s = gp.parse_status(b"<Idle|MPos:12.500,-3.000,0.000|FS:0,0>\r\n")
    assert s.state == "Idle" and s.substate is None
    assert s.mpos == {"X": 12.5, "Y": -3.0, "Z": 0.0} and s.wpos is None
    assert s.feed == 0.0 and s.spindle == 0.0


def test_status_substate_wpos_wco_and_extra_fields():
    s = gp.parse_status("<Hold:0|WPos:1.000,2.000|Bf:15,128|FS:500,8000|WCO:0.500,-1.000|Ov:100,100,100|Pn:XZ|A:SF>")
    assert (s.state, s.substate) == ("Hold", 0)
    assert s.wpos == {"X": 1.0, "Y": 2.0} and s.mpos is None and s.wco == {"X": 0.5, "Y": -1.0}
    assert s.feed == 500.0 and s.spindle == 8000.0 and s.fields["Pn"] == "XZ"
    assert s.position(work=False) == {"X": 1.5, "Y": 1.0}
    assert s.position() == {"X": 1.0, "Y": 2.0}
    m = gp.parse_status("<Run|MPos:10.000,5.000|F:300>")
    assert m.feed == 300.0 and m.spindle is None
    assert m.position({"X": 1.0}) == {"X": 9.0, "Y": 5.0}


@pytest.mark.parametrize("state", gp.STATES)
def test_every_state_parses(state):
    assert gp.parse_status(f"<{state}|MPos:0.000|FS:0,0>").state == state


@pytest.mark.parametrize(
    "line",
    [
        "<Idle|FS:0,0>",  # no position
        "<Idle|MPos:0,0|WPos:0,0>",  # both
        "<Idling|MPos:0.000>",  # unknown state
        "<Idle|MPos:1.0,abc>",
        "<Idle|MPos:nan>",
        "<Idle|MPos:inf>",
        "<Idle|MPos:1,2,3,4,5,6,7>",
        "<Idle|MPos:0.000|FS:1>",
        "<Idle|MPos:0.000|MPos:1.000>",
        "<Idle|MPos:0.000",  # truncated
        "Idle|MPos:0.000>",
        "<Idle|FS:0,0|MPos:0.000>",  # position must come second
        "<Hold:x|MPos:0.000>",
        "<Idle|MPos:0.000|junk>",
    ],
)
def test_malformed_status_raises(line):
    with pytest.raises(ProtocolError, match="GRBL status|in GRBL"):
        gp.parse_status(line)


@given(
    st.lists(st.floats(-99999.0, 99999.0, allow_nan=False), min_size=1, max_size=6),
    st.sampled_from(gp.STATES),
    st.floats(0, 1e5),
)
@settings(max_examples=60, deadline=None)
def test_status_round_trip(values, state, feed):
    text = "<" + state + "|MPos:" + ",".join(gp.format_number(v) for v in values) + f"|FS:{feed:.0f},0>"
    s = gp.parse_status(text)
    assert s.state == state
    for axis, v in zip(gp.AXES[: len(values)], values, strict=True):  # a status reports 1..6 axes
        assert abs(s.mpos[axis] - v) <= 0.0005 + 1e-9


def test_move_abs_bytes():
    assert gp.move_abs({"X": 12.5}) == b"G90 G0 X12.500\n"
    assert gp.move_abs({"y": -0.0004, "X": 1}) == b"G90 G0 X1.000 Y0.000\n"
    assert gp.move_abs({"X": 90}, feed_deg_min=600) == b"G90 G1 X90.000 F600.0\n"
    assert gp.move_abs({"A": 1e5}) == b"G90 G0 A100000.000\n"


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, "12", None, True, 1e5 + 1, [1]])
def test_move_abs_rejects_bad_angles(value):
    with pytest.raises(InputError, match="axis X"):
        gp.move_abs({"X": value})


def test_move_abs_rejects_limits_axes_feeds():
    with pytest.raises(InputError, match=r"outside the soft range \[-10, 10\]"):
        gp.move_abs({"X": 10.5}, limits={"X": (-10.0, 10.0)})
    assert gp.move_abs({"X": 10.0}, limits={"X": (-10.0, 10.0)}) == b"G90 G0 X10.000\n"
    with pytest.raises(InputError, match="axis 'Q'"):
        gp.move_abs({"Q": 1.0})
    with pytest.raises(InputError, match="non-empty"):
        gp.move_abs({})
    for f in (0, -5, math.nan, "fast"):
        with pytest.raises(InputError, match="feed rate"):
            gp.move_abs({"X": 1.0}, feed_deg_min=f)


@given(st.floats(-gp.MAX_ABS_COORD, gp.MAX_ABS_COORD, allow_nan=False))
@settings(max_examples=80, deadline=None)
def test_move_abs_value_round_trip(v):
    line = gp.move_abs({"X": v}).decode()
    assert line.startswith("G90 G0 X") and line.endswith("\n") and "e" not in line
    assert abs(float(line[8:-1]) - v) <= 0.0005 + 1e-9
    assert len(line) < gp.LINE_BUFFER_SIZE


def test_encode_line_rejects_realtime_bytes_control_chars_and_overflow():
    assert gp.encode_line("$$") == b"$$\n"
    assert gp.encode_line(b"G4 P0\r\n") == b"G4 P0\n"
    for bad in ("G0 X1?", "!", "~", "G0\x18", "G0\tX1", "G0 X1\nG0 X2", "é"):
        with pytest.raises(InputError):
            gp.encode_line(bad)
    with pytest.raises(InputError, match="at most 79"):
        gp.encode_line("G0 X" + "1" * 80)


def test_command_encoders():
    assert gp.unlock() == b"$X\n"
    assert gp.home() == b"$H\n" and gp.home("y") == b"$HY\n"
    assert gp.get_settings() == b"$$\n" and gp.build_info() == b"$I\n" and gp.parser_state() == b"$G\n"
    assert gp.set_setting(110, 1800) == b"$110=1800.000\n"
    assert (gp.STATUS_QUERY, gp.FEED_HOLD, gp.CYCLE_START, gp.SOFT_RESET) == (b"?", b"!", b"~", b"\x18")
    for bad in ((256, 1.0), (-1, 1.0), (100, math.nan), (True, 1.0), (100, "x")):
        with pytest.raises(InputError):
            gp.set_setting(*bad)
    with pytest.raises(InputError):
        gp.home("XY")


def test_parse_settings():
    lines = [b"$0=10\r\n", b"$100=80.000\r\n", b"$N0=\r\n", b"ok\r\n"]
    assert gp.parse_settings(lines) == {0: 10.0, 100: 80.0}
