"""External calibrated image sets → sessions that ``build`` accepts.

``import_colmap``: a COLMAP text model (``cameras.txt``, ``images.txt``) with its
images (PNG/JPG, sRGB-decoded to linear; or EXR, taken as linear) and optional masks
(a folder of single-channel images named like the images, or the images' own alpha)
becomes a session with

* phase ``lightfield``: one linear RGB EXR per image, view ``c{i}_t000.000`` (each image
  is its own "camera" at table angle 0 — the poses are not tied by a turntable);
* phase ``mask``: the alpha per image as a one-channel EXR (when masks or alpha exist);
* ``cameras/``: a COLMAP text model whose image names are the view ids (read by
  :meth:`Session.view_cameras`), in COLMAP's world frame;
* ``[rig]``: one camera entry per image, derived from its pose as distance, elevation
  and azimuth about the point closest to all optical axes (``target_m``); no lights,
  no displays.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..camera import Camera, read_colmap_text, write_colmap_text
from ..errors import FormatError, InputError
from ..imageio import read_exr, read_png
from ..riggeometry import view_id
from ..session import SessionWriter, shot_key

__all__ = ["import_colmap", "closest_point_to_axes"]

_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff")


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
    for c, d in zip(C, D):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    c0 = C.mean(axis=0)
    # solution nearest to the centroid among all least-squares solutions
    return c0 + np.linalg.pinv(A, rcond=1e-9) @ (b - A @ c0)


def _find(folder: Path, name: str, *, exts=_IMAGE_EXTS) -> Path | None:
    """``folder/name``, else ``name`` + an image extension (COLMAP's mask convention
    ``img.jpg.png``), else ``name`` with its extension replaced."""
    rel = Path(name)
    cands = [folder / rel] + [folder / (name + e) for e in exts] + [folder / rel.with_suffix(e) for e in exts]
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


def import_colmap(model_dir, images_dir, out, *, masks_dir=None,
                  progress: Callable[[int, int], None] | None = None) -> dict:
    """Turn a COLMAP text model and its images into a session folder ``out``.

    Returns ``{"session", "images", "masks", "target_m", "cameras"}``.
    """
    model_dir, images_dir, out = Path(model_dir), Path(images_dir), Path(out)
    if not images_dir.is_dir():
        raise InputError(f"--images {images_dir}: not a folder")
    if masks_dir is not None and not Path(masks_dir).is_dir():
        raise InputError(f"--masks {masks_dir}: not a folder")
    if out.exists() and any(out.iterdir()):
        raise InputError(f"--out {out}: the folder is not empty; choose an empty folder")
    entries = read_colmap_text(model_dir)
    if not entries:
        raise FormatError(f"--model {model_dir}: images.txt lists no images")
    # resolve every file before writing anything
    files = []
    for name, cam in entries:
        p = _find(images_dir, name)
        if p is None:
            raise InputError(f"--images {images_dir}: no image file for COLMAP image {name!r}")
        mp = None
        if masks_dir is not None:
            mp = _find(Path(masks_dir), name)
            if mp is None:
                raise InputError(f"--masks {masks_dir}: no mask for image {name!r} (expected e.g. "
                                 f"{Path(masks_dir) / (name + '.png')})")
        files.append((name, cam, p, mp))

    centres = np.array([cam.centre_world for _, cam in entries])
    forwards = np.array([cam.forward_world for _, cam in entries])
    target = closest_point_to_axes(centres, forwards)
    geo_cams = []
    view_cams: list[Camera] = []
    vids = []
    for i, (name, cam) in enumerate(entries):
        off = cam.centre_world - target
        d = float(np.linalg.norm(off))
        if d < 1e-9:  # the camera sits on the target: any direction will do for a nominal entry
            off, d = -cam.forward_world, 1e-6
        el = math.degrees(math.asin(max(-1.0, min(1.0, off[1] / d))))
        az = math.degrees(math.atan2(off[0], off[2]))
        geo_cams.append({"name": f"cam{i}", "width": int(cam.width), "height": int(cam.height), "distance_m": d,
                         "elevation_deg": el, "azimuth_deg": az, "focal_px": float(0.5 * (cam.fx + cam.fy)),
                         "cx": float(cam.cx), "cy": float(cam.cy), "gain": 1.0})
        vid = view_id(i, 0.0)
        vids.append(vid)
        view_cams.append(cam.with_name(vid))

    meta = {
        "session": {"rig_source": f"import:colmap:{model_dir}", "plan_name": "import-colmap", "white_level": 1.0,
                    "software_version": __version__},
        "rig": {"target_m": [float(x) for x in target], "cameras": geo_cams},
        "plan": {"plan": {"name": "import-colmap"}},
        "import": {"kind": "colmap", "model": str(model_dir.resolve()), "images": str(images_dir.resolve()),
                   "masks": str(Path(masks_dir).resolve()) if masks_dir is not None else "",
                   "names": [n for n, _ in entries]},
        "camera_info": [{"index": i, "name": f"cam{i}", "width": int(c.width), "height": int(c.height),
                         "white_level": 1.0, "linear": True} for i, (_, c) in enumerate(entries)],
    }
    n_masks = 0
    with SessionWriter(out).create(meta) as w:
        write_colmap_text(out / "cameras", view_cams, names=vids)
        for i, (name, cam, p, mp) in enumerate(files):
            rgb, alpha = _read_rgb_alpha(p)
            if rgb.shape[:2] != (cam.height, cam.width):
                raise FormatError(f"{p}: image is {rgb.shape[1]}x{rgb.shape[0]}, COLMAP camera says "
                                  f"{cam.width}x{cam.height}")
            if mp is not None:
                alpha = _read_mask(mp)
                if alpha.shape != (cam.height, cam.width):
                    raise FormatError(f"{mp}: mask is {alpha.shape[1]}x{alpha.shape[0]}, image is "
                                      f"{cam.width}x{cam.height}")
            key = shot_key("lightfield", i, 0.0)
            w.add_image(np.ascontiguousarray(rgb, np.float32), id=f"{key}/e0", shot=key, phase="lightfield",
                        camera=i, table_deg=0.0, rel_path=f"images/{key}_e0.exr", exposure_s=1.0,
                        extra={"source": name})
            if alpha is not None:
                mkey = shot_key("mask", i, 0.0)
                w.add_image(np.ascontiguousarray(np.clip(alpha, 0, 1)[..., None], np.float32), id=f"{mkey}/e0",
                            shot=mkey, phase="mask", camera=i, table_deg=0.0, rel_path=f"images/{mkey}_e0.exr",
                            extra={"source": str(mp.name if mp is not None else p.name)})
                n_masks += 1
            if progress is not None:
                progress(i + 1, len(files))
    return {"session": str(out), "images": len(files), "masks": n_masks, "target_m": [float(x) for x in target],
            "cameras": len(files)}
