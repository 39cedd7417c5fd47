"""The capture runner's image queue (issue #14 item 5): encoding, hashing and fsync run
on one writer thread while the rig takes the next exposure. The manifest must be
exactly what a synchronous capture writes, in capture order; a write error stops the
capture with nothing half-written; Ctrl-C / SIGTERM write everything already exposed."""

from __future__ import annotations

import errno
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest

from opacityhull.acquire import runner
from opacityhull.acquire.runner import DiskFull, _ImageQueue, _Job, run_capture
from opacityhull.acquire.schedule import schedule
from opacityhull.acquire.verify import verify_session
from opacityhull.errors import ConfigError, Terminated
from opacityhull.session import SessionWriter, read_manifest

from rigkit import LabRig, tiny_plan


def _capture_order() -> list[str]:
    return [iid for st in schedule(tiny_plan(), LabRig().geometry) for s in st.shots for iid in s.ids()]


def _records(out: Path) -> list[dict]:
    return [{k: v for k, v in vars(r).items()} for r in read_manifest(out / "manifest.jsonl")]


def _assert_safe(rig):
    rig.settle()  # DMX is not acknowledged: the all-off packet may still be in the pty
    assert not rig.display_emulator.is_lit()
    assert all(v == 0 for v in rig.dmx_levels().values())
    assert not rig.grbl.is_moving


def _no_temporaries(out: Path) -> None:
    assert not [p for p in (out / "images").rglob(".tmp-*")], "a temporary file was left behind"


def _count_captures(rig, at: int | None = None, fn=None) -> dict:
    n = {"k": 0}

    def hook(cam):
        n["k"] += 1
        if at is not None and n["k"] == at and fn is not None:
            fn()

    for c in rig.cameras:
        c.before_capture = hook
    return n


def test_queued_manifest_equals_synchronous_in_capture_order(tmp_path, monkeypatch):
    threads: set[str] = set()
    orig = runner.write_capture_exr

    def spy(*a, **kw):
        threads.add(threading.current_thread().name)
        return orig(*a, **kw)

    monkeypatch.setattr(runner, "write_capture_exr", spy)
    done: list[int] = []
    with LabRig() as rig:
        res_q = run_capture(rig, tiny_plan(), tmp_path / "q", queue_images=4, progress=lambda d, t: done.append(d))
    assert threads == {"opacityhull-capture-writer"}  # encoding ran off the capture thread
    threads.clear()
    with LabRig() as rig:
        res_s = run_capture(rig, tiny_plan(), tmp_path / "s", queue_images=0)
    assert threads == {threading.main_thread().name}

    order = _capture_order()
    q, s = _records(tmp_path / "q"), _records(tmp_path / "s")
    assert [r["id"] for r in q] == order
    assert q == s  # same ids, paths, fields and pixel hashes, in the same order
    assert res_q.complete and res_q.images == res_q.taken == len(order) == res_s.images
    assert res_q.bytes_written == res_s.bytes_written == sum(r["bytes"] for r in q)
    assert done == list(range(len(order) + 1))  # progress on the capture thread, once per image, in order
    assert verify_session(tmp_path / "q")["ok"]


@pytest.mark.parametrize("at, where", [(1, "encode"), (9, "encode"), (9, "list")])
def test_writer_disk_full_mid_stage_is_raised_and_nothing_half_written(tmp_path, monkeypatch, at, where):
    """ENOSPC on the writer thread, while encoding (``encode``) or while listing the
    already-renamed image (``list``: the runner must delete it, leaving nothing unlisted)."""
    calls = {"k": 0}
    failed: list[Path] = []

    def boom(path) -> None:
        calls["k"] += 1
        if calls["k"] == at:
            failed.append(Path(path))
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

    if where == "encode":
        orig = runner.write_capture_exr

        def failing(path, image, **kw):
            boom(path)
            return orig(path, image, **kw)

        monkeypatch.setattr(runner, "write_capture_exr", failing)
    else:
        orig_add = SessionWriter.add_file

        def failing_add(self, path, **kw):
            boom(path)
            return orig_add(self, path, **kw)

        monkeypatch.setattr(SessionWriter, "add_file", failing_add)
    out = tmp_path / "s"
    order = _capture_order()
    with LabRig() as rig:
        n = _count_captures(rig)
        with pytest.raises(
            DiskFull,
            match=rf"disk full writing \S+ \(.*\); {at - 1} of {len(order)} images are in "
            r"the session.*--resume",
        ):
            run_capture(rig, tiny_plan(), out, queue_images=4)
        _assert_safe(rig)
        # raised at the next enqueue: the rig ran at most the queue (plus the one in the writer
        # and the one being exposed) ahead of the failure
        assert at <= n["k"] <= at + 4 + 2
    assert len(failed) == 1 and not failed[0].exists()  # the failing image is not left unlisted
    ids = [r["id"] for r in _records(out)]
    assert ids == order[: at - 1]  # exactly the images before the failing one, in order
    assert verify_session(out)["ok"]
    _no_temporaries(out)
    monkeypatch.undo()
    with LabRig() as rig:
        res = run_capture(rig, tiny_plan(), out, resume=True)
    assert res.complete and res.taken == len(order) - (at - 1)
    assert [r["id"] for r in _records(out)] == order


def test_a_read_only_disk_mid_stage_propagates_and_lists_exactly_the_prefix(tmp_path, monkeypatch):
    orig_add = SessionWriter.add_file
    calls = {"k": 0}
    failed: list[Path] = []

    def read_only(self, path, **kw):
        calls["k"] += 1
        if calls["k"] >= 5:  # the disk was remounted read-only: every later write fails too
            failed.append(Path(path))
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return orig_add(self, path, **kw)

    monkeypatch.setattr(SessionWriter, "add_file", read_only)
    out = tmp_path / "s"
    with LabRig() as rig:
        with pytest.raises(OSError) as ei:
            run_capture(rig, tiny_plan(), out, queue_images=4)
        _assert_safe(rig)
    assert ei.value.errno == errno.EROFS and not isinstance(ei.value, DiskFull)
    assert len(failed) == 1 and not failed[0].exists()  # the writer stopped at the first failure
    assert [r["id"] for r in _records(out)] == _capture_order()[:4]
    assert verify_session(out)["ok"]


def test_a_non_disk_writer_error_propagates_unchanged(tmp_path, monkeypatch):
    def broken(path, image, **kw):
        raise RuntimeError("encoder exploded")

    monkeypatch.setattr(runner, "write_capture_exr", broken)
    out = tmp_path / "s"
    with LabRig() as rig:
        with pytest.raises(RuntimeError, match="encoder exploded"):
            run_capture(rig, tiny_plan(), out, queue_images=3)
        _assert_safe(rig)
    assert _records(out) == []
    assert not (out / ".capture.lock").exists()
    assert verify_session(out)["ok"]


def test_sigterm_writes_everything_already_exposed(tmp_path, monkeypatch):
    """The writer is held on the first image until the drain starts, so when SIGTERM lands
    (before the 4th exposure) three exposed images sit in memory; all three must be listed."""
    gate = threading.Event()
    orig_write, orig_close = runner.write_capture_exr, _ImageQueue.close

    def held(path, image, **kw):
        assert gate.wait(60), "the drain never started"
        return orig_write(path, image, **kw)

    def close(self):
        gate.set()
        orig_close(self)

    monkeypatch.setattr(runner, "write_capture_exr", held)
    monkeypatch.setattr(_ImageQueue, "close", close)
    out = tmp_path / "s"
    order = _capture_order()
    before = signal.getsignal(signal.SIGTERM)
    with LabRig() as rig:
        _count_captures(rig, at=4, fn=lambda: os.kill(os.getpid(), signal.SIGTERM))
        with pytest.raises(Terminated):
            run_capture(rig, tiny_plan(), out, queue_images=4)
        _assert_safe(rig)
    assert signal.getsignal(signal.SIGTERM) == before
    assert [r["id"] for r in _records(out)] == order[:3]
    assert not (out / ".capture.lock").exists()
    assert verify_session(out)["ok"]
    _no_temporaries(out)


def test_image_queue_unit(tmp_path):
    with pytest.raises(ConfigError, match="queue_images must be >= 0, got -1"):
        _ImageQueue(SessionWriter(tmp_path), half=False, compression="rle", maxsize=-1)
    w = SessionWriter(tmp_path / "u", fsync=False).create({"session": {}})
    (tmp_path / "u" / "images").mkdir()
    sink = _ImageQueue(w, half=False, compression="rle", maxsize=2)
    rng = np.random.default_rng(0)
    for k in range(7):
        sink.submit(
            _Job(
                path=tmp_path / "u" / "images" / f"{k}.exr",
                image=rng.random((3, 4, 3), np.float32),
                id=f"i{k}",
                replace=False,
                record=dict(shot=f"i{k}", phase="lightfield", camera=0, table_deg=0.0),
            )
        )
        assert sink._q is not None and sink._q.qsize() <= 2  # bounded
    sink.flush()
    assert [j.id for j, _ in sink.done] == [f"i{k}" for k in range(7)]
    sink.close()
    sink.close()  # idempotent
    w.close()
    assert [r.id for r in read_manifest(tmp_path / "u" / "manifest.jsonl")] == [f"i{k}" for k in range(7)]
