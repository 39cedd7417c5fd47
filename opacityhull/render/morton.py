"""3-D Morton (Z-order) codes: the surfel order of the renderer (:func:`..renderer.spatially_sorted`),
the level-of-detail tree (:mod:`.lod`, the frame runner's cut order) and the viewer's
octree point code (:mod:`opacityhull.view.octree_code`)."""

from __future__ import annotations

import numpy as np

__all__ = ["part1by2", "interleave3", "morton_codes"]


def part1by2(x: np.ndarray) -> np.ndarray:
    """(N,) uint64: the low 21 bits of ``x`` spread to every third bit (bit i to bit 3i)."""
    x = x.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def interleave3(q: np.ndarray) -> np.ndarray:
    """(N,) uint64 Morton codes of (N, 3) integer cell coordinates (each < 2²¹): x in bit
    3i, y in 3i + 1, z in 3i + 2."""
    return part1by2(q[:, 0]) | (part1by2(q[:, 1]) << np.uint64(1)) | (part1by2(q[:, 2]) << np.uint64(2))


def morton_codes(positions: np.ndarray, *, bits: int = 16) -> np.ndarray:
    """(N,) uint64 Morton codes of ``positions`` (N, 3) on a ``2**bits`` grid over the
    bounding cube of the finite ones (``bits`` ≤ 21); a non-finite coordinate counts as 0."""
    P = np.asarray(positions, dtype=np.float64)
    fin = np.all(np.isfinite(P), axis=1)
    lo = P[fin].min(axis=0) if fin.any() else np.zeros(3)
    span = float((P[fin].max(axis=0) - lo).max()) if fin.any() else 1.0
    q = np.clip(np.nan_to_num((P - lo) / (span or 1.0)) * (2**bits - 1), 0, 2**bits - 1).astype(np.uint64)
    return interleave3(q)
