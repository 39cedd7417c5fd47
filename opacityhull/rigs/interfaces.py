"""Device interfaces (``typing.Protocol``) the pipeline depends on.

``acquire`` types its rig against these and never against a concrete driver or
``sim``. Hardware drivers (``rigs``) and the simulated rig (``sim``) both implement
them. All angles are in degrees, times in seconds. (The wire protocols are the
``*_protocol`` modules; this module is about Python interfaces only.)
"""

from __future__ import annotations

import logging
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from ..errors import DeviceError
from ..riggeometry import RigGeometry

log = logging.getLogger(__name__)

__all__ = [
    "DeviceInfo",
    "Turntable",
    "RotaryAxis",
    "LightArray",
    "Backdrops",
    "PatternStore",
    "PatternMissing",
    "StorageFull",
    "ImageOutput",
    "LockablePanels",
    "DisplayDrift",
    "CameraDevice",
    "CameraInfo",
    "Rig",
    "GroundTruthSource",
    "PhaseAware",
    "Port",
]


@dataclass(frozen=True)
class DeviceInfo:
    """What ``rig check`` reports for one device."""

    name: str
    ok: bool
    detail: str
    identity: str = ""
    state: dict = field(default_factory=dict)


def check_opened(device: Any, probe: Callable[[], DeviceInfo]) -> DeviceInfo:
    """``probe()`` with ``device`` open; never raises.

    A closed device is opened for the probe and closed again, so ``rig check`` leaves every
    port as it found it; a :class:`~opacityhull.errors.DeviceError` becomes ``ok=False`` with
    the reason.
    """
    opened_here = False
    try:
        if not device.is_open:
            device.open()
            opened_here = True
        return probe()
    except DeviceError as e:
        return DeviceInfo(device.name, False, str(e), state={"url": device.url})
    finally:
        if opened_here:
            device.close()


@runtime_checkable
class RotaryAxis(Protocol):
    """A motorised rotation (turntable, light-array rotation)."""

    name: str

    def move_to(self, angle_deg: float, *, timeout_s: float | None = None) -> float:
        """Absolute move; blocks until idle at the target; returns the reached angle."""
        ...

    def position_deg(self) -> float:
        """Current angle from the controller's status report."""
        ...

    def home(self) -> None:
        """Run the homing cycle (angle 0 afterwards)."""
        ...

    def stop(self) -> None:
        """Feed hold: stop motion now (safe to call at any time, never raises on a dead port)."""
        ...

    def check(self) -> DeviceInfo: ...


class Turntable(RotaryAxis, Protocol):
    """The object turntable (carries the bottom display)."""


@runtime_checkable
class LightArray(Protocol):
    """Overhead array of lights on DMX channels, rotating about the table axis."""

    name: str

    @property
    def light_ids(self) -> Sequence[int]: ...

    def set_levels(self, levels: Mapping[int, int]) -> None:
        """Set the given lights (id → 0..255) and switch every other light off."""
        ...

    def all_off(self) -> None:
        """Every light off (never raises on a dead port; used by ``Rig.safe``)."""
        ...

    def levels(self) -> dict[int, int]:
        """Last levels sent, per light id."""
        ...

    @property
    def rotation(self) -> RotaryAxis | None:
        """The array's rotation axis (None: the array is fixed)."""
        ...

    @property
    def last_error(self) -> Exception | None:
        """What the last :meth:`all_off` swallowed (None: it went through)."""
        ...

    def check(self) -> DeviceInfo: ...


@runtime_checkable
class Backdrops(Protocol):
    """The plasma displays under and behind the object."""

    name: str

    @property
    def displays(self) -> Sequence[str]: ...

    def upload(self, display: str, pattern_id: int, image_rgb8: np.ndarray) -> object:
        """Store pattern ``pattern_id`` (uint8 (rows, cols, 3)) in the display controller
        (the hardware driver returns whether bytes were sent)."""
        ...

    def show(self, display: str, pattern_id: int) -> None:
        """Show a stored pattern (powers the panel on)."""
        ...

    def blank(self, display: str | None = None) -> None:
        """Show black on one display or all (never raises on a dead port)."""
        ...

    def shown(self) -> dict[str, int | None]:
        """Pattern id shown per display (None = blank)."""
        ...

    @property
    def last_error(self) -> str | None:
        """What the last :meth:`blank` swallowed (None: it went through)."""
        ...

    def check(self) -> DeviceInfo: ...


class PatternMissing(DeviceError):
    """The display controller holds no pattern of that id (SHOW or DELETE of an id it
    does not store: never uploaded, or lost in a power cycle)."""


class StorageFull(DeviceError):
    """The display controller's pattern store is full: delete a pattern before uploading."""


@runtime_checkable
class PatternStore(Protocol):
    """Backdrops whose controller stores uploaded patterns in a fixed number of slots
    (the display controller). The capture runner uses the store as a least-recently-used
    cache (:mod:`opacityhull.acquire.pattern_cache`); :meth:`Backdrops.upload` raises
    :class:`StorageFull` when it is full and :meth:`Backdrops.show` / :meth:`delete`
    :class:`PatternMissing` for an id it does not hold. Backdrops without a store (a
    video output, :class:`ImageOutput`) are not a ``PatternStore``."""

    def stored(self) -> list[int]:
        """The pattern ids the controller holds now (it may have been power-cycled)."""
        ...

    def delete(self, pattern_id: int | None = None) -> None:
        """Delete one stored pattern (None: all of them)."""
        ...

    def slots(self) -> int | None:
        """How many patterns the store holds (the controller's IDENTIFY ``slots=``),
        None when the controller does not say: then it is filled until :class:`StorageFull`.
        (A method, not a property: asking may talk to the device, and ``isinstance`` on a
        runtime protocol reads every member.)"""
        ...

    def identity(self) -> str:
        """The controller's IDENTIFY reply (model, firmware, outputs, slots)."""
        ...


@runtime_checkable
class ImageOutput(Protocol):
    """Backdrops that draw any image as it is shown (a video output): no upload, no store."""

    def show_image(self, display: str, image_rgb8: np.ndarray, *, pattern_id: int | None = -1) -> object:
        """Show ``image_rgb8`` (uint8 (rows, cols, 3)) full-screen on ``display``; returns
        once it is on the panel. ``pattern_id`` is what :meth:`Backdrops.shown` reports."""
        ...


class DisplayDrift(DeviceError):
    """A backdrop panel may change its own radiance during matting (auto-brightness,
    dynamic contrast) and the capture was not told to allow it (raised by the capture
    runner after :meth:`LockablePanels.lock_panels`)."""


@runtime_checkable
class LockablePanels(Protocol):
    """Backdrops whose panels' radiance settings (auto-brightness, dynamic contrast) can
    be locked over a control port (video outputs on MDC panels)."""

    def lock_panels(self) -> dict[str, Any]:
        """Lock every panel's radiance settings; their states (raises DeviceError on a NAK)."""
        ...

    def drift(self) -> dict[str, list[str]]:
        """Per display, what still lets its panel change its own radiance (empty: locked)."""
        ...


@dataclass(frozen=True)
class CameraInfo:
    name: str
    width: int
    height: int
    model: str = ""
    serial: str = ""
    white_level: float = 1.0
    linear: bool = True


@runtime_checkable
class CameraDevice(Protocol):
    """A camera that returns linear float32 RGB images (H, W, 3)."""

    name: str

    def capture(self, exposure_s: float) -> np.ndarray: ...

    def info(self) -> CameraInfo: ...


@runtime_checkable
class Rig(Protocol):
    """A capture rig: devices plus geometry.

    ``with rig.safe():`` guarantees lights off, backdrops blank and a feed hold on
    the axes on any exit, Ctrl-C included.
    """

    geometry: RigGeometry
    turntable: Turntable
    light_array: LightArray | None
    backdrops: Backdrops | None
    cameras: Sequence[CameraDevice]

    def open(self) -> object: ...

    def close(self) -> None: ...

    def safe(self) -> AbstractContextManager[Any]: ...

    def check(self) -> list[DeviceInfo]: ...

    def describe(self) -> dict[str, Any]:
        """The rig TOML content (geometry and devices) to record in a session."""
        ...

    def operator(self, action: str, **details: Any) -> None:
        """A manual step between phases, asked of the operator on a hardware rig (and
        waited for) or performed by a simulated rig. Actions: ``"place_board"``
        (details: ``charuco`` = :class:`~opacityhull.charuco.CharucoSpec`),
        ``"remove_board"``, ``"remove_object"``, ``"place_object"``."""
        ...


@runtime_checkable
class PhaseAware(Protocol):
    """A rig that renders shots differently by capture phase (the simulated rig: a matting
    shot and an envmatte shot look alike in the rig state, but need different samples).

    The capture runner calls :meth:`note_phase` before the shots of each phase on rigs
    that have it (``isinstance(rig, PhaseAware)``); hardware needs nothing of the kind.
    """

    def note_phase(self, phase: str | None) -> None:
        """Declare the phase of the shots that follow (None: undeclared)."""
        ...


@runtime_checkable
class GroundTruthSource(Protocol):
    """A rig that knows the truth about what it captured (simulated rigs; not hardware).

    A capture calls :meth:`ground_truth` only on rigs that have it (``isinstance(rig,
    GroundTruthSource)``); a hardware :class:`Rig` does not.
    """

    def ground_truth(self, root: Path, views: Sequence[tuple[int, float]]) -> object:
        """Write what the rig knows exactly about the given views (camera index, table
        angle) under ``root / "groundtruth"``: true cameras, coverage alpha, the object
        mesh and light positions."""
        ...


@runtime_checkable
class Port(Protocol):
    """One connection a rig opens and closes: a GRBL controller, a DMX widget, the
    display controller. :class:`~opacityhull.rigs.rig.HardwareRig` opens, closes and
    reconnects its ports through this and nothing else."""

    name: str

    @property
    def url(self) -> str: ...

    @property
    def is_open(self) -> bool: ...

    def open(self) -> object: ...

    def close(self) -> None: ...
