"""Detected ChArUco corners saved to a compact ``.npz`` and read back, so that a calibration
from videos runs again without decoding them (:func:`opacityhull.calibrate.run.calibrate_detected`
takes what :func:`read_corners` gives).

``benchmarks/calibration_real.py --write-corners`` saves what ``calibrate`` finds in every
frame of caliscope's four extrinsic videos
(``tests/data/real/calibration/caliscope/extrinsic_corners.npz``, 17 KB for 10 MB of
video); the tests and the benchmark's ``--quick`` calibrate from it.

The file holds, for the ``M`` observations (one camera's board in one video frame) of
``C`` cameras and their ``N`` corners in all:

=============  ================  ======================================================
key            shape, dtype      what
=============  ================  ======================================================
camera         (M,) int16        the observation's camera (0 .. C-1)
frame          (M,) int32        its frame index in that camera's video
instant        (M,) str          its instant key (``sync000123``, ``unsynced:CAM:FRAME``)
sharpness      (M,) float32      variance of the Laplacian over the board
start          (M+1,) int32      observation k's corners are ``start[k]:start[k+1]``
corner_id      (N,) int16        ChArUco corner ids
corner_xy      (N, 2) float32    pixels, OpenCV convention, in the un-mirrored image
mirrored       (C,) bool         the camera's frames were found flipped left-right
=============  ================  ======================================================

Not saved: the board (given again as ``charuco``), the image size, the frames in which
nothing was found (the rejection report) and the print's polarity (``inverted`` is read
back from ``charuco.polarity``).
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..charuco import BoardDetection, CharucoSpec
from ..errors import FormatError, InputError
from .inputs import CameraInput, DetectedCamera, FrameObservation

KEYS = ("camera", "frame", "instant", "sharpness", "start", "corner_id", "corner_xy", "mirrored")


def write_corners(path: Path, detected: Sequence[DetectedCamera]) -> None:
    """Save the observations of ``detected`` (cameras in order) to ``path`` (``.npz``).

    Parameters
    ----------
    path : Path
        The file written (NumPy adds ``.npz`` when the name has another suffix).
    detected : sequence of DetectedCamera
        What :func:`~opacityhull.calibrate.inputs.detect_frames` (and
        ``reinterpolate_frames``) gave for each video; ``detected[c]`` is camera ``c``.

    Raises
    ------
    InputError
        An observation is not a video frame (its ``where`` is not ``FILE#N``).
    """
    cam, frame, instant, start, ids, xy, sharp = [], [], [], [0], [], [], []
    for d in detected:
        for o in d.observations:
            head, _, n = o.where.rpartition("#")
            if not head or not n.isdigit():
                raise InputError(f"{o.where}: not a video frame (FILE#N); saved corners come from videos")
            cam.append(o.camera)
            frame.append(int(n))
            instant.append(o.instant)
            ids.append(o.detection.ids)
            sharp.append(o.sharpness)
            xy.append(o.detection.image_points)
            start.append(start[-1] + len(o.detection.ids))
    np.savez_compressed(
        path,
        camera=np.array(cam, np.int16),
        frame=np.array(frame, np.int32),
        instant=np.array(instant),
        sharpness=np.array(sharp, np.float32),
        start=np.array(start, np.int32),
        corner_id=np.concatenate(ids).astype(np.int16),
        corner_xy=np.concatenate(xy).astype(np.float32),
        mirrored=np.array([any(o.detection.mirrored for o in d.observations) for d in detected]),
    )


def read_corners(
    path: Path,
    *,
    charuco: CharucoSpec,
    size: tuple[int, int],
    sources: Sequence[str] | None = None,
) -> list[DetectedCamera]:
    """The detections :func:`write_corners` saved, as the cameras ``calibrate_detected`` takes.

    Parameters
    ----------
    path : Path
        A file written by :func:`write_corners`.
    charuco : CharucoSpec
        The board the corners were found on (object points from its corner ids).
    size : (2,) int
        The videos' frame size (width, height), pixels.
    sources : sequence of str, optional
        Each camera's video name, for messages: observation ``k`` of camera ``c`` is
        ``f"{sources[c]}#{frame[k]}"``. Default ``camera C``.

    Returns
    -------
    list of DetectedCamera
        One per camera, its observations in the file's order: ids int32 (n,), image
        points float64 (n, 2), object points float64 (n, 3) metres; ``frames_read`` 0 and no
        rejections (neither is saved).

    Raises
    ------
    FormatError
        ``path`` is missing, not an ``.npz``, lacks a key, or its arrays disagree in
        length or name a corner the board does not have.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in KEYS if k not in z.files]
            if missing:
                raise FormatError(f"{path}: not a saved-corners file, missing {missing} (expected {list(KEYS)})")
            a = {k: z[k] for k in KEYS}
    except FileNotFoundError:
        raise FormatError(f"{path}: no such file (saved corners, written by write_corners)") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise FormatError(f"{path}: cannot be read as an .npz of saved corners ({e})") from None
    m, n_cams = len(a["camera"]), len(a["mirrored"])
    start = a["start"]
    lengths = {k: len(a[k]) for k in ("frame", "instant", "sharpness")}
    if (
        any(v != m for v in lengths.values())
        or start.shape != (m + 1,)
        or start[0] != 0
        or np.any(np.diff(start) < 0)
        or start[-1] != len(a["corner_id"])
        or a["corner_xy"].shape != (len(a["corner_id"]), 2)
    ):
        raise FormatError(
            f"{path}: arrays disagree: {m} observations, frame/instant/sharpness {lengths}, start "
            f"{start.shape} ending at {start[-1] if len(start) else None}, corner_id {a['corner_id'].shape}, "
            f"corner_xy {a['corner_xy'].shape} (expected M, M, M, (M+1,) ending at N, (N,), (N, 2))"
        )
    if m and (a["camera"].min() < 0 or a["camera"].max() >= n_cams):
        raise FormatError(f"{path}: camera indices {a['camera'].min()}..{a['camera'].max()}, mirrored has {n_cams}")
    if sources is not None and len(sources) != n_cams:
        raise InputError(f"{path}: {n_cams} camera(s) saved, {len(sources)} source name(s) given")
    names = list(sources) if sources is not None else [f"camera {i}" for i in range(n_cams)]
    board_xyz = np.asarray(charuco.board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    if len(a["corner_id"]) and (a["corner_id"].min() < 0 or a["corner_id"].max() >= len(board_xyz)):
        raise FormatError(
            f"{path}: corner ids up to {a['corner_id'].max()}, the {charuco.squares_x}x{charuco.squares_y} "
            f"board has {len(board_xyz)} corners (wrong --board for this file?)"
        )
    inverted = charuco.polarity == "inverted"
    dets = [
        DetectedCamera(camera=CameraInput(index=i, source=names[i]), size=(int(size[0]), int(size[1])))
        for i in range(n_cams)
    ]
    for k in range(m):
        c = int(a["camera"][k])
        s0, s1 = int(start[k]), int(start[k + 1])
        ids = a["corner_id"][s0:s1].astype(np.int32)
        det = BoardDetection(
            ids=ids,
            image_points=a["corner_xy"][s0:s1].astype(np.float64),
            object_points=board_xyz[ids],
            inverted=inverted,
            mirrored=bool(a["mirrored"][c]),
        )
        dets[c].observations.append(
            FrameObservation(
                camera=c,
                instant=str(a["instant"][k]),
                where=f"{names[c]}#{int(a['frame'][k])}",
                detection=det,
                sharpness=float(a["sharpness"][k]),
            )
        )
    return dets
