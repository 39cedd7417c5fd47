"""GrblEmulator as a pure state machine (bytes in, bytes out) on a fake clock.

The emulator's clock is replaced by a number the test advances, so states in the middle
of a move are checked exactly, with no sleeping.
"""

from __future__ import annotations

import pytest

from opacityhull.rigs import grbl_protocol as gp
from opacityhull.rigs.emulators.grbl import GrblEmulator
from opacityhull.rigs.motion import move_duration_s


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def make(**kw):
    clock = Clock()
    kw.setdefault("steps_per_deg", 80.0)
    emu = GrblEmulator(**kw)
    emu.now = clock
    emu.tick()  # swallow the power-up banner
    return emu, clock


def talk(emu, data: bytes) -> list[str]:
    out = list(emu.receive(data)) + list(emu.tick())
    text = b"".join(r.data for r in out).decode()
    return [ln for ln in text.split("\r\n") if ln]


def configure(emu, rate_deg_s=30.0, accel=60.0):
    assert (
        talk(emu, f"$110={rate_deg_s * 60}\n$111={rate_deg_s * 60}\n$120={accel}\n$121={accel}\n".encode())
        == ["ok"] * 4
    )


@pytest.mark.parametrize(
    "line,code",
    [
        ("G0 X1.2.3", 1),
        ("12", 1),
        ("G0 X", 2),
        ("G0 Xabc", 2),
        ("$100=abc", 2),
        ("$100=", 2),
        ("$Q", 3),
        ("$999=1", 3),
        ("$HZ", 5),
        ("$100=-1", 4),
        ("G0 F-1", 4),
        ("$H", 5),
        ("$0=2", 6),
        ("$20=1", 10),
        ("G0 X" + "1" * 80, 11),
        ("$100=4000", 12),
        ("G0 Z1", 20),
        ("G2 X1", 20),
        ("G28", 20),
        ("M99", 20),
        ("G0 G1 X1", 21),
        ("G90 G91", 21),
        ("G1 X1", 22),
        ("M5.5", 23),
        ("G0 X1 X2", 25),
        ("N0 G0", 27),
        ("G4", 28),
        ("G59.1", 29),
        ("G80 G53 X1", 30),
        ("G80 X1", 31),
        ("G0 X1 I2", 36),
        ("T300", 38),
        ("$J=G0 X1 F10", 16),
        ("$J=", 16),
        ("$J=G91 X1", 22),
    ],
)
def test_invalid_lines_get_grbl_error_codes(line, code):
    emu, _ = make()
    assert talk(emu, line.encode() + b"\n") == [f"error:{code}"]
    assert emu.position_deg("X") == 0.0


def test_line_handling_like_grbl():
    emu, _ = make()
    assert talk(emu, b"\n") == ["ok"]
    assert talk(emu, b"g0 x1 (comment) ; more\r\n") == ["ok", "ok"]  # \r\n = two lines, as on real GRBL
    assert emu.position_deg("X") == 1.0
    assert talk(emu, b"(only a comment)\n") == ["ok"]
    assert emu.lines[-1] == "(only a comment)"


def test_status_reports_wco_first_then_overrides():
    emu, _ = make()
    r1, r2, r3 = talk(emu, b"?"), talk(emu, b"?"), talk(emu, b"?")
    assert r1 == ["<Idle|MPos:0.000,0.000|FS:0,0|WCO:0.000,0.000>"]
    assert r2 == ["<Idle|MPos:0.000,0.000|FS:0,0|Ov:100,100,100>"]
    assert r3 == ["<Idle|MPos:0.000,0.000|FS:0,0>"]
    for r in (r1, r2, r3):
        assert gp.parse_status(r[0]).mpos == {"X": 0.0, "Y": 0.0}


def test_settings_print_write_and_restore():
    emu, _ = make(axes=("X", "Y", "A"), steps_per_deg={"X": 80.0, "Y": 40.0, "A": 10.0})
    settings = gp.parse_settings(talk(emu, b"$$\n"))
    assert settings[100] == 80.0 and settings[101] == 40.0 and settings[103] == 10.0 and 102 not in settings
    assert settings[110] == 500.0 and settings[22] == 0
    assert talk(emu, b"$100=100\n") == ["ok"] and emu.settings[100] == 100.0
    assert talk(emu, b"$RST=$\n") == ["[MSG:Restoring defaults]", "ok"] and emu.settings[100] == 80.0


def test_instant_moves_are_quantised_to_steps():
    emu, _ = make()
    assert talk(emu, b"G90 G0 X12.5 Y-0.01\n") == ["ok"]
    assert emu.position_deg("X") == 12.5 and emu.position_deg("Y") == -0.0125  # 0.8 step -> 1 step
    assert emu.state == "Idle"
    assert talk(emu, b"G91 G0 X1\n") == ["ok"] and emu.position_deg("X") == 13.5
    assert talk(emu, b"G20 G90 G0 X1\n") == ["ok"] and emu.position_deg("X") == pytest.approx(25.4, abs=0.0125)


def test_move_follows_a_trapezoid_in_scaled_time():
    emu, clock = make(time_scale=1.0)
    configure(emu)
    T = move_duration_s(30.0, 30.0, 60.0)  # 1.5 s: 0.5 s ramps, 0.5 s cruise
    assert T == pytest.approx(1.5)
    talk(emu, b"G90 G0 X30\n")
    samples = []
    for _k in range(1, 15):
        clock.t += T / 15
        samples.append((emu.state, emu.position_deg("X")))
    assert all(s == "Run" for s, _ in samples)
    xs = [x for _, x in samples]
    assert xs == sorted(xs) and 0 < xs[0] < xs[-1] < 30
    assert xs[0] == pytest.approx(0.5 * 60 * 0.1**2, abs=0.0125)  # t=0.1 s: accelerating, a t^2 / 2
    assert xs[6] == pytest.approx(7.5 + 30 * 0.2, abs=0.0125)  # t=0.7 s: 0.5 s ramp, then cruising
    assert xs[11] == pytest.approx(30 - 0.5 * 60 * 0.3**2, abs=0.0125)  # t=1.2 s: decelerating
    st = gp.parse_status(talk(emu, b"?")[0])
    assert st.state == "Run" and st.feed == pytest.approx(60.0 * 0.1 * 60, abs=1.0)  # a*t in deg/min
    clock.t += T / 15 + 1e-9
    assert emu.state == "Idle" and emu.position_deg("X") == 30.0


def moving(*, after_s: float):
    """A configured emulator ``after_s`` seconds (real-time scale) into ``G0 X30``, and its clock."""
    emu, clock = make(time_scale=1.0)
    configure(emu)
    talk(emu, b"G0 X30\n")
    clock.t += after_s
    return emu, clock


def test_queued_moves_run_back_to_back():
    emu, clock = make(time_scale=1.0)
    configure(emu)
    assert talk(emu, b"G0 X30\nG0 X0\n") == ["ok", "ok"]
    clock.t += 1.5 + 0.75
    assert emu.state == "Run" and emu.position_deg("X") == pytest.approx(15.0, abs=0.02)
    clock.t += 0.75
    assert emu.state == "Idle" and emu.position_deg("X") == 0.0


def test_feed_hold_and_resume():
    emu, clock = moving(after_s=0.75)
    assert talk(emu, b"!") == []
    assert (emu.state, emu.substate) == ("Hold", 1)  # decelerating: v/a = 0.5 s
    held = emu.position_deg("X")
    assert talk(emu, b"$$\n") == ["error:8"]
    clock.t += 0.6
    assert (emu.state, emu.substate) == ("Hold", 0) and emu.position_deg("X") == held
    assert talk(emu, b"?")[0].startswith("<Hold:0|MPos:")
    talk(emu, b"~")
    assert emu.state == "Run"
    clock.t += 5
    assert emu.state == "Idle" and emu.position_deg("X") == 30.0


def test_soft_reset_mid_move_alarm_3_then_banner_then_unlock():
    emu, clock = moving(after_s=0.75)
    out = talk(emu, b"\x18")
    assert out == ["ALARM:3", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    pos = emu.position_deg("X")
    assert 0 < pos < 30
    clock.t += 5
    assert emu.state == "Alarm" and emu.position_deg("X") == pos  # motion discarded, counters kept
    assert talk(emu, b"G0 X1\n") == ["error:9"]
    assert talk(emu, b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]
    assert emu.state == "Idle"


def test_reset_from_hold_complete_keeps_position_without_alarm():
    emu, clock = moving(after_s=0.75)
    talk(emu, b"!")
    clock.t += 1.0
    pos = emu.position_deg("X")
    assert talk(emu, b"\x18") == ["Grbl 1.1h ['$' for help]"]
    assert emu.state == "Idle" and emu.position_deg("X") == pos
    assert emu.reset_mid_move() is False


def test_critical_alarm_blocks_everything_until_reset():
    emu, clock = moving(after_s=0.3)
    emu.inject_alarm(1)
    assert talk(emu, b"") == ["ALARM:1", "[MSG:Reset to continue]"]
    assert emu.critical
    assert talk(emu, b"?") == [] and talk(emu, b"$X\n") == [] and talk(emu, b"G0 X1\n") == []
    assert talk(emu, b"\x18") == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert emu.state == "Alarm" and not emu.critical
    assert talk(emu, b"?")[0].startswith("<Alarm|")


@pytest.mark.parametrize("code", range(3, 11))
def test_noncritical_alarms_still_answer_status(code):
    emu, _ = make()
    emu.inject_alarm(code)
    assert talk(emu, b"?") == [f"ALARM:{code}", "<Alarm|MPos:0.000,0.000|FS:0,0|WCO:0.000,0.000>"]


def test_soft_limits_raise_critical_alarm_2():
    emu, _ = make(homing=True)
    assert emu.state == "Alarm"  # HOMING_INIT_LOCK
    assert talk(emu, b"$20=1\n$X\n") == ["ok", "[MSG:Caution: Unlocked]", "ok"]
    assert talk(emu, b"G0 X10\n") == ["ok"]
    assert talk(emu, b"G0 X-5\n") == ["ALARM:2", "[MSG:Reset to continue]"]
    assert emu.critical and emu.position_deg("X") == 10.0


def test_homing_cycle_in_scaled_time():
    emu, clock = make(homing=True, time_scale=1.0)
    assert talk(emu, b"G0 X5\n") == ["error:9"]
    assert talk(emu, b"$X\nG0 X50 Y20\n") == ["[MSG:Caution: Unlocked]", "ok", "ok"]
    clock.t += 100
    assert talk(emu, b"$H\n?") == []  # no ok yet, and no status during homing
    assert emu.state == "Home"
    assert talk(emu, b"G0 X1\n") == []  # waits in the serial buffer
    clock.t += 50 / (500 / 60) + 2 * 1.0 / (25 / 60) + 0.01
    assert talk(emu, b"") == ["ok", "ok"]  # homing done, then the buffered line ran
    assert emu.state == "Run"
    clock.t += 2
    assert emu.state == "Idle" and emu.positions() == {"X": 1.0, "Y": 0.0}


def test_single_axis_homing_and_homing_failure():
    emu, _ = make(homing=True)
    talk(emu, b"$X\nG0 X10 Y10\n")
    assert talk(emu, b"$HZ\n") == ["error:3"]  # no Z axis fitted
    assert talk(emu, b"$HY\n") == ["ok"]
    assert emu.positions() == {"X": 10.0, "Y": 0.0}
    emu.fail_homing = 9
    assert talk(emu, b"$H\n") == ["ALARM:9"]
    assert emu.state == "Alarm"
    no_h, _ = make(homing=True, options="V")
    assert talk(no_h, b"$HX\n") == ["error:3"]


def test_reset_during_homing_is_alarm_6():
    emu, clock = make(homing=True, time_scale=1.0)
    talk(emu, b"$X\nG0 X50\n")
    clock.t += 100
    talk(emu, b"$H\n")
    clock.t += 1
    assert talk(emu, b"\x18")[0] == "ALARM:6"


def test_dwell_answers_after_motion_and_time():
    emu, clock = make(time_scale=1.0)
    configure(emu)
    assert talk(emu, b"G0 X30\nG4 P2\n") == ["ok"]
    clock.t += 1.5 + 1.9
    assert talk(emu, b"") == []
    clock.t += 0.2
    assert talk(emu, b"") == ["ok"]


def test_check_mode_parses_without_moving():
    emu, _ = make()
    assert talk(emu, b"$C\n") == ["[MSG:Enabled]", "ok"]
    assert emu.state == "Check"
    assert talk(emu, b"G0 X10\n") == ["ok"] and emu.position_deg("X") == 0.0
    assert talk(emu, b"$C\n") == ["[MSG:Disabled]", "ok", "Grbl 1.1h ['$' for help]"]
    assert emu.state == "Idle"


def test_jog_and_jog_cancel():
    emu, clock = make(time_scale=1.0)
    configure(emu)
    assert talk(emu, b"$J=G91 X20 F600\n") == ["ok"]
    clock.t += 0.5
    assert emu.state == "Jog"
    assert talk(emu, b"G0 X1\n") == ["error:9"]
    talk(emu, b"\x85")
    assert emu.state == "Idle" and 0 < emu.position_deg("X") < 20


def test_door_holds_and_resumes():
    emu, clock = moving(after_s=0.5)
    emu.open_door()
    out = talk(emu, b"?")
    assert out[0] == "[MSG:Check Door]" and out[1].startswith("<Door:1|")
    assert (emu.state, emu.substate) == ("Door", 1)
    talk(emu, b"~")
    assert emu.state == "Door"  # cannot resume while ajar
    emu.close_door()
    talk(emu, b"~")
    clock.t += 5
    assert emu.state == "Idle" and emu.position_deg("X") == 30.0


def test_sleep_then_reset_is_alarm():
    emu, _ = make()
    assert talk(emu, b"$SLP\n") == ["[MSG:Sleeping]", "ok"]
    assert talk(emu, b"G0 X1\n") == []
    assert talk(emu, b"?")[0].startswith("<Sleep|")
    talk(emu, b"\x18")
    assert emu.state == "Alarm"


def test_information_commands():
    emu, _ = make()
    assert talk(emu, b"$I\n") == ["[VER:1.1h.20190830:]", "[OPT:VH,15,128]", "ok"]
    assert talk(emu, b"$G\n") == ["[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok"]
    assert talk(emu, b"G1 G91 X1 F300\n$G\n")[1] == "[GC:G1 G54 G17 G21 G91 G94 M5 M9 T0 F300 S0]"
    assert talk(emu, b"$N\n") == ["$N0=", "$N1=", "ok"]
    assert talk(emu, b"$#\n")[-3:] == ["[TLO:0.000]", "[PRB:0.000,0.000:0]", "ok"]
    assert talk(emu, b"$\n")[0].startswith("[HLP:")
    assert talk(emu, b"M30\n") == ["[MSG:Pgm End]", "ok"]


def test_fault_knobs_lose_lines_and_force_errors():
    emu, _ = make()
    emu.lose_lines = 1
    assert talk(emu, b"G0 X5\n") == [] and emu.position_deg("X") == 0.0
    emu.force_errors = [33]
    assert talk(emu, b"G0 X5\n") == ["error:33"] and emu.position_deg("X") == 0.0
    assert talk(emu, b"G0 X5\n") == ["ok"] and emu.position_deg("X") == 5.0
    emu.power_cycle()
    assert talk(emu, b"")[0] == "Grbl 1.1h ['$' for help]" and emu.position_deg("X") == 0.0


def test_realtime_bytes_inside_a_line():
    emu, _ = make()
    out = talk(emu, b"G0 X?7\n")
    assert out[0].startswith("<Idle") and out[1] == "ok"
    assert emu.position_deg("X") == 7.0 and emu.realtime == [b"?"]
