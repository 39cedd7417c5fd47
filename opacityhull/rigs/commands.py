"""CLI commands of `opacityhull.rigs` (registered by :mod:`opacityhull.cli`):
``opacityhull rig emulate``, ``opacityhull rig check``, ``opacityhull rig bringup`` and
``opacityhull rig monitors``."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, List

import typer

from ..cliutil import cli_errors, emit

log = logging.getLogger(__name__)

_WRITE_CONFIG_HELP = "Where to write the runtime rig TOML (same rig, real URLs)."
_TCP_HELP = "Serve on TCP sockets (socket://127.0.0.1:PORT) instead of ptys (/dev/pts/N)."
_TIME_SCALE_HELP = "Real seconds per physical second of motion (0 = instant, 1 = real)."
_FAULT_HELP = (
    "DEVICE:KIND[:ARGS] (repeatable): inject a fault, e.g. "
    "turntable:babble:5000, backdrops:garble:3, light_array:vanish:10; kinds: "
    "drop, garble, truncate, late, delay, silent, babble, vanish "
    "(docs/emulator-faults.md)."
)
_CHECK_CONFIG_HELP = "Rig TOML with real URLs (e.g. written by `rig emulate`)."
_CHECK_JSON_HELP = 'Print {"ok", "devices": [{"name", "ok", "detail"}]}.'


def _parse_faults(fault: list[str]) -> dict[str, list[str]]:
    from ..errors import ConfigError

    faults: dict[str, list[str]] = {}
    for f in fault:
        dev, sep, spec = f.partition(":")
        if not sep or not dev or not spec:
            raise ConfigError(f"--fault {f!r}: expected DEVICE:KIND[:ARGS], e.g. turntable:babble:5000")
        faults.setdefault(dev, []).append(spec)
    return faults


def register(app, groups) -> None:
    """Add ``rig emulate``, ``rig check``, ``rig bringup`` and ``rig monitors`` to the ``rig`` group."""
    rig = groups["rig"]

    @rig.command("emulate")
    @cli_errors
    def emulate(
        config: Annotated[Path, typer.Option("--config", help="Rig TOML whose emulator:KIND URLs to serve.")],
        write_config: Annotated[Path, typer.Option("--write-config", help=_WRITE_CONFIG_HELP)],
        tcp: Annotated[bool, typer.Option("--tcp", help=_TCP_HELP)] = False,
        time_scale: Annotated[float, typer.Option("--time-scale", min=0.0, help=_TIME_SCALE_HELP)] = 0.0,
        fault: Annotated[List[str], typer.Option("--fault", help=_FAULT_HELP)] = [],
        json_out: Annotated[bool, typer.Option("--json", help="Print {config, devices} as one JSON line.")] = False,
    ):
        """Start an emulator for every `emulator:` device of a rig TOML and serve until Ctrl-C / SIGTERM.

        Writes RUNTIME.toml (the same rig with real URLs) for `rig check`, `capture` and
        scripts to use from other processes. pty URLs work across processes on Linux while
        this process runs (it keeps the pty masters open); --tcp works across machines too.
        """
        import signal
        import threading

        from ..errors import ConfigError
        from .config import load_rig_config
        from .emulators.launch import start_emulators

        cfg = load_rig_config(config)
        if not cfg.emulated():
            raise ConfigError(f"{config}: no device has an emulator:KIND URL — nothing to emulate")
        faults = _parse_faults(fault)
        stop = threading.Event()
        received: list[int] = []

        def on_signal(signum, frame):
            received.append(signum)
            stop.set()

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        try:
            with start_emulators(cfg, kind="tcp" if tcp else "pty", time_scale=time_scale, faults=faults) as emus:
                emus.config.write(write_config)
                summary = {
                    "config": str(write_config),
                    "devices": emus.devices(),
                    "transport": "tcp" if tcp else "pty",
                    "time_scale": time_scale,
                    "faults": faults,
                }

                def human(s):  # human text on stderr, like every command (stdout is for --json)
                    typer.echo(f"runtime config: {s['config']}", err=True)
                    for name, url in s["devices"].items():
                        typer.echo(f"  {name:24s} {url}", err=True)
                    for name, fl in s["faults"].items():
                        typer.echo(f"  fault on {name}: {', '.join(fl)}", err=True)
                    typer.echo("serving; Ctrl-C or SIGTERM stops", err=True)

                emit(summary, json_out, human)
                while not stop.is_set():
                    stop.wait(0.25)
        finally:
            for s, h in old.items():
                signal.signal(s, h)

    @rig.command("check")
    @cli_errors
    def check(
        config: Annotated[Path, typer.Option("--config", help=_CHECK_CONFIG_HELP)],
        timeout_s: Annotated[float, typer.Option("--timeout", min=0.05, help="Seconds to wait for each reply.")] = 1.0,
        json_out: Annotated[bool, typer.Option("--json", help=_CHECK_JSON_HELP)] = False,
    ):
        """Talk to every device of a rig and print its identity and state; exit 3 naming the devices that fail.

        Simulated cameras (driver = "sim") are reported as checked by the simulator.
        """
        from ..errors import DeviceError
        from .rig import check_rig_config

        infos = check_rig_config(config, timeout_s=timeout_s)
        ok = all(i.ok for i in infos)
        summary = {
            "ok": ok,
            "config": str(config),
            "devices": [
                {"name": i.name, "ok": i.ok, "detail": i.detail, "identity": i.identity, "state": i.state}
                for i in infos
            ],
        }

        def human(s):
            for d in s["devices"]:
                mark = "ok  " if d["ok"] else "FAIL"
                ident = f"  [{d['identity']}]" if d["identity"] and d["identity"] not in d["detail"] else ""
                typer.echo(f"{mark} {d['name']:24s} {d['detail']}{ident}", err=True)

        emit(summary, json_out, human)
        if not ok:
            bad = [i for i in infos if not i.ok]
            raise DeviceError("rig check failed: " + "; ".join(f"{i.name}: {i.detail}" for i in bad))

    @rig.command("monitors")
    @cli_errors
    def monitors(
        display: Annotated[str, typer.Option("--display", help="X display (default $DISPLAY).")] = "",
        json_out: Annotated[bool, typer.Option("--json", help='Print {"monitors": [...]}.')] = False,
    ):
        """List the monitors a video-output rig can name in [devices.backdrops.monitors]."""
        from dataclasses import asdict

        from .video import list_monitors

        mons = list_monitors(display or None)

        def human(s):
            for m in s["monitors"]:
                typer.echo(f"{m['name']:16s} {m['width']}x{m['height']}+{m['x']}+{m['y']}  (X screen {m['x_screen']})")

        emit({"monitors": [asdict(m) for m in mons]}, json_out, human)

    @rig.command("bringup")
    @cli_errors
    def bringup(
        config: Annotated[Path, typer.Option("--config", help="Rig TOML (emulator: URLs are started here).")],
        plan: Annotated[
            str, typer.Option("--plan", help="Plan whose calibration board and exposures the walk uses.")
        ] = "builtin:demo",
        state: Annotated[
            Path | None, typer.Option("--state", help="Progress file (default: RIG.bringup.json beside the TOML).")
        ] = None,
        restart: Annotated[bool, typer.Option("--restart", help="Forget earlier passed steps.")] = False,
        scene: Annotated[
            str, typer.Option("--scene", help='Scene the simulated cameras see (driver = "sim" cameras).')
        ] = "builtin:diffuse",
        spp: Annotated[int, typer.Option("--spp", min=1, help="Samples per pixel of simulated cameras.")] = 4,
        fault: Annotated[List[str], typer.Option("--fault", help=_FAULT_HELP)] = [],
        json_out: Annotated[bool, typer.Option("--json", help='Print {"ok", "steps": [...]}.')] = False,
    ):
        """Walk the rig device by device: every device answers, the turntable turns 90 deg and back and a camera
        sees the board turn, each lamp lights, each display shows white and black (with its contrast), the exposure
        bracket is unclipped. Resumable: passed steps are skipped the next time. Exit 3 names the failed steps."""
        from ..acquire.plan import load_plan
        from ..errors import DeviceError
        from .bringup import BringupOptions, open_for_bringup, run_bringup
        from .config import load_rig_config

        the_plan = load_plan(plan)
        cfg = load_rig_config(config)
        calib = the_plan.calibration
        exposures = tuple(sorted(set(the_plan.default_exposures_s)))
        opts = BringupOptions(
            charuco=calib.charuco if calib is not None else BringupOptions().charuco,
            exposure_s=max(exposures),
            bracket_s=exposures,
            lamp_exposure_s=max(the_plan.exposures("reflectance")) if the_plan.reflectance is not None else None,
        )
        faults = _parse_faults(fault)
        state_path = state if state is not None else config.with_name(config.stem + ".bringup.json")

        def emit_step(r):
            typer.echo(r.line(), err=True)

        with open_for_bringup(cfg, faults=faults, scene=scene, spp=spp) as (the_rig, failed):
            results = run_bringup(
                the_rig, options=opts, state_path=state_path, restart=restart, failed_ports=failed, emit=emit_step
            )
        ok = all(r.verdict == "pass" for r in results)
        summary = {
            "ok": ok,
            "config": str(config),
            "state": str(state_path),
            "steps": [
                {
                    "step": r.step,
                    "device": r.device,
                    "checks": r.checks,
                    "verdict": r.verdict,
                    "measurement": r.measurement,
                    "what_to_check": r.what_to_check,
                    "earlier": r.earlier,
                }
                for r in results
            ],
        }

        def human(s):
            n_ok = sum(1 for r in s["steps"] if r["verdict"] == "pass")
            typer.echo(f"bring-up: {n_ok} of {len(s['steps'])} steps pass (progress in {s['state']})", err=True)

        emit(summary, json_out, human)
        if not ok:
            bad = [r for r in results if r.verdict == "fail"]
            raise DeviceError("bring-up failed: " + "; ".join(f"{r.step}: {r.what_to_check}" for r in bad))
