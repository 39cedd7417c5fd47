"""The holes of imported masks judged by the photograph: see-through holes (carved like
the contour), shadow holes (filled in the views' alpha), bright extensions (doubted by
a tolerant carve), and the strong silhouette they make."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import cast
from collections.abc import Iterator, Sequence

import numpy as np

from ..errors import InputError
from ..model import FILLED_HOLES, write_hole_masks
from ..session import Session
from .buildconfig import BuildConfig, _is_rig_session, default_carve_tolerance
from .buildstore import _StepStore
from .hull import backdrop_holes, bright_extensions, enclosed_holes
from .lazyviews import Mattes, PackedMasks
from .matte_step import _rgb

log = logging.getLogger(__name__)

#: :func:`bright_extension_masks`: how far beyond the outline to look, as a fraction of
#: the object's size in pixels (the square root of its mask area; the dino's plates
#: stick out 5-16 px at ~250 px), the opening's radius (px: the glow's width) and the
#: brightness limit between backdrop (0) and object (1). Measured on the dino at every
#: 4th view: margin 0.15 / 0.2 / 0.25 / 0.35 -> geometry holdout 18.32 / 18.39 / 18.36 /
#: 18.06 dB (17.95 without); 0.08 doubts the whole glow band (147 k px) and loses 0.17 dB
BRIGHT_REACH_FRAC = 0.06
BRIGHT_OPEN_PX = 3
BRIGHT_MARGIN = 0.2


def hole_masks(alpha: np.ndarray, photo_rgb: np.ndarray, *, threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """``(open, shadow)``, (H, W) bool each: a view's mask's enclosed holes (α ≤
    ``threshold``) split by the raw photograph's luminance in display values
    (:func:`.hull.backdrop_holes`): those that show the backdrop (see-through gaps, to
    carve) and the others (shadows as dark as the backdrop, which a threshold lost).
    Neither depends on the other holes being filled: the judgement is each hole's own
    brightness against the backdrop outside the outer contour."""
    sil = np.asarray(alpha) > threshold
    lum = _display_luminance(photo_rgb)
    filled = enclosed_holes(sil)
    open_ = filled & ~backdrop_holes(sil, lum)
    return open_, filled & ~sil & ~open_


def _display_luminance(photo_rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 luminance in display values (0-1) of a linear RGB photograph."""
    rgb = np.nan_to_num(np.asarray(photo_rgb, np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32), 0.0, None) ** (1.0 / 2.2)


def bright_extension_masks(
    alpha: np.ndarray,
    photo_rgb: np.ndarray,
    *,
    threshold: float = 0.5,
    reach_frac: float = BRIGHT_REACH_FRAC,
    open_px: int = BRIGHT_OPEN_PX,
    margin: float = BRIGHT_MARGIN,
) -> np.ndarray:
    """(H, W) bool: the thick bright extensions of a view's mask (α > ``threshold``;
    :func:`.hull.bright_extensions` on the raw photograph's display luminance), looked for
    within ``ceil(reach_frac * sqrt(A))`` px of an object of A mask pixels (holes
    filled). A tolerant carve doubts them like the shadow holes
    (``BuildConfig.doubt_bright_extensions``)."""
    sil = np.asarray(alpha) > threshold
    if not reach_frac >= 0:
        raise InputError(f"bright_extension_masks: reach_frac must be >= 0, got {reach_frac}")
    r = int(math.ceil(reach_frac * math.sqrt(float(enclosed_holes(sil).sum())) - 1e-9))
    return bright_extensions(sil, _display_luminance(photo_rgb), reach_px=r, open_px=open_px, margin=margin)


def open_hole_masks(alpha: np.ndarray, photo_rgb: np.ndarray, *, threshold: float = 0.5) -> np.ndarray:
    """The see-through holes of :func:`hole_masks`: carved like the outer contour."""
    return hole_masks(alpha, photo_rgb, threshold=threshold)[0]


def shadow_hole_masks(alpha: np.ndarray, photo_rgb: np.ndarray, *, threshold: float = 0.5) -> np.ndarray:
    """The shadow holes of :func:`hole_masks`: the enclosed holes that do *not* show the
    backdrop."""
    return hole_masks(alpha, photo_rgb, threshold=threshold)[1]


def strong_silhouette(
    silhouette: np.ndarray, *, open_holes: np.ndarray | None = None, doubtful_extensions: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """The strong silhouette of a tolerant carve (:func:`.hull.carve_robust`), outside which a
    rejection is trusted: the silhouette with its enclosed holes filled, minus the holes
    that show the backdrop (``open_holes``), plus the outline's bright extensions
    (``doubtful_extensions``: doubted, not trusted). Returns it ((H, W) bool) and the
    number of extension pixels it added. The build applies it to each view's dilated
    silhouette before undistorting; ``benchmarks/outline.py`` to the stored pinhole ones."""
    t = enclosed_holes(np.asarray(silhouette, bool))
    if open_holes is not None:
        t &= ~np.asarray(open_holes, bool)
    n_ext = 0
    if doubtful_extensions is not None:
        db = np.asarray(doubtful_extensions, bool) & ~t
        n_ext = int(db.sum())
        t |= db
    return t, n_ext


class _HolesFilled(Sequence):
    """``alphas`` with each view's ``fill`` mask (:class:`PackedMasks`, entries may be
    None) set to 1 on access; one view at a time, like the alphas it wraps."""

    def __init__(self, alphas: Sequence, fill: PackedMasks):
        if len(alphas) != len(fill):
            raise InputError(f"_HolesFilled: {len(fill)} fill masks for {len(alphas)} alphas")
        self.alphas, self.fill = alphas, fill

    def __len__(self) -> int:
        return len(self.alphas)

    def __getitem__(self, i):
        if isinstance(i, slice):
            raise TypeError("_HolesFilled does not slice")
        a = self.alphas[i]
        m = cast("np.ndarray | None", self.fill[int(i)])
        if m is None or not m.any():
            return a
        a = np.array(a, np.float32, copy=True) if not (isinstance(a, np.ndarray) and a.flags.writeable) else a
        a[m] = 1.0
        return a

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[i] for i in range(len(self)))


def fill_shadow_holes(
    session: Session,
    mattes: Mattes,
    colour: Sequence,
    vids: Sequence[str],
    config: BuildConfig,
    store: _StepStore,
) -> tuple[Mattes, dict, PackedMasks | None, PackedMasks | None]:
    """The matting step's alphas with the shadow holes of imported masks filled
    (``BuildConfig.fill_shadow_holes``; :func:`hole_masks` on each view's colour
    photograph), one view at a time, ``{"views", "px"}`` filled, and the open holes and
    (``BuildConfig.doubt_bright_extensions``) the bright extensions found on the way (for :func:`step_geometry`,
    which would otherwise load every photograph again; None when the rule does not
    apply). Writes :data:`FILLED_HOLES` (removes a stale one when nothing is filled); the
    returned :class:`Mattes` has a new ``content`` digest, so later steps see the change."""
    import hashlib

    rig = _is_rig_session(session)
    tolerant = default_carve_tolerance(config, rig_session=rig, n_views=len(vids))
    path = store.dir / FILLED_HOLES
    none = {"views": 0, "px": 0}
    if not (config.fill_shadow_holes and config.backdrop_holes and tolerant and mattes.use_masks):
        path.unlink(missing_ok=True)
        return mattes, none, None, None
    fill, opened = PackedMasks(), PackedMasks()
    extensions = PackedMasks() if _extensions_apply(config, bool(tolerant), mattes.use_masks) else None
    h = hashlib.sha256(mattes.content.encode())
    n_px = n_views = 0
    for i, shot in enumerate(colour):
        rgb = None if shot[0] is None else _rgb(session.load_radiance(shot[0]))
        o, m = (None, None) if rgb is None else hole_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
        if extensions is not None:
            extensions.append(
                None if rgb is None else bright_extension_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
            )
        del rgb
        opened.append(o)
        fill.append(m)
        if m is not None and m.any():
            n_px += int(m.sum())
            n_views += 1
            h.update(vids[i].encode() + np.packbits(m, axis=1).tobytes())
    if n_px == 0:
        path.unlink(missing_ok=True)
        return mattes, none, opened, extensions
    write_hole_masks(path, {vids[i]: m for i, m in enumerate(fill) if m is not None and m.any()})
    filled = replace(mattes, alphas=_HolesFilled(mattes.alphas, fill), content=h.hexdigest())
    return filled, {"views": n_views, "px": n_px}, opened, extensions


def _extensions_apply(config: BuildConfig, tolerant: bool, use_masks: bool) -> bool:
    """Whether the bright-extension rule applies: asked for, a tolerant carve (something to
    doubt with) and imported masks (a rig's triangulation mattes are no thresholds)."""
    return bool(config.doubt_bright_extensions and tolerant and use_masks)
