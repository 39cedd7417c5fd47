"""Per-surfel samples of the opacity light field: what each captured view saw of each surfel.

Shared by every export that turns the surfel model into coloured points or splats and by
the fitting's start colours (:mod:`opacityhull.optimize.data`), hence in the core: the
visibility bits say which views saw a surfel (depth-tested), and the surfel's projection
into such a view gives the colour and alpha the view recorded there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from collections.abc import Iterator, Sequence

import numpy as np

from .camera import Camera
from .model import Surfels

log = logging.getLogger(__name__)

__all__ = ["ViewSamples", "iter_view_samples", "mean_colours"]


@dataclass(frozen=True)
class ViewSamples:
    """What view ``view`` recorded of the surfels ``index``.

    Attributes
    ----------
    view : int, view index (bit order).
    index : (n,) int64, surfel indices seen by the view and projecting inside it.
    uv : (n, 2) float64, pixel positions (OpenCV: top-left pixel centre at (0, 0)).
    rgba : (n, 4) float32, straight linear colour and alpha (bilinear over premultiplied
        texels, so colour does not bleed from the background across the matte edge).
    dirs : (n, 3) float64, unit directions from the view's centre to the surfel
        (the 3DGS convention for evaluating view-dependent colour).
    """

    view: int
    index: np.ndarray
    uv: np.ndarray
    rgba: np.ndarray
    dirs: np.ndarray


def _bilinear_premul(img_straight: np.ndarray, uv: np.ndarray) -> np.ndarray:
    import cv2

    pre = np.ascontiguousarray(img_straight, dtype=np.float32).copy()
    pre[..., :3] *= pre[..., 3:4]
    # cv2.remap refuses maps of 32767 columns or more: lay the samples out in rows
    n = len(uv)
    cols = max(1, min(n, 4096))
    rows = -(-n // cols)
    pad = np.zeros((rows * cols, 2), np.float32)
    pad[:n] = uv
    mx = np.ascontiguousarray(pad[:, 0].reshape(rows, cols))
    my = np.ascontiguousarray(pad[:, 1].reshape(rows, cols))
    out = cv2.remap(pre, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 4)[:n]
    a = out[:, 3:4]
    out[:, :3] = np.where(a > 1e-6, out[:, :3] / np.maximum(a, 1e-6), 0.0)
    return out


def iter_view_samples(
    surfels: Surfels, cameras: Sequence[Camera], images: Sequence[np.ndarray], *, subset: np.ndarray | None = None
) -> Iterator[ViewSamples]:
    """Yield the samples of every view in turn.

    Parameters
    ----------
    surfels : the model's surfels (N, visibility over V views).
    cameras : V view cameras (object frame).
    images : V straight RGBA images (H_v, W_v, 4) float32.
    subset : optional (M,) int indices of the surfels to sample (default all).
    """
    idx_all = np.arange(len(surfels)) if subset is None else np.asarray(subset, np.int64)
    pos = surfels.positions[idx_all].astype(np.float64)
    for v, (cam, img) in enumerate(zip(cameras, images, strict=True)):
        seen = ((surfels.visibility[idx_all, v // 8] >> (v % 8)) & 1).astype(bool)
        if not seen.any():
            continue
        p = pos[seen]
        uv, z = cam.project(p)
        ok = (z > 0) & cam.in_image(uv, margin=0.0) & np.all(np.isfinite(uv), axis=1)
        if not ok.any():
            continue
        p, uv = p[ok], uv[ok]
        d = p - cam.centre_world
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        yield ViewSamples(v, idx_all[seen][ok], uv, _bilinear_premul(img, uv), d)


def mean_colours(surfels: Surfels, cameras, images) -> tuple[np.ndarray, np.ndarray]:
    """Mean straight colour (weighted by alpha · cos² θ) and mean alpha (weighted by cos² θ)
    per surfel over the views that see it; θ is the angle between the surfel's normal and
    the ray to the view, so grazing views (silhouette pixels) count least.

    Returns
    -------
    rgb : (N, 3) float32 linear straight colour (0 where no view sees the surfel).
    alpha : (N,) float32 mean alpha (0 where unseen).
    Surfels no view sees get rgb = alpha = 0.
    """
    n = len(surfels)
    acc = np.zeros((n, 3))
    asum = np.zeros(n)
    cnt = np.zeros(n)
    nrm = surfels.normals.astype(np.float64)
    for s in iter_view_samples(surfels, cameras, images):
        # grazing views see the surfel over a silhouette pixel mixed with background:
        # weight each sample by the cosine between the normal and the ray to the camera
        cos = np.clip(-np.sum(nrm[s.index] * s.dirs, axis=1), 0.0, 1.0) ** 2
        a = s.rgba[:, 3].astype(np.float64)
        np.add.at(acc, s.index, s.rgba[:, :3] * (a * cos)[:, None])
        np.add.at(asum, s.index, a * cos)
        np.add.at(cnt, s.index, cos)
    rgb = np.where(asum[:, None] > 0, acc / np.maximum(asum, 1e-12)[:, None], 0.0)
    alpha = np.where(cnt > 0, asum / np.maximum(cnt, 1e-12), 0.0)
    return rgb.astype(np.float32), alpha.astype(np.float32)
