"""Fault specs for the emulators: ``KIND[:ARGS]`` strings, as given to ``rig emulate
--fault DEVICE:KIND[:ARGS]`` or in an ``emulator:`` URL's ``?fault=`` query.

Documented for users in ``docs/emulator-faults.md``. Each spec sets fields of the
emulator's :class:`~opacityhull.rigs.emulators.base.Faults` (or, for ``vanish``,
unplugs the port after a delay), so the same faults the tests use in Python are
available to anyone testing their own rig software against the emulators.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from ...errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["FaultSpec", "FAULT_KINDS", "parse_fault", "apply_fault"]

#: kind → (argument names, defaults, what it does)
FAULT_KINDS = {
    "drop": (("count",), (1,), "the next COUNT replies are discarded"),
    "garble": (("count",), (1,), "the next COUNT replies have every even byte XOR 0x5A (line ending kept)"),
    "truncate": (("count",), (1,), "the next COUNT replies are cut to half (the terminator is lost)"),
    "late": (("count", "seconds"), (1, 1.0), "the next COUNT replies arrive SECONDS late, overtaken by later ones"),
    "delay": (("seconds",), (0.5,), "every reply is delayed by SECONDS"),
    "silent": ((), (), "nothing is answered at all (a hung device)"),
    "babble": (
        ("bytes_per_s",),
        (2000.0,),
        "BYTES_PER_S of noise that never parses, continuously (wrong baud rate, a babbling device)",
    ),
    "vanish": (("after_s",), (0.0,), "the port disappears AFTER_S seconds after the emulator starts (unplugged)"),
}


@dataclass(frozen=True)
class FaultSpec:
    """One parsed fault: ``kind`` and its arguments by name."""

    kind: str
    args: tuple

    def __str__(self) -> str:
        return ":".join([self.kind, *(f"{a:g}" if isinstance(a, float) else str(a) for a in self.args)])


def parse_fault(text: str, *, where: str = "fault") -> FaultSpec:
    """``"late:2:0.5"`` → ``FaultSpec("late", (2, 0.5))``; :class:`ConfigError` naming
    ``where``, the value and the kinds otherwise."""
    if not isinstance(text, str) or not text:
        raise ConfigError(f"{where}: expected KIND[:ARGS], got {text!r}")
    kind, *raw = text.split(":")
    if kind not in FAULT_KINDS:
        raise ConfigError(
            f"{where}: unknown fault {kind!r} in {text!r}; expected one of {', '.join(FAULT_KINDS)} "
            "(see docs/emulator-faults.md)"
        )
    names, defaults, _ = FAULT_KINDS[kind]
    if len(raw) > len(names):
        raise ConfigError(
            f"{where}: {text!r}: {kind} takes at most {len(names)} argument(s) "
            f"({':'.join(n.upper() for n in names) or 'none'})"
        )
    args = list(defaults)
    for i, v in enumerate(raw):
        want = type(defaults[i])
        try:
            x = want(v) if want is float else int(v)
        except ValueError:
            raise ConfigError(
                f"{where}: {text!r}: {names[i].upper()} = {v!r} is not {'a number' if want is float else 'an integer'}"
            ) from None
        if not x >= 0 or (names[i] in ("count", "bytes_per_s") and x == 0):
            raise ConfigError(
                f"{where}: {text!r}: {names[i].upper()} must be "
                f"{'> 0' if names[i] in ('count', 'bytes_per_s') else '>= 0'}, got {v}"
            )
        args[i] = x
    return FaultSpec(kind, tuple(args))


def apply_fault(spec: FaultSpec, device, server=None) -> None:
    """Set ``spec`` on ``device.faults`` (and, for ``vanish``, arm a timer on ``server``)."""
    f = device.faults
    a = spec.args
    with device.lock:
        if spec.kind in ("drop", "garble", "truncate"):
            setattr(f, spec.kind, getattr(f, spec.kind) + a[0])
        elif spec.kind == "late":
            f.late += a[0]
            f.late_s = a[1]
        elif spec.kind == "delay":
            f.delay_s = a[0]
        elif spec.kind == "silent":
            f.silent = True
        elif spec.kind == "babble":
            f.babble = a[0]
    if spec.kind == "vanish":
        if server is None:
            raise ConfigError(f"fault {spec}: needs a running emulator server")
        if a[0] <= 0:
            server.vanish()
        else:
            t = threading.Timer(a[0], server.vanish)
            t.daemon = True
            t.start()
