"""Enttec DMX USB Pro framing (API 1.44): encoders, replies, and the re-synchronising parser."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import InputError
from opacityhull.rigs import enttec_protocol as ep
from opacityhull.rigs.transport import ProtocolError


def test_send_dmx_frame_bytes():
    f = ep.encode_send_dmx(bytes([255, 0, 7]) + bytes(509))
    assert f[:5] == bytes([0x7E, 6, 0x01, 0x02, 0x00])  # label 6, length 513 = 0x0201, start code 0
    assert f[5:8] == bytes([255, 0, 7]) and len(f) == 4 + 513 + 1 and f[-1] == 0xE7
    short = ep.encode_send_dmx(b"\x10")  # padded to the 24-channel minimum the widget accepts
    assert short == bytes([0x7E, 6, 25, 0, 0, 0x10]) + bytes(23) + b"\xe7"


def test_requests_and_replies():
    assert ep.encode_get_widget_parameters() == bytes([0x7E, 3, 2, 0, 0, 0, 0xE7])
    assert ep.encode_get_widget_parameters(300) == bytes([0x7E, 3, 2, 0, 0x2C, 0x01, 0xE7])
    assert ep.encode_get_serial() == bytes([0x7E, 10, 0, 0, 0xE7])
    assert ep.encode_serial_reply(0x12345678) == bytes([0x7E, 10, 4, 0, 0x78, 0x56, 0x34, 0x12, 0xE7])
    assert ep.parse_serial(ep.decode_one(ep.encode_serial_reply(0x12345678))) == "12345678"
    assert ep.encode_set_widget_parameters(20, 5, 30) == bytes([0x7E, 4, 5, 0, 0, 0, 20, 5, 30, 0xE7])


def test_widget_parameters_round_trip():
    p = ep.WidgetParameters(firmware=(1, 44), break_time=9, mab_time=1, rate_hz=40, user_config=b"\x01\x02")
    raw = ep.encode_widget_parameters_reply(p)
    assert raw[:9] == bytes([0x7E, 3, 7, 0, 44, 1, 9, 1, 40])  # firmware LSB first
    q = ep.parse_widget_parameters(ep.decode_one(raw))
    assert q == p and q.firmware_version == "1.44"
    assert q.break_us == pytest.approx(96.03) and q.mab_us == pytest.approx(10.67)


def test_reply_parsers_reject_other_frames():
    with pytest.raises(ProtocolError, match="expected label 3"):
        ep.parse_widget_parameters(ep.Frame(3, b"\x01\x02"))
    with pytest.raises(ProtocolError, match="expected label 10"):
        ep.parse_serial(ep.Frame(6, b"\x00\x00\x00\x00"))
    with pytest.raises(ProtocolError, match="not exactly one"):
        ep.decode_one(ep.encode_get_serial() + b"\x00")


def test_encoders_validate_before_producing_bytes():
    with pytest.raises(InputError, match="at most 600"):
        ep.encode(6, bytes(601))
    with pytest.raises(InputError, match="label"):
        ep.encode(256)
    with pytest.raises(InputError, match="513 DMX channels"):
        ep.encode_send_dmx(bytes(513))
    with pytest.raises(InputError, match="start code"):
        ep.encode_send_dmx(b"", start_code=300)
    with pytest.raises(InputError, match="integers 0..255"):
        ep.encode_send_dmx([0, 256])
    with pytest.raises(InputError, match="break time"):
        ep.encode_set_widget_parameters(break_time=8)


def test_parser_byte_by_byte():
    frames = [ep.encode_get_serial(), ep.encode_send_dmx(bytes(range(30))), ep.encode(3, b"\x7e\xe7\x7e")]
    p = ep.FrameParser()
    got = []
    for b in b"".join(frames):
        got += p.feed(bytes([b]))
    assert [ep.encode(f.label, f.data) for f in got] == frames and not p.bad and p.pending == 0


def test_parser_resyncs_after_oversize_length():
    good = ep.encode(10, b"\x01\x02\x03\x04")
    p = ep.FrameParser()
    got = p.feed(b"\x7e\x06\xff\xff" + good)  # claims 65535 bytes: impossible, rescan
    assert got == [ep.Frame(10, b"\x01\x02\x03\x04")]
    assert p.bad[0] == ep.BadFrame("length", b"\x7e\x06\xff\xff")


def test_parser_resyncs_after_wrong_end_byte_and_finds_the_frame_inside():
    inner = ep.encode(10, b"\x01\x02\x03\x04")
    bogus = b"\x7e\x06" + bytes([len(inner) + 1, 0]) + inner + b"\x00\x00"  # end byte missing
    p = ep.FrameParser()
    got = p.feed(bogus + ep.encode_get_serial())
    assert got == [ep.Frame(10, b"\x01\x02\x03\x04"), ep.Frame(10, b"")]
    assert "end" in [b.reason for b in p.bad]


def test_truncated_frame_followed_by_valid_frames():
    whole = ep.encode_send_dmx(bytes(range(100)))
    p = ep.FrameParser()
    got = p.feed(whole[:60] + ep.encode_get_serial() + ep.encode_send_dmx(bytes(512)))
    # the cut frame claims 101 bytes, swallows the next two frames' bytes, finds no end byte where it
    # needs one, and the rescan recovers both
    assert got == [ep.Frame(10, b""), ep.Frame(6, bytes(513))]
    assert p.bad_count >= 1


def test_abandon_gives_up_on_a_frame_that_never_completes():
    p = ep.FrameParser()
    good = ep.encode_get_serial()
    assert p.feed(b"\x7e\x03\x05\x00" + good) == []  # waits for 9 more bytes of the first candidate
    assert p.pending > 0
    assert p.abandon() == [ep.Frame(10, b"")]
    assert p.pending == 0


_label = st.integers(0, 255)
_frame = st.tuples(_label, st.binary(max_size=40) | st.binary(min_size=500, max_size=600))
_noise = st.binary(max_size=30).map(lambda b: b.replace(b"\x7e", b"\x00"))


@given(st.lists(st.tuples(_noise, _frame), max_size=8), _noise, st.integers(1, 64))
@settings(max_examples=100, deadline=None)
def test_noise_between_frames_never_breaks_the_valid_ones(pairs, tail, chunk):
    """Noise without the start byte (any other bytes, 0xE7 included) between frames whose data
    may contain 0x7E and 0xE7, fed in arbitrary chunks: every frame decodes, in order."""
    stream = b"".join(noise + ep.encode(label, data) for noise, (label, data) in pairs) + tail
    p = ep.FrameParser()
    got = []
    for i in range(0, len(stream), chunk):
        got += p.feed(stream[i : i + chunk])
    assert got == [ep.Frame(label, data) for _, (label, data) in pairs]
    assert p.pending == 0
    noise_bytes = sum(len(n) for n, _ in pairs) + len(tail)
    assert sum(len(b.data) for b in p.bad) == noise_bytes  # every noise byte reported, nothing else


@given(st.binary(max_size=1500), st.integers(1, 97))
@settings(max_examples=150, deadline=None)
def test_arbitrary_bytes_never_raise_and_frames_are_real(data, chunk):
    """Any byte soup: the parser never raises, and every frame it returns is really there."""
    p = ep.FrameParser()
    got = []
    for i in range(0, len(data), chunk):
        got += p.feed(data[i : i + chunk])
    got += p.abandon()
    assert p.pending == 0
    for f in got:
        assert ep.encode(f.label, f.data) in data
