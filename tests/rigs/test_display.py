"""Display controller driver against the emulator, over a real pty / TCP socket."""

from dataclasses import replace

import numpy as np
import pytest

from opacityhull.errors import InputError
from opacityhull.rigs import display_protocol as dp
from opacityhull.rigs.backdrops import DISPLAY_SERIAL, DisplayController, DisplayNak
from opacityhull.rigs.emulators.base import EmulatorServer
from opacityhull.rigs.emulators.display import DisplayEmulator
from opacityhull.rigs.interfaces import Backdrops, ImageOutput, PatternMissing, PatternStore, StorageFull
from opacityhull.rigs.transport import DeviceGone, DeviceTimeout

OUTPUTS = {"bottom": 0, "back": 1}


def pattern(seed, rows=36, cols=64):
    return np.random.default_rng(seed).integers(0, 256, (rows, cols, 3), dtype=np.uint8)


@pytest.fixture
def emu():
    e = DisplayEmulator(outputs=2)
    with EmulatorServer(e) as srv:
        yield e, srv


def _small_chunk_controller(srv, *, retries: int, reconnect_attempts: int) -> DisplayController:
    """A controller on ``srv`` uploading in 256-byte chunks (several per image), 0.3 s
    reply timeout and a quick 10 ms reconnect."""
    return DisplayController.from_url(
        srv.url,
        outputs=OUTPUTS,
        serial=replace(
            DISPLAY_SERIAL,
            timeout_s=0.3,
            retries=retries,
            reconnect_attempts=reconnect_attempts,
            reconnect_delay_s=0.01,
        ),
        chunk_bytes=256,
    )


@pytest.fixture
def ctl(emu):
    e, srv = emu
    c = _small_chunk_controller(srv, retries=3, reconnect_attempts=1)
    with c:
        yield c


def test_implements_backdrops_protocol(ctl):
    assert isinstance(ctl, Backdrops) and isinstance(ctl, PatternStore) and not isinstance(ctl, ImageOutput)
    assert ctl.displays == ["bottom", "back"]


def test_pattern_store_errors_are_typed():
    """STORAGE_FULL and NO_PATTERN NAKs are the protocol's StorageFull and PatternMissing
    (still DisplayNak with the reason): the capture runner catches them by type."""
    e = DisplayEmulator(outputs=2, slots=2)
    with EmulatorServer(e) as srv, _small_chunk_controller(srv, retries=1, reconnect_attempts=0) as c:
        assert c.slots() == 2 and c.stored() == []
        c.upload("bottom", 1, pattern(1))
        c.upload("bottom", 2, pattern(2))
        with pytest.raises(StorageFull) as full:
            c.upload("bottom", 3, pattern(3))
        assert isinstance(full.value, DisplayNak) and full.value.reason == dp.NAK_STORAGE_FULL
        c.delete(1)
        assert c.stored() == [2]
        with pytest.raises(PatternMissing):
            c.show("back", 1)


def test_upload_show_blank_roundtrip(emu, ctl):
    e, _ = emu
    img = pattern(0)
    done = []
    assert ctl.upload("bottom", 7, img, progress=lambda d, t: done.append((d, t))) is True
    assert done[-1] == (img.size, img.size) and len(done) == -(-img.size // 256)
    np.testing.assert_array_equal(e.pattern(7), img)
    ctl.show("back", 7)
    assert e.shown(1) == 7 and e.powered(1) and e.shown(0) is None
    assert ctl.shown() == {"bottom": None, "back": 7}
    # the panel scales the pattern with nearest neighbour: every 3x3 block of a 192x108 panel is one pixel
    big = e.displayed(1, 192, 108)
    np.testing.assert_array_equal(big[::3, ::3], img)
    np.testing.assert_array_equal(big[2::3, 2::3], img)
    ctl.blank()
    assert ctl.shown() == {"bottom": None, "back": None}
    assert not e.is_lit()
    assert e.displayed(1).max() == 0


def test_reupload_identical_pattern_is_skipped(emu, ctl):
    e, _ = emu
    img = pattern(1)
    assert ctl.upload("back", 3, img)
    n = len(e.history)
    assert ctl.upload("back", 3, img) is False
    assert [h[0] for h in e.history[n:]] == ["PATTERN_INFO"]
    img2 = img.copy()
    img2[5, 5, 1] ^= 1  # one bit differs: CRC-32 differs, so it is sent again
    assert ctl.upload("back", 3, img2) is True
    np.testing.assert_array_equal(e.pattern(3), img2)


def test_garbled_truncated_dropped_replies_are_resent(emu, ctl):
    e, _ = emu
    ctl.upload("bottom", 1, pattern(2))
    for fault in ("garble", "truncate", "drop"):
        setattr(e.faults, fault, 1)
        ctl.show("bottom", 1)
        assert e.shown(0) == 1
        ctl.blank("bottom")
        assert e.shown(0) is None
    kinds = [k for k, _ in e.faults.log]
    assert kinds == ["garble", "truncate", "drop"]
    assert ctl.stats["resends"] >= 3


def on_nth_upload_chunk(e, n, action):
    """Run ``action()`` when the emulator ``e`` has received its ``n``-th UPLOAD_DATA frame."""
    count = [0]

    def hook(frame):
        if frame.cmd == dp.CMD_UPLOAD_DATA:
            count[0] += 1
            if count[0] == n:
                action()

    e.on_command = hook


def test_bad_checksum_gets_nak_then_retry_mid_upload(emu, ctl):
    e, _ = emu
    img = pattern(3)
    # after the 3rd chunk, corrupt the next two frames on the wire (the 4th chunk and its
    # first resend): the controller NAKs them, the driver resends that chunk only
    on_nth_upload_chunk(e, 3, lambda: setattr(e, "corrupt_rx", 2))
    ctl.upload("bottom", 9, img)
    np.testing.assert_array_equal(e.pattern(9), img)
    offsets = [int.from_bytes(p[2:6], "big") for k, p in e.history if k == "UPLOAD_DATA"]
    assert offsets == list(range(0, img.size, 256))  # every chunk stored exactly once, in order
    corrupted = [int.from_bytes(p[2:6], "big") for k, p in e.history if k == "corrupted"]
    assert corrupted == [768, 768]  # the 4th chunk was NAKed twice, then resent (only it)
    assert ctl.stats["resends"] == 2


def test_busy_nak_is_retried_semantic_nak_is_not(emu, ctl):
    e, _ = emu
    ctl.upload("bottom", 2, pattern(4))
    e.busy = 2
    ctl.show("back", 2)
    assert e.shown(1) == 2
    n_show = sum(1 for k, _ in e.history if k == "SHOW")
    with pytest.raises(DisplayNak, match="pattern 99 is not stored.*upload it first") as ei:
        ctl.show("back", 99)
    assert ei.value.reason == dp.NAK_NO_PATTERN and isinstance(ei.value, PatternMissing)
    assert sum(1 for k, _ in e.history if k == "SHOW") == n_show + 1  # no pointless resends


def test_late_replies_do_not_confuse_later_commands(emu, ctl):
    e, _ = emu
    ctl.upload("bottom", 1, pattern(5))
    ctl.upload("bottom", 2, pattern(6))
    e.faults.delay_s = 0.45  # every reply arrives after the 0.3 s timeout: resends, late duplicates
    ctl.show("bottom", 1)
    e.faults.delay_s = 0.0
    ctl.show("back", 2)
    ctl.blank("bottom")
    assert (e.shown(0), e.shown(1)) == (None, 2)
    assert ctl.shown() == {"bottom": None, "back": 2}


def test_silent_controller_times_out_naming_device(emu):
    e, srv = emu
    e.faults.silent = True
    c = DisplayController.from_url(
        srv.url, outputs=OUTPUTS, serial=replace(DISPLAY_SERIAL, timeout_s=0.1, retries=2), name="backdrops"
    )
    with (
        c,
        pytest.raises(
            DeviceTimeout,
            match=r"backdrops: no valid reply to POWER back on after 3 attempt\(s\) on .*no reply within 0.1 s",
        ) as ei,
    ):
        c.show("back", 1)
    assert srv.url in str(ei.value) and "powered" in str(ei.value)
    assert sum(1 for k, _ in e.history if k == "POWER") == 3
    info = c.check()
    assert not info.ok and "IDENTIFY" in info.detail


def test_unplug_mid_upload_then_replug(tmp_path):
    """TCP emulator vanishes after the 4th chunk; the driver gives up naming the device; the
    controller stores nothing; after a re-plug on the same port the upload completes."""
    e = DisplayEmulator(outputs=2)
    srv = EmulatorServer(e, kind="tcp")
    srv.start()
    port = int(srv.url.rsplit(":", 1)[1])
    chunks = {"n": 0}

    def pull_plug(frame):
        if frame.cmd == dp.CMD_UPLOAD_DATA:
            chunks["n"] += 1
            if chunks["n"] == 4:
                srv.vanish()

    e.on_command = pull_plug
    c = _small_chunk_controller(srv, retries=1, reconnect_attempts=2)
    img = pattern(7)
    try:
        with (
            pytest.raises(DeviceGone, match=r"backdrops: .*(did not come back|cannot open|lost the connection)"),
            c,
        ):
            c.upload("bottom", 4, img)
        assert e.stored_ids() == []  # the partial upload was never committed
        c.blank()  # never raises on a dead port
        assert c.last_error and "backdrops" in c.last_error
        # re-plug: same device state, same TCP port
        e.on_command = None
        srv2 = EmulatorServer(e, kind="tcp", port=port)
        srv2.start()
        try:
            c.upload("bottom", 4, img)  # re-opens on first use
            np.testing.assert_array_equal(e.pattern(4), img)
            c.show("bottom", 4)
            assert e.shown(0) == 4
        finally:
            c.close()
            srv2.stop()
    finally:
        srv.stop()


def test_controller_restart_mid_upload_restarts_upload(emu, ctl):
    """After the controller forgets an upload (power cycle), UPLOAD_DATA is NAKed 'no upload'
    and the driver starts the upload over once."""
    e, _ = emu
    img = pattern(8)
    # what a controller power cycle does to an upload in progress
    on_nth_upload_chunk(e, 2, lambda: setattr(e, "_upload", None))
    ctl.upload("back", 5, img)
    np.testing.assert_array_equal(e.pattern(5), img)
    assert sum(1 for k, _ in e.history if k == "UPLOAD_BEGIN") == 2


def test_config_errors_and_bad_output(emu):
    e, srv = emu
    from opacityhull.errors import ConfigError

    with pytest.raises(ConfigError, match="share one controller output"):
        DisplayController.from_url(srv.url, outputs={"a": 0, "b": 0})
    with pytest.raises(ConfigError, match="chunk_bytes"):
        DisplayController.from_url(srv.url, outputs={"a": 0}, chunk_bytes=4096)
    c = DisplayController.from_url(
        srv.url, outputs={"bottom": 0, "side": 5}, serial=replace(DISPLAY_SERIAL, timeout_s=0.3)
    )
    with c:
        with pytest.raises(InputError, match="no display named 'top'"):
            c.show("top", 1)
        c.upload("bottom", 1, pattern(9))
        with pytest.raises(DisplayNak, match="no such output"):
            c.show("side", 1)
        info = c.check()
    assert not info.ok and "['side']" in info.detail


def test_check_reports_identity_and_state(emu, ctl):
    e, _ = emu
    ctl.upload("bottom", 11, pattern(10))
    ctl.show("bottom", 11)
    info = ctl.check()
    assert info.ok and "OHDC-2" in info.identity
    assert info.state["shown"] == {"bottom": 11, "back": None}
    assert info.state["stored"] == [11]


def test_missing_port_is_device_gone():
    c = DisplayController.from_url(
        "/dev/does-not-exist-42", outputs=OUTPUTS, serial=replace(DISPLAY_SERIAL, reconnect_attempts=0)
    )
    with pytest.raises(DeviceGone, match="backdrops: cannot open /dev/does-not-exist-42"):
        c.open()
    with pytest.raises(DeviceGone):
        c.identity()
