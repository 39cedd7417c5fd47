"""Inputs of ``opacityhull calibrate``: the board spec, the cameras' images or videos, and
the frames kept (with a rejection report of the ones dropped).

Cameras and synchronisation (the documented input):

- every **video** is one camera; frame *k* of every video is the same instant unless
  ``--sync CSV`` says otherwise (caliscope's ``timestamps.csv``: columns ``sync_index``,
  ``cam_id``, ``frame_index``; ``cam_id`` is the camera's position among the inputs, and
  a camera's video starts at the first ``frame_index`` listed for it);
- every **directory** is one camera; its images with the same file name in two
  directories are the same instant;
- loose **image files** together are one camera (one instant each).

Frames are decoded with OpenCV, searched with :func:`opacityhull.charuco.detect_board`,
and dropped with a reason when they carry too few corners, are blurred (variance of the
Laplacian over the board's bounding box below ``blur_ratio`` × the camera's median) or
repeat the last kept frame (same corners within ``duplicate_px``).
"""

from __future__ import annotations

import csv
import logging
import math
import re
from dataclasses import dataclass, field
from dataclasses import replace
from pathlib import Path
from typing import Literal
from collections.abc import Sequence

import numpy as np

from ..charuco import (
    BoardDetection,
    CharucoSpec,
    detect_board,
    laplacian_sharpness,
    marker_points,
    reinterpolate_board,
    single_threaded_solvers,
)
from ..errors import ConfigError, FormatError, InputError

log = logging.getLogger(__name__)

__all__ = [
    "CameraInput",
    "FrameObservation",
    "Rejection",
    "parse_board",
    "camera_inputs",
    "read_sync_csv",
    "detect_frames",
    "screen_frames",
    "reinterpolate_frames",
    "Interpolation",
    "UNSYNCED",
]

#: How the ChArUco corners are first placed before ``cornerSubPix``: ``homography``
#: (OpenCV's ``CharucoDetector`` without a camera: each corner from the homography of its
#: neighbouring markers) or ``aruco-calib`` (OpenCV's ``calibrate_camera_charuco`` sample:
#: a first calibration from the ArUco marker corners, ``calibrateCameraAruco``, then every
#: frame's corners interpolated again through that camera, lens distortion included).
#: ``cornerSubPix`` stops at 0.1 px (OpenCV's ``cornerRefinementMinAccuracy``), so where it
#: starts shows in the result. ``aruco-calib`` is the default: measured on the five real
#: cameras of tests/data/real/calibration, it lowers every camera's reprojection RMS
#: (OpenCV photographs 0.188 -> 0.183 px; caliscope's four webcams 0.16/0.14/0.28/0.27 ->
#: 0.15/0.10/0.14/0.20 px) and halves caliscope's cam 2 held-out residual (see
#: benchmarks/calibration_real.py).
Interpolation = Literal["homography", "aruco-calib"]

#: Instant-key prefix of a frame whose instant's cameras are out of sync (``--max-skew``):
#: used for its camera's intrinsics only.
UNSYNCED = "unsynced:"

IMAGE_EXT = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
VIDEO_EXT = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg"}


@dataclass(frozen=True, kw_only=True)
class CameraInput:
    """One camera's source: a video, or image files (``frames`` names their instants)."""

    index: int
    source: str  # what the user gave (a video, a directory, or "N image files")
    video: Path | None = None
    images: tuple[Path, ...] = ()
    instants: tuple[str, ...] = ()  # one per image: the instant's key


@dataclass(frozen=True, kw_only=True)
class FrameObservation:
    """The board corners one camera saw at one instant."""

    camera: int
    instant: str  # sync key: frame number or file name
    where: str  # the file (and frame) for messages
    detection: BoardDetection
    sharpness: float


@dataclass(frozen=True, kw_only=True)
class Rejection:
    """A frame left out, and why (the rejection report)."""

    camera: int
    where: str
    reason: str

    def to_dict(self) -> dict:
        return {"camera": self.camera, "frame": self.where, "reason": self.reason}


_SPEC_KEYS = {"squares", "squares_x", "squares_y", "square_m", "marker_m", "dictionary", "polarity", "layout"}


def _spec_from_mapping(d: dict, where: str) -> CharucoSpec:
    d = dict(d)
    if "charuco" in d and isinstance(d["charuco"], dict):
        d = dict(d["charuco"])
    if "columns" in d and "rows" in d:  # caliscope's charuco.toml
        try:
            square_m = float(d["square_size_override_cm"]) / 100.0
            kw = {
                "squares_x": int(d["columns"]),
                "squares_y": int(d["rows"]),
                "square_m": square_m,
                "marker_m": square_m * float(d.get("aruco_scale", 0.75)),
                "dictionary": str(d["dictionary"]),
                "polarity": "inverted" if d.get("inverted") else "normal",
            }
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"{where}: caliscope board spec needs square_size_override_cm ({e})") from None
        return CharucoSpec.from_dict(kw, where=where)
    unknown = sorted(set(d) - _SPEC_KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(_SPEC_KEYS)}")
    kw: dict = {}
    if "squares" in d:
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(d.pop("squares")))
        if not m:
            raise ConfigError(f"{where}: squares must be COLSxROWS, e.g. 5x7")
        kw["squares_x"], kw["squares_y"] = int(m.group(1)), int(m.group(2))
    for k in ("squares_x", "squares_y"):
        if k in d:
            kw[k] = int(d[k])
    for k in ("square_m", "marker_m"):
        if k in d:
            try:
                kw[k] = float(d[k])
            except (TypeError, ValueError):
                raise ConfigError(f"{where}: {k}={d[k]!r} is not a number (metres)") from None
    for k in ("dictionary", "polarity", "layout"):
        if k in d:
            kw[k] = str(d[k])
    missing = [k for k in ("squares_x", "squares_y", "square_m", "marker_m", "dictionary") if k not in kw]
    if missing:
        raise ConfigError(
            f"{where}: missing {missing} (e.g. squares=5x7,square_m=0.04,marker_m=0.02,dictionary=DICT_6X6_250)"
        )
    spec = CharucoSpec.from_dict(kw, where=where)
    spec.board()  # names an unknown dictionary now
    return spec


def parse_board(text: str) -> CharucoSpec:
    """``--board``: a TOML file (``[charuco]`` or top-level keys, or caliscope's
    ``charuco.toml``) or ``key=value`` pairs mirroring OpenCV's names:
    ``squares=5x7,square_m=0.04,marker_m=0.02,dictionary=DICT_6X6_250[,polarity=inverted][,layout=legacy]``."""
    p = Path(text)
    if text.endswith(".toml") or (p.exists() and p.is_file()):
        from ..tomlio import read_toml

        d = read_toml(p, error=InputError, what="--board TOML")
        spec = _spec_from_mapping(d, f"--board {text}")
        spec.board()
        return spec
    d: dict = {}
    for part in text.split(","):
        if not part.strip():
            continue
        k, eq, v = part.partition("=")
        if not eq:
            raise ConfigError(f"--board {text!r}: {part!r} is not key=value")
        d[k.strip()] = v.strip()
    return _spec_from_mapping(d, f"--board {text!r}")


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def camera_inputs(paths: Sequence[Path]) -> list[CameraInput]:
    """Group the command's inputs into cameras (see the module docstring)."""
    cams: list[CameraInput] = []
    loose: list[Path] = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise InputError(f"{p}: no such file or directory")
        if p.is_dir():
            imgs = sorted((q for q in p.iterdir() if q.suffix.lower() in IMAGE_EXT), key=_natural_key)
            if not imgs:
                raise InputError(f"{p}: directory holds no images ({', '.join(sorted(IMAGE_EXT))})")
            cams.append(
                CameraInput(index=len(cams), source=str(p), images=tuple(imgs), instants=tuple(q.name for q in imgs))
            )
        elif p.suffix.lower() in VIDEO_EXT:
            cams.append(CameraInput(index=len(cams), source=str(p), video=p))
        elif p.suffix.lower() in IMAGE_EXT:
            loose.append(p)
        else:
            raise InputError(
                f"{p}: not an image ({', '.join(sorted(IMAGE_EXT))}) nor a video ({', '.join(sorted(VIDEO_EXT))})"
            )
    if loose:
        if cams:
            raise InputError(
                "give either image files (one camera) or videos / image directories (one camera each), not both: "
                f"{loose[0]} and {cams[0].source}"
            )
        cams.append(
            CameraInput(
                index=0, source=f"{len(loose)} image files", images=tuple(loose), instants=tuple(str(q) for q in loose)
            )
        )
    if not cams:
        raise InputError("no inputs: give board photographs, a directory of them per camera, or videos")
    return cams


def read_sync_csv(path: Path, n_cameras: int, *, max_skew_s: float = 0.005) -> dict[tuple[int, int], str]:
    """``--sync``: (camera, frame index) → instant key from a CSV with columns
    ``sync_index, cam_id, frame_index`` and optionally ``frame_time`` (seconds).

    With ``frame_time``, an instant whose cameras' frames lie more than ``max_skew_s``
    apart is mapped to ``""`` (left out of the multi-camera stage, used for each camera's
    own intrinsics: a board moving by hand travels millimetres in
    that time; measured on caliscope's set, the skew is 3 ms at the median and 14 ms at
    the 90th percentile, and the instants above 5 ms hold the worst residuals)."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"--sync {path}: cannot read ({e})") from None
    need = {"sync_index", "cam_id", "frame_index"}
    if not rows or not need <= set(rows[0]):
        raise InputError(f"--sync {path}: expected a CSV with columns {sorted(need)}")
    parsed: list[tuple[int, int, int, float]] = []
    for i, r in enumerate(rows, start=2):
        try:
            s, c, k = int(r["sync_index"]), int(r["cam_id"]), int(r["frame_index"])
            t = float(r["frame_time"]) if r.get("frame_time") not in (None, "") else math.nan
        except (TypeError, ValueError):
            raise InputError(
                f"--sync {path}: line {i}: sync_index, cam_id, frame_index must be integers (frame_time seconds)"
            ) from None
        if not 0 <= c < n_cameras:
            raise InputError(f"--sync {path}: line {i}: cam_id {c}, but {n_cameras} camera(s) were given")
        parsed.append((s, c, k, t))
    # A recording's frame numbers need not start at 0 (caliscope's start where the
    # recording was trimmed): each camera's video starts at its first listed frame.
    first: dict[int, int] = {}
    times: dict[int, list[float]] = {}
    for s, c, k, t in parsed:
        first[c] = min(first.get(c, k), k)
        times.setdefault(s, []).append(t)
    skew = {s: (max(v) - min(v)) if all(math.isfinite(x) for x in v) else 0.0 for s, v in times.items()}
    return {(c, k - first[c]): (f"sync{s:06d}" if skew[s] <= max_skew_s else "") for s, c, k, _ in parsed}


def _gray(frame: np.ndarray) -> np.ndarray:
    """8-bit grey of a decoded frame (16-bit or float images scaled by their maximum)."""
    import cv2

    g = (
        frame
        if frame.ndim == 2
        else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY if frame.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    )
    if g.dtype == np.uint8:
        return g
    g = np.asarray(g, dtype=np.float64)
    top = float(np.nanmax(g)) if g.size else 0.0
    return np.clip(np.nan_to_num(g / top if top > 0 else g) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _frames(cam: CameraInput, *, step: int):
    """Yield (instant key, where, gray uint8) of one camera; FormatError for undecodable files."""
    import cv2

    if cam.video is not None:
        cap = cv2.VideoCapture(str(cam.video))
        try:
            if not cap.isOpened():
                raise FormatError(f"{cam.video}: cannot be decoded as a video (OpenCV/FFmpeg could not open it)")
            k = 0
            n_read = 0
            while True:
                ok, fr = cap.read()
                if not ok or fr is None:
                    break
                n_read += 1
                if k % step == 0:
                    yield str(k), f"{cam.video}#{k}", _gray(fr)
                k += 1
            if n_read == 0:
                raise FormatError(f"{cam.video}: no frame could be decoded (corrupt or not a video)")
        finally:
            cap.release()
        return
    for p, key in zip(cam.images, cam.instants, strict=True):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FormatError(f"{p}: cannot be decoded as an image")
        yield key, str(p), _gray(img)


@dataclass(kw_only=True)
class DetectedCamera:
    """What the frames of one camera gave."""

    camera: CameraInput
    size: tuple[int, int] | None = None
    observations: list[FrameObservation] = field(default_factory=list)
    rejected: list[Rejection] = field(default_factory=list)
    frames_read: int = 0
    variants: dict[str, int] = field(default_factory=dict)


def detect_frames(
    cam: CameraInput,
    *,
    charuco: CharucoSpec,
    sync: dict[tuple[int, int], str] | None = None,
    step: int = 1,
    upscale: Sequence[int] = (1, 2),
    try_mirrored: bool = True,
    progress=None,
) -> DetectedCamera:
    """Decode and search every frame of one camera (frames with no corners are rejected
    here; blur, duplicates and too few corners in :func:`screen_frames`)."""
    out = DetectedCamera(camera=cam)
    prefer: BoardDetection | None = None
    for key, where, gray in _frames(cam, step=step):
        out.frames_read += 1
        h, w = gray.shape
        if out.size is None:
            out.size = (w, h)
        elif out.size != (w, h):
            raise InputError(
                f"{where}: image is {w}x{h}, the other images of camera {cam.index} ({cam.source}) are "
                f"{out.size[0]}x{out.size[1]}; give each camera's images in their own directory"
            )
        if sync is not None and cam.video is not None:
            k = int(key)
            if (cam.index, k) not in sync:
                out.rejected.append(Rejection(camera=cam.index, where=where, reason="not listed in --sync"))
                continue
            # An instant whose cameras are out of sync still shows this camera a sharp board:
            # it calibrates this camera's intrinsics, under a key no other camera shares, and
            # stays out of the multi-camera stage (measured on caliscope's extrinsic videos:
            # 40 of 111 frames per camera; using them moved the focal lengths from
            # +1.1/+0.5/-4.3/+0.8 % to +1.0/-0.2/-1.8/+0.8 % of caliscope's).
            key = sync[(cam.index, k)] or f"{UNSYNCED}{cam.index}:{k}"
        det = detect_board(gray, charuco=charuco, upscale=upscale, try_mirrored=try_mirrored, prefer=prefer)
        if progress is not None:
            progress(out.frames_read)
        if len(det) == 0:
            out.rejected.append(
                Rejection(camera=cam.index, where=where, reason=f"no ChArUco corners ({det.n_markers} markers decoded)")
            )
            continue
        prefer = det
        out.variants[det.variant] = out.variants.get(det.variant, 0) + 1
        if det.mirrored:
            # corners are in the flipped image: the camera model is that of the un-mirrored sensor
            gray = np.ascontiguousarray(gray[:, ::-1])
        out.observations.append(
            FrameObservation(
                camera=cam.index,
                instant=key,
                where=where,
                detection=det,
                sharpness=laplacian_sharpness(gray, det.image_points),
            )
        )
    return out


def _minor_std(points2: np.ndarray) -> float:
    if points2.shape[0] < 3:
        return 0.0
    c = np.cov(points2.T)
    return float(math.sqrt(max(np.linalg.eigvalsh(c)[0], 0.0)))


def screen_frames(
    dc: DetectedCamera,
    *,
    charuco: CharucoSpec,
    min_corners: int = 6,
    blur_ratio: float = 0.35,
    duplicate_px: float = 0.5,
    min_image_spread_px: float = 3.0,
) -> DetectedCamera:
    """Drop frames with too few or collinear corners, blurred ones and duplicates, each with
    its reason in ``dc.rejected`` (in place; returns ``dc``)."""
    kept: list[FrameObservation] = []
    for o in dc.observations:
        d = o.detection
        if len(d) < min_corners:
            dc.rejected.append(
                Rejection(camera=o.camera, where=o.where, reason=f"only {len(d)} corners (< {min_corners})")
            )
        elif _minor_std(d.object_points[:, :2]) / charuco.square_m < 0.3:
            dc.rejected.append(Rejection(camera=o.camera, where=o.where, reason="corners collinear on the board"))
        elif _minor_std(d.image_points) < min_image_spread_px:
            dc.rejected.append(
                Rejection(camera=o.camera, where=o.where, reason="board seen edge-on (corners collinear in the image)")
            )
        else:
            kept.append(o)
    if kept and blur_ratio > 0:
        med = float(np.median([o.sharpness for o in kept]))
        sharp = []
        for o in kept:
            if o.sharpness < blur_ratio * med:
                dc.rejected.append(
                    Rejection(
                        camera=o.camera,
                        where=o.where,
                        reason=f"blurred: Laplacian variance {o.sharpness:.1f} < {blur_ratio} x median {med:.1f}",
                    )
                )
            else:
                sharp.append(o)
        kept = sharp
    if duplicate_px > 0:
        uniq: list[FrameObservation] = []
        for o in kept:
            if uniq:
                last = uniq[-1].detection
                d = o.detection
                if np.array_equal(last.ids, d.ids):
                    move = float(np.max(np.linalg.norm(last.image_points - d.image_points, axis=1)))
                    if move < duplicate_px:
                        dc.rejected.append(
                            Rejection(
                                camera=o.camera,
                                where=o.where,
                                reason=f"duplicate of {uniq[-1].where} (corners moved {move:.2f} px < {duplicate_px})",
                            )
                        )
                        continue
            uniq.append(o)
        kept = uniq
    dc.observations = kept
    return dc


def reinterpolate_frames(dc: DetectedCamera, *, charuco: CharucoSpec, step: int = 1) -> DetectedCamera:
    """``--interpolate aruco-calib``: OpenCV's ``calibrate_camera_charuco`` sample on one
    camera. A first calibration from the decoded ArUco marker corners alone
    (``calibrateCamera`` with OpenCV's default flags, as ``calibrateCameraAruco``), then
    each kept frame decoded again and its ChArUco corners interpolated through that camera
    (:func:`opacityhull.charuco.reinterpolate_board`). In place; returns ``dc``. A camera
    with fewer than 3 frames of 2 or more markers keeps its corners (logged)."""
    import cv2

    pairs = [marker_points(o.detection, charuco) for o in dc.observations]
    use = [(obj, img) for obj, img in pairs if len(obj) >= 8]
    if dc.size is None or len(use) < 3:
        log.warning(
            "camera %d (%s): %d frame(s) with 2+ markers, 3 needed for --interpolate aruco-calib; corners kept",
            dc.camera.index,
            dc.camera.source,
            len(use),
        )
        return dc
    try:
        with single_threaded_solvers():
            _, K, dist, _, _ = cv2.calibrateCamera(
                [o.astype(np.float32) for o, _ in use], [i.astype(np.float32) for _, i in use], dc.size, None, None
            )
    except cv2.error as e:
        log.warning("camera %d: calibration from marker corners failed (%s); corners kept", dc.camera.index, e)
        return dc
    wanted = {o.where: k for k, o in enumerate(dc.observations)}
    for _, where, gray in _frames(dc.camera, step=step):
        k = wanted.get(where)
        if k is not None:
            o = dc.observations[k]
            dc.observations[k] = replace(
                o, detection=reinterpolate_board(gray, o.detection, charuco=charuco, K=K, dist=dist)
            )
    return dc
