"""Size checks of a binary COLMAP model against its format, before pycolmap reads it.

pycolmap does not check for the end of the file: a ``cameras.bin`` cut by 8 bytes read
as garbage intrinsics (exit 0), and a half ``points3D.bin`` spent 98 s before
``std::bad_alloc``. :func:`check_colmap_binary` walks the record layout of
``cameras.bin``, ``images.bin`` and ``points3D.bin`` (COLMAP's ``reconstruction_io``;
unchanged in COLMAP 4, whose ``rigs.bin``/``frames.bin`` pycolmap checks itself) reading
only the counts and lengths, and raises :class:`~opacityhull.errors.FormatError` naming
the file, the record and the length the format expects.

Layouts (little-endian):

- ``cameras.bin``: u64 count; per camera i32 id, i32 model, u64 width, u64 height,
  f64 × (the model's parameter count).
- ``images.bin``: u64 count; per image i32 id, f64 × 7 (qw qx qy qz tx ty tz), i32
  camera id, the name (bytes up to a NUL), u64 points, (f64 x, f64 y, i64 id) × points.
- ``points3D.bin``: u64 count; per point u64 id, f64 × 3, u8 × 3, f64 error, u64 track
  length, (i32 image id, i32 point index) × track length.
"""

from __future__ import annotations

import struct
from pathlib import Path

from .errors import FormatError

__all__ = ["COLMAP_MODEL_PARAMS", "check_colmap_binary", "check_colmap_text", "read_colmap_checked"]

#: Parameters per COLMAP camera model id (``colmap/sensor/models.h``).
COLMAP_MODEL_PARAMS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4),
    13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3),
    15: ("FISHEYE", 4),
    16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}

_MAX_NAME = 4096  # bytes: a longer image name is a damaged file, not a path


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def need(self, n: int, what: str) -> None:
        left = len(self.data) - self.pos
        if n > left:
            raise FormatError(
                f"{self.path}: truncated at {what}: the format needs {n} more byte(s) at offset {self.pos}, "
                f"the file has {left} ({len(self.data)} bytes in all); copy the model again or re-export it"
            )

    def unpack(self, fmt: str, what: str) -> tuple:
        n = struct.calcsize(fmt)
        self.need(n, what)
        v = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += n
        return v

    def skip(self, n: int, what: str) -> None:
        self.need(n, what)
        self.pos += n

    def count(self, what: str, min_record: int) -> int:
        (n,) = self.unpack("<Q", f"the {what} count")
        # a count the rest of the file cannot hold even at the smallest record size is
        # damage, found before any allocation
        if n * min_record > len(self.data) - self.pos:
            raise FormatError(
                f"{self.path}: {n} {what} recorded, which needs at least {n * min_record} bytes after the count "
                f"(≥ {min_record} per record); the file has {len(self.data) - self.pos}: truncated or damaged"
            )
        return n

    def end(self) -> None:
        extra = len(self.data) - self.pos
        if extra:
            raise FormatError(
                f"{self.path}: {extra} unexpected byte(s) after the last record (offset {self.pos} of "
                f"{len(self.data)}): not a COLMAP binary file, or damaged"
            )


def _check_cameras(path: Path) -> None:
    r = _Reader(path)
    n = r.count("cameras", 24)
    for i in range(n):
        cid, model, _w, _h = r.unpack("<iiQQ", f"camera record {i}")
        if model not in COLMAP_MODEL_PARAMS:
            raise FormatError(
                f"{path}: camera record {i} (id {cid}): unknown camera model id {model} "
                f"(COLMAP's are 0..{max(COLMAP_MODEL_PARAMS)})"
            )
        name, k = COLMAP_MODEL_PARAMS[model]
        r.skip(8 * k, f"camera record {i} (id {cid}, {name}: {k} parameters = {8 * k} bytes)")
    r.end()


def _check_images(path: Path) -> None:
    r = _Reader(path)
    n = r.count("images", 4 + 56 + 4 + 1 + 8)
    for i in range(n):
        (iid,) = r.unpack("<i", f"image record {i}")
        r.skip(56 + 4, f"image record {i} (id {iid}: pose and camera id, 60 bytes)")
        end = r.data.find(b"\0", r.pos, r.pos + _MAX_NAME)
        if end < 0:
            raise FormatError(
                f"{path}: image record {i} (id {iid}): the name has no terminating NUL within "
                f"{min(_MAX_NAME, len(r.data) - r.pos)} bytes: truncated or damaged"
            )
        r.pos = end + 1
        (npts,) = r.unpack("<Q", f"image record {i} (id {iid}): its points2D count")
        if npts > (len(r.data) - r.pos) // 24:
            raise FormatError(
                f"{path}: image record {i} (id {iid}) lists {npts} points2D = {24 * npts} bytes, the file has "
                f"{len(r.data) - r.pos} left: truncated or damaged"
            )
        r.skip(24 * npts, f"image record {i} (id {iid}): {npts} points2D")
    r.end()


def _check_points(path: Path) -> None:
    r = _Reader(path)
    n = r.count("points3D", 51)
    for i in range(n):
        r.skip(8 + 24 + 3 + 8, f"point record {i}")
        (tl,) = r.unpack("<Q", f"point record {i}: its track length")
        if tl > (len(r.data) - r.pos) // 8:
            raise FormatError(
                f"{path}: point record {i} has a track of {tl} = {8 * tl} bytes, the file has "
                f"{len(r.data) - r.pos} left: truncated or damaged"
            )
        r.skip(8 * tl, f"point record {i}: track of {tl}")
    r.end()


def check_colmap_binary(directory) -> None:
    """Check the sizes of ``cameras.bin``, ``images.bin`` and ``points3D.bin`` in
    ``directory`` against the format (see the module notes); a missing file is left to
    the reader's own message. Raises :class:`FormatError` naming file, record and length."""
    d = Path(directory)
    for name, check in (
        ("cameras.bin", _check_cameras),
        ("images.bin", _check_images),
        ("points3D.bin", _check_points),
    ):
        p = d / name
        if p.is_file():
            check(p)


def check_colmap_text(directory) -> None:
    """``cameras.txt``, ``images.txt`` and ``points3D.txt`` are UTF-8 text (COLMAP writes
    ASCII): a damaged byte was a UnicodeDecodeError traceback. Names the file, line and byte."""
    d = Path(directory)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        p = d / name
        if not p.is_file():
            continue
        data = p.read_bytes()
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as e:
            line = data[: e.start].count(b"\n") + 1
            raise FormatError(
                f"{p}:{line}: not UTF-8 text (byte {e.start}: {data[e.start : e.start + 1]!r}); "
                "a damaged file, or not a COLMAP text model"
            ) from None


def read_colmap_checked(directory):
    """A COLMAP model as ``import colmap`` reads it: the format checks above, then
    :func:`opacityhull.camera.read_colmap_model`; a camera the reader refuses without
    naming the file (``focal lengths must be > 0``) is a :class:`FormatError` naming the
    model's cameras file."""
    from .camera import colmap_model_kind, read_colmap_model
    from .errors import InputError

    d = Path(directory)
    kind = colmap_model_kind(d)
    if kind == "binary":
        check_colmap_binary(d)
    else:
        check_colmap_text(d)
    try:
        return read_colmap_model(d)
    except InputError as e:
        msg = str(e)
        if str(d) in msg:
            raise
        raise FormatError(f"{d / ('cameras.bin' if kind == 'binary' else 'cameras.txt')}: {msg}") from None
