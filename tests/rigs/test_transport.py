"""SerialTransport and EmulatorServer over real ptys and TCP sockets (no pyserial mocks)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from opacityhull.errors import ConfigError, DeviceError
from opacityhull.rigs.emulators.base import EmulatedDevice, EmulatorServer, Faults, Reply
from opacityhull.rigs.backdrops import DISPLAY_SERIAL
from opacityhull.rigs.lights import DMX_SERIAL
from opacityhull.rigs.transport import DeviceGone, DeviceTimeout, SerialTransport, check_url, reopen


class Echo(EmulatedDevice):
    """Answers every line with ``got:<line>``; ``mute`` lines are not answered."""

    name = "echo"

    def __init__(self):
        super().__init__()
        self.buf = bytearray()

    def receive(self, data):
        out = []
        self.buf += data
        while b"\n" in self.buf:
            line, _, rest = bytes(self.buf).partition(b"\n")
            self.buf = bytearray(rest)
            if line != b"mute":
                out.append(Reply(b"got:" + line + b"\r\n"))
        return out


@pytest.fixture
def echo(kind):
    dev = Echo()
    with EmulatorServer(dev, kind=kind) as srv:
        # generous: a reply that comes must never miss its read because the machine is
        # loaded; tests that expect a timeout pass their own short one
        t = SerialTransport(srv.url, name="echo-dev", timeout_s=10.0)
        t.open()
        yield srv, dev, t
        t.close()


def test_round_trip_and_exact_lines(echo):
    srv, dev, t = echo
    t.write(b"a\nbb\n")
    assert t.read_until(b"\n") == b"got:a\r\n"
    assert t.read_until(b"\n") == b"got:bb\r\n"
    assert dev.received == bytearray(b"a\nbb\n")


def test_timeout_names_device_url_and_what_to_check(echo):
    srv, dev, t = echo
    t.write(b"mute\n")
    with pytest.raises(DeviceTimeout) as ei:
        t.read_until(b"\n", what="answer to mute", timeout_s=0.3)
    msg = str(ei.value)
    assert "echo-dev" in msg and srv.url in msg and "answer to mute" in msg and "powered" in msg


def _emulator_saw(dev, data: bytes) -> bool:
    # the server appends to ``received`` and queues the replies under one hold of the
    # lock, so once ``data`` is seen here its (undelayed) replies are already sent
    with dev.lock:
        return data in dev.received


def test_partial_reply_is_quoted_in_the_timeout(echo, wait_for):
    srv, dev, t = echo
    dev.faults.truncate = 1
    t.write(b"hello\n")
    wait_for(lambda: _emulator_saw(dev, b"hello\n"), what="the truncated reply sent")
    with pytest.raises(DeviceTimeout) as ei:
        t.read_until(b"\n", timeout_s=0.3)
    assert "partial: b'got:h'" in str(ei.value)


def test_query_flushes_a_late_reply_first(echo, wait_for):
    """A reply nobody read (it came after its read timed out) must not answer the next
    query. Ordered by state, not by racing a 0.1 s read against a 0.5 s delay."""
    srv, dev, t = echo
    t.write(b"first\n")
    wait_for(lambda: _emulator_saw(dev, b"first\n") and srv.backlog == 0, what="late reply delivered")
    assert t.query(b"second\n") == b"got:second\r\n"
    assert t.read_some(timeout_s=0.05) == b""  # and "got:first" was discarded, not kept for later


def test_read_exact_and_read_some(echo):
    srv, dev, t = echo
    t.write(b"xyz\n")
    assert t.read_exact(4) == b"got:"
    assert t.read_until(b"\n") == b"xyz\r\n"
    assert t.read_some(timeout_s=0.05) == b""
    with pytest.raises(DeviceTimeout, match="got 0 of 3 bytes"):
        t.read_exact(3, timeout_s=0.05)


def test_vanish_gives_device_gone_on_read_and_write(echo):
    srv, dev, t = echo
    srv.vanish()
    with pytest.raises(DeviceGone) as ei:
        for _ in range(3):  # the first write into a closed TCP peer may still be buffered
            t.write(b"x\n")
            t.read_until(b"\n", timeout_s=0.2)
    assert srv.url in str(ei.value) and "unplugged" in str(ei.value)
    assert not t.is_open
    with pytest.raises(DeviceGone, match="not open"):
        t.write(b"x")


def test_vanished_port_is_noticed_by_read_available(echo):
    srv, dev, t = echo
    srv.vanish()
    with pytest.raises(DeviceGone):
        t.read_available()


def test_reappear_serves_again(echo):
    srv, dev, t = echo
    srv.vanish()
    with pytest.raises(DeviceGone):
        t.read_available()
    url = srv.reappear()
    if srv.kind == "tcp":
        assert url == t.url  # same port: a reconnect finds it again
    t.url = url
    t.open()
    t.write(b"back\n")
    assert t.read_until(b"\n") == b"got:back\r\n"


def test_open_missing_port_names_url():
    t = SerialTransport("/dev/ttyDOESNOTEXIST9", name="turntable")
    with pytest.raises(DeviceGone, match=r"turntable: cannot open /dev/ttyDOESNOTEXIST9 .*plugged in"):
        t.open()
    t2 = SerialTransport("socket://127.0.0.1:1", name="t2")
    with pytest.raises(DeviceGone, match="socket://127.0.0.1:1"):
        t2.open()
    assert isinstance(DeviceGone("x"), DeviceError)


def test_loop_url_without_file_descriptor():
    t = SerialTransport("loop://", timeout_s=0.1)
    with t:
        t.write(b"ping\n")
        assert t.read_until(b"\n") == b"ping\n"
        with pytest.raises(DeviceTimeout):
            t.read_until(b"\n")


@pytest.mark.parametrize("url", ["/dev/ttyUSB0", "socket://h:1", "loop://", "emulator:grbl#a", "COM3"])
def test_check_url_accepts(url):
    assert check_url(url) == url


@pytest.mark.parametrize("url", ["", "http://x", "ttyUSB0", 5, None])
def test_check_url_rejects_naming_the_key(url):
    with pytest.raises(ConfigError, match="devices.turntable.url"):
        check_url(url, where="devices.turntable.url")


def test_faults_match_targets_only_matching_replies():
    f = Faults(drop=1, match=b"ok")
    assert f.apply(Reply(b"<Idle>\r\n")).data == b"<Idle>\r\n"
    assert f.apply(Reply(b"ok\r\n")) is None
    assert f.apply(Reply(b"ok\r\n")).data == b"ok\r\n"  # the counter is spent
    g = Faults(garble=1)
    assert g.apply(Reply(b"ok\r\n")).data == bytes([ord("o") ^ 0x5A, ord("k"), ord("\r"), ord("\n")])
    late = Faults(late=1, late_s=0.25).apply(Reply(b"ok\r\n"))
    assert late.independent and late.delay_s == 0.25


def test_late_reply_is_overtaken_but_delayed_replies_keep_order(kind, wait_for):
    dev = Echo()
    with EmulatorServer(dev, kind=kind) as srv:
        t = SerialTransport(srv.url, timeout_s=2.0)
        with t:
            dev.faults.late, dev.faults.late_s = 1, 0.3
            # one write: both lines reach the emulator in one receive(), so "two" is
            # queued while "one" is late however slowly this thread runs
            t.write(b"one\ntwo\n")
            assert t.read_until(b"\n") == b"got:two\r\n"  # overtook the late one
            assert t.read_until(b"\n") == b"got:one\r\n"
            dev.faults.delay_s = 0.2
            t.write(b"three\n")
            # the delay must have applied to "three" before it is switched off
            wait_for(lambda: _emulator_saw(dev, b"three\n"), what="three received")
            dev.faults.delay_s = 0.0
            t.write(b"four\n")
            assert t.read_until(b"\n") == b"got:three\r\n"  # one serial line: order kept
            assert t.read_until(b"\n") == b"got:four\r\n"


@pytest.mark.parametrize(
    "change, match",
    [
        ({"timeout_s": 0}, r"SerialSettings: timeout_s = 0, expected a number of seconds > 0"),
        ({"timeout_s": float("inf")}, r"timeout_s = inf"),
        ({"baudrate": 9600.0}, r"baudrate = 9600.0, expected an integer > 0"),
        ({"retries": -1}, r"retries = -1, expected an integer >= 0"),
        ({"reconnect_attempts": True}, r"reconnect_attempts = True"),
        ({"reconnect_delay_s": -0.1}, r"reconnect_delay_s = -0.1, expected a number of seconds >= 0"),
    ],
)
def test_serial_settings_reject_bad_values_naming_the_field(change, match):
    with pytest.raises(ConfigError, match=match):
        replace(DISPLAY_SERIAL, **change)


def test_serial_transport_from_settings_uses_the_timeout_for_reads_and_writes():
    t = SerialTransport.from_settings("loop://", replace(DMX_SERIAL, timeout_s=0.25), name="dmx")
    assert (t.name, t.baudrate, t.timeout_s, t.write_timeout_s) == ("dmx", 57600, 0.25, 0.25)
    assert not t.is_open and t.exclusive


def test_reopen_is_bounded_spaced_and_names_the_last_error(monkeypatch):
    sleeps: list[float] = []
    monkeypatch.setattr("opacityhull.rigs.transport.time.sleep", sleeps.append)
    calls: list[int] = []

    def fail(attempt: int) -> None:
        calls.append(attempt)
        raise DeviceGone(f"gone {attempt}")

    with pytest.raises(DeviceGone, match=r"3 tries, last: gone 3") as ei:
        reopen(fail, attempts=3, delay_s=0.2, gave_up=lambda n, e: DeviceGone(f"{n} tries, last: {e}"))
    assert calls == [1, 2, 3] and sleeps == [0.2, 0.2] and ei.value.__cause__ is None
    assert reopen(lambda attempt: attempt, attempts=0, delay_s=1.0, gave_up=lambda n, e: DeviceGone("")) == 1

    def silent(_attempt: int) -> None:
        raise DeviceTimeout("silent")

    with pytest.raises(DeviceTimeout, match="silent"):  # not a failure it retries: raised at once
        reopen(silent, attempts=5, delay_s=0.0, gave_up=lambda n, e: DeviceGone(""))
    assert sleeps == [0.2, 0.2]
