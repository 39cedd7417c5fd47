"""Fitting benchmark: test PSNR of the optimized opacity hull against iterations and
seconds, per set and appearance mode (issue 29, item 7).

    .venv/bin/python benchmarks/optimize.py [--quick] [--json] [--sets temple,dino]
        [--model NAME=DIR ...] [--iterations N] [--train-scale S]
        [--modes hull,ulr,sh+ulr] [--residual-steps N] [--stem NAME]

Sets: the Middlebury rings (``tests/data/real/templeSR``, ``dinoSR``; imported and
built with the defaults unless ``--model temple=DIR`` names a built model), every 4th
view held out; ``--model demo=DIR`` (e.g. ``out/demo/model``) every 8th; ``--model
tiny=DIR`` (the README's ``capture --plan builtin:tiny`` session, built) every 4th. A held-out
view's coincident twins are held out with it. The held-out views are in nothing the fit
sees: the hull, surfels and visibility are rebuilt without them
(:func:`opacityhull.evaluate.holdout.geometry_without`, what ``eval loo --holdout
geometry`` runs), the start colour and the fit use the other views only.

Appearance modes, scored on the held-out views with ``eval loo``'s metric
(:func:`opacityhull.evaluate.loo.loo_metrics`: PSNR over the union of the masks,
colour over black, sRGB; the photograph's own mask where the build filled shadow
holes):

* ``hull`` — today's model: the rebuilt hull rendered by ULR blending of the training
  views (the default render);
* ``sh`` — the fitted surfels with their SH colour, rendered by the rasterizer;
* ``ulr`` — the fitted geometry (positions, normals, sizes; surfels of opacity < ½
  dropped; visibility recomputed by the z-buffer test) shaded by today's ULR of the
  captured training views: the opacity light field on optimized geometry.
* ``sh+ulr`` — SH plus a ULR residual: the fitted geometry of ``sh`` (frozen), every
  surfel shaded by the per-surfel ULR blend of the training views (a training view
  itself and its coincident twins excluded from its own blend, so that fitting and test
  see the same kind of colour), plus per-surfel SH coefficients fitted for
  ``--residual-steps`` steps as the signed residual photograph − ULR
  (``colour = max(ULR + Σ c_j Y_j, 0)``: :func:`opacityhull.optimize.appearance.sh_colors`
  with ``base``), rendered by the rasterizer. ``ulr-r`` is its start (residual 0): the
  same per-surfel ULR through the rasterizer, with the fitted opacities and shapes.

Writes ``benchmarks/out/optimize.md``, ``.json`` and ``.png`` (``optimize_quick.*``
with ``--quick``: fewer steps at half resolution, untracked). Figures taken while other
work shares the two cores are slow by that load.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, print_result, pyplot, report_head, save_figure

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "real"
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
EVERY = {"temple": 4, "dino": 4, "demo": 8, "tiny": 4}
GOALS = {"temple": 20.0, "dino": 19.0, "demo": 30.0}


def build_real(name: str, tmp: Path) -> Path:
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    src = DATA / f"{name}SR"
    session, model = tmp / f"{name}_session", tmp / f"{name}_model"
    import_colmap(src / "sparse", src / "images", session, masks_dir=src / "masks")
    build_model(session, model, config=BuildConfig(pictures=False))
    return model


def work_model(model_dir: Path, surfels, tmp: Path, name: str) -> Path:
    """A model folder sharing the model's views and cameras, with ``surfels`` (the hull
    rebuilt without the held-out views) as its surfels."""
    from opacityhull.model import write_surfels_ply

    out = tmp / f"{name}_heldout_model"
    out.mkdir(parents=True, exist_ok=True)
    for sub in ("views", "cameras"):
        if not (out / sub).exists():
            (out / sub).symlink_to((model_dir / sub).resolve())
    for f in ("model.toml", "report.json"):
        if (model_dir / f).is_file():
            (out / f).write_bytes((model_dir / f).read_bytes())
    write_surfels_ply(out / "surfels.ply", surfels)
    return out


def score(model, test: list[int], render) -> dict:
    """Mean ``loo_metrics`` over the test views of ``render(i) -> straight RGBA``."""
    from opacityhull.model import BUILD_DIR, FILLED_HOLES, read_hole_masks
    from opacityhull.evaluate.loo import _photograph, loo_metrics

    filled = read_hole_masks(Path(model.root) / BUILD_DIR / FILLED_HOLES)
    ms, rows = [], []
    for i in test:
        t0 = time.perf_counter()
        rgba = render(i)
        ms.append(1e3 * (time.perf_counter() - t0))
        photo, _, _ = _photograph(model, i, filled, rgba)
        rows.append(loo_metrics(photo, rgba))
    return {
        "psnr": float(np.mean([r["psnr"] for r in rows])),
        "ssim": float(np.mean([r["ssim"] for r in rows])),
        "coverage_iou": float(np.mean([r["coverage_iou"] for r in rows])),
        "render_ms": float(np.mean(ms)),
        "psnr_views": [float(r["psnr"]) for r in rows],
    }


def ulr_surfels(params: dict, cameras, held: list[int]):
    """The fitted geometry as ULR surfels: opaque ones only, radius from the larger
    tangent std-dev (the renderer's σ = ½ r), visibility by the z-buffer test."""
    from opacityhull.model import Surfels
    from opacityhull.optimize.surfelparams import normals_of, sigmoid
    from opacityhull.reconstruct.visibility import surfel_visibility

    keep = sigmoid(params["opacity_logits"]) >= 0.5
    pos = params["means"][keep].astype(np.float64)
    nrm = normals_of(params["quats"][keep]).astype(np.float64)
    rad = np.exp(params["log_scales"][keep].astype(np.float64)).max(axis=1) / 0.5
    # the tolerance of the build's test (the largest radius) would be a pruned outlier's here
    vis = np.asarray(surfel_visibility(pos, nrm, rad, cameras, depth_tol_m=float(np.percentile(rad, 99))), bool)
    vis[:, held] = False
    return Surfels.from_bool(pos, nrm, rad, vis)


def surfel_ulr_display(surf, pv, centre, exclude, *, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Per-surfel ULR colour seen from ``centre``: (N, 3) float32 display (sRGB) colour of
    the k-view blend (premultiplied, then divided by the blended α, as the renderer's
    per-surfel shading), and (N,) bool where some allowed view saw the surfel."""
    from opacityhull.imageio import srgb_encode
    from opacityhull.render import kernels as K
    from opacityhull.render.renderer import _allowed

    N = len(surf)
    allowed = _allowed(pv.n_views, sorted(set(int(v) for v in exclude)))
    out = np.zeros((N, 4), np.float32)
    ok = np.zeros(N, np.bool_)
    order, s_lb = np.arange(pv.n_views, dtype=np.int64), np.zeros(pv.n_views)
    C = np.asarray(centre, np.float64).reshape(3)
    K.parallel_for(
        K.ulr_shade,
        N,
        (
            K.UlrHead(surf.positions, surf.visibility, np.ones(N, np.bool_), allowed, C, pv.centres, pv.cams, pv.sizes),
            pv.offsets,
            pv.texels,
            order,
            s_lb,
            pv.tie_rank,
            int(k),
            out,
            0,
            ok,
        ),
        threads=1,
    )
    a = out[:, 3:4]
    straight = np.where(a > 1e-4, out[:, :3] / np.maximum(a, 1e-4), 0.0)
    return srgb_encode(np.clip(straight, 0.0, 1.0)).astype(np.float32), ok & (a[:, 0] > 1e-4)


def render_colored(params: dict, colors: np.ndarray, camera) -> np.ndarray:
    """:func:`opacityhull.optimize.fit.render_params` with given (N, 3) display colours."""
    from opacityhull.imageio import srgb_decode
    from opacityhull.optimize.fit import _raster_camera, _splat_params
    from opacityhull.optimize.raster import RasterConfig, rasterize

    out = rasterize(_splat_params(params, colors), _raster_camera(camera), config=RasterConfig())
    a = np.clip(out.alpha, 0.0, 1.0).astype(np.float32)
    premul = srgb_decode(np.clip(out.image, 0.0, 1.0))
    straight = np.where(a[..., None] > 1e-6, premul / np.maximum(a[..., None], 1e-6), 0.0)
    return np.concatenate([straight, a[..., None]], axis=2).astype(np.float32)


def residual_fit(params: dict, data, base: list[np.ndarray], cfg, *, steps: int, observe):
    """Fit per-surfel SH coefficients (degree ``cfg.sh_degree``, zero start) as the
    residual over the per-surfel ULR colours ``base[j]`` of ``data.views[j]``, the
    geometry frozen. Same loss, Adam,
    rates and screen filter as the fit. Returns (coefficients (N, B, 3), ms per step)."""
    from opacityhull.optimize.adam import Adam
    from opacityhull.optimize.fit import _raster_camera, view_gradient, view_order
    from opacityhull.optimize.raster import RasterConfig

    rc = RasterConfig(lowpass_px2=RasterConfig().lowpass_px2 * cfg.train_scale**2)
    deg = int(cfg.sh_degree)
    B = (deg + 1) ** 2
    res = np.zeros((len(params["means"]), B, 3), np.float32)
    adam = Adam({"sh": res})
    lr = np.full((B, 1), cfg.lr_sh_rest, np.float32)
    lr[0] = cfg.lr_sh_dc
    order = view_order(len(data.views), steps, cfg.seed + 1)
    cams = [_raster_camera(v.camera) for v in data.views]
    ms = []
    observe(0, res)
    for it in range(steps):
        t0 = time.perf_counter()
        j = int(order[it])
        view = data.views[j]
        vg = view_gradient(
            params,
            res,
            cams[j],
            view.camera.centre_world,
            view.target,
            view.alpha,
            degree=deg,
            raster_config=rc,
            ssim_weight=cfg.ssim_weight,
            alpha_weight=cfg.alpha_weight,
            color_loss=cfg.color_loss,
            base=base[j],
        )
        adam.step({"sh": res}, {"sh": vg.sh}, {"sh": lr})
        ms.append(1e3 * (time.perf_counter() - t0))
        if (it + 1) % max(1, steps // 3) == 0 or it + 1 == steps:
            observe(it + 1, res)
    return res, float(np.mean(ms)) if ms else float("nan")


def fitted_surfels(params: dict, cameras, held: list[int]):
    """Every fitted surfel as ULR surfels (the ``ulr`` mode's :func:`ulr_surfels` without
    its opacity cut: the residual needs a base colour under each surfel the rasterizer
    draws); the z-buffer sees them all."""
    from opacityhull.model import Surfels
    from opacityhull.optimize.surfelparams import normals_of
    from opacityhull.reconstruct.visibility import surfel_visibility

    pos = params["means"].astype(np.float64)
    nrm = normals_of(params["quats"]).astype(np.float64)
    rad = np.exp(params["log_scales"].astype(np.float64)).max(axis=1) / 0.5
    vis = np.asarray(surfel_visibility(pos, nrm, rad, cameras, depth_tol_m=float(np.percentile(rad, 99))), bool)
    vis[:, held] = False
    return Surfels.from_bool(pos, nrm, rad, vis)


def run_residual(name, wm, params, data, cfg, cams, pv, test, held, train, *, steps: int) -> dict:
    """The ``ulr-r`` and ``sh+ulr`` modes on the fitted ``params`` (see the module docstring)."""
    from opacityhull.evaluate.loo import held_out_groups
    from opacityhull.optimize.appearance import sh_colors, view_dirs

    t0 = time.perf_counter()
    fs = fitted_surfels(params, cams, held)
    twins = held_out_groups(wm, train)
    dc, _, _ = sh_colors(params["sh"], view_dirs(params["means"], np.zeros(3)), degree=0)  # the fit's own DC colour

    def with_fallback(col, ok):
        return np.where(ok[:, None], col, dc).astype(np.float32)

    base_train, drawn = [], []
    for v in data.views:
        col, ok = surfel_ulr_display(fs, pv, cams[v.index].centre_world, set(held) | set(twins[v.index]))
        base_train.append(with_fallback(col, ok))
        drawn.append(float(ok.mean()))
    base_test = {}
    for i in test:
        col, ok = surfel_ulr_display(fs, pv, cams[i].centre_world, held)
        base_test[i] = with_fallback(col, ok)
    prep_s = time.perf_counter() - t0
    deg = int(cfg.sh_degree)
    out: dict = {"curve": []}

    def observe(it, res):
        def render(i):
            col, _, _ = sh_colors(res, view_dirs(params["means"], cams[i].centre_world), degree=deg, base=base_test[i])
            return render_colored(params, col, cams[i])

        sc = score(wm, test, render)
        out["curve"].append({"iteration": it, **sc})
        print(f"{name}: sh+ulr residual step {it} test {sc['psnr']:.2f} dB", file=sys.stderr)

    t1 = time.perf_counter()
    _, ms = residual_fit(params, data, base_train, cfg, steps=steps, observe=observe)
    return {
        "ulr-r": {**out["curve"][0], "surfels": len(fs)},
        "sh+ulr": {**out["curve"][-1], "surfels": len(fs), "residual_steps": steps, "residual_ms_per_step": ms},
        "residual_curve": out["curve"],
        "residual_prep_s": round(prep_s, 1),
        "residual_wall_s": round(time.perf_counter() - t1, 1),
        "ulr_drawn_fraction_train": float(np.mean(drawn)),
    }


def run_set(
    name: str, model_dir: Path, tmp: Path, cfg, *, observe_every: int, modes: list[str], residual_steps: int = 300
) -> dict:
    from opacityhull.model import OpacityHullModel
    from opacityhull.optimize.data import load_fit_data
    from opacityhull.optimize.fit import fit_params, render_params
    from opacityhull.optimize.surfelparams import start_params, thin_start
    from opacityhull.evaluate.holdout import geometry_without
    from opacityhull.evaluate.loo import held_out_groups
    from opacityhull.render.renderer import RenderConfig, prepare_model_views, render_image

    model = OpacityHullModel.open(model_dir)
    V = len(model.views)
    test = list(range(0, V, EVERY[name]))
    groups = held_out_groups(model, test)
    held = sorted({j for g in groups.values() for j in g})
    train = [i for i in range(V) if i not in held]
    t0 = time.perf_counter()
    surf = geometry_without(model)(tuple(held))
    rebuild_s = time.perf_counter() - t0
    work = work_model(Path(model_dir), surf, tmp, name)
    wm = OpacityHullModel.open(work)
    cams = [v.camera for v in wm.views]
    res: dict = {"set": name, "views": V, "test": test, "held": held, "train": len(train), "surfels_hull": len(surf)}
    res["rebuild_s"] = round(rebuild_s, 1)
    pv = prepare_model_views(wm)
    rc = RenderConfig()
    if "hull" in modes:
        res["hull"] = score(
            wm, test, lambda i: render_image(surf, cams, pv, cams[i], config=rc, exclude_views=held).rgba
        )
        print(f"{name}: hull (today's model) {res['hull']['psnr']:.2f} dB", file=sys.stderr)
    t0 = time.perf_counter()
    data = load_fit_data(work, train, train_scale=cfg.train_scale, start_surface=cfg.start_surface)
    res["load_s"] = round(time.perf_counter() - t0, 1)
    keep, grow = thin_start(len(surf), cfg.max_start_surfels, seed=cfg.seed)
    pos = surf.shading_positions() if cfg.start_surface == "refined" else surf.positions
    p0 = start_params(pos[keep], surf.normals[keep], surf.radii[keep] * grow, data.sh_dc[keep], sh_degree=0)
    res["start"] = score(wm, test, lambda i: render_params(p0, cams[i]))
    print(f"{name}: start (hull surfels, blended colour) {res['start']['psnr']:.2f} dB", file=sys.stderr)
    curve = [{"iteration": 0, "seconds": 0.0, **res["start"]}]
    clock = {"start": 0.0, "scoring": 0.0}

    def observe(it, params):
        t_obs = time.perf_counter()
        secs = t_obs - clock["start"] - clock["scoring"]  # the steps' time, scoring excluded
        sc = score(wm, test, lambda i: render_params(params, cams[i]))
        curve.append({"iteration": it, "seconds": secs, "n_surfels": len(params["means"]), **sc})
        print(f"{name}: step {it} test {sc['psnr']:.2f} dB ({secs:.0f} s of steps)", file=sys.stderr)
        clock["scoring"] += time.perf_counter() - t_obs

    clock["start"] = t0 = time.perf_counter()
    params, rep = fit_params(data, cfg, observe=observe, observe_every=observe_every)
    res["fit_wall_s"] = round(time.perf_counter() - t0, 1)
    t = rep.timings()
    res["fit"] = {**rep.summary(), "seconds": t["seconds"], "ms_per_iteration": t["ms_per_iteration"]}
    res["fit"]["step_s"] = round(float(np.sum(rep.step_ms)) / 1e3, 1)
    res["sh"] = curve[-1]
    res["curve"] = curve
    res["densify"] = rep.densify
    sheet_modes = {"photograph": None, "sh": lambda i: render_params(params, cams[i])}
    if "hull" in modes:
        sheet_modes["hull"] = lambda i: render_image(surf, cams, pv, cams[i], config=rc, exclude_views=held).rgba
    res["sheet_views"] = test[:2]
    res["_sheet"] = {k: [f(i) if f else wm.load_view_rgba(i) for i in test[:2]] for k, f in sheet_modes.items()}
    if "ulr" in modes:
        us = ulr_surfels(params, cams, held)
        res["ulr"] = {
            **score(wm, test, lambda i: render_image(us, cams, pv, cams[i], config=rc, exclude_views=held).rgba),
            "surfels": len(us),
        }
        print(f"{name}: ulr on fitted geometry {res['ulr']['psnr']:.2f} dB", file=sys.stderr)
    if "sh+ulr" in modes:
        res.update(run_residual(name, wm, params, data, cfg, cams, pv, test, held, train, steps=residual_steps))
    return res


MODES = ("hull", "start", "sh", "ulr", "ulr-r", "sh+ulr")


def table(rows: list[dict]) -> str:
    out = [
        "| set | mode | test PSNR (dB) | SSIM | coverage IoU | steps | fit s (steps) | ms / step | surfels | goal |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        fit = r["fit"]
        for mode in MODES:
            if mode not in r:
                continue
            m = r[mode]
            fitted = mode not in ("hull", "start")
            steps = fit["iterations"] if fitted else 0
            secs = fit["step_s"] if fitted else 0
            ms = fit["ms_per_iteration"] if fitted else float("nan")
            if mode == "sh+ulr":
                steps += m["residual_steps"]
                secs += m["residual_steps"] * m["residual_ms_per_step"] / 1e3
                ms = m["residual_ms_per_step"]
            n = m.get("surfels", m.get("n_surfels", r["surfels_hull"] if mode == "hull" else fit["n_surfels_start"]))
            out.append(
                f"| {r['set']} | {mode} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m['coverage_iou']:.3f} | {steps} | "
                f"{secs:.0f} | {ms:.0f} | {n} | {GOALS.get(r['set'], float('nan')):.1f} |"
            )
    return "\n".join(out)


def paired(rows: list[dict], a: str = "sh", b: str = "sh+ulr") -> list[str]:
    """Per held-out view PSNR of ``b`` − ``a``: mean and the spread (sample std-dev) over views."""
    out = []
    for r in rows:
        if a in r and b in r:
            d = np.subtract(r[b]["psnr_views"], r[a]["psnr_views"])
            sd = float(np.std(d, ddof=1)) if d.size > 1 else float("nan")
            out.append(
                f"- {r['set']}: {b} − {a} per held-out view "
                + ", ".join(f"{x:+.2f}" for x in d)
                + f" dB; mean {d.mean():+.2f}, spread (std over views) {sd:.2f} dB"
            )
    return out


def write_sheets(rows: list[dict], path: Path) -> None:
    """Photograph | hull | sh of the first two held-out views of every set."""
    from opacityhull.pictures import contact_sheet, write_sheet
    from opacityhull.evaluate.loo import _display

    tiles, labels, headers = [], [], []
    for r in rows:
        sheet = r.pop("_sheet")
        headers = list(sheet)
        for j, v in enumerate(r["sheet_views"]):
            for k in sheet:
                tiles.append((np.clip(_display(sheet[k][j]), 0, 1) * 255).round().astype(np.uint8))
                labels.append(f"{r['set']} view {v} {k}")
    write_sheet(path, contact_sheet(tiles, columns=len(headers), labels=labels, headers=headers, max_width=1800))


def plot(rows: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for r in rows:
        c = r["curve"]
        it = [p["iteration"] for p in c]
        s = [p["seconds"] for p in c]
        ps = [p["psnr"] for p in c]
        (line,) = ax[0].plot(it, ps, "o-", label=f"{r['set']} sh")
        ax[1].plot(s, ps, "o-", color=line.get_color(), label=f"{r['set']} sh")
        for mode, mk in (("hull", "--"), ("ulr", ":"), ("sh+ulr", "-.")):
            if mode in r:
                for a in ax:
                    a.axhline(r[mode]["psnr"], ls=mk, color=line.get_color(), lw=1, label=f"{r['set']} {mode}")
    ax[0].set_xlabel("fitting steps")
    ax[1].set_xlabel("seconds of fitting steps (shared 2-core machine)")
    for a in ax:
        a.set_ylabel("held-out PSNR, mask union (dB)")
        a.grid(alpha=0.3)
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main(argv=None) -> int:
    from opacityhull.optimize.config import fit_preset

    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer steps, half resolution (untracked files)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--sets", default="temple,dino", help="comma list of temple, dino (imported and built)")
    ap.add_argument("--model", action="append", default=[], help="NAME=DIR: a built model (temple, dino, demo)")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--train-scale", type=float, default=None)
    ap.add_argument("--modes", default="hull,ulr,sh+ulr", help="besides sh: hull, ulr, sh+ulr")
    ap.add_argument("--residual-steps", type=int, default=300, help="sh+ulr: steps of the residual SH fit")
    ap.add_argument("--stem", default=None, help="output file stem (default optimize, optimize_quick)")
    ap.add_argument("--observe-every", type=int, default=None)
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE: a FitConfig field (JSON value)")
    a = ap.parse_args(argv)
    mode = "fast"
    cfg = fit_preset(mode, checkpoint_every=0)
    if a.quick:
        cfg = replace(
            cfg,
            iterations=200,
            train_scale=0.5,
            densify_from=50,
            densify_until=150,
            densify_every=50,
            sh_degree_every=60,
            max_start_surfels=100_000,
        )
    if a.iterations:
        cfg = replace(cfg, iterations=a.iterations)
    if a.train_scale:
        cfg = replace(cfg, train_scale=a.train_scale)
    for kv in a.set:
        k, _, v = kv.partition("=")
        cfg = replace(cfg, **{k: json.loads(v) if v[:1] in "0123456789-[{tfn" else v})
    every = a.observe_every or max(1, cfg.iterations // 4)
    models = dict(s.split("=", 1) for s in a.model)
    names = [s for s in a.sets.split(",") if s] + [n for n in models if n not in a.sets.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="optimize_") as td:
        tmp = Path(td)
        for name in names:
            if name not in EVERY:
                print(f"unknown set {name!r}: expected one of {', '.join(EVERY)}", file=sys.stderr)
                return 2
            md = Path(models[name]) if name in models else build_real(name, tmp)
            rows.append(
                run_set(
                    name,
                    md,
                    tmp,
                    cfg,
                    observe_every=every,
                    modes=a.modes.split(","),
                    residual_steps=a.residual_steps,
                )
            )
    OUT.mkdir(parents=True, exist_ok=True)
    stem = a.stem or ("optimize_quick" if a.quick else "optimize")
    md = report_head(
        "Optimized opacity hull: held-out PSNR against fitting steps and time",
        f"`benchmarks/optimize.py {' '.join(sys.argv[1:] if argv is None else argv)}`: every 4th view held out "
        "(demo every 8th), "
        "with its coincident twins, out of the hull, the start colour and the fit. PSNR/SSIM over the union of "
        "the photograph's mask and the rendered coverage, colour over black, sRGB (`eval loo`'s metric). "
        "`hull` is today's model (hull rebuilt without the held-out views, ULR of the training views), `start` "
        "the fit's start (hull surfels, blended colour, the rasterizer), `sh` the fitted surfels with SH colour, "
        "`ulr` the fitted geometry shaded by ULR (today's renderer), `ulr-r` the per-surfel ULR of the training "
        "views on the fitted surfels through the rasterizer, `sh+ulr` that plus a fitted SH residual (the fitted "
        "geometry of `sh` frozen; the module docstring). Times are wall seconds of the fitting steps alone on a 2-core "
        "machine shared with other work (slow by that load).",
        "Fit options: " + json.dumps({k: v for k, v in asdict(cfg).items()}),
    )
    md += [table(rows), "", *paired(rows), ""]
    for r in rows:
        md.append(
            f"- {r['set']}: "
            + ", ".join(f"step {p['iteration']} {p['psnr']:.2f} dB ({p['seconds']:.0f} s)" for p in r["curve"])
        )
    md.append("")
    write_sheets(rows, OUT / f"{stem}_views.png")
    path = OUT / f"{stem}.md"
    path.write_text("\n".join(md))
    (OUT / f"{stem}.json").write_text(json.dumps({"config": asdict(cfg), "rows": rows}, indent=1, default=float))
    plot(rows, OUT / f"{stem}.png")
    print_result({"rows": rows, "table": str(path)}, path, as_json=a.json)
    return 0 if all(math.isfinite(r["sh"]["psnr"]) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
