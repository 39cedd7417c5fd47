"""File-level runners behind ``opacityhull render`` and ``opacityhull eval loo``: open a
model, choose cameras, render, write images (EXR/PNG), orbits as frames plus an animated
GIF (and an MP4 when an ffmpeg writer is available), and JSON-ready summaries."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import write_exr, write_png
from ..model import OpacityHullModel
from .background import EnvMap, fit_image, load_background
from .cameras import (captured_view_camera, look_at_camera, mean_fov_y_deg, orbit_cameras, parse_look_at,
                      parse_view_spec, resize_camera, scene_target)
from .renderer import RenderConfig, RenderResult, model_surfels, prepare_model_views, render_image

__all__ = ["choose_cameras", "run_render", "run_loo", "run_demo_step", "write_frame"]

_SUFFIXES = (".png", ".exr")


def choose_cameras(model: OpacityHullModel, *, view: str | None = None, look_at: str | None = None,
                   orbit: int | None = None, width: int | None = None, height: int | None = None) -> list[Camera]:
    """Cameras from the CLI options (at most one of view / look_at / orbit; default: the
    first captured view)."""
    given = [n for n, v in (("--view", view), ("--look-at", look_at), ("--orbit", orbit)) if v is not None]
    if len(given) > 1:
        raise InputError(f"give only one of --view, --look-at, --orbit (got {', '.join(given)})")
    cams = [v.camera for v in model.views]
    if orbit is not None:
        fallback = model_surfels(model).positions.mean(axis=0)
        return orbit_cameras(cams, int(orbit), width=width, height=height, target=scene_target(cams, fallback))
    if look_at is not None:
        eye, target, fov = parse_look_at(look_at)
        ref = cams[0]
        w = int(width) if width else ref.width
        h = int(height) if height else (ref.height if not width else max(1, round(ref.height * w / ref.width)))
        return [look_at_camera(eye, target, fov_y_deg=fov if fov is not None else mean_fov_y_deg(cams), width=w,
                               height=h)]
    if view is not None:
        c, a = parse_view_spec(view)
        cam = captured_view_camera(model.views, c, a)
    else:
        cam = cams[0]
    return [resize_camera(cam, width, height)]


def write_frame(path: Path, result: RenderResult, background) -> Path:
    """EXR: straight RGBA float (or composited RGB when a background is given). PNG:
    sRGB-encoded RGBA with straight alpha (or composited RGB)."""
    if background is None:
        img = result.rgba
    else:
        img = result.over(background)
    if path.suffix.lower() == ".exr":
        write_exr(path, img)
    else:
        write_png(path, img)
    return path


def _animation(frames: list[np.ndarray], out_stem: Path, fps: float) -> dict:
    import imageio.v2 as iio

    from ..imageio import srgb_encode

    out = {}
    u8 = [np.round(srgb_encode(f) * 255).astype(np.uint8) for f in frames]
    gif = out_stem.with_suffix(".gif")
    tmp = gif.with_name(f".tmp-{gif.name}")
    iio.mimsave(tmp, u8, duration=1000.0 / fps, loop=0)
    tmp.replace(gif)
    out["gif"] = str(gif)
    if shutil.which("ffmpeg"):
        try:
            mp4 = out_stem.with_suffix(".mp4")
            tmp = mp4.with_name(f".tmp-{mp4.name}")
            iio.mimsave(tmp, u8, fps=fps, format="FFMPEG")
            tmp.replace(mp4)
            out["mp4"] = str(mp4)
        except Exception as e:  # the optional writer plugin may be missing
            out["mp4_error"] = str(e)
    return out


def run_render(model_path, out, *, view=None, look_at=None, orbit=None, width=None, height=None,
               config: RenderConfig = RenderConfig(), background: str | None = None, background_kind: str = "auto",
               env_yaw_deg: float = 0.0, exclude: Sequence[str] = (), fps: float = 12.0,
               progress: Callable[[int, int], None] | None = None) -> dict:
    """Render one frame or an orbit of a model folder to ``out`` (``.png`` or ``.exr``)."""
    out = Path(out)
    if out.suffix.lower() not in _SUFFIXES:
        raise InputError(f"--out {out}: expected a .png or .exr file name")
    model = OpacityHullModel.open(model_path)
    cams = choose_cameras(model, view=view, look_at=look_at, orbit=orbit, width=width, height=height)
    bg = load_background(background, yaw_deg=env_yaw_deg, kind=background_kind) if background is not None else None
    if isinstance(bg, np.ndarray):
        bg = fit_image(bg, cams[0])
    excl = []
    for e in exclude:
        excl.append(int(e) if str(e).isdigit() else model.view_index(str(e)))
    t0 = time.perf_counter()
    pv = prepare_model_views(model)
    surfels = model_surfels(model)
    t_load = time.perf_counter() - t0
    paths, frames, ms = [], [], []
    anim_bg = bg if bg is not None else (0.18, 0.18, 0.18)
    for i, cam in enumerate(cams):
        t = time.perf_counter()
        res = render_image(surfels, [v.camera for v in model.views], pv, cam, config=config, exclude_views=excl)
        ms.append(1e3 * (time.perf_counter() - t))
        p = out if orbit is None else out.with_name(f"{out.stem}_{i:03d}{out.suffix}")
        paths.append(str(write_frame(p, res, bg)))
        if orbit is not None:
            frames.append(res.over(anim_bg))
        if progress:
            progress(i + 1, len(cams))
    summary = {
        "model": str(model_path),
        "frames": len(cams),
        "paths": paths,
        "width": cams[0].width,
        "height": cams[0].height,
        "k": config.k,
        "surfels": len(surfels),
        "ms_per_frame": float(np.mean(ms)),
        "ms_first_frame": ms[0],
        "ms_load": 1e3 * t_load,
        "background": None if background is None else ("envmap" if isinstance(bg, EnvMap) else str(background)),
    }
    if orbit is not None:
        summary.update(_animation(frames, out.with_name(out.stem), fps))
    return summary


def run_loo(model_path, *, views=None, config: RenderConfig = RenderConfig(), out=None,
            progress: Callable[[int, int], None] | None = None) -> dict:
    """Leave-one-out evaluation of a model folder; writes ``loo.json`` and
    ``loo_sheet.png`` to ``out`` (default ``MODEL/pictures``)."""
    import json

    from ..cliutil import to_jsonable
    from ..imageio import atomic_path
    from .evaluate import leave_one_out, select_views

    model = OpacityHullModel.open(model_path)
    idx = select_views(model, views)
    out = Path(out) if out is not None else Path(model_path) / "pictures"
    summary = leave_one_out(model, views=idx, config=config, sheet_path=out / "loo_sheet.png", progress=progress)
    with atomic_path(out / "loo.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable(summary), indent=1))
    summary["json"] = str(out / "loo.json")
    return summary


def run_demo_step(model_path, out, *, frames: int = 24, loo_views: str | None = "every:2",
                  background: str = "grey", progress: Callable[[int, int], None] | None = None) -> dict:
    """The renderer's part of ``opacityhull demo``: an orbit of the model (PNG frames +
    GIF) and a leave-one-out evaluation (JSON + contact sheet) under ``out``. Returns a
    summary with the paths, ready for the demo's report."""
    out = Path(out)
    orbit = run_render(model_path, out / "orbit" / "orbit.png", orbit=frames, background=background, progress=progress)
    loo = run_loo(model_path, views=loo_views, out=out)
    return {
        "orbit_gif": orbit.get("gif"),
        "orbit_frames": orbit["paths"],
        "ms_per_frame": orbit["ms_per_frame"],
        "loo": {k: loo[k] for k in ("psnr_mean", "ssim_mean", "alpha_mae", "ms_per_view")},
        "loo_sheet": loo.get("sheet"),
        "loo_json": loo["json"],
    }
