"""CLI commands of `opacityhull.rigs` (registered by :mod:`opacityhull.cli`):
``opacityhull rig emulate``, ``opacityhull rig check`` and ``opacityhull rig monitors``
(``opacityhull rig bringup`` is registered by :mod:`opacityhull.acquire.commands`: it reads
a capture plan and builds simulated cameras, both above rigs/)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from ..cliutil import cli_errors, emit

log = logging.getLogger(__name__)

_WRITE_CONFIG_HELP = "Where to write the runtime rig TOML (same rig, real URLs)."
_TCP_HELP = "Serve on TCP sockets (socket://127.0.0.1:PORT) instead of ptys (/dev/pts/N)."
_TIME_SCALE_HELP = "Real seconds per physical second of motion (0 = instant, 1 = real)."
FAULT_HELP = (
    "DEVICE:KIND[:ARGS] (repeatable): inject a fault, e.g. "
    "turntable:babble:5000, backdrops:garble:3, light_array:vanish:10; kinds: "
    "drop, garble, truncate, late, delay, silent, babble, vanish "
    "(docs/emulator-faults.md)."
)
_CHECK_CONFIG_HELP = "Rig TOML with real URLs (e.g. written by `rig emulate`)."
_CHECK_JSON_HELP = 'Print {"ok", "devices": [{"name", "ok", "detail"}]}.'


def parse_faults(fault: list[str]) -> dict[str, list[str]]:
    from ..errors import ConfigError

    faults: dict[str, list[str]] = {}
    for f in fault:
        dev, sep, spec = f.partition(":")
        if not sep or not dev or not spec:
            raise ConfigError(f"--fault {f!r}: expected DEVICE:KIND[:ARGS], e.g. turntable:babble:5000")
        faults.setdefault(dev, []).append(spec)
    return faults


def register(app, groups) -> None:
    """Add ``rig emulate``, ``rig check`` and ``rig monitors`` to the ``rig`` group."""
    rig = groups["rig"]

    @rig.command("emulate")
    @cli_errors
    def emulate(
        config: Annotated[Path, typer.Option("--config", help="Rig TOML whose emulator:KIND URLs to serve.")],
        write_config: Annotated[Path, typer.Option("--write-config", help=_WRITE_CONFIG_HELP)],
        tcp: Annotated[bool, typer.Option("--tcp", help=_TCP_HELP)] = False,
        time_scale: Annotated[float, typer.Option("--time-scale", min=0.0, help=_TIME_SCALE_HELP)] = 0.0,
        fault: Annotated[list[str], typer.Option("--fault", help=FAULT_HELP)] = [],  # noqa: B006  typer hands the body a fresh list; the body only reads it
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
        faults = parse_faults(fault)
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
