"""Silhouettes → hull → surfels → visibility (→ photo refinement) as one function,
:func:`build_geometry`, over per-view alphas and cameras: the build's geometry step and
the geometry holdout of ``eval loo`` run the same code."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any, cast
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, InputError
from ..model import Surfels
from .buildconfig import (
    SHADING_TEXTURE_STD,
    BuildConfig,
    choose_resolution,
    default_carve_tolerance,
    default_dilate_base_px,
)
from .holes import strong_silhouette
from .hull import (
    EmptyHullError,
    HullGrid,
    carve_octree,
    carve_robust,
    enclosed_holes,
    hull_bounds,
    silhouette_from_alpha,
    undistort_silhouette,
    view_rejections,
)
from .lazyviews import CARVE_BATCH_MAX_VIEWS, PackedMasks, _Deferred
from .surfels import sample_hull_surfels
from .visibility import surfel_visibility

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Geometry:
    """What :func:`build_geometry` made: pinhole silhouettes and cameras, the carved
    grid, the surfels with visibility, and what to report."""

    #: pinhole silhouettes per view (:class:`PackedMasks`; a list in geometry pickled before)
    sils: Sequence
    pin: list
    dilations: list
    occ: np.ndarray
    grid: HullGrid
    surfels: Surfels
    info: dict
    notes: list


def _nullstep(name):
    from contextlib import nullcontext

    return nullcontext()


def build_geometry(
    alphas: Sequence[np.ndarray],
    cameras: Sequence[Camera],
    rms_px: Sequence[float],
    view_ids: Sequence[str],
    *,
    config: BuildConfig,
    rig_session: bool = False,
    fallback_box=None,
    step=None,
    progress=None,
    images=None,
    open_holes=None,
    doubtful_extensions=None,
    carve_batch: int | None = None,
    photo_slots: int | None = None,
) -> Geometry:
    """Silhouettes → hull → surfels → visibility from per-view alphas and cameras.

    The build runs this once over all views; ``eval loo --holdout geometry`` runs it
    again without the held-out view. ``rms_px`` is each view's calibration RMS (the
    silhouette dilation), ``fallback_box`` a box for unbounded LPs (the rig volume),
    ``rig_session`` clips the hull at the table top. ``step`` is the build's step timer
    (a context-manager factory taking the step name). ``images``: per-view linear RGB
    (callable ``i → (H, W, 3)`` or a sequence), needed by ``config.refine``.
    ``open_holes``: per view None or an (H, W) bool mask of the enclosed mask holes that
    show the backdrop (:func:`open_hole_masks`); a tolerant carve trusts rejections
    through them like those of the outer contour. ``doubtful_extensions``: per view None or an
    (H, W) bool mask of the outline's thick bright extensions
    (:func:`bright_extension_masks`); a tolerant carve doubts rejections through them like those
    through shadow holes (the counts go to ``info["bright_extensions"]``).
    """
    step = step or _nullstep
    prog = progress or (lambda done, total: None)
    notes: list[str] = []
    V = len(cameras)
    with step("silhouettes"):
        # one view at a time: its alpha read, thresholded, undistorted and bit-packed
        sils, strong_in = PackedMasks(), PackedMasks()
        pin, dil, covers, empty, full = [], [], [], [], []
        base_px = default_dilate_base_px(config, rig_session=rig_session)
        ext_px = ext_views = 0
        for i, cam in enumerate(cameras):
            alpha = alphas[i]
            d = base_px + config.dilate_rms_factor * float(rms_px[i])
            dil.append(int(math.ceil(d - 1e-9)))
            s = silhouette_from_alpha(alpha, threshold=config.alpha_threshold, dilate_px=d)
            del alpha
            oh = None if open_holes is None else open_holes[i]
            db = None if doubtful_extensions is None else doubtful_extensions[i]
            for what, m in (("open_holes", oh), ("doubtful_extensions", db)):
                if m is not None and np.shape(m) != s.shape:
                    raise InputError(f"{what} of view {view_ids[i]}: {np.shape(m)}, expected {s.shape}")
            if oh is not None or db is not None:
                t, n_ext = strong_silhouette(s, open_holes=oh, doubtful_extensions=db)
                if n_ext:
                    ext_px += n_ext
                    ext_views += 1
                strong_in.append(undistort_silhouette(t, cam)[0])
                del t
            else:
                strong_in.append(None)
            del oh, db
            s, pc = undistort_silhouette(s, cam)
            covers.append(float(s.mean()))
            if not s.any():
                empty.append(view_ids[i])
            elif s.all():
                full.append(view_ids[i])
            sils.append(s)
            pin.append(pc)
            del s
        cover = float(np.median(covers))
        if cover > 0.8:
            notes.append(
                f"the silhouettes cover {100 * cover:.0f} % of the images (median): the mattes are nearly "
                "all opaque — were the backdrops lit in the object-present matting shots?"
            )
        if empty:
            raise EmptyHullError(
                f"empty silhouette (alpha <= {config.alpha_threshold} everywhere) in view(s) {', '.join(empty[:10])}"
                f"{' ...' if len(empty) > 10 else ''}: the visual hull would be empty. Check those images, lower "
                "--alpha-threshold, or leave the views out with --exclude-view"
            )
        if full:
            notes.append(f"view(s) {', '.join(full[:10])} are opaque everywhere (full mask): they carve nothing")
    tol = default_carve_tolerance(config, rig_session=rig_session, n_views=V)
    if tol >= V:
        raise ConfigError(f"carve_tolerance {tol} >= the {V} views: every voxel would survive")
    with step("hull"):
        if config.bounds_m is not None:
            lo, hi = (np.asarray(x, dtype=np.float64) for x in config.bounds_m)
        else:
            fb = fallback_box
            if fb is not None and not config.clip_below_table:
                fb = (fb[0] - np.array([0.0, fb[1][1], 0.0]), fb[1])
            lo, hi = hull_bounds(sils, pin, fallback=fb, min_component_frac=config.bounds_min_component_frac)
        res = choose_resolution(lo, hi, pin, config=config)
        pad = 2.0 * float(np.max(hi - lo)) / res.hull_res
        lo_p, hi_p = lo - pad, hi + pad
        if rig_session and config.clip_below_table and config.bounds_m is None:
            lo_p[1] = max(lo_p[1], 0.0)
        grid = HullGrid.from_bounds(lo_p, hi_p, res.hull_res)
        strong = None
        carve_batches = 1
        if tol > 0:
            # a tolerant carve counts rejections over every view at once: unpacked
            sils_l = list(sils)
            # return_stats=True: (occupancy, stats, strong silhouettes)
            occ, ostats, strong = cast(
                "tuple[np.ndarray, Any, Any]",
                carve_robust(
                    sils_l,
                    pin,
                    grid,
                    tolerance=tol,
                    root_cell=config.root_cell,
                    return_stats=True,
                    strong_silhouettes=(
                        None
                        if all(t is None for t in strong_in)
                        else [enclosed_holes(sl) if t is None else t for t, sl in zip(strong_in, sils_l, strict=True)]
                    ),
                ),
            )
        else:
            occ, ostats, carve_batches = _carve_batched(
                sils, pin, grid, root_cell=config.root_cell, batch=carve_batch or CARVE_BATCH_MAX_VIEWS
            )
        n_occ = int(occ.sum())
        if n_occ == 0:
            raise EmptyHullError(
                "the visual hull is empty: the silhouettes have no common volume (inconsistent cameras or mattes?)"
            )
        info = {
            "dilate_base_px": base_px,
            "dilate_px_per_view": dict(zip(view_ids, dil, strict=True)),
            "grid_shape": list(grid.shape),
            "voxel_m": grid.voxel_m,
            "lo_m": grid.lo.tolist(),
            "hi_m": grid.hi.tolist(),
            "occupied_voxels": n_occ,
            "octree_cells": ostats.cells,
            "octree_tests": ostats.tests,
            "resolution": res.to_dict(),
            "carve_tolerance": tol,
            # bright extensions doubted by the tolerant carve (none for a classical one: nothing to doubt)
            "bright_extensions": {"views": ext_views, "px": ext_px} if tol > 0 else {"views": 0, "px": 0},
            "carve_batches": carve_batches,
            "silhouettes_packed_bytes": sils.nbytes,
        }
        # where a view's mask disagrees with the hull (shadow holes, lit cloth, frame
        # edges): the share of the kept voxels it would have carved on its own
        idx = np.argwhere(occ)
        if len(idx) > 200_000:
            idx = idx[np.random.default_rng(0).choice(len(idx), 200_000, replace=False)]
        rej = view_rejections(grid.centres(idx), sils_l, pin).mean(axis=0) if tol > 0 else np.zeros(V)
        info["view_disagreement"] = {view_ids[i]: round(float(rej[i]), 5) for i in range(V)}
        bad = [(view_ids[i], float(rej[i])) for i in np.argsort(-rej) if rej[i] > 0.01]
        info["views_disagreeing_with_hull"] = [v for v, _ in bad]
        if bad:
            notes.append(
                "mask(s) disagree with the hull the other views agree on (tolerant carve kept what "
                "they alone rejected): "
                + ", ".join(f"{v} ({100 * f:.1f} % of the hull)" for v, f in bad[:8])
                + (" ..." if len(bad) > 8 else "")
            )
    with step("surfels"):
        sample = sample_hull_surfels(
            occ,
            grid,
            sils,
            pin,
            oversample=res.oversample,
            bisection_iters=config.bisection_iters,
            radius_scale=config.radius_scale,
            normal_scale_vox=max(1.0, res.pixel_footprint_m / grid.voxel_m),
            tolerance=tol,
            strong_silhouettes=strong,
        )
        if tol > 0:
            del sils_l, strong
        info.update({"pixel_footprint_m": res.pixel_footprint_m, "surfel_spacing_m": sample.spacing_m})
        if sample.spacing_m > 1.5 * res.pixel_footprint_m:
            notes.append(
                f"surfel spacing {sample.spacing_m * 1e3:.2f} mm is coarser than the pixel footprint "
                f"{res.pixel_footprint_m * 1e3:.2f} mm (--hull-res {res.hull_res}): drop --hull-res "
                "for full capture resolution"
            )
    with step("visibility"):
        vis = cast(
            np.ndarray,
            surfel_visibility(
                sample.positions,
                sample.normals,
                sample.radii,
                pin,
                depth_tol_m=config.depth_tol_m,
                facing_cos=config.facing_cos,
            ),
        )
        surfels = Surfels.from_bool(sample.positions, sample.normals, sample.radii, vis)
        info["visible_views_per_surfel"] = float(vis.sum(1).mean()) if len(vis) else 0.0
        info["surfels_seen_by_no_view"] = int((~vis.any(1)).sum()) if len(vis) else 0
        prog(V, V)
    if config.refine != "none":
        if images is None:
            raise ConfigError(f"refine={config.refine!r} needs the views' images (build_geometry(images=...))")
        with step("refine"):
            from .photo import PhotoConfig, refine_surfels

            # deferred: refine_surfels packs each view's grey and alpha into its stacks as it
            # reads it, so only one photograph is alive at a time here
            src = images
            imgs = [_Deferred((lambda i=i: src(i)) if callable(src) else (lambda i=i: src[i])) for i in range(V)]
            alps = [_Deferred(lambda i=i: alphas[i]) for i in range(V)]
            move = config.refine == "surfels"
            # shading depth only: coverage and radii stay the hull's, so neither the outline
            # restoration nor the radius growth of moved surfels is needed
            pc = (
                PhotoConfig()
                if move
                else PhotoConfig(keep_coverage=False, radius_neighbours=0, texture_std=SHADING_TEXTURE_STD)
            )
            if photo_slots is not None:  # the memory plan's share (MemoryPlan.photo_slots)
                pc = replace(pc, max_views_in_memory=max(int(photo_slots), pc.n_views))
            pos, nrm, rad, st = refine_surfels(
                sample.positions, sample.normals, sample.radii, vis, pin, imgs, alps, config=pc
            )
            if move:
                vis = cast(
                    np.ndarray,
                    surfel_visibility(pos, nrm, rad, pin, depth_tol_m=config.depth_tol_m, facing_cos=config.facing_cos),
                )
                surfels = Surfels.from_bool(pos, nrm, rad, vis)
            else:
                surfels.depth_m = np.ascontiguousarray(st["depth_m"], np.float32)
            info["refine"] = {"mode": config.refine, **{k: v for k, v in st.items() if np.ndim(v) == 0}}
    return Geometry(sils=sils, pin=pin, dilations=dil, occ=occ, grid=grid, surfels=surfels, info=info, notes=notes)


def _carve_batched(sils: Sequence, pin: Sequence[Camera], grid: HullGrid, *, root_cell: int, batch: int):
    """The classical (tolerance 0) octree carve over at most ``batch`` views at a time,
    the batches' hulls intersected: a voxel survives the carve iff no view carves its
    centre, so this is voxel for voxel :func:`.hull.carve_octree` over all views, with
    only ``batch`` views' unpacked silhouettes and summed-area tables alive. Returns
    (occupancy, OctreeStats summed over the batches, number of batches)."""
    from .hull import OctreeStats

    V = len(pin)
    b = max(1, int(batch))
    occ, cells, tests, n = None, 0, 0, 0
    for b0 in range(0, V, b):
        part = sils[b0 : b0 + b]
        o, st = cast(
            "tuple[np.ndarray, Any]",
            carve_octree(part, list(pin[b0 : b0 + b]), grid, root_cell=root_cell, return_stats=True),
        )
        del part
        occ = o if occ is None else (occ & o)
        cells, tests, n = cells + st.cells, tests + st.tests, n + 1
        if not occ.any():
            break  # empty already: the caller says so
    assert occ is not None
    return occ, OctreeStats(cells, tests, int(root_cell)), n


# --------------------------------------------------------------------------- steps on disk

#: the build's own products, inside the model folder (reused by ``build --resume``)
