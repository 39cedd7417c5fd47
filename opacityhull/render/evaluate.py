"""Leave-one-out evaluation: render each chosen captured view from the model with that
view excluded from blending, and compare with its photograph.

The model's ``views/`` are the opacity light field's samples, i.e. the photographs'
RGBA (colour and matte alpha). A held-out view is excluded from ULR blending only: the
hull geometry and the visibility vectors were built from all views and cannot be
un-built, so the comparison measures the renderer's view interpolation (blending,
resampling, splatting), not the reconstruction's generalisation.

Metrics, per view, inside the union of the photograph's and the rendering's masks
(α > ``alpha_threshold``):

* PSNR (dB) of the colour composited over black (= premultiplied RGB), sRGB-encoded
  and clipped to [0, 1] — what a viewer sees, and defined where α → 0;
* SSIM (``skimage.metrics.structural_similarity``, data range 1, per channel) of the same
  images, averaged over the mask;
* alpha MAE: mean |α_photo − α_render|.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..errors import InputError
from ..imageio import srgb_encode
from ..model import OpacityHullModel
from .renderer import RenderConfig, model_surfels, prepare_model_views, render_image

__all__ = ["loo_metrics", "select_views", "leave_one_out", "contact_sheet", "ALPHA_THRESHOLD"]

ALPHA_THRESHOLD = 1.0 / 255.0


def _display(rgba_straight: np.ndarray) -> np.ndarray:
    a = np.clip(rgba_straight[..., 3:4], 0, 1)
    return srgb_encode(np.clip(rgba_straight[..., :3] * a, 0.0, 1.0))


def loo_metrics(photo_rgba: np.ndarray, render_rgba: np.ndarray, *, alpha_threshold: float = ALPHA_THRESHOLD) -> dict:
    """PSNR, SSIM and alpha MAE of a rendering against a photograph (both (H, W, 4)
    straight RGBA) inside the union of their masks. Empty masks give NaN metrics."""
    from skimage.metrics import structural_similarity

    if photo_rgba.shape != render_rgba.shape or photo_rgba.ndim != 3 or photo_rgba.shape[2] != 4:
        raise InputError(f"photo {photo_rgba.shape} and render {render_rgba.shape} must both be (H, W, 4)")
    p = np.nan_to_num(photo_rgba.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    r = np.nan_to_num(render_rgba.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    mask = (p[..., 3] > alpha_threshold) | (r[..., 3] > alpha_threshold)
    n = int(mask.sum())
    if n == 0:
        return {"psnr": float("nan"), "ssim": float("nan"), "alpha_mae": float("nan"), "mask_px": 0}
    dp, dr = _display(p), _display(r)
    mse = float(np.mean((dp[mask] - dr[mask]) ** 2))
    psnr = float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)
    win = min(7, min(p.shape[:2]) // 2 * 2 - 1)
    if win >= 3:
        _, smap = structural_similarity(dp, dr, channel_axis=2, data_range=1.0, full=True, win_size=win)
        ssim = float(np.mean(smap[mask]))
    else:
        ssim = float("nan")
    amae = float(np.mean(np.abs(np.clip(p[..., 3], 0, 1)[mask] - np.clip(r[..., 3], 0, 1)[mask])))
    return {"psnr": psnr, "ssim": ssim, "alpha_mae": amae, "mask_px": n}


def select_views(model: OpacityHullModel, spec: str | Sequence | None) -> list[int]:
    """View indices from a ``--views`` value: None/"all"; "every:N"; "camera:C"; or a
    comma list of view ids (``c0_t030.000``) and/or indices."""
    V = len(model.views)
    if spec is None or (isinstance(spec, str) and spec.strip().lower() in ("", "all")):
        return list(range(V))
    if isinstance(spec, str):
        s = spec.strip()
        if s.startswith("every:"):
            try:
                step = int(s[6:])
            except ValueError:
                step = 0
            if step < 1:
                raise InputError(f"--views {spec!r}: every:N needs an integer N >= 1")
            return list(range(0, V, step))
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


def _heat(err: np.ndarray, scale: float) -> np.ndarray:
    import matplotlib

    return matplotlib.colormaps["inferno"](np.clip(err * scale, 0, 1))[..., :3].astype(np.float32)


def contact_sheet(rows: Sequence[tuple[str, np.ndarray, np.ndarray, str]], path, *, error_scale: float = 4.0,
                  background=(0.5, 0.5, 0.5), max_width: int = 1800) -> Path:
    """Write a PNG with one row per view: photograph | rendering | error, colour over a
    grey backdrop; the error panel is mean |Δ| of the displayed colour plus |Δα|, times
    ``error_scale``, in the inferno colour map. ``rows`` are (label, photo, render, note)."""
    import cv2

    from ..imageio import write_png

    tiles = []
    bg = srgb_encode(np.asarray(background, np.float32))
    for label, photo, render, note in rows:
        ap, ar = np.clip(photo[..., 3:4], 0, 1), np.clip(render[..., 3:4], 0, 1)
        dp = srgb_encode(np.clip(photo[..., :3], 0, 1)) * ap + bg * (1 - ap)
        dr = srgb_encode(np.clip(render[..., :3], 0, 1)) * ar + bg * (1 - ar)
        err = np.abs(_display(photo) - _display(render)).mean(axis=2) + np.abs(ap[..., 0] - ar[..., 0])
        row = np.concatenate([dp, dr, _heat(err, error_scale)], axis=1)
        scale = min(1.0, max_width / row.shape[1])
        if scale < 1:
            row = cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        if row.shape[0] < 96:  # small views: enlarge for legibility
            f = int(math.ceil(96 / row.shape[0]))
            row = cv2.resize(row, None, fx=f, fy=f, interpolation=cv2.INTER_NEAREST)
        row = np.ascontiguousarray(np.round(np.clip(row, 0, 1) * 255).astype(np.uint8))
        cv2.putText(row, f"{label}  {note}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(row.astype(np.float32) / 255.0)
    width = max(t.shape[1] for t in tiles)
    tiles = [np.pad(t, ((0, 2), (0, width - t.shape[1]), (0, 0))) for t in tiles]
    sheet = np.concatenate(tiles, axis=0)
    path = Path(path)
    write_png(path, sheet, linear=True)
    return path


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
) -> dict:
    """Leave-one-out rendering of the chosen views (default all).

    Returns ``{"views", "psnr_mean", "ssim_mean", "alpha_mae", "per_view": [...], ...}``;
    means are over views with a non-empty mask. Writes a contact sheet (photo | render |
    error) of up to ``max_sheet_rows`` evenly spaced views when ``sheet_path`` is given.
    """
    idx = list(range(len(model.views))) if views is None else list(views)
    if not idx:
        raise InputError("leave_one_out: no views selected")
    pv = prepared if prepared is not None else prepare_model_views(model)
    surfels = model_surfels(model)
    cams = [v.camera for v in model.views]
    sheet_pick = set(np.unique(np.linspace(0, len(idx) - 1, min(max_sheet_rows, len(idx))).round().astype(int)))
    per_view, rows = [], []
    for j, i in enumerate(idx):
        t0 = time.perf_counter()
        res = render_image(surfels, cams, pv, cams[i], config=config, exclude_views=[i])
        ms = 1e3 * (time.perf_counter() - t0)
        photo = model.load_view_rgba(i)
        m = loo_metrics(photo, res.rgba, alpha_threshold=alpha_threshold)
        per_view.append({"view": model.views[i].id, "index": i, **m, "ms": ms})
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
        "psnr_mean": mean("psnr"),
        "ssim_mean": mean("ssim"),
        "alpha_mae": mean("alpha_mae"),
        "per_view": per_view,
        "ms_per_view": float(np.mean([p["ms"] for p in per_view])),
        "config": {"k": config.k, "filter": config.filter, "sigma_radius": config.sigma_radius,
                   "cutoff_sigma": config.cutoff_sigma, "epsilon_z": config.epsilon_z},
        "held_out_from": "ULR blending only (hull and visibility were built with all views)",
        "metric_space": "sRGB-encoded colour over black, inside the union of photo and render masks",
    }
    if sheet_path is not None and rows:
        summary["sheet"] = str(contact_sheet(rows, sheet_path))
    return summary
