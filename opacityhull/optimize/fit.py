"""Fit the hull's surfels to the training photographs by differentiable EWA splatting.

The start is the opacity hull (surfel positions, normals, radii) with its blended
colour; every step renders one training view with the rasterizer
(:mod:`opacityhull.optimize.raster`), scores it with (1 − λ)·L1 + λ·(1 − SSIM) on the
display-space colour plus an L1 between the rendered α and the view's matte (the
opacity hull's own supervision), and takes an Adam step on positions, orientations,
tangent scales, opacities and SH colour. Views come in a random order fixed by the
seed; densification is seeded by (seed, step): the same inputs give the same bytes,
resumed or not.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import atomic_path, srgb_decode
from .adam import Adam, exp_decay
from .appearance import sh_colors, sh_colors_backward, view_dirs
from .config import FitConfig, position_rates
from .data import FitData, load_fit_data, model_fingerprint
from .densify import GradStats, densify_and_prune
from .splatply import read_splat_ply, write_splat_ply
from .ssim import ssim_and_grad
from .surfelparams import PARAM_NAMES, scene_extent, start_params, thin_start

__all__ = [
    "OPTIMIZED_DIR",
    "SPLATS_PLY",
    "CheckpointError",
    "FitReport",
    "FitProgress",
    "fit_model",
    "fit_params",
    "render_fitted",
    "render_params",
    "load_fitted",
    "step_loss",
    "view_gradient",
    "ViewGradient",
]

log = logging.getLogger(__name__)

OPTIMIZED_DIR = "optimized"
SPLATS_PLY = "splats.ply"
CHECKPOINT_NAME = "fit_checkpoint.npz"
_CKPT_FORMAT = "opacityhull.fit-checkpoint/1"


class CheckpointError(InputError):
    """A checkpoint that cannot resume this fit (another model, other views or options)."""


@dataclass(frozen=True)
class FitProgress:
    """What ``progress`` is called with after every step."""

    iteration: int
    iterations: int
    loss: float
    psnr: float  # running mean over the last views, mask union, display space
    n_surfels: int
    elapsed_s: float


@dataclass
class FitReport:
    """What :func:`fit_model` returns (and writes as ``optimized/fit.json``, less the
    wall-clock ``seconds`` and ``step_ms``: :meth:`timings`).

    loss : per step, the total loss. psnr : per step, the training view's PSNR (dB) over
    the mask union. step_ms : per step, wall time. n_surfels : start and end counts.
    densify : one entry per densification. stopped_by : "iterations" | "time_budget".
    """

    iterations: int = 0
    loss: list[float] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)
    step_ms: list[float] = field(default_factory=list)
    n_surfels_start: int = 0
    n_surfels_end: int = 0
    densify: list[dict] = field(default_factory=list)
    stopped_by: str = "iterations"
    resumed_from: int = 0
    seconds: float = 0.0
    splats_ply: str = ""
    config: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """The fit's outcome without wall-clock times (``fit.json``; see :meth:`timings`)."""
        tail = [p for p in self.psnr[-20:] if math.isfinite(p)]
        return {
            "iterations": self.iterations,
            "train_psnr_last": float(np.mean(tail)) if tail else float("nan"),
            "n_surfels_start": self.n_surfels_start,
            "n_surfels_end": self.n_surfels_end,
            "stopped_by": self.stopped_by,
        }

    def timings(self) -> dict:
        """This run's wall-clock times (``seconds``, ``ms_per_iteration``, ``step_ms``):
        kept out of ``fit.json`` and the checkpoint so that a model repeats byte for byte
        (#35); the build step puts them into ``report.json``'s ``optimize`` only."""
        return {
            "seconds": self.seconds,
            "ms_per_iteration": float(np.mean(self.step_ms)) if self.step_ms else float("nan"),
            "step_ms": list(self.step_ms),
        }


def _raster_camera(cam: Camera):
    from .raster import RasterCamera

    return RasterCamera(
        K=np.asarray(cam.K, np.float64),
        cam_from_world=np.asarray(cam.cam_from_world, np.float64)[:3, :4],
        width=int(cam.width),
        height=int(cam.height),
    )


def _splat_params(params: dict[str, np.ndarray], colors: np.ndarray):
    from .raster import SplatParams

    return SplatParams(
        means=params["means"],
        quats=params["quats"],
        log_scales=params["log_scales"],
        opacity_logits=params["opacity_logits"],
        colors=colors,
    )


def _mask_psnr(img: np.ndarray, target: np.ndarray, alpha_img: np.ndarray, alpha_t: np.ndarray) -> float:
    sel = (alpha_img > 1 / 255) | (alpha_t > 1 / 255)
    if not sel.any():
        return float("nan")
    mse = float(np.mean((np.clip(img[sel], 0, 1) - target[sel]) ** 2))
    return float("inf") if mse == 0 else 10 * math.log10(1 / mse)


def step_loss(
    image: np.ndarray,
    alpha: np.ndarray,
    target: np.ndarray,
    matte: np.ndarray,
    *,
    ssim_weight: float,
    alpha_weight: float,
    color_loss: str = "l1",
) -> tuple[float, np.ndarray, np.ndarray]:
    """The loss of one rendered view and its gradient.

    (1 − λ)·D(I, T) + λ·(1 − SSIM(I, T)) + w_α·mean|α − A| with I, T (H, W, 3) display
    colour over black, α, A (H, W), and D the mean |I − T| (``color_loss="l1"``) or the
    mean (I − T)² (``"l2"``). Returns (loss, ∂L/∂I, ∂L/∂α).
    """
    d = image - target
    n = d.size
    if color_loss == "l2":
        g_img = ((1 - ssim_weight) * 2.0 / n) * d
        loss = (1 - ssim_weight) * float(np.mean(d * d))
    else:
        g_img = ((1 - ssim_weight) / n) * np.sign(d)
        loss = (1 - ssim_weight) * float(np.abs(d).mean())
    if ssim_weight > 0:
        s, gs = ssim_and_grad(image, target)
        loss += ssim_weight * (1 - s)
        g_img = g_img - ssim_weight * gs
    da = alpha - matte
    loss += alpha_weight * float(np.abs(da).mean())
    g_a = (alpha_weight / da.size) * np.sign(da)
    return loss, g_img.astype(np.float32), g_a.astype(np.float32)


@dataclass(frozen=True)
class ViewGradient:
    """One view's forward and backward pass (:func:`view_gradient`)."""

    loss: float
    out: Any  # raster.RasterOutput: the rendered image, alpha, n_fragments
    raster: Any  # raster.RasterGrads: per-surfel gradients, means2d_abs, visible
    sh: np.ndarray  # (N, B, 3) float32, dL/d(SH coefficients)

    def param_grads(self) -> dict[str, np.ndarray]:
        """The gradient of every fitted parameter, keyed as the parameters are
        (``means``, ``quats``, ``log_scales``, ``opacity_logits``, ``sh``): what
        :meth:`Adam.step` takes."""
        g = self.raster
        return {
            "means": g.means,
            "quats": g.quats,
            "log_scales": g.log_scales,
            "opacity_logits": g.opacity_logits,
            "sh": self.sh,
        }


def view_gradient(
    params: dict[str, np.ndarray],
    sh: np.ndarray,
    raster_camera,
    centre_world: np.ndarray,
    target: np.ndarray,
    matte: np.ndarray,
    *,
    degree: int,
    raster_config,
    ssim_weight: float,
    alpha_weight: float,
    color_loss: str = "l1",
    base: np.ndarray | float = 0.5,
) -> ViewGradient:
    """Render one view of the surfels with SH colour ``sh`` (N, B, 3) over ``base``
    (:func:`appearance.sh_colors`), score it against ``target`` (H, W, 3) and ``matte``
    (H, W) with :func:`step_loss`, and take the gradients back to every parameter: the
    one step the fit, the residual-SH benchmark and the Dask benchmark all take."""
    from .raster import rasterize, rasterize_backward

    dirs = view_dirs(params["means"], centre_world)
    colors, basis, positive = sh_colors(sh, dirs, degree=degree, base=base)
    sp = _splat_params(params, colors)
    out = rasterize(sp, raster_camera, config=raster_config)
    loss, g_img, g_a = step_loss(
        out.image,
        out.alpha,
        target,
        matte,
        ssim_weight=ssim_weight,
        alpha_weight=alpha_weight,
        color_loss=color_loss,
    )
    g = rasterize_backward(out, sp, raster_camera, dL_dimage=g_img, dL_dalpha=g_a, config=raster_config)
    return ViewGradient(
        loss=loss,
        out=out,
        raster=g,
        sh=sh_colors_backward(g.colors, basis, positive, sh.shape[1]),
    )


def _sh_degree_at(config: FitConfig, it: int) -> int:
    if config.sh_degree_every <= 0:
        return int(config.sh_degree)
    return int(min(config.sh_degree, it // config.sh_degree_every))


def view_order(n_views: int, iterations: int, seed: int) -> np.ndarray:
    """The training view of every step: seeded permutations of the views, one per epoch."""
    rng = np.random.default_rng(seed)
    epochs = -(-max(iterations, 1) // max(n_views, 1))
    return np.concatenate([rng.permutation(n_views) for _ in range(epochs)])[:iterations]


def _checkpoint_meta(fingerprint: str, train_views: Sequence[int], config: FitConfig) -> dict:
    cfg = asdict(config)
    for k in ("time_budget_s", "checkpoint_every", "iterations"):  # may change on resume
        cfg.pop(k, None)
    return {"format": _CKPT_FORMAT, "model": fingerprint, "train_views": [int(v) for v in train_views], "config": cfg}


def _save_checkpoint(path: Path, meta: dict, it: int, params, adam: Adam, stats: GradStats, report: FitReport) -> None:
    arrays = {f"p_{k}": v for k, v in params.items()}
    arrays.update(adam.state())
    arrays["grad_accum"] = stats.accum
    arrays["grad_count"] = stats.count
    # no wall-clock times: a checkpoint repeats byte for byte (#35); a resumed fit's step_ms
    # holds only the steps run since
    rep = {"loss": report.loss, "psnr": report.psnr, "densify": report.densify}
    arrays["meta"] = np.frombuffer(json.dumps({**meta, "iteration": it, "report": rep}).encode(), np.uint8)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _load_checkpoint(path: Path, meta: dict):
    try:
        z = np.load(path)
        got = json.loads(bytes(z["meta"]).decode())
    except (OSError, ValueError, KeyError) as e:
        raise CheckpointError(f"{path}: unreadable fit checkpoint ({e})") from None
    if got.get("format") != _CKPT_FORMAT:
        raise CheckpointError(f"{path}: format {got.get('format')!r}, expected {_CKPT_FORMAT}")
    if got.get("model") != meta["model"]:
        raise CheckpointError(
            f"{path}: checkpoint of another model (fingerprint {str(got.get('model'))[:12]}…, this model {meta['model'][:12]}…)"
        )
    for k in ("train_views", "config"):
        if got.get(k) != meta[k]:
            raise CheckpointError(
                f"{path}: checkpoint fitted with other {k.replace('_', ' ')}; remove it to start over"
            )
    params = {k: np.asarray(z[f"p_{k}"]).copy() for k in PARAM_NAMES}
    return got, params, {k: z[k] for k in z.files}


def fit_params(
    data: FitData,
    config: FitConfig,
    *,
    progress: Callable[[FitProgress], None] | None = None,
    checkpoint_path: Path | None = None,
    checkpoint_meta: dict | None = None,
    observe: Callable[[int, dict[str, np.ndarray]], None] | None = None,
    observe_every: int = 0,
) -> tuple[dict[str, np.ndarray], FitReport]:
    """The optimization itself over in-memory :class:`FitData` (see :func:`fit_model`).

    ``observe(step, params)`` is called every ``observe_every`` steps and after the
    last (a benchmark scores held-out views there; its time is not in ``step_ms``)."""
    from .raster import RasterConfig, spatial_order

    t_start = time.perf_counter()
    # the screen filter is a fixed area in pixels: at train_scale < 1 it would let the splats
    # shrink below a full-resolution pixel, which then renders holes (measured on the demo cup)
    rc = RasterConfig(lowpass_px2=RasterConfig().lowpass_px2 * config.train_scale**2)
    surf = data.surfels
    keep, grow = thin_start(len(surf), config.max_start_surfels, seed=config.seed)
    pos = surf.shading_positions() if config.start_surface == "refined" else surf.positions
    params = start_params(
        pos[keep], surf.normals[keep], surf.radii[keep] * grow, data.sh_dc[keep], sh_degree=config.sh_degree
    )
    extent = scene_extent(surf.positions)
    adam = Adam(params)
    stats = GradStats(len(params["means"]))
    report = FitReport(n_surfels_start=len(params["means"]), config=asdict(config))
    start_it = 0
    if checkpoint_path is not None and checkpoint_path.is_file():
        got, params, z = _load_checkpoint(checkpoint_path, checkpoint_meta or {})
        adam = Adam(params)
        adam.load(z)
        stats = GradStats(len(params["means"]))
        stats.accum, stats.count = z["grad_accum"].copy(), z["grad_count"].copy()
        start_it = int(got["iteration"])
        rep = got["report"]
        report.loss, report.psnr, report.densify = rep["loss"], rep["psnr"], rep["densify"]
        report.resumed_from = start_it
        log.info("fit: resumed from %s at step %d", checkpoint_path, start_it)
    T = int(config.iterations)
    order = view_order(len(data.views), T, config.seed)
    lr_start, lr_final = position_rates(config, len(data.views))
    cams = [_raster_camera(v.camera) for v in data.views]
    B = params["sh"].shape[1]
    it = start_it
    for it in range(start_it, T):
        if config.time_budget_s is not None and time.perf_counter() - t_start > config.time_budget_s:
            report.stopped_by = "time_budget"
            break
        t0 = time.perf_counter()
        view = data.views[int(order[it])]
        cam = cams[int(order[it])]
        deg = _sh_degree_at(config, it)
        vg = view_gradient(
            params,
            params["sh"],
            cam,
            view.camera.centre_world,
            view.target,
            view.alpha,
            degree=deg,
            raster_config=rc,
            ssim_weight=config.ssim_weight,
            alpha_weight=config.alpha_weight,
            color_loss=config.color_loss,
        )
        loss, out, g = vg.loss, vg.out, vg.raster
        grads = vg.param_grads()
        lr_pos = exp_decay(it, T, start=lr_start * extent, final=lr_final * extent)
        sh_lr = np.full((B, 1), config.lr_sh_rest, np.float32)
        sh_lr[0] = config.lr_sh_dc
        lrs = {
            "means": lr_pos,
            "quats": config.lr_rotation,
            "log_scales": config.lr_scale,
            "opacity_logits": config.lr_opacity,
            "sh": sh_lr,
        }
        adam.step(params, grads, lrs, active_cols={"sh": 3 * (deg + 1) ** 2})
        if config.densify_from <= it < config.densify_until:
            stats.add(np.asarray(g.means2d_abs, np.float64) * 0.5 * view.camera.width, np.asarray(g.visible, bool))
            if (it + 1) % config.densify_every == 0 and it + 1 > config.densify_from:
                params, res = densify_and_prune(
                    params,
                    adam,
                    stats,
                    grad_threshold=config.densify_grad_threshold,
                    scale_limit_m=config.densify_scale_fraction * extent,
                    prune_opacity=config.prune_opacity,
                    prune_scale_m=config.prune_scale_fraction * extent,
                    max_surfels=config.max_surfels,
                    rng=np.random.default_rng([config.seed, it]),
                )
                # new surfels were appended: back to a spatially coherent memory order
                # (the rasterizer's tile passes stream through it)
                perm = spatial_order(params["means"])
                params = {k: np.ascontiguousarray(v[perm]) for k, v in params.items()}
                adam.keep(perm)
                stats = GradStats(len(params["means"]))
                report.densify.append({"iteration": it + 1, **asdict(res)})
                log.info("fit: step %d densify %s", it + 1, res)
        report.loss.append(float(loss))
        report.psnr.append(_mask_psnr(out.image, view.target, out.alpha, view.alpha))
        report.step_ms.append(1e3 * (time.perf_counter() - t0))
        if progress is not None:
            tail = [p for p in report.psnr[-len(data.views) :] if math.isfinite(p)]
            progress(
                FitProgress(
                    it + 1,
                    T,
                    float(loss),
                    float(np.mean(tail)) if tail else float("nan"),
                    len(params["means"]),
                    time.perf_counter() - t_start,
                )
            )
        if observe is not None and observe_every and (it + 1) % observe_every == 0:
            observe(it + 1, params)
        if checkpoint_path is not None and config.checkpoint_every and (it + 1) % config.checkpoint_every == 0:
            _save_checkpoint(checkpoint_path, checkpoint_meta or {}, it + 1, params, adam, stats, report)
    else:
        it = T
    report.iterations = len(report.loss)
    if observe is not None and (not observe_every or report.iterations % observe_every):
        observe(report.iterations, params)
    report.n_surfels_end = len(params["means"])
    report.seconds = time.perf_counter() - t_start
    return params, report


def fit_model(
    model_dir: Path,
    *,
    train_views: Sequence[int],
    config: FitConfig,
    progress: Callable[[FitProgress], None] | None = None,
    checkpoint_dir: Path | None = None,
) -> FitReport:
    """Fit the model's surfels to its training views and write them into the model.

    Parameters
    ----------
    model_dir : a built model (``model.toml``, ``surfels.ply``, ``views/``).
    train_views : indices of the model's views to fit (the held-out views are left out
        here; they must also have been left out of the hull by the caller).
    config : :class:`FitConfig` (``mode="none"`` writes nothing and returns an empty report).
    progress : called with a :class:`FitProgress` after every step.
    checkpoint_dir : where ``fit_checkpoint.npz`` is written every
        ``config.checkpoint_every`` steps and resumed from when present; a checkpoint of
        another model, other views or other options raises :class:`CheckpointError`
        before anything is written.

    Returns
    -------
    :class:`FitReport`; ``MODEL/optimized/splats.ply`` (3DGS/2DGS layout,
    :mod:`.splatply`) and ``MODEL/optimized/fit.json`` are written at the end.
    """
    model_dir = Path(model_dir)
    if config.mode == "none":
        return FitReport(config=asdict(config))
    data = load_fit_data(model_dir, train_views, train_scale=config.train_scale, start_surface=config.start_surface)
    ckpt = None if checkpoint_dir is None else Path(checkpoint_dir) / CHECKPOINT_NAME
    meta = _checkpoint_meta(data.fingerprint, train_views, config)
    if ckpt is not None and ckpt.is_file():
        _load_checkpoint(ckpt, meta)  # refuse another model's before any work
    params, report = fit_params(data, config, progress=progress, checkpoint_path=ckpt, checkpoint_meta=meta)
    out = model_dir / OPTIMIZED_DIR
    out.mkdir(exist_ok=True)
    write_splat_ply(out / SPLATS_PLY, params)
    report.splats_ply = str(out / SPLATS_PLY)
    with atomic_path(out / "fit.json") as tmp:
        tmp.write_text(
            json.dumps(
                {
                    **report.summary(),
                    "train_views": [int(v) for v in train_views],
                    "model": model_fingerprint(model_dir),
                    "loss": report.loss,
                    "psnr": report.psnr,
                    "densify": report.densify,
                    "config": report.config,
                }
            )
        )
    return report


def load_fitted(model_dir: Path) -> dict[str, np.ndarray]:
    """The fitted parameters of a model (``MODEL/optimized/splats.ply``)."""
    p = Path(model_dir) / OPTIMIZED_DIR / SPLATS_PLY
    if not p.is_file():
        raise InputError(f"{model_dir}: no fitted surfels ({p} missing); build with fitting first")
    return read_splat_ply(p)


def render_params(params: dict[str, np.ndarray], camera: Camera, *, sh_degree: int | None = None) -> np.ndarray:
    """(H, W, 4) float32 straight linear RGBA of the fitted surfels seen by ``camera``
    (the same image type as :func:`opacityhull.render.renderer.render_image`'s ``rgba``)."""
    from .raster import RasterConfig, rasterize

    B = params["sh"].shape[1]
    deg = int(round(math.sqrt(B))) - 1 if sh_degree is None else int(sh_degree)
    colors, _, _ = sh_colors(params["sh"], view_dirs(params["means"], camera.centre_world), degree=deg)
    out = rasterize(_splat_params(params, colors), _raster_camera(camera), config=RasterConfig())
    a = np.clip(out.alpha, 0.0, 1.0).astype(np.float32)
    premul = srgb_decode(np.clip(out.image, 0.0, 1.0))
    straight = np.where(a[..., None] > 1e-6, premul / np.maximum(a[..., None], 1e-6), 0.0)
    return np.concatenate([straight, a[..., None]], axis=2).astype(np.float32)


def render_fitted(model_dir: Path, camera: Camera) -> np.ndarray:
    """The fitted model of ``model_dir`` rendered for any ``camera``: (H, W, 4) straight
    linear RGBA (see :func:`render_params`)."""
    return render_params(load_fitted(model_dir), camera)
