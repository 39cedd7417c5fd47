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
from collections.abc import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import atomic_path, straight_from_premul, write_exr, write_png
from ..pictures import auto_exposure, contact_sheet, to_srgb8, write_animation, write_sheet
from ..envmap import EnvironmentMap
from .envmap import default_yaw_deg, load_envmap
from .relit import Relighter, RelightConfig

__all__ = [
    "view_camera",
    "orbit_cameras",
    "parse_view_spec",
    "auto_exposure",
    "write_gif",
    "builtin_envmap",
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


def _display(rgb: np.ndarray, exposure: float) -> np.ndarray:
    """Linear → display-linear in [0, 1] (sRGB encoding happens in write_png)."""
    return np.clip(np.asarray(rgb[..., :3], np.float32) * np.float32(exposure), 0, 1)


def write_gif(path, frames_linear: Sequence[np.ndarray], *, fps: float = 12.0) -> Path:
    """Animated GIF of display-linear frames in [0, 1] (sRGB-encoded, looping) at
    ``fps`` (:func:`opacityhull.pictures.write_animation`)."""
    return write_animation(path, [to_srgb8(f) for f in frames_linear], fps=fps)


# --------------------------------------------------------------------------- runner


def builtin_envmap(probe: str) -> EnvironmentMap:
    """The shipped light probe ``probe`` (``builtin:<probe>``) with its default yaw."""
    spec = f"builtin:{probe}"
    return load_envmap(spec, yaw_deg=default_yaw_deg(spec))


def relight_model(
    model_path,
    *,
    out,
    envmap: EnvironmentMap | None = None,
    lights: tuple[np.ndarray, np.ndarray] | None = None,
    view: tuple[int, float] | None = None,
    orbit: int | None = None,
    fps: float = 12.0,
    config: RelightConfig = RelightConfig(),
    exposure: float | None = None,
    write_views: bool = True,
    render_config=None,
    renderer: str = "auto",
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Relight a model and write the pictures.

    ``envmap`` (:func:`~.envmap.load_envmap`) and/or ``lights`` ((M, 3) unit directions
    towards the lights and (M, 3) RGB irradiance, :func:`~.basis.parse_lights`) give the
    new lighting; at least one is required.

    Writes ``out/views/<view id>.exr`` (relit premultiplied RGBA of every captured
    view) and ``.png`` (over the environment), ``out/views.png`` (contact sheet);
    with ``view`` ``out/view_<id>.exr|png``; with ``orbit`` ``out/orbit/frame_NNN.exr|png``,
    ``out/orbit.gif`` (at ``fps``) and ``out/orbit.png``; and ``out/relight.json`` (the summary,
    also returned).

    ``renderer`` (``view``/``orbit``): ``"fitted"`` draws the fitted splats of ``build
    --optimize``, each with the relit views' ULR colour at its nearest hull surfel
    (:meth:`opacityhull.render.splats.FittedSplats.render_relit`); ``"ulr"`` the hull's
    surfels; ``"auto"`` the splats when the model has current ones. The captured views are
    relit from their own one-light images either way.
    """
    from ..model import OpacityHullModel
    from ..render.splats import resolve_renderer

    t0 = time.perf_counter()
    out = Path(out)
    model = OpacityHullModel.open(model_path)
    used = resolve_renderer(Path(model.root), renderer)
    out.mkdir(parents=True, exist_ok=True)
    if envmap is None and lights is None:
        raise InputError("relight: no lighting given (an environment map, lights, or both)")
    if lights is not None:
        d, e = (np.asarray(x, np.float64) for x in lights)
        if d.ndim != 2 or d.shape[1:] != (3,) or e.shape != d.shape or not np.isfinite(np.r_[d, e]).all():
            raise InputError(f"relight: lights of shapes {d.shape} and {e.shape}, expected two finite (M, 3) arrays")
        lights = (d, e)
    env, light_list = envmap, lights
    R = Relighter(model, config=config)
    n = len(model.views)
    n_frames = (1 if view is not None else 0) + (orbit or 0)
    total = n + n_frames
    summary: dict = {
        "model": str(model.root),
        "out": str(out),
        "lighting": {
            "envmap": env.stats() if env is not None else None,
            "lights": None
            if light_list is None
            else [{"direction": d.tolist(), "irradiance_rgb": e.tolist()} for d, e in zip(*light_list, strict=True)],
        },
        "n_lights_captured": len(R.lights),
        # what draws --view/--orbit: the fitted splats (build --optimize) or the hull by ULR
        "renderer": used,
        "light_spacing_deg": math.degrees(R.lights.spacing_rad()),
        "config": {"kernel": asdict(config.kernel), "near_light": R.near_light, "pca_rank": config.pca_rank},
        "n_views": n,
    }

    # step 1: relight every captured view
    t1 = time.perf_counter()
    relit = []
    # the sphere split: the display fields relight the directions the displays cover,
    # the one-light images every other direction (each counted once)
    from .natural_views import array_envmap, natural_centre_m

    split = env is not None and bool(model.meta.get("natural", {}).get("present"))
    centre = natural_centre_m(model) if split else None
    for i in range(n):
        env_i = array_envmap(model, env, model.views[i].table_deg, centre_m=centre) if split else env
        relit.append(R.relight_view(i, envmap=env_i, lights=light_list))
        if progress:
            progress(i + 1, total)
    if env is not None and model.meta.get("natural", {}).get("present"):
        # the display-domain field (refraction, high resolution) adds to the light-array
        # field (everything else): the environment seen through the displays' solid angles
        from .natural_views import relight_model_views_natural

        t_nat = time.perf_counter()
        for i, part in enumerate(relight_model_views_natural(model, env)):
            if part is not None:
                relit[i][..., :3] += part
        summary["natural_field_s"] = time.perf_counter() - t_nat
    summary["relit_views_s"] = time.perf_counter() - t1
    summary["relit_views_per_s"] = n / max(summary["relit_views_s"], 1e-9)
    if config.pca_rank is not None and R.pca_stats:
        st = list(R.pca_stats.values())
        summary["pca"] = {
            "rank": config.pca_rank,
            "reflectance_rel_error_mean": float(np.mean([s["rel_error"] for s in st])),
            "reflectance_rel_error_max": float(np.max([s["rel_error"] for s in st])),
            "compression_ratio": float(np.mean([s["compression_ratio"] for s in st])),
        }

    # one exposure for everything written, from the captured views (no flicker)
    if exposure is None:
        mid = relit[len(relit) // 2]
        exposure = auto_exposure(mid[..., :3], mid[..., 3])
    summary["exposure"] = exposure

    from ..render.background import composite_over, resolve_background

    bg = env if env is not None else (0.0, 0.0, 0.0)
    if write_views:
        tiles, labels = [], []
        for i, rgba in enumerate(relit):
            vid = model.views[i].id
            write_exr(out / "views" / f"{vid}.exr", rgba)
            straight = straight_from_premul(rgba)
            over = composite_over(straight, resolve_background(bg, model.views[i].camera))
            write_png(out / "views" / f"{vid}.png", _display(over, exposure))
            tiles.append(_display(over, exposure))
            labels.append(vid)
        write_sheet(
            out / "views.png", contact_sheet([to_srgb8(t) for t in tiles[:64]], labels=labels[:64], min_width=160)
        )
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
        fitted = None
        if used == "fitted":
            from ..render.splats import FittedSplats

            fitted = FittedSplats.load(Path(model.root))

        def draw(cam):
            if fitted is not None:
                return fitted.render_relit(cam, surfels, cams, relit, k=rc.k)
            return render_image(surfels, cams, pv, cam, config=rc)

        done = n
        t2 = time.perf_counter()
        if view is not None:
            cam = view_camera(model, *view)
            res = draw(cam)
            img = res.over(bg)
            write_exr(out / f"view_{cam.name}.exr", res.premul)  # premultiplied, as every EXR
            write_png(out / f"view_{cam.name}.png", _display(img, exposure))
            summary["view"] = {
                "camera": cam.name,
                "exr": str(out / f"view_{cam.name}.exr"),
                "png": str(out / f"view_{cam.name}.png"),
                "ms": res.stats.get("ms", {}).get("total"),
            }
            done += 1
            if progress:
                progress(done, total)
        if orbit:
            frames = []
            t3 = time.perf_counter()
            for k, cam in enumerate(orbit_cameras(model, orbit)):
                res = draw(cam)
                img = res.over(bg)
                write_exr(out / "orbit" / f"frame_{k:03d}.exr", res.premul)
                frames.append(_display(img, exposure))
                write_png(out / "orbit" / f"frame_{k:03d}.png", frames[-1])
                done += 1
                if progress:
                    progress(done, total)
            orbit_s = time.perf_counter() - t3
            write_gif(out / "orbit.gif", frames, fps=fps)
            step = max(1, len(frames) // 16)
            write_sheet(
                out / "orbit.png",
                contact_sheet(
                    [to_srgb8(f) for f in frames[::step]],
                    min_width=160,
                    labels=[f"{k * step}" for k in range(len(frames[::step]))],
                ),
            )
            summary["orbit"] = {
                "frames": orbit,
                "dir": str(out / "orbit"),
                "gif": str(out / "orbit.gif"),
                "sheet": str(out / "orbit.png"),
                "render_s": orbit_s,
                "total_s": orbit_s + summary["relit_views_s"],
            }
        summary["render_s"] = time.perf_counter() - t2
    summary["total_s"] = time.perf_counter() - t0
    with atomic_path(out / "relight.json") as tmp:
        from ..jsonio import to_jsonable

        tmp.write_text(json.dumps(to_jsonable(summary), indent=2))
    return summary


def demo_step(
    model_dir,
    out_dir,
    *,
    probe: str = "grace",
    orbit: int = 24,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """The relighting step of ``opacityhull demo``: relight the captured model under a
    shipped probe (``builtin:<probe>``, ICT yaw applied), render an orbit of ``orbit``
    frames over the probe. Returns ``{"gif", "sheet", "views_sheet", ...}`` with the
    paths to show the user (the comparison with Mitsuba is
    :func:`opacityhull.evaluate.runner.demo_relight_eval`)."""
    out = Path(out_dir)
    s = relight_model(model_dir, out=out, envmap=builtin_envmap(probe), orbit=orbit, progress=progress)
    res = {
        "probe": probe,
        "out": str(out),
        "gif": s["orbit"]["gif"],
        "sheet": s["orbit"]["sheet"],
        "views_sheet": s.get("views_sheet"),
        "relit_views_per_s": s["relit_views_per_s"],
        "orbit_s": s["orbit"]["total_s"],
    }
    return res
