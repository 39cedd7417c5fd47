"""Runners of the relighting stage: model folder in, images and a JSON summary out.

``relight_model`` relights every captured view (step 1) and, for ``--view`` or
``--orbit``, blends the relit views onto the surfels with the ULR renderer (step 2),
compositing over the environment map. ``eval_relight`` (in :mod:`.evaluate`) compares
relit captured views with the simulator's direct render.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import atomic_path, write_exr, write_png
from .basis import parse_lights
from .envmap import default_yaw_deg, load_envmap
from .relit import Relighter, RelightConfig

__all__ = [
    "view_camera",
    "orbit_cameras",
    "parse_view_spec",
    "auto_exposure",
    "contact_sheet",
    "write_gif",
    "relight_model",
]


# --------------------------------------------------------------------------- cameras


def parse_view_spec(spec: str) -> tuple[int, float]:
    """``"CAM,TABLE_DEG"`` → (camera index, table angle); the renderer's parser."""
    from ..render.cameras import parse_view_spec as parse

    return parse(spec)


def view_camera(model, camera_index: int, table_deg: float) -> Camera:
    """Physical camera ``camera_index`` at table angle ``table_deg`` in the object frame
    (the captured view itself, or its camera turned by the table): the renderer's
    ``captured_view_camera``, so ``relight --view`` and ``render --view`` agree."""
    from ..render.cameras import captured_view_camera

    return captured_view_camera(model.views, camera_index, table_deg)


def orbit_cameras(model, n: int) -> list[Camera]:
    """The renderer's orbit (``render --orbit N``): ``n`` cameras on a circle about +Y
    through the point the rig aims at, at the captured cameras' mean elevation and
    distance."""
    from ..render.renderer import model_surfels
    from ..render.cameras import orbit_cameras as orbit, scene_target

    cams = [v.camera for v in model.views]
    return orbit(cams, int(n), target=scene_target(cams, model_surfels(model).positions.mean(axis=0)))


# --------------------------------------------------------------------------- pictures


def auto_exposure(rgb_premul: np.ndarray, alpha: np.ndarray, *, key: float = 0.18) -> float:
    """Exposure multiplier mapping the log-average luminance of the object (alpha >
    0.5) to ``key`` (Reinhard's key value); 1 when the object is black or absent."""
    lum = np.asarray(rgb_premul[..., :3], np.float64) @ [0.2126, 0.7152, 0.0722]
    m = alpha > 0.5
    if not m.any():
        return 1.0
    a = np.clip(alpha[m], 1e-6, None)
    L = lum[m] / a
    L = L[L > 0]
    if L.size == 0:
        return 1.0
    return float(key / math.exp(np.mean(np.log(L + 1e-12))))


def contact_sheet(images: Sequence[np.ndarray], *, columns: int | None = None, labels: Sequence[str] | None = None,
                  gap: int = 2, min_width: int = 160) -> np.ndarray:
    """Tile (H, W, 3) float images (possibly different sizes) into one sheet, each
    with an optional label; display-ready values in [0, 1] are expected. Tiles
    narrower than ``min_width`` are enlarged by an integer factor (nearest) so the
    labels stay readable."""
    import cv2

    n = len(images)
    f = max(1, int(math.ceil(min_width / max(1, max(im.shape[1] for im in images)))))
    if f > 1:
        images = [np.repeat(np.repeat(np.asarray(im), f, axis=0), f, axis=1) for im in images]
    if n == 0:
        raise InputError("contact sheet of no images")
    cols = columns or int(math.ceil(math.sqrt(n)))
    rows = int(math.ceil(n / cols))
    h = max(im.shape[0] for im in images)
    w = max(im.shape[1] for im in images)
    sheet = np.ones((rows * (h + gap) + gap, cols * (w + gap) + gap, 3), np.float32) * 0.25
    for i, im in enumerate(images):
        r, c = divmod(i, cols)
        y, x = gap + r * (h + gap), gap + c * (w + gap)
        tile = np.clip(np.asarray(im[..., :3], np.float32), 0, 1).copy()
        if labels is not None and labels[i]:
            # OpenCV draws text on 8-bit images only: draw into a mask and paint the
            # label white on a dark band so it reads on any tile
            text = str(labels[i])
            scale = 0.4
            (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
            if tw > tile.shape[1] - 4:
                scale *= (tile.shape[1] - 4) / tw
                (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
            band = min(tile.shape[0], th + base + 4)
            tile[:band] *= 0.35
            mask = np.zeros(tile.shape[:2], np.uint8)
            cv2.putText(mask, text, (2, th + 2), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1, cv2.LINE_AA)
            m = mask.astype(np.float32)[..., None] / 255.0
            tile[:] = tile * (1 - m) + m
        sheet[y : y + tile.shape[0], x : x + tile.shape[1]] = tile
    return sheet


def _display(rgb: np.ndarray, exposure: float) -> np.ndarray:
    """Linear → display-linear in [0, 1] (sRGB encoding happens in write_png)."""
    return np.clip(np.asarray(rgb[..., :3], np.float32) * np.float32(exposure), 0, 1)


def write_gif(path, frames_linear: Sequence[np.ndarray], *, fps: float = 12.0) -> None:
    """Animated GIF of display-linear frames in [0, 1] (sRGB-encoded, looping)."""
    import imageio.v2 as iio

    from ..imageio import srgb_encode

    frames = [np.round(srgb_encode(f) * 255).astype(np.uint8) for f in frames_linear]
    path = Path(path)
    with atomic_path(path) as tmp:
        iio.mimsave(str(tmp), frames, format="GIF", duration=1.0 / fps, loop=0)


# --------------------------------------------------------------------------- runner


def _load_lighting(envmap_path, yaw_deg, probe_format, flip_u, lights_spec):
    env = None
    lights = None
    if envmap_path is None and not lights_spec:
        raise InputError("give --envmap X.exr|X.hdr or --lights 'dx,dy,dz,r,g,b;...'")
    if envmap_path is not None:
        if yaw_deg is None:
            yaw_deg = default_yaw_deg(envmap_path)
        env = load_envmap(envmap_path, yaw_deg=yaw_deg, probe_format=probe_format, flip_u=flip_u)
    if lights_spec:
        lights = parse_lights(lights_spec)
    return env, lights


def relight_model(
    model_path,
    *,
    out,
    envmap: str | Path | None = None,
    yaw_deg: float | None = None,
    probe_format: str = "latlong",
    flip_u: bool = False,
    lights: str | None = None,
    view: tuple[int, float] | None = None,
    orbit: int | None = None,
    config: RelightConfig = RelightConfig(),
    exposure: float | None = None,
    write_views: bool = True,
    render_config=None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Relight a model and write the pictures.

    Writes ``out/views/<view id>.exr`` (relit premultiplied RGBA of every captured
    view) and ``.png`` (over the environment), ``out/views.png`` (contact sheet);
    with ``view`` ``out/view_<id>.exr|png``; with ``orbit`` ``out/orbit/frame_NNN.exr|png``,
    ``out/orbit.gif`` and ``out/orbit.png``; and ``out/relight.json`` (the summary,
    also returned).
    """
    from ..model import OpacityHullModel

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = OpacityHullModel.open(model_path)
    env, light_list = _load_lighting(envmap, yaw_deg, probe_format, flip_u, lights)
    R = Relighter(model, config=config)
    n = len(model.views)
    n_frames = (1 if view is not None else 0) + (orbit or 0)
    total = n + n_frames
    summary: dict = {
        "model": str(model.root),
        "out": str(out),
        "lighting": {"envmap": env.stats() if env is not None else None,
                     "lights": None if light_list is None else
                     [{"direction": d.tolist(), "irradiance_rgb": e.tolist()} for d, e in zip(*light_list)]},
        "n_lights_captured": len(R.lights),
        "light_spacing_deg": math.degrees(R.lights.spacing_rad()),
        "config": {"kernel": asdict(config.kernel), "near_light": R.near_light, "pca_rank": config.pca_rank},
        "n_views": n,
    }

    # step 1: relight every captured view
    t1 = time.perf_counter()
    relit = []
    for i in range(n):
        relit.append(R.relight_view(i, envmap=env, lights=light_list))
        if progress:
            progress(i + 1, total)
    if env is not None and model.meta.get("natural", {}).get("present"):
        # the display-domain field (refraction, high resolution) adds to the light-array
        # field (everything else): the environment seen through the displays' solid angles
        from .natural import relight_model_views_natural

        t_nat = time.perf_counter()
        for i, part in enumerate(relight_model_views_natural(model, env)):
            if part is not None:
                relit[i][..., :3] += part
        summary["natural_field_s"] = time.perf_counter() - t_nat
    summary["relit_views_s"] = time.perf_counter() - t1
    summary["relit_views_per_s"] = n / max(summary["relit_views_s"], 1e-9)
    if config.pca_rank is not None and R.pca_stats:
        st = list(R.pca_stats.values())
        summary["pca"] = {"rank": config.pca_rank,
                          "reflectance_rel_error_mean": float(np.mean([s["rel_error"] for s in st])),
                          "reflectance_rel_error_max": float(np.max([s["rel_error"] for s in st])),
                          "compression_ratio": float(np.mean([s["compression_ratio"] for s in st]))}

    # one exposure for everything written, from the captured views (no flicker)
    if exposure is None:
        mid = relit[len(relit) // 2]
        exposure = auto_exposure(mid[..., :3], mid[..., 3])
    summary["exposure"] = exposure

    from ..render.background import EnvMap, composite_over, resolve_background

    bg = EnvMap(np.asarray(env.radiance)) if env is not None else (0.0, 0.0, 0.0)
    if write_views:
        tiles, labels = [], []
        for i, rgba in enumerate(relit):
            vid = model.views[i].id
            write_exr(out / "views" / f"{vid}.exr", rgba)
            straight = _straight(rgba)
            over = composite_over(straight, resolve_background(bg, model.views[i].camera))
            write_png(out / "views" / f"{vid}.png", _display(over, exposure))
            tiles.append(_display(over, exposure))
            labels.append(vid)
        write_png(out / "views.png", contact_sheet(tiles[:64], labels=labels[:64]))
        summary["views_dir"] = str(out / "views")
        summary["views_sheet"] = str(out / "views.png")

    # step 2: ULR blending of the relit views onto the surfels (colour and opacity)
    if n_frames:
        from ..render import RenderConfig, prepare_views, render_image
        from ..render.renderer import model_surfels

        rc = render_config or RenderConfig()
        cams = [v.camera for v in model.views]
        pv = prepare_views(cams, relit)
        surfels = model_surfels(model)
        done = n
        t2 = time.perf_counter()
        if view is not None:
            cam = view_camera(model, *view)
            res = render_image(surfels, cams, pv, cam, config=rc)
            img = res.over(bg)
            write_exr(out / f"view_{cam.name}.exr", res.rgba)
            write_png(out / f"view_{cam.name}.png", _display(img, exposure))
            summary["view"] = {"camera": cam.name, "exr": str(out / f"view_{cam.name}.exr"),
                               "png": str(out / f"view_{cam.name}.png"), "ms": res.stats.get("ms", {}).get("total")}
            done += 1
            if progress:
                progress(done, total)
        if orbit:
            frames = []
            t3 = time.perf_counter()
            for k, cam in enumerate(orbit_cameras(model, orbit)):
                res = render_image(surfels, cams, pv, cam, config=rc)
                img = res.over(bg)
                write_exr(out / "orbit" / f"frame_{k:03d}.exr", res.rgba)
                frames.append(_display(img, exposure))
                write_png(out / "orbit" / f"frame_{k:03d}.png", frames[-1])
                done += 1
                if progress:
                    progress(done, total)
            orbit_s = time.perf_counter() - t3
            write_gif(out / "orbit.gif", frames)
            step = max(1, len(frames) // 16)
            write_png(out / "orbit.png", contact_sheet(frames[::step], labels=[f"{k * step}" for k in range(len(frames[::step]))]))
            summary["orbit"] = {"frames": orbit, "dir": str(out / "orbit"), "gif": str(out / "orbit.gif"),
                                "sheet": str(out / "orbit.png"), "render_s": orbit_s,
                                "total_s": orbit_s + summary["relit_views_s"]}
        summary["render_s"] = time.perf_counter() - t2
    summary["total_s"] = time.perf_counter() - t0
    with atomic_path(out / "relight.json") as tmp:
        from ..cliutil import to_jsonable

        tmp.write_text(json.dumps(to_jsonable(summary), indent=2))
    return summary


def _straight(rgba_premul: np.ndarray) -> np.ndarray:
    out = np.asarray(rgba_premul, np.float32).copy()
    a = np.clip(out[..., 3:4], 0, 1)
    ok = a > 1.0 / 4096
    out[..., :3] = np.where(ok, out[..., :3] / np.where(ok, a, 1), 0)
    return out


def demo_step(model_dir, out_dir, *, probe: str = "grace", orbit: int = 24, eval_views: int | None = 6,
              progress: Callable[[int, int], None] | None = None) -> dict:
    """The relighting step of ``opacityhull demo``: relight the captured model under a
    shipped probe (``builtin:<probe>``, ICT yaw applied), render an orbit of ``orbit``
    frames over the probe, and — for a simulated model — compare ``eval_views`` relit
    views with Mitsuba's render. Returns ``{"gif", "sheet", "views_sheet", "eval"...}``
    with the paths to show the user."""
    out = Path(out_dir)
    s = relight_model(model_dir, out=out, envmap=f"builtin:{probe}", orbit=orbit, progress=progress)
    res = {"probe": probe, "out": str(out), "gif": s["orbit"]["gif"], "sheet": s["orbit"]["sheet"],
           "views_sheet": s.get("views_sheet"), "relit_views_per_s": s["relit_views_per_s"],
           "orbit_s": s["orbit"]["total_s"]}
    if eval_views:
        from .evaluate import eval_relight

        try:
            e = eval_relight(model_dir, envmap=f"builtin:{probe}", out=out / "eval", max_views=eval_views, spp=32)
            res["eval"] = {"rel_err_mean": e["rel_err_mean"], "psnr_mean": e["psnr_mean"], "sheet": e["sheet"]}
        except InputError as err:  # not a simulated model: nothing to compare with
            res["eval"] = {"skipped": str(err)}
    return res
