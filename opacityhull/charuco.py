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

import math
from dataclasses import asdict, dataclass

import numpy as np

from .camera import rot_y
from .errors import ConfigError

__all__ = ["CharucoSpec", "BOARD_R0", "rot_x"]

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

    @classmethod
    def from_dict(cls, d: dict, where: str = "charuco") -> "CharucoSpec":
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
        """Every field, as :meth:`from_dict` reads it back (``offset_m`` a list, for TOML/JSON)."""
        return {**asdict(self), "offset_m": list(self.offset_m)}

    @property
    def size_m(self) -> tuple[float, float]:
        return (self.squares_x * self.square_m, self.squares_y * self.square_m)

    def board(self):
        """The ``cv2.aruco.CharucoBoard``."""
        import cv2

        name = self.dictionary
        if not hasattr(cv2.aruco, name):
            raise ConfigError(f"charuco.dictionary: unknown ArUco dictionary {name!r}")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)

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
