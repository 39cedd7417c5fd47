"""Image files in and out. In memory: float32, linear Rec.709 RGB(A), shape (H, W, C).

* EXR through the OpenEXR package (the OpenCV 5 wheel has no EXR codec). float32 by
  default; half only on request, after clamping to the half range (65504) with a
  warning that names the file, since half overflows to Inf silently otherwise.
* Radiance ``.hdr`` (RGBE) through OpenCV (it stores BGR).
* PNG 8/16-bit through OpenCV, sRGB-encoded on write and decoded on read unless
  ``linear=True`` (masks, data images).

All writes are atomic: a temporary file in the target folder, fsync, rename — a
crash leaves either the old file or the new one, never a torn one.

Alpha convention (one for every EXR the project writes): colour with coverage is stored
**premultiplied** by alpha in an RGBA file, as OpenEXR, Nuke and compositors assume
(over a background ``B`` the pixel is ``RGB + (1 - A) B``). OpenEXR has no standard
flag for it, so :func:`write_exr` states it in the string header attribute
``opacityhull:alpha = "premultiplied"`` (:data:`ALPHA_ATTRIBUTE`) of every file with an
``A`` channel. In memory, renders and the model's ``load_view_rgba`` are straight
(un-premultiplied); :func:`straight_from_premul` is the one conversion, with one
cut-off, :data:`ALPHA_CUTOFF`. PNGs stay straight (8/16-bit PNG has no premultiplied
form).
"""

from __future__ import annotations

import logging
import os
import shutil
import warnings
from contextlib import contextmanager, suppress
from pathlib import Path
from collections.abc import Iterator

import numpy as np

from .errors import FormatError, InputError, ShapeError, write_error

log = logging.getLogger(__name__)

__all__ = [
    "HALF_MAX",
    "to_half",
    "read_image",
    "write_image",
    "read_exr",
    "exr_attribute",
    "write_exr",
    "read_hdr",
    "write_hdr",
    "read_png",
    "write_png",
    "srgb_encode",
    "srgb_decode",
    "atomic_path",
    "replacing_dir",
    "fsync_dir",
    "write_exr_layers",
    "read_exr_layers",
    "read_exr_header",
    "REC709_CHROMATICITIES",
    "ALPHA_ATTRIBUTE",
    "ALPHA_PREMULTIPLIED",
    "ALPHA_CUTOFF",
    "straight_from_premul",
    "premul_from_straight",
]

HALF_MAX = 65504.0

#: OpenEXR ``chromaticities`` attribute of linear Rec.709 / sRGB primaries with a D65
#: white point: (red x, y, green x, y, blue x, y, white x, y).
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)

_CHANNEL_SETS = {1: "Y", 2: "YA", 3: "RGB", 4: "RGBA"}

#: EXR header attribute (string) stating how colour relates to the ``A`` channel.
ALPHA_ATTRIBUTE = "opacityhull:alpha"
#: Its value: colour is premultiplied by alpha (the only convention the project writes).
ALPHA_PREMULTIPLIED = "premultiplied"
#: Below this alpha a pixel has no straight colour (:func:`straight_from_premul` gives
#: 0). 2⁻¹² because (a) dividing by alpha must not amplify quantisation: half floats keep
#: their full 11-bit relative precision down to 2⁻¹⁴ (their smallest normal), and 2⁻¹² keeps
#: two binades of margin above the subnormals, where a stored alpha has few bits; and
#: (b) nothing visible is lost: such a pixel adds at most 2⁻¹² of its colour to any
#: composite, 1/16 of an 8-bit code. It was already the renderer's cut-off (its kernels
#: and the viewer's shader use it); the relighter had the same, the model reader 1e-6 and
#: the matte's straight colour 1e-3 (that one is the build's matte noise floor, an option,
#: ``BuildConfig.alpha_eps``, passed as ``alpha_floor``).
ALPHA_CUTOFF = 2.0**-12


def straight_from_premul(rgba_premul, *, alpha_floor: float = ALPHA_CUTOFF) -> np.ndarray:
    """Premultiplied (H, W, 4) RGBA → straight: alpha clipped to [0, 1], colour divided
    by it where alpha >= ``alpha_floor`` (default :data:`ALPHA_CUTOFF`) and 0 elsewhere
    (NaN/Inf colour becomes 0). Returns a new (H, W, 4) float32 array."""
    out = np.array(rgba_premul, dtype=np.float32, copy=True)
    if out.ndim != 3 or out.shape[2] != 4:
        raise ShapeError(f"premultiplied RGBA has shape {out.shape}, expected (H, W, 4)")
    a = np.clip(np.nan_to_num(out[..., 3], nan=0.0), 0.0, 1.0)
    ok = a >= float(alpha_floor)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        rgb = np.where(ok[..., None], out[..., :3] / np.where(ok, a, 1.0)[..., None], 0.0)
    out[..., :3] = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    out[..., 3] = a
    return out


def premul_from_straight(rgba) -> np.ndarray:
    """Straight (H, W, 4) RGBA → premultiplied (colour times alpha), a new float32 array."""
    out = np.array(rgba, dtype=np.float32, copy=True)
    if out.ndim != 3 or out.shape[2] != 4:
        raise ShapeError(f"RGBA has shape {out.shape}, expected (H, W, 4)")
    out[..., :3] *= out[..., 3:4]
    return out


_LIBRARY_LOCK = __import__("threading").Lock()
#: Lines the image libraries print on a damaged file (OpenEXR's C core and its Python
#: binding, libjpeg, libpng, OpenCV's log): they go into the error message instead.
_LIBRARY_NOISE = ("EXR_ERR_", "Warning: Exception raised", "libpng", "JPEG", "[ERROR:", "[ WARN:", "imread_")


@contextmanager
def library_output() -> Iterator[list[str]]:
    """Capture what C libraries print on file descriptors 1 and 2 inside the block, so a
    damaged file gives one clean error and not raw lines (``EXR_ERR_BAD_CHUNK_LEADER``,
    ``[ERROR:0@0.013] ... RGBE read error``, ``Premature end of JPEG file``) before it.

    Yields a list that receives the library's lines (for the error message). Anything
    else written meanwhile (another thread's progress) is written back to stderr. One
    block at a time (the descriptors are process-wide)."""
    import sys

    lines: list[str] = []
    with _LIBRARY_LOCK:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            saved = (os.dup(1), os.dup(2))
        except (OSError, ValueError, AttributeError):  # no real descriptors (embedded): nothing to capture
            yield lines
            return
        tmp = _capture_file()
        tmp.seek(0)
        tmp.truncate()
        # one capture file per process, reused: a new one per read cost 0.1 ms
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        py_out, py_err = sys.stdout, sys.stderr
        try:
            yield lines
        finally:
            # Python-level prints of the bindings (pybind's "Warning: ...") sit in
            # sys.stdout's buffer: flush them into the capture before restoring
            for stream in (py_out, py_err):
                with suppress(OSError, ValueError, AttributeError):
                    stream.flush()
            libc = _libc()
            if libc is not None:
                libc.fflush(None)
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            tmp.seek(0)
            other = []
            for line in tmp.read().decode("utf-8", "replace").splitlines():
                (lines if any(k in line for k in _LIBRARY_NOISE) else other).append(line)
            if other:
                os.write(2, ("\n".join(other) + "\n").encode())
            for line in lines:
                log.debug("image library: %s", line)


_CAPTURE: dict = {}


def _capture_file():
    """The process's capture file for :func:`library_output` (reopened after a fork)."""
    import tempfile

    import atexit

    f = _CAPTURE.get(os.getpid())
    if f is None:
        f = _CAPTURE[os.getpid()] = tempfile.TemporaryFile()  # noqa: SIM115  one per process, closed at exit
        atexit.register(f.close)
    return f


def _libc():
    """libc for ``fflush(NULL)`` (C stdio buffers of the libraries), or None."""
    if "libc" not in _CAPTURE:
        try:
            import ctypes

            _CAPTURE["libc"] = ctypes.CDLL(None)
        except OSError:
            _CAPTURE["libc"] = None
    return _CAPTURE["libc"]


def _first_noise(lines: list[str]) -> str:
    """The most telling captured library line (OpenEXR's error code first), for a message."""
    best = [ln for ln in lines if "EXR_ERR_" in ln] or lines
    return f": {best[0].strip()}" if best else ""


def _check_jpeg_complete(path: Path) -> None:
    """A JPEG cut short decodes with grey or repeated rows and only libjpeg's warning
    "Premature end of JPEG file": refuse it when the end-of-image marker is missing."""
    with open(path, "rb") as f:
        head = f.read(2)
        if head != b"\xff\xd8":
            return  # not a JPEG by content: OpenCV decides (or fails) by its own sniffing
        f.seek(0, os.SEEK_END)
        n = f.tell()
        f.seek(max(0, n - 4096))
        tail = f.read().rstrip(b"\x00")  # some cameras pad after the marker
    if not tail.endswith(b"\xff\xd9"):
        raise FormatError(f"{path}: truncated JPEG ({n} bytes, no end-of-image marker); copy the file again")


class HalfOverflowWarning(RuntimeWarning):
    """Values above the half-float range were clamped before a half EXR write."""


def fsync_dir(directory) -> None:
    """fsync a directory so a rename into it survives a power cut (no-op where unsupported)."""
    try:
        fd = os.open(str(directory), os.O_RDONLY)
    except OSError as e:  # some filesystems cannot open a folder: the rename itself stands
        log.debug("fsync %s: cannot open the folder (%s)", directory, e)
        return
    try:
        os.fsync(fd)
    except OSError as e:  # EINVAL on filesystems without directory fsync
        log.debug("fsync %s: %s", directory, e)
    finally:
        os.close(fd)


@contextmanager
def replacing_dir(out, *, command: str | None = None) -> Iterator[Path]:
    """A fresh temporary folder next to ``out`` to write into; on success it replaces ``out``
    (removing what was there), on error it is removed and ``out`` is left as it was.

    With ``command`` the folder gets the list of the files written (``outputs.WRITTEN``),
    so a later ``--overwrite`` can tell its own output from anything else: call
    :func:`opacityhull.outputs.check_replaceable` before the work starts."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if command is not None:
        from .outputs import write_written_manifest

        write_written_manifest(tmp, command=command)
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)


class atomic_path:
    """Context manager yielding a temporary path next to ``path``; on success the
    temporary file is fsynced and renamed over ``path``; on error it is removed.

    The temporary name keeps the suffix so that libraries choosing a codec by
    extension still work.
    """

    def __init__(self, path):
        self.path = Path(path)
        self.tmp = self.path.with_name(f".tmp-{os.getpid()}-{id(self):x}-{self.path.name}")

    def __enter__(self) -> Path:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise (write_error(e, self.path) or e) from None
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            try:
                self.tmp.unlink(missing_ok=True)
            except OSError as e:  # the error being raised is the one to report
                log.warning("could not remove the temporary file %s: %s", self.tmp, e)
            # a full or read-only disk surfaces as OSError, OpenEXR's RuntimeError or
            # OpenCV's False: name the path and the cause instead
            if isinstance(exc, Exception):
                err = write_error(exc, self.path)
                if err is not None and err is not exc:
                    raise err from None
            return False
        try:
            with open(self.tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(self.tmp, self.path)
        except BaseException as e:
            try:
                self.tmp.unlink(missing_ok=True)
            except OSError as e2:  # the error being raised is the one to report
                log.warning("could not remove the temporary file %s: %s", self.tmp, e2)
            err = write_error(e, self.path) if isinstance(e, Exception) else None
            if err is not None:
                raise err from None
            raise
        fsync_dir(self.path.parent)
        return False


def _as_hwc(name, image) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4):
        raise ShapeError(f"{name} has shape {np.shape(image)}, expected (H, W), (H, W, 1..4)")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ShapeError(f"{name} is empty: shape {a.shape}")
    return a


# --------------------------------------------------------------------------- sRGB


def srgb_encode(linear) -> np.ndarray:
    """Linear [0, 1] → sRGB-encoded [0, 1] (IEC 61966-2-1). Values are clipped to [0, 1]."""
    x = np.clip(np.nan_to_num(np.asarray(linear, dtype=np.float32), nan=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def srgb_decode(encoded) -> np.ndarray:
    """sRGB-encoded [0, 1] → linear [0, 1]."""
    x = np.asarray(encoded, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


# --------------------------------------------------------------------------- EXR


def to_half(a, *, path) -> tuple[np.ndarray, dict | None]:
    """``a`` as float16 for a half EXR at ``path``: finite values beyond ±65504 are
    clamped, with one :class:`HalfOverflowWarning` naming the file (half would turn them
    into ±Inf silently); NaN and ±Inf stay as they are, as float32 keeps them. Returns the
    array and ``{"values": n, "max_abs": m}`` of what was clamped, or None."""
    a32 = np.asarray(a, dtype=np.float32)
    over = np.isfinite(a32) & (np.abs(a32) > HALF_MAX)
    if not over.any():
        return a32.astype(np.float16), None
    n, mx = int(np.count_nonzero(over)), float(np.max(np.abs(a32[over])))
    warnings.warn(
        f"{path}: {n} values beyond the half-float range (max |v| = {mx:.4g}) clamped to ±{HALF_MAX:g}",
        HalfOverflowWarning,
        stacklevel=3,
    )
    return np.where(over, np.copysign(np.float32(HALF_MAX), a32), a32).astype(np.float16), {"values": n, "max_abs": mx}


def write_exr(
    path, image, *, half: bool = False, channels: str | None = None, header: dict | None = None
) -> dict | None:
    """Write an (H, W[, C]) image as EXR, atomically.

    Parameters
    ----------
    path : path
    image : array (H, W) or (H, W, C), C in 1..4, any float dtype.
    half : bool
        Store 16-bit floats (:func:`to_half`: finite values beyond ±65504 are clamped
        with a :class:`HalfOverflowWarning` naming the file; NaN and ±Inf stay).
    channels : str, optional
        Channel names, one letter each (default Y, YA, RGB, RGBA by channel count).
    header : dict, optional
        Extra header attributes, typed by :func:`exr_attribute` (str → string,
        int → int, float → float, 3 numbers → v3f, ``chromaticities`` → its 8 floats).

    An image with an ``A`` channel must hold colour premultiplied by it (the module's
    convention); the file says so in ``opacityhull:alpha = "premultiplied"``.

    Returns
    -------
    What a half write clamped (:func:`to_half`), or None.
    """
    path = Path(path)
    a = _as_hwc(f"image for {path}", image)
    names = channels or _CHANNEL_SETS[a.shape[2]]
    if len(names) != a.shape[2]:
        raise InputError(f"{len(names)} channel names {names!r} for {a.shape[2]} channels ({path})")
    clamped = None
    if half:
        data, clamped = to_half(a, path=path)
    else:
        data = a.astype(np.float32)
    chans = {n: np.ascontiguousarray(data[:, :, i]) for i, n in enumerate(names)}
    if "A" in names and len(names) > 1:
        header = {ALPHA_ATTRIBUTE: ALPHA_PREMULTIPLIED, **(header or {})}
    _write_exr_channels(path, chans, header)
    return clamped


def _read_exr_channels(path: Path) -> dict[str, np.ndarray]:
    """Every channel of the EXR at ``path`` by name; :class:`FormatError` naming the file
    when it is missing or unreadable."""
    import OpenEXR

    if not path.is_file():
        raise FormatError(f"image {path} not found")
    noise: list[str] = []
    try:
        with library_output() as noise, OpenEXR.File(str(path), separate_channels=True) as f:
            chans = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as e:  # noqa: BLE001  OpenEXR raises bare Exception on truncated files; re-raised, named
        raise FormatError(f"{path}: not a readable EXR file ({e}{_first_noise(noise)})") from None
    if noise or not chans or any(v.dtype == object or v.ndim != 2 for v in chans.values()):
        # the binding may warn and hand back partial pixel data instead of raising
        raise FormatError(f"{path}: damaged EXR file{_first_noise(noise) or ' (no pixel data)'}")
    return chans


def _write_exr_channels(path, chans: dict, header) -> None:
    """Write named float channels as a ZIP-compressed scanline EXR, atomically, with the
    extra ``header`` attributes (checked by :func:`exr_attribute`)."""
    import OpenEXR

    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (header or {}).items():
        hdr[k] = exr_attribute(k, v, path)
    with atomic_path(path) as tmp, OpenEXR.File(hdr, chans) as f:
        f.write(str(tmp))


def exr_attribute(name: str, value, path):
    """A header value as the OpenEXR package types it: str → string, bool/int → int,
    float → float, ``chromaticities`` → a tuple of 8 floats, 3 numbers → v3f."""
    if name == "chromaticities":
        c = tuple(float(x) for x in np.asarray(value, np.float64).reshape(-1))
        if len(c) != 8 or not all(np.isfinite(c)):
            raise InputError(
                f"EXR attribute chromaticities for {path}: expected 8 finite numbers "
                f"(red, green, blue, white x y), got {value!r}"
            )
        return c
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_, int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    a = np.asarray(value)
    if a.shape == (3,) and np.issubdtype(a.dtype, np.number):
        return np.ascontiguousarray(a, dtype=np.float32)  # v3f
    return str(value)


def read_exr_header(path) -> dict:
    """The header attributes of an EXR file as the OpenEXR package returns them
    (``chromaticities`` a tuple of 8 floats, v3f a (3,) float32 array, ...)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"image {path} not found")
    noise: list[str] = []
    try:
        with library_output() as noise, OpenEXR.File(str(path), header_only=True) as f:
            return dict(f.header())
    except Exception as e:  # noqa: BLE001  OpenEXR raises bare Exception on damaged headers; re-raised, named
        raise FormatError(f"{path}: not a readable EXR file ({e}{_first_noise(noise)})") from None


def read_exr(path, *, channels: str | None = None) -> np.ndarray:
    """Read an EXR as float32 (H, W, C).

    Channel order: ``channels`` if given (e.g. ``"RGBA"``), else R, G, B, A in that
    order when present, else Y (and A), else all channels sorted by name. Half data
    are widened to float32.
    """
    path = Path(path)
    ch = _read_exr_channels(path)
    if channels:
        missing = [c for c in channels if c not in ch]
        if missing:
            raise FormatError(f"{path}: missing channel(s) {missing}; has {sorted(ch)}")
        order = list(channels)
    elif all(c in ch for c in "RGB"):
        order = list("RGB") + (["A"] if "A" in ch else [])
    elif "Y" in ch:
        order = ["Y"] + (["A"] if "A" in ch else [])
    else:
        order = sorted(ch)
    return np.stack([ch[c].astype(np.float32) for c in order], axis=-1)


# --------------------------------------------------------------------------- HDR


def read_hdr(path) -> np.ndarray:
    """Read a Radiance RGBE ``.hdr`` as float32 linear RGB (H, W, 3)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"image {path} not found")
    with open(path, "rb") as f:
        magic = f.read(10)
    # OpenCV picks the codec by content: a JPEG renamed .hdr came back as 8-bit pixels,
    # taken as radiance
    if not (magic.startswith(b"#?RADIANCE") or magic.startswith(b"#?RGBE")):
        raise FormatError(
            f"{path}: not a Radiance .hdr file (it starts with {magic[:4]!r}, not '#?RADIANCE'); "
            "convert it to .hdr or .exr (linear radiance)"
        )
    with library_output() as noise:
        bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if bgr is None or bgr.ndim != 3 or bgr.dtype != np.float32:
        raise FormatError(f"{path}: not a readable Radiance .hdr file (truncated or damaged{_first_noise(noise)})")
    return np.ascontiguousarray(bgr[:, :, ::-1].astype(np.float32))


def write_hdr(path, image) -> None:
    """Write linear RGB (H, W, 3) as Radiance RGBE ``.hdr`` (atomic). Negative and NaN
    values cannot be stored in RGBE and raise :class:`InputError`."""
    import cv2

    path = Path(path)
    a = _as_hwc(f"image for {path}", image).astype(np.float32)
    if a.shape[2] != 3:
        raise ShapeError(f"image for {path} has {a.shape[2]} channels, .hdr needs 3")
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise InputError(f"image for {path}: RGBE cannot store negative, NaN or Inf values")
    with atomic_path(path) as tmp:
        # on a full disk OpenCV may report success for an empty file
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(a[:, :, ::-1])) or tmp.stat().st_size == 0:
            raise FormatError(f"OpenCV could not write {path}")


# --------------------------------------------------------------------------- PNG


def write_png(path, image, *, bits: int = 8, linear: bool = False) -> None:
    """Write (H, W[, C]) float data in [0, 1] as PNG, atomically.

    ``linear=False`` (default) sRGB-encodes colour channels (alpha is never encoded);
    ``linear=True`` writes values as they are (masks, data). Values are clipped to
    [0, 1]; NaN becomes 0.
    """
    import cv2

    if bits not in (8, 16):
        raise InputError(f"PNG bit depth must be 8 or 16, got {bits}")
    path = Path(path)
    a = _as_hwc(f"image for {path}", image).astype(np.float32)
    a = np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0)
    if not linear:
        n_colour = 1 if a.shape[2] in (1, 2) else 3
        a = a.copy()
        a[:, :, :n_colour] = srgb_encode(a[:, :, :n_colour])
    a = np.clip(a, 0.0, 1.0)
    maxv = 255 if bits == 8 else 65535
    q = np.round(a * maxv).astype(np.uint8 if bits == 8 else np.uint16)
    if q.shape[2] == 3:
        q = q[:, :, ::-1]
    elif q.shape[2] == 4:
        q = q[:, :, [2, 1, 0, 3]]
    elif q.shape[2] == 2:
        raise ShapeError(f"image for {path}: PNG cannot store 2 channels (gray+alpha) through OpenCV")
    with atomic_path(path) as tmp:
        # on a full disk OpenCV may report success for an empty file
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(q)) or tmp.stat().st_size == 0:
            raise FormatError(f"OpenCV could not write {path}")


def read_png(path, *, linear: bool = False) -> np.ndarray:
    """Read an 8- or 16-bit PNG (or JPEG) to float32 (H, W, C) in [0, 1].

    ``linear=False`` decodes sRGB colour channels to linear light.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"image {path} not found")
    _check_jpeg_complete(path)
    with library_output() as noise:
        q = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if q is None:
        raise FormatError(f"{path}: not a readable PNG/JPEG file{_first_noise(noise)}")
    if q.ndim == 2:
        q = q[:, :, None]
    if q.shape[2] == 3:
        q = q[:, :, ::-1]
    elif q.shape[2] == 4:
        q = q[:, :, [2, 1, 0, 3]]
    maxv = 65535.0 if q.dtype == np.uint16 else 255.0
    a = q.astype(np.float32) / maxv
    if not linear:
        n_colour = 1 if a.shape[2] in (1, 2) else 3
        a[:, :, :n_colour] = srgb_decode(a[:, :, :n_colour])
    return np.ascontiguousarray(a)


# --------------------------------------------------------------------------- dispatch


def read_image(path, **kw) -> np.ndarray:
    """Read EXR, HDR or PNG/JPEG by extension, float32 (H, W, C), linear."""
    suffix = Path(path).suffix.lower()
    if suffix == ".exr":
        return read_exr(path, **kw)
    if suffix in (".hdr", ".pic"):
        return read_hdr(path)
    if suffix in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        return read_png(path, **kw)
    raise InputError(f"{path}: unknown image extension {suffix!r} (expected .exr, .hdr, .png, .jpg)")


def write_image(path, image, **kw) -> None:
    """Write by extension: ``.exr`` (float), ``.hdr`` (RGBE) or ``.png`` (sRGB 8-bit)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".exr":
        write_exr(path, image, **kw)
        return
    if suffix == ".hdr":
        return write_hdr(path, image)
    if suffix == ".png":
        return write_png(path, image, **kw)
    raise InputError(f"{path}: unknown image extension {suffix!r} (expected .exr, .hdr or .png)")


# --------------------------------------------------------------------------- layered EXR


def write_exr_layers(
    path, layers: dict, *, half: bool = False, header: dict | None = None, shape: tuple[int, int] | None = None
) -> dict | None:
    """Write several same-sized images into one EXR as layers ``<name>.R``, ``.G``, ...

    ``layers`` maps a layer name (no dots) to an (H, W, C) array, C in 1..4. Used for a
    view's one-light-at-a-time images: one file per view, one layer per light.
    ``header``: extra attributes, typed as in :func:`write_exr`. ``half`` as in
    :func:`write_exr` (one warning per file); ``shape``: the (H, W) every layer must have.
    Returns what a half write clamped (:func:`to_half`), or None.
    """
    path = Path(path)
    if not layers:
        raise InputError(f"no layers to write to {path}")
    chans = {}
    given = shape is not None
    for name, img in layers.items():
        if "." in name:
            raise InputError(f"layer name {name!r} must not contain '.' ({path})")
        a = _as_hwc(f"layer {name} for {path}", img)
        if shape is None:
            shape = a.shape[:2]
        elif a.shape[:2] != tuple(shape):
            other = "the image is" if given else "other layers are"
            raise ShapeError(f"layer {name} for {path} is {a.shape[:2]}, {other} {tuple(shape)}")
        for i, c in enumerate(_CHANNEL_SETS[a.shape[2]]):
            chans[f"{name}.{c}"] = np.ascontiguousarray(a[:, :, i], dtype=np.float32)
    clamped = None
    if half:
        # one conversion over all layers: one warning and one record per file
        keys = list(chans)
        stacked, clamped = to_half(np.stack([chans[k] for k in keys]), path=path)
        chans = {k: np.ascontiguousarray(stacked[i]) for i, k in enumerate(keys)}
    _write_exr_channels(path, chans, header)
    return clamped


def read_exr_layers(path) -> dict:
    """Inverse of :func:`write_exr_layers`: ``{layer: (H, W, C) float32}``."""
    path = Path(path)
    ch = _read_exr_channels(path)
    groups: dict[str, dict[str, np.ndarray]] = {}
    for k, v in ch.items():
        layer, _, c = k.rpartition(".")
        groups.setdefault(layer, {})[c] = v
    out = {}
    for layer, cs in groups.items():
        for order in ("RGBA", "RGB", "YA", "Y"):
            if set(cs) == set(order):
                out[layer] = np.stack([cs[c].astype(np.float32) for c in order], axis=-1)
                break
        else:
            raise FormatError(f"{path}: layer {layer!r} has channels {sorted(cs)}, expected RGB(A) or Y(A)")
    return out
