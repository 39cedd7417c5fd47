"""Octree coding of point positions (Botsch, Wiratanaya & Kobbelt 2002, seed 001).

Positions are quantised to the cells of a 2^D grid over the bounding cube; the occupied
cells form an octree whose breadth-first sequence of non-zero child-occupancy bytes
("byte codes") reconstructs every occupied cell — a point is its cell's centre. On a
surface the branching factor is about 4, so there are ≈ N/3 byte codes for N leaves: ≈ 2.7
bits per point before entropy coding, less after (the seed reports < 2 bits with an
arithmetic coder; here zlib). Any prefix of the breadth-first stream decodes to a coarser
level of the same model (progressive transmission).

Several surfels in one leaf cell share its centre; their number is carried in a count
stream (one byte per leaf, only when some leaf holds more than one). Attributes follow
the decoded order (breadth-first = Morton order of the leaf cells), given by ``order``.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import FormatError, InputError

__all__ = [
    "OctreeCode",
    "encode_positions",
    "decode_positions",
    "depth_for_spacing",
    "median_spacing",
    "pack",
    "unpack",
    "encode_offsets",
    "apply_offsets",
    "OFFSET_RANGE",
]


@dataclass(frozen=True)
class OctreeCode:
    """Encoded positions.

    origin : (3,) float64 corner of the bounding cube; size : its edge (m); depth : D.
    codes : (B,) uint8 breadth-first byte codes. counts : (L,) uint8 surfels per leaf cell
        (empty when every leaf holds one). order : (N,) int64 — surfel index of each
        decoded position (attributes are stored in this order).
    """

    origin: np.ndarray
    size: float
    depth: int
    codes: np.ndarray
    counts: np.ndarray
    order: np.ndarray

    def nbytes(self, *, compress: bool = True) -> int:
        raw = self.codes.tobytes() + self.counts.tobytes()
        return len(zlib.compress(raw, 9)) if compress else len(raw)

    def bits_per_point(self, *, compress: bool = True) -> float:
        return 8.0 * self.nbytes(compress=compress) / max(1, len(self.order))


def _morton(q: np.ndarray) -> np.ndarray:
    from ..render.morton import interleave3

    return interleave3(q)


def depth_for_spacing(positions, spacing_m: float) -> int:
    """Smallest D whose cells are no larger than ``spacing_m`` (the surfel spacing)."""
    P = np.asarray(positions, np.float64)
    span = float((P.max(axis=0) - P.min(axis=0)).max()) if len(P) else 1.0
    return int(np.clip(np.ceil(np.log2(max(span, 1e-12) / spacing_m)), 1, 21))


def encode_positions(positions, depth: int | None = None, *, cell_m: float | None = None) -> OctreeCode:
    """Octree byte codes of ``positions`` (N, 3).

    Either ``depth`` (1..21: a 2^depth grid over the bounding cube) or ``cell_m`` (the leaf
    cell edge in metres; the cube grows to cell_m · 2^D with the smallest D that covers the
    points). A leaf cell about the surfel spacing gives the seed's regime: branching ≈ 4 on
    every level, < 3 bits per point, with a few surfels sharing a cell (see ``counts``).
    """
    P = np.asarray(positions, np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise InputError(f"encode_positions: positions shape {P.shape}, expected (N>0, 3)")
    if not np.all(np.isfinite(P)):
        raise InputError("encode_positions: non-finite positions")
    lo = P.min(axis=0)
    span = float((P.max(axis=0) - lo).max()) or 1.0
    if (depth is None) == (cell_m is None):
        raise InputError("encode_positions: give exactly one of depth or cell_m")
    if cell_m is not None:
        if not (np.isfinite(cell_m) and cell_m > 0):
            raise InputError(f"encode_positions: cell_m {cell_m!r}, expected > 0")
        depth = max(1, int(np.ceil(np.log2(span * (1 + 1e-9) / cell_m))))
    assert depth is not None
    if not 1 <= int(depth) <= 21:
        raise InputError(f"encode_positions: depth {depth}, expected 1..21")
    D = int(depth)
    size = float(cell_m) * 2**D if cell_m is not None else span * (1 + 1e-9)  # the maximum inside the last cell
    q = np.clip(np.floor((P - lo) / size * 2**D), 0, 2**D - 1).astype(np.uint64)
    code = _morton(q)
    order = np.argsort(code, kind="stable")
    leaf, counts = np.unique(code[order], return_counts=True)
    out = []
    cells = leaf
    levels = []
    for _ in range(D):  # from the leaves up: the byte code of each parent cell
        parent = cells >> np.uint64(3)
        child = (cells & np.uint64(7)).astype(np.uint8)
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]])
        bits = np.bitwise_or.reduceat((np.uint8(1) << child).astype(np.uint8), starts)
        levels.append(bits)
        cells = parent[starts]
    for bits in reversed(levels):  # stream: root first (breadth-first, Morton order per level)
        out.append(bits)
    cnt = counts.astype(np.int64)
    if np.any(cnt > 255):
        raise InputError(f"encode_positions: {int(cnt.max())} surfels in one cell at depth {D}; use a deeper grid")
    return OctreeCode(
        lo,
        size,
        D,
        np.concatenate(out).astype(np.uint8),
        cnt.astype(np.uint8) if np.any(cnt > 1) else np.zeros(0, np.uint8),
        order.astype(np.int64),
    )


def decode_positions(oc: OctreeCode) -> np.ndarray:
    """(N, 3) float64 cell centres in the stored order (repeated for cells of several surfels)."""
    cells = np.zeros((1, 3), np.int64)
    pos = 0
    codes = oc.codes
    for level in range(oc.depth):
        n = len(cells)
        if pos + n > len(codes):
            raise FormatError(f"octree code stream ends at level {level}: {len(codes)} bytes, need {pos + n}")
        b = codes[pos : pos + n]
        pos += n
        bits = np.unpackbits(b[:, None], axis=1, bitorder="little").astype(bool)  # (n, 8) child octants
        if not bits.any(axis=1).all():
            raise FormatError(f"octree code stream: zero byte code at level {level}")
        parent_idx, child = np.nonzero(bits)
        off = np.stack([(child >> 0) & 1, (child >> 1) & 1, (child >> 2) & 1], 1)
        cells = 2 * cells[parent_idx] + off
    if pos != len(codes):
        raise FormatError(f"octree code stream: {len(codes) - pos} bytes left after the leaves")
    h = oc.size / 2**oc.depth
    centres = oc.origin + (cells + 0.5) * h
    if len(oc.counts):
        if len(oc.counts) != len(centres):
            raise FormatError(f"octree counts: {len(oc.counts)} for {len(centres)} leaf cells")
        centres = np.repeat(centres, oc.counts.astype(np.int64), axis=0)
    return centres


def median_spacing(positions) -> float:
    """Median distance (m) from each point to its nearest other point (the surfel spacing)."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # scipy's stubs omit it

    P = np.asarray(positions, np.float64)
    if len(P) < 2:
        return 1.0
    d, _ = cKDTree(P).query(P, 2)
    d = d[:, 1][d[:, 1] > 0]
    return float(np.median(d)) if d.size else 1.0


def pack(oc: OctreeCode) -> tuple[dict, bytes, bytes]:
    """(header, zlib(byte codes), zlib(counts)) as stored in a viewer bundle.

    The streams are deflated separately (zlib format, what the browser's
    ``DecompressionStream("deflate")`` reads): the byte codes compress to the seed's regime,
    the counts (mostly 1) to a fraction of a bit per cell. ``counts`` is empty when every
    leaf cell holds one point.
    """
    n_cells = len(oc.counts) if len(oc.counts) else len(oc.order)
    head = {
        "origin": [float(x) for x in oc.origin],
        "size": float(oc.size),
        "depth": int(oc.depth),
        "n_codes": int(len(oc.codes)),
        "n_cells": int(n_cells),
        "n_points": int(len(oc.order)),
    }
    counts = zlib.compress(oc.counts.tobytes(), 9) if len(oc.counts) else b""
    return head, zlib.compress(oc.codes.tobytes(), 9), counts


def unpack(head: dict, codes_z: bytes, counts_z: bytes, *, what: str = "positions") -> OctreeCode:
    """Inverse of :func:`pack` (``order`` is the identity: attributes are stored decoded-order)."""
    try:
        codes = np.frombuffer(zlib.decompress(codes_z), np.uint8)
        counts = np.frombuffer(zlib.decompress(counts_z), np.uint8) if counts_z else np.zeros(0, np.uint8)
        origin = np.asarray(head["origin"], np.float64).reshape(3)
        size, depth, n = float(head["size"]), int(head["depth"]), int(head["n_points"])
    except (zlib.error, KeyError, TypeError, ValueError) as e:
        raise FormatError(f"{what}: octree stream or header unreadable ({e})") from e
    if len(codes) != int(head.get("n_codes", len(codes))):
        raise FormatError(f"{what}: {len(codes)} byte codes, header says {head.get('n_codes')}")
    if len(counts) and int(counts.astype(np.int64).sum()) != n:
        raise FormatError(f"{what}: counts sum to {int(counts.astype(np.int64).sum())}, header says {n} points")
    return OctreeCode(origin, size, depth, codes, counts, np.arange(n, dtype=np.int64))


OFFSET_RANGE = float(np.sqrt(3.0) / 2.0)
"""|λ| bound of a normal offset in cell edges: a point lies within half a cell diagonal of its centre."""


def encode_offsets(positions, centres, normals, cell_m: float, bits: int) -> np.ndarray:
    """Botsch et al.'s offset attributes: per point the signed distance λ·h of the point from
    its cell centre along its normal, λ ∈ [−√3/2, √3/2] quantised to ``bits`` bits (uniform
    bins). Returns (N,) uint8 bin indices. ``centres`` are the decoded cell centres and
    ``normals`` the normals the decoder will use (both in decoded order)."""
    if not 1 <= int(bits) <= 8:
        raise InputError(f"offset bits {bits}, expected 1..8")
    P, C, n = (np.asarray(a, np.float64) for a in (positions, centres, normals))
    nn = np.linalg.norm(n, axis=1)
    lam = np.where(nn > 1e-12, np.sum((P - C) * n, axis=1) / np.maximum(nn, 1e-30), 0.0) / cell_m
    step = 2 * OFFSET_RANGE / 2**bits
    return np.clip(np.floor((lam + OFFSET_RANGE) / step), 0, 2**bits - 1).astype(np.uint8)


def apply_offsets(centres, normals, q, cell_m: float, bits: int) -> np.ndarray:
    """Inverse of :func:`encode_offsets`: centres moved to their bin's centre along the unit normal."""
    C, n = np.asarray(centres, np.float64), np.asarray(normals, np.float64)
    q = np.asarray(q)
    if q.shape != (len(C),):
        raise FormatError(f"octree offsets: {q.shape[0] if q.ndim else 0} for {len(C)} points")
    if len(q) and int(q.max()) >= 2**bits:
        raise FormatError(f"octree offsets: bin {int(q.max())} out of range for {bits} bits")
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    u = np.where(nn > 1e-12, n / np.maximum(nn, 1e-30), 0.0)
    step = 2 * OFFSET_RANGE / 2**bits
    lam = (q.astype(np.float64) + 0.5) * step - OFFSET_RANGE
    return C + (lam * cell_m)[:, None] * u
