"""Per-view data held lazily or packed between the build's steps (the mattes read back
from ``build/mattes``, bit-packed masks, views made on access) and the memory budget
(:class:`MemoryPlan`)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from ..errors import ConfigError, InputError
from ..session import Session
from .matte_step import _load_matte, _rgb
from .matting import straight_from_premul

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Mattes:
    """The matting step's product: alphas in view order, per-view stats, where the
    backdrops came from, NaN/Inf notes, and the step key."""

    #: per view (H, W) float32, read from ``build/mattes`` on access (:class:`_MatteFiles`)
    alphas: Sequence
    stats: list
    sources: set
    nonfinite: list
    key: str
    #: SHA-256 over the alphas' bytes: what the later steps depend on (a re-matted view
    #: whose alpha came out the same leaves them fresh)
    content: str
    use_masks: bool
    drift_mode: str


class _LazyViews(Sequence):
    """``[view_rgba(i) for i in range(n)]`` computed on access: the writer streams the
    views one at a time instead of holding them all."""

    def __init__(self, fn: Callable[[int], np.ndarray], n: int):
        self.fn, self.n = fn, int(n)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):  # int only: the writer iterates
        if isinstance(i, slice):
            raise TypeError("_LazyViews does not slice")
        if not -self.n <= i < self.n:
            raise IndexError(i)
        return self.fn(i % self.n)

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self.fn(i) for i in range(self.n))


class _Subset(Sequence):
    """``[seq[j] for j in idx]`` read on access (the training views of a lazy per-view
    sequence, one at a time)."""

    def __init__(self, seq: Sequence, idx: Sequence[int]):
        self.seq, self.idx = seq, [int(j) for j in idx]

    def __len__(self) -> int:
        return len(self.idx)

    def __getitem__(self, i):
        if isinstance(i, slice):
            raise TypeError("_Subset does not slice")
        return self.seq[self.idx[i]]

    def __iter__(self) -> Iterator:
        return (self[i] for i in range(len(self)))


class PackedMasks(Sequence):
    """Per-view (H, W) bool masks held bit-packed (:func:`numpy.packbits` along rows, 1 bit
    a pixel): ``masks[i]`` unpacks view ``i`` alone. The build keeps its silhouettes this
    way between the stages, so that holding every view's mask costs V·H·W/8 bytes; an
    entry may be None (no mask for that view)."""

    def __init__(self, masks: Sequence | None = None):
        self._bits: list = []
        for m in masks or ():
            self.append(m)

    def append(self, mask) -> None:
        if mask is None:
            self._bits.append(None)
            return
        m = np.asarray(mask, bool)
        if m.ndim != 2:
            raise InputError(f"PackedMasks: a mask is (H, W), got shape {m.shape}")
        self._bits.append((np.packbits(m, axis=1), m.shape))

    def __len__(self) -> int:
        return len(self._bits)

    def __getitem__(self, i):
        if isinstance(i, slice):
            out = PackedMasks()
            out._bits = self._bits[i]
            return out
        e = self._bits[i]
        if e is None:
            return None
        bits, (h, w) = e
        return np.unpackbits(bits, axis=1, count=w).view(bool)

    def __iter__(self) -> Iterator:
        return (self[i] for i in range(len(self)))

    @property
    def nbytes(self) -> int:
        return sum(e[0].nbytes for e in self._bits if e is not None)


class _MatteFiles(Sequence):
    """The matting step's alphas, read from ``build/mattes/<view>.npy`` on access (one
    view at a time; nothing cached): ``alphas[i]`` is view ``i``'s (H, W) float32 matte,
    registered with :data:`.perview.LIVE_VIEWS`."""

    def __init__(self, paths: Sequence[Path], shapes: Sequence[tuple[int, int]], vids: Sequence[str]):
        self.paths, self.shapes, self.vids = list(paths), [tuple(x) for x in shapes], list(vids)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i):
        if isinstance(i, slice):
            raise TypeError("_MatteFiles does not slice")
        from .liveviews import LIVE_VIEWS

        i = range(len(self.paths))[i]
        return LIVE_VIEWS.track(self.vids[i], _load_matte(self.paths[i], self.shapes[i]))

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[i] for i in range(len(self)))


class _Deferred:
    """An array computed when NumPy asks for it (``np.asarray``), not before: a list of
    these stands for a list of per-view images without holding them (the photo
    refinement packs its inputs one view at a time)."""

    __slots__ = ("fn",)

    def __init__(self, fn: Callable[[], np.ndarray]):
        self.fn = fn

    def __array__(self, dtype=None, copy=None):
        a = np.asarray(self.fn())
        return a if dtype is None else a.astype(dtype, copy=False)


#: the default ``--memory-gb``: this fraction of the machine's RAM
MEMORY_FRACTION = 0.25
#: views the classical carve stacks at once (its silhouettes and summed-area tables cost
#: 5 bytes a pixel a view): more are carved in batches whose hulls are intersected,
#: voxel for voxel the same hull
CARVE_BATCH_MAX_VIEWS = 48
#: the fewest view slots the memory plan gives the photo refinement (at least its
#: ``n_views``, 5: one surfel's views are scored together)
PHOTO_MIN_SLOTS = 8


def total_ram_bytes() -> int:
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def default_memory_gb() -> float:
    """``build --memory-gb`` when not given: :data:`MEMORY_FRACTION` of the RAM."""
    return MEMORY_FRACTION * total_ram_bytes() / 2**30


def check_memory_gb(memory_gb) -> float:
    """``memory_gb`` as a float > 0, else a ConfigError naming ``--memory-gb``."""
    try:
        g = float(memory_gb)
    except (TypeError, ValueError):
        g = float("nan")
    if not (math.isfinite(g) and g > 0):
        raise ConfigError(f"--memory-gb {memory_gb!r}: expected a number of GB > 0 (the build's memory budget)")
    return g


@dataclass(frozen=True)
class MemoryPlan:
    """How the ``--memory-gb`` budget is spent: views in flight in the per-view steps
    (matting on threads/processes), views stacked per carve batch."""

    budget_gb: float
    view_bytes: int
    in_flight: int
    carve_batch: int
    #: views whose grey image and matte the photo refinement holds at once
    #: (:attr:`opacityhull.reconstruct.photo.PhotoConfig.max_views_in_memory`)
    photo_slots: int = 32

    @classmethod
    def for_build(cls, budget_gb: float, *, pixels: int, images_per_view: int, workers: int, views: int):
        budget = budget_gb * 2**30
        # one view being matted: its matting shots and backdrops as float32 RGB, plus
        # the solver's working arrays (~4 more images) and its alpha
        view_bytes = int((images_per_view + 4) * pixels * 12 + 4 * pixels)
        in_flight = int(max(1, min(max(1, workers), (0.5 * budget) // max(view_bytes, 1))))
        carve = int(max(1, min(CARVE_BATCH_MAX_VIEWS, views, (0.25 * budget) // max(5 * pixels, 1))))
        # the refinement's slots cost 8 bytes a pixel (float32 grey + matte); a quarter of
        # the budget, never fewer than one surfel's scored views nor more than the views
        # (its result does not depend on the number: fewer slots only re-read photographs)
        slots = int(max(PHOTO_MIN_SLOTS, min(max(views, PHOTO_MIN_SLOTS), (0.25 * budget) // max(8 * pixels, 1))))
        return cls(budget_gb, view_bytes, in_flight, carve, slots)


def peak_rss_mb() -> float:
    """This process's peak resident set so far (``ru_maxrss``), MB."""
    import resource
    import sys

    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (2**20 if sys.platform == "darwin" else 1024.0)


def _view_rgba(
    session: Session, shots: tuple, alpha: np.ndarray, *, use_masks: bool, alpha_eps: float, finite=None
) -> np.ndarray:
    """Step 7 for one view: straight RGBA from its colour shot (minus the object-absent
    one) and its alpha."""
    finite = finite or (lambda img, where: img)
    obj, bg = shots
    Cimg = finite(_rgb(session.load_radiance(obj)), f"view colour shot {obj}")
    if bg is not None:
        prem = Cimg - (1.0 - alpha)[..., None] * _rgb(session.load_radiance(bg))
    elif use_masks:
        prem = Cimg * alpha[..., None]  # external images: colour seen through the mask
    else:
        prem = Cimg
    F = straight_from_premul(np.dstack([prem, alpha]), alpha_floor=alpha_eps)[..., :3]  # imageio's one conversion
    return np.concatenate([np.maximum(F, 0.0), alpha[..., None]], axis=-1).astype(np.float32)
