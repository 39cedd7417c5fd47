"""The calibration runner: observations → rig model (:func:`calibrate_observations`), and
a session's calibration phase → observations → rig model (:func:`calibrate_session`).

Steps, each in its own module: detection and screening (:mod:`.detect`), intrinsics per
camera (:mod:`.intrinsics`), turntable axis and rig frame per camera (:mod:`.axis`), one
board placement for all cameras (:mod:`.board`), joint refinement (:mod:`.refine`).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING
from collections.abc import Mapping, Sequence

import numpy as np

from ...camera import Camera, rig_from_object
from ...charuco import BoardDetection, CharucoSpec, detect_board, single_threaded_solvers
from ...errors import FormatError, InputError
from ...riggeometry import RigGeometry, view_id
from ...se3 import invert_rigid, mean_pose, rigid, rodrigues
from .axis import estimate_turntable_axis, rig_from_axis
from .board import board_params, board_pose
from .config import CalibrationConfig, CalibrationError, ProgressCallback
from .detect import CharucoObservation, detection_gray, observation_from, screen_observation
from .intrinsics import fit_intrinsics
from .refine import CamBlock, RigModel, refine_nlopt
from .reinterpolate import reinterpolate_views
from .result import CalibrationResult, reprojection_rms_px

if TYPE_CHECKING:
    from ...session import Session, ShotRecord

__all__ = ["calibrate_observations", "calibrate_session"]


def _still_calibrated(cams: list[int], uncalibrated: Mapping[int, str]) -> list[int]:
    """``cams`` without the cameras given up on; CalibrationError naming why when none is left."""
    left = [c for c in cams if c not in uncalibrated]
    if not left:
        raise CalibrationError(
            "no camera has three usable calibration views: " + " | ".join(uncalibrated[c] for c in sorted(uncalibrated))
        )
    return left


def calibrate_observations(
    observations: Sequence[CharucoObservation],
    *,
    image_sizes: Mapping[int, tuple[int, int]] | Sequence[tuple[int, int]],
    charuco: CharucoSpec,
    nominal: Sequence[Camera] | None = None,
    config: CalibrationConfig = CalibrationConfig(),
    dropped: Mapping[str, str] | None = None,
) -> CalibrationResult:
    """Calibrate the rig from ChArUco detections, bit-reproducibly (OpenCV and BLAS at one
    thread: :func:`opacityhull.charuco.single_threaded_solvers`); see
    :func:`_calibrate_observations` for the parameters."""
    with single_threaded_solvers():
        return _calibrate_observations(
            observations, image_sizes=image_sizes, charuco=charuco, nominal=nominal, config=config, dropped=dropped
        )


def _calibrate_observations(
    observations: Sequence[CharucoObservation],
    *,
    image_sizes: Mapping[int, tuple[int, int]] | Sequence[tuple[int, int]],
    charuco: CharucoSpec,
    nominal: Sequence[Camera] | None = None,
    config: CalibrationConfig = CalibrationConfig(),
    dropped: Mapping[str, str] | None = None,
) -> CalibrationResult:
    """Calibrate the rig (intrinsics, distortion, rig poses, board placement) from
    ChArUco detections.

    Parameters
    ----------
    observations : sequence of CharucoObservation
        Detections, one per view (camera, table angle); at most one per view.
    image_sizes : mapping or sequence camera index → (width, height)
        Every camera listed here must be calibrated.
    charuco : CharucoSpec
        The board and its nominal placement (fixes the gauge about the table axis).
    nominal : sequence of Camera, optional
        Nominal rig cameras (initial ``K``; names). Default: principal point at the
        image centre, focal length from OpenCV's homography initialisation.
    config : CalibrationConfig
    dropped : mapping view id → reason, optional
        Views already dropped upstream (e.g. unreadable images); copied into the result.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        A camera has fewer than three usable views, or its views do not span two
        distinct table angles.
    """
    t_start = time.perf_counter()
    sizes = dict(image_sizes) if isinstance(image_sizes, Mapping) else dict(enumerate(image_sizes))
    if not sizes:
        raise InputError("calibrate_observations: image_sizes is empty (no cameras to calibrate)")
    cams = sorted(int(c) for c in sizes)
    if nominal is not None and len(nominal) < max(cams) + 1:
        raise InputError(f"nominal has {len(nominal)} cameras, image_sizes names camera {max(cams)}")
    names = {c: (nominal[c].name if nominal is not None and nominal[c].name else f"cam{c}") for c in cams}
    dropped_views: dict[str, str] = dict(dropped or {})
    notes: list[str] = []
    by_cam: dict[int, list[CharucoObservation]] = {c: [] for c in cams}
    seen: set[str] = set()
    for obs in observations:
        if obs.view in seen:
            raise InputError(f"two observations of view {obs.view}; expected one per (camera, table angle)")
        seen.add(obs.view)
        if obs.camera not in by_cam:
            raise InputError(f"observation {obs.view}: camera {obs.camera} is not in image_sizes (cameras {cams})")
        reason = screen_observation(obs, charuco=charuco, config=config)
        if reason is None:
            w, h = sizes[obs.camera]
            ip = obs.image_points
            if np.any(ip < -0.5) or np.any(ip[:, 0] > w - 0.5) or np.any(ip[:, 1] > h - 0.5):
                reason = f"corners outside the {w}x{h} image"
        if reason is None:
            by_cam[obs.camera].append(obs)
        else:
            dropped_views[obs.view] = reason

    def _too_few(c, usable):
        mine = {v: r for v, r in dropped_views.items() if v.startswith(f"c{c}_t")}
        why = "; ".join(f"{v}: {r}" for v, r in sorted(mine.items())) or "no calibration views captured"
        return CalibrationError(
            f"camera {c} ({names[c]}): only {usable} usable calibration view(s), need at least 3 "
            f"({len(mine)} dropped — {why})"
        )

    uncalibrated: dict[int, str] = {}

    def _unusable(c, usable):
        err = _too_few(c, usable)
        if not config.skip_unusable_cameras:
            raise err
        uncalibrated[c] = str(err)
        notes.append(f"{names[c]}: not calibrated (skip_unusable_cameras): {err}")

    for c in list(cams):
        if len(by_cam[c]) < 3:
            _unusable(c, len(by_cam[c]))
    cams = _still_calibrated(cams, uncalibrated)

    # ---- step 2: intrinsics per camera
    K_init: dict[int, np.ndarray] = {}
    dist_init: dict[int, np.ndarray] = {}
    poses: dict[int, list[tuple[CharucoObservation, np.ndarray]]] = {}
    fixed: dict[int, tuple[str, ...]] = {}
    for c in cams:
        fitted = fit_intrinsics(
            by_cam[c], size=sizes[c], K0=None if nominal is None else nominal[c].K, config=config, name=names[c]
        )
        dropped_views.update(fitted.dropped)
        notes.extend(fitted.notes)
        if fitted.K is None or fitted.dist is None:
            _unusable(c, fitted.n_views)
            continue
        fixed[c] = fitted.fixed
        K_init[c] = fitted.K
        dist_init[c] = fitted.dist
        poses[c] = fitted.poses
    cams = _still_calibrated(cams, uncalibrated)
    t_intr = time.perf_counter()

    # ---- step 3: axis and rig frame per camera, then one board placement for all
    axis_dirs = np.full((max(cams) + 1, 3), np.nan)
    board_est = []
    for c in cams:
        angles = [o.table_deg for o, _ in poses[c]]
        Ts = [T for _, T in poses[c]]
        try:
            d, o, B0 = estimate_turntable_axis(angles, Ts)
        except CalibrationError as e:
            raise CalibrationError(f"camera {c} ({names[c]}): {e}") from None
        axis_dirs[c] = d
        cam_from_rig = rig_from_axis(d, o, B0, charuco)
        board_est.append((invert_rigid(cam_from_rig) @ B0, len(Ts)))
    obj_from_board = mean_pose([T for T, _ in board_est], [n for _, n in board_est])
    bparams = board_params(charuco, obj_from_board)
    if not config.fit_board_tilt:
        bparams[:2] = 0.0
    obj_from_board = board_pose(charuco, *bparams)
    board_from_object = invert_rigid(obj_from_board)
    blocks = []
    for c in cams:
        # cam_from_rig consistent with the common board: mean over views of
        # cam_from_board(c, a) · board_from_object · object_from_rig(a)
        cands = [T @ board_from_object @ invert_rigid(rig_from_object(o.table_deg)) for o, T in poses[c]]
        cam_from_rig = mean_pose(cands)
        views = [o for o, _ in poses[c]]
        free = []
        if "fx/fy" in fixed[c]:
            free.append("f")
        else:
            free += ["fx", "fy"]
        if "cx" not in fixed[c]:
            free += ["cx", "cy"]
        free += [nm for nm in ("k1", "k2", "p1", "p2", "k3") if nm not in fixed[c]]
        K = K_init[c]
        blocks.append(
            CamBlock(
                index=c,
                size=sizes[c],
                K=K.copy(),
                dist=dist_init[c].copy(),
                cam_from_rig=cam_from_rig,
                free=tuple(free),
                aspect=float(K[0, 0] / K[1, 1]),
                obj=np.concatenate([o.object_points for o in views]),
                img=np.concatenate([o.image_points for o in views]),
                angle=np.concatenate([np.full(len(o), o.table_deg) for o in views]),
                view_of_point=np.concatenate([np.full(len(o), i) for i, o in enumerate(views)]),
                views=[o.view for o in views],
            )
        )
    model = RigModel(blocks, charuco, bparams, fit_tilt=config.fit_board_tilt, fit_scale=config.fit_table_scale)
    x0 = model.pack()
    t_axis = time.perf_counter()

    def rms_per_cam(x):
        return [reprojection_rms_px(r) for r in model.residuals(x)]

    initial_rms = rms_per_cam(x0)
    # ---- step 4: joint refinement
    x = x0
    info: dict = {}
    if config.refine:
        x, info = refine_nlopt(model, x0, max_iter=config.max_iter, restarts=config.restarts)
    t_refine = time.perf_counter()

    res = model.residuals(x)
    n_cams = len(nominal) if nominal is not None else max(cams) + 1
    rig_cams: list[Camera | None] = [None] * n_cams
    rms_final, rms_init = [float("nan")] * n_cams, [float("nan")] * n_cams
    per_view: dict[str, float] = {}
    rows, row_views = [], []
    for b, r, r_end, r_start in zip(blocks, res, rms_per_cam(x), initial_rms, strict=True):
        K, dist, rv, tv = model.camera_params(b, x)
        cam_from_rig = rigid(rodrigues(rv), tv)
        rig_cams[b.index] = Camera(
            K=K,
            dist=dist,
            width=b.size[0],
            height=b.size[1],
            world_from_cam=invert_rigid(cam_from_rig),
            name=names[b.index],
        )
        rms_final[b.index], rms_init[b.index] = r_end, r_start
        for i, v in enumerate(b.views):
            per_view[v] = reprojection_rms_px(r[b.view_of_point == i])
        rows.append(r)
        row_views.append(np.array(b.views, dtype=object)[b.view_of_point])
    missing = [c for c in range(n_cams) if rig_cams[c] is None]
    if missing:
        if nominal is None:
            raise InputError(
                f"calibrate_observations: cameras {missing} were not calibrated (not in image_sizes, "
                "or skipped); give `nominal` (the whole rig) to keep them as designed"
            )
        for c in missing:  # cameras not calibrated: kept nominal, marked, never used for views
            rig_cams[c] = nominal[c]
            uncalibrated.setdefault(c, "no images in the session: left nominal")
    return CalibrationResult(
        rig_cameras=[cam for cam in rig_cams if cam is not None],  # every slot is filled by now
        reproj_rms_px=rms_final,
        per_view_rms_px=per_view,
        object_from_board=model.object_from_board(x),
        axis_dir_prealign=axis_dirs,
        used_views=tuple(v for b in blocks for v in b.views),
        dropped_views=dropped_views,
        residuals_px=np.concatenate(rows),
        residual_views=np.concatenate(row_views).astype(str),
        table_scale=model.scale(x),
        fixed_intrinsics=fixed,
        initial_rms_px=rms_init,
        seconds={"intrinsics": t_intr - t_start, "axis": t_axis - t_intr, "refine": t_refine - t_axis},
        refine_info=dict(info),
        notes=tuple(notes),
        charuco=charuco,
        camera_indices=tuple(cams),
        uncalibrated=dict(sorted(uncalibrated.items())),
    )


def calibrate_session(
    session: Session, *, config: CalibrationConfig = CalibrationConfig(), progress: ProgressCallback | None = None
) -> CalibrationResult:
    """Calibrate the rig from the ``calibration`` phase of a session.

    Parameters
    ----------
    session : opacityhull.session.Session
        Its calibration records (one shot per (camera, table angle), board on the table,
        linear EXR, HDR merges preferred), ``session.geometry`` (nominal rig: initial
        guess and camera names) and ``session.meta["charuco"]`` (the board; default
        :class:`CharucoSpec` when absent). Every camera with images in the session (any
        phase) is calibrated; cameras without any image are left out
        (``result.camera_indices``).
    config : CalibrationConfig
    progress : callable(done, total), optional
        Called after each image is searched for corners.

    Returns
    -------
    CalibrationResult
        ``seconds["detect"]`` holds the detection time (both passes with
        ``config.interpolate="aruco-calib"``, whose per-camera notes lead ``notes``).

    Raises
    ------
    CalibrationError
        No calibration phase, or a camera with fewer than three usable views.
    """

    geometry: RigGeometry = session.geometry
    nominal = geometry.nominal_cameras()
    spec_d = session.meta.get("charuco")
    spec = CharucoSpec.from_dict(spec_d, where=f"{session.root / 'session.toml'}:charuco") if spec_d else CharucoSpec()
    # kind=None (any kind) is documented; select's unannotated default makes pyright infer str.
    recs = session.select(phase="calibration", kind=None)  # pyright: ignore[reportArgumentType]
    if not recs:
        raise CalibrationError(
            f"{session.root}: the session has no 'calibration' phase records "
            "(capture the ChArUco board first, or provide calibration/<camera>.yaml)"
        )
    shots: dict[str, ShotRecord] = {}
    for r in recs:
        shots.setdefault(r.shot, r)
    t0 = time.perf_counter()
    detections: list[tuple[CharucoObservation, BoardDetection]] = []
    dropped: dict[str, str] = {}
    # Calibrate every camera the session used (in any phase): a camera the plan left out
    # entirely needs no calibration; one with images but no usable board views is an error.
    used = sorted({r.camera for r in session.records})
    sizes = {i: (nominal[i].width, nominal[i].height) for i in used if 0 <= i < len(nominal)}
    by_view: dict[str, str] = {}
    seen_size: dict[int, tuple[int, int]] = {}
    total = len(shots)
    for k, (shot, r) in enumerate(sorted(shots.items())):
        if progress is not None:
            progress(k, total)
        vid = view_id(r.camera, r.table_deg)
        if not 0 <= r.camera < len(nominal):
            raise FormatError(
                f"{session.root}: calibration shot {shot} names camera {r.camera}; the rig has {len(nominal)} cameras"
            )
        if vid in by_view:
            dropped.setdefault(vid, f"several calibration shots of this view ({by_view[vid]}, {shot}); used the first")
            continue
        by_view[vid] = shot
        try:
            img = session.load_radiance(shot)
        except (FormatError, OSError) as e:
            dropped[vid] = f"image unreadable: {e}"
            continue
        h, w = img.shape[:2]
        if r.camera in seen_size and seen_size[r.camera] != (w, h):
            dropped[vid] = (
                f"image is {w}x{h}, the camera's other calibration images are "
                f"{seen_size[r.camera][0]}x{seen_size[r.camera][1]}"
            )
            continue
        seen_size[r.camera] = sizes[r.camera] = (w, h)
        det = detect_board(
            detection_gray(img, percentile=config.tonemap_percentile),
            charuco=spec,
            upscale=config.detect_upscale,
            max_upscaled_px=config.detect_max_upscaled_px,
        )
        detections.append((observation_from(det, camera=r.camera, table_deg=r.table_deg), det))
    if progress is not None:
        progress(total, total)
    # Nominal intrinsics scaled to the image size actually captured.
    nom = list(nominal)
    for i in sizes:
        w, h = sizes[i]
        c = nominal[i]
        nom[i] = c if (w, h) == (c.width, c.height) else c.scaled(w / c.width)
    observations = [o for o, _ in detections]
    notes: list[str] = []
    if config.interpolate == "aruco-calib":

        def gray_of(vid: str) -> np.ndarray:
            # loaded again rather than kept: a rig's views at full resolution are large
            return detection_gray(session.load_radiance(by_view[vid]), percentile=config.tonemap_percentile)

        with single_threaded_solvers():
            observations, notes = reinterpolate_views(
                detections, gray_of=gray_of, image_sizes=sizes, charuco=spec, nominal=nom, config=config
            )
    t_detect = time.perf_counter() - t0
    result = calibrate_observations(
        observations, image_sizes=sizes, charuco=spec, nominal=nom, config=config, dropped=dropped
    )
    return replace(result, seconds={"detect": t_detect, **result.seconds}, notes=tuple(notes) + result.notes)
