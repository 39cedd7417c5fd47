"""`opacityhull rig emulate` / `rig check` end to end, in separate processes."""

import json
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "rig-emulated.toml"
CLI = [sys.executable, "-m", "opacityhull.cli"]
SERIAL_DEVICES = ["turntable", "light_array.rotation", "light_array", "backdrops"]


def start_emulate(runtime: Path, *extra):
    proc = subprocess.Popen(
        [*CLI, "rig", "emulate", "--config", str(EXAMPLE), "--write-config", str(runtime), "--json", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    line = proc.stdout.readline()
    if not line:
        proc.kill()
        raise AssertionError(f"rig emulate printed nothing: {proc.communicate()[1]}")
    return proc, json.loads(line)


def rig_check(runtime: Path, *extra, timeout=30):
    return subprocess.run(
        [*CLI, "rig", "check", "--config", str(runtime), *extra],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout,
    )


def flat(text: str) -> str:
    """stderr without rich's line wrapping."""
    return " ".join(text.split())


def stop(proc, sig):
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_emulate_tcp_check_ok_then_killed_emulator_fails_fast(tmp_path):
    runtime = tmp_path / "runtime.toml"
    proc, info = start_emulate(runtime, "--tcp")
    try:
        assert info["config"] == str(runtime) and runtime.is_file()
        assert list(info["devices"]) == ["turntable", "light_array", "light_array.rotation", "backdrops"]
        assert all(u.startswith("socket://127.0.0.1:") for u in info["devices"].values())
        assert info["devices"]["turntable"] == info["devices"]["light_array.rotation"]
        r = rig_check(runtime, "--json")
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout)
        assert out["ok"] is True
        names = [d["name"] for d in out["devices"]]
        assert names == SERIAL_DEVICES + [f"cam{i}" for i in range(6)]
        assert all(d["ok"] for d in out["devices"])
        by = {d["name"]: d for d in out["devices"]}
        assert "Grbl 1.1h" in by["turntable"]["identity"] and by["turntable"]["state"]["state"] == "Idle"
        assert "OHDC-2" in by["backdrops"]["identity"]
        assert by["cam3"]["detail"] == "simulated: checked by sim"
    finally:
        proc.kill()  # a crash, not a clean stop
        proc.wait()
    # every serial device is gone now; check must say so, by name, quickly (subprocess timeout = 10 s)
    r = rig_check(runtime, "--json", timeout=10)
    assert r.returncode == 3
    out = json.loads(r.stdout)
    assert out["ok"] is False
    failed = [d["name"] for d in out["devices"] if not d["ok"]]
    assert failed == SERIAL_DEVICES
    assert "Connection refused" in {d["name"]: d for d in out["devices"]}["backdrops"]["detail"]
    assert "rig check failed: turntable:" in flat(r.stderr) and "backdrops:" in flat(r.stderr)


def test_emulate_pty_serves_other_processes_until_sigterm(tmp_path):
    """pty URLs work across processes on Linux while the emulating process keeps the masters open."""
    runtime = tmp_path / "rt.toml"
    proc, info = start_emulate(runtime)
    try:
        assert all(u.startswith("/dev/pts/") for u in info["devices"].values())
        r = rig_check(runtime)  # human output
        assert r.returncode == 0, r.stderr
        assert r.stdout == ""  # human text goes to stderr, like every command's (stdout is for --json)
        lines = [x for x in r.stderr.splitlines() if x.startswith(("ok ", "FAIL"))]
        assert lines[0].startswith("ok   turntable") and len(lines) == 10
        assert all(line.startswith("ok ") for line in lines)
    finally:
        rc = stop(proc, signal.SIGTERM)
    assert rc == 0
    from opacityhull.rigs.rig import check_rig_config

    infos = check_rig_config(runtime)  # the ptys are gone with the process
    assert [i.name for i in infos if not i.ok] == SERIAL_DEVICES
    assert "No such file or directory" in infos[0].detail


def test_emulate_stops_cleanly_on_ctrl_c(tmp_path):
    proc, info = start_emulate(tmp_path / "rt.toml", "--time-scale", "1")
    assert stop(proc, signal.SIGINT) == 0


def test_bad_invocations_exit_with_input_error(tmp_path):
    import typer
    from typer.testing import CliRunner

    from opacityhull.rigs.commands import register

    # only this stage's commands, in-process (the subprocess tests above use the real entry point)
    app = typer.Typer()
    groups = {"rig": typer.Typer()}
    app.add_typer(groups["rig"], name="rig")
    register(app, groups)
    runner = CliRunner()
    r = runner.invoke(app, ["rig", "check", "--config", str(EXAMPLE)])
    assert r.exit_code == 2 and "rig emulate" in flat(r.output)
    real = tmp_path / "real.toml"
    real.write_text(
        EXAMPLE.read_text()
        .replace('"emulator:grbl"', '"/dev/ttyUSB0"')
        .replace('"emulator:enttec"', '"/dev/ttyUSB1"')
        .replace('"emulator:display"', '"/dev/ttyS0"')
    )
    r = runner.invoke(app, ["rig", "emulate", "--config", str(real), "--write-config", str(tmp_path / "x.toml")])
    assert r.exit_code == 2 and "nothing to emulate" in flat(r.output) and not (tmp_path / "x.toml").exists()
    r = runner.invoke(app, ["rig", "check", "--config", str(tmp_path / "missing.toml"), "--json"])
    assert r.exit_code == 2 and "missing.toml not found" in flat(r.output)
