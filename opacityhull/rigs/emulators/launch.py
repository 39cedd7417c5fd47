"""Start the emulators a rig config asks for (``emulator:KIND[#tag]`` URLs).

:func:`start_emulators` starts one in-process emulator per distinct emulator URL —
a GRBL controller whose axes are the config's axes on that URL, an Enttec DMX USB
Pro, a display controller with as many outputs as the config uses, a Samsung MDC panel
per ``emulator:mdc#tag`` control port — each behind an
:class:`~opacityhull.rigs.emulators.base.EmulatorServer` (a pty by default, or TCP),
and returns an :class:`EmulatorSet`: a copy of the config with the real URLs, and the
emulator objects (so the simulator, or a test, can read their state).

pty or TCP across processes: a pty slave (``/dev/pts/N``) can be opened by any
process of the same user on Linux for as long as the emulating process keeps the
master open (the server does, until :meth:`EmulatorSet.stop`). TCP
(``socket://127.0.0.1:PORT``) works the same and also from other machines' tools
that speak TCP; ``opacityhull rig emulate --tcp`` uses it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from ...errors import ConfigError
from ..config import RigConfig, emulator_url_faults, parse_emulator_url
from .base import EmulatedDevice, EmulatorServer

log = logging.getLogger(__name__)

__all__ = ["EmulatorSet", "start_emulators"]


@dataclass
class EmulatorSet:
    """Running emulators for one rig config.

    Attributes
    ----------
    config : RigConfig
        Copy of the config with every ``emulator:`` URL replaced by the real URL.
    handles : dict emulator URL (``"emulator:grbl"``) → emulator object
    servers : dict emulator URL → :class:`EmulatorServer`
    by_device : dict device name (``"turntable"``, ``"light_array"``,
        ``"light_array.rotation"``, ``"backdrops"``) → emulator object
    urls : dict emulator URL → real URL
    """

    config: RigConfig
    handles: dict[str, EmulatedDevice] = field(default_factory=dict)
    servers: dict[str, EmulatorServer] = field(default_factory=dict)
    by_device: dict[str, EmulatedDevice] = field(default_factory=dict)
    urls: dict[str, str] = field(default_factory=dict)

    def devices(self) -> dict[str, str]:
        """Device name → real URL (every serial device of the config)."""
        return self.config.device_urls()

    def stop(self) -> None:
        """Stop every server (the ports disappear)."""
        for srv in self.servers.values():
            try:
                srv.stop()
            except Exception as e:  # noqa: BLE001  stop the others all the same
                log.warning("emulator %s: stop failed: %s", srv.url, e)

    def __enter__(self) -> EmulatorSet:
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


def _make(kind: str, url: str, config: RigConfig, time_scale: float) -> EmulatedDevice:
    if kind == "grbl":
        from .grbl import GrblEmulator

        axes = [a for a in config.axes() if a.url == url]
        return GrblEmulator(
            axes=tuple(a.axis for a in axes),
            steps_per_deg={a.axis: a.steps_per_deg for a in axes},
            time_scale=time_scale,
        )
    if kind == "enttec":
        from .enttec import EnttecEmulator

        return EnttecEmulator(time_scale=time_scale)
    if kind == "display":
        from .display import DisplayEmulator

        bd = config.backdrops
        n = max(bd.output_map.values()) + 1 if bd is not None and bd.url == url else 2
        return DisplayEmulator(outputs=max(n, 2), time_scale=time_scale)
    if kind == "mdc":
        from .mdc import MdcEmulator

        panel = next(p for p in config.panels if p.url == url)
        return MdcEmulator(display_id=panel.display_id, time_scale=time_scale)
    raise ConfigError(f"{config.source}: unknown emulator kind {kind!r} in {url!r}")


def start_emulators(
    config: RigConfig, *, kind: str = "pty", time_scale: float = 0.0, faults: dict[str, list[str]] | None = None
) -> EmulatorSet:
    """Start one emulator per distinct ``emulator:KIND[#tag]`` URL of ``config``.

    Parameters
    ----------
    config : RigConfig
    kind : "pty" or "tcp"
        Transport of the servers.
    time_scale : float
        Real seconds per physical second of motion/switching (0 = instant).
    faults : dict device name → list of ``KIND[:ARGS]`` specs, optional
        Faults to inject (:mod:`~opacityhull.rigs.emulators.faults`), in addition to
        those in the URLs' ``?fault=`` queries. A device sharing its emulator with
        another (``turntable`` and ``light_array.rotation`` on one GRBL) shares its faults.

    Returns
    -------
    EmulatorSet
        Use as a context manager, or call :meth:`EmulatorSet.stop`. Non-emulator URLs are
        left as they are.
    """
    if kind not in ("pty", "tcp"):
        raise ConfigError(f"emulator transport must be 'pty' or 'tcp', got {kind!r}")
    if time_scale < 0:
        raise ConfigError(f"time_scale must be >= 0, got {time_scale}")
    from .faults import apply_fault, parse_fault

    emu = EmulatorSet(config=config)
    names_by_url: dict[str, list[str]] = {}
    for name, url in config.device_urls().items():
        if parse_emulator_url(url) is not None:
            names_by_url.setdefault(url, []).append(name)
    specs: dict[str, list] = {
        u: [parse_fault(f, where=f"{config.source}: {u}") for f in emulator_url_faults(u)] for u in names_by_url
    }
    for dev_name, fl in (faults or {}).items():
        url = config.device_urls().get(dev_name)
        if url is None or url not in names_by_url:
            known = [n for u, ns in names_by_url.items() for n in ns]
            raise ConfigError(
                f"--fault {dev_name}:...: no emulated device {dev_name!r} in {config.source} "
                f"(emulated: {', '.join(known) or 'none'})"
            )
        specs[url] += [parse_fault(f, where=f"--fault {dev_name}:{f}") for f in fl]
    try:
        for url, names in names_by_url.items():
            parsed = parse_emulator_url(url)
            assert parsed is not None  # names_by_url holds emulator URLs only
            k, _tag = parsed
            dev = _make(k, url, config, time_scale)
            srv = EmulatorServer(dev, kind=kind)
            emu.servers[url] = srv
            emu.urls[url] = srv.start()
            emu.handles[url] = dev
            for n in names:
                emu.by_device[n] = dev
        # faults once every port is open: `vanish:0` closed a pty master at once, and the
        # next emulator got the freed pty number, so the written config sent the vanished
        # device's URL to another device (rig check: exit 2 instead of 3)
        for url in names_by_url:
            for spec in specs[url]:
                apply_fault(spec, emu.handles[url], emu.servers[url])
    except BaseException:
        emu.stop()
        raise
    emu.config = config.with_urls(emu.urls)
    return emu
