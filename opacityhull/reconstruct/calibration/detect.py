"""Step 1 of the calibration: ChArUco corners in linear images, and which views can be used.

Linear float images are tone-mapped to 8 bit (luminance / high percentile, sRGB
encoding) and searched by the project's one detector, :func:`opacityhull.charuco.detect_board`
(OpenCV 5's ``CharucoDetector.detectBoard`` → ``board.matchImagePoints``, both print
polarities and layouts the board spec allows, sub-pixel corners). Views with too few corners, or whose corners are (nearly)
collinear on the board or in the image, are dropped with the reason recorded (collinear
corners make ``cv2.calibrateCamera`` assert).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from ...charuco import BoardDetection, CharucoSpec, detect_board, marker_points, tonemap_for_detection
from ...errors import ShapeError
from ...riggeometry import view_id
from .config import CalibrationConfig

__all__ = [
    "CharucoObservation",
    "tonemap_for_detection",
    "detect_charuco",
    "detection_gray",
    "observation_from",
    "marker_observation",
    "screen_observation",
]


@dataclass(frozen=True)
class CharucoObservation:
    """Detected ChArUco corners of one view (camera ``camera`` at ``table_deg``).

    Attributes
    ----------
    camera : int
        Physical camera index.
    table_deg : float
        Turntable angle in degrees.
    ids : (N,) int array
        ChArUco corner ids.
    image_points : (N, 2) float array
        Corner positions in pixels (OpenCV convention: top-left pixel centre = (0, 0)).
    object_points : (N, 3) float array
        The same corners in the board frame, metres (z = 0).
    """

    camera: int
    table_deg: float
    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray

    def __post_init__(self):
        ids = np.asarray(self.ids, dtype=np.int32).ravel()
        ip = np.asarray(self.image_points, dtype=np.float64).reshape(-1, 2)
        op = np.asarray(self.object_points, dtype=np.float64).reshape(-1, 3)
        if not (ids.shape[0] == ip.shape[0] == op.shape[0]):
            raise ShapeError(
                f"observation {self.view}: {ids.shape[0]} ids, {ip.shape[0]} image points and "
                f"{op.shape[0]} object points; expected the same count"
            )
        object.__setattr__(self, "camera", int(self.camera))
        object.__setattr__(self, "table_deg", float(self.table_deg))
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "image_points", ip)
        object.__setattr__(self, "object_points", op)

    @property
    def view(self) -> str:
        return view_id(self.camera, self.table_deg)

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def detect_charuco(
    image,
    *,
    charuco: CharucoSpec,
    camera: int = 0,
    table_deg: float = 0.0,
    percentile: float = 99.5,
    upscale: Sequence[int] = (1, 2, 3),
    max_upscaled_px: int = 2048,
) -> CharucoObservation:
    """Detect the ChArUco corners of ``charuco`` in one image.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
        Linear float image (or already 8-bit: uint8 images are used as they are).
    charuco : CharucoSpec
        The board.
    camera, table_deg : the view the image belongs to (copied into the result).
    percentile : tone-mapping white point, see :func:`tonemap_for_detection`.
    upscale : sequence of int
        Resolution factors tried in turn (bicubic) until every corner of the board is
        found; the factor finding the most corners wins. Markers of a few pixels per bit
        (small boards, low-resolution cameras, grazing views) are found only on an
        upscaled image. Factors whose image would exceed ``max_upscaled_px`` on its long
        side are skipped.

    Returns
    -------
    CharucoObservation
        Corner positions in the original image's pixels; possibly zero corners.
    """
    gray = detection_gray(image, percentile=percentile)
    det = detect_board(gray, charuco=charuco, upscale=upscale, max_upscaled_px=max_upscaled_px)
    return observation_from(det, camera=camera, table_deg=table_deg)


def detection_gray(image, *, percentile: float = 99.5) -> np.ndarray:
    """The (H, W) uint8 image the detector searches: a linear float image tone-mapped
    (:func:`tonemap_for_detection`), an 8-bit one as it is (channels averaged)."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return (
            a if a.ndim == 2 else (a[..., :3].mean(axis=2).round().astype(np.uint8) if a.shape[2] >= 3 else a[..., 0])
        )
    return tonemap_for_detection(a, percentile=percentile)


def observation_from(det: BoardDetection, *, camera: int, table_deg: float) -> CharucoObservation:
    """The ChArUco corners of ``det`` as the observation of view (``camera``, ``table_deg``)."""
    return CharucoObservation(camera, table_deg, det.ids, det.image_points, det.object_points)


def marker_observation(
    det: BoardDetection, *, charuco: CharucoSpec, camera: int, table_deg: float
) -> CharucoObservation:
    """The decoded ArUco markers' corners of ``det`` as an observation (ids 0..4M-1, not
    ChArUco corner ids): what a first calibration from marker corners fits
    (:func:`opacityhull.charuco.marker_points`)."""
    obj, img = marker_points(det, charuco)
    return CharucoObservation(camera, table_deg, np.arange(len(obj)), img, obj)


def _minor_std(points2: np.ndarray) -> float:
    """Standard deviation along the minor principal axis of a 2-D point set."""
    if points2.shape[0] < 2:
        return 0.0
    c = np.cov(points2.T)
    return float(math.sqrt(max(np.linalg.eigvalsh(c)[0], 0.0)))


def screen_observation(
    obs: CharucoObservation, *, charuco: CharucoSpec, config: CalibrationConfig = CalibrationConfig()
) -> str | None:
    """Why ``obs`` cannot be used for calibration, or None when it can.

    Checks the corner count, finiteness, collinearity on the board (minor-axis spread
    of the object points, in squares) and in the image (board seen edge-on).
    """
    n = len(obs)
    if n == 0:
        return "no ChArUco corners detected"
    if n < config.min_corners:
        return f"only {n} corners detected (min_corners={config.min_corners})"
    if not (np.all(np.isfinite(obs.image_points)) and np.all(np.isfinite(obs.object_points))):
        return "non-finite corner coordinates"
    spread = _minor_std(obs.object_points[:, :2]) / charuco.square_m
    if spread < config.min_spread_squares:
        return (
            f"corners (nearly) collinear on the board: minor-axis spread {spread:.3f} squares "
            f"< min_spread_squares={config.min_spread_squares}"
        )
    ispread = _minor_std(obs.image_points)
    if ispread < config.min_image_spread_px:
        return (
            f"corners (nearly) collinear in the image (board seen edge-on): minor-axis spread "
            f"{ispread:.2f} px < min_image_spread_px={config.min_image_spread_px}"
        )
    return None
