"""Captured views packed for the kernels: cameras as rows of numbers, all premultiplied
RGBA images in one texel buffer, and the per-frame scan order of the ULR search."""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError, ShapeError

__all__ = ["PreparedViews", "prepare_views", "pack_camera", "scan_order"]


def pack_camera(cam: Camera, *, ignore_distortion: bool = False) -> np.ndarray:
    """``float64[21]`` row: cam_from_world R (row-major), t, fx, fy, cx, cy, k1, k2, p1, p2, k3."""
    T = cam.cam_from_world
    row = np.zeros(21)
    row[0:9] = T[:3, :3].ravel()
    row[9:12] = T[:3, 3]
    row[12:16] = (cam.fx, cam.fy, cam.cx, cam.cy)
    if not ignore_distortion:
        row[16:21] = cam.dist
    return row


@dataclass(frozen=True, eq=False)
class PreparedViews:
    """Captured views in kernel form. Build with :func:`prepare_views` once and reuse
    across frames (an orbit, a leave-one-out sweep): packing copies every image.

    Attributes
    ----------
    cameras : list of the V :class:`Camera` objects.
    cams : (V, 21) float64 packed cameras (see :func:`pack_camera`).
    centres : (V, 3) float64 camera centres, object frame, metres.
    sizes : (V, 2) int64 (width, height).
    offsets : (V,) int64 first texel of each view in ``texels``.
    texels : (P, 4) float32 premultiplied RGBA of all views, row-major per view
        (empty when prepared without images).
    tie_rank : (V,) int64 rank of each view when sorted by centre (x, y, z), then index:
        breaks exact angle ties independently of the order of the views.
    nonfinite_texels : number of NaN/Inf texel values replaced by 0.
    """

    cameras: list
    cams: np.ndarray
    centres: np.ndarray
    sizes: np.ndarray
    offsets: np.ndarray
    texels: np.ndarray
    tie_rank: np.ndarray
    nonfinite_texels: int = 0

    @property
    def n_views(self) -> int:
        return self.cams.shape[0]

    @property
    def has_images(self) -> bool:
        return self.texels.shape[0] > 0

    def image(self, v: int) -> np.ndarray:
        """(H, W, 4) premultiplied RGBA of view ``v`` (a view into the texel buffer)."""
        w, h = self.sizes[v]
        o = self.offsets[v]
        return self.texels[o : o + w * h].reshape(h, w, 4)


def prepare_views(
    view_cameras: Sequence[Camera], view_rgba_premul: Sequence[np.ndarray] | None = None
) -> PreparedViews:
    """Pack cameras and (optionally) premultiplied RGBA images.

    Parameters
    ----------
    view_cameras : V cameras (object frame).
    view_rgba_premul : V arrays (H_v, W_v, 4), premultiplied, matching each camera's
        size; or None to pack cameras only (enough for :func:`ulr_weights`).

    Non-finite texels (NaN, ±Inf) are replaced by 0 and counted, so that one bad pixel
    cannot poison every surfel that blends it.
    """
    cams = list(view_cameras)
    if not cams:
        raise InputError("no views: at least one captured view is needed to render")
    V = len(cams)
    packed = np.stack([pack_camera(c) for c in cams])
    centres = np.stack([c.centre_world for c in cams])
    sizes = np.array([[c.width, c.height] for c in cams], dtype=np.int64)
    npx = sizes[:, 0] * sizes[:, 1]
    offsets = np.zeros(V, np.int64)
    offsets[1:] = np.cumsum(npx)[:-1]
    bad = 0
    if view_rgba_premul is not None:
        imgs = list(view_rgba_premul)
        if len(imgs) != V:
            raise InputError(f"{len(imgs)} view images for {V} view cameras")
        texels = np.empty((int(npx.sum()), 4), np.float32)
        for v, (c, img) in enumerate(zip(cams, imgs, strict=True)):
            a = np.asarray(img)
            if a.shape != (c.height, c.width, 4):
                raise ShapeError(
                    f"view {v} ({c.name or 'unnamed'}) RGBA has shape {a.shape}, expected ({c.height}, {c.width}, 4)"
                )
            dst = texels[offsets[v] : offsets[v] + npx[v]]
            dst[:] = a.reshape(-1, 4)
            fin = np.isfinite(dst)
            if not fin.all():
                bad += int((~fin).sum())
                dst[~fin] = 0.0
    else:
        texels = np.zeros((0, 4), np.float32)
    keys = np.lexsort((np.arange(V), centres[:, 2], centres[:, 1], centres[:, 0]))
    tie_rank = np.empty(V, np.int64)
    tie_rank[keys] = np.arange(V)
    return PreparedViews(cams, packed, centres, sizes, offsets, texels, tie_rank, bad)


def scan_order(centres: np.ndarray, desired_centre, cloud_centre, cloud_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame scan order of the views for the ULR search and a lower bound of each
    view's ``s = 1 − cos θ`` valid for every surfel within ``cloud_radius`` of
    ``cloud_centre``.

    The angle at a surfel p between the rays to the desired centre C and to a view centre
    C_v differs from the same angle at the cloud centre o by at most
    ``asin(ρ/|C − o|) + asin(ρ/|C_v − o|)`` (the segment o–p subtends at most
    ``asin(ρ/D)`` from a point at distance D). Views sorted by that lower bound let the
    per-surfel search stop as soon as the next bound exceeds its current k-th best:
    exact, and with a rig far from a small object it visits only the few views near the
    desired direction.

    Returns
    -------
    order : (V,) int64 view indices by ascending bound. s_lb : (V,) float64 bounds in that order.
    """
    C = np.asarray(desired_centre, dtype=np.float64)
    o = np.asarray(cloud_centre, dtype=np.float64)
    rho = float(cloud_radius)
    a = C - o
    b = centres - o
    da = float(np.linalg.norm(a))
    db = np.linalg.norm(b, axis=1)

    def spread(dist):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(dist > rho, np.arcsin(np.clip(rho / np.maximum(dist, 1e-300), 0.0, 1.0)), math.pi)

    if da <= 0 or not math.isfinite(da):
        lb = np.zeros(len(centres))
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            cos = (b @ a) / (db * da)
        theta = np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))
        theta = np.where(db > 0, theta, 0.0)
        lb = theta - spread(np.array(da)) - spread(db) - 1e-7
        lb = np.clip(np.nan_to_num(lb, nan=0.0), 0.0, math.pi)
    s_lb = np.maximum(1.0 - np.cos(lb) - 1e-12, 0.0)
    order = np.argsort(s_lb, kind="stable")
    return order.astype(np.int64), s_lb[order]
