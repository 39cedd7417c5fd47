"""Per-view tasks for :mod:`opacityhull.executor`: module-level functions that process
one view given only paths, so any worker that sees the session folder can run them.

A task item is a :class:`ViewTask` (session folder, camera index, table angle, optional
output folder). The worker opens the session itself (cached per process: the manifest is
parsed once per worker, not once per view) and sends back either the alpha or, with
``out_dir``, only a small summary after writing ``<out_dir>/<view_id>.exr`` atomically.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..riggeometry import RigGeometry, view_id
from ..session import Session
from .liveviews import LIVE_VIEWS, LiveViews
from .matting import MattingOptions, solve_matte

log = logging.getLogger(__name__)

__all__ = [
    "ViewTask",
    "matte_view",
    "matte_view_result",
    "matte_view_checksum",
    "view_tasks",
    "BuildMatteTask",
    "build_matte",
    "run_build_matte",
    "LiveViews",
    "LIVE_VIEWS",
]


@dataclass(frozen=True, kw_only=True)
class ViewTask:
    """One view of a session to matte.

    session_dir : session folder (a path every worker can read).
    camera, table_deg : the view (c, a).
    out_dir : where to write ``<view_id>.exr`` (alpha, float32); None = return the alpha.
    backdrops : as ``BuildConfig.backdrops`` (auto | object-absent | geometry).
    matting : MattingOptions.
    view_camera : the view's camera as the build resolved it (needed only for backdrops
        predicted from the display geometry); None = from ``calibration/``.
    """

    session_dir: str
    camera: int
    table_deg: float
    out_dir: str | None = None
    backdrops: str = "auto"
    matting: MattingOptions = MattingOptions()
    view_camera: Camera | None = None

    @property
    def view(self) -> str:
        return view_id(self.camera, self.table_deg)


@lru_cache(maxsize=4)
def _session(root: str, mtime_ns: int) -> Session:
    # keyed by the manifest's mtime so a session appended to since is re-read
    return Session.open(root)


def _open(root: str) -> Session:
    p = Path(root) / "manifest.jsonl"
    try:
        m = p.stat().st_mtime_ns
    except OSError:
        m = -1  # Session.open names the problem
    return _session(str(root), m)


def view_tasks(
    session_dir, *, out_dir=None, backdrops: str = "auto", matting: MattingOptions = MattingOptions()
) -> list[ViewTask]:
    """One :class:`ViewTask` per view of the session's matting phase, in view order."""
    s = _open(str(session_dir))
    return [
        ViewTask(
            session_dir=str(session_dir),
            camera=c,
            table_deg=a,
            out_dir=None if out_dir is None else str(out_dir),
            backdrops=backdrops,
            matting=matting,
        )
        for c, a in s.views("matting")
    ]


def _view_camera(s: Session, camera: int, table_deg: float):
    cams = s.calibration_cameras()
    if cams and camera in cams:
        return RigGeometry.view_camera(cams[camera], table_deg, name=view_id(camera, table_deg))
    return None  # only the display-geometry backdrops need it; load_matting_pairs says so


def matte_view_result(task: ViewTask) -> dict:
    """Matte of one view with what ``build`` reports about it: ``alpha`` (H, W) float32,
    ``unknown_frac``, ``saturated_frac``, ``invalid_frac``, ``noise_sigma``, ``K`` and the
    backdrop ``source``."""
    from .matte_step import load_matting_pairs

    s = _open(task.session_dir)
    cam = task.view_camera
    if cam is None and task.backdrops != "object-absent":
        cam = _view_camera(s, task.camera, task.table_deg)
    C, B, cc, bc, src = load_matting_pairs(s, task.camera, task.table_deg, cam, backdrops=task.backdrops)
    res = solve_matte(C, B, c_saturation=cc, b_saturation=bc, options=task.matting)
    return {
        "view": task.view,
        "alpha": res.alpha,
        "unknown_frac": float(res.unknown.mean()),
        "saturated_frac": float(res.saturated.mean()),
        "invalid_frac": float(res.invalid.mean()),
        "noise_sigma": res.noise_sigma,
        "K": int(C.shape[0]),
        "source": src,
    }


def matte_view(task: ViewTask):
    """Triangulation matte of one view (what ``build``'s matting step does per view).

    Returns
    -------
    (H, W) float32 alpha in [0, 1] when ``task.out_dir`` is None, else a dict
    ``{"view", "path", "unknown_frac", "K", "bytes"}`` after writing the alpha EXR.
    """
    r = matte_view_result(task)
    if task.out_dir is None:
        return r["alpha"]
    from ..imageio import write_exr

    path = Path(task.out_dir) / f"{task.view}.exr"
    write_exr(path, r["alpha"])  # atomic: a killed worker leaves no half-written matte
    return {
        "view": task.view,
        "path": str(path),
        "unknown_frac": r["unknown_frac"],
        "K": r["K"],
        "bytes": path.stat().st_size,
    }


def matte_view_checksum(task: ViewTask) -> dict:
    """:func:`matte_view` returning only the view id and a SHA-256 of the alpha bytes
    (benchmarks: what crosses the network is then the work, not the pixels)."""
    import hashlib

    a = np.ascontiguousarray(matte_view(ViewTask(**{**task.__dict__, "out_dir": None})))
    return {"view": task.view, "sha256": hashlib.sha256(a.tobytes()).hexdigest(), "shape": list(a.shape)}


@dataclass(frozen=True, kw_only=True)
class BuildMatteTask:
    """One view of ``build``'s matting step (:func:`.build.step_matting`).

    session_dir : session folder (a path every worker can read).
    camera, table_deg : the view; view_camera : its camera as the build resolved it.
    use_masks : the view's alpha is the imported mask (no matting).
    backdrops, matting : as ``BuildConfig.backdrops`` and the drift-resolved MattingOptions.
    alpha_path : where the alpha goes (``MODEL/build/mattes/<view>.npy``, a path the
        workers can write); key : the step key written beside it.
    """

    session_dir: str
    camera: int
    table_deg: float
    view_camera: Camera
    use_masks: bool
    backdrops: str
    matting: MattingOptions
    alpha_path: str
    key: str


def run_build_matte(session: Session, task: BuildMatteTask) -> dict:
    """Matte ``task``'s view of ``session``, store it (:func:`.matte_step.store_matte`) and
    return its small sidecar dict (source, stats, NaN notes, key, SHA-256) — never the
    pixels."""
    from .matte_step import matte_for_build, store_matte

    alpha, meta = matte_for_build(
        session,
        task.camera,
        task.table_deg,
        task.view_camera,
        use_masks=task.use_masks,
        backdrops=task.backdrops,
        matting=task.matting,
    )
    return store_matte(Path(task.alpha_path), alpha, {**meta, "key": task.key})


def build_matte(task: BuildMatteTask) -> dict:
    """:func:`run_build_matte` in a worker process: the session is opened from its path
    (once per worker process, re-read when its manifest changes)."""
    return run_build_matte(_open(task.session_dir), task)
