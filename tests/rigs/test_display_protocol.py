"""Pure wire protocol of the display controller: framing, CRC, payloads, resize."""

import binascii

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from opacityhull.errors import InputError, ShapeError
from opacityhull.rigs import display_protocol as dp


def test_crc16_check_value_and_independent_reference():
    assert dp.crc16_ccitt(b"123456789") == 0x29B1
    rng = np.random.default_rng(1)
    for n in (0, 1, 7, 300):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert dp.crc16_ccitt(data) == binascii.crc_hqx(data, 0xFFFF)


def _crc16_old_table(data: bytes, crc: int = 0xFFFF) -> int:
    """The table-driven CRC the module carried before ``binascii.crc_hqx`` (#33)."""
    table = []
    for b in range(256):
        c = b << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ b) & 0xFF]
    return crc


@settings(max_examples=60, deadline=None)
@given(data=st.binary(max_size=600), start=st.sampled_from([0xFFFF, 0x0000, 0x1D0F]))
def test_crc16_is_the_library_crc_and_keeps_the_old_tables_values(data, start):
    assert not hasattr(dp, "_CRC16_TABLE")  # the hand-written table is gone: binascii does it
    assert dp.crc16_ccitt(data, start) == _crc16_old_table(data, start)


def test_documented_example_bytes():
    # docs/display-protocol.md lists these; a change here is a protocol change
    assert dp.encode_frame(1, *dp.identify()).hex(" ").upper() == "7E 01 01 3E 1F 7E"
    assert dp.encode_frame(2, *dp.show(1, 5)).hex(" ").upper() == "7E 02 11 01 00 05 5F 09 7E"
    assert (
        dp.encode_frame(5, *dp.upload_data(7, 0, bytes([0x7E, 0x7D, 0x00, 0xFF]))).hex(" ").upper()
        == "7E 05 21 00 07 00 00 00 00 7D 5E 7D 5D 00 FF 2D 46 7E"
    )


@settings(max_examples=80, deadline=None)
@given(
    seq=st.integers(0, 255),
    cmd=st.integers(0, 255),
    payload=st.binary(max_size=dp.MAX_PAYLOAD),
    split=st.integers(0, 3000),
)
def test_frame_roundtrip_any_split(seq, cmd, payload, split):
    wire = dp.encode_frame(seq, cmd, payload)
    inner = wire[1:-1]
    assert dp.FLAG not in inner  # escaping removed every flag from the body
    dec = dp.FrameDecoder()
    k = split % (len(wire) + 1)
    out = dec.feed(wire[:k]) + dec.feed(wire[k:])
    assert out == [dp.Frame(seq, cmd, payload)]


def test_decoder_resynchronises_after_garbage_and_reports_bad_frames():
    good = dp.encode_frame(3, dp.ACK, b"\x11")
    corrupt = bytearray(dp.encode_frame(4, dp.ACK, b"\x12"))
    corrupt[3] ^= 0x01
    dec = dp.FrameDecoder()
    out = dec.feed(b"\x00\x13junk" + bytes(corrupt) + b"\x7e\x7e" + good)
    frames = [x for x in out if isinstance(x, dp.Frame)]
    errors = [x for x in out if isinstance(x, dp.FrameError)]
    assert frames == [dp.Frame(3, dp.ACK, b"\x11")]
    # the junk before the first flag and the corrupted frame: both fail their CRC
    assert [e.reason for e in errors] == ["checksum mismatch", "checksum mismatch"]
    assert errors[1].seq == 4  # raw seq of the corrupt frame, as the controller echoes it in its NAK


def test_decoder_bad_escape_and_overlong_frame_bounded():
    dec = dp.FrameDecoder()
    out = dec.feed(b"\x7e\x01\x02\x7d\x00\x03\x04\x7e")
    assert len(out) == 1 and out[0].reason == "bad escape sequence"
    out = dec.feed(b"\x7e" + b"\x01" * 5000 + b"\x7e" + dp.encode_frame(9, 1))
    assert [type(x) for x in out] == [dp.FrameError, dp.Frame]
    assert out[0].reason.startswith("frame too long")
    assert len(dec.pending) == 0


def test_state_roundtrip_and_truncation():
    s = dp.ControllerState(power=(True, False, True), shown=(5, None, 0), stored=(0, 5, 65534))
    assert dp.parse_state(dp.encode_state(s)) == s
    data = dp.encode_state(s)
    for n in (0, 3, len(data) - 1):
        with pytest.raises(InputError, match="truncated"):
            dp.parse_state(data[:n])
    with pytest.raises(InputError, match="trailing"):
        dp.parse_state(data + b"\x00")


def test_payload_validation():
    with pytest.raises(InputError, match="pattern id"):
        dp.show(0, 0xFFFF)
    with pytest.raises(InputError, match="output"):
        dp.power(256, True)
    with pytest.raises(InputError, match="chunk"):
        dp.upload_data(1, 0, b"x" * (dp.MAX_CHUNK + 1))
    with pytest.raises(ShapeError, match="uint8"):
        dp.pattern_bytes(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ShapeError, match=r"\(rows, cols, 3\)"):
        dp.pattern_bytes(np.zeros((4, 4), np.uint8))
    assert list(dp.pattern_chunks(1000, 512)) == [(0, 512), (512, 488)]


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(1, 12), cols=st.integers(1, 12), h=st.integers(1, 40), w=st.integers(1, 40))
def test_nearest_resize_matches_slow_reference(rows, cols, h, w):
    img = np.arange(rows * cols * 3, dtype=np.int64).reshape(rows, cols, 3)
    fast = dp.nearest_resize(img, w, h)
    ref = np.empty((h, w, 3), np.int64)
    for j in range(h):
        for i in range(w):
            # pixel centre of the output mapped back into the input, floored
            ref[j, i] = img[min(int((j + 0.5) * rows / h), rows - 1), min(int((i + 0.5) * cols / w), cols - 1)]
    np.testing.assert_array_equal(fast, ref)
