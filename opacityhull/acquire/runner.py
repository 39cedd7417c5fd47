"""The capture runner: executes a plan on a rig into a session folder, resumably.

``run_capture(rig, plan, out_dir)`` depends only on the device protocols
(:mod:`opacityhull.rigs.interfaces`): the rig may be hardware, emulated or simulated.

Guarantees
----------
* Nothing is lost or duplicated: every image is written to a temporary file, fsynced
  and renamed into place, and only then listed in ``manifest.jsonl`` (flushed and
  fsynced) — :class:`~opacityhull.session.SessionWriter`. A crash, Ctrl-C or SIGKILL
  leaves at worst an unlisted image or a temporary file, which a resume overwrites or
  removes.
* ``resume=True`` re-verifies every listed image (sha256), shoots only what is missing
  or corrupt (the new record supersedes the old one: the last record of an id wins),
  and re-issues the manual step of the stage it continues in.
* Free disk space is checked against the byte estimate before anything is written; a
  full disk mid-run (ENOSPC, EDQUOT, EFBIG) stops the capture cleanly with
  :class:`DiskFull` (resumable).
* Everything runs inside ``rig.safe()``: lights off, backdrops blank and the axes held
  on any exit, Ctrl-C included.
* Encoding, hashing and fsync overlap the next exposure: exposed images wait in a
  bounded queue (``queue_images``, default 4) for ONE writer thread that lists them in
  capture order (:class:`_ImageQueue`). A write error is raised at the next image or
  at the end of the stage; on any exit whatever was exposed is written before
  ``rig.safe()`` runs, so the manifest is what a synchronous run would have left.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable, Sequence

import numpy as np

from .. import __version__
from ..cliutil import terminate_as_interrupt
from ..interrupts import signals_off_this_thread
from ..errors import (
    CaptureInterrupted,
    ConfigError,
    DeviceError,
    FormatError,
    InputError,
    OpacityHullError,
    Terminated,
    write_error,
)
from ..rigs.interfaces import DisplayDrift, GroundTruthSource, ImageOutput, LockablePanels, PhaseAware
from ..session import Session, SessionWriter, sha256_file
from ..tomlio import toml_dumps
from .exr import write_capture_exr
from .pattern_cache import PatternSlots, device_pattern_id, pattern_slots
from .patterns import check_saved_patterns, plan_patterns, save_patterns
from .plan import CapturePlan
from .schedule import (
    Estimate,
    MotionRates,
    PlannedShot,
    Stage,
    estimate,
    expected_counts,
    image_bytes,
    lamps_for_plan,
    schedule,
)

__all__ = [
    "CaptureResult",
    "DiskFull",
    "GroundTruthError",
    "run_capture",
    "resume_mismatch",
    "device_pattern_id",
    "views_of",
]

ProgressCallback = Callable[[int, int], None]

_DISK_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
_DISK_FULL_TEXT = ("No space left on device", "Disk quota exceeded", "File too large")


class GroundTruthError(OpacityHullError):
    """The capture is complete but the (simulated) rig could not write its ground truth."""


class DiskFull(CaptureInterrupted):
    """Not enough disk space to start, or the disk filled up during the capture (resumable)."""


@dataclass
class CaptureResult:
    """What a capture run did. ``images`` counts valid images listed in the session."""

    session: Path
    complete: bool
    images: int
    planned: int
    taken: int = 0
    reshot: int = 0
    per_phase: dict = field(default_factory=dict)
    planned_per_phase: dict = field(default_factory=dict)
    seconds: float = 0.0
    phase_seconds: dict = field(default_factory=dict)
    bytes_written: int = 0
    estimate: Estimate | None = None
    dry_run: bool = False
    stopped: str = ""

    def to_dict(self) -> dict:
        d = {
            "complete": self.complete,
            "images": self.images,
            "session": str(self.session),
            "planned": self.planned,
            "taken": self.taken,
            "reshot": self.reshot,
            "per_phase": self.per_phase,
            "planned_per_phase": self.planned_per_phase,
            "seconds": self.seconds,
            "phase_seconds": self.phase_seconds,
            "bytes_written": self.bytes_written,
            "dry_run": self.dry_run,
        }
        if self.estimate is not None:
            d["estimate"] = self.estimate.to_dict()
        if self.stopped:
            d["stopped"] = self.stopped
        return d


def views_of(stages: Sequence[Stage]) -> list[tuple[int, float]]:
    """Distinct (camera, table_deg) views of the object stage, sorted."""
    return sorted({(s.camera, s.table_deg) for st in stages if st.scene == "object" for s in st.shots})


def _caused_by_interrupt(e: BaseException | None) -> KeyboardInterrupt | None:
    """A Ctrl-C (or a SIGTERM/SIGHUP as :class:`Terminated`) that a library wrapped in
    another exception (Dr.Jit turns a KeyboardInterrupt inside ``mi.render`` into a
    RuntimeError whose cause it is): the interrupt, to re-raise, or None."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def _is_disk_full(e: BaseException) -> bool:
    if isinstance(e, OSError) and e.errno in _DISK_FULL_ERRNOS:
        return True
    return any(t in str(e) for t in _DISK_FULL_TEXT)


def _strip_none(v) -> Any:
    if isinstance(v, dict):
        return {str(k): _strip_none(x) for k, x in v.items() if x is not None}
    if isinstance(v, (list, tuple)):
        return [_strip_none(x) for x in v if x is not None]
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def _roundtrip(table: dict) -> dict:
    """A table as it reads back from session.toml (for comparing with a stored one)."""
    return tomllib.loads(toml_dumps({"t": _strip_none(table)})).get("t", {})


def _free_bytes(path: Path) -> int:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return shutil.disk_usage(p).free


def _stale_temporaries(root: Path) -> list[Path]:
    """Temporary files of interrupted atomic writes (``.tmp-*``) under images/ and patterns/."""
    out = []
    for sub in ("images", "patterns"):
        d = root / sub
        if d.is_dir():
            out += [p for p in d.rglob(".tmp-*") if p.is_file()]
    return out


class _SessionLock:
    """An advisory lock (``flock``) on ``<session>/.capture.lock``: two captures must never
    write one session at once. The kernel drops it when the process dies (SIGKILL
    included), so a stale file never blocks a resume."""

    def __init__(self, root: Path):
        self.path = Path(root) / ".capture.lock"
        self._f = None

    def acquire(self) -> None:
        import fcntl

        try:
            f = open(self.path, "a+")  # noqa: SIM115  held (with its flock) until release()
        except OSError as e:  # a read-only or full disk: say so, naming the lock
            err = write_error(e, self.path)
            if err is None:
                raise
            raise err from None
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            who = f.read().strip()
            f.close()
            raise InputError(
                f"--out {self.path.parent}: another capture is writing this session (process {who or '?'},"
                f" lock {self.path}); wait for it to finish or stop it first"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        self._f = f

    def release(self) -> None:
        if self._f is not None:
            try:
                self.path.unlink(missing_ok=True)
            finally:
                self._f.close()
                self._f = None


# --------------------------------------------------------------------------- the rig, driven


def _lock_backdrop_panels(rig, *, allow: bool, log: Callable[[str], None]) -> None:
    """Before the first backdrop shot: lock the panels' radiance settings over their
    control ports (video-output backdrops with MDC panels) and refuse to go on while one
    may still change its own radiance, unless ``allow``."""
    bd = rig.backdrops
    if not isinstance(bd, LockablePanels):
        return
    problems: list[str] = []
    try:
        bd.lock_panels()
    except DeviceError as e:  # a NAKed (locked) setting: what remains is named below
        problems.append(str(e))
    try:
        for display, what in bd.drift().items():
            problems.append(f"display {display}: {', '.join(what)}")
    except DeviceError as e:
        problems.append(str(e))
    if not problems:
        return
    text = "; ".join(problems)
    if allow:
        log(f"backdrop panels may drift (--allow-display-drift): {text}")
        return
    raise DisplayDrift(
        f"matting needs backdrops of constant radiance, but {text} — switch auto-brightness and dynamic contrast "
        "off in the panel's menu (or unlock them for MDC control), or pass --allow-display-drift to capture anyway "
        "(the matting stage then has to correct the drift)"
    )


class _RigDriver:
    """Issues device commands only when the state changes; forgets the state after an error."""

    def __init__(self, rig, log: Callable[[str], None] | None, slots: PatternSlots | None = None):
        self.rig = rig
        self.log = log or (lambda msg: None)
        self.table: float | None = None
        self.array: float | None = None
        self.levels: dict | None = None
        self.shown: dict[str, int | None] = {}
        self.scene: dict[str, bool | None] = {"board": None, "object": None}
        self.slots = slots

    def forget(self):
        self.table = self.array = self.levels = None
        self.shown = {}
        if self.slots is not None:
            self.slots.forget()

    def operator(self, action: str, **details):
        self.log(f"operator: {action}")
        self.rig.operator(action, **details)

    def enter_stage(self, stage: Stage):
        sc = self.scene
        if stage.scene == "board":
            if sc["board"] is not True:
                self.operator("place_board", charuco=stage.charuco)
                sc["board"] = True
        else:
            if sc["board"] is not False:
                self.operator("remove_board")
                sc["board"] = False
            want = stage.scene == "object"
            if sc["object"] is not want:
                self.operator("place_object" if want else "remove_object")
                sc["object"] = want
        # A manual step may have touched anything: re-send every state.
        self.forget()

    def set_state(self, shot: PlannedShot, n_displays: Sequence[str]):
        rig = self.rig
        la = rig.light_array
        if la is not None and shot.lights_deg is not None and self.array != shot.lights_deg:
            if la.rotation is None:
                raise ConfigError(
                    f"the plan asks for the light array at {shot.lights_deg} deg, but this rig's "
                    "light array has no rotation axis (check [light_array] rotation in the rig config)"
                )
            la.rotation.move_to(shot.lights_deg)
            self.array = shot.lights_deg
        if self.table != shot.table_deg:
            rig.turntable.move_to(shot.table_deg)
            self.table = shot.table_deg
        if la is not None:
            want = {lid: shot.level for lid in shot.lights_on} if shot.level else {}
            if self.levels != want:
                if want:
                    la.set_levels(want)
                else:
                    la.all_off()
                self.levels = want
        bd = rig.backdrops
        if bd is not None:
            for i, name in enumerate(n_displays):
                pid = shot.pattern
                want = None if pid is None else device_pattern_id(pid, i)
                if name in self.shown and self.shown[name] == want:
                    continue
                if want is None or pid is None:
                    bd.blank(name)
                    if self.slots is not None:
                        self.slots.showing.pop(name, None)
                elif self.slots is None:
                    bd.show(name, want)
                else:
                    self.slots.show(name, i, pid, keep=self._wanted(shot, n_displays))
                self.shown[name] = want

    @staticmethod
    def _wanted(shot: PlannedShot, n_displays: Sequence[str]) -> set[int]:
        """Slots this shot shows: none of them may be evicted to make room for another."""
        if shot.pattern is None:
            return set()
        return {device_pattern_id(shot.pattern, i) for i in range(len(n_displays))}


# --------------------------------------------------------------------------- the image queue


@dataclass
class _Job:
    """One exposed image waiting to be encoded, hashed and listed."""

    path: Path
    image: np.ndarray
    id: str
    replace: bool
    record: dict


class _ImageQueue:
    """Encodes and lists exposed images while the rig takes the next ones.

    ``maxsize > 0``: ONE writer thread drains a bounded ``queue.Queue`` and does
    :func:`write_capture_exr` then ``writer.add_file`` (sha256, fsync, manifest append)
    for each image, in submission order, so the manifest lists images in capture order
    and a resume sees exactly what a synchronous run would have left. EXR encoding,
    hashing and fsync release the GIL, so they overlap the next motion and exposure.
    Memory is bounded by ``maxsize + 1`` images (queued plus the one being written).
    ``maxsize == 0`` writes inline (the old behaviour, kept for benchmarks).

    The first write error stops the writer (later images are dropped, not written: the
    disk is full or read-only) and is raised in the capture thread at the next
    :meth:`submit` or :meth:`flush`. :meth:`close` writes everything already queued
    (Ctrl-C, SIGTERM, a device error) and stops the thread. Completed writes are handed
    back through :attr:`done` for the capture thread to count, so the counters and the
    progress callback stay on the capture thread.
    """

    def __init__(self, writer: SessionWriter, *, half: bool, compression: str, maxsize: int):
        import collections
        import queue
        import threading

        if maxsize < 0:
            raise ConfigError(f"queue_images must be >= 0, got {maxsize}")
        self.writer = writer
        self.half = half
        self.compression = compression
        self.done: collections.deque = collections.deque()  # (job, record), in write order
        self.error: BaseException | None = None
        self.failed: _Job | None = None
        self._raised = False
        self._q: queue.Queue | None = None
        self._t: threading.Thread | None = None
        if maxsize > 0:
            self._q = queue.Queue(maxsize=maxsize)
            self._t = threading.Thread(target=self._run, name="opacityhull-capture-writer", daemon=True)
            self._t.start()

    @property
    def queued(self) -> bool:
        return self._q is not None

    def _write(self, job: _Job):
        write_capture_exr(job.path, job.image, half=self.half, compression=self.compression)
        try:
            return self.writer.add_file(job.path, id=job.id, replace=job.replace, **job.record)
        except OSError:
            # not listed (add_file cut its half line): leave no unlisted file
            if not job.replace:
                job.path.unlink(missing_ok=True)
            raise

    def _run(self) -> None:
        signals_off_this_thread()  # a C signal handler must not interrupt the EXR encoder's malloc
        q = self._q
        assert q is not None
        while True:
            job = q.get()
            try:
                if job is None:
                    return
                if self.error is None:
                    try:
                        self.done.append((job, self._write(job)))
                    except BaseException as e:  # noqa: BLE001  handed to the capture thread, which re-raises it
                        self.error, self.failed = e, job
            finally:
                job = None  # drop the image before waiting for the next one (bounded memory)
                q.task_done()

    def check(self) -> None:
        """Raise the writer's error (once) in the calling thread."""
        if self.error is not None and not self._raised:
            self._raised = True
            raise self.error

    def submit(self, job: _Job) -> None:
        self.check()
        if self._q is None:
            try:
                self.done.append((job, self._write(job)))
            except BaseException:
                self.failed = job
                raise
            return
        self._q.put(job)  # blocks while maxsize images wait: the capture cannot outrun the disk

    def flush(self) -> None:
        """Wait until everything submitted is written; raise a write error."""
        if self._q is not None:
            self._q.join()
        self.check()

    def close(self) -> None:
        """Write what is queued and stop the writer thread (idempotent)."""
        if self._q is not None and self._t is not None:
            self._q.put(None)
            self._t.join()
            self._t = None


# --------------------------------------------------------------------------- main entry


def run_capture(
    rig,
    plan: CapturePlan,
    out_dir,
    *,
    resume: bool = False,
    dry_run: bool = False,
    progress: ProgressCallback | None = None,
    rig_source: str = "",
    fsync: bool = True,
    log: Callable[[str], None] | None = None,
    queue_images: int = 4,
    allow_display_drift: bool = False,
) -> CaptureResult:
    """Capture ``plan`` on ``rig`` into the session folder ``out_dir``.

    Parameters
    ----------
    rig : :class:`~opacityhull.rigs.interfaces.Rig`
        Already opened by the caller (the runner neither opens nor closes it).
    plan : CapturePlan
    out_dir : path
        Session folder: absent or empty for a new capture; an existing session with
        ``resume=True``. A non-empty folder without ``resume`` is refused untouched.
    resume : bool
        Continue a session: verify what is listed, take what is missing or corrupt.
    dry_run : bool
        Only compute counts, bytes and time (:attr:`CaptureResult.estimate`) from the
        rig's geometry and declared rates; no device is touched, nothing is written.
    progress : callable(done, total), optional
        Called after every image (``done`` counts valid images of the plan).
    rig_source : str
        What ``--rig`` was (a TOML path or ``sim:...``), recorded in the session.
    fsync : bool
        fsync each manifest record (keep True outside benchmarks of the file system).
    log : callable(str), optional
        Receives one-line messages (operator steps, re-shoots).
    queue_images : int
        Exposed images that may wait for encoding and fsync while the rig moves on to
        the next exposure (one writer thread, in capture order; memory is bounded by
        ``queue_images + 1`` images). 0 writes each image before the next exposure.
        Whatever is queued is written before the rig is made safe, however the run ends.
    allow_display_drift : bool
        Start matting even when a backdrop panel may change its own radiance (its
        auto-brightness or dynamic contrast is on and could not be locked); otherwise
        :class:`~opacityhull.rigs.interfaces.DisplayDrift` is raised before the first matting shot.

    Returns
    -------
    CaptureResult

    Raises
    ------
    InputError : ``out_dir`` is not empty and ``resume`` is False.
    ConfigError : the plan does not fit the rig, or differs from the resumed session's.
    DiskFull : too little free space to start, or the disk filled up (resumable).
    DeviceError : a device failed; the rig was left safe and the session is resumable.
    KeyboardInterrupt : propagated after leaving the rig safe (resumable); SIGTERM and
        SIGHUP arrive as its subclass :class:`~opacityhull.errors.Terminated`.
    """
    t_start = time.monotonic()
    log = log or (lambda msg: None)
    fit = getattr(rig, "fit_lamps", None)
    geometry = lamps_for_plan(plan, rig.geometry, can_fit=fit is not None)
    if geometry is not rig.geometry and fit is not None:
        fit(geometry)
        geometry = rig.geometry
    stages = schedule(plan, geometry)
    planned = expected_counts(stages)
    n_planned = sum(planned.values())
    out = Path(out_dir)

    if dry_run:
        desc = rig.describe() if hasattr(rig, "describe") else {}
        est = estimate(plan, geometry, MotionRates.from_devices((desc or {}).get("devices")), stages)
        return CaptureResult(
            session=out,
            complete=False,
            images=0,
            planned=n_planned,
            planned_per_phase=planned,
            estimate=est,
            dry_run=True,
        )

    patterns = plan_patterns(plan, geometry)
    existing = out.exists() and (not out.is_dir() or any(out.iterdir()))
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    if existing and not resume:
        raise InputError(
            f"--out {out}: the folder is not empty; use --resume to continue the session there, "
            "or choose an empty folder"
        )

    done: set[str] = set()
    corrupt: set[str] = set()
    lock = _SessionLock(out)
    with terminate_as_interrupt():
        if existing:
            if not (out / "session.toml").is_file():
                raise InputError(f"--out {out}: not empty and holds no session.toml; nothing to resume there")
            lock.acquire()
            try:
                done, corrupt = _verify_existing(out, plan, geometry, patterns, log, rig_source=rig_source)
            except BaseException:
                lock.release()
                raise

        try:
            return _capture(
                rig,
                plan,
                out,
                stages=stages,
                planned=planned,
                patterns=patterns,
                done=done,
                corrupt=corrupt,
                existing=existing,
                lock=lock,
                progress=progress,
                rig_source=rig_source,
                fsync=fsync,
                log=log,
                t_start=t_start,
                queue_images=queue_images,
                allow_display_drift=allow_display_drift,
            )
        finally:
            lock.release()


def _verify_existing(out: Path, plan, geometry, patterns, log, *, rig_source: str = "") -> tuple[set[str], set[str]]:
    """Ids of the listed images that are intact, and of those missing or corrupt."""
    done: set[str] = set()
    corrupt: set[str] = set()
    sess = Session.open(out)
    _check_resume_matches(sess, plan, geometry, out)
    _check_resume_source(sess, rig_source, out)
    for r in sess.records:
        if r.kind != "raw":
            continue
        p = out / r.path
        if p.is_file() and p.stat().st_size == r.bytes and sha256_file(p) == r.sha256:
            done.add(r.id)
        else:
            corrupt.add(r.id)
    for tmp in _stale_temporaries(out):
        tmp.unlink(missing_ok=True)
    bad = check_saved_patterns(out, patterns)
    if bad:
        log(f"rewriting {len(bad)} pattern file(s) missing or damaged: {bad[:3]}")
        save_patterns(out, patterns)
    if corrupt:
        log(f"{len(corrupt)} listed image(s) missing or corrupt: re-taking them")
    return done, corrupt


def _capture(
    rig,
    plan,
    out: Path,
    *,
    stages,
    planned,
    patterns,
    done,
    corrupt,
    existing,
    lock,
    progress,
    rig_source,
    fsync,
    log,
    t_start,
    queue_images: int = 4,
    allow_display_drift: bool = False,
) -> CaptureResult:
    geometry = rig.geometry
    n_planned = sum(planned.values())

    # what remains, in capture order
    todo: list[tuple[Stage, list[tuple[PlannedShot, list[int]]]]] = []
    need_bytes = 0
    for st in stages:
        pend = []
        for s in st.shots:
            idx = [i for i, iid in enumerate(s.ids()) if iid not in done]
            if idx:
                pend.append((s, idx))
                cam = geometry.cameras[s.camera]
                need_bytes += len(idx) * image_bytes(cam.width, cam.height, half=plan.half_float)
        todo.append((st, pend))
    n_done = sum(1 for st in stages for s in st.shots for iid in s.ids() if iid in done)

    from ..errors import WRITE_ERRNOS, WriteError, _advice, _fs_problem

    why = _fs_problem(out)
    if why is not None and why != WRITE_ERRNOS[28]:
        # a read-only disk has no free space either: say what is really wrong (exit 2)
        raise WriteError(f"--out {out}: cannot write there: {why} — {_advice(why)}; nothing was written")
    free = _free_bytes(out)
    margin = 1 << 20
    if need_bytes + margin > free:
        raise DiskFull(
            f"not enough free disk space for {out}: the capture needs about "
            f"{need_bytes / 1e6:.1f} MB ({n_planned - n_done} images), {free / 1e6:.1f} MB are free — "
            "free some space or choose another --out"
        )

    result = CaptureResult(session=out, complete=False, images=n_done, planned=n_planned, planned_per_phase=planned)
    if progress is not None:
        progress(n_done, n_planned)

    writer = SessionWriter(out, fsync=fsync)
    drv = _RigDriver(rig, log)
    displays = [d.name for d in geometry.displays]
    taken = reshot = 0
    bytes_written = 0
    phase_t: dict[str, float] = {}
    stopped = ""
    run_started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    try:
        with rig.safe():
            cam_info = {i: cam.info() for i, cam in enumerate(rig.cameras)}
            try:
                if not existing:
                    writer.create(_session_meta(rig, cam_info, plan, geometry, stages, patterns, rig_source))
                    lock.acquire()
                    save_patterns(out, patterns)
                else:
                    writer.resume()
            except OSError as e:
                if _is_disk_full(e):
                    raise DiskFull(
                        f"disk full while creating the session in {out} ({e}); free space and run again with --resume"
                    ) from None
                raise
            # The board may still be on the table when resuming a plan with calibration.
            drv.scene["board"] = None if (existing and plan.calibration is not None) else False
            with writer:
                sink = _ImageQueue(writer, half=plan.half_float, compression=plan.exr_compression, maxsize=queue_images)

                def collect(report: bool = True) -> None:
                    """Count the images the writer has listed (capture thread only)."""
                    nonlocal taken, reshot, bytes_written
                    while sink.done:
                        job, rec = sink.done.popleft()
                        if job.replace:
                            reshot += 1
                            corrupt.discard(job.id)
                        taken += 1
                        bytes_written += rec.bytes
                        result.images += 1
                        if report and progress is not None:
                            progress(result.images, n_planned)

                def write_failed(e: BaseException) -> BaseException:
                    collect(report=False)
                    if isinstance(e, (OSError, RuntimeError)) and _is_disk_full(e):
                        where = sink.failed.path if sink.failed is not None else out / "images"
                        return DiskFull(
                            f"disk full writing {where} ({e}); {result.images} of {n_planned} images "
                            "are in the session — free space and run again with --resume"
                        )
                    return e

                drift_checked = False
                try:
                    if any(pend for _, pend in todo) and patterns:
                        drv.slots = pattern_slots(rig.backdrops, patterns, displays, log)
                    for st, pend in todo:
                        if not pend:
                            continue
                        drv.enter_stage(st)
                        phase_aware = isinstance(rig, PhaseAware)
                        for shot, idxs in pend:
                            if not drift_checked and shot.pattern is not None:
                                _lock_backdrop_panels(rig, allow=allow_display_drift, log=log)
                                drift_checked = True
                            t0 = time.monotonic()
                            if phase_aware:  # the simulator spends samples by phase
                                rig.note_phase(shot.phase)
                            drv.set_state(shot, displays)
                            cam = rig.cameras[shot.camera]
                            spec = geometry.cameras[shot.camera]
                            for i in idxs:
                                iid = f"{shot.key}/e{i}"
                                exp = shot.exposures_s[i]
                                try:
                                    raw = cam.capture(exp)
                                except Exception as e:
                                    ki = _caused_by_interrupt(e)
                                    if ki is not None:  # keep its kind: SIGTERM must still exit 143
                                        raise (
                                            Terminated(ki.signum) if isinstance(ki, Terminated) else KeyboardInterrupt()
                                        ) from e
                                    raise
                                img = _check_image(raw, spec, cam)
                                if sink.queued and np.may_share_memory(img, raw):
                                    # a driver may hand out its frame buffer again for the next exposure
                                    img = img.copy()
                                fields = dict(
                                    exposure_s=exp,
                                    lights_deg=shot.lights_deg,
                                    light=shot.light,
                                    pattern=shot.pattern,
                                    object_present=shot.object_present,
                                    extra=_extra(shot),
                                )
                                job = _Job(
                                    path=out / shot.rel_path(i),
                                    image=img,
                                    id=iid,
                                    replace=iid in corrupt,
                                    record=dict(
                                        shot=shot.key,
                                        phase=shot.phase,
                                        camera=shot.camera,
                                        table_deg=shot.table_deg,
                                        **fields,
                                    ),
                                )
                                del img, raw
                                try:
                                    sink.submit(job)
                                except Exception as e:
                                    err = write_failed(e)
                                    if err is e:
                                        raise
                                    raise err from None
                                del job
                                collect()
                            phase_t[shot.phase] = phase_t.get(shot.phase, 0.0) + time.monotonic() - t0
                        # a stage ends with a manual step or the end of the run: all of it on disk first
                        try:
                            sink.flush()
                        except Exception as e:
                            err = write_failed(e)
                            if err is e:
                                raise
                            raise err from None
                        collect()
                finally:
                    # Ctrl-C, SIGTERM or a device error: what was exposed is written before
                    # rig.safe() runs; a write error here is secondary to the one propagating.
                    try:
                        sink.close()
                    finally:
                        collect(report=False)
            if drv.slots is not None and not isinstance(rig.backdrops, ImageOutput):
                log(f"backdrop patterns: {drv.slots.uploads} uploaded, {drv.slots.evictions} deleted to make room")
            result.complete = result.images == n_planned
            if result.complete and isinstance(rig, GroundTruthSource) and (taken or not (out / "groundtruth").is_dir()):
                try:
                    rig.ground_truth(out, views_of(stages))
                except (OpacityHullError, KeyboardInterrupt):
                    raise
                except Exception as e:  # the simulator's failure must not read as a lost capture
                    raise GroundTruthError(
                        f"all {n_planned} images are captured in {out}, but the rig failed to write ground truth "
                        f"({type(e).__name__}: {e}); `capture --resume` retries it"
                    ) from e
    except DeviceError as e:
        stopped = f"device error: {e}"
        raise DeviceError(
            f"{e} — the rig was left safe; {result.images} of {n_planned} images are in {out}; "
            "fix the device and run again with --resume"
        ) from e
    except CaptureInterrupted as e:
        stopped = str(e)
        raise
    except Terminated as e:
        stopped = f"terminated ({e.signame})"
        raise
    except KeyboardInterrupt:
        stopped = "interrupted (Ctrl-C)"
        raise
    finally:
        result.taken, result.reshot, result.bytes_written = taken, reshot, bytes_written
        result.seconds = time.monotonic() - t_start
        result.phase_seconds = phase_t
        result.stopped = stopped
        result.per_phase = _valid_per_phase(stages, done, result, taken)
        if (out / "session.toml").is_file():
            _append_run_log(out, run_started, result)
    return result


def _valid_per_phase(stages, done, result, taken) -> dict:
    # Only meaningful at the end: count from the manifest (cheap, no hashing).
    try:
        sess = Session.open(result.session)
    except (FormatError, InputError, OSError):
        return {}
    out: dict[str, int] = {}
    for r in sess.records:
        if r.kind == "raw":
            out[r.phase] = out.get(r.phase, 0) + 1
    return out


def _append_run_log(out: Path, started: str, result: CaptureResult) -> None:
    rec = {
        "started_utc": started,
        "seconds": round(result.seconds, 3),
        "taken": result.taken,
        "reshot": result.reshot,
        "bytes": result.bytes_written,
        "images": result.images,
        "planned": result.planned,
        "complete": result.complete,
        "phase_seconds": result.phase_seconds,
        "stopped": result.stopped,
        "software_version": __version__,
    }
    try:
        with open(out / "runs.jsonl", "a") as f:
            f.write(json.dumps(rec, sort_keys=True) + "\n")
    except OSError:
        pass  # a full disk must not hide the real reason the run stopped


def _differences(a, b, prefix: str = "", limit: int = 3) -> list[str]:
    """Up to ``limit`` dotted keys where tables ``a`` (stored) and ``b`` (given) differ,
    as "key: stored -> given"."""
    out: list[str] = []
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if len(out) >= limit:
                break
            out += _differences(a.get(k), b.get(k), f"{prefix}{k}.", limit - len(out))
        return out
    if a != b:
        out.append(f"{prefix.rstrip('.')}: {a!r} in the session, {b!r} now")
    return out


def resume_mismatch(session_dir, plan: CapturePlan, geometry) -> str | None:
    """Why a capture in ``session_dir`` cannot be resumed with ``plan`` on a rig of
    ``geometry`` (a message naming the differing keys), or None when it can (or when
    there is no session yet)."""
    out = Path(session_dir)
    if not (out / "session.toml").is_file():
        return None
    return _mismatch(Session.open(out), plan, geometry, out)


def _mismatch(sess: Session, plan: CapturePlan, geometry, out: Path) -> str | None:
    stored_plan = sess.plan
    given = _roundtrip(plan.to_dict())
    if stored_plan and given != stored_plan:
        diff = "; ".join(_differences(stored_plan, given))
        return (
            f"--plan {plan.source or plan.name}: differs from the plan of the session in {out} "
            f"({sess.meta.get('session', {}).get('plan_source', '?')}): {diff}; resume with the same plan"
        )
    stored_rig = sess.meta.get("rig", {})
    given_rig = _roundtrip(geometry.to_dict())
    if given_rig != stored_rig:
        diff = "; ".join(_differences(stored_rig, given_rig))
        return (
            f"--rig: its geometry differs from the rig recorded in {out / 'session.toml'}: {diff}; "
            "resume on the same rig"
        )
    return None


def _check_resume_source(sess: Session, rig_source: str, out: Path) -> None:
    """A simulated session resumed with another scene (``sim:builtin:glass`` on a
    ``sim:builtin:diffuse`` session) would mix two objects in one session; the geometry
    check cannot see it, the scene is only in ``rig_source``. A hardware rig TOML may
    move between runs (``rig emulate`` writes a new runtime file each time), so for
    those the geometry and plan checks are what holds."""
    old = sess.source
    if not old or not rig_source or old == rig_source:
        return
    if old.startswith("sim:") or rig_source.startswith("sim:"):
        raise ConfigError(
            f"--rig {rig_source}: {out / 'session.toml'} was captured with rig_source = {old!r}; "
            "resume it with the same --rig, or capture into a new folder"
        )


def _check_resume_matches(sess: Session, plan: CapturePlan, geometry, out: Path) -> None:
    why = _mismatch(sess, plan, geometry, out)
    if why:
        raise ConfigError(why)


def _session_meta(rig, cam_info, plan, geometry, stages, patterns, rig_source) -> dict:
    desc = {}
    try:
        desc = rig.describe() or {}
    except Exception:  # noqa: BLE001  a driver's describe() is best effort; the geometry is what matters
        desc = {}
    cams = []
    for i, info in sorted(cam_info.items()):
        cams.append(
            {
                "index": i,
                "name": info.name,
                "width": info.width,
                "height": info.height,
                "model": info.model,
                "serial": info.serial,
                "white_level": float(info.white_level),
                "linear": bool(info.linear),
            }
        )
    used = {s.camera for st in stages for s in st.shots}
    white = min((c["white_level"] for c in cams if c["index"] in used), default=1.0)
    meta = {
        "session": {
            "rig_source": rig_source,
            "plan_source": plan.source,
            "plan_name": plan.name,
            "seed": plan.seed,
            "white_level": white,
            "software_version": __version__,
        },
        "rig": geometry.to_dict(),
        "devices": _strip_none(desc.get("devices", {})),
        "plan": plan.to_dict(),
        "camera_info": cams,
        "patterns": {},
    }
    if desc.get("rig"):
        meta["rig_info"] = _strip_none(desc["rig"])
    if plan.calibration is not None:
        meta["charuco"] = plan.calibration.charuco.to_dict()
    # pattern table without writing (the files follow right after the session exists)
    from .patterns import pattern_entry

    for pid, p in sorted(patterns.items()):
        device_ids = {d: device_pattern_id(pid, i) for i, d in enumerate(p.images)}
        meta["patterns"][f"p{pid:03d}"] = pattern_entry(pid, p, device_ids=device_ids)
    return _strip_none(meta)


def _check_image(img, spec, cam) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.shape[:2] != (spec.height, spec.width):
        raise DeviceError(
            f"camera {getattr(cam, 'name', spec.name)} returned an image of shape {a.shape}, expected "
            f"({spec.height}, {spec.width}, 3) as in the rig geometry"
        )
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float32)
    return a


def _extra(shot: PlannedShot) -> dict:
    e = {}
    if shot.lights_on and shot.light is None:
        e["level"] = shot.level
        e["lights_on"] = list(shot.lights_on)
    elif shot.light is not None:
        e["level"] = shot.level
    return e
