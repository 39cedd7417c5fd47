"""The ChArUco calibration target: one definition for the simulator that renders it and
the calibration that detects it.

The board lies flat on the turntable. Its pose at table angle 0 fixes the gauge of the
rig frame about the table axis: board x along rig +X, board y (down the board image)
along rig +Z, so the board's z axis (into the board, as OpenCV defines it) is rig −Y.
``offset_m`` / ``yaw_deg`` describe how far the board's centre is from the table centre
and how it is turned — a real user never places it exactly; calibration estimates the
true placement and the table axis from the observations.

``tilt_deg`` stands the board on a wedge: rotated about its own x axis (rig +X at yaw 0)
so that, at table angle 0, it leans back to face the cameras (which sit on the +Z side).
A flat board is seen edge-on by cameras near the table plane; a board tilted by about
the middle of the cameras' elevation range is seen by all of them at some table angles.
"""

from __future__ import annotations

import functools
import math
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from typing import Literal
from collections.abc import Sequence

import numpy as np

from .camera import rot_y
from .errors import ConfigError, ShapeError

__all__ = [
    "CharucoSpec",
    "BOARD_R0",
    "rot_x",
    "BoardDetection",
    "detect_board",
    "reinterpolate_board",
    "marker_points",
    "tonemap_for_detection",
    "laplacian_sharpness",
    "single_threaded_solvers",
    "Polarity",
    "Layout",
]

#: Board print: black markers on white squares (``normal``, OpenCV's ``generateImage``) or
#: the negative (``inverted``: white markers on black, as some tools print it).
Polarity = Literal["auto", "normal", "inverted"]
#: OpenCV ≥ 4.6 ChArUco layout (``new``) or the one before it (``legacy``: with an even
#: number of rows the top-left square is white). The two differ only for an even
#: ``squares_y``.
Layout = Literal["auto", "new", "legacy"]

#: Orientation of a flat board at yaw 0: board x → rig +X, board y → +Z, board z → −Y.
BOARD_R0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def rot_x(angle_rad: float) -> np.ndarray:
    """3×3 right-handed rotation about +X (+Y turns towards +Z)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board and its nominal placement on the table.

    Parameters
    ----------
    squares_x, squares_y : squares along the board's x and y.
    square_m, marker_m : square and marker side lengths in metres.
    dictionary : OpenCV predefined ArUco dictionary name (``DICT_5X5_100``).
    offset_m : (x, z) of the board centre from the table centre, rig frame, table angle 0.
    yaw_deg : rotation of the board about +Y at table angle 0.
    height_m : height of the board's centre above the table top (a flat board's
        thickness; for a tilted board, whatever the wedge makes it).
    tilt_deg : lean of the board about its x axis, towards the cameras at table angle 0.
    polarity : ``auto`` (try the print as it is, then its negative), ``normal`` or
        ``inverted``.
    layout : ``auto`` (try OpenCV's current layout, then the legacy one when they
        differ), ``new`` or ``legacy``.
    """

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.04
    marker_m: float = 0.03
    dictionary: str = "DICT_5X5_100"
    offset_m: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    height_m: float = 0.0
    tilt_deg: float = 0.0
    polarity: Polarity = "auto"
    layout: Layout = "auto"

    def __post_init__(self):
        if self.squares_x < 3 or self.squares_y < 3:
            raise ConfigError(f"charuco: need at least 3x3 squares, got {self.squares_x}x{self.squares_y}")
        if not 0 < self.marker_m < self.square_m:
            raise ConfigError(f"charuco: marker_m={self.marker_m} must be in (0, square_m={self.square_m})")
        if not 0.0 <= self.tilt_deg < 90.0:
            raise ConfigError(f"charuco.tilt_deg: must be in [0, 90), got {self.tilt_deg}")
        # checked here, not when the board is first drawn: a dry run accepted DICT_BOGUS and
        # the capture failed after writing session.toml
        import cv2

        name = self.dictionary
        if not (isinstance(name, str) and name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)):
            known = sorted(
                k for k in dir(cv2.aruco) if k.startswith("DICT_") and isinstance(getattr(cv2.aruco, k), int)
            )
            raise ConfigError(
                f"charuco.dictionary: unknown ArUco dictionary {name!r}; expected one of OpenCV's, e.g. "
                f"{', '.join(known[:4])} ... ({len(known)} in all)"
            )
        if self.polarity not in ("auto", "normal", "inverted"):
            raise ConfigError(f"charuco.polarity={self.polarity!r}: expected auto, normal or inverted")
        if self.layout not in ("auto", "new", "legacy"):
            raise ConfigError(f"charuco.layout={self.layout!r}: expected auto, new or legacy")

    @classmethod
    def from_dict(cls, d: dict, where: str = "charuco") -> CharucoSpec:
        allowed = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")
        kw = dict(d)
        if "offset_m" in kw:
            kw["offset_m"] = tuple(float(v) for v in kw["offset_m"])
        try:
            return cls(**kw)
        except ConfigError as e:  # name the file and table (the checks say only "charuco.KEY")
            msg = str(e)
            raise ConfigError(
                f"{where}{msg[len('charuco') :]}" if msg.startswith("charuco") else f"{where}: {msg}"
            ) from None

    def to_dict(self) -> dict:
        """Every field, as :meth:`from_dict` reads it back (``offset_m`` a list, for TOML/JSON).
        ``polarity`` and ``layout`` are left out while ``auto``, so sessions written before
        they existed keep their bytes."""
        d = {**asdict(self), "offset_m": list(self.offset_m)}
        for k in ("polarity", "layout"):
            if d[k] == "auto":
                del d[k]
        return d

    @property
    def size_m(self) -> tuple[float, float]:
        return (self.squares_x * self.square_m, self.squares_y * self.square_m)

    def board(self, *, legacy: bool | None = None):
        """The ``cv2.aruco.CharucoBoard`` (``legacy``: None follows ``layout``, ``auto`` = new)."""
        import cv2

        name = self.dictionary
        if not hasattr(cv2.aruco, name):
            raise ConfigError(f"charuco.dictionary: unknown ArUco dictionary {name!r}")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        b = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)
        b.setLegacyPattern(self.layout == "legacy" if legacy is None else bool(legacy))
        return b

    def layouts(self) -> tuple[bool, ...]:
        """``legacy`` values the detector tries: both for ``auto`` when they differ (even
        ``squares_y``), else the one the spec names."""
        if self.layout == "auto":
            return (False, True) if self.squares_y % 2 == 0 else (False,)
        return (self.layout == "legacy",)

    def polarities(self) -> tuple[bool, ...]:
        """``inverted`` values the detector tries."""
        return (False, True) if self.polarity == "auto" else (self.polarity == "inverted",)

    def image(self, px_per_square: int = 100) -> np.ndarray:
        """Board image, uint8 (rows, cols), row 0 = board y = 0 (no margin)."""
        w, h = self.squares_x * px_per_square, self.squares_y * px_per_square
        return self.board().generateImage((w, h), marginSize=0, borderBits=1)

    def tilt_rotation(self) -> np.ndarray:
        """Rotation about rig +X that leans the board's upper face (−board z) towards +Z."""
        return rot_x(math.radians(self.tilt_deg))

    def object_from_board(self) -> np.ndarray:
        """4×4 pose of the board frame (OpenCV board coordinates, metres) in the object
        frame (= rig frame at table angle 0), as placed nominally."""
        w, h = self.size_m
        R = rot_y(math.radians(self.yaw_deg)) @ self.tilt_rotation() @ BOARD_R0
        centre = np.array([self.offset_m[0], self.height_m, self.offset_m[1]])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ np.array([w / 2, h / 2, 0.0])
        return T


@dataclass(frozen=True, kw_only=True)
class BoardDetection:
    """ChArUco corners found in one image by :func:`detect_board`.

    Attributes
    ----------
    ids : (N,) int32 array
        ChArUco corner ids.
    image_points : (N, 2) float64 array
        Pixels, OpenCV convention (top-left pixel centre at 0, 0), in the image as given
        (or, when ``mirrored``, in the image flipped left-right).
    object_points : (N, 3) float64 array
        The corners on the board, metres (z = 0).
    n_markers : int
        ArUco markers decoded.
    inverted, legacy, mirrored : bool
        The variant that found the corners: negative print, legacy layout, image flipped
        left-right (a webcam's mirrored preview).
    upscale : int
        Resolution factor the corners were found at.
    marker_corners : (M, 4, 2) float64 array
        The decoded ArUco markers' corners, pixels, same frame as ``image_points``
        (what :func:`reinterpolate_board` and an ArUco-marker calibration start from).
    marker_ids : (M,) int32 array
    """

    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray
    n_markers: int = 0
    inverted: bool = False
    legacy: bool = False
    mirrored: bool = False
    upscale: int = 1
    variant_tries: tuple[str, ...] = field(default=())
    marker_corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 2)))
    marker_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def variant(self) -> str:
        """``normal``/``inverted`` + ``legacy`` + ``mirrored``, e.g. ``inverted+mirrored``."""
        parts = ["inverted" if self.inverted else "normal"]
        if self.legacy:
            parts.append("legacy")
        if self.mirrored:
            parts.append("mirrored")
        return "+".join(parts)


@functools.lru_cache(maxsize=16)
def _charuco_detector(spec: CharucoSpec, legacy: bool):
    import cv2

    board = spec.board(legacy=legacy)
    params = cv2.aruco.DetectorParameters()
    return board, cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(), params)


def _empty(n_markers: int = 0) -> BoardDetection:
    return BoardDetection(
        ids=np.zeros(0, np.int32), image_points=np.zeros((0, 2)), object_points=np.zeros((0, 3)), n_markers=n_markers
    )


def _detect_once(gray: np.ndarray, spec: CharucoSpec, *, legacy: bool, upscale: Sequence[int], max_upscaled_px: int):
    """Best (corners, ids, factor, n_markers, marker corners, marker ids) over the upscale
    factors of one variant."""
    import cv2

    board, det = _charuco_detector(spec, legacy)
    n_total = (spec.squares_x - 1) * (spec.squares_y - 1)
    best = (None, None, 1, 0, None, None)
    for f in upscale:
        f = int(f)
        if f < 1 or (f > 1 and max(gray.shape) * f > max_upscaled_px):
            continue
        g = gray if f == 1 else cv2.resize(gray, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
        corners, ids, mcorners, mids = det.detectBoard(g)
        n = 0 if ids is None or corners is None else len(ids)
        if n > (0 if best[1] is None else len(best[1])):
            best = (corners, ids, f, 0 if mids is None else len(mids), mcorners, mids)
        if n >= n_total:
            break
    return board, best


def _from_upscaled(points, f: int) -> np.ndarray:
    """Pixels of an image upscaled ``f`` times → the original's (OpenCV pixel centres)."""
    if points is None or len(points) == 0:
        return np.zeros((0, 2))
    p = np.concatenate([np.asarray(q, dtype=np.float64).reshape(-1, 2) for q in points])
    return (p + 0.5) / f - 0.5


def detect_board(
    gray,
    *,
    charuco: CharucoSpec,
    upscale: Sequence[int] = (1,),
    max_upscaled_px: int = 2048,
    try_mirrored: bool = False,
    prefer: BoardDetection | None = None,
) -> BoardDetection:
    """Find the ChArUco corners of ``charuco`` in one 8-bit image: the project's one detector
    (the turntable calibration phase and ``opacityhull calibrate`` both use it).

    Parameters
    ----------
    gray : (H, W) uint8 array
        The image (tone-mapped for linear captures).
    charuco : CharucoSpec
        The board; its ``polarity`` and ``layout`` say which prints to try.
    upscale : sequence of int
        Resolution factors (bicubic) tried in turn until every corner is found; markers
        of a few pixels per bit are found only on an upscaled image. Factors whose image
        would exceed ``max_upscaled_px`` on its long side are skipped.
    try_mirrored : bool
        Also search the image flipped left-right when no variant finds corners (webcam
        previews are often mirrored; the corners are then given in the flipped image).
    prefer : BoardDetection, optional
        A detection of an earlier frame of the same stream: its variant is tried first.

    Returns
    -------
    BoardDetection
        The variant finding the most corners (possibly none). ChArUco corners are refined
        to sub-pixel accuracy inside OpenCV's ``detectBoard`` (``cornerSubPix`` on the
        chessboard saddle, window from the marker size); the positions are mapped back
        from an upscaled image by ``x = (x_up + 0.5) / f − 0.5``.
    """
    g0 = np.ascontiguousarray(np.asarray(gray))
    if g0.dtype != np.uint8 or g0.ndim != 2:
        raise ConfigError(f"detect_board: expected an (H, W) uint8 image, got {g0.dtype} {g0.shape}")
    variants = [(inv, leg, False) for inv in charuco.polarities() for leg in charuco.layouts()]
    if try_mirrored:
        variants += [(inv, leg, True) for inv, leg, _ in list(variants)]
    if prefer is not None:
        key = (prefer.inverted, prefer.legacy, prefer.mirrored)
        if key in variants:
            variants.remove(key)
            variants.insert(0, key)
    n_total = (charuco.squares_x - 1) * (charuco.squares_y - 1)
    best: BoardDetection = _empty()
    tried: list[str] = []
    for inv, leg, mir in variants:
        if mir and len(best) > 0:
            break  # a mirrored search only when the image as given shows no board
        g = 255 - g0 if inv else g0
        if mir:
            g = np.ascontiguousarray(g[:, ::-1])
        board, (corners, ids, f, nm, mcorners, mids) = _detect_once(
            g, charuco, legacy=leg, upscale=upscale, max_upscaled_px=max_upscaled_px
        )
        tried.append(("inverted" if inv else "normal") + ("+legacy" if leg else "") + ("+mirrored" if mir else ""))
        n = 0 if ids is None or corners is None else len(ids)
        if n > len(best):
            # OpenCV's stub types detectedCorners as a sequence of arrays; the C++ takes
            # the one (N, 1, 2) array detectBoard returns for ChArUco corners.
            obj, img = board.matchImagePoints(corners, ids)  # pyright: ignore[reportCallIssue, reportArgumentType]
            img = (np.asarray(img, dtype=np.float64).reshape(-1, 2) + 0.5) / f - 0.5
            best = BoardDetection(
                ids=np.asarray(ids, dtype=np.int32).ravel(),
                image_points=img,
                object_points=np.asarray(obj, dtype=np.float64).reshape(-1, 3),
                n_markers=nm,
                inverted=inv,
                legacy=leg,
                mirrored=mir,
                upscale=f,
                marker_corners=_from_upscaled(mcorners, f).reshape(-1, 4, 2),
                marker_ids=np.asarray(mids, dtype=np.int32).ravel(),
            )
        if len(best) >= max(1, n_total // 2):
            break  # half the board or more: the other variants would find nothing better
    return replace(best, variant_tries=tuple(tried))


def marker_points(det: BoardDetection, charuco: CharucoSpec) -> tuple[np.ndarray, np.ndarray]:
    """The decoded markers' corners of ``det`` as (object (4M, 3) metres, image (4M, 2)
    pixels) pairs, for a calibration from ArUco marker corners (OpenCV's
    ``calibrateCameraAruco``)."""
    board = charuco.board(legacy=det.legacy)
    obj = {
        int(i): np.asarray(p, dtype=np.float64).reshape(4, 3)
        for i, p in zip(np.ravel(board.getIds()), board.getObjPoints(), strict=True)
    }
    keep = [k for k, i in enumerate(det.marker_ids) if int(i) in obj]
    if not keep:
        return np.zeros((0, 3)), np.zeros((0, 2))
    o = np.concatenate([obj[int(det.marker_ids[k])] for k in keep])
    return o, det.marker_corners[keep].reshape(-1, 2)


def reinterpolate_board(gray, det: BoardDetection, *, charuco: CharucoSpec, K, dist) -> BoardDetection:
    """The ChArUco corners of ``det`` found again through a camera model: OpenCV's
    interpolation with ``CharucoParameters.cameraMatrix`` set (the board pose from the
    decoded markers, the corners projected through ``K``/``dist``, then the same
    ``cornerSubPix``), as OpenCV's ``calibrate_camera_charuco`` sample does with the camera
    of a first calibration from the marker corners. Same variant, markers and upscale
    factor as ``det``; ``K``/``dist`` are for the image as ``det`` gives its pixels
    (flipped when ``det.mirrored``)."""
    import cv2

    g = np.ascontiguousarray(np.asarray(gray))
    if g.dtype != np.uint8 or g.ndim != 2:
        raise ConfigError(f"reinterpolate_board: expected an (H, W) uint8 image, got {g.dtype} {g.shape}")
    if len(det.marker_ids) == 0:
        return det
    if det.inverted:
        g = 255 - g
    if det.mirrored:
        g = np.ascontiguousarray(g[:, ::-1])
    f = int(det.upscale)
    Kf = np.asarray(K, dtype=np.float64).copy()
    if f > 1:
        g = cv2.resize(g, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
        Kf[:2, :2] *= f
        Kf[:2, 2] = (Kf[:2, 2] + 0.5) * f - 0.5
    board = charuco.board(legacy=det.legacy)
    params = cv2.aruco.CharucoParameters()
    params.cameraMatrix = Kf
    params.distCoeffs = np.asarray(dist, dtype=np.float64).reshape(1, -1)
    detector = cv2.aruco.CharucoDetector(board, params, cv2.aruco.DetectorParameters())
    mc = [((m + 0.5) * f - 0.5).astype(np.float32).reshape(1, 4, 2) for m in det.marker_corners]
    corners, ids, _, _ = detector.detectBoard(g, markerCorners=mc, markerIds=det.marker_ids.reshape(-1, 1))
    if ids is None or corners is None or len(ids) == 0:
        return det
    obj, img = board.matchImagePoints(corners, ids)  # pyright: ignore[reportCallIssue, reportArgumentType]
    return replace(
        det,
        ids=np.asarray(ids, dtype=np.int32).ravel(),
        image_points=(np.asarray(img, dtype=np.float64).reshape(-1, 2) + 0.5) / f - 0.5,
        object_points=np.asarray(obj, dtype=np.float64).reshape(-1, 3),
    )


def tonemap_for_detection(image, *, percentile: float = 99.5) -> np.ndarray:
    """Linear float image → 8-bit sRGB-encoded luminance for the marker detector.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
        Linear values (C = 1..4; the first three channels are Rec.709 RGB, a fourth
        channel (alpha) is ignored). NaN counts as black, +Inf as white.
    percentile : float
        Luminance percentile mapped to white (robust against specular highlights).

    Returns
    -------
    (H, W) uint8 array.
    """
    from .imageio import srgb_encode

    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 3:
        if a.shape[2] >= 3:
            lum = 0.2126 * a[..., 0] + 0.7152 * a[..., 1] + 0.0722 * a[..., 2]
        elif a.shape[2] in (1, 2):
            lum = a[..., 0]
        else:
            raise ShapeError(f"image has shape {a.shape}, expected (H, W) or (H, W, 1..4)")
    elif a.ndim == 2:
        lum = a
    else:
        raise ShapeError(f"image has shape {a.shape}, expected (H, W) or (H, W, 1..4)")
    finite = np.isfinite(lum)
    scale = float(np.percentile(lum[finite], percentile)) if finite.any() else 0.0
    if not scale > 0:
        scale = float(lum[finite].max()) if finite.any() else 0.0
    if not scale > 0:  # nothing positive and finite: only +Inf shows
        return np.where(np.isposinf(lum), 255, 0).astype(np.uint8)
    v = np.where(finite, lum / scale, np.where(np.isposinf(lum), 1.0, 0.0))
    return np.round(srgb_encode(v) * 255.0).astype(np.uint8)


def laplacian_sharpness(gray, points=None, *, margin_px: float = 10.0) -> float:
    """Variance of the Laplacian of ``gray`` (a focus measure: a blurred frame has little
    high-frequency energy), over the bounding box of ``points`` (N, 2) plus a margin, or
    over the whole image."""
    import cv2

    g = np.asarray(gray)
    if points is not None and len(points):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        x0, y0 = np.floor(p.min(axis=0) - margin_px).astype(int)
        x1, y1 = np.ceil(p.max(axis=0) + margin_px).astype(int)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, g.shape[1]), min(y1, g.shape[0])
        if x1 - x0 >= 3 and y1 - y0 >= 3:
            g = g[y0:y1, x0:x1]
    return float(cv2.Laplacian(g, cv2.CV_64F).var())


@contextmanager
def single_threaded_solvers():
    """OpenCV's and the BLAS thread pools at one thread inside the block, so that a
    calibration repeats bit for bit. Measured on the tiny plan's session: with OpenCV's
    default threads, one ``calibrate_session`` in four gave another rig (K differing in
    the 12th digit: ``cv2.calibrateCamera`` sums its normal equations across threads in
    the order they finish); with one thread, 8 of 8 identical. BLAS is held at one thread
    too, or the refinement's products would depend on the machine's core count. The
    detection stays parallel (its results were identical in 8 of 8 runs: OpenCV merges
    the per-thread marker candidates in a fixed order)."""
    import cv2
    from threadpoolctl import threadpool_limits

    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(prev)
