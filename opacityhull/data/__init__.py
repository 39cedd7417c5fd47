"""Data shipped with the package: real HDR light probes for tests and demos.

``probes/`` holds five 256×128 equirectangular Radiance files (ennis, grace, pisa,
uffizi from the USC ICT light probe gallery; wells by Bernhard Vogl), in the downsampled
form redistributed by the open-source Probulator project (see ``probes/README.md``).
Their centre column looks along −Z (the ICT convention): use ``yaw_deg=180`` to bring
them to the project convention (+Z).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError

PROBES_DIR = Path(__file__).resolve().parent / "probes"
PROBE_NAMES = ("ennis", "grace", "pisa", "uffizi", "wells")
#: Yaw that converts the shipped probes to the project convention (centre column along +Z).
PROBE_YAW_DEG = 180.0


def probe_path(name: str) -> Path:
    """Path of a shipped probe by name (``"grace"``) or ``builtin:grace``."""
    name = name.removeprefix("builtin:")
    if name not in PROBE_NAMES:
        raise InputError(f"unknown built-in probe {name!r}; choose one of {', '.join(PROBE_NAMES)}")
    return PROBES_DIR / f"{name}.hdr"
