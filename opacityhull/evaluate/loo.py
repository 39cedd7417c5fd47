"""Leave-one-out evaluation: render each chosen captured view from the model with that
view excluded from blending, and compare with its photograph.

The model's ``views/`` are the opacity light field's samples, i.e. the photographs'
RGBA (colour and matte alpha). A held-out view is excluded from ULR blending only: the
hull geometry and the visibility vectors were built from all views and cannot be
un-built, so the comparison measures the renderer's view interpolation (blending,
resampling, splatting), not the reconstruction's generalisation.

A view photographed twice (:func:`~opacityhull.camera.coincident_views`: the same
camera centre and orientation) is held out together with its twins by default
(``twins="together"``), or the held-out view's twin would show the renderer its own
photograph: on the Middlebury temple ring, whose first viewpoint is photographed twice,
that view scores 25.3 dB with its twin in the model and 14.8 dB without it (geometry
holdout).

Metrics, per view, inside the union of the photograph's and the rendering's masks
(α > ``alpha_threshold``):

* PSNR (dB) of the colour composited over black (= premultiplied RGB), sRGB-encoded
  and clipped to [0, 1] — what a viewer sees, and defined where α → 0;
* SSIM (``skimage.metrics.structural_similarity``, data range 1, per channel) of the same
  images, averaged over the mask;
* alpha MAE: mean |α_photo − α_render|.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Literal, cast
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import InputError
from ..imageio import srgb_encode
from ..model import BUILD_DIR, FILLED_HOLES, OpacityHullModel, Surfels, read_hole_masks
from ..render.config import Twins
from ..render.renderer import RenderConfig, model_surfels, prepare_model_views, render_image

__all__ = [
    "loo_metrics",
    "region_masks",
    "select_views",
    "held_out_groups",
    "leave_one_out",
    "contact_sheet",
    "ALPHA_THRESHOLD",
]

log = logging.getLogger(__name__)

ALPHA_THRESHOLD = 1.0 / 255.0


def _display(rgba_straight: np.ndarray) -> np.ndarray:
    a = np.clip(rgba_straight[..., 3:4], 0, 1)
    return srgb_encode(np.clip(rgba_straight[..., :3] * a, 0.0, 1.0))


def _disc(r: int):
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def region_masks(photo_alpha: np.ndarray, *, band_px: int = 3, opaque: float = 0.99) -> dict:
    """The photograph's regions the metrics are split by (all (H, W) bool).

    ``mask`` photo α > ½; ``interior`` the mask eroded by ``band_px``; ``band`` the
    ``2 band_px + 1``-px wide band around the silhouette (dilated minus eroded mask);
    ``opaque`` pixels with α ≥ ``opaque`` eroded by ``band_px`` (where the rendering's
    α must be 1).
    """
    import cv2

    a = np.clip(np.nan_to_num(photo_alpha, nan=0.0), 0, 1)
    m = (a > 0.5).astype(np.uint8)
    k = _disc(band_px)
    er = cv2.erode(m, k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    di = cv2.dilate(m, k).astype(bool)
    op = cv2.erode((a >= opaque).astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    return {"mask": m.astype(bool), "interior": er, "band": di & ~er, "opaque": op}


def _psnr_ssim(dp: np.ndarray, dr: np.ndarray, sel: np.ndarray, smap: np.ndarray | None) -> tuple[float, float]:
    n = int(sel.sum())
    if n == 0:
        return float("nan"), float("nan")
    mse = float(np.mean((dp[sel] - dr[sel]) ** 2))
    psnr = float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)
    ssim = float(np.mean(smap[sel])) if smap is not None else float("nan")
    return psnr, ssim


def loo_metrics(
    photo_rgba: np.ndarray,
    render_rgba: np.ndarray,
    *,
    alpha_threshold: float = ALPHA_THRESHOLD,
    band_px: int = 3,
    coverage: np.ndarray | None = None,
) -> dict:
    """Metrics of a rendering against a photograph (both (H, W, 4) straight RGBA).

    ``psnr``/``ssim``/``alpha_mae`` inside the union of the masks (α > ``alpha_threshold``);
    ``psnr_interior``/``ssim_interior`` inside the photo's mask eroded by ``band_px`` and
    ``psnr_band``/``ssim_band`` in the ``2 band_px + 1``-px band around its silhouette
    (see :func:`region_masks`); ``coverage_iou`` of rendered α > ½ against photo α > ½;
    ``spill_px`` rendered pixels (α > ½) outside the photo's mask dilated by one pixel;
    ``interior_alpha`` the mean rendered α where the photo is opaque (α ≥ 0.99, eroded
    by ``band_px``) and ``interior_alpha_deficit`` = 1 − that. With the rendering's
    ``coverage`` (H, W), ``interior_alpha_covered`` is that mean over the opaque pixels the
    geometry covers (coverage ≥ ½): the blending's own opacity deficit, apart from pixels
    where the hull and the photo's mask disagree (a thresholded mask's blobs and holes).
    Empty masks give NaN.
    """
    from skimage.metrics import structural_similarity

    if photo_rgba.shape != render_rgba.shape or photo_rgba.ndim != 3 or photo_rgba.shape[2] != 4:
        raise InputError(f"photo {photo_rgba.shape} and render {render_rgba.shape} must both be (H, W, 4)")
    p = np.nan_to_num(photo_rgba.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    r = np.nan_to_num(render_rgba.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    mask = (p[..., 3] > alpha_threshold) | (r[..., 3] > alpha_threshold)
    n = int(mask.sum())
    nan = float("nan")
    if n == 0:
        return {
            "psnr": nan,
            "ssim": nan,
            "alpha_mae": nan,
            "mask_px": 0,
            "psnr_interior": nan,
            "ssim_interior": nan,
            "psnr_band": nan,
            "ssim_band": nan,
            "coverage_iou": nan,
            "spill_px": 0,
            "interior_alpha": nan,
            "interior_alpha_deficit": nan,
            "interior_alpha_covered": nan,
        }
    dp, dr = _display(p), _display(r)
    win = min(7, min(p.shape[:2]) // 2 * 2 - 1)
    smap = None
    if win >= 3:
        _, smap = cast(
            tuple[float, np.ndarray],
            structural_similarity(dp, dr, channel_axis=2, data_range=1.0, full=True, win_size=win),
        )
        smap = smap.mean(axis=2) if smap.ndim == 3 else smap
    psnr, ssim = _psnr_ssim(dp, dr, mask, smap)
    pa = np.clip(p[..., 3], 0, 1)
    ra = np.clip(r[..., 3], 0, 1)
    amae = float(np.mean(np.abs(pa[mask] - ra[mask])))
    reg = region_masks(pa, band_px=band_px)
    psnr_i, ssim_i = _psnr_ssim(dp, dr, reg["interior"], smap)
    psnr_b, ssim_b = _psnr_ssim(dp, dr, reg["band"], smap)
    pm, rm = reg["mask"], ra > 0.5
    union = int((pm | rm).sum())
    iou = float((pm & rm).sum()) / union if union else nan
    import cv2

    near = cv2.dilate(pm.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    spill = int((rm & ~near).sum())
    ia = float(ra[reg["opaque"]].mean()) if reg["opaque"].any() else nan
    iac = nan
    if coverage is not None:
        if np.shape(coverage) != pa.shape:
            raise InputError(f"coverage {np.shape(coverage)} must be (H, W) = {pa.shape}")
        sel = reg["opaque"] & (np.nan_to_num(np.asarray(coverage, np.float32)) >= 0.5)
        iac = float(ra[sel].mean()) if sel.any() else nan
    return {
        "psnr": psnr,
        "ssim": ssim,
        "alpha_mae": amae,
        "mask_px": n,
        "psnr_interior": psnr_i,
        "ssim_interior": ssim_i,
        "psnr_band": psnr_b,
        "ssim_band": ssim_b,
        "coverage_iou": iou,
        "spill_px": spill,
        "interior_alpha": ia,
        "interior_alpha_deficit": (1.0 - ia) if ia == ia else nan,
        "interior_alpha_covered": iac,
    }


def select_views(model: OpacityHullModel, spec: str | Sequence | None) -> list[int]:
    """View indices from a ``--views`` value: None/"all"; "every:N"; "camera:C"; or a
    comma list of view ids (``c0_t030.000``) and/or indices."""
    V = len(model.views)
    if spec is None or (isinstance(spec, str) and spec.strip().lower() in ("", "all")):
        return list(range(V))
    if isinstance(spec, str):
        s = spec.strip()
        if s.startswith("every:"):
            from ..reconstruct.steps.split import every_step

            return list(range(0, V, every_step(s, flag=f"--views {spec!r}", need="an integer N >= 1")))
        if s.startswith("camera:"):
            try:
                c = int(s[7:])
            except ValueError:
                raise InputError(f"--views {spec!r}: camera:C needs an integer C") from None
            out = [v.index for v in model.views if v.camera_index == c]
            if not out:
                raise InputError(f"--views {spec!r}: no views of camera {c}")
            return out
        items = [t.strip() for t in s.split(",") if t.strip()]
    else:
        items = list(spec)
    out = []
    for it in items:
        if isinstance(it, (int, np.integer)) or (isinstance(it, str) and it.isdigit()):
            i = int(it)
            if not 0 <= i < V:
                raise InputError(f"--views: index {i} out of range [0, {V})")
            out.append(i)
        else:
            out.append(model.view_index(str(it)))
    if not out:
        raise InputError(f"--views {spec!r}: no views selected")
    return sorted(set(out), key=out.index)


def contact_sheet(
    rows: Sequence[tuple[str, np.ndarray, np.ndarray, str]],
    path,
    *,
    error_scale: float = 4.0,
    background=(0.5, 0.5, 0.5),
    max_width: int = 1800,
    holdout: str | None = None,
) -> Path:
    """Write a PNG with one row per view: photograph | rendering | error, colour over a
    grey backdrop; the error panel is mean |Δ| of the displayed colour plus |Δα| in the
    inferno colour map, saturating at ``1 / error_scale`` (the colour bar says so).
    ``rows`` are (label, photo, render, note); rows wider than ``max_width`` px shrink.
    ``holdout`` names what was held out in the rendering column's header (``"blend"`` →
    "render, blend holdout"), so the sheet says which protocol it shows."""
    from ..pictures import ColorBar, contact_sheet as sheet, encoded_to_u8, heat, write_sheet

    tiles, labels = [], []
    bg = srgb_encode(np.asarray(background, np.float32))
    for label, photo, render, note in rows:
        ap, ar = np.clip(photo[..., 3:4], 0, 1), np.clip(render[..., 3:4], 0, 1)
        dp = srgb_encode(np.clip(photo[..., :3], 0, 1)) * ap + bg * (1 - ap)
        dr = srgb_encode(np.clip(render[..., :3], 0, 1)) * ar + bg * (1 - ar)
        err = np.abs(_display(photo) - _display(render)).mean(axis=2) + np.abs(ap[..., 0] - ar[..., 0])
        tiles += [encoded_to_u8(dp), encoded_to_u8(dr), heat(err, vmin=0.0, vmax=1.0 / error_scale)]
        labels += [f"{label}  {note}", "", ""]
    img = sheet(
        tiles,
        columns=3,
        labels=labels,
        headers=["photo", "render" if holdout is None else f"render, {holdout} holdout", f"error x{error_scale:g}"],
        colorbar=ColorBar(cmap="inferno", vmin=0.0, vmax=1.0 / error_scale, label="mean |d sRGB| + |d alpha|"),
        min_width=128,
        max_width=max(1, max_width // 3),
    )
    return write_sheet(path, img)


def _photograph(model: OpacityHullModel, i: int, filled: dict, render_rgba: np.ndarray):
    """View ``i`` as photographed: the model's view with the photograph's own mask where
    the build filled shadow holes (``filled``: :data:`~opacityhull.model.FILLED_HOLES`),
    the number of such pixels, and the coverage IoU of ``render_rgba`` against the
    filled mask (None where nothing was filled)."""
    photo = model.load_view_rgba(i)
    holes = filled.get(model.views[i].id)
    if holes is None or not holes.any():
        return photo, 0, None
    if holes.shape != photo.shape[:2]:
        raise InputError(
            f"{model.root}/{BUILD_DIR}/{FILLED_HOLES}: view {model.views[i].id} mask {holes.shape}, "
            f"expected {photo.shape[:2]}; rebuild the model"
        )
    model_mask = np.nan_to_num(photo[..., 3]) > 0.5
    rendered = np.nan_to_num(render_rgba[..., 3]) > 0.5
    union = int((model_mask | rendered).sum())
    iou = float((model_mask & rendered).sum()) / union if union else float("nan")
    photo = photo.copy()
    photo[..., 3][holes] = 0.0
    return photo, int(holes.sum()), iou


def held_out_groups(
    model: OpacityHullModel,
    views: Sequence[int],
    *,
    twins: Twins = "together",
    groups: Sequence[Sequence[int]] | None = None,
) -> dict[int, tuple[int, ...]]:
    """``{i: views held out with i}`` (``i`` first, then its twins ascending) for the
    chosen ``views``. ``twins="together"``: a view and the views coincident with it
    (``groups``, default :func:`~opacityhull.camera.coincident_views` of the model's
    cameras: the same viewpoint photographed again), since a view whose twin stays in
    the model is no novel view; ``"keep"``: each view alone (the protocol of a plain
    leave-one-out script)."""
    from ..camera import coincident_views

    if twins not in ("together", "keep"):
        raise InputError(f"twins {twins!r}: expected 'together' or 'keep'")
    if twins == "keep":
        groups = []
    elif groups is None:
        groups = coincident_views([v.camera for v in model.views])
    of = {j: g for g in groups for j in g}
    return {int(i): (int(i), *(j for j in of.get(int(i), ()) if j != int(i))) for i in views}


def leave_one_out(
    model: OpacityHullModel,
    *,
    views: Sequence[int] | None = None,
    config: RenderConfig = RenderConfig(),
    sheet_path=None,
    max_sheet_rows: int = 12,
    alpha_threshold: float = ALPHA_THRESHOLD,
    prepared=None,
    progress: Callable[[int, int], None] | None = None,
    holdout: Literal["blend", "geometry"] = "blend",
    twins: Twins = "together",
    geometry_without: Callable[[tuple[int, ...]], Surfels] | None = None,
    surfels: Surfels | None = None,
) -> dict:
    """Leave-one-out rendering of the chosen views (default all).

    ``holdout="blend"`` excludes the view from ULR blending only; ``"geometry"`` also
    renders surfels whose hull and visibility were rebuilt without it
    (``geometry_without(held)`` returns them for the tuple of held-out views, visibility
    over all V views with their bits clear: the reconstruct stage provides it, see
    :func:`opacityhull.evaluate.holdout.geometry_without`). ``twins``
    (:func:`held_out_groups`): with ``"together"`` (default) a view's coincident twins
    are held out with it, from the blend and from the rebuilt geometry, and
    ``per_view[...]["held_out_with"]`` names them; ``"keep"`` leaves them in. The
    summary's ``coincident_views`` lists the groups either way. ``surfels`` replaces the
    model's own in the blend holdout (a benchmark's thinned or altered geometry, visibility
    over the model's V views).

    Returns ``{"views", "psnr_mean", "ssim_mean", "alpha_mae", ..., "per_view": [...]}``
    with the means of every :func:`loo_metrics` key over views with a non-empty mask.
    Writes a contact sheet (photo | render | error) of up to ``max_sheet_rows`` evenly
    spaced views when ``sheet_path`` is given.
    """
    if holdout not in ("blend", "geometry"):
        raise InputError(f"holdout {holdout!r}: expected 'blend' or 'geometry'")
    if holdout == "geometry" and geometry_without is None:
        raise InputError("holdout 'geometry' needs geometry_without (the hull rebuilt without the held-out view)")
    idx = list(range(len(model.views))) if views is None else list(views)
    if not idx:
        raise InputError("leave_one_out: no views selected")
    pv = prepared if prepared is not None else prepare_model_views(model)
    cams = [v.camera for v in model.views]
    if surfels is None:
        surfels = model_surfels(model)
    elif surfels.n_views != len(cams):
        raise InputError(f"surfels have visibility over {surfels.n_views} views, expected the model's {len(cams)}")
    sheet_pick = set(np.unique(np.linspace(0, len(idx) - 1, min(max_sheet_rows, len(idx))).round().astype(int)))
    per_view, rows = [], []
    build_ms = []
    filled = read_hole_masks(Path(model.root) / BUILD_DIR / FILLED_HOLES)
    from ..camera import coincident_views

    groups = coincident_views(cams)
    held = held_out_groups(model, idx, twins=twins, groups=groups)
    coincident = [[model.views[v].id for v in g] for g in groups]
    if coincident:
        log.warning(
            "views %s photograph the same viewpoint: %s",
            "; ".join(" = ".join(g) for g in coincident),
            "held out together" if twins == "together" else "kept in the model (their scores are no novel views)",
        )
    for j, i in enumerate(idx):
        use = surfels
        if holdout == "geometry" and geometry_without is not None:  # checked above: not None here
            t0 = time.perf_counter()
            use = geometry_without(held[i])
            build_ms.append(1e3 * (time.perf_counter() - t0))
            if use.n_views != len(cams):
                raise InputError(
                    f"geometry_without({held[i]}) gave visibility over {use.n_views} views, expected {len(cams)}"
                )
        t0 = time.perf_counter()
        res = render_image(use, cams, pv, cams[i], config=config, exclude_views=list(held[i]))
        ms = 1e3 * (time.perf_counter() - t0)
        photo, filled_px, iou_filled = _photograph(model, i, filled, res.rgba)
        m = loo_metrics(photo, res.rgba, alpha_threshold=alpha_threshold, coverage=res.coverage)
        # the same rendering against the mask the build used (shadow holes opaque): how much
        # of the score is the threshold's loss of shadowed object, not the rendering's
        psnr_filled = m["psnr"]
        if filled_px:
            psnr_filled = loo_metrics(model.load_view_rgba(i), res.rgba, alpha_threshold=alpha_threshold)["psnr"]
        per_view.append(
            {
                "view": model.views[i].id,
                "index": i,
                **m,
                "coverage_iou_holes_filled": m["coverage_iou"] if iou_filled is None else iou_filled,
                "psnr_holes_filled": psnr_filled,
                "shadow_holes_px": filled_px,
                "held_out_with": [model.views[v].id for v in held[i][1:]],
                "ms": ms,
                **({"rebuild_ms": build_ms[-1], "surfels": len(use)} if build_ms else {}),
            }
        )
        if j in sheet_pick:
            rows.append((model.views[i].id, photo, res.rgba, f"PSNR {m['psnr']:.1f} dB  SSIM {m['ssim']:.3f}"))
        if progress:
            progress(j + 1, len(idx))

    def mean(key):
        vals = [p[key] for p in per_view if p[key] == p[key] and math.isfinite(p[key])]
        return float(np.mean(vals)) if vals else float("nan")

    summary = {
        "model": str(model.root),
        "views": [model.views[i].id for i in idx],
        "holdout": holdout,
        "twins": twins,
        "coincident_views": coincident,
        "psnr_mean": mean("psnr"),
        "ssim_mean": mean("ssim"),
        "alpha_mae": mean("alpha_mae"),
        **{
            f"{k}_mean": mean(k)
            for k in (
                "psnr_interior",
                "ssim_interior",
                "psnr_band",
                "ssim_band",
                "coverage_iou",
                "coverage_iou_holes_filled",
                "psnr_holes_filled",
                "interior_alpha",
                "interior_alpha_deficit",
                "interior_alpha_covered",
                "spill_px",
            )
        },
        "coverage_iou_min": float(np.nanmin([p["coverage_iou"] for p in per_view])) if per_view else float("nan"),
        "per_view": per_view,
        "ms_per_view": float(np.mean([p["ms"] for p in per_view])),
        "config": {
            "k": config.k,
            "filter": config.filter,
            "sigma_radius": config.sigma_radius,
            "cutoff_sigma": config.cutoff_sigma,
            "epsilon_z": config.epsilon_z,
            "shading": getattr(config, "shading", "surfel"),
        },
        "held_out_from": (
            "ULR blending only (hull and visibility were built with all views)"
            if holdout == "blend"
            else "ULR blending, hull, surfels and visibility (rebuilt without the held-out view)"
        ),
        "metric_space": "sRGB-encoded colour over black, inside the union of photo and render masks "
        "(interior: photo mask eroded 3 px; band: the 7-px band around its silhouette); the photograph's "
        "own mask, also where the build filled its shadow holes (coverage_iou_holes_filled: against the "
        "filled mask; psnr_holes_filled: the PSNR against it)",
    }
    if build_ms:
        summary["rebuild_ms_per_view"] = float(np.mean(build_ms))
    if sheet_path is not None and rows:
        summary["sheet"] = str(contact_sheet(rows, sheet_path, holdout=holdout))
    return summary
