"""Exports of a model folder to the formats other tools read.

* ``nerfstudio`` — ``transforms.json`` + 8-bit sRGB images (RGBA, or RGB + single-channel
  ``mask_path``) + ``sparse_pc.ply`` (coloured surfel positions, ``ply_file_path``).
* ``colmap`` — ``sparse/0`` in COLMAP text and binary (written by pycolmap), ``images/``,
  points3D = surfel positions with their mean colour and tracks from the visibility bits.
* ``ply`` — ``points.ply`` (x y z nx ny nz red green blue alpha) and ``splats.ply``
  (the 3DGS layout: ``f_dc_*``, ``f_rest_*``, ``opacity`` logit, ``scale_*`` log, ``rot_*``):
  a model built with ``--optimize`` exports its fitted splats (``MODEL/optimized/``), any
  other the hull's surfels with an SH fit to the views (``--splats`` chooses).
* ``opencv`` — one FileStorage YAML per physical camera (``world_from_cam`` =
  ``rig_from_cam``) and one per view under ``views/``.
* ``mesh`` — ``mesh.ply`` and ``mesh.obj`` with vertex colours (:mod:`.mesh`).

Camera conventions are converted in :mod:`opacityhull.camera` only; this module decides
the layout. Each file is written atomically, and a format's folder is first built next to
``out`` and renamed into place, so a failed export leaves nothing half-written.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import InputError
from ..imageio import replacing_dir
from ..outputs import check_output, check_replaceable
from ..model import OpacityHullModel

log = logging.getLogger(__name__)

__all__ = [
    "FORMATS",
    "ExportFormat",
    "export_model",
    "export_nerfstudio_model",
    "export_colmap_model",
    "export_ply",
    "export_fitted_ply",
    "export_opencv",
    "splat_params",
]

ExportFormat = Literal["nerfstudio", "colmap", "ply", "opencv"]
FORMATS: tuple[str, ...] = ("nerfstudio", "colmap", "ply", "opencv", "mesh")


def _views(model: OpacityHullModel) -> list[np.ndarray]:
    return [model.load_view_rgba(i) for i in range(len(model.views))]


def _write_png_u8(path: Path, img01: np.ndarray) -> None:
    from ..imageio import write_png

    write_png(path, img01, bits=8)


def _points_ply(path: Path, pos, nrm, rgb_lin, alpha, *, with_alpha: bool = True) -> None:
    from plyfile import PlyData, PlyElement

    from ..imageio import atomic_path, srgb_encode

    fields = [(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")] + [(k, "u1") for k in ("red", "green", "blue")]
    if with_alpha:
        fields.append(("alpha", "u1"))
    arr = np.empty(len(pos), dtype=fields)
    for i, k in enumerate("xyz"):
        arr[k] = pos[:, i]
        arr["n" + k] = nrm[:, i]
    c8 = np.round(np.clip(srgb_encode(np.clip(rgb_lin, 0, 1)), 0, 1) * 255).astype(np.uint8)
    arr["red"], arr["green"], arr["blue"] = c8[:, 0], c8[:, 1], c8[:, 2]
    if with_alpha:
        arr["alpha"] = np.round(np.clip(alpha, 0, 1) * 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        PlyData(
            [PlyElement.describe(arr, "vertex")],
            text=False,
            byte_order="<",
            comments=["opacityhull export: sRGB 8-bit colour, straight alpha"],
        ).write(str(tmp))


# --------------------------------------------------------------------------- nerfstudio


def export_nerfstudio_model(model: OpacityHullModel, out: Path, *, alpha: Literal["rgba", "mask"] = "rgba") -> dict:
    """nerfstudio dataset: ``transforms.json``, ``images/<view>.png``, [``masks/<view>.png``],
    ``sparse_pc.ply``.

    ``alpha="rgba"``: 8-bit sRGB RGBA PNGs with straight alpha (nerfstudio composites
    them over its background colour). ``alpha="mask"``: RGB PNGs composited over black
    and single-channel masks (255 where α ≥ 0.5), listed as ``mask_path``.
    """
    from ..reconstruct.exports import export_nerfstudio

    if alpha not in ("rgba", "mask"):
        raise InputError(f"--nerfstudio-alpha {alpha!r}: expected 'rgba' or 'mask'")
    imgs, masks = [], []
    for i, v in enumerate(model.views):
        rgba = model.load_view_rgba(i)
        p = out / "images" / f"{v.id}.png"
        if alpha == "rgba":
            _write_png_u8(p, rgba)
        else:
            _write_png_u8(p, rgba[..., :3] * rgba[..., 3:4])
            mp = out / "masks" / f"{v.id}.png"
            from ..imageio import write_png

            write_png(mp, (rgba[..., 3] >= 0.5).astype(np.float32), bits=8, linear=True)
            masks.append(mp.relative_to(out))
        imgs.append(p.relative_to(out))
    from ..surfel_samples import mean_colours

    s = model.surfels
    rgb, a = mean_colours(s, [v.camera for v in model.views], _views(model))
    _points_ply(out / "sparse_pc.ply", s.positions, s.normals, rgb, a, with_alpha=False)
    js = export_nerfstudio(
        [v.camera for v in model.views],
        imgs,
        out / "transforms.json",
        mask_paths=masks if alpha == "mask" else None,
        extra={"ply_file_path": "sparse_pc.ply"},
    )
    return {"transforms": js, "images": len(imgs), "masks": len(masks), "points": len(s)}


# --------------------------------------------------------------------------- colmap


def export_colmap_model(model: OpacityHullModel, out: Path, *, max_points: int = 50000) -> dict:
    """COLMAP dataset: ``images/<view>.png`` (8-bit sRGB RGBA, straight colour, alpha the matte) and ``sparse/0``
    (text and binary, written by pycolmap).

    points3D: up to ``max_points`` surfels (evenly spaced in file order), colour = mean
    sRGB colour over the views that see them, track = one observation in every view whose
    visibility bit is set and inside whose image the surfel projects (COLMAP pixel
    coordinates: +0.5), error = the reprojection error, 0 by construction.
    """
    import pycolmap

    from ..camera import colmap_reconstruction
    from ..imageio import srgb_encode
    from ..surfel_samples import iter_view_samples, mean_colours

    if max_points < 0:
        raise InputError(f"--max-points {max_points}: expected >= 0")
    s = model.surfels
    cams = [v.camera for v in model.views]
    names = [f"{v.id}.png" for v in model.views]
    images = _views(model)
    for v, rgba in zip(model.views, images, strict=True):
        # RGBA (straight colour, alpha = the matte) as the nerfstudio export: RGB over
        # black dropped the matte, so the export could not be imported and built again
        _write_png_u8(out / "images" / f"{v.id}.png", rgba)
    sparse = out / "sparse" / "0"
    rec = colmap_reconstruction(cams, names, share_intrinsics=[v.camera_index for v in model.views])
    by_name = {rec.image(i).name: i for i in rec.images}
    n = len(s)
    pick = (
        np.unique(np.linspace(0, n - 1, min(n, max_points)).round().astype(np.int64))
        if n and max_points
        else np.zeros(0, np.int64)
    )
    rgb, _ = mean_colours(s.subset(pick), cams, images)
    obs: list[tuple[int, np.ndarray, np.ndarray]] = []  # (view, local point index, uv)
    for smp in iter_view_samples(s, cams, images, subset=pick):
        obs.append((smp.view, np.searchsorted(pick, smp.index), smp.uv + 0.5))
    # every image's 2-D points first, then the 3-D points with their tracks
    point_obs: list[list[tuple[int, int]]] = [[] for _ in range(len(pick))]
    for v, loc, uv in obs:
        iid = by_name[names[v]]
        img = rec.image(iid)
        img.points2D = pycolmap.Point2DList([pycolmap.Point2D(np.asarray(p, np.float64)) for p in uv])
        for j, li in enumerate(loc):
            point_obs[int(li)].append((iid, j))
    c8 = np.round(np.clip(srgb_encode(np.clip(rgb, 0, 1)), 0, 1) * 255).astype(np.uint8)
    n_pts = 0
    for li, track_list in enumerate(point_obs):
        if len(track_list) < 2:  # COLMAP drops points seen by fewer than two images
            continue
        tr = pycolmap.Track()
        for iid, j in track_list:
            tr.add_element(iid, j)
        rec.add_point3D(s.positions[pick[li]].astype(np.float64), tr, c8[li])
        n_pts += 1
    sparse.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(sparse))
    rec.write_binary(str(sparse))
    return {
        "sparse": sparse,
        "images": len(names),
        "points3D": n_pts,
        "observations": int(sum(len(t) for t in point_obs if len(t) >= 2)),
    }


# --------------------------------------------------------------------------- ply


def splat_params(model_or_surfels, *, sigma_radius: float = 0.5):
    """3DGS geometry of the surfels: ``scale`` (N, 3) log σ (two tangent axes σ =
    ``sigma_radius``·r, the normal axis 1 % of it) and ``rot`` (N, 4) unit quaternions
    (w, x, y, z) whose rotation maps the local z axis onto the normal."""
    from scipy.spatial.transform import Rotation

    s = model_or_surfels.surfels if hasattr(model_or_surfels, "surfels") else model_or_surfels
    n = s.normals.astype(np.float64)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(nn > 1e-12, n / np.maximum(nn, 1e-12), [0.0, 0.0, 1.0])
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    R = np.stack([t1, t2, n], axis=2)  # columns = local axes
    x, y, z, w = Rotation.from_matrix(R).as_quat().T
    rot = np.stack([w, x, y, z], axis=1)
    sig = np.maximum(sigma_radius * s.radii.astype(np.float64), 1e-9)
    scale = np.log(np.stack([sig, sig, 0.01 * sig], axis=1))
    return scale.astype(np.float32), rot.astype(np.float32)


SplatSource = Literal["auto", "fitted", "hull"]
SPLAT_SOURCES: tuple[SplatSource, ...] = ("auto", "fitted", "hull")


def export_ply(model: OpacityHullModel, out: Path, *, sh_degree: int = 3, splats: str = "auto") -> dict:
    """``points.ply`` (coloured points) and ``splats.ply`` (3DGS layout with SH colour).

    ``splats``: ``"fitted"`` exports the fitted splats of ``build --optimize``
    (:func:`export_fitted_ply`), ``"hull"`` the hull's surfels with an SH fit to the
    captured views, ``"auto"`` the fitted splats when the model has current ones
    (:func:`opacityhull.render.splats.fitted_state`).

    Returns, for the hull, the SH fit report: RMS residual (sRGB [0, 1] units) per degree
    ≤ ``sh_degree``; ``"splats"`` says which was exported.
    """
    from plyfile import PlyData, PlyElement

    from ..imageio import atomic_path
    from ..surfel_samples import mean_colours
    from ..sh import fit_sh

    if not 1 <= int(sh_degree) <= 3:
        raise InputError(f"--sh-degree {sh_degree!r}: expected 1, 2 or 3")
    if ply_source(model, splats) == "fitted":
        return export_fitted_ply(model, out, sh_degree=sh_degree)
    s = model.surfels
    cams = [v.camera for v in model.views]
    images = _views(model)
    rgb, alpha = mean_colours(s, cams, images)
    _points_ply(out / "points.ply", s.positions, s.normals, rgb, alpha)
    fit = fit_sh(s, cams, images, degree=sh_degree)
    scale, rot = splat_params(s)
    B = fit.coeffs.shape[1]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (B - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.empty(len(s), dtype=[(k, "f4") for k in names])
    for i, k in enumerate("xyz"):
        arr[k] = s.positions[:, i]
        arr["n" + k] = s.normals[:, i]
    for c in range(3):
        arr[f"f_dc_{c}"] = fit.coeffs[:, 0, c]
    # 3DGS stores features_rest as (N, 3, B−1) flattened: all R coefficients, then G, then B
    for c in range(3):
        for j in range(1, B):
            arr[f"f_rest_{c * (B - 1) + j - 1}"] = fit.coeffs[:, j, c]
    a = np.clip(alpha, 1e-4, 1 - 1e-4)
    arr["opacity"] = np.log(a / (1 - a))
    for i in range(3):
        arr[f"scale_{i}"] = scale[:, i]
    for i in range(4):
        arr[f"rot_{i}"] = rot[:, i]
    with atomic_path(out / "splats.ply") as tmp:
        PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(tmp))
    return {
        "splats": "hull",
        "points": len(s),
        "sh_degree": int(sh_degree),
        "sh_rms": {str(k): v for k, v in fit.rms.items()},
        "sh_observations": fit.n_obs,
    }


def ply_source(model: OpacityHullModel, splats: str) -> Literal["fitted", "hull"]:
    """What ``export --format ply --splats SPLATS`` exports from ``model``; an
    :class:`InputError` naming ``--splats`` for an unknown value or ``fitted`` on a model
    without current fitted splats."""
    from ..cliutil import check_choice
    from ..render.splats import resolve_renderer

    src = check_choice("--splats", splats, SPLAT_SOURCES, one_of=True)
    used = resolve_renderer(Path(model.root), {"hull": "ulr"}.get(src, src), flag="--splats")
    return "fitted" if used == "fitted" else "hull"


#: The normal-axis std-dev of an exported fitted splat, as a fraction of its smaller
#: tangent one: the fit's surfels are flat discs (2DGS), a 3DGS viewer wants three scales.
FLAT_AXIS_FRACTION = 0.01


def export_fitted_ply(model: OpacityHullModel, out: Path, *, sh_degree: int = 3) -> dict:
    """The fitted splats of ``build --optimize`` as a 3DGS viewer opens them.

    ``splats.ply``: per splat, float32, ``x y z`` (m), ``nx ny nz`` (the disc's normal),
    ``f_dc_0..2`` and ``f_rest_*`` (SH in the display space with 3DGS's ½ offset,
    channel-major, as 3DGS writes them; the fitted degree, or ``sh_degree`` when lower:
    the higher bands are dropped), ``opacity`` (logit), ``scale_0 scale_1`` (log tangent
    std-devs, m) and ``scale_2`` (log of :data:`FLAT_AXIS_FRACTION` × the smaller one: a
    3DGS viewer draws the flat disc as a thin ellipsoid), ``rot_0..3`` (quaternion wxyz).
    Every value but ``scale_2`` is the fit's own (``MODEL/optimized/splats.ply``,
    :mod:`opacityhull.optimize.splatply`). ``points.ply``: the splats' centres with their
    DC colour (view-independent) and opacity.
    """
    from plyfile import PlyData, PlyElement

    from ..sh import SH_C0
    from ..imageio import atomic_path, srgb_decode
    from ..optimize.surfelparams import normals_of
    from ..render.splats import FittedSplats

    fs = FittedSplats.load(Path(model.root))
    p = fs.params
    N = len(fs)
    deg = min(int(sh_degree), fs.sh_degree)
    B = (deg + 1) ** 2
    sh = p["sh"][:, :B, :]
    nrm = normals_of(p["quats"]).astype(np.float32)
    cols: list[tuple[str, np.ndarray]] = [(k, p["means"][:, i]) for i, k in enumerate("xyz")]
    cols += [(f"n{k}", nrm[:, i]) for i, k in enumerate("xyz")]
    cols += [(f"f_dc_{c}", sh[:, 0, c]) for c in range(3)]
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(N, -1)  # (N, 3, B−1): all R, then G, then B
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    cols += [("opacity", p["opacity_logits"])]
    ls = p["log_scales"]
    cols += [("scale_0", ls[:, 0]), ("scale_1", ls[:, 1])]
    cols += [("scale_2", np.minimum(ls[:, 0], ls[:, 1]) + np.float32(np.log(FLAT_AXIS_FRACTION)))]
    cols += [(f"rot_{i}", p["quats"][:, i]) for i in range(4)]
    arr = np.empty(N, dtype=[(k, "<f4") for k, _ in cols])
    for k, v in cols:
        arr[k] = v
    with atomic_path(out / "splats.ply") as tmp:
        PlyData(
            [PlyElement.describe(arr, "vertex")],
            text=False,
            byte_order="<",
            comments=["opacityhull export: the fitted splats of build --optimize (3DGS layout)"],
        ).write(str(tmp))
    dc = np.clip(0.5 + SH_C0 * p["sh"][:, 0, :], 0.0, 1.0)
    opacity = 1.0 / (1.0 + np.exp(-p["opacity_logits"].astype(np.float64)))
    _points_ply(out / "points.ply", p["means"], nrm, srgb_decode(dc), opacity)
    return {"splats": "fitted", "points": N, "sh_degree": deg, "sh_degree_fitted": fs.sh_degree}


# --------------------------------------------------------------------------- opencv


def export_opencv(model: OpacityHullModel, out: Path) -> dict:
    """``<camera>.yaml`` per physical camera (``world_from_cam`` = rig_from_cam, read by
    :func:`opacityhull.camera.read_opencv_yaml` and any OpenCV FileStorage reader) and
    ``views/<view id>.yaml`` per view (object frame)."""
    from ..camera import rig_from_object, write_opencv_yaml

    geo = model.geometry
    names = {}
    if geo is not None:
        for i, c in enumerate(geo.nominal_cameras()):
            names[i] = c.name or f"cam{i}"
    done: set[int] = set()
    for v in model.views:
        write_opencv_yaml(
            out / "views" / f"{v.id}.yaml",
            v.camera.with_name(v.id),
            extra={"table_deg": float(v.table_deg), "camera_index": int(v.camera_index)},
        )
        if v.camera_index in done:
            continue
        done.add(v.camera_index)
        rig_cam = v.camera.with_pose(rig_from_object(v.table_deg) @ v.camera.world_from_cam)
        name = names.get(v.camera_index, f"cam{v.camera_index}")
        write_opencv_yaml(out / f"{name}.yaml", rig_cam.with_name(name), extra={"camera_index": int(v.camera_index)})
    return {"cameras": len(done), "views": len(model.views)}


def _export_mesh(model: OpacityHullModel, out: Path, *, method: str = "marching-cubes") -> dict:
    from .mesh import export_mesh

    return export_mesh(model, out, method=method)


# --------------------------------------------------------------------------- driver


def export_model(model_dir, fmt: str, out, *, overwrite: bool = False, **options) -> dict:
    """Export a model folder to ``out`` in format ``fmt`` (one of :data:`FORMATS`).

    The export is built in a sibling temporary folder and renamed to ``out`` when
    complete; an existing non-empty ``out`` is an :class:`InputError` unless ``overwrite``.
    """
    if fmt not in FORMATS:
        raise InputError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    out = Path(out)
    # before anything is read: `export M --out M --overwrite` deleted the model
    check_output(out, {"MODEL": model_dir}, replaces=True)
    check_replaceable(out, command="export", overwrite=overwrite)
    model = OpacityHullModel.open(model_dir)
    if fmt == "ply":  # bad --splats before the output folder is made
        ply_source(model, options.get("splats", "auto"))
    fn = {
        "nerfstudio": export_nerfstudio_model,
        "colmap": export_colmap_model,
        "ply": export_ply,
        "opencv": export_opencv,
        "mesh": _export_mesh,
    }[fmt]
    with replacing_dir(out, command="export") as tmp:
        summary = fn(model, tmp, **options)
    summary = {k: (out / Path(v).relative_to(tmp) if isinstance(v, Path) else v) for k, v in summary.items()}
    return {"format": fmt, "model": str(Path(model_dir)), "out": str(out), **summary}
