"""Capture: plans, sessions on disk (manifest, resume), HDR merge, imports.

Depends only on the device protocols (:mod:`opacityhull.rigs.interfaces`) and the
session format (:mod:`opacityhull.session`); never on a concrete driver or on ``sim``.

* :mod:`.plan` — capture plans (TOML → frozen dataclasses; ``builtin:tiny|demo|paper``)
* :mod:`.schedule` — plan × rig geometry → ordered shots; counts, bytes, time estimates
* :mod:`.patterns` — backdrop patterns (random + complements, natural images)
* :mod:`.runner` — :func:`run_capture`: resumable, crash-safe capture into a session
* :mod:`.verify` — ``session verify`` / ``session info``
* :mod:`.hdr` — exposure brackets → radiance (linear merge, Debevec–Malik)
* :mod:`.importers` — COLMAP-calibrated image sets → sessions
"""

from .plan import CapturePlan, load_plan, parse_plan
from .runner import CaptureResult, DiskFull, run_capture

__all__ = ["CapturePlan", "CaptureResult", "DiskFull", "load_plan", "parse_plan", "run_capture"]
