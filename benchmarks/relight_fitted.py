"""Relighting a fitted model (#29 item 4): do the one-light reflectance fields carried onto
the fitted splats relight novel views closer to Mitsuba than the hull does?

    .venv/bin/python benchmarks/relight_fitted.py MODEL_ULR MODEL_FITTED [--envmap builtin:uffizi] [--quick]

Both models are builds of one simulated session with ``--hold-out`` (the second with
``--optimize``; the same geometry, ``build --resume``). For every held-out view (never in
the hull, the blend or the fit) the view is relit three ways and compared with Mitsuba's
render under the map (``eval relight``'s truth and metrics, inside the truth's coverage):

* ``captured`` — the view's own one-light images weighted (``eval relight``'s figure; it
  needs no surfels, so it is the same for both models);
* ``ulr`` — the hull's surfels blended from the relit training views (``relight --view``
  of an unfitted model);
* ``fitted`` — the fitted splats, each with the ULR blend of the relit training views
  sampled where it projects, over the views that see its nearest hull surfel
  (:meth:`opacityhull.render.splats.FittedSplats.render_relit`, ``relight --view`` of a
  fitted model).

Reproduce (the session and models of the report)::

    # builtin:tiny with 8 table angles and 4 lights x 6 array steps (24 light samples)
    opacityhull capture --rig sim:builtin:diffuse --plan benchmarks/out/relight_fitted_plan.toml --out s
    opacityhull build s --out ml --ground-truth --hold-out every:4
    cp -r ml mlf && opacityhull build s --out mlf --ground-truth --hold-out every:4 \
        --optimize fast --optimize-iterations 300 --resume

Writes ``benchmarks/out/relight_fitted_<map>.json`` and ``.md``. Measured on a shared, loaded
machine: the seconds are indicative only; the errors do not depend on load.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser

OUT = out_dir()


def run(model_ulr: Path, model_fit: Path, *, envmap: str = "builtin:uffizi", spp: int = 32) -> dict:
    from opacityhull.evaluate.heldout import held_out_views
    from opacityhull.evaluate.metrics import relight_metrics
    from opacityhull.evaluate.relight import MASK_ALPHA, _truth_renderer, find_scene
    from opacityhull.model import OpacityHullModel
    from opacityhull.relight.envmap import load_envmap
    from opacityhull.relight.relit import Relighter
    from opacityhull.render import RenderConfig, prepare_views, render_image
    from opacityhull.render.renderer import model_surfels
    from opacityhull.render.splats import FittedSplats, fitted_state

    env = load_envmap(envmap)
    mu, mf = OpacityHullModel.open(model_ulr), OpacityHullModel.open(model_fit)
    assert fitted_state(mf.root) == "fitted", f"{model_fit}: no current fitted splats"
    test = held_out_views(mf)
    kind, ref = find_scene(mf)
    truth_fn = _truth_renderer(mf, kind, ref, spp=spp)
    rows = []
    for name, m in (("ulr", mu), ("fitted", mf)):
        R = Relighter(m)
        relit = [R.relight_view(i, envmap=env) for i in range(len(m.views))]
        cams = [v.camera for v in m.views]
        surfels = model_surfels(m)
        pv = prepare_views(cams, relit)
        fs = FittedSplats.load(m.root) if name == "fitted" else None
        for i in test:
            truth, cover = truth_fn(i, env)
            mask = cover >= MASK_ALPHA
            t = time.perf_counter()
            if fs is None:
                got = {
                    "captured": relit[i],
                    "ulr": render_image(surfels, cams, pv, cams[i], config=RenderConfig()).premul,
                }
            else:
                got = {"fitted": fs.render_relit(cams[i], surfels, cams, relit).premul}
            ms = 1e3 * (time.perf_counter() - t)
            for how, img in got.items():
                r = relight_metrics(img[..., :3], truth, mask)
                rows.append({"model": name, "how": how, "view": m.views[i].id, "ms": ms, **r})
    summary = {"envmap": envmap, "views": [mf.views[i].id for i in test], "spp": spp}
    for how in ("captured", "ulr", "fitted"):
        sel = [r for r in rows if r["how"] == how and r["pixels"] > 0]
        summary[how] = {
            "rel_err_mean": float(np.mean([r["rel_err"] for r in sel])),
            "psnr_norm_mean": float(np.mean([r["psnr_norm"] for r in sel])),
            "psnr_mean": float(np.mean([r["psnr"] for r in sel])),
        }
    summary["per_view"] = rows
    return summary


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("model_ulr", type=Path)
    ap.add_argument("model_fitted", type=Path)
    ap.add_argument("--envmap", default="builtin:uffizi")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--quick", action="store_true", help="8 spp truth, outputs under benchmarks/out/quick/")
    a = ap.parse_args()
    s = run(a.model_ulr, a.model_fitted, envmap=a.envmap, spp=8 if a.quick else a.spp)
    OUT.mkdir(parents=True, exist_ok=True)
    stem = "relight_fitted_" + a.envmap.split(":")[-1].split("/")[-1].split(".")[0]
    (OUT / f"{stem}.json").write_text(json.dumps(s, indent=1))
    lines = [
        "# Relighting held-out views: the hull by ULR against the fitted splats",
        "",
        f"{a.model_ulr} / {a.model_fitted}, {a.envmap}, held-out views {', '.join(s['views'])}; "
        "Mitsuba truth, inside its coverage (eval relight's metrics).",
        "",
        "| relit | rel. error | PSNR (mean-normalised) | PSNR |",
        "|---|---:|---:|---:|",
    ]
    for how in ("captured", "ulr", "fitted"):
        r = s[how]
        lines.append(f"| {how} | {r['rel_err_mean']:.3f} | {r['psnr_norm_mean']:.2f} dB | {r['psnr_mean']:.2f} dB |")
    (OUT / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
