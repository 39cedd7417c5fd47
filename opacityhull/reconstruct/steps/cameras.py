"""Build step ``cameras``: the object-frame camera of every view."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np

from ...camera import Camera, read_colmap_text, read_opencv_yaml
from ...errors import FormatError, InputError
from ...model import BUILD_DIR
from ...riggeometry import RigGeometry, view_id
from ...session import Session
from ..buildconfig import BuildConfig
from ..buildstore import _digest, _files_digest, _records_digest, _StepStore, cached
from ..lazyviews import MemoryPlan
from .base import Step

log = logging.getLogger(__name__)


def view_list(session: Session, *, exclude: Sequence[str] = ()) -> list[tuple[int, float]]:
    """The views of the model: (camera, table_deg) of the lightfield phase, else of the
    matting or mask phase; minus ``exclude`` (view ids)."""
    phases = session.phases()
    for ph in ("lightfield", "matting", "mask"):
        if ph in phases:
            views = session.views(ph)
            break
    else:
        raise FormatError(f"{session.root}: no lightfield, matting or mask images: nothing to build from")
    ex = set(exclude)
    unknown = ex - {view_id(c, a) for c, a in views}
    if unknown:
        raise InputError(f"exclude_views: {sorted(unknown)[:5]} are not views of {session.root}")
    out = [(c, a) for c, a in views if view_id(c, a) not in ex]
    if not out:
        raise InputError(f"{session.root}: every view is excluded")
    return out


def _read_yaml_number(path: Path, key: str) -> float | None:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode(key)
        return None if node.empty() else float(node.real())
    finally:
        fs.release()


@dataclass
class _Cameras:
    views: list[Camera]
    #: rig cameras by index, None for a camera that could not be calibrated
    rig: Sequence[Camera | None] | None
    rms_px: dict[int, float]
    source: str
    calibration: Any = None  # the CalibrationResult when calibrated here
    #: the views these cameras belong to (``views`` minus those of uncalibrated cameras)
    kept: list | None = None
    #: camera index → why it was left out (its views dropped)
    dropped_cameras: dict = field(default_factory=dict)


def resolve_cameras(
    session: Session,
    views: Sequence[tuple[int, float]],
    *,
    source: str = "auto",
    progress=None,
    drop_uncalibrated: bool = True,
) -> _Cameras:
    """Object-frame cameras of ``views`` (see the module docstring for the order).

    Returns an object with ``views`` (Camera per kept view, named by view id), ``kept``
    (the kept views: all of ``views`` unless a camera could not be calibrated),
    ``dropped_cameras`` (camera index → reason), ``rig`` (rig cameras or None; None
    entries for uncalibrated cameras), ``rms_px`` (camera index → reprojection RMS),
    ``source`` and ``calibration`` (the CalibrationResult when calibrated here).

    ``drop_uncalibrated``: with a calibration phase, a camera without three usable
    board views is left uncalibrated and its views are dropped (``kept``); False makes
    it an error (:class:`.calibration.CalibrationError`).
    """
    views = list(views)
    vids = [view_id(c, a) for c, a in views]
    if source == "groundtruth":
        gt = session.groundtruth_dir
        if gt is None or not (gt / "cameras" / "images.txt").is_file():
            raise InputError(f"--cameras groundtruth: {session.root} has no groundtruth/cameras (not simulated?)")
        cams = dict(read_colmap_text(gt / "cameras"))
        missing = [v for v in vids if v not in cams]
        if missing:
            raise FormatError(f"{gt / 'cameras'}: no true camera for views {missing[:5]}")
        rig = None
        if (gt / "calibration").is_dir():
            rig = [read_opencv_yaml(gt / "calibration" / f"{s.name}.yaml") for s in session.geometry.cameras]
        return _Cameras([cams[v].with_name(v) for v in vids], rig, {}, "groundtruth (debug)")
    if source == "nominal":
        g = session.geometry
        rig = g.nominal_cameras()
        return _Cameras(
            [RigGeometry.view_camera(rig[c], a, name=view_id(c, a)) for c, a in views],
            rig,
            {},
            "nominal (debug: the rig as designed, not calibrated)",
        )
    # auto
    if "calibration" in session.phases():
        from ..calibration import CalibrationConfig, CalibrationError, calibrate_session, view_cameras

        try:
            result = calibrate_session(
                session, progress=progress, config=CalibrationConfig(skip_unusable_cameras=drop_uncalibrated)
            )
        except CalibrationError as e:
            # never fall back silently to another camera source: say what to do instead
            raise CalibrationError(
                f"{e} — the session's calibration phase could not be used; fix the "
                "calibration captures, or (debugging only) build with --cameras "
                "groundtruth|nominal"
            ) from None
        ok = set(result.camera_indices)
        kept = [(c, a) for c, a in views if c in ok]
        dropped = {}
        for c in sorted({c for c, _ in views} - ok):
            dropped[c] = result.uncalibrated.get(c, "not calibrated")
        if not kept:
            raise CalibrationError(
                f"{session.root}: no camera could be calibrated from the calibration phase ("
                + "; ".join(f"camera {c}: {why}" for c, why in dropped.items())
                + ") — nothing to build. Fix the calibration captures, or (debugging only) build with "
                "--cameras groundtruth|nominal"
            )
        cams = view_cameras(result, kept)
        # only calibrated cameras have an RMS (uncalibrated ones report NaN)
        rms = {
            c: float(result.reproj_rms_px[c])
            for c in result.camera_indices
            if math.isfinite(float(result.reproj_rms_px[c]))
        }
        rig = [rc if i in ok else None for i, rc in enumerate(result.rig_cameras)]
        return _Cameras(list(cams), rig, rms, "calibration phase (calibrated)", result, kept, dropped)
    known = session.calibration_cameras()
    if known:
        missing = sorted({c for c, _ in views} - set(known))
        if missing:
            raise FormatError(f"{session.root / 'calibration'}: no YAML for camera(s) {missing}")
        rms = {}
        for i, spec in enumerate(session.geometry.cameras):
            p = session.root / "calibration" / f"{spec.name}.yaml"
            if p.is_file():
                r = _read_yaml_number(p, "reproj_rms_px")
                if r is not None:
                    if not (math.isfinite(r) and r >= 0):
                        # the silhouettes are dilated by this: an unknown RMS cannot size that
                        raise FormatError(
                            f"{p}: reproj_rms_px is {r}; expected a finite number >= 0 (or no "
                            "such key when the calibration error is unknown)"
                        )
                    rms[i] = r
        rig = [known.get(i) for i in range(len(session.geometry.cameras))]
        return _Cameras(
            [RigGeometry.view_camera(known[c], a, name=view_id(c, a)) for c, a in views],
            rig,
            rms,
            "calibration/ (known rig cameras)",
        )
    per_view = session.view_cameras()
    if per_view:
        missing = [v for v in vids if v not in per_view]
        if missing:
            raise FormatError(f"{session.root / 'cameras'}: no camera for views {missing[:5]}")
        return _Cameras([per_view[v] for v in vids], None, {}, "cameras/ (per-view, imported)")
    raise FormatError(
        f"{session.root}: no cameras — the session has no calibration phase, no calibration/<camera>.yaml and "
        "no cameras/ model. Capture the ChArUco board, add calibration files, or (debugging only) use "
        "--cameras groundtruth|nominal"
    )


def _colour_shot(session: Session, camera: int, table_deg: float) -> tuple[str | None, str | None]:
    """(object shot, object-absent shot) giving the view's colour."""
    lf = session.select(phase="lightfield", camera=camera, table_deg=table_deg, kind=None)
    obj = sorted({r.shot for r in lf if r.object_present})
    bg = sorted({r.shot for r in lf if not r.object_present})
    if obj:
        return obj[0], (bg[0] if bg else None)
    mt = session.select(phase="matting", camera=camera, table_deg=table_deg, kind=None, pattern=None)
    obj = sorted({r.shot for r in mt if r.object_present})
    bg = sorted({r.shot for r in mt if not r.object_present})
    if obj:
        return obj[0], (bg[0] if bg else None)
    return None, None


def _plan_reflectance_level(session: Session):
    """The reflectance phase's DMX level from the plan recorded in the session (None if
    not recorded)."""
    plan = session.meta.get("plan", {})
    ph = plan.get("phases", {}).get("reflectance", {}) if isinstance(plan, dict) else {}
    return ph.get("level") if isinstance(ph, dict) else None


def _camera_names(session: Session) -> dict[int, str]:
    if "rig" not in session.meta:  # an imported session: no rig, no camera names
        return {}
    return {i: c.name for i, c in enumerate(session.geometry.cameras)}


def _rig_volume(geo: RigGeometry | None) -> tuple[np.ndarray, np.ndarray] | None:
    """A generous box above the table (for unbounded LPs): the bottom display's extent."""
    if geo is None:
        return None
    bottom = [d for d in geo.displays if d.rotates_with_table]
    if bottom:
        w, h = bottom[0].size_m
        r = 0.5 * math.hypot(w, h)
    else:
        r = 2.0 * float(np.linalg.norm(geo.target_m)) + 0.5
    top = 2.0 * r
    return np.array([-r, 0.0, -r]), np.array([r, top, r])


def step_cameras(
    session: Session, config: BuildConfig, store: _StepStore, *, progress=None, timings: dict | None = None
):
    """Step 1: (views kept, cameras, key, notes). Inputs: the calibration phase's images,
    ``calibration/``, ``cameras/``, the rig table and the view list. A calibration run
    here leaves its stage seconds in ``timings`` (not in the pickled cameras)."""
    params = {
        "cameras": config.cameras,
        "drop_uncalibrated_cameras": config.drop_uncalibrated_cameras,
        "exclude_views": list(config.exclude_views),
    }
    phases = session.phases()
    inputs = {
        "calibration_images": _digest(
            _records_digest(session, session.select(phase="calibration", kind=None)) if "calibration" in phases else []
        ),
        "calibration_dir": _digest(_files_digest(session.root / "calibration")),
        "cameras_dir": _digest(_files_digest(session.root / "cameras")),
        "groundtruth_cameras": _digest(
            _files_digest(session.root / "groundtruth" / "cameras") if config.cameras == "groundtruth" else []
        ),
        "rig": _digest(session.meta.get("rig")),
        "views": _digest({ph: session.views(ph) for ph in ("lightfield", "matting", "mask") if ph in phases}),
    }

    def resolve():
        views = view_list(session, exclude=config.exclude_views)
        cams = resolve_cameras(
            session, views, source=config.cameras, progress=progress, drop_uncalibrated=config.drop_uncalibrated_cameras
        )
        cal = cams.calibration
        if cal is not None and cal.seconds:
            if timings is not None:
                timings.update(cal.seconds)
            cams = replace(cams, calibration=replace(cal, seconds={}))
        return (views, cams)

    got = cached(
        store,
        "cameras",
        inputs=inputs,
        params=params,
        run=resolve,
        pickle_as=f"{BUILD_DIR}/cameras.pkl",
        expect=lambda v: isinstance(v, tuple) and len(v) == 2 and isinstance(v[1], _Cameras),
    )
    views, cams = got.value
    key = got.key
    notes = []
    if cams.kept is not None and len(cams.kept) < len(views):
        names = _camera_names(session)
        for c, why in cams.dropped_cameras.items():
            n = sum(1 for cc, _ in views if cc == c)
            notes.append(
                f"camera {names.get(c, c)} could not be calibrated ({why}): its {n} view(s) were left out of the model"
            )
        views = cams.kept
    return list(views), cams, key, notes


@dataclass(frozen=True, kw_only=True)
class CameraProduct:
    """The cameras step's product: the views kept (camera, table angle), their ids, the
    cameras, and the step's key."""

    views: list
    vids: list
    cams: _Cameras
    key: str


def run(ctx) -> None:
    with ctx.timer.step("cameras"):
        views, cams, key, notes = step_cameras(
            ctx.session,
            ctx.config,
            ctx.store,
            progress=ctx.progress,
            timings=ctx.timer.detail.setdefault("calibration", {}),
        )
        ctx.notes.extend(notes)
    ctx.cameras = CameraProduct(views=views, vids=[view_id(c, a) for c, a in views], cams=cams, key=key)


def plan_memory(ctx) -> None:
    """The memory budget's plan for this build's views (:class:`..lazyviews.MemoryPlan`)."""
    session, views, cams = ctx.session, ctx.cameras.views, ctx.cameras.cams
    ctx.plan = MemoryPlan.for_build(
        ctx.budget_gb,
        pixels=max(c.width * c.height for c in cams.views),
        images_per_view=len(
            session.select(
                phase="mask" if ("mask" in session.phases() and "matting" not in session.phases()) else "matting",
                camera=views[0][0],
                table_deg=views[0][1],
                kind=None,
            )
        ),
        workers=int(getattr(ctx.executor, "n_workers", 1)),
        views=len(views),
    )


STEP = Step(
    name="cameras",
    run=run,
    inputs=("session", "config", "store"),
    product="cameras",
    params=("cameras", "drop_uncalibrated_cameras", "exclude_views"),
)
MEMORY = Step(name="memory", run=plan_memory, inputs=("cameras", "budget_gb", "executor"), product="plan")
