"""caliscope's own calibration, ``camera_array.toml``: what a user bringing a caliscope
project compares ``opacityhull calibrate`` with, or holds its intrinsics from (caliscope's
``charuco.toml`` is read by :func:`opacityhull.calibrate.inputs.parse_board`).

One ``[cameras.N]`` table per camera with (among others) ``size = [w, h]``,
``matrix`` (3×3), ``distortions`` (OpenCV's k1, k2, p1, p2, k3), and, once caliscope has
posed the cameras, ``rotation`` (3×3) and ``translation`` (metres) mapping world points
into the camera: ``x_cam = R @ x_world + t``.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError


@dataclass(frozen=True, kw_only=True)
class CaliscopeCamera:
    """One camera of caliscope's ``camera_array.toml``.

    Attributes
    ----------
    index : int
        caliscope's camera id (the ``N`` of ``[cameras.N]``).
    size : (2,) int
        Image width, height, pixels.
    K : (3, 3) float64 array
        Intrinsics, pixels (OpenCV convention).
    dist : (5,) float64 array
        OpenCV's k1, k2, p1, p2, k3.
    R_cam_from_world : (3, 3) float64 array
    t_cam_from_world : (3,) float64 array
        Metres.
    """

    index: int
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    R_cam_from_world: np.ndarray
    t_cam_from_world: np.ndarray

    @property
    def centre_world(self) -> np.ndarray:
        """The camera centre ``-Rᵀ t`` in caliscope's world frame, metres, (3,)."""
        return -self.R_cam_from_world.T @ self.t_cam_from_world


def read_camera_array(path: Path) -> dict[int, CaliscopeCamera]:
    """The posed cameras of caliscope's ``camera_array.toml``, by camera id (ascending).

    Raises
    ------
    FormatError
        ``path`` is missing or not TOML, has no ``[cameras.N]`` table, or a camera lacks
        one of ``size``, ``matrix``, ``distortions``, ``rotation``, ``translation`` (an
        unposed camera) or has one of the wrong shape.
    """
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise FormatError(f"{path}: no such file (caliscope's camera_array.toml)") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise FormatError(f"{path}: cannot be read as TOML ({e})") from None
    tables = doc.get("cameras")
    if not isinstance(tables, dict) or not tables:
        raise FormatError(f"{path}: no [cameras.N] tables (is it caliscope's camera_array.toml?)")
    shapes = {"size": (2,), "matrix": (3, 3), "distortions": (5,), "rotation": (3, 3), "translation": (3,)}
    out: dict[int, CaliscopeCamera] = {}
    for key in sorted(tables, key=lambda k: int(k) if str(k).isdigit() else -1):
        if not str(key).isdigit() or not isinstance(tables[key], dict):
            raise FormatError(f"{path}: [cameras.{key}]: expected a table named by the camera id")
        t = tables[key]
        arr = {}
        for k, shape in shapes.items():
            if k not in t:
                raise FormatError(
                    f"{path}: [cameras.{key}] has no {k} (caliscope writes it once the cameras are posed)"
                )
            try:
                a = np.array(t[k], dtype=np.float64)
            except (TypeError, ValueError):
                a = None
            if a is None or a.shape != shape:
                raise FormatError(f"{path}: [cameras.{key}] {k} = {t[k]!r}: expected numbers of shape {shape}")
            arr[k] = a
        i = int(key)
        out[i] = CaliscopeCamera(
            index=i,
            size=(int(arr["size"][0]), int(arr["size"][1])),
            K=np.array(t["matrix"]),
            dist=np.array(t["distortions"]),
            R_cam_from_world=np.array(t["rotation"]),
            t_cam_from_world=np.array(t["translation"]),
        )
    return out
