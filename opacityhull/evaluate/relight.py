"""``opacityhull eval relight``: relit captured views against the scene's ground truth.

For a model built from a simulated session, the truth of view (c, a) is Mitsuba's
direct render of the same object on the rig (displays present but dark, no light
array) at table angle a, seen by the view's camera, under the same environment map in
the object frame (:func:`opacityhull.sim.groundtruth.render_under_envmap`). The
scene comes from the model's provenance: ``[provenance] session`` → the session's
``[session] rig_source = "sim:<scene spec>"``. A model with a natural-illumination
field (``[natural] present``, a glass) is relit as ``relight`` relights it — the
light-array part plus the display-domain part — and its truth adds, to that render,
Mitsuba's render of each field's display showing the environment map over the
display's solid angle as the object centre sees it (as two 8-bit layers rendered and
summed, so a bright probe's dim part is not lost to quantisation:
:func:`~opacityhull.evaluate.natural.render_envmap_on_displays`), the same mapping
relight uses (:func:`~opacityhull.reconstruct.natural.envmap_display_image`). The analytic sphere of
:mod:`.synthetic` (provenance ``scene = "analytic:lambertian-sphere"``) is evaluated
against its exact quadrature instead, so the command can be exercised without Mitsuba.

Metrics, per view, on premultiplied colour (what the camera sees over black) over the
pixels the object fully covers according to the truth's coverage (α ≥ 0.99): this
measures relighting, not the matte, and no background leaks in:

* ``rel_err`` = ‖relit − truth‖₂ / ‖truth‖₂ (all channels),
* ``psnr`` = 10 log₁₀(peak² / MSE) with ``peak`` the largest truth value in the mask
  (HDR images have no fixed white; the object's own peak is the natural range),
* ``psnr_norm`` = 10 log₁₀(mean² / MSE), both images divided by the truth's mean: a dim
  probe with one highlight no longer hides a relit image that is half wrong (the
  relative error is the figure that matters; this is the PSNR that agrees with it).

An all-zero environment map is refused (:class:`~opacityhull.errors.InputError`): every
relative figure would divide by a zero truth.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import FormatError, InputError
from ..imageio import write_exr
from ..pictures import auto_exposure, contact_sheet, to_srgb8, write_sheet
from ..envmap import EnvironmentMap
from ..relight.envmap import require_light
from .metrics import relight_metrics
from ..relight.relit import Relighter, RelightConfig

__all__ = ["relight_metrics", "find_scene", "eval_relight", "MASK_ALPHA"]

#: matte alpha above which a pixel counts as fully covered by the object
MASK_ALPHA = 0.99


def find_scene(model) -> tuple[str, Any]:
    """The ground-truth source of a model: ``("sim", (scene spec str, session))`` or
    ``("analytic", provenance dict)``. Raises :class:`InputError` saying why a model
    cannot be evaluated (not simulated, session gone)."""
    prov = model.meta.get("provenance", {}) or {}
    if str(prov.get("scene", "")).startswith("analytic:"):
        return "analytic", prov
    sess_ref = None
    for key in ("session", "session_path", "session_dir"):
        if prov.get(key):
            sess_ref = prov[key]
            break
    if sess_ref is None and str(prov.get("rig_source", "")).startswith("sim:"):
        return "sim", (_scene_of(str(prov["rig_source"])), None)
    if sess_ref is None:
        raise InputError(
            f"{model.root}: eval relight needs a model built from a simulated session; its provenance "
            f"({sorted(prov)}) names no session"
        )
    from ..session import Session

    p = Path(sess_ref)
    candidates = [p] if p.is_absolute() else [model.root / p, Path.cwd() / p, model.root.parent / p]
    for c in candidates:
        if (c / "session.toml").is_file():
            sess = Session.open(c)
            break
    else:
        raise InputError(f"{model.root}: its session {sess_ref!r} is not found (tried {[str(c) for c in candidates]})")
    src = sess.source
    if not src.startswith("sim:"):
        raise InputError(
            f"{model.root}: eval relight compares against the simulator's ground truth, but this model's session "
            f"{sess.root} was captured on {src!r}, not a simulated rig (rig_source 'sim:<scene>')"
        )
    return "sim", (_scene_of(src), sess)


def _scene_of(rig_source: str) -> str:
    """Scene spec of a simulated rig source ``sim:SCENE[@RIG.toml][?options]``, parsed
    by the simulator's own parser."""
    try:
        from ..sim.simrig import parse_sim_spec
    except ImportError:  # simulator not installed: the same grammar, minimal
        body = rig_source[4:].split("?", 1)[0].split("@", 1)[0]
        return body
    return parse_sim_spec(rig_source)[0]


def _truth_renderer(model, kind, ref, *, spp: int) -> Callable:
    """callable(view index, envmap) → ((H, W, 3) premultiplied truth radiance, (H, W)
    true coverage alpha)."""
    if kind == "analytic":
        from ..relight.synthetic import SphereScene, sphere_groundtruth

        sph = ref.get("sphere", {})
        scene = SphereScene(
            centre_m=tuple(sph.get("centre_m", (0, 0.1, 0))),
            radius_m=float(sph.get("radius_m", 0.08)),
            albedo_rgb=tuple(sph.get("albedo_rgb", (0.75, 0.55, 0.35))),
            texture=float(sph.get("texture", 0.3)),
        )

        def analytic_truth(i, env):
            from ..relight.synthetic import sphere_hits

            _, h = sphere_hits(model.views[i].camera, scene, ss=2)
            return sphere_groundtruth(model.views[i].camera, scene, env, upper_only=True), h.mean(axis=2)

        return analytic_truth
    try:
        from ..sim.groundtruth import render_under_envmap
        from ..sim.scenes import load_scene
    except ImportError as e:
        raise InputError(
            f"eval relight needs the simulator's ground-truth renderer (opacityhull.sim.groundtruth): {e}"
        ) from None
    spec, _sess = ref
    scene = load_scene(spec)
    geom = model.geometry
    try:  # one Mitsuba scene cache for every view
        from ..sim.render import SimRenderer

        renderer = SimRenderer(scene, geom)
    except (ImportError, TypeError):
        renderer = None

    # The relit view is an image of the *physical* view (c, a): render the truth with the
    # simulator's true camera of that view, not the calibrated estimate (which may also
    # have fx != fy, which Mitsuba's sensor cannot represent).
    true_cams = {}
    if _sess is not None and _sess.groundtruth_dir is not None and (_sess.groundtruth_dir / "cameras").is_dir():
        from ..camera import read_colmap_text

        true_cams = dict(read_colmap_text(_sess.groundtruth_dir / "cameras"))

    def truth(i, env):
        v = model.views[i]
        cam = true_cams.get(v.id, v.camera)
        if cam is None:
            raise FormatError(f"{model.root}: view {v.id} has no camera to render its truth from")
        # a writable copy: Mitsuba's Bitmap refuses read-only arrays
        img = np.asarray(
            render_under_envmap(
                scene, cam, np.array(env.radiance), spp=spp, rig=geom, table_deg=v.table_deg, renderer=renderer
            ),
            np.float32,
        )
        return img[..., :3] * img[..., 3:4], img[..., 3]  # premultiplied by the true coverage

    return truth


def _natural_eval(model, kind, ref) -> dict | None:
    """For a simulated model with a natural-illumination field: callables adding the
    display-domain part to a relit view and the display-lit render to its truth."""
    nat = model.meta.get("natural", {}) or {}
    if kind != "sim" or not nat.get("present"):
        return None
    from ..relight.natural_views import natural_centre_m
    from .natural import natural_part_of_view, render_envmap_on_displays

    spec, sess = ref
    if sess is not None:
        from .natural import sim_rig_for_session

        rig = sim_rig_for_session(sess)
    else:
        from ..sim.simrig import open_sim_rig

        rig = open_sim_rig(str((model.meta.get("provenance", {}) or {}).get("rig_source")), open=False)
    displays = sorted(nat.get("displays", {}) or {})
    centre = natural_centre_m(model)

    def part(i, env):
        return natural_part_of_view(model, i, env, centre_m=centre)

    def array_env(i, env):
        from ..relight.natural_views import array_envmap

        return array_envmap(model, env, model.views[i].table_deg, centre_m=centre)

    def truth(i, env):
        v = model.views[i]
        return render_envmap_on_displays(rig, v.camera_index, v.table_deg, env, displays, centre_m=centre, seed=11)

    info = {
        "displays": displays,
        "centre_m": [float(x) for x in centre],
        "truth": "mitsuba: each field's display showing the map over its solid angle (two 8-bit layers, summed)",
    }
    info["split"] = "sphere split: the light array relights only the directions no field display covers"
    return {"part": part, "truth": truth, "info": info, "array_env": array_env}


def _pick(n: int, k: int | None) -> list[int]:
    if k is None or k >= n:
        return list(range(n))
    if k < 1:
        raise InputError(f"eval relight: max_views {k}, need at least 1")
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})


#: Fewer captured light directions than this and ``eval relight`` warns (terminal, JSON,
#: sheet): the light basis is too coarse for an environment map (a judgement, not a
#: measured threshold).
FEW_LIGHTS = 8


def few_lights_warning(n_lights: int) -> str:
    """What relighting from ``n_lights`` captured directions can show, and what to do."""
    return (
        f"only {n_lights} captured light direction(s): relighting sums one-light images, so an environment "
        f"map is seen through {n_lights} cell(s) of the sphere — expect large errors (the tiny plan's 2 "
        f"lights measured 58-82 %); capture with more lights (plan [phases.reflectance] lights/array_steps)"
    )


def eval_relight(
    model_path,
    *,
    envmap: EnvironmentMap,
    out=None,
    spp: int = 64,
    max_views: int | None = None,
    views: Sequence[int] | None = None,
    config: RelightConfig = RelightConfig(),
    write_images: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Relight the captured views of a simulated (or analytic) model and compare them
    with the ground truth under ``envmap`` (:func:`~.envmap.load_envmap`). Returns ``{"psnr_mean", "rel_err_mean", "per_view", ...}``
    and writes ``out/eval_relight.png`` (rows: truth | relit | error ×4) and
    ``out/eval_relight.json``."""
    import json

    from ..jsonio import to_jsonable
    from ..imageio import atomic_path
    from ..model import OpacityHullModel

    t0 = time.perf_counter()
    model = OpacityHullModel.open(model_path)
    if not isinstance(envmap, EnvironmentMap):
        raise InputError(f"eval relight: envmap {type(envmap).__name__}, expected an EnvironmentMap (load_envmap)")
    env = envmap
    require_light(env, "eval relight")
    kind, ref = find_scene(model)
    truth_fn = _truth_renderer(model, kind, ref, spp=spp)
    R = Relighter(model, config=config)
    idx = list(views) if views is not None else _pick(len(model.views), max_views)
    natural = _natural_eval(model, kind, ref)
    out = Path(out) if out is not None else model.root / "eval_relight"
    per_view, rows = [], []
    t_relight = t_truth = 0.0
    for n, i in enumerate(idx):
        ta = time.perf_counter()
        env_array = natural["array_env"](i, env) if natural is not None else env
        rgba = R.relight_view(i, envmap=env_array)
        part = natural["part"](i, env) if natural is not None else None
        if part is not None:
            rgba[..., :3] += part
        tb = time.perf_counter()
        truth, cover = truth_fn(i, env)
        truth_disp = None
        if natural is not None:
            truth_disp = natural["truth"](i, env) * cover[..., None]
            truth = truth + truth_disp
        tc = time.perf_counter()
        t_relight += tb - ta
        t_truth += tc - tb
        if truth.shape[:2] != rgba.shape[:2]:
            raise FormatError(f"view {model.views[i].id}: truth is {truth.shape[:2]}, relit view {rgba.shape[:2]}")
        # the object's interior by the truth's own coverage: the comparison measures
        # relighting, not the matte (edge pixels mix with the background)
        mask = cover >= MASK_ALPHA
        m = relight_metrics(rgba[..., :3], truth, mask)
        m.update({"view": model.views[i].id, "index": i})
        if truth_disp is not None:
            # the two halves apart: the field against the display-lit truth alone, and how
            # much of the truth comes from outside the fields' solid angles (light the
            # display field cannot carry; for a glass the light-array part is black)
            d = relight_metrics(part if part is not None else np.zeros_like(truth_disp), truth_disp, mask)
            n_all = float(np.linalg.norm(truth[mask])) if mask.any() else 0.0
            n_out = float(np.linalg.norm((truth - truth_disp)[mask])) if mask.any() else 0.0
            m["display_part"] = {"psnr": d["psnr"], "rel_err": d["rel_err"]}
            # the light array's half: the one-light images' sum against the truth outside the fields
            arr = rgba[..., :3] - (part if part is not None else 0.0)
            a = relight_metrics(arr, truth - truth_disp, mask)
            m["array_part"] = {"psnr": a["psnr"], "rel_err": a["rel_err"]}
            m["truth_outside_fields"] = n_out / n_all if n_all > 0 else float("nan")
        if i in R.pca_stats:
            m["pca"] = R.pca_stats[i]
        per_view.append(m)
        if write_images:
            write_exr(out / "views" / f"{model.views[i].id}_truth.exr", truth)
            write_exr(out / "views" / f"{model.views[i].id}_relit.exr", rgba)
            rows.append((truth, rgba, mask))
        if progress:
            progress(n + 1, len(idx))
    good = [p for p in per_view if p["pixels"] > 0]
    if not good:
        raise InputError(f"{model.root}: no view has pixels fully covered by the object (matte >= {MASK_ALPHA})")
    summary = {
        "model": str(model.root),
        "truth": "analytic quadrature"
        if kind == "analytic"
        else f"mitsuba render_under_envmap (scene {ref[0]}, spp {spp})",
        "envmap": env.stats(),
        "rel_err_mean": float(np.mean([p["rel_err"] for p in good])),
        "psnr_norm_mean": float(np.mean([p["psnr_norm"] for p in good])),
        "psnr_mean": float(np.mean([p["psnr"] for p in good])),
        "rel_err_max": float(np.max([p["rel_err"] for p in good])),
        "per_view": per_view,
        "n_lights_captured": len(R.lights),
        "natural": None
        if natural is None
        else dict(
            natural["info"],
            display_part_psnr_mean=float(np.mean([p["display_part"]["psnr"] for p in good])),
            display_part_rel_err_mean=float(np.mean([p["display_part"]["rel_err"] for p in good])),
            array_part_rel_err_mean=float(np.mean([p["array_part"]["rel_err"] for p in good])),
            truth_outside_fields_mean=float(np.mean([p["truth_outside_fields"] for p in good])),
        ),
        "config": {
            "kernel": R.config.kernel.kind,
            "width": R.config.kernel.width,
            "lower_hemisphere": R.config.kernel.lower_hemisphere,
            "near_light": R.near_light,
            "pca_rank": R.config.pca_rank,
        },
        "relight_s": t_relight,
        "truth_s": t_truth,
        "total_s": time.perf_counter() - t0,
    }
    n_lights = len(R.lights)
    if n_lights < FEW_LIGHTS:
        summary["warnings"] = [few_lights_warning(n_lights)]  # printed by the command and on the sheet
    if write_images:
        tiles, labels = [], []
        ref_img = rows[len(rows) // 2]
        exposure = auto_exposure(ref_img[0], ref_img[2].astype(np.float32))
        for (truth, rgba, mask), p in zip(rows, per_view, strict=True):
            err = np.abs(rgba[..., :3] - truth) * mask[..., None]
            tiles += [
                to_srgb8(truth, exposure=exposure),
                to_srgb8(rgba[..., :3], exposure=exposure),
                to_srgb8(err, exposure=4 * exposure),
            ]
            labels += [str(p["view"]), f"{p['psnr_norm']:.1f} dB (mean-norm.)", f"rel. err {100 * p['rel_err']:.1f}%"]
        write_sheet(
            out / "eval_relight.png",
            contact_sheet(
                tiles[: 3 * 24],
                columns=3,
                labels=labels[: 3 * 24],
                headers=["truth", "relit", "|relit - truth| x4"],
                min_width=160,
                notes=summary.get("warnings"),
            ),
        )
        summary["sheet"] = str(out / "eval_relight.png")
        with atomic_path(out / "eval_relight.json") as tmp:
            tmp.write_text(json.dumps(to_jsonable(summary), indent=2))
    return summary
