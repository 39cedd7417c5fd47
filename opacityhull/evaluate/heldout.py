"""``eval test``: the train/test protocol of nerfstudio and the NeRF papers. A model built
with ``build --hold-out`` keeps its test views' cameras and photographs on record but
never saw them (no geometry, no blending: their visibility bits are clear); each is
rendered from the model and compared with its photograph.

Two metrics per view, both on the sRGB-encoded colour:

* **whole image** on a chosen background (white or black): photograph and rendering are
  each composited over it and PSNR / SSIM taken over every pixel — the NeRF papers'
  protocol (their synthetic sets on white);
* **mask union**: :func:`.loo.loo_metrics` (PSNR / SSIM over black inside the union of
  the photograph's and the rendering's masks) — ``eval loo``'s metric, on the
  photograph's own mask also where the build filled shadow holes.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Literal, cast
from collections.abc import Callable

import numpy as np

from ..errors import InputError
from ..imageio import srgb_encode
from ..model import BUILD_DIR, FILLED_HOLES, OpacityHullModel, read_hole_masks
from ..render.renderer import RenderConfig, model_surfels, prepare_model_views, render_image
from ..render.splats import RENDERERS, FittedSplats, Renderer, fitted_state, resolve_renderer
from .loo import _photograph, contact_sheet, loo_metrics

__all__ = [
    "Background",
    "BACKGROUNDS",
    "Renderer",
    "RENDERERS",
    "fitted_state",
    "held_out_views",
    "image_metrics",
    "eval_test",
]

Background = Literal["white", "black"]
BACKGROUNDS: tuple[Background, ...] = ("white", "black")


def held_out_views(model: OpacityHullModel) -> list[int]:
    """The model's test views (``model.toml`` ``[split] held_out``), as indices; an
    :class:`InputError` when the model was built without ``--hold-out``."""
    split = model.meta.get("split") or {}
    ids = split.get("held_out") or []
    if not ids:
        raise InputError(
            f"{model.root}: built without --hold-out, so it has no test views; build with --hold-out every:N "
            "(or use eval loo, which holds views out of the blend of a model built from all of them)"
        )
    return [model.view_index(str(v)) for v in ids]


def _on(rgba: np.ndarray, background: Background) -> np.ndarray:
    bg = np.float32(1.0 if background == "white" else 0.0)
    a = np.clip(np.nan_to_num(rgba[..., 3:4], nan=0.0), 0.0, 1.0)
    rgb = np.clip(np.nan_to_num(rgba[..., :3], nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
    return srgb_encode(np.clip(rgb * a + bg * (1.0 - a), 0.0, 1.0))


def image_metrics(photo_rgba: np.ndarray, render_rgba: np.ndarray, *, background: Background) -> dict:
    """PSNR (dB) and SSIM over the whole image of the two straight RGBA images (H, W, 4)
    composited over ``background`` and sRGB-encoded (skimage SSIM, 7-px window, data
    range 1, averaged over the channels)."""
    from skimage.metrics import structural_similarity

    if photo_rgba.shape != render_rgba.shape or photo_rgba.ndim != 3 or photo_rgba.shape[2] != 4:
        raise InputError(f"photo {photo_rgba.shape} and render {render_rgba.shape} must both be (H, W, 4)")
    p, r = _on(photo_rgba, background), _on(render_rgba, background)
    mse = float(np.mean((p - r) ** 2))
    psnr = float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)
    win = min(7, min(p.shape[:2]) // 2 * 2 - 1)
    ssim = float("nan")
    if win >= 3:
        ssim = float(cast(float, structural_similarity(p, r, channel_axis=2, data_range=1.0, win_size=win)))
    return {"psnr": psnr, "ssim": ssim}


def eval_test(
    model_path,
    *,
    background: Background = "white",
    config: RenderConfig = RenderConfig(),
    renderer: Renderer = "auto",
    out=None,
    max_sheet_rows: int = 12,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Render every held-out view of a model built with ``--hold-out`` and score it
    (see the module docstring). Writes ``test.json`` and ``test_sheet.png`` (photo |
    render | error, each row labelled with the view and both PSNRs) to ``out`` (default
    ``MODEL/eval/test``). Returns the summary: ``views``, ``background``, ``renderer``,
    ``psnr_mean``/``ssim_mean`` (whole image), ``psnr_mask_mean``/``ssim_mask_mean``
    (mask union) and ``per_view``.

    ``renderer``: ``"fitted"`` renders the splats of ``build --optimize``
    (:func:`opacityhull.optimize.fit.render_params`), ``"ulr"`` the hull's surfels blended
    from the training views (:func:`~opacityhull.render.renderer.render_image`); ``"auto"``
    takes the fitted splats when the model has them (fitted from this build, see
    :func:`fitted_state`), else ULR."""
    import json

    from ..jsonio import to_jsonable
    from ..imageio import atomic_path
    from .runner import default_out

    if background not in BACKGROUNDS:
        raise InputError(f"--background {background!r}: expected one of {', '.join(BACKGROUNDS)}")
    model = OpacityHullModel.open(model_path)
    idx = held_out_views(model)
    used = resolve_renderer(Path(model.root), renderer)
    fitted = FittedSplats.load(Path(model.root)) if used == "fitted" else None
    out = Path(out) if out is not None else default_out(model_path, "test")
    cams = [v.camera for v in model.views]
    surfels = model_surfels(model)
    visible = surfels.visible_bool()
    blended = [model.views[i].id for i in idx if len(surfels) and visible[:, i].any()]
    if blended:
        raise InputError(
            f"{model.root}: test views {blended} are visible in the surfels: the model was not built with them "
            "held out (rebuild with --hold-out)"
        )
    pv = prepare_model_views(model)
    filled = read_hole_masks(Path(model.root) / BUILD_DIR / FILLED_HOLES)
    pick = set(np.unique(np.linspace(0, len(idx) - 1, min(max_sheet_rows, len(idx))).round().astype(int)))
    per_view, rows = [], []
    for j, i in enumerate(idx):
        t0 = time.perf_counter()
        # nothing to exclude: the held-out view's bits are clear, so it is never blended
        if fitted is not None:
            rgba, coverage = fitted.rgba(cams[i]), None
        else:
            res = render_image(surfels, cams, pv, cams[i], config=config)
            rgba, coverage = res.rgba, res.coverage
        ms = 1e3 * (time.perf_counter() - t0)
        photo, _, _ = _photograph(model, i, filled, rgba)
        whole = image_metrics(photo, rgba, background=background)
        mask = loo_metrics(photo, rgba, coverage=coverage)
        per_view.append(
            {
                "view": model.views[i].id,
                "index": i,
                "psnr": whole["psnr"],
                "ssim": whole["ssim"],
                "psnr_mask": mask["psnr"],
                "ssim_mask": mask["ssim"],
                "coverage_iou": mask["coverage_iou"],
                "alpha_mae": mask["alpha_mae"],
                "ms": ms,
            }
        )
        if j in pick:
            note = f"{background} {whole['psnr']:.1f} dB | mask {mask['psnr']:.1f} dB"
            rows.append((model.views[i].id, photo, rgba, note))
        if progress:
            progress(j + 1, len(idx))

    def mean(key):
        vals = [p[key] for p in per_view if math.isfinite(p[key])]
        return float(np.mean(vals)) if vals else float("nan")

    summary = {
        "model": str(model.root),
        "views": [model.views[i].id for i in idx],
        "train_views": len(model.views) - len(idx),
        "hold_out": (model.meta.get("split") or {}).get("hold_out"),
        "background": background,
        # which images were scored: the fitted splats (build --optimize) or the hull blended by ULR
        "renderer": used,
        "psnr_mean": mean("psnr"),
        "ssim_mean": mean("ssim"),
        "psnr_mask_mean": mean("psnr_mask"),
        "ssim_mask_mean": mean("ssim_mask"),
        "coverage_iou_mean": mean("coverage_iou"),
        "alpha_mae": mean("alpha_mae"),
        "ms_per_view": mean("ms"),
        "per_view": per_view,
        "metric_space": f"sRGB-encoded colour; psnr/ssim: the whole image composited over {background}; "
        "psnr_mask/ssim_mask: over black inside the union of photo and render masks (eval loo's metric)",
    }
    if rows:
        summary["sheet"] = str(contact_sheet(rows, out / "test_sheet.png", holdout="test-view"))
    with atomic_path(out / "test.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable(summary), indent=1))
    summary["json"] = str(out / "test.json")
    return summary
