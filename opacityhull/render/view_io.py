"""The model's views as the renderer reads them: packed once per model into a texel
buffer that is memory-mapped from an unlinked temporary file (:func:`prepare_model_views`),
and the views' mattes with their opaque part dilated (:func:`dilated_matte_views`,
the pixel driver's opaque interior), mapped the same way with the source pages released
(``madvise``) as they are read."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..model import OpacityHullModel
from .views import PreparedViews, prepare_views

__all__ = ["OPAQUE_MATTE", "dilated_matte_views", "prepare_model_views"]


def prepare_model_views(model: OpacityHullModel, *, mapped: bool = True) -> PreparedViews:
    """Pack all views of a model once (for several frames), texel for texel what
    ``prepare_views(cameras, model.load_views_premul())`` packs.

    ``mapped`` (default): the views are read one at a time (each view's file decoded,
    converted to float32 and its non-finite texels zeroed) into an unlinked temporary
    file that the texel buffer memory-maps (copy-on-write). A frame then makes resident
    only the pages of the views its surfels sample (the k nearest of each), so a
    432-view model costs what the views one frame needs cost, not 432 float32 images;
    the OS drops the pages again under memory pressure. ``mapped=False`` holds them in
    memory (the eager path; the images are equal)."""
    cams = [v.camera for v in model.views]
    if not mapped:
        return prepare_views(cams, model.load_views_premul())
    from dataclasses import replace

    pv = prepare_views(cams)  # cameras, offsets and tie ranks; no texels
    texels, bad = _mapped_texels(model, cams, pv.offsets)
    return replace(pv, texels=texels, nonfinite_texels=bad)


def _mapped_texels(model: OpacityHullModel, cams: Sequence[Camera], offsets: np.ndarray) -> tuple[np.ndarray, int]:
    """(P, 4) float32 texels of every view in a memory-mapped temporary file, written one
    view at a time, and the number of non-finite values replaced by 0."""
    from ..errors import ShapeError

    total = int(sum(c.width * c.height for c in cams))
    bad = 0

    def rows():
        nonlocal bad
        for v, c in enumerate(cams):
            a = model.load_views_premul([v])[0]
            if a.shape != (c.height, c.width, 4):
                raise ShapeError(
                    f"view {v} ({c.name or 'unnamed'}) RGBA has shape {a.shape}, expected ({c.height}, {c.width}, 4)"
                )
            t = np.ascontiguousarray(a.reshape(-1, 4), np.float32)
            del a
            fin = np.isfinite(t)
            if not fin.all():
                t = t.copy() if not t.flags.writeable else t
                bad += int((~fin).sum())
                t[~fin] = 0.0
            yield int(offsets[v]), t

    return _map_texel_rows(total, rows()), bad


def _map_texel_rows(total: int, rows) -> np.ndarray:
    """(total, 4) float32 texels in a memory-mapped temporary file, written from ``rows``
    (``(texel offset, (n, 4) float32)`` in order, one view at a time): the renderer's
    views stay out of the process's anonymous memory, whatever their number."""
    import mmap
    import tempfile

    if total == 0:
        return np.zeros((0, 4), np.float32)
    with tempfile.TemporaryFile(prefix="opacityhull-views-") as f:
        for off, t in rows:
            if f.tell() != off * 16:
                raise AssertionError("view offsets out of step with the texel file")
            f.write(np.ascontiguousarray(t, np.float32).data.cast("B"))
        f.flush()
        # copy-on-write: writable like an ordinary array (the kernels' signatures are
        # those of in-memory texels: no recompilation), never written back to the file
        mm = mmap.mmap(f.fileno(), total * 16, access=mmap.ACCESS_COPY)
    return np.ndarray((total, 4), dtype=np.float32, buffer=mm)


_DILATED_CACHE: dict = {}

OPAQUE_MATTE = 0.99
"""A view's matte α from which it counts as opaque (:func:`dilated_matte_views`)."""


def dilated_matte_views(pv: PreparedViews, radius_px: int, *, opaque: float = OPAQUE_MATTE) -> PreparedViews:
    """``pv`` with every texel's four channels replaced by its view's matte α, or 1
    where the matte is opaque (α ≥ ``opaque``) within a disc of ``radius_px``: what a
    view's matte says once the carve's silhouette dilation is allowed for. Only the
    opaque part grows; fractional mattes (fur, glass) keep their values. Cached for the
    last ``pv`` (one model renders many frames)."""
    import mmap
    from dataclasses import replace

    import cv2

    key = (id(pv.texels), int(radius_px), float(opaque))
    hit = _DILATED_CACHE.get("last")
    if hit is not None and hit[0] == key and hit[1] is pv.texels:
        return hit[2]
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))

    src = pv.texels.base if isinstance(pv.texels.base, mmap.mmap) else None

    def rows():
        for v in range(pv.n_views):
            w, h = int(pv.sizes[v, 0]), int(pv.sizes[v, 1])
            o = int(pv.offsets[v])
            a = np.array(pv.texels[o : o + w * h, 3]).reshape(h, w)
            if src is not None:
                # every view's pages were just read: unmap them again (clean private file
                # pages — nothing writes the texels — come back from the page cache when a
                # frame uses the view), so the renderer's RSS stays flat in the views
                lo = -(-o * 16 // mmap.PAGESIZE) * mmap.PAGESIZE
                hi = (o + w * h) * 16 // mmap.PAGESIZE * mmap.PAGESIZE
                if hi > lo:
                    src.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
            b = (a >= opaque).astype(np.uint8)
            d = np.maximum(a, cv2.dilate(b, k) if radius_px > 0 else b)
            yield o, np.repeat(d.reshape(-1, 1).astype(np.float32), 4, axis=1)

    if src is not None:  # mapped views (the default): map these too
        tex = _map_texel_rows(int(pv.texels.shape[0]), rows())
    else:
        tex = np.empty_like(pv.texels)
        for o, t in rows():
            tex[o : o + t.shape[0]] = t
    out = replace(pv, texels=tex)
    _DILATED_CACHE["last"] = (key, pv.texels, out)
    return out
