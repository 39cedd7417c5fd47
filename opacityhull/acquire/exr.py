"""EXR writing for captures, with a choice of compression.

:func:`opacityhull.imageio.write_exr` always ZIP-compresses. Sensor data is noisy, and
ZIP buys ~4 % on a noisy float32 image for ~10x the write time (and ~6x the read
time) of an uncompressed one; RLE costs ~1.3x and still shrinks the black
backgrounds of one-light-at-a-time and object-absent images about as well as ZIP
(measured in ``benchmarks/acquire.py``). Captures default to RLE.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, get_args

import numpy as np

from ..errors import ConfigError, ShapeError
from ..imageio import atomic_path, to_half

__all__ = ["COMPRESSIONS", "ExrCompression", "write_capture_exr"]

ExrCompression = Literal["none", "rle", "zip", "zips", "piz", "zstd"]
COMPRESSIONS: tuple[ExrCompression, ...] = get_args(ExrCompression)
_NAMES = {
    "none": "NO_COMPRESSION",
    "rle": "RLE_COMPRESSION",
    "zip": "ZIP_COMPRESSION",
    "zips": "ZIPS_COMPRESSION",
    "piz": "PIZ_COMPRESSION",
    "zstd": "ZSTD_COMPRESSION",
}


def _compression(name: str):
    import OpenEXR

    if name not in _NAMES:
        raise ConfigError(f"EXR compression {name!r} unknown; expected one of {list(COMPRESSIONS)}")
    c = getattr(OpenEXR, _NAMES[name], None)
    if c is None:
        raise ConfigError(f"EXR compression {name!r} is not available in this OpenEXR build")
    return c


def write_capture_exr(path, image, *, half: bool = False, compression: str = "rle") -> None:
    """Write an (H, W, C) image (C = 1, 3 or 4) as EXR, atomically (temporary file,
    fsync, rename). ``half``: :func:`~opacityhull.imageio.to_half` (finite values beyond ±65504
    clamped, with a warning naming the file)."""
    import OpenEXR

    path = Path(path)
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ShapeError(f"image for {path} has shape {np.shape(image)}, expected (H, W, 1|3|4)")
    names = {1: "Y", 3: "RGB", 4: "RGBA"}[a.shape[2]]
    a = a.astype(np.float32)
    if half:
        a, _ = to_half(a, path=path)
    chans = {n: np.ascontiguousarray(a[:, :, i]) for i, n in enumerate(names)}
    hdr = {"compression": _compression(compression), "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(hdr, chans) as f:
        f.write(str(tmp))
