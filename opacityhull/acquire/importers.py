"""External calibrated image sets → sessions that ``build`` accepts.

Two sources:

* ``import_colmap``: a COLMAP model — binary (``cameras.bin``, ``images.bin``, ...,
  read through ``pycolmap``) or text (``cameras.txt``, ``images.txt``); ``.bin`` wins
  over ``.txt`` as in COLMAP — with its images and optional masks (a folder of
  single-channel images named like the images, COLMAP's ``img.jpg.png`` convention
  included). Camera models with an exact OpenCV equivalent are mapped
  (:func:`opacityhull.camera.colmap_intrinsics`), others are refused by name.
* ``import_nerfstudio``: a nerfstudio / instant-ngp / Blender-synthetic
  ``transforms.json``: intrinsics ``fl_x fl_y cx cy w h`` (per frame, else top level;
  or ``camera_angle_x`` [+ ``camera_angle_y``]), ``OPENCV`` distortion ``k1 k2 k3 p1
  p2``, per-frame ``file_path`` (relative to the JSON file; Blender sets leave out
  ``.png``) and ``transform_matrix`` (OpenGL camera-to-world), optional ``mask_path``
  (on every frame or none, as nerfstudio requires). ``applied_transform`` — the
  rigid map nerfstudio's ``ns-process-data`` applied to the source (e.g. COLMAP) world
  — is undone, so the session's world is the source's world and the cameras equal
  those of ``import colmap`` on the same model; it is recorded in ``[import]``.
  instant-ngp's ``scale``/``offset``/``aabb_scale`` are loader settings, not part of
  the poses, and are ignored.

Images are PNG/JPG (sRGB-decoded to linear) or EXR (taken as linear). The matte of a
view is its mask file when given, else the image's own alpha channel (RGBA PNG, EXR
with A), else the view has none.

Both write a session with

* phase ``lightfield``: one linear RGB EXR per image, view ``c{i}_t000.000`` (each image
  is its own "camera" at table angle 0 — the poses are not tied by a turntable);
* phase ``mask``: the matte per image as a one-channel EXR (when masks or alpha exist);
* ``cameras/``: a COLMAP text model whose image names are the view ids (read by
  :meth:`Session.view_cameras`), in the source's world frame;
* ``[rig]``: one camera entry per image, derived from its pose as distance, elevation
  and azimuth about the point closest to all optical axes (``target_m``); no lights,
  no displays.

Validation and atomicity: everything that can be checked without pixels (keys, files,
poses, camera models) is checked before anything is written; then the session is
written into a hidden sibling folder ``.NAME.partial-PID`` and renamed onto ``out`` only
when complete, so any failure (a bad image, a mask of the wrong size, an empty mask,
a full disk) leaves no ``out`` behind. Errors: malformed source files (missing keys,
unparsable JSON, zero or non-unit quaternions, non-finite or non-rigid poses,
unsupported camera models) are :class:`FormatError` (exit 4); files that do not fit
together (missing image, image or mask of another size than its camera, an empty or
full matte, a non-empty ``out``) are :class:`InputError` (exit 2); a full disk or a
read-only file system is a ``WriteError`` (an ``InputError``, exit 2) naming the path.

Mattes: a matte is *empty* when no pixel reaches 0.5 (no object: such a view would
carve the whole hull away) — always an error; *full* when no pixel is below 0.5 (no
background) — an error by default because it is almost always a wrong mask convention
(inverted, or nerfstudio's "all pixels valid" loss mask), allowed with
``allow_full_masks=True`` for genuine close-ups, where such a view carves nothing.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable, Iterator

import numpy as np

from .. import __version__
from ..camera import Camera, camera_from_nerfstudio, colmap_model_kind, write_colmap_text
from ..errors import FormatError, InputError, OpacityHullError
from ..imageio import fsync_dir, read_exr, read_png
from ..riggeometry import view_id
from ..outputs import check_output
from ..session import SessionWriter, shot_key

try:  # the shared write-failure mapping (errors.py); older trees lack it
    from ..errors import WriteError, write_error
except ImportError:  # pragma: no cover
    WriteError, write_error = InputError, None

__all__ = ["import_colmap", "import_nerfstudio", "closest_point_to_axes", "MATTE_HALF"]

log = logging.getLogger(__name__)

_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff")
#: A matte pixel is object when alpha >= MATTE_HALF (the default silhouette threshold of build).
MATTE_HALF = 0.5
_WRITE_ERRNOS = {
    errno.ENOSPC: "the disk is full (ENOSPC)",
    errno.EDQUOT: "the disk quota is exceeded (EDQUOT)",
    errno.EROFS: "the file system is read-only (EROFS)",
    errno.EACCES: "permission denied (EACCES)",
    errno.EPERM: "operation not permitted (EPERM)",
}
#: nerfstudio camera models that are perspective (its CAMERA_MODEL_TO_TYPE); the rest are refused.
_NS_PERSPECTIVE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def closest_point_to_axes(centres: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Least-squares point nearest to the lines ``c_i + s d_i``.

    Solves ``sum_i (I - d_i d_iᵀ)(p - c_i) = 0``. When the lines do not pin a point
    (all parallel, or a single camera) the system is rank deficient and the solution
    closest to the centroid of the centres is returned (pseudo-inverse), so coincident
    or parallel viewpoints still give a finite target.

    Parameters
    ----------
    centres : (N, 3) points on the lines.
    directions : (N, 3) line directions (any length, non-zero).

    Returns
    -------
    (3,) point.
    """
    C = np.asarray(centres, np.float64).reshape(-1, 3)
    D = np.asarray(directions, np.float64).reshape(-1, 3)
    if len(C) == 0 or len(C) != len(D):
        raise InputError(f"closest_point_to_axes: {len(C)} centres and {len(D)} directions")
    n = np.linalg.norm(D, axis=1)
    if np.any(n <= 0) or not np.all(np.isfinite(D)):
        raise InputError("closest_point_to_axes: directions must be finite and non-zero")
    D = D / n[:, None]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(C, D, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    c0 = C.mean(axis=0)
    # solution nearest to the centroid among all least-squares solutions
    return c0 + np.linalg.pinv(A, rcond=1e-9) @ (b - A @ c0)


# --------------------------------------------------------------------------- files


def _find(folder: Path, name: str, *, exts=_IMAGE_EXTS) -> Path | None:
    """``folder/name``, else ``name`` + an image extension (COLMAP's mask convention
    ``img.jpg.png``, Blender's extension-less ``file_path``), else ``name`` with its
    extension replaced."""
    rel = Path(name)
    cands = [folder / rel] + [folder / (name + e) for e in exts]
    if rel.suffix:
        cands += [folder / rel.with_suffix(e) for e in exts]
    for p in cands:
        if p.is_file():
            return p
    return None


def _read_rgb_alpha(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    if path.suffix.lower() == ".exr":
        img = read_exr(path)
        if img.shape[2] in (2, 4):
            return (np.repeat(img[..., :1], 3, -1) if img.shape[2] == 2 else img[..., :3]), img[..., -1]
        return (np.repeat(img, 3, -1) if img.shape[2] == 1 else img[..., :3]), None
    img = read_png(path)  # sRGB-decoded colour, alpha untouched
    if img.shape[2] == 1:
        return np.repeat(img, 3, -1), None
    if img.shape[2] == 2:
        return np.repeat(img[..., :1], 3, -1), img[..., 1]
    if img.shape[2] == 4:
        return img[..., :3], img[..., 3]
    return img[..., :3], None


def _read_mask(path: Path) -> np.ndarray:
    m = read_exr(path) if path.suffix.lower() == ".exr" else read_png(path, linear=True)
    if m.shape[2] == 4:
        return m[..., 3]
    if m.shape[2] == 2:
        return m[..., 1]
    return m[..., 0]


@dataclass(frozen=True, kw_only=True)
class _View:
    cam: Camera
    image: Path
    mask: Path | None
    source: str  # the name in the source (COLMAP image name, nerfstudio file_path)
    what: str  # how errors name the view ("COLMAP image 'a.png'", "frame 3 ('./r_3')")


@dataclass(frozen=True, kw_only=True)
class _Imported:
    """What an importer read, for :func:`_write_session` to write."""

    kind: str  # "colmap", "nerfstudio"
    source: str  # the path imported from, as given
    views: list[_View]
    meta: dict  # the importer's own keys of the session's [import] table
    report: dict  # the importer's own keys of the returned report (after the common ones)
    how_to_mask: str = "give masks or RGBA images"  # how the user supplies a matte for this format


# --------------------------------------------------------------------------- staging


def _check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"--out {out}: the folder is not empty (or is a file); choose a new or empty folder")


def _write_failure(exc: BaseException, out: Path) -> InputError | None:
    """The error naming the path for a write that failed for lack of room or rights
    (``None`` when ``exc`` is something else)."""
    msg = None
    if WriteError is not InputError and isinstance(exc, WriteError):  # imageio already named the file
        msg = str(exc).split(" — ")[0]
    elif isinstance(exc, OSError) and exc.errno in _WRITE_ERRNOS:
        msg = f"cannot write {exc.filename or out}: {_WRITE_ERRNOS[exc.errno]}"
    elif write_error is not None and not isinstance(exc, OpacityHullError):
        we = write_error(exc, out.absolute().parent)  # codecs report a full disk as RuntimeError
        msg = str(we).split(" — ")[0] if we is not None else None
    if msg is None:
        return None
    return WriteError(
        f"--out {out}: {msg}; the partial import was removed, nothing was written — free space or choose another --out"
    )


@contextmanager
def _staged(out: Path) -> Iterator[Path]:
    """Yield a fresh sibling folder to write into; on success it becomes ``out``
    (renamed, parent directory fsynced), on any failure it is removed."""
    _check_out(out)
    parent = out.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = parent / f".{out.name}.partial-{os.getpid()}"
        if tmp.exists():  # left by a killed import of this pid number
            shutil.rmtree(tmp)
    except OSError as e:
        raise (_write_failure(e, out) or InputError(f"--out {out}: cannot create a folder next to it ({e})")) from None
    try:
        yield tmp
        if out.exists():
            out.rmdir()  # empty (checked above); rename() would replace it too, but not on every OS
        os.rename(tmp, out)
        fsync_dir(parent)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, Exception):
            we = _write_failure(e, out)
            if we is not None:
                raise we from None
        raise


# --------------------------------------------------------------------------- common writer


def _add_view_image(w, phase: str, camera: int, pixels, source: str, **fields) -> None:
    """One imported image (table angle 0, one exposure) of ``camera`` in ``phase``."""
    key = shot_key(phase, camera, 0.0)
    w.add_image(
        np.ascontiguousarray(pixels, np.float32),
        id=f"{key}/e0",
        shot=key,
        phase=phase,
        camera=camera,
        table_deg=0.0,
        rel_path=f"images/{key}_e0.exr",
        extra={"source": source},
        **fields,
    )


def _matte_problem(alpha: np.ndarray) -> str | None:
    obj = alpha >= MATTE_HALF
    if not obj.any():
        return "empty"
    if obj.all():
        return "full"
    return None


def _write_session(
    out: Path, found: _Imported, *, allow_full_masks: bool, progress: Callable[[int, int], None] | None
) -> dict:
    views, kind, source = found.views, found.kind, found.source
    centres = np.array([v.cam.centre_world for v in views])
    forwards = np.array([v.cam.forward_world for v in views])
    target = closest_point_to_axes(centres, forwards)
    geo_cams = []
    view_cams: list[Camera] = []
    vids = []
    for i, v in enumerate(views):
        cam = v.cam
        off = cam.centre_world - target
        d = float(np.linalg.norm(off))
        if d < 1e-9:  # the camera sits on the target: any direction will do for a nominal entry
            off, d = -cam.forward_world, 1e-6
        el = math.degrees(math.asin(max(-1.0, min(1.0, off[1] / d))))
        az = math.degrees(math.atan2(off[0], off[2]))
        geo_cams.append(
            {
                "name": f"cam{i}",
                "width": int(cam.width),
                "height": int(cam.height),
                "distance_m": d,
                "elevation_deg": el,
                "azimuth_deg": az,
                "focal_px": float(0.5 * (cam.fx + cam.fy)),
                "cx": float(cam.cx),
                "cy": float(cam.cy),
                "gain": 1.0,
            }
        )
        vid = view_id(i, 0.0)
        vids.append(vid)
        view_cams.append(cam.with_name(vid))
    meta = {
        "session": {
            "rig_source": f"import:{kind}:{source}",
            "plan_name": f"import-{kind}",
            "white_level": 1.0,
            "software_version": __version__,
        },
        "rig": {"target_m": [float(x) for x in target], "cameras": geo_cams},
        "plan": {"plan": {"name": f"import-{kind}"}},
        "import": {"kind": kind, **found.meta, "names": [v.source for v in views]},
        "camera_info": [
            {
                "index": i,
                "name": f"cam{i}",
                "width": int(v.cam.width),
                "height": int(v.cam.height),
                "white_level": 1.0,
                "linear": True,
            }
            for i, v in enumerate(views)
        ],
    }
    n_masks = 0
    full_views: list[str] = []
    with _staged(out) as tmp, SessionWriter(tmp).create(meta) as w:
        write_colmap_text(tmp / "cameras", view_cams, names=vids)
        for i, v in enumerate(views):
            cam = v.cam
            rgb, alpha = _read_rgb_alpha(v.image)
            if rgb.shape[:2] != (cam.height, cam.width):
                raise InputError(
                    f"{v.image}: image is {rgb.shape[1]}x{rgb.shape[0]}, but the camera of {v.what} "
                    f"is {cam.width}x{cam.height}"
                )
            if not np.all(np.isfinite(rgb)):
                raise FormatError(f"{v.image}: {int((~np.isfinite(rgb)).sum())} colour values are NaN or Inf")
            matte_file = v.image
            if v.mask is not None:
                alpha, matte_file = _read_mask(v.mask), v.mask
                if alpha.shape != (cam.height, cam.width):
                    raise InputError(
                        f"{v.mask}: mask is {alpha.shape[1]}x{alpha.shape[0]}, but the image of "
                        f"{v.what} is {cam.width}x{cam.height}"
                    )
            if alpha is not None:
                if not np.all(np.isfinite(alpha)):
                    raise FormatError(f"{matte_file}: {int((~np.isfinite(alpha)).sum())} matte values are NaN or Inf")
                prob = _matte_problem(alpha)
                if prob == "empty":
                    raise InputError(
                        f"{matte_file}: the matte of {v.what} is empty (no pixel reaches alpha "
                        f"{MATTE_HALF}: no object), so it would carve the whole hull away; fix the "
                        "mask or leave the image out"
                    )
                if prob == "full":
                    if not allow_full_masks:
                        raise InputError(
                            f"{matte_file}: the matte of {v.what} is full (no pixel below alpha {MATTE_HALF}: no "
                            "background) — an inverted mask or an 'all valid' loss mask? For a genuine close-up "
                            "pass --allow-full-masks (such a view carves nothing)"
                        )
                    full_views.append(v.what)
            if alpha is None:
                # `build` needs a silhouette per view: without one it failed later with exit 4
                raise InputError(
                    f"{v.image}: {v.what} has no matte: the image has no alpha channel and no mask was given; "
                    f"`build` needs one silhouette per view — {found.how_to_mask}"
                )
            _add_view_image(w, "lightfield", i, rgb, v.source, exposure_s=1.0)
            if alpha is not None:
                _add_view_image(w, "mask", i, np.clip(alpha, 0, 1)[..., None], str(matte_file.name))
                n_masks += 1
            if progress is not None:
                progress(i + 1, len(views))
    if full_views:
        log.warning("%d full matte(s) kept (--allow-full-masks): %s", len(full_views), ", ".join(full_views[:5]))
    return {
        "session": str(out),
        "images": len(views),
        "masks": n_masks,
        "full_masks": len(full_views),
        "target_m": [float(x) for x in target],
        "cameras": len(views),
        **found.report,
    }


# --------------------------------------------------------------------------- COLMAP


def import_colmap(
    model_dir,
    images_dir,
    out,
    *,
    masks_dir=None,
    allow_full_masks: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Turn a COLMAP model (binary or text) and its images into a session folder ``out``.

    Parameters
    ----------
    model_dir : path
        COLMAP model folder; ``cameras.bin``/``images.bin`` win over ``.txt``.
    images_dir : path
        Folder the COLMAP image names are relative to.
    out : path
        New (absent or empty) session folder; absent after any failure.
    masks_dir : path, optional
        Mattes named like the images (``name``, ``name.png``, or the stem with an image
        extension). Without it, images with an alpha channel use it as the matte.
    allow_full_masks : bool
        Keep mattes without background pixels (close-ups) instead of refusing them.

    Returns
    -------
    ``{"session", "images", "masks", "full_masks", "target_m", "cameras", "model_format"}``.
    """
    model_dir, images_dir, out = Path(model_dir), Path(images_dir), Path(out)
    if not model_dir.is_dir():
        raise InputError(f"--model {model_dir}: not a folder (expected a COLMAP model, e.g. sparse/0)")
    if not images_dir.is_dir():
        raise InputError(f"--images {images_dir}: not a folder")
    if masks_dir is not None and not Path(masks_dir).is_dir():
        raise InputError(f"--masks {masks_dir}: not a folder")
    check_output(out, {"--model": model_dir, "--images": images_dir, "--masks": masks_dir}, replaces=True)
    _check_out(out)
    kind = colmap_model_kind(model_dir)
    from ..colmapbin import read_colmap_checked

    # sizes checked before pycolmap reads past the end of a truncated file
    entries = read_colmap_checked(model_dir)
    if not entries:
        raise FormatError(f"--model {model_dir}: the {kind} model lists no registered images")
    views = []
    for name, cam in entries:
        p = _find(images_dir, name)
        if p is None:
            raise InputError(f"--images {images_dir}: no image file for COLMAP image {name!r}")
        mp = None
        if masks_dir is not None:
            mp = _find(Path(masks_dir), name)
            if mp is None:
                raise InputError(
                    f"--masks {masks_dir}: no mask for image {name!r} (expected e.g. "
                    f"{Path(masks_dir) / (name + '.png')})"
                )
        views.append(_View(cam=cam, image=p, mask=mp, source=name, what=f"COLMAP image {name!r}"))
    meta = {
        "model": str(model_dir.resolve()),
        "model_format": kind,
        "images": str(images_dir.resolve()),
        "masks": str(Path(masks_dir).resolve()) if masks_dir is not None else "",
    }
    found = _Imported(
        kind="colmap",
        source=str(model_dir),
        views=views,
        meta=meta,
        report={"model_format": kind},
        how_to_mask="pass --masks DIR (one mask per image, named like it, e.g. IMG.png) or use RGBA images "
        "whose alpha is the matte",
    )
    return _write_session(out, found, allow_full_masks=allow_full_masks, progress=progress)


# --------------------------------------------------------------------------- nerfstudio


def _rigid4(name: str, M, where: str) -> np.ndarray:
    A = np.asarray(M, dtype=np.float64)
    if A.shape == (3, 4):
        A = np.vstack([A, [0.0, 0.0, 0.0, 1.0]])
    if A.shape != (4, 4) or not np.all(np.isfinite(A)):
        raise FormatError(f"{where}: {name} must be a finite 3x4 or 4x4 matrix, got shape {A.shape}")
    R = A[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-4 or np.linalg.det(R) <= 0 or not np.allclose(A[3], [0, 0, 0, 1]):
        raise FormatError(
            f"{where}: {name} is not a rigid transform (rotation + translation); scaled or mirrored "
            "worlds are not supported"
        )
    return A


def _number(d: dict, key: str, where: str) -> float:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise FormatError(f"{where}: {key} = {v!r} is not a finite number")
    return float(v)


def import_nerfstudio(
    transforms, out, *, allow_full_masks: bool = False, progress: Callable[[int, int], None] | None = None
) -> dict:
    """Turn a nerfstudio ``transforms.json`` and its images into a session folder ``out``.

    Parameters
    ----------
    transforms : path
        The JSON file; ``file_path``/``mask_path`` are relative to its folder.
    out : path
        New (absent or empty) session folder; absent after any failure.
    allow_full_masks : bool
        Keep mattes without background pixels (close-ups) instead of refusing them.

    Returns
    -------
    ``{"session", "images", "masks", "full_masks", "target_m", "cameras",
    "applied_transform_undone"}``.

    Notes
    -----
    Per frame, each intrinsic key is taken from the frame, else the top level (as
    nerfstudio does). Focal length: ``fl_x``, else ``0.5 w / tan(camera_angle_x / 2)``;
    ``fl_y``, else from ``camera_angle_y``, else ``fl_x``. ``w``/``h`` default to the
    image's size (Blender sets have none) and must match it when given; ``cx``/``cy``
    default to ``w/2``, ``h/2`` (nerfstudio's pixel-centre convention, = OpenCV
    ``w/2 − 0.5``). ``k4`` (nerfstudio's r⁸ term) must be 0 and fisheye or
    equirectangular ``camera_model`` values are refused.
    """
    path = Path(transforms)
    out = Path(out)
    if not path.is_file():
        raise InputError(f"--transforms {path}: no such file (expected a nerfstudio transforms.json)")
    check_output(out, {"--transforms": path, "--transforms' folder (its images)": path.parent}, replaces=True)
    _check_out(out)
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise FormatError(f"{path}: expected a JSON object with 'frames', got {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise FormatError(
            f"{path}: missing key 'frames' (or it is empty): expected a list of frames with "
            "file_path and transform_matrix"
        )
    A = None
    if meta.get("applied_transform") is not None:
        A = _rigid4("applied_transform", meta["applied_transform"], f"{path}")
    file_from_source = A if A is not None else np.eye(4)
    source_from_file = np.linalg.inv(file_from_source)
    root = path.parent
    has_mask = [isinstance(f, dict) and "mask_path" in f for f in frames]
    if any(has_mask) and not all(has_mask):
        i = has_mask.index(False)
        raise FormatError(
            f"{path}: frame {i} has no mask_path but frame {has_mask.index(True)} has one; nerfstudio "
            "needs mask_path on every frame or on none"
        )
    views: list[_View] = []
    sizes: dict[Path, tuple[int, int]] = {}
    for i, fr in enumerate(frames):
        where = f"{path}: frame {i}"
        if not isinstance(fr, dict):
            raise FormatError(f"{where}: expected an object, got {type(fr).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise FormatError(f"{where}: missing key {key!r}")
        fp = str(fr["file_path"])
        where = f"{path}: frame {i} ({fp!r})"

        def get(key, _fr=fr):
            return _fr[key] if key in _fr else meta.get(key)

        model = get("camera_model") or "OPENCV"
        if model not in _NS_PERSPECTIVE:
            raise FormatError(
                f"{where}: camera_model {model!r} not supported (perspective models only: "
                f"{', '.join(_NS_PERSPECTIVE)}; undistort fisheye/equirectangular images first)"
            )
        img = _find(root, fp)
        if img is None:
            raise InputError(f"{where}: image file {root / fp} not found (also tried {fp}.png etc.)")
        mask = None
        if "mask_path" in fr:
            mask = _find(root, str(fr["mask_path"]))
            if mask is None:
                raise InputError(f"{where}: mask file {root / str(fr['mask_path'])} not found")
        num = {
            k: _number(fr if k in fr else meta, k, where)
            for k in (
                "fl_x",
                "fl_y",
                "cx",
                "cy",
                "w",
                "h",
                "k1",
                "k2",
                "k3",
                "k4",
                "p1",
                "p2",
                "camera_angle_x",
                "camera_angle_y",
            )
            if get(k) is not None
        }
        if "w" not in num or "h" not in num:
            if img not in sizes:
                rgb, _ = _read_rgb_alpha(img)  # Blender sets give no size: the image's own
                sizes[img] = (rgb.shape[1], rgb.shape[0])
            num.setdefault("w", float(sizes[img][0]))
            num.setdefault("h", float(sizes[img][1]))
        w, h = num["w"], num["h"]
        if w != int(w) or h != int(h) or w <= 0 or h <= 0:
            raise FormatError(f"{where}: image size w={w}, h={h} must be positive integers")
        fx = _nerf_focal_px(num, "x", w, where)
        if fx is None:
            raise FormatError(f"{where}: missing key 'fl_x' (or 'camera_angle_x'), in the frame or at the top level")
        fy = _nerf_focal_px(num, "y", h, where)
        if fy is None:
            fy = fx
        if num.get("k4", 0.0) != 0.0:
            raise FormatError(
                f"{where}: k4 = {num['k4']} (nerfstudio's r^8 radial term) is not representable in "
                "the OpenCV 5-term model; undistort the images first"
            )
        try:
            T = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise FormatError(f"{where}: transform_matrix is not a numeric matrix") from None
        if T.shape == (3, 4):
            T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
        if T.shape != (4, 4):
            raise FormatError(f"{where}: transform_matrix has shape {T.shape}, expected 4x4 (or 3x4)")
        try:
            cam = camera_from_nerfstudio(
                source_from_file @ T,
                fl_x=fx,
                fl_y=fy,
                cx=num.get("cx", w / 2),
                cy=num.get("cy", h / 2),
                w=int(w),
                h=int(h),
                k1=num.get("k1", 0.0),
                k2=num.get("k2", 0.0),
                k3=num.get("k3", 0.0),
                p1=num.get("p1", 0.0),
                p2=num.get("p2", 0.0),
                name=fp,
            )
        except InputError as e:
            raise FormatError(f"{where}: {e}") from None
        views.append(_View(cam=cam, image=img, mask=mask, source=fp, what=f"frame {i} ({fp!r})"))
    imeta = {
        "transforms": str(path.resolve()),
        "applied_transform": file_from_source[:3].tolist() if A is not None else [],
        "applied_transform_undone": A is not None,
    }
    report = {"applied_transform_undone": A is not None}
    _check_duplicate_frames(path, views)
    found = _Imported(
        kind="nerfstudio",
        source=str(path),
        views=views,
        meta=imeta,
        report=report,
        how_to_mask="add a mask_path to every frame of transforms.json, or use RGBA images whose alpha is the matte",
    )
    return _write_session(out, found, allow_full_masks=allow_full_masks, progress=progress)


def _check_duplicate_frames(path: Path, views: list[_View]) -> None:
    """Two frames of one image file with different cameras cannot both be right: refuse
    (an exact repeat is harmless and kept)."""
    first: dict[Path, tuple[int, _View]] = {}
    for i, v in enumerate(views):
        key = v.image.resolve()
        if key not in first:
            first[key] = (i, v)
            continue
        j, u = first[key]
        a, b = u.cam, v.cam
        same = (
            np.allclose(a.world_from_cam, b.world_from_cam, rtol=0, atol=1e-9)
            and np.allclose(a.K, b.K, rtol=0, atol=1e-9)
            and np.allclose(a.dist, b.dist, rtol=0, atol=1e-12)
        )
        if not same:
            raise FormatError(
                f"{path}: frames {j} and {i} both use the image {v.source!r} with different cameras "
                "(pose or intrinsics); one photograph has one camera — remove the wrong frame"
            )


def _nerf_focal_px(num: dict, axis: str, size_px: float, where: str) -> float | None:
    """``fl_{axis}``, else the focal length from ``camera_angle_{axis}`` (the full field of
    view in radians, over ``size_px``); None if the frame gives neither."""
    if f"fl_{axis}" in num:
        return num[f"fl_{axis}"]
    angle = num.get(f"camera_angle_{axis}")
    if angle is None:
        return None
    if not 0 < angle < math.pi:
        raise FormatError(f"{where}: camera_angle_{axis} = {angle} rad, expected in (0, pi)")
    return 0.5 * size_px / math.tan(0.5 * angle)
