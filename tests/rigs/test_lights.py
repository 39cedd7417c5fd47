"""EnttecDmx / DmxLightArray against the Enttec emulator over a real pty and over TCP."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from opacityhull.errors import ConfigError, InputError
from opacityhull.rigs import enttec_protocol as ep
from opacityhull.rigs.emulators.enttec import EnttecEmulator
from opacityhull.rigs.lights import DMX_SERIAL, DmxLightArray, EnttecDmx
from opacityhull.rigs.interfaces import LightArray
from opacityhull.rigs.transport import DeviceGone, DeviceTimeout


def test_set_levels_reaches_the_universe_and_switches_others_off(enttec, wait_for):
    e = enttec(channels={0: 1, 1: 2, 2: 3, 3: 10})
    arr = e.array
    assert isinstance(arr, LightArray) and arr.light_ids == (0, 1, 2, 3) and arr.rotation is None
    arr.set_levels({0: 255, 3: 7})
    wait_for(lambda: e.emu.dmx_packets == 1, what="first DMX packet")
    u = e.emu.levels()
    assert len(u) == 512 and u[0] == 255 and u[9] == 7 and sum(u) == 262
    assert arr.levels() == {0: 255, 1: 0, 2: 0, 3: 7}
    arr.set_levels({1: 128})
    wait_for(lambda: e.emu.dmx_packets == 2, what="second DMX packet")
    assert e.emu.level(2) == 128 and e.emu.level(1) == 0 and e.emu.level(10) == 0
    arr.all_off()
    wait_for(lambda: e.emu.dmx_packets == 3, what="all off")
    assert e.emu.levels() == bytes(512) and arr.levels() == {0: 0, 1: 0, 2: 0, 3: 0}
    assert e.emu.other_start_codes == [] and e.emu.bad_frames == []


@pytest.mark.parametrize(
    "levels,match",
    [
        ({0: 256}, "light 0: level 256 is outside 0..255"),
        ({1: -1}, "light 1: level -1 is outside 0..255"),
        ({2: 1.5}, "light 2: level 1.5 is not an integer"),
        ({2: math.nan}, "light 2: level nan is not an integer"),
        ({0: True}, "light 0: level True is not an integer"),
        ({0: "255"}, "light 0: level '255' is not an integer"),
        ({7: 10}, r"unknown light id 7 \(known ids: \[0, 1, 2, 3\]\)"),
        ({"0": 10}, "unknown light id '0'"),
        ({0: 10, 9: 1}, "unknown light id 9"),
        ([(0, 10)], "must be a mapping"),
    ],
)
def test_bad_levels_are_rejected_before_a_byte_is_sent(enttec, levels, match):
    e = enttec()
    before = bytes(e.emu.received)
    with pytest.raises(InputError, match=match):
        e.array.set_levels(levels)
    assert bytes(e.emu.received) == before and e.emu.dmx_packets == 0
    assert e.array.levels() == {0: 0, 1: 0, 2: 0, 3: 0}


def test_numpy_integers_are_accepted(enttec, wait_for):
    e = enttec()
    e.array.set_levels({np.int64(2): np.uint8(200)})
    wait_for(lambda: e.emu.dmx_packets == 1, what="DMX packet")
    assert e.emu.level(3) == 200


def test_vanished_widget_is_device_gone_and_all_off_never_raises(enttec):
    e = enttec()
    e.array.set_levels({0: 50})
    e.server.vanish()
    with pytest.raises(DeviceGone) as ei:
        e.array.set_levels({0: 60})
    assert "dmx" in str(ei.value) and e.server.url in str(ei.value) and "unplugged" in str(ei.value)
    assert e.array.levels()[0] == 50  # what was last sent successfully
    e.array.all_off()
    assert isinstance(e.array.last_error, DeviceGone)
    info = e.array.check()
    assert not info.ok


def test_check_reports_parameters_and_serial(enttec):
    e = enttec(emu_kw={"serial": 0x00201234, "firmware": (1, 44)})
    info = e.array.check()
    assert info.ok and info.identity == "Enttec DMX USB Pro serial 00201234"
    assert info.state["firmware"] == "1.44" and info.state["rate_hz"] == 40
    assert "break 96 us" in info.detail and e.server.url in info.detail
    assert info.state["channels"] == {0: 1, 1: 2, 2: 3, 3: 4}


def test_widget_parameters_round_trip_through_the_widget(enttec):
    e = enttec()
    e.dmx.set_widget_parameters(break_time=20, mab_time=5, rate_hz=30)
    p = e.dmx.get_widget_parameters(user_config_size=3)
    assert (p.firmware, p.break_time, p.mab_time, p.rate_hz, p.user_config) == ((1, 44), 20, 5, 30, bytes(3))
    assert e.dmx.get_serial_number() == "12345678"


def test_hung_widget_times_out_naming_what_to_check(enttec, open_silent):
    e = enttec(open=False)
    msg = open_silent(e, e.dmx)
    assert "dmx" in msg and "Get Widget Parameters" in msg and "DMX USB Pro" in msg
    info = e.array.check()
    assert not info.ok and "Open DMX" in info.detail


def test_garbled_and_truncated_replies_then_recovery(enttec):
    e = enttec()
    e.emu.faults.garble = 1
    with pytest.raises(DeviceTimeout, match="last bad bytes"):
        e.dmx.get_serial_number()
    assert e.dmx.get_serial_number() == "12345678"
    e.emu.faults.truncate = 1
    with pytest.raises(DeviceTimeout):
        e.dmx.get_widget_parameters()
    assert e.dmx.get_widget_parameters().rate_hz == 40


def test_late_reply_is_flushed_before_the_next_request(enttec, wait_for):
    e = enttec()
    e.emu.faults.late, e.emu.faults.late_s = 1, 0.5
    with pytest.raises(DeviceTimeout):
        e.dmx.get_serial_number()
    wait_for(lambda: e.server.backlog == 0, what="late reply delivered")
    e.emu.serial = 0x99999999
    assert e.dmx.get_serial_number() == "99999999"  # not the stale 12345678


def test_keepalive_resends_and_reports_a_dead_widget(enttec, wait_for):
    e = enttec()
    e.array.set_levels({2: 9})
    e.dmx.start_keepalive(0.01)
    wait_for(lambda: e.emu.dmx_packets >= 4, what="keepalive re-sends")
    assert e.emu.history[-1] == e.emu.history[0] and e.emu.level(3) == 9
    e.server.vanish()
    wait_for(lambda: e.dmx.keepalive_error is not None, what="keepalive to notice")
    with pytest.raises(DeviceGone):
        e.array.set_levels({2: 10})
    e.dmx.stop_keepalive()


def test_refresh_resends_current_levels(enttec, wait_for):
    e = enttec()
    e.array.set_levels({3: 77})
    e.array.refresh()
    wait_for(lambda: e.emu.dmx_packets == 2, what="two packets")
    assert e.emu.history[0] == e.emu.history[1] and e.emu.level(4) == 77


def test_rotation_is_a_grbl_axis_on_the_shared_controller(enttec, grbl):
    g = grbl()
    e = enttec(rotation=g.lights)
    assert e.array.rotation is g.lights
    assert e.array.rotation.move_to(45.0) == 45.0 and g.emu.position_deg("Y") == 45.0


@pytest.mark.parametrize(
    "channels,match",
    [
        ({}, "non-empty"),
        ({0: 0}, r"channels.0 = 0, expected a DMX channel 1..512"),
        ({0: 513}, "channels.0 = 513"),
        ({0: 1.0}, "channels.0 = 1.0"),
        ({"a": 1}, "key 'a' is not an integer light id"),
        ({-1: 1}, "not a light id"),
        ({0: 1, "0": 2}, "light id 0 appears twice"),
        ({0: 5, 1: 5}, "lights 0 and 1 are both on DMX channel 5"),
    ],
)
def test_channel_map_errors_name_the_key(channels, match):
    dmx = EnttecDmx.from_url("loop://", name="dmx")
    with pytest.raises(ConfigError, match=match):
        DmxLightArray(dmx, channels=channels, name="light_array")


def test_toml_string_keys_are_light_ids():
    arr = DmxLightArray(EnttecDmx.from_url("loop://"), channels={"3": 4, "1": 2})
    assert arr.light_ids == (1, 3) and arr.channels == {1: 2, 3: 4}


def test_driver_config_errors():
    with pytest.raises(ConfigError, match="universe_size = 10"):
        EnttecDmx.from_url("loop://", universe_size=10)
    with pytest.raises(ConfigError, match="timeout_s"):
        EnttecDmx.from_url("loop://", serial=replace(DMX_SERIAL, timeout_s=0))
    with pytest.raises(InputError, match="513 DMX channels given"):
        EnttecDmx.from_url("loop://").send_dmx(bytes(513))


# ---------------------------------------------------------------------------- emulator alone


def test_emulator_applies_dmx_and_flags_malformed_frames():
    emu = EnttecEmulator(universe_size=512)
    assert emu.receive(ep.encode_send_dmx(bytes([1, 2, 3]) + bytes(100))) == []
    assert emu.levels()[:4] == bytes([1, 2, 3, 0]) and emu.dmx_packets == 1
    emu.receive(ep.encode(6, b"\x00\x09\x09"))  # 2 channels < 24: ignored, flagged
    emu.receive(ep.encode_send_dmx(bytes([200] * 30), start_code=0xCC))  # RDM start code: not levels
    emu.receive(b"\x01\x02garbage")
    emu.receive(ep.encode(42, b"?"))  # unknown label: ignored
    assert emu.levels()[:4] == bytes([1, 2, 3, 0]) and emu.dmx_packets == 1
    assert emu.other_start_codes == [0xCC] and [f.label for f in emu.ignored] == [42]
    reasons = [b.reason for b in emu.bad_frames]
    assert "noise" in reasons and any("2 channels < 24" in r for r in reasons)
    emu.receive(ep.encode_send_dmx(bytes([5] * 24)))  # shorter packet: channels 25.. not transmitted
    assert emu.levels()[:24] == bytes([5] * 24) and emu.levels()[24:] == bytes(488)
    assert emu.frames_received == 5  # the garbage is not a frame


def test_emulator_answers_labels_3_and_10():
    emu = EnttecEmulator(serial=0x87654321, firmware=(2, 10))
    (r,) = emu.receive(ep.encode_get_widget_parameters(2))
    p = ep.parse_widget_parameters(ep.decode_one(r.data))
    assert p.firmware == (2, 10) and p.user_config == b"\x00\x00"
    (r,) = emu.receive(ep.encode_get_serial())
    assert ep.parse_serial(ep.decode_one(r.data)) == "87654321"
    emu.faults.silent = True
    assert emu.receive(ep.encode_get_serial()) == [] and emu.receive(ep.encode_send_dmx(bytes(24))) == []
    assert emu.dmx_packets == 0
