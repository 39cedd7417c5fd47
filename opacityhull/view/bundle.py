"""The static web bundle of a model: ``index.html``, ``viewer.js``, ``manifest.json`` and
binary chunks (layout in ``docs/viewer-format.md``).

The browser does what :func:`opacityhull.render.renderer.render_image` does, on the GPU:
per surfel the k nearest visible views by angle (ULR weights) sampled from a texture
array of the views, EWA resampling kernels ``J V Jᵀ + H`` splatted with an ε-z-buffer
(depth pre-pass, then additive accumulation of Σw·rgba, Σw, Σw·A) and normalised with
edge coverage. The numbers it needs and cannot cheaply compute (the surfel areas of the
coverage term) are computed here, with the same function the CPU renderer uses.

The records are the nodes of a sequential point tree (:mod:`opacityhull.view.lod`): the
surfels are its leaves, coarser discs stand for subtrees, each with its error interval
[r_min, r_max), sorted by r_max, largest first. The page draws a splat budget by choosing
τ and keeping, in the vertex shader, the nodes with r_min ≤ τ·distance < r_max; with the
full budget (τ = 0) exactly the leaves are drawn, i.e. the model itself. Chunks grow in
size, and since the order is coarse first, the first chunk already is a complete coarse
cut: the page draws it at once and refines as chunks arrive.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..model import OpacityHullModel

log = logging.getLogger(__name__)

__all__ = ["VIEWER_FORMAT", "MAX_VIEWS", "write_bundle", "record_bytes"]

VIEWER_FORMAT = "opacityhull-viewer/1"
MAX_VIEWS = 256
"""Visibility bits per surfel the shader reads (two uvec4 attributes)."""

STATIC_FILES = ("index.html", "viewer.js")


def record_bytes(n_views: int) -> tuple[int, int]:
    """(visibility words, bytes per node record) for ``n_views`` views."""
    words = 4 if n_views <= 128 else 8
    return words, 40 + 4 * words


def _chunk_sizes(n: int, first: int) -> list[int]:
    sizes, done, c = [], 0, max(1, first)
    while done < n:
        s = min(c, n - done)
        sizes.append(s)
        done += s
        c *= 2
    return sizes


def _is_bundle(path: Path) -> bool:
    try:
        return json.loads((path / "manifest.json").read_text()).get("format") == VIEWER_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def _static_dir() -> Path:
    return Path(str(resources.files("opacityhull.view") / "static"))


def write_bundle(model_dir, out, *, k: int = 4, background=(0.0, 0.0, 0.0), first_chunk: int | None = None,
                 envmap: str | None = None, env_yaw_deg: float | None = None, overwrite: bool = True,
                 progress=None) -> dict:
    """Write the viewer bundle of a model folder.

    Parameters
    ----------
    model_dir : model folder (read through :class:`OpacityHullModel`).
    out : bundle folder; built as a sibling temporary folder and renamed into place.
    k : initial ULR k of the page (1..8; the page lets the user change it).
    background : initial background colour (linear RGB in [0, 1]).
    envmap : optional environment map (an equirectangular ``.hdr``/``.exr`` path or
        ``builtin:NAME``) the page can show behind the model (``envmap.bin``).
    env_yaw_deg : its rotation about +Y (default: 180° for ``builtin:`` probes, else 0).
    first_chunk : nodes in the first (coarse) chunk; default max(4096, M/256) of the M
        nodes of the point tree (later chunks double in size).
        Later chunks double in size.
    progress : callable(done, total) or None.

    Returns
    -------
    Summary dict: paths, surfels, views, bytes (total, per surfel, per view).
    """
    from ..imageio import srgb_encode
    from ..render.config import RenderConfig
    from ..render.renderer import ALPHA_MIN, coverage_full, surfel_areas

    if not 1 <= int(k) <= 8:
        raise InputError(f"--k {k}: the viewer supports k in [1, 8]")
    bg = np.asarray(background, float).reshape(-1)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise InputError(f"background {background!r}: expected three finite numbers")
    model = OpacityHullModel.open(model_dir)
    s = model.surfels
    V = len(model.views)
    if V > MAX_VIEWS:
        raise InputError(f"{model_dir}: {V} views; the viewer reads at most {MAX_VIEWS} visibility bits per surfel")
    N = len(s)
    if N == 0:
        raise InputError(f"{model_dir}/surfels.ply: no surfels to view")
    env = None
    if envmap is not None:
        from ..relight.envmap import default_yaw_deg, resolve_envmap_path
        from ..render.background import load_background

        yaw = default_yaw_deg(envmap) if env_yaw_deg is None else float(env_yaw_deg)
        env = load_background(str(resolve_envmap_path(envmap)), yaw_deg=yaw, kind="envmap")
        img = env.image
        if not np.all(np.isfinite(img)) or (img < 0).any():
            raise InputError(f"--envmap {envmap}: the map has non-finite or negative texels")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        # replace only an earlier bundle, never a folder of something else
        if not overwrite or not _is_bundle(out):
            raise InputError(f"--out {out}: exists and is not an earlier viewer bundle (no manifest.json of "
                             f"format {VIEWER_FORMAT}); choose an empty or new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        summary = _write(tmp, model, s, V, N, k, bg, first_chunk, progress, srgb_encode, RenderConfig(),
                         ALPHA_MIN, coverage_full, surfel_areas)
        if env is not None:
            summary["envmap"] = _write_envmap(tmp, env, str(envmap))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    summary["out"] = str(out)
    summary["index"] = str(out / "index.html")
    return summary


def _write_envmap(tmp: Path, env, spec: str) -> dict:
    img = np.ascontiguousarray(env.image[:, :, :3], dtype="<f4")
    (tmp / "envmap.bin").write_bytes(img.tobytes())
    meta = {"file": "envmap.bin", "width": int(img.shape[1]), "height": int(img.shape[0]), "bytes": img.nbytes,
            "yaw_deg": float(env.yaw_deg), "source": spec,
            "encoding": "float32 linear RGB, equirectangular (render/background.py convention)"}
    mp = tmp / "manifest.json"
    man = json.loads(mp.read_text())
    man["envmap"] = meta
    mp.write_text(json.dumps(man, indent=1) + "\n")
    return meta


def _write(tmp, model, s, V, N, k, bg, first_chunk, progress, srgb_encode, cfg, alpha_min, coverage_full,
           surfel_areas) -> dict:
    from .lod import build_point_tree

    words, rec = record_bytes(V)
    fin = np.all(np.isfinite(s.positions), axis=1) & np.isfinite(s.radii) & (s.radii > 0)
    if not fin.all():
        log.warning("%s: %d surfels with non-finite position or radius left out of the viewer bundle",
                    model.root, int((~fin).sum()))
        s = s.subset(fin)
        if len(s) == 0:
            raise InputError(f"{model.root}/surfels.ply: no surfel has a finite position and radius")
    areas = surfel_areas(s)
    tree = build_point_tree(s, areas)
    M = len(tree)
    # visibility: packed bytes (LSB first) → little-endian uint32 words, view v = word v//32, bit v%32
    vis8 = np.zeros((M, 4 * words), np.uint8)
    vis8[:, : tree.visibility.shape[1]] = tree.visibility
    recs = np.zeros(M, dtype=[("pos", "<f4", 3), ("nrm", "<f4", 3), ("radius", "<f4"), ("area", "<f4"),
                              ("r_min", "<f4"), ("r_max", "<f4"), ("vis", "<u4", words)])
    recs["pos"] = tree.positions
    recs["nrm"] = tree.normals
    recs["radius"] = tree.radii
    recs["area"] = tree.areas
    recs["r_min"] = tree.r_min
    recs["r_max"] = tree.r_max
    recs["vis"] = vis8.view("<u4")
    assert recs.itemsize == rec
    # splats drawn by a uniform threshold t (the page interpolates t for a budget)
    pos_err = np.unique(tree.r_min[tree.r_min > 0])
    ts = np.r_[0.0, np.geomspace(pos_err[0], pos_err[-1] * 1.01, 64)] if pos_err.size else np.zeros(1)
    counts = [int(np.count_nonzero((tree.r_min <= t) & (t < tree.r_max))) for t in ts]
    N = M
    sizes = _chunk_sizes(N, first_chunk or max(4096, N // 256))
    total_steps = V + len(sizes)
    chunks, done, first = [], 0, 0
    for ci, n in enumerate(sizes):
        name = f"surfels_{ci:03d}.bin"
        data = recs[first: first + n].tobytes()
        (tmp / name).write_bytes(data)
        chunks.append({"file": name, "first": first, "count": n, "bytes": len(data),
                       "r_max_last": min(float(tree.r_max[first + n - 1]), 3e38)})  # JSON has no Infinity
        first += n
        done += 1
        if progress:
            progress(done, total_steps)
    # views: one texture-array layer per view, padded to the largest view
    Wp = max(v.camera.width for v in model.views)
    Hp = max(v.camera.height for v in model.views)
    layers = []
    with open(tmp / "views.bin", "wb") as f:
        for i, v in enumerate(model.views):
            rgba = model.load_view_rgba(i)
            a = np.clip(np.nan_to_num(rgba[..., 3], nan=0.0), 0, 1)
            pre = np.clip(np.nan_to_num(rgba[..., :3], nan=0.0, posinf=1.0), 0, 1) * a[..., None]
            layer = np.zeros((Hp, Wp, 4), np.uint8)
            h, w = a.shape
            layer[:h, :w, :3] = np.round(srgb_encode(pre) * 255)
            layer[:h, :w, 3] = np.round(a * 255)
            f.write(layer.tobytes())
            cam = v.camera
            layers.append({
                "id": v.id, "width": cam.width, "height": cam.height,
                "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "dist": [float(d) for d in cam.dist],
                "world_from_cam": [float(x) for x in np.asarray(cam.world_from_cam).ravel()],
                "centre": [float(x) for x in cam.centre_world],
            })
            done += 1
            if progress:
                progress(done, total_steps)
    # ties between equal angles go to the view first in centre-coordinate order (as on the CPU)
    from ..render.views import prepare_views

    tie = prepare_views([v.camera for v in model.views], None).tie_rank
    for i, L in enumerate(layers):
        L["tie_rank"] = int(tie[i])
    P = s.positions.astype(np.float64)
    lo, hi = P.min(axis=0), P.max(axis=0)
    centre = 0.5 * (lo + hi)
    manifest = {
        "format": VIEWER_FORMAT,
        "model": str(model.root),
        "n_surfels": int(tree.is_leaf.sum()),
        "n_nodes": M,
        "lod": {"t": [float(t) for t in ts], "splats": counts},
        "n_views": V,
        "vis_words": words,
        "record_bytes": rec,
        "chunks": chunks,
        "views": {"file": "views.bin", "layer_width": Wp, "layer_height": Hp, "bytes": Wp * Hp * 4 * V,
                  "encoding": "rgba8: sRGB-encoded premultiplied colour, linear alpha", "layers": layers},
        "bounds": {"min": lo.tolist(), "max": hi.tolist(), "centre": centre.tolist(),
                   "radius": float(0.5 * np.linalg.norm(hi - lo))},
        "render": {"k": int(k), "sigma_radius": cfg.sigma_radius, "filter": cfg.filter, "cutoff": cfg.cutoff_sigma,
                   "epsilon_z": cfg.epsilon_z, "coverage_full": coverage_full(cfg), "alpha_min": alpha_min,
                   "m_floor": 1e-6, "zdev_footprints": 4.0},
        "background": [float(x) for x in bg],
    }
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    for name in STATIC_FILES:
        shutil.copyfile(_static_dir() / name, tmp / name)
    total = sum(p.stat().st_size for p in tmp.iterdir())
    model_bytes = sum(c["bytes"] for c in chunks)
    n_leaves = int(tree.is_leaf.sum())
    return {"surfels": n_leaves, "nodes": M, "views": V, "chunks": len(chunks), "bytes": total,
            "bytes_per_surfel": model_bytes / n_leaves, "bytes_per_node": rec, "bytes_per_view": Wp * Hp * 4}
