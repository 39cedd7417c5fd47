"""Byte-exchange tests (pymeasure style): every driver on the in-memory transport of
:mod:`opacityhull.rigs.testing`, each write checked against bytes written out by hand
from the device's documentation (GRBL 1.1 text, Enttec DMX USB Pro API frames, the
display protocol of ``docs/display-protocol.md``: HDLC framing with CRC-16/CCITT-FALSE
from :func:`binascii.crc_hqx`, not from ``display_protocol``). The emulator tests next
to these drive the same drivers over real ptys and sockets."""

from __future__ import annotations

import binascii
import logging
import struct
import zlib
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import ConfigError, InputError
from opacityhull.rigs.backdrops import DISPLAY_SERIAL, DisplayController, DisplayNak
from opacityhull.rigs.interfaces import Port
from opacityhull.rigs.lights import DMX_SERIAL, DmxLightArray, EnttecDmx
from opacityhull.rigs.motion import GRBL_SERIAL, GrblAxis, GrblCommandError, GrblController
from opacityhull.rigs.testing import ExpectedExchangeTransport, expected_exchange
from opacityhull.rigs.transport import DeviceTimeout, Transport

# ----------------------------------------------------------------------------- GRBL 1.1


def idle(x: float = 0.0, y: float = 0.0) -> bytes:
    return f"<Idle|MPos:{x:.3f},{y:.3f}|FS:0,0>\r\n".encode()


BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
#: $100/$110 already as the axis wants them (80 steps/deg, 30 deg/s = 1800 deg/min); $120 is not
SETTINGS = (
    b"$13=0\r\n$100=80.000\r\n$101=250.000\r\n$110=1800.000\r\n$111=500.000\r\n$120=10.000\r\n$121=10.000\r\nok\r\n"
)
GRBL_OPEN = [
    (None, BANNER),  # an Arduino resets when the port opens and greets
    (b"?", idle()),
    (b"$I\n", b"[VER:1.1h.20190830:]\r\n[OPT:VH,15,128]\r\nok\r\n"),
    (b"?", idle()),
    (b"$$\n", SETTINGS),
    (b"$120=60.000\n", b"ok\r\n"),  # only the setting that differs is written
]


def grbl_with_turntable(transport: Transport) -> GrblAxis:
    ctl = GrblController(transport, serial=replace(GRBL_SERIAL, timeout_s=0.3), boot_timeout_s=0.3, poll_s=0.001)
    return GrblAxis(ctl, axis="X", steps_per_deg=80.0, max_rate_deg_s=30.0, accel_deg_s2=60.0, name="turntable")


def test_grbl_open_reads_identity_and_writes_only_the_settings_that_differ():
    with expected_exchange(grbl_with_turntable, GRBL_OPEN, name="grbl") as tt:
        tt.controller.open()
        c = tt.controller
        assert (c.version, c.build, c.options) == ("1.1h", "1.1h.20190830", "VH")
        assert c.settings[100] == 80.0 and c.settings[120] == 60.0
        assert c.is_open and c.url == "memory://expected" and isinstance(c, Port)


_MOVES = {
    "polls-until-idle": (
        [
            (b"?", idle()),
            (b"G90 G0 X90.000\n", b"ok\r\n"),
            (b"?", b"<Run|MPos:45.000,0.000|FS:1800,0>\r\n"),
            (b"?", idle(90.0)),
        ],
        90.0,
        1,
    ),
    # 350 deg on a continuous axis at 0: -10 deg is the short way
    "continuous-short-way": ([(b"?", idle()), (b"G90 G0 X-10.000\n", b"ok\r\n"), (b"?", idle(-10.0))], 350.0, 1),
    # no ``ok`` for the move: ``?`` says idle at the start, so the line never arrived;
    # ``$G`` flushes any late reply before the same absolute move is sent again
    "lost-line-resent-after-asking": (
        [
            (b"?", idle()),
            (b"G90 G0 X90.000\n", b""),  # lost
            (b"?", idle()),
            (b"$G\n", b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n"),
            (b"G90 G0 X90.000\n", b"ok\r\n"),
            (b"?", idle(90.0)),
        ],
        90.0,
        2,
    ),
}


@pytest.mark.parametrize("case", list(_MOVES))
def test_grbl_move_exchange(case):
    tail, target_deg, moves = _MOVES[case]
    with expected_exchange(grbl_with_turntable, GRBL_OPEN + tail, name="grbl") as tt:
        tt.controller.open()
        assert tt.move_to(target_deg) == pytest.approx(target_deg)
        assert tt.moves == moves


def test_grbl_error_reply_names_code_and_meaning():
    script = GRBL_OPEN + [(b"?", idle()), (b"G90 G0 X90.000\n", b"error:9\r\n")]
    with expected_exchange(grbl_with_turntable, script, name="grbl") as tt:
        tt.controller.open()
        with pytest.raises(GrblCommandError) as ei:
            tt.move_to(90.0)
    assert ei.value.code == 9 and "error:9" in str(ei.value) and "grbl" in str(ei.value)


def test_grbl_stop_is_one_feed_hold_byte_without_a_reply():
    with expected_exchange(grbl_with_turntable, GRBL_OPEN + [(b"!", b"")], name="grbl") as tt:
        tt.controller.open()
        tt.stop()


def test_grbl_silent_port_is_a_timeout_naming_the_device():
    """Nothing answers ``?`` nor the soft reset (0x18) that follows."""
    script = [(b"?", b""), (b"?", b""), (b"\x18", b"")]

    def make(t):
        return GrblController(t, serial=replace(GRBL_SERIAL, timeout_s=0.1), boot_timeout_s=0.5)

    with expected_exchange(make, script, name="grbl") as c, pytest.raises(DeviceTimeout) as ei:
        c.open()
    msg = str(ei.value)
    assert "grbl" in msg and "silent" in msg and not c.is_open


# ----------------------------------------------------------------------------- Enttec DMX USB Pro


def enttec(label: int, data: bytes = b"") -> bytes:
    """An Enttec API frame: 0x7E, label, data length (LSB, MSB), data, 0xE7."""
    return bytes([0x7E, label, len(data) & 0xFF, len(data) >> 8]) + data + b"\xe7"


#: label 3 reply: firmware 1.44, break 9 x 10.67 us, MAB 1 x 10.67 us, 40 packets/s
PARAMS = enttec(3, bytes([44, 1, 9, 1, 40]))


def dmx_array(transport: Transport) -> DmxLightArray:
    dmx = EnttecDmx(transport, universe_size=24, serial=replace(DMX_SERIAL, timeout_s=0.3))
    return DmxLightArray(dmx, channels={0: 1, 1: 2}, name="light_array")


def test_enttec_open_asks_the_widget_parameters():
    with expected_exchange(dmx_array, [(enttec(3, b"\x00\x00"), PARAMS)], name="dmx") as arr:
        arr.dmx.open()
        p = arr.dmx.parameters
        assert p is not None and p.rate_hz == 40


def test_enttec_set_levels_sends_one_universe_with_start_code_zero():
    universe = bytes([0, 200]) + bytes(22)
    script = [
        (enttec(3, b"\x00\x00"), PARAMS),
        (enttec(6, b"\x00" + universe), b""),
        (enttec(6, b"\x00" + bytes(24)), b""),
    ]
    with expected_exchange(dmx_array, script, name="dmx") as arr:
        arr.dmx.open()
        arr.set_levels({1: 200})
        assert arr.levels() == {0: 0, 1: 200}
        arr.all_off()
        assert arr.last_error is None


def test_enttec_check_reads_parameters_and_serial_number():
    script = [
        (enttec(3, b"\x00\x00"), PARAMS),
        (enttec(3, b"\x00\x00"), PARAMS),
        (enttec(10), enttec(10, struct.pack("<I", 0x12345678))),
    ]
    with expected_exchange(dmx_array, script, name="dmx") as arr:
        arr.dmx.open()
        info = arr.check()
    assert info.ok and "12345678" in info.identity


def test_enttec_bad_level_sends_nothing():
    with expected_exchange(dmx_array, [(enttec(3, b"\x00\x00"), PARAMS)], name="dmx") as arr:
        arr.dmx.open()
        with pytest.raises(InputError):
            arr.set_levels({1: 256})


# ----------------------------------------------------------------------------- display controller


def hdlc(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    """A frame of docs/display-protocol.md: flag, escaped SEQ|CMD|PAYLOAD|CRC16-BE, flag."""
    body = bytes([seq, cmd]) + payload
    body += struct.pack(">H", binascii.crc_hqx(body, 0xFFFF))  # CRC-16/CCITT-FALSE
    esc = bytearray()
    for b in body:
        esc += bytes([0x7D, b ^ 0x20]) if b in (0x7D, 0x7E) else bytes([b])
    return b"\x7e" + bytes(esc) + b"\x7e"


ACK, NAK = 0x06, 0x15


def ack(seq: int, cmd: int, data: bytes = b"") -> bytes:
    return hdlc(seq, ACK, bytes([cmd]) + data)


def displays(transport: Transport) -> DisplayController:
    return DisplayController(
        transport,
        outputs={"bottom": 0, "back": 1},
        serial=replace(DISPLAY_SERIAL, timeout_s=0.2, retries=1, reconnect_attempts=0),
    )


def test_crc_oracle_is_ccitt_false():
    assert binascii.crc_hqx(b"123456789", 0xFFFF) == 0x29B1


def test_display_show_powers_the_panel_then_shows_the_pattern():
    # STATE: 2 outputs (power u8, shown u16 with 0xFFFF = blank), then 1 stored id (u16)
    state = bytes([2, 0, 0xFF, 0xFF, 1, 0x00, 0x07]) + b"\x00\x01\x00\x07"
    script = [
        (hdlc(1, 0x10, b"\x01\x01"), ack(1, 0x10)),  # POWER output 1 on
        (hdlc(2, 0x11, b"\x01\x00\x07"), ack(2, 0x11)),  # SHOW output 1, pattern 7
        (hdlc(3, 0x02), ack(3, 0x02, state)),  # STATE
        (hdlc(4, 0x12, b"\xff"), ack(4, 0x12)),
    ]  # BLANK all
    with expected_exchange(displays, script, name="backdrops") as d:
        d.open()
        d.show("back", 7)
        assert d.shown() == {"bottom": None, "back": 7}
        d.blank()
        assert d.last_error is None


def test_display_upload_is_begin_chunks_end_with_a_crc32():
    img = np.full((2, 3, 3), 200, np.uint8)
    data = img.tobytes()
    script = [
        (hdlc(1, 0x23, b"\x00\x01"), hdlc(1, NAK, b"\x23\x05")),  # INFO: no such pattern yet
        (hdlc(2, 0x20, b"\x00\x01\x00\x03\x00\x02"), ack(2, 0x20)),  # BEGIN id 1, 3 wide, 2 high
        (hdlc(3, 0x21, b"\x00\x01\x00\x00\x00\x00" + data), ack(3, 0x21, b"\x00\x00\x00\x00")),  # @0
        (hdlc(4, 0x22, b"\x00\x01" + struct.pack(">I", zlib.crc32(data))), ack(4, 0x22)),
    ]
    with expected_exchange(displays, script, name="backdrops") as d:
        d.open()
        d.upload("back", 1, img)


def test_display_bad_frame_nak_resends_the_same_frame():
    frame = hdlc(1, 0x12, b"\xff")
    script = [(frame, hdlc(1, NAK, b"\x12\x01")), (frame, ack(1, 0x12))]
    with expected_exchange(displays, script, name="backdrops") as d:
        d.open()
        d.blank()
        assert d.stats["resends"] == 1 and d.last_error is None


def test_display_refusal_is_raised_with_its_reason():
    script = [(hdlc(1, 0x10, b"\x00\x01"), ack(1, 0x10)), (hdlc(2, 0x11, b"\x00\x00\x09"), hdlc(2, NAK, b"\x11\x05"))]
    with expected_exchange(displays, script, name="backdrops") as d:
        d.open()
        with pytest.raises(DisplayNak) as ei:
            d.show("bottom", 9)
    assert ei.value.reason == 5 and "backdrops" in str(ei.value)


# ----------------------------------------------------------------------------- the helper itself


def test_a_write_that_differs_names_the_pair_and_both_byte_strings():
    with (
        pytest.raises(AssertionError) as ei,
        expected_exchange(grbl_with_turntable, [(None, BANNER), (b"$I\n", b"ok\r\n")], name="grbl") as tt,
    ):
        tt.controller.open()
    msg = str(ei.value)
    assert "pair #1" in msg and "b'?'" in msg and "b'$I\\n'" in msg


def test_an_unused_pair_is_reported_at_exit():
    with (
        pytest.raises(AssertionError, match=r"pair #1 of 2 was never used: \(b'!', b''\)"),
        expected_exchange(grbl_with_turntable, [(None, BANNER), (b"!", b"")], name="grbl"),
    ):
        pass


def test_a_mismatch_the_driver_swallows_is_still_raised():
    """``stop()`` never raises (``Rig.safe`` relies on it): the mismatch surfaces at exit."""
    with (
        pytest.raises(AssertionError, match="differs from pair #6"),
        expected_exchange(grbl_with_turntable, GRBL_OPEN + [(b"~", b"")], name="grbl") as tt,
    ):
        tt.controller.open()
        tt.stop()  # sends '!', not the scripted '~'


def test_write_after_the_script_ended_is_a_mismatch():
    t = ExpectedExchangeTransport([(b"a", b"1")])
    t.open()
    t.write(b"a")
    with pytest.raises(AssertionError, match="all 1 expected pairs were already used"):
        t.write(b"b")
    with pytest.raises(AssertionError):
        t.verify()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.binary(min_size=1, max_size=8), min_size=1, max_size=5), st.data())
def test_any_split_of_the_expected_bytes_is_accepted(outs, data):
    """A pair may arrive over several writes; the reply comes once it is complete."""
    t = ExpectedExchangeTransport([(o, bytes([k])) for k, o in enumerate(outs)])
    t.open()
    stream = b"".join(outs)
    cuts = sorted(data.draw(st.sets(st.integers(1, max(1, len(stream) - 1)), max_size=4)))
    pos = 0
    for c in [*cuts, len(stream)]:
        if c > pos:
            t.write(stream[pos:c])
            pos = c
    assert t.read_available() == bytes(range(len(outs)))
    t.verify()


def test_bad_scripts_and_bad_transports_are_refused():
    with pytest.raises(TypeError, match="pair #0"):
        ExpectedExchangeTransport([("?", b"")])  # type: ignore[list-item]
    with pytest.raises(TypeError, match="nothing written, nothing read"):
        ExpectedExchangeTransport([(None, b"")])
    for make in (GrblController, EnttecDmx):
        with pytest.raises(ConfigError, match="from_url"):
            make("/dev/ttyUSB0")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="from_url"):
        DisplayController("/dev/ttyUSB0", outputs={"a": 0})  # type: ignore[arg-type]


def test_transport_logs_every_byte_at_debug(caplog):
    t = ExpectedExchangeTransport([(b"?", b"<Idle>\r\n")], name="turntable")
    with caplog.at_level(logging.DEBUG, logger="opacityhull.rigs.transport"):
        t.open()
        t.write(b"?")
        assert t.read_until(b"\n") == b"<Idle>\r\n"
    lines = [r.getMessage() for r in caplog.records]
    assert "turntable > b'?'" in lines and "turntable < b'<Idle>\\r\\n'" in lines


# ----------------------------------------------------------------------------- the rig around them


def test_rig_safe_exit_sends_feed_hold_lights_off_and_blank_exactly():
    """``with rig.safe():`` on a rig of three scripted ports: the bytes of the clean-up are
    a feed hold, an all-zero universe and BLANK all, each answered as the device would."""
    from opacityhull.rigs.config import parse_rig_config
    from opacityhull.rigs.rig import HardwareRig
    from opacityhull.rigs.testing import LAB_RIG_CONFIG

    config = parse_rig_config(LAB_RIG_CONFIG, source="lab-rig")
    grbl_t = ExpectedExchangeTransport(GRBL_OPEN + [(b"!", b"")], name="grbl")
    dmx_t = ExpectedExchangeTransport(
        [(enttec(3, b"\x00\x00"), PARAMS), (enttec(6, b"\x00" + bytes(24)), b"")], name="dmx"
    )
    disp_t = ExpectedExchangeTransport([(hdlc(1, 0x12, b"\xff"), ack(1, 0x12))], name="backdrops")
    tt = grbl_with_turntable(grbl_t)
    arr = dmx_array(dmx_t)
    disp = displays(disp_t)
    rig = HardwareRig(
        config, turntable=tt, light_array=arr, backdrops=disp, ports=[tt.controller, arr.dmx, disp, tt.controller]
    )
    assert [p.name for p in rig.ports] == ["grbl", "dmx", "backdrops"]  # each port once
    with rig, rig.safe():
        pass
    assert rig.safe_errors == []
    for t in (grbl_t, dmx_t, disp_t):
        t.verify()
        assert not t.is_open


def test_rig_refuses_a_port_that_is_not_one():
    from opacityhull.rigs.config import parse_rig_config
    from opacityhull.rigs.rig import HardwareRig
    from opacityhull.rigs.testing import LAB_RIG_CONFIG

    config = parse_rig_config(LAB_RIG_CONFIG, source="lab-rig")
    tt = grbl_with_turntable(ExpectedExchangeTransport([], name="grbl"))
    with pytest.raises(ConfigError, match="ports: str is not a Port"):
        HardwareRig(config, turntable=tt, ports=["/dev/ttyUSB0"])  # type: ignore[list-item]
