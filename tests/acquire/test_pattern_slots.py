"""Lazy pattern upload through the real display driver and emulator: a natural phase with
more patterns than the controller's slots (N = 70 on 2 displays = 140 slots against 64).

Ground truth is the emulator itself: at every shutter, the pattern the emulator shows on
each output must be byte for byte the session's pattern image that the manifest records
for that image, the store must never hold more than its capacity, identical images
(the black of the display a natural image does not light) are uploaded once, and a
capture cut in the middle must resume on a power-cycled controller (fresh emulator) to
the same images.
"""

from __future__ import annotations

import numpy as np
import pytest
import rigkit

from opacityhull.acquire.patterns import plan_patterns
from opacityhull.acquire.plan import parse_plan
from opacityhull.acquire.pattern_cache import PatternSlots, controller_slots, device_pattern_id
from opacityhull.acquire.runner import run_capture
from opacityhull.errors import ConfigError
from opacityhull.rigs import display_protocol as dp
from opacityhull.rigs.interfaces import Backdrops, ImageOutput, PatternStore, StorageFull
from opacityhull.session import Session


def natural_plan(n: int, *, steps: int = 1):
    return parse_plan(
        {
            "plan": {"name": "lab-natural", "seed": 3, "cameras": [0]},
            "table": {"steps": steps},
            "exposures": {"default_s": [0.5]},
            "phases": {"natural": {"images": n, "kernels": 4, "sources": ["noise", "probes"], "displays": ["back"]}},
        },
        where="lab-natural",
    )


class Watch:
    """Records, at every shutter, what the emulator shows on each output."""

    def __init__(self, rig, stop_after: int | None = None):
        self.rig = rig
        self.seen: list[dict[str, tuple[int | None, bytes | None]]] = []
        self.max_stored = 0
        self.stop_after = stop_after

    def __call__(self, cam):
        emu = self.rig.display_emulator
        if self.stop_after is not None and len(self.seen) >= self.stop_after:
            raise KeyboardInterrupt
        shot = {}
        for name, out in (("bottom", 0), ("back", 1)):
            sid = emu.shown(out) if emu.powered(out) else None
            pat = emu.pattern(sid) if sid is not None else None
            shot[name] = (sid, None if pat is None else bytes(np.asarray(pat, np.uint8).tobytes()))
        self.seen.append(shot)
        self.max_stored = max(self.max_stored, len(emu.stored_ids()))


def _expected_bytes(img) -> bytes:
    return dp.pattern_bytes(img)[2]


def _check_shown(watch: Watch, sess: Session, patterns, start: int = 0) -> None:
    recs = [r for r in sess.records if r.kind == "raw"][start : start + len(watch.seen)]
    assert len(recs) == len(watch.seen)
    for rec, shot in zip(recs, watch.seen, strict=True):
        for i, name in enumerate(("bottom", "back")):
            sid, got = shot[name]
            img = patterns[rec.pattern].images[name]
            assert sid is not None and got is not None and got == _expected_bytes(img), (rec.id, name)
            if img.any():  # every natural image differs: shown from its own slot
                assert sid == device_pattern_id(rec.pattern, i), (rec.id, name)


def test_natural_phase_beyond_the_controller_slots(tmp_path):
    plan = natural_plan(70)
    with rigkit.LabRig() as rig:
        slots = rig.display_emulator.slots
        patterns = plan_patterns(plan, rig.geometry)
        assert len(patterns) * 2 > slots  # the point of the test: it cannot all be uploaded up front
        watch = Watch(rig)
        rig.cameras[0].before_capture = watch
        logs: list[str] = []
        res = run_capture(rig, plan, tmp_path / "s", rig_source="lab", log=logs.append)
        history = [name for name, _ in rig.display_emulator.history]
    assert res.complete and res.images == 70
    assert 0 < watch.max_stored <= slots
    sess = Session.open(tmp_path / "s")
    _check_shown(watch, sess, patterns)
    assert sorted({r.pattern for r in sess.records}) == sorted(patterns)
    # one upload per distinct image shown (70 on the back display, one black for the
    # bottom one: 71 of the 140 slots) and deletes only to make room
    assert history.count("UPLOAD_END") == 71
    assert history.count("DELETE") == 71 - slots
    assert any("71 uploaded, 7 deleted" in m for m in logs), logs


def test_cut_capture_resumes_on_a_power_cycled_controller(tmp_path):
    plan = natural_plan(40, steps=2)  # 80 images; 40 x 2 displays = 80 slots > 64
    out = tmp_path / "s"
    with rigkit.LabRig() as rig:
        patterns = plan_patterns(plan, rig.geometry)
        watch = Watch(rig, stop_after=50)
        rig.cameras[0].before_capture = watch
        with pytest.raises(KeyboardInterrupt):
            run_capture(rig, plan, out, rig_source="lab")
    first = Session.open(out)
    n_first = len([r for r in first.records if r.kind == "raw"])
    assert n_first == 50
    _check_shown(watch, first, patterns)
    with rigkit.LabRig() as rig:  # fresh emulator: an empty store, as after a power cycle
        watch2 = Watch(rig)
        rig.cameras[0].before_capture = watch2
        res = run_capture(rig, plan, out, resume=True, rig_source="lab")
        ends = [n for n, _ in rig.display_emulator.history].count("UPLOAD_END")
    assert res.complete and res.images == 80 and res.taken == 30
    assert len(watch2.seen) == 30 and ends == 31  # only the remaining shots' images (and one black)
    sess = Session.open(out)
    _check_shown(watch2, sess, patterns, start=50)


class PlainBackdrops:
    """Backdrops with a pattern store it does not declare (no :class:`PatternStore`): it
    can be uploaded to and shown from, and says :class:`StorageFull` when full."""

    name = "fake"

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.store: dict[int, bytes] = {}
        self.log: list[tuple[str, int]] = []

    @property
    def displays(self):
        return ["a", "b"]

    def upload(self, display, pattern_id, image):
        from opacityhull.rigs.backdrops import DisplayStorageFull

        if pattern_id not in self.store and len(self.store) >= self.capacity:
            raise DisplayStorageFull("storage full", dp.NAK_STORAGE_FULL)
        self.store[pattern_id] = np.asarray(image).tobytes()
        self.log.append(("upload", pattern_id))

    def show(self, display, pattern_id):
        assert pattern_id in self.store
        self.log.append(("show", pattern_id))

    def blank(self, display=None):
        pass

    def shown(self):
        return {}

    last_error = None

    def check(self):
        raise NotImplementedError


class FakeBackdrops(PlainBackdrops):
    """A :class:`PatternStore` that does not report its capacity: only STORAGE_FULL says it is full."""

    def stored(self):
        return list(self.store)

    def delete(self, pattern_id=None):
        del self.store[pattern_id]
        self.log.append(("delete", pattern_id))

    def slots(self):
        return None

    def identity(self):
        return "fake;fw=0"


class _P:
    def __init__(self, k):
        self.images = {"a": np.full((2, 2, 3), k, np.uint8), "b": np.zeros((2, 2, 3), np.uint8)}


def test_lru_without_reported_capacity_evicts_least_recently_shown():
    bd = FakeBackdrops(3)
    slots = PatternSlots(bd, {k: _P(k) for k in range(1, 6)}, ["a", "b"], lambda m: None)
    assert slots.capacity is None
    order = [1, 2, 3, 1, 4, 2, 5]
    for pid in order:
        slots.show("a", 0, pid, keep={device_pattern_id(pid, 0)})
    s = device_pattern_id
    # 1,2,3 fill it; 1 is re-shown (no upload); 4 evicts 2 (least recent); 2 evicts 3; 5 evicts 1
    assert [x for x in bd.log if x[0] != "show"] == [
        ("upload", s(1, 0)),
        ("upload", s(2, 0)),
        ("upload", s(3, 0)),
        ("delete", s(2, 0)),
        ("upload", s(4, 0)),
        ("delete", s(3, 0)),
        ("upload", s(2, 0)),
        ("delete", s(1, 0)),
        ("upload", s(5, 0)),
    ]
    assert sorted(bd.store) == sorted([s(4, 0), s(2, 0), s(5, 0)])
    assert slots.uploads == 6 and slots.evictions == 3


def test_full_store_that_cannot_delete_is_a_named_error():
    bd = PlainBackdrops(1)
    slots = PatternSlots(bd, {k: _P(k) for k in range(1, 3)}, ["a", "b"], lambda m: None, capacity=1)
    slots.show("a", 0, 1, keep=set())
    with pytest.raises(ConfigError, match="stores 1 patterns"):
        slots.show("a", 0, 2, keep=set())


def test_a_backdrop_without_a_pattern_store_is_known_by_its_type():
    """The cache asks the protocol, not the attributes: backdrops that are no
    :class:`PatternStore` are never read back, sized or deleted from, whatever attributes
    they carry (an emulator's ``slots`` count, a ``delete`` that is not the store's), and a
    full store surfaces as the typed :class:`StorageFull`."""
    bd = PlainBackdrops(1)
    bd.slots = 1  # an int, as the emulator has: not the protocol's slots()
    bd.delete = lambda pattern_id=None: pytest.fail("a backdrop without a store is not deleted from")
    assert isinstance(bd, Backdrops) and not isinstance(bd, PatternStore) and not isinstance(bd, ImageOutput)
    assert controller_slots(bd) is None
    slots = PatternSlots(bd, {k: _P(k) for k in range(1, 3)}, ["a", "b"], lambda m: None)
    assert slots.store is None and slots.capacity is None
    slots.show("a", 0, 1, keep=set())
    with pytest.raises(StorageFull):
        slots.show("a", 0, 2, keep=set())
    assert [x[0] for x in bd.log] == ["upload", "show"]
    full = FakeBackdrops(1)
    assert isinstance(full, PatternStore) and controller_slots(full) is None


def test_capacity_is_read_from_identify():
    assert dp.parse_identity_slots("OHDC-2;fw=1.3.0;outputs=2;slots=17;max=512x512") == 17
    assert dp.parse_identity_slots("OHDC-2;fw=1.3.0") is None
    assert dp.parse_identity_slots("OHDC-2;slots=0") is None
    with rigkit.LabRig() as rig:
        bd = rig.backdrops
        assert isinstance(bd, PatternStore) and not isinstance(bd, ImageOutput)
        assert controller_slots(bd) == rig.display_emulator.slots == bd.slots()


def test_identical_images_share_a_slot_and_a_shown_slot_is_never_evicted():
    bd = FakeBackdrops(2)
    slots = PatternSlots(bd, {k: _P(k) for k in range(1, 4)}, ["a", "b"], lambda m: None, capacity=2)
    s = device_pattern_id
    shown_b = [slots.show("b", 1, pid, keep={s(pid, 0), s(pid, 1)}) for pid in (1, 2, 3)]
    assert shown_b == [s(1, 1)] * 3  # every "b" image is the same black: one slot, one upload
    assert [x for x in bd.log if x[0] == "upload"] == [("upload", s(1, 1))]
    # the store holds 2: "a" patterns cycle through the other slot; the black one stays,
    # because display "b" shows it
    for pid in (1, 2, 3):
        slots.show("a", 0, pid, keep={s(pid, 0)})
    assert s(1, 1) in bd.store and len(bd.store) == 2
    assert [x for x in bd.log if x[0] == "delete"] == [("delete", s(1, 0)), ("delete", s(2, 0))]
