"""The fitting's inputs, read from a built model directory: the training views'
photographs (display-space colour over black, and the matte), their cameras as
pinholes at the training resolution, and the hull's surfels with their start colour."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import srgb_encode
from ..model import OpacityHullModel, Surfels

__all__ = ["TrainView", "FitData", "display_target", "scaled_camera", "load_fit_data", "model_fingerprint"]


@dataclass(frozen=True)
class TrainView:
    """One training view.

    index : the view's index in the model.
    camera : the pinhole camera at the training resolution (no distortion).
    target : (H, W, 3) float32, the photograph's colour × matte, sRGB-encoded (what
        ``eval`` compares: premultiplied over black, in display space).
    alpha : (H, W) float32, the matte.
    """

    index: int
    camera: Camera
    target: np.ndarray
    alpha: np.ndarray


@dataclass(frozen=True)
class FitData:
    views: list[TrainView]
    surfels: Surfels
    sh_dc: np.ndarray  # (N, 3) start colour as SH DC (display space, ½ offset removed)
    fingerprint: str


def display_target(rgba_straight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 4) straight linear RGBA → (display colour over black (H, W, 3), α (H, W)),
    the same image :func:`opacityhull.evaluate.loo.loo_metrics` scores."""
    a = np.clip(np.nan_to_num(rgba_straight[..., 3]), 0.0, 1.0).astype(np.float32)
    rgb = np.nan_to_num(rgba_straight[..., :3]) * a[..., None]
    return srgb_encode(np.clip(rgb, 0.0, 1.0)), a


def scaled_camera(cam: Camera, scale: float) -> Camera:
    """``cam`` resampled by ``scale`` (pixel centres: u' = (u + ½)·s − ½), distortion dropped."""
    if scale == 1.0:
        return Camera(K=cam.K, width=cam.width, height=cam.height, world_from_cam=cam.world_from_cam, name=cam.name)
    K = cam.K.copy()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
    w = max(1, int(round(cam.width * scale)))
    h = max(1, int(round(cam.height * scale)))
    return Camera(K=K, width=w, height=h, world_from_cam=cam.world_from_cam, name=cam.name)


def model_fingerprint(model_dir: Path) -> str:
    """sha256 of the model's ``model.toml`` and ``surfels.ply``: what a checkpoint must
    have been fitted from."""
    h = hashlib.sha256()
    for name in ("model.toml", "surfels.ply"):
        p = Path(model_dir) / name
        h.update(name.encode())
        h.update(p.read_bytes() if p.is_file() else b"")
    return h.hexdigest()


def _undistorted(img: np.ndarray, cam: Camera) -> np.ndarray:
    if not np.any(cam.dist != 0):
        return img
    import cv2

    return cv2.undistort(img, cam.K, cam.dist)


def load_fit_data(
    model_dir: Path, train_views: Sequence[int], *, train_scale: float = 1.0, start_surface: str = "hull"
) -> FitData:
    """Read the training views and the start surfels of the model at ``model_dir``.

    The start colour is the SH DC of :func:`opacityhull.sh.fit_sh` at degree 0
    over the training views only (the mean visible colour, cos²-weighted, in display
    space), sampled on the hull or, with ``start_surface="refined"``, at the surfels'
    photo-consistent depth; surfels no training view saw start mid-grey.
    """
    import cv2

    from ..sh import fit_sh

    model = OpacityHullModel.open(model_dir)
    V = len(model.views)
    idx = [int(i) for i in train_views]
    if not idx:
        raise InputError(f"{model_dir}: no training views given")
    bad = [i for i in idx if not 0 <= i < V]
    if bad:
        raise InputError(f"{model_dir}: training views {bad[:5]} are not indices of the model's {V} views")
    if len(set(idx)) != len(idx):
        raise InputError(f"{model_dir}: training views listed twice")
    surfels = model.surfels
    views: list[TrainView] = []
    straight = []
    for i in idx:
        rgba = model.load_view_rgba(i)
        cam = model.views[i].camera
        straight.append(rgba)
        und = _undistorted(rgba, cam)
        tgt, a = display_target(und)
        cam_t = scaled_camera(cam, train_scale)
        if train_scale != 1.0:
            tgt = cv2.resize(tgt, (cam_t.width, cam_t.height), interpolation=cv2.INTER_AREA)
            a = cv2.resize(a, (cam_t.width, cam_t.height), interpolation=cv2.INTER_AREA)
        views.append(TrainView(i, cam_t, np.ascontiguousarray(tgt, np.float32), np.ascontiguousarray(a, np.float32)))
    vis = surfels.visible_bool()[:, idx]
    pos = surfels.shading_positions() if start_surface == "refined" else surfels.positions
    sub = Surfels.from_bool(pos, surfels.normals, surfels.radii, vis)
    fit = fit_sh(sub, [model.views[i].camera for i in idx], straight, degree=0)
    sh_dc = fit.coeffs[:, 0, :].astype(np.float32)
    return FitData(views, surfels, sh_dc, model_fingerprint(model_dir))
