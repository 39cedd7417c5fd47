"""The backdrop patterns of a capture, as the display controller's store holds them.

:class:`PatternSlots` keeps the controller's pattern store as a least-recently-used cache
over a run's patterns. It talks to the backdrops through the device protocols only
(:mod:`opacityhull.rigs.interfaces`), decided by type: a :class:`PatternStore` (the
display controller) is read back, evicted from and sized by its own answers; a
:class:`ImageOutput` (a video output) draws each image as it is shown, with no store; any
other :class:`Backdrops` is uploaded to until it says :class:`StorageFull`, and cannot
make room.
"""

from __future__ import annotations

import contextlib

from collections import OrderedDict
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import ConfigError
from ..rigs.interfaces import ImageOutput, PatternMissing, PatternStore, StorageFull
from .patterns import Pattern

__all__ = ["PatternSlots", "controller_slots", "device_pattern_id", "pattern_slots"]


def device_pattern_id(pattern_id: int, display_index: int) -> int:
    """Controller slot of a session pattern on one display.

    The controller stores patterns globally, not per output, while each display has
    its own image for a session pattern id; so slot = id * 16 + display index."""
    if not 0 <= display_index < 16:
        raise ConfigError(f"at most 16 displays are supported, got display index {display_index}")
    return int(pattern_id) * 16 + int(display_index)


class PatternSlots:
    """The display controller's pattern store, used as a least-recently-used cache.

    A controller stores a fixed number of patterns (``slots=M`` in its IDENTIFY reply: 64
    on the OHDC-2) while a natural-illumination phase shows N images on every display (N =
    200 in the paper), so uploading every pattern up front cannot work. A pattern is
    uploaded when it is first shown; when the store is full, the least recently shown one
    that the current shot does not need is deleted first (patterns the controller held
    before this run, e.g. another session's, go before any of ours). The driver's
    ``upload`` skips a stored pattern whose size and CRC-32 match, so a resume or a
    re-check after a manual step costs one PATTERN_INFO per slot, not a re-upload.

    A controller that does not report its capacity is filled until it answers
    :class:`StorageFull`, then evicted one pattern at a time. Backdrops that are no
    :class:`PatternStore` cannot delete: a full store is then a named error.

    Identical images share one slot: every natural pattern is black on the displays it
    does not light, and each display has its own slot per pattern id (:func:`device_pattern_id`),
    so without sharing a two-display natural phase would upload N black images and
    re-upload them at every table angle once the store cycles. A pattern whose bytes a
    slot checked this run already holds is shown from that slot.
    """

    def __init__(
        self, backdrops, patterns: dict[int, Pattern], displays: Sequence[str], log, capacity: int | None = None
    ):
        self.bd = backdrops
        self.store = backdrops if isinstance(backdrops, PatternStore) else None
        self.patterns = patterns
        self.displays = list(displays)
        self.log = log
        self.capacity = capacity if capacity is not None else controller_slots(backdrops)
        self.stored: OrderedDict[int, None] = OrderedDict()  # on the controller, least recently shown first
        self.verified: set[int] = set()  # content checked (or sent) since the last forget()
        self.by_content: dict[bytes, int] = {}  # image digest -> a verified slot holding it
        self.showing: dict[str, int] = {}  # display -> slot it shows now (never evicted for the next)
        self.uploads = 0
        self.evictions = 0
        self._synced = False

    def forget(self) -> None:
        """After a manual step or a device error the controller may have been power-cycled:
        re-read what it stores and re-check each pattern before showing it again."""
        self.verified.clear()
        self.by_content.clear()
        self.showing.clear()
        self._synced = False

    def _sync(self) -> None:
        # without a readable store, what this run uploaded is all that is known
        ids = [int(x) for x in (self.store.stored() if self.store is not None else list(self.stored))]
        fresh = [x for x in ids if x not in self.stored]
        order = fresh + [x for x in self.stored if x in set(ids)]
        self.stored.clear()
        for x in order:
            self.stored[x] = None
        self._synced = True

    def _evict_one(self, keep: set[int]) -> bool:
        if self.store is None:
            return False
        victim = next((x for x in self.stored if x not in keep), None)
        if victim is None:
            return False
        with contextlib.suppress(PatternMissing):  # already gone is what we wanted
            self.store.delete(victim)
        del self.stored[victim]
        self.verified.discard(victim)
        self.by_content = {k: v for k, v in self.by_content.items() if v != victim}
        self.showing = {k: v for k, v in self.showing.items() if v != victim}
        self.evictions += 1
        return True

    def ensure(self, display: str, slot: int, image: np.ndarray, keep: set[int]) -> None:
        """Make ``slot`` hold ``image`` on the controller, evicting outside ``keep`` if full."""
        if not self._synced:
            self._sync()
        keep = keep | {v for k, v in self.showing.items() if k != display}  # what the other displays show
        if slot in self.verified:
            self.stored.move_to_end(slot)
            return
        if slot not in self.stored and self.capacity is not None:
            while len(self.stored) >= self.capacity:
                if not self._evict_one(keep):
                    raise ConfigError(
                        f"backdrops {getattr(self.bd, 'name', '?')}: the controller stores {self.capacity} "
                        f"patterns and none can be deleted to make room for pattern {slot} (one shot needs "
                        f"{len(keep)}, or the device has no DELETE)"
                    )
        while True:
            try:
                sent = self.bd.upload(display, slot, image)
                break
            except StorageFull:
                if self._evict_one(keep | {slot}):
                    continue
                raise
        if sent is not False:
            self.uploads += 1
        self.stored[slot] = None
        self.stored.move_to_end(slot)
        self.verified.add(slot)
        self.by_content.setdefault(_image_digest(image), slot)

    def show(self, display: str, index: int, pattern_id: int, *, keep: set[int]) -> int:
        """Show session pattern ``pattern_id`` on ``display`` (rig display ``index``);
        returns the slot shown (its own, or one already holding the same image)."""
        image = self.patterns[pattern_id].images[display]
        if isinstance(self.bd, ImageOutput):  # a video output shows images as they are: no store, no slots
            own = device_pattern_id(pattern_id, index)
            self.bd.show_image(display, image, pattern_id=own)
            self.showing[display] = own
            return own
        for attempt in range(2):
            if not self._synced:
                self._sync()
            own = device_pattern_id(pattern_id, index)
            alias = self.by_content.get(_image_digest(image))
            slot = alias if alias is not None and alias in self.verified else own
            self.ensure(display, slot, image, keep)
            try:
                self.bd.show(display, slot)
            except PatternMissing:
                if attempt:
                    raise
                # lost since it was checked (a power cycle between shots): upload it again, once
                self.log(f"backdrops: pattern {slot} vanished from the controller; uploading it again")
                self.forget()
                continue
            self.showing[display] = slot
            return slot
        raise AssertionError("unreachable")  # pragma: no cover


def _image_digest(image: np.ndarray) -> bytes:
    import hashlib

    a = np.ascontiguousarray(image)
    return hashlib.sha256(repr((a.shape, a.dtype.str)).encode() + a.tobytes()).digest()


def controller_slots(backdrops) -> int | None:
    """The pattern capacity a :class:`PatternStore` reports (:meth:`PatternStore.slots`),
    or None: it does not say, or the backdrops have no store."""
    if not isinstance(backdrops, PatternStore):
        return None
    n = backdrops.slots()
    return n if isinstance(n, int) and not isinstance(n, bool) and n > 0 else None


def pattern_slots(backdrops, patterns: dict[int, Pattern], displays: list[str], log: Callable[[str], None]):
    """The run's pattern cache: patterns are uploaded as they are first shown (the
    controller may have been power-cycled since the last run; the driver skips identical
    stored patterns)."""
    if backdrops is None:
        raise ConfigError("the plan shows backdrop patterns but the rig has no backdrops device")
    slots = PatternSlots(backdrops, patterns, displays, log)
    if isinstance(backdrops, ImageOutput):
        log(f"{len(patterns)} pattern(s) on {len(displays)} display(s), drawn as shown (video output)")
        return slots
    log(
        f"{len(patterns)} pattern(s) on {len(displays)} display(s), uploaded as shown "
        f"(controller capacity: {slots.capacity if slots.capacity is not None else 'not reported'} slots)"
    )
    return slots
