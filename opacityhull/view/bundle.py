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

Format 3 — statistical nodes (Kalaiah & Varshney 2003, :mod:`opacityhull.render.spg`)
and positions from the octree code (Botsch, Wiratanaya & Kobbelt 2002):

* ``codebooks.bin``, ``visibility.bin``: the k-means codebooks of the spreads and the
  dictionary of visibility patterns.
* ``nodes_NNN.bin``: the inner nodes as 17-byte PCA records in r_max order (chunks
  doubling in size); the page draws each as one anisotropic EWA splat.
* ``positions.oct``: deflated breadth-first byte codes of the leaves' cells;
  ``counts.oct``: deflated uint8 points per leaf cell (absent when all are 1);
  ``offsets.oct``: deflated uint8 bin per point of the offset along its normal.
* ``leaves.bin``: the leaves' 8-byte records, in the code's decoded order; they are
  records ``n_float …`` of the page's buffers.

:func:`read_bundle` reads it back (the reference for the page's decoder).
"""

from __future__ import annotations

import json
import logging
import shutil
import zlib
from importlib import resources
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from ..imageio import replacing_dir
from ..outputs import check_output, check_replaceable
from ..model import OpacityHullModel
from .octree_code import decode_positions, encode_offsets, encode_positions, median_spacing, pack

log = logging.getLogger(__name__)

__all__ = ["VIEWER_FORMAT", "MAX_VIEWS", "write_bundle", "record_bytes", "read_bundle", "decoded_surfels", "bundle_cut"]

VIEWER_FORMAT = "opacityhull-viewer/3"
MAX_VIEWS = 256
"""Visibility bits per surfel the shader reads (two uvec4 attributes)."""

STATIC_FILES = ("index.html", "viewer.js")


LEAF_QUANTILE = 0.999
"""Leaves with r_max above this quantile of the leaves' r_max keep float positions (see ``_write``)."""


def record_bytes(n_views: int) -> tuple[int, int]:
    """(visibility words, bytes per node attribute record) for ``n_views`` views."""
    words = 4 if n_views <= 128 else 8
    return words, 28 + 4 * words


def _attr_dtype(words: int) -> np.dtype:
    return np.dtype(
        [
            ("nrm", "<f4", 3),
            ("radius", "<f4"),
            ("area", "<f4"),
            ("r_min", "<f4"),
            ("r_max", "<f4"),
            ("vis", "<u4", words),
        ]
    )


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


def write_bundle(
    model_dir,
    out,
    *,
    k: int = 4,
    background=(0.18, 0.18, 0.18),
    first_chunk: int | None = None,
    envmap: str | None = None,
    env_yaw_deg: float | None = None,
    overwrite: bool = True,
    position_cell_m: float | None = None,
    offset_bits: int = 3,
    relight: bool = True,
    probes: Sequence[str] | None = None,
    yaw_steps: int = 72,
    relight_error: float = 0.01,
    relight_rank: int | None = None,
    renderer: str = "auto",
    progress=None,
) -> dict:
    """Write the viewer bundle of a model folder.

    Parameters
    ----------
    model_dir : model folder (read through :class:`OpacityHullModel`).
    out : bundle folder; built as a sibling temporary folder and renamed into place.
    k : initial ULR k of the page (1..8; the page lets the user change it).
    background : initial background colour (linear RGB in [0, 1]); default a neutral
        grey (18 %), against which both the lit and the unlit side of a model show.
    envmap : optional environment map (an equirectangular ``.hdr``/``.exr`` path or
        ``builtin:NAME``) the page can show behind the model (``envmap.bin``).
    env_yaw_deg : its rotation about +Y (default: 180° for ``builtin:`` probes, else 0).
    first_chunk : nodes in the first (coarse) chunk; default max(4096, M/256) of the M
        nodes of the point tree (later chunks double in size).
        Later chunks double in size.
    position_cell_m : leaf cell edge (m) of the octree position code; default the surfels'
        median nearest-neighbour spacing (the seed's balance of sampling and quantisation).
    offset_bits : bits of the per-leaf offset along the normal that refines the octree cell
        centre (Botsch et al. 2002, §5 "offset attributes"); 0 stores cell centres only.
    relight : for a model with reflectance, add the relighting chunks
        (:mod:`opacityhull.view.relit`): the page then has an environment-map picker and a
        rotation slider, and relights on the GPU with the CPU relighter's weights.
    probes : builtin probes to bundle for relighting (default all five); ``envmap`` is added.
    yaw_steps : rotations of each map the light weights are tabulated at (360 / steps apart).
    relight_error : relative relit error the PCA rank is chosen for.
    relight_rank : fix the PCA rank instead (1..16).
    renderer : ``"fitted"`` adds the fitted splats of ``build --optimize``
        (``splats.bin``, :mod:`opacityhull.view.splats`), which the page then draws (the
        ULR data stay: the page switches between the two); ``"ulr"`` leaves them out;
        ``"auto"`` adds them when the model has current ones
        (:func:`opacityhull.render.splats.resolve_renderer`).
    progress : callable(done, total) or None.

    Returns
    -------
    Summary dict: paths, surfels, views, bytes (total, per surfel, per view).
    """
    if not 1 <= int(k) <= 8:
        raise InputError(f"--k {k}: the viewer supports k in [1, 8]")
    if position_cell_m is not None and not (np.isfinite(position_cell_m) and position_cell_m > 0):
        raise InputError(f"--position-cell-m {position_cell_m!r}: expected a finite cell edge > 0 (metres)")
    if not 0 <= int(offset_bits) <= 8:
        raise InputError(f"--offset-bits {offset_bits!r}: expected 0..8")
    bg = np.asarray(background, float).reshape(-1)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise InputError(f"background {background!r}: expected three finite numbers")
    check_output(out, {"MODEL": model_dir, "--envmap": envmap}, replaces=True)
    model = OpacityHullModel.open(model_dir)
    from ..render.splats import resolve_renderer

    used = resolve_renderer(Path(model.root), renderer)
    s = model.surfels
    V = len(model.views)
    if V > MAX_VIEWS:
        raise InputError(f"{model_dir}: {V} views; the viewer reads at most {MAX_VIEWS} visibility bits per surfel")
    N = len(s)
    if N == 0:
        raise InputError(f"{model_dir}/surfels.ply: no surfels to view")
    if relight and model.has_reflectance:
        _check_relight_options(model, probes, yaw_steps, relight_error, relight_rank)
    elif relight and (probes is not None or relight_rank is not None):
        log.warning("%s: the model has no reflectance (no one-light images): nothing to relight", model.root)
    env = None
    env_yaw = 0.0
    if envmap is not None:
        from ..envmap import EnvironmentMap
        from ..relight.envmap import default_yaw_deg, resolve_envmap_path
        from ..render.background import load_background

        env_yaw = default_yaw_deg(envmap) if env_yaw_deg is None else float(env_yaw_deg)
        # the page turns the map by its yaw at lookup: the bundle stores it unturned
        # (EnvironmentMap checks the radiance is finite and >= 0, naming the file)
        env = load_background(str(resolve_envmap_path(envmap)), yaw_deg=0.0, kind="envmap")
        if not isinstance(env, EnvironmentMap):  # kind="envmap" always gives one; the check narrows the type
            raise InputError(f"--envmap {envmap}: not an equirectangular environment map")
    out = Path(out)
    # replace only an earlier bundle (its written-files list, or an older bundle's
    # manifest.json), never a folder of something else
    check_replaceable(out, command="view", overwrite=overwrite, legacy=_is_bundle)
    with replacing_dir(out, command="view") as tmp:
        summary = _write(tmp, model, k, bg, first_chunk, progress, position_cell_m, int(offset_bits))
        summary["renderer"] = used
        if used == "fitted":
            from .splats import write_splats

            summary["splats"] = write_splats(tmp, Path(model.root))
            summary["bytes"] += summary["splats"]["bytes"]
        if env is not None:
            summary["envmap"] = _write_envmap(tmp, env, env_yaw, str(envmap))
        if relight and model.has_reflectance:
            summary["relight"] = _write_relight(
                tmp,
                model,
                summary,
                probes=probes,
                envmap=None if env is None else (str(envmap), env_yaw, "envmap.bin"),
                yaw_steps=yaw_steps,
                relight_error=relight_error,
                relight_rank=relight_rank,
                progress=progress,
            )
    summary["out"] = str(out)
    summary["index"] = str(out / "index.html")
    return summary


def _check_relight_options(model, probes, yaw_steps, relight_error, relight_rank) -> None:
    """The relighting options, checked before anything is written."""
    from ..data import PROBE_NAMES
    from .relit import RANK_MAX

    names = list(PROBE_NAMES) if probes is None else list(probes)
    bad = [p for p in names if p not in PROBE_NAMES]
    if bad:
        raise InputError(f"--probes {','.join(names)}: unknown probe {bad[0]!r}; choose from {', '.join(PROBE_NAMES)}")
    if not (isinstance(yaw_steps, (int, np.integer)) and 1 <= int(yaw_steps) <= 3600):
        raise InputError(f"--yaw-steps {yaw_steps!r}: expected an integer in 1..3600")
    if not (np.isfinite(relight_error) and 0 < relight_error < 1):
        raise InputError(f"--relight-error {relight_error!r}: expected a relative error in (0, 1)")
    K = len(model.light_samples)
    if relight_rank is not None and not 1 <= int(relight_rank) <= min(K, RANK_MAX):
        raise InputError(
            f"--relight-rank {relight_rank}: expected 1..{min(K, RANK_MAX)} (the model has {K} light samples, "
            f"the page supports rank {RANK_MAX})"
        )


def _write_relight(
    tmp: Path, model, summary, *, probes, envmap, yaw_steps, relight_error, relight_rank, progress
) -> dict:
    from ..data import PROBE_NAMES
    from .relit import write_relight

    names = list(PROBE_NAMES) if probes is None else list(probes)
    V = len(model.views)
    done = [0]

    def tick():
        done[0] += 1
        if progress:
            progress(done[0], V)

    rl = write_relight(
        tmp,
        model,
        probes=names,
        extra_envmap=envmap,
        yaw_steps=yaw_steps,
        rel_error_target=relight_error,
        rank=relight_rank,
        progress=tick,
    )
    mp = tmp / "manifest.json"
    man = json.loads(mp.read_text())
    man["relight"] = rl
    mp.write_text(json.dumps(man, indent=1) + "\n")
    model_bytes = rl["basis"]["bytes"] + rl["coeffs"]["bytes"]
    env_bytes = sum(e["weights"]["bytes"] for e in rl["envmaps"])
    summary["bytes"] = sum(p.stat().st_size for p in tmp.iterdir())
    return {
        "rank": rl["rank"],
        "relit_rel_error": rl["relit_rel_error"],
        "stack_rel_error_mean": rl["stack_rel_error_mean"],
        "stack_rel_error_max": rl["stack_rel_error_max"],
        "n_lights": rl["n_lights"],
        "envmaps": [e["name"] for e in rl["envmaps"]],
        "bytes": model_bytes + env_bytes,
        "bytes_per_view": model_bytes / V,
        "bytes_per_surfel": model_bytes / max(1, summary["surfels"]),
        "weights_bytes_per_envmap": env_bytes / len(rl["envmaps"]),
    }


def _write_envmap(tmp: Path, env, yaw_deg: float, spec: str) -> dict:
    img = np.ascontiguousarray(env.radiance, dtype="<f4")
    (tmp / "envmap.bin").write_bytes(img.tobytes())
    meta = {
        "file": "envmap.bin",
        "width": int(img.shape[1]),
        "height": int(img.shape[0]),
        "bytes": img.nbytes,
        "yaw_deg": float(yaw_deg),
        "source": spec,
        "encoding": "float32 linear RGB, equirectangular (opacityhull/envmap.py convention)",
    }
    mp = tmp / "manifest.json"
    man = json.loads(mp.read_text())
    man["envmap"] = meta
    mp.write_text(json.dumps(man, indent=1) + "\n")
    return meta


def _write(tmp, model, k, bg, first_chunk, progress, position_cell_m, offset_bits) -> dict:
    from ..imageio import srgb_encode
    from ..render.config import RenderConfig
    from ..render.renderer import ALPHA_MIN, coverage_full, surfel_areas
    from ..render.spg import LEAF_DTYPE, NODE_DTYPE, NODE_SCALE, node_statistics, pack_nodes, unpack_nodes
    from .lod import build_point_tree

    s, V, cfg = model.surfels, len(model.views), RenderConfig()
    words, rec = record_bytes(V)
    fin = np.all(np.isfinite(s.positions), axis=1) & np.isfinite(s.radii) & (s.radii > 0)
    if not fin.all():
        log.warning(
            "%s: %d surfels with non-finite position or radius left out of the viewer bundle",
            model.root,
            int((~fin).sum()),
        )
        s = s.subset(fin)
        if len(s) == 0:
            raise InputError(f"{model.root}/surfels.ply: no surfel has a finite position and radius")
    areas = surfel_areas(s)
    tree = build_point_tree(s, areas)
    M = len(tree)
    stats = node_statistics(tree)
    pk = pack_nodes(tree, stats)
    n_inner, n_coded = len(pk.inner), len(pk.leaf_ids)
    # codebooks (log σ, float32) and the visibility dictionary (uint32 words per pattern)
    cb = pk.codebook_p.centres.astype("<f4").tobytes() + pk.codebook_n.centres.astype("<f4").tobytes()
    (tmp / "codebooks.bin").write_bytes(cb)
    vis8 = np.zeros((len(pk.vis_dict), 4 * words), np.uint8)
    vis8[:, : pk.vis_dict.shape[1]] = pk.vis_dict
    (tmp / "visibility.bin").write_bytes(vis8.tobytes())
    # what the page will decode: the error codes' values (the LOD table and the leaf threshold)
    dec_tree, _ = unpack_nodes(pk)
    # splats drawn by a uniform threshold t (the page interpolates t for a budget)
    pos_err = np.unique(dec_tree.r_min[dec_tree.r_min > 0])
    ts = np.r_[0.0, np.geomspace(pos_err[0], pos_err[-1] * 1.01, 64)] if pos_err.size else np.zeros(1)
    counts = [int(np.count_nonzero((dec_tree.r_min <= t) & (t < dec_tree.r_max))) for t in ts]
    # Inner nodes are packed records in r_max order (the tree is sorted): any prefix is a
    # complete cut for t ≥ max(its r_max_last, the leaves' largest r_max). The leaves come
    # last, positions from the octree code, records in the code's decoded order.
    sizes = _chunk_sizes(n_inner, first_chunk or max(4096, M // 256)) if n_inner else []
    total_steps = V + len(sizes) + 1
    chunks, done, first = [], 0, 0
    for ci, n in enumerate(sizes):
        name = f"nodes_{ci:03d}.bin"
        data = pk.inner[first : first + n].tobytes()
        (tmp / name).write_bytes(data)
        last = float(dec_tree.r_max[pk.inner_ids[first + n - 1]])
        chunks.append({"file": name, "first": first, "count": n, "bytes": len(data), "r_max_last": min(last, 3e38)})
        first += n
        done += 1
        if progress:
            progress(done, total_steps)
    P = tree.positions[pk.leaf_ids].astype(np.float64)
    cell = position_cell_m if position_cell_m is not None else median_spacing(P)
    oc = None
    for _ in range(8):  # a cell holds at most 255 points (one count byte): refine until it does
        try:
            oc = encode_positions(P, cell_m=cell)
            break
        except InputError:
            cell *= 0.5
    assert oc is not None
    head, codes_z, counts_z = pack(oc)
    (tmp / "positions.oct").write_bytes(codes_z)
    if counts_z:
        (tmp / "counts.oct").write_bytes(counts_z)
    h = oc.size / 2**oc.depth
    leaf_nrm = dec_tree.normals[pk.leaf_ids][oc.order]  # the decoded normals the page offsets along
    off_z = b""
    if offset_bits:
        q = encode_offsets(P[oc.order], decode_positions(oc), leaf_nrm, h, offset_bits)
        off_z = zlib.compress(q.tobytes(), 9)
        (tmp / "offsets.oct").write_bytes(off_z)
    data = pk.leaves[oc.order].tobytes()
    (tmp / "leaves.bin").write_bytes(data)
    leaf_rmax = dec_tree.r_max[pk.leaf_ids]
    t_leaf = float(leaf_rmax[np.isfinite(leaf_rmax)].max()) if np.isfinite(leaf_rmax).any() else 3e38
    leaves_meta = {"file": "leaves.bin", "first": n_inner, "count": n_coded, "bytes": len(data), "r_max_max": t_leaf}
    pos_meta = {
        **head,
        "cell_m": float(h),
        "codes_file": "positions.oct",
        "codes_bytes": len(codes_z),
        "counts_file": "counts.oct" if counts_z else None,
        "counts_bytes": len(counts_z),
        "bits_per_point": 8.0 * (len(codes_z) + len(counts_z)) / n_coded,
        "offset_bits": offset_bits,
        "offsets_file": "offsets.oct" if off_z else None,
        "offsets_bytes": len(off_z),
        "offset_bits_per_point": 8.0 * len(off_z) / n_coded,
        "encoding": "Botsch et al. 2002 breadth-first octree byte codes (bit c = child octant "
        "x + 2y + 4z), deflate (zlib); counts: uint8 points per leaf cell, deflate; "
        "offsets: uint8 bin of λ in [-√3/2, √3/2] cell edges along the normal, deflate",
    }
    spg_meta = {
        **pk.header,
        "node_scale": NODE_SCALE,
        "codebooks": {
            "file": "codebooks.bin",
            "bytes": len(cb),
            "sigma_p": len(pk.codebook_p.centres),
            "sigma_n": len(pk.codebook_n.centres),
        },
        "visibility": {"file": "visibility.bin", "bytes": int(vis8.nbytes), "patterns": len(pk.vis_dict)},
        "node_record_bytes": NODE_DTYPE.itemsize,
        "leaf_record_bytes": LEAF_DTYPE.itemsize,
    }
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
            layers.append(
                {
                    "id": v.id,
                    "width": cam.width,
                    "height": cam.height,
                    "fx": cam.fx,
                    "fy": cam.fy,
                    "cx": cam.cx,
                    "cy": cam.cy,
                    "dist": [float(d) for d in cam.dist],
                    "world_from_cam": [float(x) for x in np.asarray(cam.world_from_cam).ravel()],
                    "centre": [float(x) for x in cam.centre_world],
                }
            )
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
        "n_float": n_inner,
        "lod": {"t": [float(t) for t in ts], "splats": counts},
        "n_views": V,
        "vis_words": words,
        "record_bytes": rec,
        "spg": spg_meta,
        "chunks": chunks,
        "leaves": leaves_meta,
        "positions": pos_meta,
        "views": {
            "file": "views.bin",
            "layer_width": Wp,
            "layer_height": Hp,
            "bytes": Wp * Hp * 4 * V,
            "encoding": "rgba8: sRGB-encoded premultiplied colour, linear alpha",
            "layers": layers,
        },
        "bounds": {
            "min": lo.tolist(),
            "max": hi.tolist(),
            "centre": centre.tolist(),
            "radius": float(0.5 * np.linalg.norm(hi - lo)),
        },
        "render": {
            "k": int(k),
            "sigma_radius": cfg.sigma_radius,
            "filter": cfg.filter,
            "cutoff": cfg.cutoff_sigma,
            "epsilon_z": cfg.epsilon_z,
            "coverage_full": coverage_full(cfg),
            "alpha_min": ALPHA_MIN,
            "m_floor": 1e-6,
            "zdev_footprints": 4.0,
        },
        "background": [float(x) for x in bg],
    }
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    for name in STATIC_FILES:
        shutil.copyfile(_static_dir() / name, tmp / name)
    total = sum(p.stat().st_size for p in tmp.iterdir())
    model_bytes = sum(c["bytes"] for c in chunks) + len(cb) + int(vis8.nbytes)
    model_bytes += leaves_meta["bytes"] + pos_meta["codes_bytes"] + pos_meta["counts_bytes"] + pos_meta["offsets_bytes"]
    n_leaves = int(tree.is_leaf.sum())
    return {
        "surfels": n_leaves,
        "nodes": M,
        "views": V,
        "chunks": len(chunks),
        "bytes": total,
        "bytes_per_surfel": model_bytes / n_leaves,
        "bytes_per_node": NODE_DTYPE.itemsize,
        "bytes_per_leaf": LEAF_DTYPE.itemsize,
        "bytes_per_view": Wp * Hp * 4,
        "octree_coded_surfels": n_coded,
        "float_nodes": n_inner,
        "visibility_patterns": len(pk.vis_dict),
        "position_bits_per_coded_surfel": pos_meta["bits_per_point"],
        "position_offset_bits_per_coded_surfel": pos_meta["offset_bits_per_point"],
        "position_cell_m": pos_meta["cell_m"],
    }


def read_bundle(bundle_dir) -> tuple[dict, np.ndarray, np.ndarray]:
    """(manifest, positions (M, 3) float64, node records (M,)) of a bundle, in the page's
    load order: the packed inner nodes of the chunks, then the octree-coded leaves
    (positions decoded by :func:`opacityhull.view.octree_code.decode_positions`). The
    records are what the page uploads to the GPU (:func:`_attr_dtype`: normal, radius,
    area, r_min, r_max, visibility words) plus ``cov``, the radius tensor of an inner node
    (xx xy xz yy yz zz, m²; zero for the leaves, drawn as discs) — the reference for the
    page's decoder (``decodeNodes`` / ``decodeLeaves`` in ``viewer.js``).
    """
    from ..errors import FormatError

    root = Path(bundle_dir)
    try:
        man = json.loads((root / "manifest.json").read_text())
    except (OSError, ValueError) as e:
        raise FormatError(f"{root}/manifest.json: not a viewer bundle ({e})") from e
    if not isinstance(man, dict) or man.get("format") != VIEWER_FORMAT:
        got = man.get("format") if isinstance(man, dict) else type(man).__name__
        raise FormatError(f"{root}/manifest.json: format {got!r}, expected {VIEWER_FORMAT!r}")
    try:
        return _read_bundle_chunks(root, man)
    except (KeyError, TypeError, ValueError, IndexError, OverflowError) as e:
        # a damaged manifest (a key missing, a count of the wrong type) or chunk
        raise FormatError(f"{root}: damaged viewer bundle ({type(e).__name__}: {e})") from None


def _read_bundle_chunks(root: Path, man: dict) -> tuple[dict, np.ndarray, np.ndarray]:
    from ..errors import FormatError
    from ..render.spg import LEAF_DTYPE, NODE_DTYPE, Codebook, PackedNodes, radius_tensors, unpack_nodes
    from .octree_code import apply_offsets, unpack

    words = int(man["vis_words"])
    S = man["spg"]
    raw = (root / S["codebooks"]["file"]).read_bytes()
    kp, kn = int(S["codebooks"]["sigma_p"]), int(S["codebooks"]["sigma_n"])
    if len(raw) != 4 * (3 * kp + 2 * kn):
        raise FormatError(f"{root}/{S['codebooks']['file']}: {len(raw)} bytes, expected {4 * (3 * kp + 2 * kn)}")
    cp = np.frombuffer(raw[: 12 * kp], "<f4").reshape(kp, 3)
    cn = np.frombuffer(raw[12 * kp :], "<f4").reshape(kn, 2)
    vis = np.frombuffer((root / S["visibility"]["file"]).read_bytes(), np.uint8).reshape(-1, 4 * words)
    inner = []
    for c in man["chunks"]:
        b = (root / c["file"]).read_bytes()
        if len(b) != int(c["count"]) * NODE_DTYPE.itemsize:
            raise FormatError(f"{root}/{c['file']}: {len(b)} bytes, expected {int(c['count']) * NODE_DTYPE.itemsize}")
        inner.append(np.frombuffer(b, NODE_DTYPE))
    inner_rec = np.concatenate(inner) if inner else np.zeros(0, NODE_DTYPE)
    L, H = man["leaves"], man["positions"]
    codes = (root / H["codes_file"]).read_bytes()
    counts = (root / H["counts_file"]).read_bytes() if H.get("counts_file") else b""
    P = decode_positions(unpack(H, codes, counts, what=f"{root}/{H['codes_file']}"))
    leaf_rec = np.frombuffer((root / L["file"]).read_bytes(), LEAF_DTYPE)
    if len(P) != L["count"] or len(leaf_rec) != L["count"]:
        raise FormatError(f"{root}: {len(P)} decoded positions and {len(leaf_rec)} leaf records, expected {L['count']}")
    ni, nl = len(inner_rec), len(leaf_rec)
    pk = PackedNodes(
        header=S,
        inner=inner_rec,
        leaves=leaf_rec,
        inner_ids=np.arange(ni),
        leaf_ids=ni + np.arange(nl),
        codebook_p=Codebook(cp),
        codebook_n=Codebook(cn),
        vis_dict=vis,
    )
    tree, _ = unpack_nodes(pk)
    if H.get("offsets_file"):
        try:
            q = np.frombuffer(zlib.decompress((root / H["offsets_file"]).read_bytes()), np.uint8)
        except zlib.error as e:
            raise FormatError(f"{root}/{H['offsets_file']}: not a deflate stream ({e})") from e
        P = apply_offsets(P, tree.normals[ni:], q, H["cell_m"], int(H["offset_bits"]))
    tree, stats = unpack_nodes(pk, leaf_positions=P)
    dt = np.dtype(_attr_dtype(words).descr + [("cov", "<f4", 6)])
    rec = np.zeros(ni + nl, dt)
    rec["nrm"] = tree.normals
    rec["radius"] = tree.radii
    rec["area"] = tree.areas
    rec["r_min"] = tree.r_min
    rec["r_max"] = tree.r_max
    rec["vis"] = np.ascontiguousarray(tree.visibility).view("<u4")
    if ni:
        rec["cov"][:ni] = radius_tensors(stats.covariance()[:ni], stats.normal[:ni], scale=float(S["node_scale"]))
    return man, tree.positions.astype(np.float64), rec


def decoded_surfels(bundle_dir, *, n_views: int):
    """The model's surfels as the page draws them: the leaves (``r_min == 0``) of
    :func:`read_bundle` with their decoded positions, normals, radii and the first
    ``n_views`` visibility bits, as :class:`~opacityhull.model.Surfels` (what the CPU
    renderer compares the browser with)."""
    from ..model import Surfels

    _, pos, rec = read_bundle(bundle_dir)
    lf = rec["r_min"] == 0
    vis = np.ascontiguousarray(rec["vis"][lf]).view(np.uint8).reshape(int(lf.sum()), -1)[:, : (n_views + 7) // 8]
    return Surfels(positions=pos[lf], normals=rec["nrm"][lf], radii=rec["radius"][lf], visibility=vis, n_views=n_views)


def bundle_cut(bundle_dir, tau: float, eye, *, n_views: int):
    """The cut the page draws at threshold ``tau`` from ``eye``: (surfels, areas, radius
    tensors) for :func:`~opacityhull.render.renderer.render_image` (``splat_cov``; a
    leaf's tensor is its disc), read through :func:`read_bundle`."""
    from ..model import Surfels

    _, pos, rec = read_bundle(bundle_dir)
    d = np.sqrt(((pos.astype(np.float32) - np.asarray(eye, np.float32)) ** 2).sum(1))
    t = np.float32(tau) * d
    m = (rec["r_min"] <= t) & (t < rec["r_max"])
    r = rec[m]
    vis = np.ascontiguousarray(r["vis"]).view(np.uint8).reshape(len(r), -1)[:, : (n_views + 7) // 8]
    s = Surfels(positions=pos[m], normals=r["nrm"], radii=r["radius"], visibility=vis, n_views=n_views)
    cov = r["cov"].astype(np.float64)
    leaf = r["r_min"] == 0
    n = r["nrm"].astype(np.float64)
    disc = (r["radius"].astype(np.float64) ** 2)[:, None] * (
        np.array([1, 0, 0, 1, 0, 1])[None]
        - np.stack(
            [n[:, 0] ** 2, n[:, 0] * n[:, 1], n[:, 0] * n[:, 2], n[:, 1] ** 2, n[:, 1] * n[:, 2], n[:, 2] ** 2], 1
        )
    )
    cov[leaf] = disc[leaf]
    return s, r["area"].astype(np.float32), cov
