"""Rig devices that misbehave and rig commands given bad faults: a babbling port has an
overall deadline and says "garbled", a silent one says "silent"; ``rig emulate --fault``
and ``emulator:...?fault=`` refuse bad specs before anything starts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from badkit import Case, flat, run_case

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "rig-emulated.toml"


def _rig_with_url(old: str, new: str):
    def setup(root):
        (root / "rig.toml").write_text(EXAMPLE.read_text().replace(f'url = "{old}"', f'url = "{new}"', 1))

    return setup


EMULATE = ("rig", "emulate", "--config", str(EXAMPLE), "--write-config", "{T}/rt.toml")


def _fault(case_id: str, spec: str, message: str) -> Case:
    """``rig emulate --fault SPEC``: exit 2 before the runtime config is written."""
    return Case(case_id, (*EMULATE, "--fault", spec), 2, message, must_not_exist=("{T}/rt.toml",))


CASES = [
    _fault(
        "fault-unknown-kind",
        "turntable:explode",
        r"--fault turntable:explode: unknown fault 'explode' .* expected one of drop, garble",
    ),
    _fault("fault-unknown-device", "kettle:silent", r"no emulated device 'kettle' .* \(emulated: turntable"),
    _fault("fault-no-kind", "turntable", r"--fault 'turntable': expected DEVICE:KIND"),
    _fault("fault-bad-count", "backdrops:garble:many", r"'garble:many': COUNT = 'many' is not an integer"),
    _fault("fault-zero-count", "backdrops:drop:0", r"COUNT must be > 0, got 0"),
    _fault("fault-too-many-args", "turntable:silent:3", r"silent takes at most 0 argument"),
    Case(
        "url-fault-unknown",
        ("rig", "emulate", "--config", "{T}/rig.toml", "--write-config", "{T}/rt.toml"),
        2,
        r"rig.toml: devices.backdrops.url: .*unknown fault 'fizz'",
        setup=_rig_with_url("emulator:display", "emulator:display?fault=fizz"),
        must_not_exist=("{T}/rt.toml",),
    ),
    Case(
        "url-query-unknown",
        ("rig", "check", "--config", "{T}/rig.toml"),
        2,
        r"devices.light_array.url: .*unknown query 'speed=3'",
        setup=_rig_with_url("emulator:enttec", "emulator:enttec?speed=3"),
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_rig_input(case, tmp_path):
    run_case(case, inputs={}, tmp_path=tmp_path)


def test_parse_fault_specs():
    from opacityhull.rigs.emulators.faults import FaultSpec, parse_fault

    assert parse_fault("late:2:0.5") == FaultSpec("late", (2, 0.5))
    assert parse_fault("garble") == FaultSpec("garble", (1,))
    assert parse_fault("babble:5000") == FaultSpec("babble", (5000.0,))
    assert str(parse_fault("vanish:2.5")) == "vanish:2.5"


def test_url_faults_are_applied_by_start_emulators():
    import tomllib

    from opacityhull.rigs.config import emulator_url_faults, parse_rig_config
    from opacityhull.rigs.emulators.launch import start_emulators

    d = tomllib.loads(EXAMPLE.read_text())
    d["devices"]["backdrops"]["url"] = "emulator:display?fault=garble:2&fault=delay:0.25"
    assert emulator_url_faults(d["devices"]["backdrops"]["url"]) == ["garble:2", "delay:0.25"]
    cfg = parse_rig_config(d, source="t")
    with start_emulators(cfg, faults={"turntable": ["delay:0.125"]}) as emus:
        bd = emus.by_device["backdrops"].faults
        assert (bd.garble, bd.delay_s) == (2, 0.25)
        assert emus.by_device["turntable"].faults.delay_s == 0.125
        assert emus.by_device["light_array.rotation"] is emus.by_device["turntable"]  # one GRBL, shared faults
        assert all(not u.startswith("emulator:") for u in emus.devices().values())


@pytest.mark.parametrize(
    "fault, words", [("babble:20000", "garbled — check the baud rate"), ("silent", "not a single byte arrived")]
)
@pytest.mark.parametrize("device", ["turntable", "light_array", "backdrops"])
def test_rig_check_tells_garbled_from_silent(device, fault, words):
    from opacityhull.rigs.config import load_rig_config
    from opacityhull.rigs.emulators.launch import start_emulators
    from opacityhull.rigs.rig import check_rig_config

    cfg = load_rig_config(EXAMPLE)
    with start_emulators(cfg, faults={device: [fault]}) as emus:
        infos = {i.name: i for i in check_rig_config(emus.config, timeout_s=0.2)}
    bad = infos[device]
    assert not bad.ok and words in bad.detail, bad.detail
    others = [n for n in ("turntable", "light_array", "backdrops") if n != device]
    assert all(infos[n].ok for n in others), {n: infos[n].detail for n in others}


def test_an_exchange_deadline_bounds_every_read_inside_it():
    """However long a read's own timeout and however many bytes flow, a read inside
    ``exchange(T)`` ends at T: it raises naming the overall deadline (a babbling port
    can no longer hold a command)."""
    from opacityhull.rigs.emulators.base import EmulatedDevice, EmulatorServer
    from opacityhull.rigs.transport import DeviceTimeout, SerialTransport

    class Mute(EmulatedDevice):
        def receive(self, data):
            return []

    dev = Mute()
    dev.faults.babble = 20000.0
    with EmulatorServer(dev) as srv:
        t = SerialTransport(srv.url, name="babbler", timeout_s=60.0)
        with t:
            with t.exchange(0.3, "reply to $I"), pytest.raises(DeviceTimeout) as ei:
                # lines keep arriving; none is accepted
                t.query(b"$I\n", timeout_s=60.0, accept=lambda line: line.startswith(b"ok"))
            msg = str(ei.value)
            assert "overall deadline of reply to $I (0.3 s)" in msg and "garbled" in msg, msg
            assert t.bytes_read > 0


def test_rig_emulate_fault_flag_end_to_end(tmp_path):
    """`rig emulate --fault turntable:silent` in one process, `rig check` in another."""
    runtime = tmp_path / "rt.toml"
    cli = [sys.executable, "-m", "opacityhull.cli"]
    proc = subprocess.Popen(
        [
            *cli,
            "rig",
            "emulate",
            "--config",
            str(EXAMPLE),
            "--write-config",
            str(runtime),
            "--json",
            "--fault",
            "turntable:silent",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        info = json.loads(proc.stdout.readline())
        assert info["faults"] == {"turntable": ["silent"]}
        r = subprocess.run(
            [*cli, "rig", "check", "--config", str(runtime), "--timeout", "0.2", "--json"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=60,
        )
        assert r.returncode == 3, r.stderr
        by = {d["name"]: d for d in json.loads(r.stdout)["devices"]}
        assert not by["turntable"]["ok"] and "silent" in by["turntable"]["detail"]
        assert by["backdrops"]["ok"] and by["light_array"]["ok"]
        assert "rig check failed: turntable:" in flat(r.stderr)
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_draining_a_port_that_never_stops_talking_ends():
    """`read_available` / `pending_lines` / `flush_input` looped while bytes kept coming:
    a device sending as fast as we read held them as long as it babbled. Now they take
    a bounded amount (no clock in this test: the port answers every read)."""
    from opacityhull.rigs.transport import SerialTransport

    class Babbler:
        is_open = True
        reads = 0

        def read(self, n):
            Babbler.reads += 1
            if Babbler.reads > 100_000:
                raise AssertionError("the drain loop never ended")
            return b"\xfe" * 100

    t = SerialTransport("loop://", name="babbler")
    t._port = Babbler()
    assert len(t.read_available()) <= 1 << 16
    assert t.pending_lines() == []
    assert Babbler.reads < 100_000
