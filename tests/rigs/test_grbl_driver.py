"""GrblController / GrblAxis against the GRBL emulator over a real pty and over TCP.

Every test runs on both transports (``kind``). Moves are instant (time_scale=0) unless a
test needs a move in progress; then it waits on the emulator's state, never on time.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from opacityhull.errors import ConfigError, DeviceError, InputError
from opacityhull.rigs import grbl_protocol as gp
from opacityhull.rigs.motion import (
    GRBL_SERIAL,
    GrblAlarm,
    GrblAxis,
    GrblCommandError,
    GrblController,
    GrblInterrupted,
    move_duration_s,
)
from opacityhull.rigs.interfaces import RotaryAxis
from opacityhull.rigs.transport import DeviceGone, DeviceTimeout, ProtocolError


def count(emu, line: str) -> int:
    return sum(1 for ln in emu.lines if ln == line)


def setting_writes(emu) -> list[str]:
    return [ln for ln in emu.lines if ln.startswith("$") and "=" in ln]


# ---------------------------------------------------------------------------- open / identity


def test_open_reads_identity_and_writes_only_differing_settings(grbl):
    g = grbl()
    assert g.ctl.version == "1.1h" and g.ctl.build == "1.1h.20190830" and g.ctl.single_axis_homing
    assert g.emu.settings[100] == 80.0 and g.emu.settings[101] == 80.0
    assert g.emu.settings[110] == 1800.0 and g.emu.settings[121] == 60.0
    writes = setting_writes(g.emu)
    assert sorted(writes) == sorted(
        ["$100=80.000", "$101=80.000", "$110=1800.000", "$111=1800.000", "$120=60.000", "$121=60.000"]
    )
    g.ctl.close()
    g.ctl.open()
    assert setting_writes(g.emu) == writes  # already right: EEPROM untouched
    assert isinstance(g.turntable, RotaryAxis) and isinstance(g.lights, RotaryAxis)
    assert set(g.ctl.axes) == {"X", "Y"}


def test_open_a_silent_port_times_out_naming_device_url_and_what_to_check(grbl, open_silent):
    g = grbl(open=False)
    msg = open_silent(g, g.ctl)
    assert "grbl" in msg and "GRBL 1.1 at 115200 baud" in msg
    assert b"?" in g.emu.received and b"\x18" in g.emu.received  # asked, then provoked a banner


def test_open_recovers_a_halted_controller_with_a_soft_reset(grbl):
    g = grbl(open=False)
    g.emu.inject_alarm(1)  # critical: '?' is not answered
    g.ctl.open(unlock=True)
    assert g.emu.realtime.count(b"\x18") == 1
    assert g.emu.state == "Idle" and g.ctl.status().state == "Idle"


def test_open_refuses_a_busy_controller_and_reset_clears_a_hold(grbl, wait_for):
    g = grbl(open=False, emu_kw={"time_scale": 1.0})
    with g.emu.lock:  # another program started a long move
        g.emu.receive(b"G0 X90\n")
    assert g.emu.state == "Run"
    with pytest.raises(GrblInterrupted) as ei:
        g.ctl.open()
    assert ei.value.state == "Run" and "busy" in str(ei.value)
    with g.emu.lock:
        g.emu.receive(b"!")
    wait_for(lambda: g.emu.substate == 0, what="hold complete")
    with pytest.raises(GrblInterrupted) as ei:
        g.ctl.open()
    assert ei.value.state == "Hold"
    held = g.emu.position_deg("X")
    g.ctl.open(reset=True)  # what Rig does after a safe() exit left a feed hold
    assert g.emu.state == "Idle" and g.emu.position_deg("X") == held
    assert g.turntable.position_deg() == pytest.approx(held, abs=1e-3)


# ---------------------------------------------------------------------------- moves


def test_move_to_and_position(grbl):
    g = grbl()
    assert g.turntable.move_to(12.5) == pytest.approx(12.5, abs=g.turntable.tolerance_deg)
    assert g.emu.position_deg("X") == 12.5 and g.emu.lines[-1] == "G90 G0 X12.500"
    assert g.turntable.position_deg() == 12.5
    assert g.lights.move_to(-45.0) == -45.0 and g.emu.positions() == {"X": 12.5, "Y": -45.0}
    assert g.turntable.move_to(12.5) == 12.5 and count(g.emu, "G90 G0 X12.500") == 1  # already there


def test_continuous_axis_takes_the_short_way(grbl):
    g = grbl()
    assert g.turntable.move_to(350.0) == pytest.approx(350.0)
    assert g.emu.position_deg("X") == -10.0 and g.turntable.position_deg() == pytest.approx(350.0)
    assert g.turntable.move_to(190.0) == pytest.approx(190.0)
    assert g.emu.position_deg("X") == -170.0  # -10 -> -170 is 160 degrees; +200 would be the long way
    assert g.turntable.move_to(-720.0 + 5.0) == pytest.approx(-715.0)
    assert g.emu.position_deg("X") == 5.0  # -170 -> 5 is +175 degrees (the other way is 185)
    assert g.turntable.position_deg() == pytest.approx(5.0)
    info = g.turntable.check()
    assert info.ok and info.state["position_deg"] == pytest.approx(5.0) and "Grbl 1.1h" in info.identity


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "90", None, True, 1e6])
def test_bad_angles_are_rejected_before_a_byte_is_sent(grbl, bad):
    g = grbl()
    before = bytes(g.emu.received)
    with pytest.raises(InputError, match="turntable"):
        g.turntable.move_to(bad)
    with pytest.raises(InputError, match="light_rotation"):
        g.lights.move_to(bad)
    assert bytes(g.emu.received) == before


def test_soft_limits_are_checked_before_sending(grbl):
    g = grbl()
    before = bytes(g.emu.received)
    with pytest.raises(InputError, match=r"181 deg is outside soft_limits_deg \[-180, 180\]"):
        g.lights.move_to(181.0)
    assert bytes(g.emu.received) == before
    assert g.lights.move_to(180.0) == 180.0 and g.lights.position_deg() == 180.0  # limited: not wrapped


def test_backlash_targets_are_always_approached_moving_up(grbl):
    g = grbl(backlash_deg=2.0)
    ax = g.lights
    ax.move_to(10.0)  # up by more than the backlash: direct
    ax.move_to(5.0)  # down: overshoot to 3, come back up
    ax.move_to(6.0)  # up, gears already engaged upwards: direct
    ax.move_to(6.5)
    moves = [ln for ln in g.emu.lines if ln.startswith("G90 G0 Y")]
    assert moves == ["G90 G0 Y10.000", "G90 G0 Y3.000", "G90 G0 Y5.000", "G90 G0 Y6.000", "G90 G0 Y6.500"]
    g.ctl.reset()  # direction unknown again
    ax.move_to(7.0)  # up by less than the backlash: take up the slack from below first
    assert [ln for ln in g.emu.lines if ln.startswith("G90 G0 Y")][-2:] == ["G90 G0 Y5.000", "G90 G0 Y7.000"]
    assert g.emu.position_deg("Y") == 7.0
    ax.move_to(-179.0)  # the overshoot is clamped at the soft limit
    assert [ln for ln in g.emu.lines if ln.startswith("G90 G0 Y")][-2:] == ["G90 G0 Y-180.000", "G90 G0 Y-179.000"]


def test_two_axes_on_one_controller_and_config_errors(grbl):
    g = grbl()
    with pytest.raises(ConfigError, match="axis X .* already used by 'turntable'"):
        GrblAxis(g.ctl, axis="X", steps_per_deg=80, max_rate_deg_s=30, name="other")
    c = GrblController.from_url("loop://", name="c")
    for kw, key in [
        ({"axis": "Q"}, "axis"),
        ({"steps_per_deg": 0}, "steps_per_deg"),
        ({"max_rate_deg_s": math.nan}, "max_rate_deg_s"),
        ({"accel_deg_s2": -1}, "accel_deg_s2"),
        ({"backlash_deg": 90}, "backlash_deg"),
        ({"soft_limits_deg": (5, 1)}, "soft_limits_deg"),
        ({"steps_per_deg": 2000, "max_rate_deg_s": 30}, "30 kHz"),
    ]:
        args = {"axis": "Z", "steps_per_deg": 80, "max_rate_deg_s": 30, "name": "bad", **kw}
        with pytest.raises(ConfigError, match=key):
            GrblAxis(c, **args)


def test_move_deadline_when_the_axis_is_slower_than_configured(grbl):
    g = grbl(emu_kw={"time_scale": 1.0})
    g.emu.settings[110] = 60.0  # someone slowed the axis to 1 deg/s behind the driver's back
    with pytest.raises(DeviceTimeout, match=r"not finished by the deadline \(state Run"):
        g.turntable.move_to(90.0, timeout_s=0.2)
    g.ctl.cancel_motion()
    assert g.emu.state == "Idle" and 0 < g.emu.position_deg("X") < 90


# ---------------------------------------------------------------------------- lost, late, garbled


def test_lost_ok_position_is_queried_and_nothing_is_resent(grbl):
    g = grbl(timeout_s=0.3)
    g.emu.faults.match, g.emu.faults.drop = b"ok", 1
    assert g.turntable.move_to(30.0) == 30.0
    assert count(g.emu, "G90 G0 X30.000") == 1
    assert g.emu.realtime.count(b"?") >= 2  # the position was asked after the timeout
    assert g.turntable.move_to(40.0) == 40.0  # resynchronised, works on


def test_late_ok_is_neither_resent_nor_taken_for_the_next_answer(grbl, wait_for):
    g = grbl(timeout_s=0.3)
    g.emu.faults.match, g.emu.faults.late, g.emu.faults.late_s = b"ok", 1, 0.6
    assert g.turntable.move_to(30.0) == 30.0
    assert count(g.emu, "G90 G0 X30.000") == 1
    wait_for(lambda: g.server.backlog == 0, what="the late ok to be delivered")
    with pytest.raises(GrblCommandError) as ei:  # the late 'ok' must not answer this line
        g.ctl.send_line("G0 Z1")  # no Z axis fitted: error:20
    assert ei.value.code == 20
    assert b"ok" in g.ctl.discarded
    pushes = g.ctl.send_line("$I")
    assert any(isinstance(p, gp.Message) and p.kind == "VER" for p in pushes)


def test_garbled_ok_position_is_queried_and_nothing_is_resent(grbl):
    g = grbl()
    g.emu.faults.match, g.emu.faults.garble = b"ok", 1
    assert g.turntable.move_to(45.0) == 45.0
    assert count(g.emu, "G90 G0 X45.000") == 1 and g.emu.faults.log[-1][0] == "garble"


def test_truncated_ok_position_is_queried_and_nothing_is_resent(grbl):
    g = grbl(timeout_s=0.3)
    g.emu.faults.match, g.emu.faults.truncate = b"ok", 1
    assert g.turntable.move_to(45.0) == 45.0
    assert count(g.emu, "G90 G0 X45.000") == 1


def test_line_lost_on_the_way_in_is_resent_once(grbl):
    g = grbl(timeout_s=0.3)
    g.emu.lose_lines = 1
    assert g.turntable.move_to(20.0) == 20.0
    assert count(g.emu, "G90 G0 X20.000") == 2
    g.turntable.retries = 0
    g.emu.lose_lines = 1
    with pytest.raises(DeviceTimeout, match="never arrived"):
        g.turntable.move_to(25.0)
    assert g.emu.position_deg("X") == 20.0


def test_garbled_status_raises_protocol_error_quoting_the_bytes(grbl):
    g = grbl()
    g.turntable.move_to(10.0)
    g.emu.faults.match, g.emu.faults.garble = b"<", 1
    with pytest.raises(ProtocolError) as ei:
        g.ctl.status()
    assert "garbled status report" in str(ei.value) and g.server.url in str(ei.value)
    kind_, original = g.emu.faults.log[-1]
    body = original.rstrip(b"\r\n")
    garbled = bytes(b ^ 0x5A if i % 2 == 0 else b for i, b in enumerate(body))
    assert kind_ == "garble" and repr(garbled)[:-1] in str(ei.value)
    assert g.turntable.position_deg() == 10.0


def test_garbled_status_during_a_move_is_tolerated(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 0.1})
    fut = background(g.turntable.move_to, 60.0)
    wait_for(lambda: g.emu.state == "Run", what="move started")
    g.emu.faults.match, g.emu.faults.garble = b"<", 1
    assert fut.result(timeout=10) == 60.0


def test_status_timeout_names_device_url_and_what_to_check(grbl):
    g = grbl(timeout_s=0.2)
    g.emu.faults.silent = True
    with pytest.raises(DeviceTimeout) as ei:
        g.ctl.status()
    msg = str(ei.value)
    assert "grbl" in msg and g.server.url in msg and "status report" in msg and "115200 baud" in msg
    with pytest.raises(DeviceTimeout):
        g.turntable.position_deg()


def test_a_stale_status_report_is_never_returned_for_a_new_query(grbl):
    g = grbl(timeout_s=0.5)
    g.turntable.move_to(30.0)
    g.emu.faults.delay_s = 0.8  # this report (X=30) arrives after the query gave up
    with pytest.raises(DeviceTimeout):
        g.ctl.status()
    g.emu.faults.delay_s = 0.0
    g.emu.power_cycle()  # the truth is now X=0; the stale X=30 report is still on its way
    assert g.ctl.status().mpos["X"] == 0.0


# ---------------------------------------------------------------------------- errors and alarms


def test_every_error_code_maps_to_a_command_error(grbl):
    g = grbl()
    for code in sorted(gp.ERROR_CODES):
        g.emu.force_errors = [code]
        with pytest.raises(GrblCommandError) as ei:
            g.ctl.send_line("G4 P0")
        e = ei.value
        short, desc, hint = gp.ERROR_CODES[code]
        assert e.code == code and isinstance(e, DeviceError)
        assert f"error:{code}" in str(e) and desc in str(e) and hint in str(e) and "'G4 P0'" in str(e)
    assert g.ctl.send_line("G4 P0") == []  # the stream is still in step


def test_every_alarm_code_maps_to_a_grbl_alarm(grbl):
    g = grbl(timeout_s=0.2)
    for code in sorted(gp.ALARM_CODES):
        g.emu.inject_alarm(code)
        with pytest.raises(GrblAlarm) as ei:
            g.turntable.move_to(5.0)
        e = ei.value
        short, desc, hint = gp.ALARM_CODES[code]
        assert e.code == code and e.critical == (code in (1, 2))
        assert f"ALARM:{code} {short.lower()}" in str(e) and desc in str(e) and hint in str(e)
        g.ctl.reset()
        g.ctl.unlock()
    assert g.turntable.move_to(5.0) == 5.0
    assert "limit switch" in gp.ALARM_CODES[1][2] and "$H" in gp.ALARM_CODES[1][2]


def test_command_error_for_homing_disabled_says_what_to_do(grbl):
    g = grbl()
    with pytest.raises(GrblCommandError, match=r"error:5 .*\$22=1") as ei:
        g.turntable.home()
    assert ei.value.code == 5


def test_homing_unlocks_and_zeroes(grbl):
    g = grbl(emu_kw={"homing": True})
    assert g.ctl.status().state == "Alarm"
    with pytest.raises(GrblAlarm, match="home"):
        g.turntable.move_to(10.0)
    g.turntable.home()
    assert g.emu.lines[-1] == "$HX" and g.emu.state == "Idle"
    assert g.turntable.move_to(10.0) == 10.0
    g.turntable.home()
    assert g.emu.position_deg("X") == 0.0
    g.emu.fail_homing = 9
    with pytest.raises(GrblAlarm, match="ALARM:9 homing fail") as ei:
        g.lights.home()
    assert ei.value.code == 9 and "limit switch" in str(ei.value)


def test_homing_without_single_axis_option_homes_all(grbl):
    g = grbl(emu_kw={"homing": True, "options": "V"}, unlock=True)
    g.lights.move_to(20.0)
    g.turntable.home()
    assert g.emu.lines[-1] == "$H" and g.emu.positions() == {"X": 0.0, "Y": 0.0}


# ---------------------------------------------------------------------------- interrupted moves


def test_unplug_mid_move_is_device_gone_and_stop_never_raises(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 1.0})
    fut = background(g.turntable.move_to, 90.0)
    wait_for(lambda: g.emu.state == "Run", what="move started")
    g.server.vanish()
    with pytest.raises(DeviceGone, match="unplugged"):
        fut.result(timeout=10)
    g.turntable.stop()
    g.lights.stop()
    g.ctl.stop()
    info = g.turntable.check()
    assert not info.ok and "not open" in info.detail
    with pytest.raises(DeviceGone):
        g.turntable.position_deg()


def test_reconnect_after_replug_rereads_state(grbl):
    g = grbl()
    g.turntable.move_to(33.0)
    g.server.vanish()
    with pytest.raises(DeviceGone):
        g.turntable.position_deg()
    url = g.server.reappear()
    g.ctl.reconnect(max_attempts=3, delay_s=0.05, url=url)
    assert g.ctl.is_open and g.turntable.position_deg() == 33.0
    assert g.turntable.move_to(34.0) == 34.0


def test_reconnect_gives_up_after_bounded_attempts(grbl):
    g = grbl()
    g.server.vanish()
    with pytest.raises(DeviceGone, match="after 3 attempts") as ei:
        g.ctl.reconnect(max_attempts=3, delay_s=0.01)
    assert g.server.url in str(ei.value) and not g.ctl.is_open
    g.turntable.stop()  # still safe


def test_serial_settings_bound_reconnect_and_default_the_axes_retries():
    serial = replace(GRBL_SERIAL, retries=3, reconnect_attempts=2, reconnect_delay_s=0.01)
    c = GrblController.from_url("/dev/does-not-exist-42", name="grbl", serial=serial)
    with pytest.raises(DeviceGone, match="grbl: could not reconnect to /dev/does-not-exist-42 after 2 attempts"):
        c.reconnect()
    assert GrblAxis(c, axis="X", steps_per_deg=80, max_rate_deg_s=30).retries == 3
    assert GrblAxis(c, axis="Y", steps_per_deg=80, max_rate_deg_s=30, retries=0).retries == 0
    assert GrblAxis(GrblController.from_url("loop://"), steps_per_deg=80, max_rate_deg_s=30).retries == 1


def test_soft_reset_mid_move_surfaces_alarm_and_requeries_position(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 1.0})
    fut = background(g.turntable.move_to, 90.0)
    wait_for(lambda: g.emu.state == "Run" and g.emu.position_deg("X") > 0, what="move under way")
    assert g.emu.reset_mid_move()
    with pytest.raises(GrblAlarm) as ei:
        fut.result(timeout=10)
    e = ei.value
    assert e.code == 3 and "reset while in motion" in str(e)
    assert e.position_deg == pytest.approx(g.emu.position_deg("X"), abs=1e-3) and 0 < e.position_deg < 90
    assert f"now at {e.position_deg:.3f} deg" in str(e)
    g.ctl.unlock()
    assert g.turntable.move_to(0.0) == 0.0


def test_feed_hold_interrupts_the_move_and_resume_finishes_it(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 0.2})
    fut = background(g.turntable.move_to, 90.0)
    wait_for(lambda: g.emu.state == "Run" and g.emu.position_deg("X") > 0, what="move under way")
    g.turntable.stop()
    with pytest.raises(GrblInterrupted) as ei:
        fut.result(timeout=10)
    assert ei.value.state == "Hold" and "resume()" in str(ei.value)
    held = g.emu.position_deg("X")
    assert 0 < held < 90
    g.ctl.resume()
    wait_for(lambda: g.emu.state == "Idle", what="resumed move finished")
    assert g.emu.position_deg("X") == 90.0
    assert g.turntable.move_to(80.0) == 80.0


def test_cancel_motion_stops_without_alarm(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 1.0})
    fut = background(g.turntable.move_to, 90.0)
    wait_for(lambda: g.emu.state == "Run", what="move started")
    g.turntable.stop()
    with pytest.raises(GrblInterrupted):
        fut.result(timeout=10)
    g.ctl.cancel_motion()
    assert g.emu.state == "Idle" and g.ctl.last_alarm is None
    pos = g.emu.position_deg("X")
    assert g.turntable.position_deg() == pytest.approx(pos)


def test_safety_door_interrupts_the_move(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 1.0})
    fut = background(g.turntable.move_to, 90.0)
    wait_for(lambda: g.emu.state == "Run", what="move started")
    g.emu.open_door()
    with pytest.raises(GrblInterrupted, match="door") as ei:
        fut.result(timeout=10)
    assert ei.value.state == "Door"


def test_hard_limit_mid_move_needs_a_reset(grbl, background, wait_for):
    g = grbl(emu_kw={"time_scale": 1.0}, timeout_s=0.3)
    fut = background(g.turntable.move_to, 90.0)
    wait_for(lambda: g.emu.state == "Run", what="move started")
    g.emu.inject_alarm(1)
    with pytest.raises(GrblAlarm, match="ALARM:1 hard limit while moving turntable .* check the limit switch") as ei:
        fut.result(timeout=10)
    assert ei.value.critical
    with pytest.raises(GrblAlarm, match="ignores everything until a soft reset"):
        g.ctl.status()
    pushes = g.ctl.reset()
    assert any(isinstance(p, gp.Banner) for p in pushes)
    assert g.ctl.status().state == "Alarm"
    info = g.turntable.check()
    assert not info.ok and "ALARM:1" in info.detail
    g.ctl.unlock()
    assert g.turntable.move_to(10.0) == 10.0


def test_move_duration_matches_the_emulated_profile():
    assert move_duration_s(0, 30, 60) == 0
    assert move_duration_s(30, 30, 60) == pytest.approx(1.5)  # 0.5 s ramps + 0.5 s cruise
    assert move_duration_s(5, 30, 60) == pytest.approx(2 * math.sqrt(5 / 60))  # triangle
    assert move_duration_s(-30, 30, 60) == pytest.approx(1.5)
