"""Samsung MDC: frames against the protocol document's examples, the driver's bytes on the
in-memory transport, and the driver against the emulator (pty and TCP) under faults.

The documented frames (docs/mdc-protocol.md cites them):
* MDC Protocol v13.7c §1.2.1: Power On to ID 0xFE is ``AA 11 FE 01 01`` with checksum
  ``11+FE+01+01 = 111`` -> ``11``;
* the SyncMaster 400MX-3 manual: Power On to ID 0 (sent as 0xFF on those models)
  ``AA 11 FF 01 01 12`` (``11+FF+01+01 = 112``);
* a Cisco digital-signage FAQ: power off to 0xFE ``aa11fe010010``;
* the ACK layout ``AA FF ID 03 'A' 11 Power CS`` (MD40B manual, power control page).
"""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from opacityhull.errors import ConfigError, InputError
from opacityhull.rigs import mdc_protocol as mdc
from opacityhull.rigs.emulators.base import EmulatorServer
from opacityhull.rigs.emulators.mdc import EMU_DYNAMIC_CONTRAST_CMD, MdcEmulator
from opacityhull.rigs.panels import MDC_SERIAL, MdcPanel, PanelNak, PanelSettings
from opacityhull.rigs.testing import expected_exchange
from opacityhull.rigs.transport import DeviceGone, DeviceTimeout


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def framed(text: str) -> bytes:
    """Hex without the checksum, checksum appended by hand: the low byte of the sum of
    every byte after the header."""
    b = h(text)
    total = 0
    for x in b[1:]:
        total += x
    return b + bytes((total % 256,))


# ----------------------------------------------------------------------------- frames


def test_documented_power_on_frames():
    assert mdc.encode_command(0x11, 0xFE, b"\x01") == h("AA 11 FE 01 01 11")
    assert mdc.encode_command(0x11, 0xFF, b"\x01") == h("AA 11 FF 01 01 12")
    assert mdc.encode_command(0x11, 0xFE, b"\x00") == h("aa11fe010010")
    assert mdc.checksum(h("11 FE 01 01")) == 0x11


def test_documented_ack_layout_parses():
    ack = framed("AA FF 01 03 41 11 01")
    assert ack == h("AA FF 01 03 41 11 01 56")
    assert mdc.encode_reply(1, 0x11, b"\x01") == ack
    (r,) = mdc.FrameParser().feed(ack)
    assert r == mdc.Reply(display_id=1, ack=True, rcmd=0x11, data=b"\x01")
    assert mdc.encode_reply(1, 0x25, b"\x01", ack=False) == h("AA FF 01 03 4E 25 01 77")
    (n,) = mdc.FrameParser().feed(framed("AA FF 01 03 4E 25 01"))
    assert n == mdc.Reply(display_id=1, ack=False, rcmd=0x25, data=b"\x01")


@given(
    cmd=st.integers(0, 0xFE),
    did=st.integers(0, 0xFF),
    data=st.binary(max_size=40),
    noise=st.binary(max_size=20).filter(lambda b: 0xAA not in b),
    split=st.integers(0, 80),
)
def test_parser_finds_every_frame_behind_noise(cmd, did, data, noise, split):
    """Noise without a header byte never hides a frame (noise with one can: a checksum
    of one byte passes by chance once in 256)."""
    if cmd == mdc.REPLY_CMD:
        cmd = 0x11
    frame = mdc.encode_command(cmd, did, data)
    stream = noise + frame
    p = mdc.FrameParser()
    items = p.feed(stream[:split]) + p.feed(stream[split:])
    frames = [i for i in items if isinstance(i, mdc.Command)]
    assert frames == [mdc.Command(cmd, did, data)]


def test_a_header_in_noise_claiming_more_bytes_does_not_hold_back_a_complete_frame():
    items = mdc.FrameParser().feed(h("AA 00") + h("AA 03 00 00 03"))
    assert items[-1] == mdc.Command(3, 0, b"")


def test_bad_checksum_is_reported_and_skipped():
    good = mdc.encode_command(0x25, 1, b"\x32")
    bad = bytearray(good)
    bad[-1] ^= 0xFF
    items = mdc.FrameParser().feed(bytes(bad) + good)
    assert isinstance(items[0], mdc.BadFrame) and items[0].reason == "checksum"
    assert items[-1] == mdc.Command(0x25, 1, b"\x32")


@pytest.mark.parametrize("bad", [-1, 254, 255, 300, True, "1"])
def test_display_id_out_of_range_is_named(bad):
    with pytest.raises(InputError, match=r"MDC display id must be an integer 0\.\.253"):
        mdc.check_display_id(bad, where="devices.panels.back.id")
    with expected_exchange(lambda t: t, []) as t, pytest.raises(InputError, match="display id"):
        MdcPanel(t, display_id=bad)


def test_settings_are_checked():
    with pytest.raises(ConfigError, match="input 'hdmi9'"):
        PanelSettings(input="hdmi9")
    with pytest.raises(ConfigError, match="brightness = 101"):
        PanelSettings(brightness=101)


# ----------------------------------------------------------------------------- bytes of the driver


def ack(did: int, cmd: int, *vals: int) -> bytes:
    return framed(f"AA FF {did:02X} {2 + len(vals):02X} 41 {cmd:02X}" + "".join(f" {v:02X}" for v in vals))


def nak(did: int, cmd: int, err: int) -> bytes:
    return framed(f"AA FF {did:02X} 03 4E {cmd:02X} {err:02X}")


def get(did: int, cmd: int) -> bytes:
    return framed(f"AA {cmd:02X} {did:02X} 00")


def put(did: int, cmd: int, v: int) -> bytes:
    return framed(f"AA {cmd:02X} {did:02X} 01 {v:02X}")


SETTINGS = PanelSettings(input="hdmi2", brightness=80, contrast=90, backlight=60, dynamic_contrast_cmd=0xE1)


def state_pairs(did: int, *, es: int = 0, dyn: int = 0) -> list:
    model = b"QM55R"
    return [
        (get(did, 0x8A), framed(f"AA FF {did:02X} 07 41 8A " + model.hex())),
        (get(did, 0x11), ack(did, 0x11, 1)),
        (get(did, 0x14), ack(did, 0x14, 0x23)),
        (get(did, 0x25), ack(did, 0x25, 80)),
        (get(did, 0x24), ack(did, 0x24, 90)),
        (get(did, 0x92), ack(did, 0x92, es)),
        (get(did, 0x57), ack(did, 0x57, 8, 0, 1, 60, 8, 0, 0, 60)),
        (get(did, 0xE1), ack(did, 0xE1, dyn)),
        (get(did, 0x0D), ack(did, 0x0D, 0, 0, 2, 0, 41, 0)),
    ]


def test_lock_sends_the_documented_bytes_and_reads_back():
    pairs = [
        (h("AA 11 03 01 01 16"), h("AA FF 03 03 41 11 01 58")),  # power on, id 3 (by hand)
        (put(3, 0x14, 0x23), ack(3, 0x14, 0x23)),  # input HDMI2
        (put(3, 0x92, 0x00), ack(3, 0x92, 0x00)),  # energy saving off
        (put(3, 0x58, 60), ack(3, 0x58, 60)),  # manual backlight
        (put(3, 0x25, 80), ack(3, 0x25, 80)),
        (put(3, 0x24, 90), ack(3, 0x24, 90)),
        (put(3, 0xE1, 0), ack(3, 0xE1, 0)),
        *state_pairs(3),
    ]
    with expected_exchange(MdcPanel, pairs, name="panels.back", display_id=3, settings=SETTINGS) as p:
        p.open()
        st_ = p.lock()
    assert (st_.model, st_.power, st_.input, st_.brightness, st_.contrast) == ("QM55R", True, "hdmi2", 80, 90)
    assert st_.energy_saving == "off" and not st_.auto_lamp and st_.dynamic_contrast is False
    assert st_.temperature_c == 41 and st_.drift == ()


def test_state_names_every_drift_source():
    with expected_exchange(MdcPanel, state_pairs(1, es=2, dyn=1), display_id=1, settings=SETTINGS) as p:
        p.open()
        s = p.state()
    assert s.drift == ("energy saving medium (auto-brightness)", "dynamic contrast on")


def test_a_nak_of_a_locked_setting_names_it():
    pairs = [(put(1, 0x25, 80), nak(1, 0x25, 0x01))]
    with expected_exchange(MdcPanel, pairs, name="panels.back", display_id=1) as p:
        p.open()
        with pytest.raises(PanelNak, match=r"panels.back: .*refused SET BRIGHTNESS 80 \(NAK, error 0x01\).*locked"):
            p.set_brightness(80)


def test_replies_of_other_panels_and_noise_are_skipped():
    pairs = [(get(2, 0x11), b"\x13\x37" + ack(5, 0x11, 0) + ack(2, 0x11, 1))]
    with expected_exchange(MdcPanel, pairs, display_id=2) as p:
        p.open()
        assert p.powered() is True


# ----------------------------------------------------------------------------- against the emulator


@pytest.fixture
def panel(kind):
    made = []

    def make(*, did: int = 1, timeout_s: float = 0.3, retries: int = 2, **emu_kw):
        emu = MdcEmulator(display_id=did, **emu_kw)
        srv = EmulatorServer(emu, kind=kind)
        srv.start()
        p = MdcPanel.from_url(
            srv.url,
            display_id=did,
            name="panels.bottom",
            serial=replace(MDC_SERIAL, timeout_s=timeout_s, retries=retries, reconnect_delay_s=0.01),
            settings=PanelSettings(brightness=90, contrast=85, dynamic_contrast_cmd=EMU_DYNAMIC_CONTRAST_CMD),
        )
        made.append((srv, p))
        p.open()
        return srv, emu, p

    yield make
    for srv, p in made:
        p.close()
        srv.stop()


def test_lock_against_the_emulator_removes_every_drift(panel):
    srv, emu, p = panel()
    assert emu.drifting()
    before = p.state()
    assert "energy saving low (auto-brightness)" in before.drift and "dynamic contrast on" in before.drift
    after = p.lock()
    assert after.drift == () and not emu.drifting()
    assert (emu.value("brightness"), emu.value("contrast"), emu.value("power")) == (90, 85, 1)
    info = p.check()
    assert info.ok and "QM55R-EMU" in info.detail and "locked" in info.detail


def test_locked_setting_on_the_emulator_is_a_named_nak(panel):
    srv, emu, p = panel()
    emu.locked.add("contrast")
    with pytest.raises(PanelNak, match="refused SET CONTRAST 85"):
        p.lock()


@pytest.mark.parametrize("fault", ["drop", "garble", "truncate", "corrupt_rx"])
def test_one_lost_or_garbled_reply_is_resent(panel, fault):
    srv, emu, p = panel()
    with emu.lock:
        if fault == "corrupt_rx":
            emu.corrupt_rx = 1
        else:
            setattr(emu.faults, fault, 1)
    p.set_brightness(42)
    assert emu.value("brightness") == 42 and p.stats["resends"] == 1


def test_silent_and_babbling_panels_time_out_saying_which(panel):
    srv, emu, p = panel(timeout_s=0.15, retries=1)
    emu.faults.silent = True
    with pytest.raises(DeviceTimeout, match="silent — is it powered"):
        p.powered()
    emu.faults.silent = False
    emu.faults.babble = 3000.0
    with pytest.raises(DeviceTimeout, match="garbled — check the baud rate"):
        p.powered()


def test_vanished_port_is_named(panel):
    srv, emu, p = panel()
    srv.vanish()
    with pytest.raises(DeviceGone, match="panels.bottom"):
        p.powered()
