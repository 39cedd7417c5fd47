"""Camera exports: OpenCV YAML per rig camera, a COLMAP text model of views, nerfstudio
``transforms.json``, and a picture of the calibration's reprojection errors.

Conventions are converted in :mod:`opacityhull.camera` only (COLMAP and nerfstudio put
the centre of the top-left pixel at (0.5, 0.5); nerfstudio's camera is OpenGL: x right,
y up, z backward); this module decides file layout, grouping and validation. Every file
is written atomically.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np

from ..camera import Camera, nerfstudio_intrinsics, nerfstudio_transform_matrix, write_colmap_text, write_opencv_yaml
from ..errors import InputError

__all__ = [
    "export_opencv_yaml",
    "export_colmap",
    "export_nerfstudio",
    "intrinsics_groups",
    "plot_reprojection_errors",
]


def export_opencv_yaml(result, out_dir) -> list[Path]:
    """One OpenCV FileStorage YAML per rig camera: ``<out_dir>/<camera name>.yaml``.

    Parameters
    ----------
    result : opacityhull.reconstruct.calibration.CalibrationResult
    out_dir : path
        Created if absent. The layout matches a session's ``calibration/`` folder, so
        :meth:`opacityhull.session.Session.calibration_cameras` reads it back.

    Returns
    -------
    list of Path, one per calibrated camera. Each file holds ``camera_matrix``,
    ``distortion_coefficients``, ``image_width``/``height``, ``world_from_cam``
    (= ``rig_from_cam``) and the extras ``reproj_rms_px``, ``used_views``,
    ``table_scale`` and ``object_from_board``.
    """
    out = Path(out_dir)
    paths = []
    for c in result.camera_indices:
        cam, rms = result.rig_cameras[c], result.reproj_rms_px[c]
        name = cam.name or f"cam{c}"
        n_views = sum(1 for v in result.used_views if v.startswith(f"c{c}_t"))
        p = out / f"{name}.yaml"
        write_opencv_yaml(
            p,
            cam,
            extra={
                "reproj_rms_px": float(rms),
                "used_views": int(n_views),
                "table_scale": float(result.table_scale),
                "object_from_board": np.asarray(result.object_from_board, dtype=np.float64),
            },
        )
        paths.append(p)
    return paths


def intrinsics_groups(cameras: Sequence[Camera]) -> list[int]:
    """Group index per camera; cameras with identical size, ``K`` and ``dist`` share one."""
    keys: dict[tuple, int] = {}
    out = []
    for cam in cameras:
        k = (cam.width, cam.height, tuple(np.round(cam.K.ravel(), 12)), tuple(np.round(cam.dist, 15)))
        out.append(keys.setdefault(k, len(keys)))
    return out


def export_colmap(
    cameras: Sequence[Camera],
    names: Sequence[str],
    out_dir,
    *,
    share_intrinsics: Sequence[int] | bool | None = True,
    points3d=None,
) -> Path:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    Parameters
    ----------
    cameras : sequence of Camera
        One per image, poses in the world (object) frame — e.g. from
        :func:`opacityhull.reconstruct.calibration.view_cameras`.
    names : sequence of str
        Image names as COLMAP will see them (relative paths, no spaces).
    out_dir : path
    share_intrinsics : sequence of int, True, False or None
        COLMAP camera index per image (images with the same index share one COLMAP
        camera); ``True``: group cameras with identical intrinsics (one COLMAP camera per
        physical camera of the rig); ``False``/``None``: one COLMAP camera per image.
        A given grouping must not merge different intrinsics.
    points3d : (M, 3) array, optional
        Sparse points for ``points3D.txt``.

    Returns
    -------
    Path of the model folder.
    """
    cameras = list(cameras)
    names = list(names)
    if len(names) != len(cameras):
        raise InputError(f"export_colmap: {len(names)} names for {len(cameras)} cameras")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"export_colmap: duplicate image names {dup[:5]}")
    if share_intrinsics is True:
        groups = intrinsics_groups(cameras)
    elif share_intrinsics is False or share_intrinsics is None:
        groups = list(range(len(cameras)))
    else:
        groups = [int(g) for g in share_intrinsics]
        if len(groups) != len(cameras):
            raise InputError(f"export_colmap: share_intrinsics has {len(groups)} entries for {len(cameras)} cameras")
        natural = intrinsics_groups(cameras)
        first: dict[int, int] = {}
        for i, g in enumerate(groups):
            j = first.setdefault(g, i)
            if natural[j] != natural[i]:
                raise InputError(
                    f"export_colmap: share_intrinsics puts images {names[j]!r} and {names[i]!r} in COLMAP camera "
                    f"group {g}, but their intrinsics differ"
                )
    out = Path(out_dir)
    write_colmap_text(out, cameras, names, share_intrinsics=groups, points3d=points3d)
    return out


def _rel_posix(path, base: Path) -> str:
    p = Path(path)
    if not p.is_absolute():
        return p.as_posix()
    return Path(os.path.relpath(p, base)).as_posix()


def export_nerfstudio(
    cameras: Sequence[Camera],
    image_paths: Sequence,
    out_path,
    *,
    mask_paths: Sequence | None = None,
    extra: dict | None = None,
) -> Path:
    """Write a nerfstudio ``transforms.json``.

    Parameters
    ----------
    cameras : sequence of Camera
        One per image; world frame = the object frame (+Y up).
    image_paths : sequence of paths
        Image files; absolute paths are made relative to the folder of ``out_path``
        (nerfstudio resolves ``file_path`` against it), relative ones are kept.
    out_path : path
        The JSON file (a folder gets ``transforms.json`` inside it).
    mask_paths : sequence of paths, optional
        One mask per image (nerfstudio needs all or none); written as ``mask_path``.
    extra : dict, optional
        More top-level keys (e.g. ``"ply_file_path"``).

    Returns
    -------
    Path of the JSON file.

    Notes
    -----
    Every frame carries its own intrinsics (``fl_x, fl_y, cx, cy, w, h, k1, k2, k3, p1,
    p2`` from :func:`opacityhull.camera.nerfstudio_intrinsics`, principal point +0.5)
    and ``transform_matrix`` = ``world_from_cam`` in the OpenGL camera convention
    (:func:`opacityhull.camera.nerfstudio_transform_matrix`); ``camera_model`` is
    ``OPENCV`` at the top level, as nerfstudio's data parser reads it there.
    """
    from ..imageio import atomic_path

    cameras = list(cameras)
    image_paths = list(image_paths)
    if len(image_paths) != len(cameras):
        raise InputError(f"export_nerfstudio: {len(image_paths)} image paths for {len(cameras)} cameras")
    if mask_paths is not None:
        mask_paths = list(mask_paths)
        if len(mask_paths) != len(cameras) or any(m is None for m in mask_paths):
            raise InputError(
                f"export_nerfstudio: mask_paths must give one mask for every image ({len(cameras)}); "
                "nerfstudio accepts masks on all frames or none"
            )
    out = Path(out_path)
    if out.is_dir() or out.suffix == "":
        out = out / "transforms.json"
    base = out.parent.resolve() if out.parent.exists() else out.parent.absolute()
    frames = []
    for i, (cam, img) in enumerate(zip(cameras, image_paths, strict=True)):
        fr: dict[str, Any] = {"file_path": _rel_posix(img, base)}
        intr = nerfstudio_intrinsics(cam)
        intr.pop("camera_model", None)
        fr.update({k: (float(v) if k not in ("w", "h") else int(v)) for k, v in intr.items()})
        fr["transform_matrix"] = nerfstudio_transform_matrix(cam)
        if mask_paths is not None:
            fr["mask_path"] = _rel_posix(mask_paths[i], base)
        if cam.name:
            fr["name"] = cam.name
        frames.append(fr)
    meta = {"camera_model": "OPENCV", **(extra or {}), "frames": frames}
    for fr in frames:
        for row in fr["transform_matrix"]:
            if not all(np.isfinite(row)):
                raise InputError(f"export_nerfstudio: camera of {fr['file_path']} has a non-finite pose")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
    return out


def plot_reprojection_errors(result, out_path, *, bins: int = 40) -> Path:
    """PNG of a calibration's reprojection errors: histogram of corner error lengths per
    camera, and per-view RMS against table angle (dropped views marked).

    Parameters
    ----------
    result : CalibrationResult
    out_path : path of the PNG (written atomically).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..imageio import atomic_path
    from ..riggeometry import parse_view_id

    err = np.linalg.norm(result.residuals_px, axis=1) if result.residuals_px.size else np.zeros(0)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
    hi = float(np.percentile(err, 99.5)) if err.size else 1.0
    edges = np.linspace(0.0, max(hi, 1e-3), bins + 1)
    for c in result.camera_indices:
        cam = result.rig_cameras[c]
        sel = np.char.startswith(result.residual_views.astype(str), f"c{c}_t")
        ax0.hist(
            err[sel], bins=edges, histtype="step", lw=1.5, label=f"{cam.name}: RMS {result.reproj_rms_px[c]:.3f} px"
        )
    ax0.set_xlabel("corner reprojection error (px)")
    ax0.set_ylabel("corners")
    ax0.set_title(f"rig model, overall RMS {result.rms_px:.3f} px")
    ax0.legend(fontsize=8)
    for c in result.camera_indices:
        cam = result.rig_cameras[c]
        pts = sorted((parse_view_id(v)[1], r) for v, r in result.per_view_rms_px.items() if v.startswith(f"c{c}_t"))
        if pts:
            a, r = zip(*pts, strict=True)
            ax1.plot(a, r, "o-", ms=3, label=cam.name)
        dropped = [parse_view_id(v)[1] for v in result.dropped_views if v.startswith(f"c{c}_t")]
        if dropped:
            ax1.plot(dropped, np.zeros(len(dropped)), "x", color=ax1.lines[-1].get_color() if pts else "k", ms=7)
    ax1.set_xlabel("table angle (deg)")
    ax1.set_ylabel("per-view RMS (px); x = dropped view")
    ax1.set_xlim(0, 360)
    ax1.legend(fontsize=8)
    fig.tight_layout()
    out = Path(out_path)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return out
