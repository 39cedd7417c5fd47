"""The ``calibrate`` runner: inputs → frames → per-camera init → chain → bundle adjustment."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..charuco import CharucoSpec, single_threaded_solvers
from ..errors import InputError
from .bundle import DIST_MODELS, BundleResult, CameraInit, Obs, bundle_adjust, chain_cameras, init_camera
from .inputs import (
    CameraInput,
    DetectedCamera,
    Interpolation,
    UNSYNCED,
    Rejection,
    camera_inputs,
    detect_frames,
    read_sync_csv,
    reinterpolate_frames,
    screen_frames,
)

log = logging.getLogger(__name__)

__all__ = ["CalibrateOptions", "CalibrateRun", "calibrate_cameras", "calibrate_detected"]


@dataclass(frozen=True, kw_only=True)
class CalibrateOptions:
    """Options of :func:`calibrate_cameras` (the command's flags)."""

    dist_model: str = "k1k2pk3"
    min_corners: int = 6
    blur_ratio: float = 0.35
    duplicate_px: float = 0.5
    step: int = 1
    upscale: tuple[int, ...] = (1, 2)
    try_mirrored: bool = True
    min_plane_spread_deg: float = 3.0
    refine_intrinsics: bool = False
    max_skew_s: float = 0.005
    fix_principal_point: bool = False
    fix_aspect_ratio: bool = False
    interpolate: Interpolation = "aruco-calib"
    #: (camera index, K (3, 3), dist (5,), (width, height), source) held as given (``--intrinsics``)
    intrinsics: tuple[tuple[int, np.ndarray, np.ndarray, tuple[int, int], str], ...] = ()

    def __post_init__(self):
        if self.dist_model not in DIST_MODELS:
            raise InputError(f"--dist {self.dist_model!r}: expected one of {', '.join(DIST_MODELS)}")
        if self.min_corners < 4:
            raise InputError(f"--min-corners {self.min_corners}: expected at least 4")
        if self.step < 1:
            raise InputError(f"--every {self.step}: expected at least 1")
        if self.interpolate not in ("homography", "aruco-calib"):
            raise InputError(f"--interpolate {self.interpolate!r}: expected homography or aruco-calib")


@dataclass(kw_only=True)
class CalibrateRun:
    """What :func:`calibrate_cameras` found."""

    charuco: CharucoSpec
    cameras: list[CameraInput]
    detected: list[DetectedCamera]
    result: BundleResult
    inits: dict[int, CameraInit]
    left_out: dict[int, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    @property
    def rejected(self) -> list[Rejection]:
        out = [r for d in self.detected for r in d.rejected]
        for c, ini in self.inits.items():
            out += [Rejection(camera=c, where=w, reason=why) for w, why in ini.dropped.items()]
        return out


def _given_intrinsics(obs: Sequence[Obs], *, index: int, size: tuple[int, int], K, dist) -> CameraInit:
    """A camera whose intrinsics are given: every frame's board pose by PnP through them."""
    import cv2

    from ..se3 import rigid, rodrigues

    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()[:5]
    poses = {}
    for o in obs:
        ok, rv, tv = cv2.solvePnP(o.object_points, o.image_points, K, dist)
        if ok:
            poses[o.instant] = rigid(rodrigues(np.ravel(rv)), np.ravel(tv))
    return CameraInit(index=index, size=size, K=K, dist=dist, free=(), cam_from_board=poses)


def calibrate_detected(
    detected: list[DetectedCamera], *, charuco: CharucoSpec, options: CalibrateOptions, cameras: list[CameraInput]
) -> CalibrateRun:
    """Screen, initialise and bundle-adjust detections (the part after decoding), with
    OpenCV and BLAS at one thread so that the result repeats bit for bit."""
    with single_threaded_solvers():
        return _calibrate_detected(detected, charuco=charuco, options=options, cameras=cameras)


def _calibrate_detected(
    detected: list[DetectedCamera], *, charuco: CharucoSpec, options: CalibrateOptions, cameras: list[CameraInput]
) -> CalibrateRun:
    for d in detected:
        screen_frames(
            d,
            charuco=charuco,
            min_corners=options.min_corners,
            blur_ratio=options.blur_ratio,
            duplicate_px=options.duplicate_px,
        )
    if all(d.frames_read > 0 and not any(len(o.detection) for o in d.observations) for d in detected) and not any(
        d.observations for d in detected
    ):
        found_any = any(r.reason.startswith("only") or "collinear" in r.reason for d in detected for r in d.rejected)
        if not found_any:
            tried = {
                "auto": "both print polarities (normal, inverted) were tried",
                "normal": "only the normal print was tried: try polarity=inverted (white markers on black)",
                "inverted": "only the inverted print was tried: try polarity=normal",
            }[charuco.polarity]
            if charuco.squares_y % 2:
                lay = "the legacy and new layouts are the same for an odd row count"
            elif charuco.layout == "auto":
                lay = "both layouts (new, legacy) were tried"
            else:
                lay = f"only layout={charuco.layout} was tried: try layout={'new' if charuco.layout == 'legacy' else 'legacy'}"
            raise InputError(
                f"--board: no ChArUco corners of a {charuco.squares_x}x{charuco.squares_y} {charuco.dictionary} board "
                f"in any of {sum(d.frames_read for d in detected)} frame(s); {tried}; {lay}; check squares "
                "(columns x rows), dictionary and marker_m"
            )
    left_out: dict[int, str] = {}
    notes: list[str] = []
    inits: dict[int, CameraInit] = {}
    n_dist = len(DIST_MODELS[options.dist_model])
    for d in detected:
        c = d.camera.index
        obs = [
            Obs(
                camera=c,
                instant=o.instant,
                where=o.where,
                object_points=o.detection.object_points,
                image_points=o.detection.image_points,
            )
            for o in d.observations
        ]
        for v, k in sorted(d.variants.items()):
            if v != "normal":
                notes.append(f"camera {c} ({d.camera.source}): board found as {v} in {k} frame(s)")
        n_params = 4 + n_dist
        n_corners = sum(len(o.object_points) for o in obs)
        need = 3
        if len(obs) < need or 2 * n_corners <= n_params + 6 * len(obs):
            why = (
                f"camera {c} ({d.camera.source}): {len(obs)} usable frame(s) with {n_corners} corners; "
                f"{4 + n_dist} intrinsics + 6 per frame need at least {need} frames of a tilted board "
                f"({len(d.rejected)} frame(s) rejected)"
            )
            if len(detected) == 1:
                raise InputError(why + ": fewer frames than the parameters need")
            left_out[c] = why
            continue
        assert d.size is not None
        given = {i: (K, dist) for i, K, dist, _, _ in options.intrinsics}
        for i, _, _, wh, src in options.intrinsics:
            if i >= len(detected):
                raise InputError(
                    f"--intrinsics {src}: given for camera {i}, but the inputs make {len(detected)} camera(s)"
                )
            if i == c and d.size is not None and tuple(wh) != tuple(d.size):
                raise InputError(
                    f"--intrinsics {src}: is for {wh[0]}x{wh[1]} images, camera {c}'s are {d.size[0]}x{d.size[1]}"
                )
        if c in given:
            inits[c] = _given_intrinsics(obs, index=c, size=d.size, K=given[c][0], dist=given[c][1])
            notes.append(f"camera {c}: intrinsics held as given (--intrinsics)")
        else:
            inits[c] = init_camera(
                obs,
                index=c,
                size=d.size,
                dist_model=options.dist_model,
                min_plane_spread_deg=options.min_plane_spread_deg,
                fix_principal_point=options.fix_principal_point,
                fix_aspect_ratio=options.fix_aspect_ratio,
            )
        notes += inits[c].notes
    if not inits:
        raise InputError("no camera has enough frames: " + " | ".join(left_out.values()))
    cam_from_world, world_from_board, unchained = chain_cameras(inits)
    for c, why in unchained.items():
        left_out[c] = why
        del inits[c]
    all_obs = [
        Obs(
            camera=d.camera.index,
            instant=o.instant,
            where=o.where,
            object_points=o.detection.object_points,
            image_points=o.detection.image_points,
        )
        for d in detected
        for o in d.observations
        if d.camera.index in inits
        and o.where not in inits[d.camera.index].dropped
        and o.instant in inits[d.camera.index].cam_from_board
    ]
    # Each camera alone first: its intrinsics and their standard deviations.
    alone: dict[int, BundleResult] = {}
    for c in sorted(inits):
        mine = [o for o in all_obs if o.camera == c]
        wfb = dict(inits[c].cam_from_board)  # world = this camera's frame
        alone[c] = bundle_adjust({c: inits[c]}, {c: np.eye(4)}, wfb, mine)
        fit = alone[c].cameras[c]
        inits[c] = replace(inits[c], K=fit.K, dist=fit.dist)
    if len(inits) == 1:
        c0 = sorted(inits)[0]
        result = alone[c0]
        fit0 = result.cameras[c0]
        result = replace(
            result, cameras={c0: replace(fit0, intrinsic_rms_px=fit0.rms_px, intrinsic_frames=fit0.n_frames)}
        )
    else:
        # Together, the poses; intrinsics held at each camera's own unless asked: an
        # instant's cameras are exposed milliseconds apart while the board moves by hand,
        # and free intrinsics absorb that (measured on caliscope's set: focal lengths
        # 12-17 % off with them free, 0.8-1.8 % with them held).
        joint = {c: replace(ini, free=ini.free if options.refine_intrinsics else ()) for c, ini in inits.items()}
        synced = [o for o in all_obs if not o.instant.startswith(UNSYNCED)]
        for c in sorted(inits):
            n_un = sum(1 for o in all_obs if o.camera == c and o.instant.startswith(UNSYNCED))
            if n_un:
                notes.append(
                    f"camera {c}: {n_un} frame(s) whose instant is out of sync (--max-skew) calibrate its "
                    "intrinsics only"
                )
        result = bundle_adjust(joint, cam_from_world, world_from_board, synced)
        if not options.refine_intrinsics:
            cams_fit = {}
            for c, f in result.cameras.items():
                std = {
                    **alone[c].cameras[c].std,
                    **{k: v for k, v in f.std.items() if k not in alone[c].cameras[c].std},
                }
                cams_fit[c] = replace(
                    f,
                    free=inits[c].free,
                    std=std,
                    intrinsic_rms_px=alone[c].cameras[c].rms_px,
                    intrinsic_frames=alone[c].cameras[c].n_frames,
                )
            result = replace(result, cameras=cams_fit)
    for why in left_out.values():
        log.warning(why)
    return CalibrateRun(
        charuco=charuco,
        cameras=cameras,
        detected=detected,
        result=result,
        inits=inits,
        left_out=left_out,
        notes=notes,
    )


def calibrate_cameras(
    inputs: Sequence[Path],
    *,
    charuco: CharucoSpec,
    sync: Path | None = None,
    options: CalibrateOptions = CalibrateOptions(),
    progress=None,
) -> CalibrateRun:
    """Calibrate the cameras behind ``inputs`` (see :mod:`.inputs` for how files map to
    cameras and instants)."""
    cams = camera_inputs(inputs)
    sync_map = read_sync_csv(sync, len(cams), max_skew_s=options.max_skew_s) if sync is not None else None
    detected = [
        detect_frames(
            c,
            charuco=charuco,
            sync=sync_map,
            step=options.step,
            upscale=options.upscale,
            try_mirrored=options.try_mirrored,
            progress=progress,
        )
        for c in cams
    ]
    if options.interpolate == "aruco-calib":
        detected = [reinterpolate_frames(d, charuco=charuco, step=options.step) for d in detected]
    return calibrate_detected(detected, charuco=charuco, options=options, cameras=cams)
