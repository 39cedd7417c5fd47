"""``opacityhull rig bringup`` with a capture plan: the walk's thresholds from the plan,
the rig opened with its cameras, the walk run and summarised.

The walk itself (:mod:`opacityhull.rigs.bringup`) knows devices only; this module adds
what sits above rigs/: the plan's calibration board and exposures, and the simulated
cameras, which the CLI (``acquire/commands.py``, the one acquire module allowed to import
sim/) passes in as ``simulated``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from collections.abc import Callable

from ..rigs.bringup import BringupOptions, SimulatedRig, StepResult, open_for_bringup, run_bringup
from .plan import CapturePlan

__all__ = ["bringup_options", "bringup_rig", "bringup_summary"]


def bringup_options(plan: CapturePlan) -> BringupOptions:
    """The walk's options from ``plan``: its calibration board (the default board without a
    calibration phase), its exposures as the bracket (the longest for the board and display
    photographs) and its reflectance exposure for the lamp photographs."""
    calib = plan.calibration
    exposures = tuple(sorted(set(plan.default_exposures_s)))
    return BringupOptions(
        charuco=calib.charuco if calib is not None else BringupOptions().charuco,
        exposure_s=max(exposures),
        bracket_s=exposures,
        lamp_exposure_s=max(plan.exposures("reflectance")) if plan.reflectance is not None else None,
    )


def bringup_rig(
    config,
    *,
    plan: CapturePlan,
    state_path: str | Path | None = None,
    restart: bool = False,
    faults: dict[str, list[str]] | None = None,
    simulated: Callable[[Any], SimulatedRig] | None = None,
    emit: Callable[[StepResult], None] = lambda r: None,
) -> list[StepResult]:
    """Open the rig of ``config`` (a :class:`~opacityhull.rigs.config.RigConfig`; emulators
    started here, with ``faults``; ``simulated`` builds ``driver = "sim"`` cameras) and
    walk it with ``plan``'s options; every step's result, in order."""
    with open_for_bringup(config, faults=faults, simulated=simulated) as (rig, failed):
        return run_bringup(
            rig, options=bringup_options(plan), state_path=state_path, restart=restart, failed_ports=failed, emit=emit
        )


def bringup_summary(results: list[StepResult], *, config: str | Path, state_path: str | Path) -> dict:
    """The ``--json`` object of ``rig bringup``: ``ok``, ``config``, ``state`` and ``steps``."""
    return {
        "ok": all(r.verdict == "pass" for r in results),
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
