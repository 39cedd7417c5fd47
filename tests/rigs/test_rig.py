"""HardwareRig / open_rig / start_emulators: the real drivers against the emulators."""

import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from opacityhull.charuco import CharucoSpec
from opacityhull.errors import ConfigError, DeviceError
from opacityhull.rigs.cameras import DirectoryCamera
from opacityhull.rigs.config import load_rig_config, parse_rig_config
from opacityhull.rigs.emulators.base import EmulatorServer
from opacityhull.rigs.emulators.display import DisplayEmulator
from opacityhull.rigs.emulators.enttec import EnttecEmulator
from opacityhull.rigs.emulators.grbl import GrblEmulator
from opacityhull.rigs.emulators.launch import start_emulators
from opacityhull.rigs.interfaces import GroundTruthSource, Port, Rig
from opacityhull.rigs.rig import HardwareRig, OperatorActionRequired, build_rig, check_rig_config, open_rig
from opacityhull.rigs.transport import DeviceGone

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "rig-emulated.toml"
PATTERN = np.full((36, 64, 3), 255, np.uint8)


def rig_dict(tmp_path) -> dict:
    """The example rig with tethered-folder cameras (real drivers that need no hardware)."""
    d = tomllib.loads(EXAMPLE.read_text())
    for i, c in enumerate(d["devices"]["cameras"]):
        folder = tmp_path / f"cam{i}"
        folder.mkdir(exist_ok=True)
        d["devices"]["cameras"][i] = {"name": c["name"], "driver": "directory", "device": str(folder)}
    return d


@pytest.fixture
def cfg(tmp_path):
    return parse_rig_config(rig_dict(tmp_path), source=str(tmp_path / "rig.toml"))


@pytest.fixture
def emus(cfg):
    with start_emulators(cfg) as e:
        yield e


def test_start_emulators_one_per_url(cfg, emus):
    assert set(emus.by_device) == {"turntable", "light_array.rotation", "light_array", "backdrops"}
    g = emus.by_device["turntable"]
    assert isinstance(g, GrblEmulator) and emus.by_device["light_array.rotation"] is g and g.axes == ("X", "Y")
    assert isinstance(emus.by_device["light_array"], EnttecEmulator)
    assert isinstance(emus.by_device["backdrops"], DisplayEmulator) and emus.by_device["backdrops"].outputs == 2
    assert set(emus.handles) == {"emulator:grbl", "emulator:enttec", "emulator:display"}
    urls = emus.config.device_urls()
    assert urls["turntable"] == urls["light_array.rotation"] and urls["turntable"].startswith("/dev/pts/")
    assert len(set(urls.values())) == 3 and not emus.config.emulated()
    assert cfg.device_urls()["turntable"] == "emulator:grbl"  # the input config is unchanged


def test_tagged_emulators_are_separate_controllers(tmp_path):
    d = rig_dict(tmp_path)
    d["devices"]["turntable"]["url"] = "emulator:grbl#table"
    d["devices"]["light_array"]["rotation"]["url"] = "emulator:grbl#lights"
    d["devices"]["light_array"]["rotation"]["axis"] = "X"
    cfg = parse_rig_config(d)
    with start_emulators(cfg, kind="tcp") as e:
        a, b = e.by_device["turntable"], e.by_device["light_array.rotation"]
        assert a is not b and a.axes == ("X",) and b.axes == ("X",)
        with open_rig(e.config) as rig:
            rig.turntable.move_to(20.0)
            rig.light_array.rotation.move_to(-35.0)
            assert len(rig.ports) == 4 and all(isinstance(p, Port) for p in rig.ports)
        assert (a.position_deg("X"), b.position_deg("X")) == (20.0, -35.0)


def test_open_rig_drives_every_device(cfg, emus, wait_for):
    with open_rig(emus.config, assume_ready=True) as rig:
        assert isinstance(rig, Rig) and isinstance(rig, HardwareRig)
        g, dmx, disp = emus.by_device["turntable"], emus.by_device["light_array"], emus.by_device["backdrops"]
        assert rig.turntable.move_to(30.0) == pytest.approx(30.0)
        rig.light_array.rotation.move_to(45.0)
        assert (g.position_deg("X"), g.position_deg("Y")) == (30.0, 45.0)
        rig.light_array.set_levels({1: 200, 3: 7})
        # DMX is send-only: wait for the emulator to have applied the packet
        wait_for(lambda: list(dmx.levels()[:4]) == [0, 200, 0, 7], 5, "the DMX levels")
        rig.backdrops.upload("back", 1, PATTERN)
        rig.backdrops.show("back", 1)
        assert disp.shown(1) == 1 and disp.shown(0) is None
        infos = rig.check()
        assert [i.name for i in infos] == ["turntable", "light_array.rotation", "light_array", "backdrops"] + [
            f"cam{i}" for i in range(6)
        ]
        assert all(i.ok for i in infos), [i for i in infos if not i.ok]
        assert infos[0].state["position_deg"] == pytest.approx(30.0)
        assert rig.describe() == emus.config.to_dict()
        assert rig.describe()["devices"]["turntable"]["url"] == emus.config.turntable.url
        # hardware knows nothing exactly: ground truth is not part of its contract
        assert isinstance(rig, Rig) and not isinstance(rig, GroundTruthSource)


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_safe_on_exception(emus, exc, wait_for):
    g, dmx, disp = emus.by_device["turntable"], emus.by_device["light_array"], emus.by_device["backdrops"]
    with open_rig(emus.config) as rig:
        with pytest.raises(exc), rig.safe():
            rig.light_array.set_levels({0: 255, 2: 255})
            rig.backdrops.upload("bottom", 4, PATTERN)
            rig.backdrops.show("bottom", 4)
            rig.backdrops.show("back", 4)
            assert disp.is_lit()
            wait_for(lambda: any(dmx.levels()), 5, "lights on")
            rig.turntable.move_to(15.0)
            raise exc("stop here")
        assert rig.safe_errors == []
    wait_for(lambda: not any(dmx.levels()), 5, "lights off")
    assert disp.shown(0) is None and disp.shown(1) is None and not disp.is_lit()
    wait_for(lambda: b"!" in b"".join(g.realtime), 5, "the feed hold byte")  # real-time bytes get no reply
    assert g.state in ("Idle", "Hold")


def test_safe_attempts_every_step_when_one_device_is_gone(emus, wait_for):
    g, dmx = emus.by_device["turntable"], emus.by_device["light_array"]
    with open_rig(emus.config) as rig:
        rig.backdrops.reconnect_attempts = 0
        with (
            pytest.raises(DeviceError, match=r"could not make the rig safe \(backdrops: blank: .*backdrops") as ei,
            rig.safe(),
        ):
            rig.light_array.set_levels({1: 255})
            emus.servers["emulator:display"].vanish()  # display controller unplugged
        assert "light_array" not in str(ei.value) and "turntable" not in str(ei.value)
        # the body raised: the original error wins, the clean-up failure is a warning
        with (
            pytest.warns(RuntimeWarning, match="clean-up incomplete: backdrops: blank"),
            pytest.raises(ZeroDivisionError),
            rig.safe(),
        ):
            rig.light_array.set_levels({2: 255})
            raise ZeroDivisionError
    wait_for(lambda: dmx.dmx_packets >= 4 and not any(dmx.levels()), 5, "lights off")  # they still went off
    wait_for(lambda: b"".join(g.realtime).count(b"!") >= 2, 5, "a feed hold per safe() exit")


def test_ctrl_c_during_move_leaves_rig_safe(tmp_path, cfg, wait_for):
    """A real SIGINT to a process in the middle of a move: afterwards (read from the emulators
    in this process) lights are off, both displays blank and the axis is held mid-way."""
    with start_emulators(cfg, kind="pty", time_scale=1.0) as emus:
        runtime = emus.config.write(tmp_path / "runtime.toml")
        g, dmx, disp = emus.by_device["turntable"], emus.by_device["light_array"], emus.by_device["backdrops"]
        script = (
            "import sys, numpy as np\n"
            "from opacityhull.rigs.rig import open_rig\n"
            "rig = open_rig(sys.argv[1])\n"
            "try:\n"
            "    with rig.safe():\n"
            "        rig.light_array.set_levels({0: 255, 3: 90})\n"
            "        rig.backdrops.upload('back', 1, np.full((36, 64, 3), 255, np.uint8))\n"
            "        rig.backdrops.show('back', 1)\n"
            "        rig.backdrops.show('bottom', 1)\n"
            "        print('moving', flush=True)\n"
            "        rig.turntable.move_to(170.0)\n"
            "        print('arrived', flush=True)\n"
            "except KeyboardInterrupt:\n"
            "    print('interrupted', flush=True)\n"
            "    sys.exit(130)\n"
            "finally:\n"
            "    rig.close()\n"
        )
        # SIG_DFL in the child: a suite started in the background by a non-interactive
        # shell inherits SIGINT ignored, and Python then raises no KeyboardInterrupt
        proc = subprocess.Popen(
            [sys.executable, "-c", script, str(runtime)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        try:
            assert proc.stdout.readline().strip() == "moving"
            wait_for(lambda: g.state == "Run" and g.position_deg("X") > 1.0, 20, "the turntable to move")
            assert disp.is_lit()
            wait_for(lambda: dmx.level(1) == 255 and dmx.level(4) == 90, 5, "lights on")
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == 130, err
        assert "interrupted" in out and "arrived" not in out
        wait_for(lambda: dmx.dmx_packets >= 2 and not any(dmx.levels()), 5, "lights off")
        assert (disp.shown(0), disp.shown(1)) == (None, None) and not disp.is_lit()
        # the feed hold may still sit in the pty when the process is gone: wait for the state, then
        # check that it stopped mid-way (a move that was never held would end Idle at 170)
        wait_for(lambda: g.state == "Hold" and g.substate == 0, 10, "Hold:0 (decelerated)")
        stopped = g.position_deg("X")
        assert 1.0 < stopped < 170.0
        # the next run clears the hold (soft reset from Hold:0) and keeps the position
        with open_rig(emus.config) as rig:
            assert g.state == "Idle"
            assert rig.turntable.position_deg() == pytest.approx(stopped, abs=0.02)
            g.time_scale = 0.0
            rig.turntable.move_to(10.0)
        assert g.position_deg("X") == pytest.approx(10.0)


def test_reconnect_is_bounded_and_names_the_device(tmp_path, cfg):
    with start_emulators(cfg, kind="tcp") as emus:
        disp = emus.by_device["backdrops"]
        srv = emus.servers["emulator:display"]
        port = int(srv.url.rsplit(":", 1)[1])
        with open_rig(emus.config, reconnect_attempts=3, reconnect_delay_s=0.01) as rig:
            srv.vanish()
            with pytest.raises(DeviceGone, match=r"backdrops: could not open socket://127.0.0.1:\d+ after 3 attempt"):
                rig.reconnect("backdrops")
            with pytest.raises(ConfigError, match="no port named 'projector'"):
                rig.reconnect("projector")
            srv2 = EmulatorServer(disp, kind="tcp", port=port)
            srv2.start()
            try:
                rig.reconnect("backdrops")
                rig.backdrops.upload("back", 2, PATTERN)
                rig.backdrops.show("back", 2)
                assert disp.shown(1) == 2
            finally:
                rig.close()
                srv2.stop()


def test_open_fails_naming_the_missing_device_and_closes_the_rest(tmp_path, cfg):
    with start_emulators(cfg, kind="tcp") as emus:
        missing = emus.config.with_urls({emus.config.backdrops.url: "/dev/nonexistent-display"})
        rig = build_rig(missing, reconnect_attempts=2, reconnect_delay_s=0.01)
        with pytest.raises(DeviceGone, match=r"backdrops: could not open /dev/nonexistent-display after 2 attempt"):
            rig.open()
        assert not any(p.is_open for p in rig.ports)


def test_cameras_from_config_or_injected(tmp_path):
    example = load_rig_config(EXAMPLE)
    with start_emulators(example) as emus:
        with pytest.raises(ConfigError, match=r"driver = \"sim\": .*use `--rig sim:SCENE`"):
            open_rig(emus.config)
        cams = [DirectoryCamera(tmp_path, name=f"cam{i}") for i in range(6)]
        with pytest.raises(ConfigError, match=r"injected cameras .* must match geometry.cameras"):
            open_rig(emus.config, cameras=cams[::-1])
        with open_rig(emus.config, cameras=cams) as rig:
            assert rig.cameras == cams
    with pytest.raises(ConfigError, match=r"emulator URLs must be started first — run `opacityhull rig emulate"):
        open_rig(EXAMPLE, cameras=cams)
    with pytest.raises(ConfigError, match="rig emulate"):
        check_rig_config(EXAMPLE)


def test_operator_prompts_or_refuses(cfg, emus, capsys):
    spec = CharucoSpec()
    rig = build_rig(emus.config, interactive=False)
    with pytest.raises(
        OperatorActionRequired,
        match=r"manual step is needed — Place the ChArUco calibration board "
        r"flat on the turntable, centred on the axis \(7x5 squares",
    ) as ei:
        rig.operator("place_board", charuco=spec)
    assert ei.value.exit_code == 5 and "assume_ready" in str(ei.value)
    build_rig(emus.config, interactive=False, assume_ready=True).operator("remove_object")
    assert "Remove the object" in capsys.readouterr().err
    prompts = []
    rig = build_rig(emus.config, interactive=True, input_fn=lambda p: prompts.append(p) or "")
    rig.operator("remove_board")
    rig.operator("inspect", what="glare")
    err = capsys.readouterr().err
    assert "Remove the calibration board" in err and "Operator action 'inspect': {'what': 'glare'}" in err
    assert len(prompts) == 2 and "Press Enter" in prompts[0]
    assert [a for a, _ in rig.operator_log] == ["remove_board", "inspect"]

    def eof(prompt):
        raise EOFError

    with pytest.raises(OperatorActionRequired, match="stdin closed"):
        build_rig(emus.config, interactive=True, input_fn=eof).operator("place_object")


def test_check_rig_config_reports_cameras(tmp_path, cfg):
    d = rig_dict(tmp_path)
    d["devices"]["cameras"][0] = {"name": "cam0", "driver": "opencv", "device": 57, "timeout_s": 1.0}
    d["devices"]["cameras"][1] = {"name": "cam1", "driver": "sim"}
    d["devices"]["cameras"][2] = {"name": "cam2", "driver": "directory", "device": str(tmp_path / "gone")}
    with start_emulators(parse_rig_config(d)) as emus:
        infos = {i.name: i for i in check_rig_config(emus.config, timeout_s=0.5)}
    assert not infos["cam0"].ok and "cannot open video device 57" in infos["cam0"].detail
    assert infos["cam1"].ok and infos["cam1"].detail == "simulated: checked by sim"
    assert not infos["cam2"].ok and "does not exist" in infos["cam2"].detail
    assert infos["cam3"].ok and infos["turntable"].ok and infos["backdrops"].ok


def test_a_capture_on_a_hardware_rig_writes_no_ground_truth(tmp_path):
    """Ground truth is not part of the hardware contract: the runner asks only rigs that
    are a GroundTruthSource (the lab rig around the same HardwareRig is one)."""
    from opacityhull.acquire.plan import parse_plan
    from opacityhull.acquire.runner import run_capture
    from opacityhull.rigs.testing import LabRig

    plan = parse_plan(
        {
            "plan": {"name": "hw-tiny", "seed": 5},
            "table": {"steps": 2},
            "exposures": {"default_s": [0.5]},
            "phases": {"lightfield": {"level": 200}},
        },
        where="hw-tiny",
    )
    with LabRig() as lab:
        assert isinstance(lab, GroundTruthSource) and not isinstance(lab.hw, GroundTruthSource)
        res = run_capture(lab.hw, plan, tmp_path / "hw", rig_source="lab")
        assert res.complete and res.images == 6 and not (tmp_path / "hw" / "groundtruth").exists()
        res = run_capture(lab, plan, tmp_path / "lab", rig_source="lab")
        assert res.complete and (tmp_path / "lab" / "groundtruth" / "views.json").is_file()
        assert len(lab.ground_truth_calls) == 1
        assert sorted(map(tuple, lab.ground_truth_calls[0])) == [(c, a) for c in range(3) for a in (0.0, 180.0)]
