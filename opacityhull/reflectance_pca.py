"""A view's reflectance field stored as a blockwise PCA (``[reflectance] storage = "pca"``).

The K one-light images of a view are cut into square pixel blocks (``block`` px, 8 by
default; ``None``: one block for the whole view, "PCA per view"). Each block's stack,
as the (3·pixels × K) matrix M_b, is kept as the uncentred truncated SVD that
:func:`compress_reflectance` computes (the optimal rank-r
approximation in the Frobenius norm; relighting is linear, so no mean is needed): r_b
basis images B_bj = (U·S)_j and per light sample r_b coefficients C_b[k, j] = V[k, j]:

    one-light image k over block b ≈ Σ_j C_b[k, j] · B_bj      (RGB share C_b).

Blocks because a view's PCA is global: on the analytic sphere one PCA per view needs
rank ≈ 38 of 60 for a 1 % error (no saving), while 8-pixel blocks, whose pixels see
nearly one normal, need rank ≈ 2–3 (benchmarks/out/reflectance_pca.md) — the "PCA per surfel
block" of the paper, in image blocks. The rank is fixed (``rank``, every non-zero block)
or allocated: the fewest components over all blocks (those of largest σ²) whose
relative Frobenius error over the view ‖M − M̂‖_F / ‖M‖_F is at most ``error``
(default 1 %). The error reported is measured on the numbers as stored (rounded to
the model's pixel type), not predicted from the singular values.

File ``reflectance/<view id>.exr``: a two-part OpenEXR file (scanline, ZIP), half or
float32 like the rest of the model, readable by OpenEXR tools (multi-part, EXR 2.0):

* part ``basis``: layers ``pc000.R/G/B`` … ``pc<R-1>.R/G/B`` (R = the largest block
  rank; in a block of rank r_b layers r_b.. are 0). Data window = the bounding box of
  the stack's non-zero pixels (outside it every one-light image is 0: black backdrop,
  premultiplied); display window = the full view. Header ``reflectanceStorage = "pca"``,
  ``pcaFormat``, ``pcaRank`` (R), ``pcaBlockWidth``/``pcaBlockHeight`` (px, blocks tile
  the data window from its top-left corner, the last ones may be smaller),
  ``pcaRelError`` (measured), ``pcaTruncationError`` (from the singular values),
  ``pcaKeys`` (comma-separated light keys), ``pcaNote`` (the formula), and the light
  attributes of the layered file (``<key>.lightId`` …);
* part ``coefficients``: one pixel per block (data window (0, 0) – (nx − 1, ny − 1)),
  channels ``<key>.c000`` … ``<key>.c<R-1>`` (C_b[k, j], 0 past the block's rank) and
  ``rank`` (r_b).

:func:`read_reflectance_pca` rebuilds ``{key: (H, W, 3)}``; a file that does not match its
model (parts, rank, a missing layer or coefficient, window sizes, non-finite
coefficients) is a :class:`~opacityhull.errors.FormatError` naming the file and the key.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args
from collections.abc import Sequence

import numpy as np

from .errors import FormatError, InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = [
    "CompressedReflectance",
    "compress_reflectance",
    "compress_reflectance_reference",
    "ReflectanceStorage",
    "REFLECTANCE_STORAGES",
    "DEFAULT_PCA_ERROR",
    "DEFAULT_PCA_BLOCK",
    "PCA_FORMAT",
    "PcaView",
    "check_pca_options",
    "allocate_ranks",
    "compress_view",
    "write_reflectance_pca",
    "read_reflectance_pca",
]

#: How ``reflectance/<view>.exr`` holds the one-light images: one layer per light sample,
#: or the rank-R PCA of this module.
ReflectanceStorage = Literal["layers", "pca"]
REFLECTANCE_STORAGES: tuple[str, ...] = get_args(ReflectanceStorage)
#: default target of the relative Frobenius error when no fixed rank is given
DEFAULT_PCA_ERROR = 0.01
PCA_FORMAT = "opacityhull.reflectance-pca/1"


#: default block edge (pixels). Measured on the analytic sphere (320x240, 60 lights, half):
#: at a 1 % target 8 px blocks store 1/6.4 of the layers' bytes, one PCA for the whole
#: view 1/0.8 (more than the layers); at 3 %, 1/11.9 (benchmarks/out/reflectance_pca.md)
DEFAULT_PCA_BLOCK = 8


# --------------------------------------------------------------------------- truncated SVD (shared with the relighter and the viewer)


@dataclass(frozen=True, eq=False)
class CompressedReflectance:
    """Rank-r truncated SVD of one view's reflectance data.

    ``stack[k].reshape(-1) ≈ Σ_j basis[j].reshape(-1) · coeffs[k, j]``.

    Attributes
    ----------
    basis : (r, H, W, 3) float32 eigen-images (U·S).
    coeffs : (K, r) float64 light-space coefficients (V).
    singular_values : (min(K, 3HW),) all singular values, descending.
    rel_error : ‖M − M_r‖_F / ‖M‖_F of the reflectance matrix M (0 when M = 0).
    """

    basis: np.ndarray
    coeffs: np.ndarray
    singular_values: np.ndarray
    rel_error: float

    @property
    def rank(self) -> int:
        return self.coeffs.shape[1]

    @property
    def n_lights(self) -> int:
        return self.coeffs.shape[0]

    @property
    def compression_ratio(self) -> float:
        """Floats of the full stack / floats of (basis + coeffs)."""
        P3 = int(np.prod(self.basis.shape[1:]))
        return (self.n_lights * P3) / max(1, self.rank * P3 + self.coeffs.size)

    def relight(self, weights) -> np.ndarray:
        """(K, 3) weights → (H, W, 3) relit image (or (M, K, 3) → (M, H, W, 3))."""
        w = np.asarray(weights, np.float64)
        single = w.ndim == 2
        w = w[None] if single else w
        if w.shape[1:] != (self.n_lights, 3):
            raise ShapeError(f"weights have shape {np.shape(weights)}, expected ({self.n_lights}, 3)")
        a = np.einsum("kr,mkc->mrc", self.coeffs, w)  # (M, r, 3)
        out = np.einsum("rhwc,mrc->mhwc", self.basis, a.astype(np.float32), optimize=True)
        return out[0] if single else out

    def reconstruct(self) -> np.ndarray:
        """(K, H, W, 3) the rank-r approximation of the stack."""
        r = self.rank
        B = self.basis.reshape(r, -1)
        return (self.coeffs.astype(np.float32) @ B).reshape((self.n_lights,) + self.basis.shape[1:])


def compress_reflectance(stack, rank: int) -> CompressedReflectance:
    """Rank-``rank`` approximation of a (K, H, W, 3) stack via the K×K Gram matrix.

    The matrix M (3HW × K) is tall, so its SVD comes from the eigen-decomposition of
    MᵀM (K × K, float64): V and σ² directly, U·S = M V. Squaring the condition number
    only affects the discarded tail. Checked against :func:`numpy.linalg.svd` by
    :func:`compress_reflectance_reference`.
    """
    s = np.asarray(stack, np.float32)
    if s.ndim != 4 or s.shape[3] != 3:
        raise ShapeError(f"reflectance stack has shape {s.shape}, expected (K, H, W, 3)")
    K = s.shape[0]
    if not 1 <= int(rank) <= K:
        raise InputError(f"PCA rank must be in [1, {K}] (the number of lights), got {rank}")
    Mt = s.reshape(K, -1)  # (K, 3HW) = Mᵀ
    G = Mt.astype(np.float64) @ Mt.T.astype(np.float64)
    evals, evecs = np.linalg.eigh(G)
    order = np.argsort(evals)[::-1]
    evals = np.clip(evals[order], 0, None)
    V = evecs[:, order[: int(rank)]]
    basis = (V.T.astype(np.float32) @ Mt).reshape((int(rank),) + s.shape[1:])
    total = float(evals.sum())
    rel = math.sqrt(max(0.0, float(evals[int(rank) :].sum())) / total) if total > 0 else 0.0
    return CompressedReflectance(basis.astype(np.float32), V, np.sqrt(evals), rel)


def compress_reflectance_reference(stack, rank: int) -> np.ndarray:
    """Rank-r approximation through :func:`numpy.linalg.svd` (oracle), (K, H, W, 3)."""
    s = np.asarray(stack, np.float64)
    K = s.shape[0]
    M = s.reshape(K, -1).T
    U, S, Vt = np.linalg.svd(M, full_matrices=False)
    Mr = (U[:, :rank] * S[:rank]) @ Vt[:rank]
    return Mr.T.reshape(s.shape).astype(np.float32)


@dataclass(frozen=True)
class PcaView:
    """One view's stored PCA, blockwise.

    Attributes
    ----------
    basis : (R, h, w, 3) float32 basis images over ``box``, as stored (rounded to half
        when the model is half); in block b only the first ``ranks[b]`` are non-zero.
    coeffs : (ny, nx, K, R) float32 coefficients per block and light (rows in the order of
        the light keys), as stored; columns past the block's rank are 0.
    ranks : (ny, nx) int rank of each block (0: an all-zero block).
    box : (x0, y0, x1, y1) half-open pixel box of the basis in the (H, W) view.
    block : (block height, block width) in pixels; blocks tile ``box`` from its corner
        (the last row and column may be smaller). ``box``'s size: one PCA for the view.
    rel_error : measured ‖M − M̂‖_F / ‖M‖_F of what is stored (0 for an all-zero stack).
    truncation_error : the same predicted from the discarded singular values.
    values_ratio : values of the K full (H, W, 3) layers / values stored (basis values
        inside each block's rank + K coefficients per block and rank).
    """

    basis: np.ndarray
    coeffs: np.ndarray
    ranks: np.ndarray
    box: tuple[int, int, int, int]
    block: tuple[int, int]
    rel_error: float
    truncation_error: float
    values_ratio: float

    @property
    def rank(self) -> int:
        """The largest block rank (the number of basis layers)."""
        return int(self.basis.shape[0])

    @property
    def rank_mean(self) -> float:
        """Block ranks averaged over the blocks' pixels."""
        return _rank_mean(self.ranks, self.box, self.block)

    def reconstruct(self) -> np.ndarray:
        """(K, h, w, 3) float32 one-light images over ``box``."""
        return _reconstruct(self.basis, self.coeffs, self.box, self.block)


def _rank_mean(ranks, box, block) -> float:
    x0, y0, x1, y1 = box
    by, bx = block
    ys = np.diff(np.minimum(np.arange(ranks.shape[0] + 1) * by, y1 - y0))
    xs = np.diff(np.minimum(np.arange(ranks.shape[1] + 1) * bx, x1 - x0))
    return float((ranks * ys[:, None] * xs[None, :]).sum() / max(1, (y1 - y0) * (x1 - x0)))


def _reconstruct(basis, coeffs, box, block) -> np.ndarray:
    x0, y0, x1, y1 = box
    h, w = y1 - y0, x1 - x0
    by, bx = block
    ny, nx, K, R = coeffs.shape
    out = np.zeros((K, h, w, 3), np.float32)
    for iy in range(ny):
        for ix in range(nx):
            ys, xs = slice(iy * by, min(h, (iy + 1) * by)), slice(ix * bx, min(w, (ix + 1) * bx))
            b = basis[:, ys, xs]
            out[:, ys, xs] = np.einsum("kr,ryxc->kyxc", coeffs[iy, ix], b)
    return out


def check_pca_options(*, rank: int | None, error: float, block: int | None = DEFAULT_PCA_BLOCK) -> None:
    """InputError unless ``rank`` is None or an integer ≥ 1, ``error`` is in (0, 1) and
    ``block`` is None (one PCA per view) or an integer ≥ 2."""
    if rank is not None and (isinstance(rank, bool) or not isinstance(rank, (int, np.integer)) or int(rank) < 1):
        raise InputError(f"PCA rank {rank!r}: expected an integer >= 1 (or none, to choose it from the error target)")
    if not (isinstance(error, (int, float)) and 0.0 < float(error) < 1.0):
        raise InputError(f"PCA error target {error!r}: expected a relative Frobenius error in (0, 1), e.g. 0.01")
    if block is not None and (isinstance(block, bool) or not isinstance(block, (int, np.integer)) or int(block) < 2):
        raise InputError(f"PCA block {block!r}: expected an edge of at least 2 pixels (or none: one PCA per view)")


def allocate_ranks(singular_values: Sequence[np.ndarray], *, target: float) -> list[int]:
    """Ranks of blocks with these singular values (descending each) that keep the fewest
    components overall with sqrt(Σ discarded σ² / Σ σ²) ≤ ``target``: the components of
    largest σ² across all blocks, so a block whose light varies more gets more (each
    component costs about the same to store). One block: the smallest rank meeting the
    target. An all-zero input keeps nothing."""
    s2 = [np.asarray(v, np.float64) ** 2 for v in singular_values]
    allv = np.concatenate(s2) if s2 else np.zeros(0)
    total = float(allv.sum())
    if total <= 0:
        return [0] * len(s2)
    order = np.argsort(-allv, kind="stable")
    tail = total - np.cumsum(allv[order])  # discarded energy when the first i + 1 are kept
    n = int(np.argmax(tail <= (float(target) ** 2) * total)) + 1
    owner = np.repeat(np.arange(len(s2)), [len(v) for v in s2])
    return np.bincount(owner[order[:n]], minlength=len(s2)).tolist()


def _nonzero_box(stack: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the pixels non-zero in any image and channel; (0, 0, 1, 1) when
    there is none (an EXR needs at least one pixel)."""
    nz = np.any(stack != 0, axis=(0, 3))
    ys, xs = np.nonzero(nz)
    if ys.size == 0:
        return 0, 0, 1, 1
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def compress_view(
    stack,
    *,
    rank: int | None = None,
    error: float = DEFAULT_PCA_ERROR,
    block: int | None = DEFAULT_PCA_BLOCK,
    half: bool = False,
    where: str = "stack",
) -> PcaView:
    """The stored PCA of a (K, H, W, 3) one-light stack.

    Parameters
    ----------
    stack : (K, H, W, 3) premultiplied radiance, finite (NaN/Inf would spread into
        every reconstructed image: an InputError naming ``where`` and the first image).
    rank : fixed rank in [1, K] for every block (all-zero blocks: 0), or None: the
        fewest components over all blocks whose relative Frobenius error over the view
        is at most ``error`` (:func:`allocate_ranks`).
    block : edge of the square pixel blocks, each with its own PCA
        (:func:`compress_reflectance` per block); None: one
        PCA for the whole view.
    half : round basis and coefficients as a half EXR will (the measured error includes it).
    where : names the data in errors (a file or view).
    """

    check_pca_options(rank=rank, error=error, block=block)
    s = np.asarray(stack, np.float32)
    if s.ndim != 4 or s.shape[3] != 3 or s.shape[0] < 1:
        raise ShapeError(f"{where}: reflectance stack has shape {s.shape}, expected (K >= 1, H, W, 3)")
    K, H, W, _ = s.shape
    if rank is not None and int(rank) > K:
        raise InputError(f"{where}: PCA rank {rank} is more than the {K} light samples")
    bad = ~np.isfinite(s)
    if bad.any():
        k = int(np.argmax(bad.reshape(K, -1).any(axis=1)))
        raise InputError(
            f"{where}: {int(bad.sum())} NaN/Inf value(s) in the one-light images (first in image {k}); "
            "a PCA would spread them into every image (store these layers, or set them to 0)"
        )
    x0, y0, x1, y1 = _nonzero_box(s)
    crop = s[:, y0:y1, x0:x1]
    h, w = y1 - y0, x1 - x0
    by, bx = (h, w) if block is None else (int(block), int(block))
    ny, nx = -(-h // by), -(-w // bx)

    def blk(iy, ix):
        return np.ascontiguousarray(crop[:, iy * by : (iy + 1) * by, ix * bx : (ix + 1) * bx])

    nonzero = [(iy, ix) for iy in range(ny) for ix in range(nx) if blk(iy, ix).any()]  # others: rank 0
    ranks = np.zeros((ny, nx), np.int64)
    if rank is None:
        # a first pass for the singular values only (rank 1: no full basis held), then
        # the ranks from all blocks at once
        svs = [compress_reflectance(blk(*b), 1).singular_values for b in nonzero]
        for b, r in zip(nonzero, allocate_ranks(svs, target=error), strict=True):
            ranks[b] = r
        del svs
    else:
        for b in nonzero:
            ranks[b] = int(rank)
    parts: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    tail2 = 0.0
    for b in nonzero:
        if ranks[b] == 0:
            tail2 += float(np.sum(blk(*b).astype(np.float64) ** 2))
            continue
        comp = compress_reflectance(blk(*b), int(ranks[b]))
        tail2 += float(np.sum(comp.singular_values[int(ranks[b]) :].astype(np.float64) ** 2))
        parts[b] = (comp.basis, comp.coeffs)
    R = max(1, int(ranks.max()))
    basis = np.zeros((R, h, w, 3), np.float32)
    coeffs = np.zeros((ny, nx, K, R), np.float32)
    for (iy, ix), (b, c) in parts.items():
        basis[: b.shape[0], iy * by : (iy + 1) * by, ix * bx : (ix + 1) * bx] = b
        coeffs[iy, ix, :, : c.shape[1]] = c
    del parts
    if half:
        for a, what in ((basis, "basis"), (coeffs, "coefficient")):
            if np.abs(a).max(initial=0.0) > 65504.0:
                raise InputError(
                    f"{where}: a PCA {what} value exceeds the half range (65504); store the model as float"
                )
        basis = basis.astype(np.float16).astype(np.float32)
        coeffs = coeffs.astype(np.float16).astype(np.float32)
    rec = _reconstruct(basis, coeffs, (x0, y0, x1, y1), (by, bx))
    den = float(np.sum(crop.astype(np.float64) ** 2))
    num = float(np.sum((rec.astype(np.float64) - crop) ** 2))
    del rec
    rel = math.sqrt(num / den) if den > 0 else 0.0
    trunc = math.sqrt(tail2 / den) if den > 0 else 0.0
    ys = np.diff(np.minimum(np.arange(ny + 1) * by, h))
    xs = np.diff(np.minimum(np.arange(nx + 1) * bx, w))
    stored = float((ranks * (3 * ys[:, None] * xs[None, :] + K)).sum())
    values_ratio = (K * H * W * 3) / max(stored, 1.0)
    return PcaView(basis, coeffs, ranks, (x0, y0, x1, y1), (by, bx), rel, trunc, values_ratio)


def write_reflectance_pca(
    path,
    layers: dict,
    keys: Sequence[str],
    *,
    shape: tuple[int, int],
    header: dict | None = None,
    half: bool = False,
    rank: int | None = None,
    error: float = DEFAULT_PCA_ERROR,
    block: int | None = DEFAULT_PCA_BLOCK,
) -> PcaView:
    """Write the one-light images ``layers[key]`` ((H, W, 3) each, ``keys`` in order) of
    one view as the two-part PCA file described in the module docstring, atomically.

    ``header``: the view's light attributes (typed as by :func:`opacityhull.imageio.write_exr`).
    Returns the :class:`PcaView` written.
    """
    import OpenEXR

    from .imageio import exr_attribute, atomic_path

    path = Path(path)
    H, W = (int(x) for x in shape)
    for k in keys:
        if "." in k:
            raise InputError(f"{path}: light key {k!r} must not contain '.'")
        if k not in layers:
            raise InputError(f"{path}: one-light image {k} missing from the reflectance to write")
        a = np.shape(layers[k])
        if a != (H, W, 3):
            raise ShapeError(f"{path}: one-light image {k} has shape {a}, expected ({H}, {W}, 3)")
    stack = np.stack([np.asarray(layers[k], np.float32) for k in keys])
    pv = compress_view(stack, rank=rank, error=error, block=block, half=half, where=str(path))
    del stack
    x0, y0, x1, y1 = pv.box
    ny, nx = pv.ranks.shape
    dt = np.float16 if half else np.float32
    display = (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32))
    basis = {}
    for j in range(pv.rank):
        for c, name in enumerate("RGB"):
            basis[f"pc{j:03d}.{name}"] = np.ascontiguousarray(pv.basis[j, :, :, c], dtype=dt)
    h0 = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "dataWindow": (np.array([x0, y0], np.int32), np.array([x1 - 1, y1 - 1], np.int32)),
        "displayWindow": display,
    }
    for k, v in (header or {}).items():
        h0[k] = exr_attribute(k, v, path)
    h0.update(
        {
            "reflectanceStorage": "pca",
            "pcaFormat": PCA_FORMAT,
            "pcaRank": int(pv.rank),
            "pcaBlockWidth": int(pv.block[1]),
            "pcaBlockHeight": int(pv.block[0]),
            "pcaRelError": float(pv.rel_error),
            "pcaTruncationError": float(pv.truncation_error),
            "pcaKeys": ",".join(keys),
            "pcaNote": "one-light image <key>, block b = sum_j coefficients.<key>.c<j>[b] * basis.pc<j> "
            "(RGB); blocks of pcaBlockWidth x pcaBlockHeight px tile the data window from its corner; "
            "0 outside it; premultiplied radiance at full DMX level",
        }
    )
    # ranks are small integers (<= K), exact in half as well
    coeffs: dict[str, np.ndarray] = {"rank": np.ascontiguousarray(pv.ranks, dtype=dt)}
    for i, k in enumerate(keys):
        for j in range(pv.rank):
            coeffs[f"{k}.c{j:03d}"] = np.ascontiguousarray(pv.coeffs[:, :, i, j], dtype=dt)
    h1 = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "dataWindow": (np.array([0, 0], np.int32), np.array([nx - 1, ny - 1], np.int32)),
        "displayWindow": display,  # a multi-part file's parts share it
    }
    with atomic_path(path) as tmp:
        parts = [OpenEXR.Part(h0, basis, name="basis"), OpenEXR.Part(h1, coeffs, name="coefficients")]
        with OpenEXR.File(parts) as f:
            f.write(str(tmp))
    return pv


def read_reflectance_pca(path, keys: Sequence[str], *, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """``{key: (H, W, 3) float32}`` rebuilt from a PCA file; :class:`FormatError` naming
    the file (and the key or layer) when it is missing, unreadable or does not match."""
    import OpenEXR

    path = Path(path)
    H, W = (int(x) for x in shape)
    if not path.is_file():
        raise FormatError(f"{path}: PCA reflectance file not found")
    from .imageio import library_output

    noise: list[str] = []
    try:
        with library_output() as noise, OpenEXR.File(str(path), separate_channels=True) as f:
            n_parts = len(f.parts)
            h = dict(f.header(0))
            basis_ch = {k: np.asarray(v.pixels) for k, v in f.channels(0).items()}
            coeff_ch = {k: np.asarray(v.pixels) for k, v in f.channels(1).items()} if n_parts > 1 else {}
            h1 = dict(f.header(1)) if n_parts > 1 else {}
    except Exception as e:  # noqa: BLE001  OpenEXR raises bare Exception on truncated files; re-raised, named
        raise FormatError(f"{path}: not a readable EXR file ({e})") from None
    if noise:  # the binding warned and returned partial pixel data
        raise FormatError(f"{path}: damaged EXR file: {noise[0].strip()}")
    if h.get("reflectanceStorage") != "pca":
        raise FormatError(
            f"{path}: header reflectanceStorage is {h.get('reflectanceStorage')!r}, expected 'pca' "
            "(model.toml says this view's reflectance is a PCA)"
        )
    if n_parts != 2:
        raise FormatError(f"{path}: {n_parts} part(s), expected 2 (basis, coefficients)")
    try:
        R, bx, by = int(h["pcaRank"]), int(h["pcaBlockWidth"]), int(h["pcaBlockHeight"])
    except (KeyError, TypeError, ValueError):
        raise FormatError(
            f"{path}: header pcaRank, pcaBlockWidth or pcaBlockHeight missing or not an integer"
        ) from None
    (dx0, dy0), (dx1, dy1) = (np.asarray(p, np.int64) for p in h["displayWindow"])
    if (int(dx1 - dx0 + 1), int(dy1 - dy0 + 1)) != (W, H):
        raise FormatError(f"{path}: display window is {dx1 - dx0 + 1}x{dy1 - dy0 + 1}, the view is {W}x{H}")
    (x0, y0), (x1, y1) = (np.asarray(p, np.int64) for p in h["dataWindow"])
    x0, y0, x1, y1 = int(x0 - dx0), int(y0 - dy0), int(x1 - dx0) + 1, int(y1 - dy0) + 1
    if not (0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H) or R < 1 or bx < 1 or by < 1:
        raise FormatError(
            f"{path}: data window {(x0, y0, x1, y1)} in the {W}x{H} view, rank {R}, block {bx}x{by}: inconsistent"
        )
    want = {f"pc{j:03d}.{c}" for j in range(R) for c in "RGB"}
    if set(basis_ch) != want:
        missing, extra = sorted(want - set(basis_ch)), sorted(set(basis_ch) - want)
        raise FormatError(
            f"{path}: PCA rank {R} needs basis layers pc000..pc{R - 1:03d} (R, G, B); "
            f"missing {missing[:6]}, unexpected {extra[:6]}"
        )
    ny, nx = -(-(y1 - y0) // by), -(-(x1 - x0) // bx)
    (cx0, cy0), (cx1, cy1) = (np.asarray(p, np.int64) for p in h1["dataWindow"])
    if (int(cy1 - cy0 + 1), int(cx1 - cx0 + 1)) != (ny, nx):
        raise FormatError(
            f"{path}: coefficients part is {cx1 - cx0 + 1}x{cy1 - cy0 + 1} blocks, the data window holds {nx}x{ny}"
        )
    basis = np.empty((R, y1 - y0, x1 - x0, 3), np.float32)
    for j in range(R):
        for c, name in enumerate("RGB"):
            basis[j, :, :, c] = basis_ch[f"pc{j:03d}.{name}"]
    coeffs = np.empty((ny, nx, len(keys), R), np.float32)
    for i, k in enumerate(keys):
        for j in range(R):
            c = coeff_ch.get(f"{k}.c{j:03d}")
            if c is None:
                raise FormatError(f"{path}: PCA coefficients {k}.c{j:03d} of one-light image {k} missing")
            if not np.isfinite(c).all():
                raise FormatError(f"{path}: PCA coefficients {k}.c{j:03d} of one-light image {k} hold NaN/Inf")
            coeffs[:, :, i, j] = c
    rec = _reconstruct(basis, coeffs, (x0, y0, x1, y1), (by, bx))
    out = {}
    for i, k in enumerate(keys):
        img = np.zeros((H, W, 3), np.float32)
        img[y0:y1, x0:x1] = rec[i]
        out[k] = img
    return out
