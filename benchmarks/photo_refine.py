"""Photo-consistent surfel refinement on real photographs (Middlebury templeSR / dinoSR).

For each data set: ``opacityhull import colmap`` → ``opacityhull build --hull-res R`` →
leave-one-out (every 2nd view) of the hull model, then of the refined surfels
(:func:`opacityhull.reconstruct.photo.refine_surfels`, visibility recomputed with
:func:`opacityhull.reconstruct.visibility.surfel_visibility`).

Hold-out protocols:

* ``blend`` — the refinement is run once with every view, written as a model copy
  (``MODEL-photo``: ``surfels.ply`` replaced, views shared) and scored by the real CLI,
  ``opacityhull eval loo MODEL --views every:2 --json`` (the held-out view is excluded from
  blending only; the geometry saw it).
* ``photo`` (default, more honest) — for each held-out view the refinement is re-run with
  ``exclude_views=[i]`` (the held-out photograph never enters the photo-consistency cost),
  and that view is rendered in-process with the same renderer call as ``eval loo``
  (``render_image(..., exclude_views=[i])``) and scored with the same ``loo_metrics``. The
  hull itself (silhouettes) still includes the held-out view.

Usage::

    .venv/bin/python benchmarks/photo_refine.py --hull-res 384 [--sets templeSR,dinoSR]

Writes ``benchmarks/out/photo_refine.md`` and ``.png``; scratch models under
``/tmp/helper-photo/bench``. Timings on a shared 2-core machine are contended.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser

ROOT = Path(__file__).resolve().parents[1]
DATA = Path("/work/shared/data/real")
OPH = str(ROOT / ".venv" / "bin" / "opacityhull")
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)


def run(cmd, **kw):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, **kw)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return r.stdout


def build(name, scratch, hull_res):
    d = DATA / name
    sess = scratch / f"{name}-sess"
    model = scratch / f"{name}-{hull_res}"
    if not (sess / "session.toml").is_file():
        run(
            [
                OPH,
                "import",
                "colmap",
                "--model",
                str(d / "sparse"),
                "--images",
                str(d / "images"),
                "--masks",
                str(d / "masks"),
                "--out",
                str(sess),
            ]
        )
    if not (model / "model.toml").is_file():
        run([OPH, "build", str(sess), "--out", str(model), "--hull-res", str(hull_res), "--no-pictures", "--json"])
    return model


def cli_loo(model, out):
    t0 = time.perf_counter()
    s = json.loads(run([OPH, "eval", "loo", str(model), "--views", "every:2", "--out", str(out), "--json"]))
    return s, time.perf_counter() - t0


def load(model_path):
    from opacityhull.model import OpacityHullModel

    m = OpacityHullModel.open(model_path)
    cams = [v.camera for v in m.views]
    rgba = [m.load_view_rgba(i) for i in range(len(m.views))]
    return m, cams, rgba


def refine(m, cams, rgba, config, exclude=()):
    from opacityhull.model import Surfels
    from opacityhull.reconstruct.photo import refine_surfels
    from opacityhull.reconstruct.visibility import surfel_visibility

    s = m.surfels
    t0 = time.perf_counter()
    pos, nrm, rad, stats = refine_surfels(
        s.positions,
        s.normals,
        s.radii,
        s.visible_bool(),
        cams,
        [a[..., :3] for a in rgba],
        [a[..., 3] for a in rgba],
        config=config,
        exclude_views=exclude,
    )
    t_ref = time.perf_counter() - t0
    vis = surfel_visibility(pos, nrm, rad, cams)
    t_vis = time.perf_counter() - t0 - t_ref
    return Surfels.from_bool(pos, nrm, rad, vis), stats, t_ref, t_vis


def write_copy(model, surfels, dst):
    from opacityhull.model import write_surfels_ply

    dst = Path(dst)
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    shutil.copytree(model / "cameras", dst / "cameras")
    os.symlink(model / "views", dst / "views")
    write_surfels_ply(dst / "surfels.ply", surfels)
    shutil.copy(model / "model.toml", dst / "model.toml")  # last: a complete model
    return dst


def photo_holdout_loo(m, cams, rgba, config, views):
    """Refinement re-run without each held-out view; render + score in-process."""
    from opacityhull.evaluate.loo import loo_metrics
    from opacityhull.render.renderer import RenderConfig, prepare_model_views, render_image, spatially_sorted

    pv = prepare_model_views(m)
    per, t_ref = [], []
    for i in views:
        sf, stats, tr, _ = refine(m, cams, rgba, config, exclude=[i])
        t_ref.append(tr)
        res = render_image(spatially_sorted(sf), cams, pv, cams[i], config=RenderConfig(), exclude_views=[i])
        per.append(loo_metrics(rgba[i], res.rgba))
    return (
        {
            "psnr_mean": float(np.mean([p["psnr"] for p in per])),
            "ssim_mean": float(np.mean([p["ssim"] for p in per])),
            "per_view": per,
        },
        float(np.mean(t_ref)),
    )


def main(argv=None):
    ap = parser(__doc__)
    ap.add_argument("--hull-res", type=int, default=256)
    ap.add_argument("--sets", default="templeSR,dinoSR")
    ap.add_argument("--scratch", default="/tmp/helper-photo/bench")
    ap.add_argument("--protocol", choices=["photo", "blend", "both"], default="both")
    ap.add_argument("--variants", default="default", help="comma list: default,pca,nosmooth,rgbwide")
    ap.add_argument("--no-write", action="store_true", help="do not write benchmarks/out")
    args = ap.parse_args(argv)

    from opacityhull.reconstruct.photo import PhotoConfig

    variants = {
        "default": PhotoConfig(),
        "deep": PhotoConfig(d_max_px=40.0),
        "nokeep": PhotoConfig(keep_coverage=False),
        "nosmooth": PhotoConfig(smooth_iters=0),
        "pca": PhotoConfig(normals="pca"),
    }
    scratch = Path(args.scratch)
    scratch.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.sets.split(","):
        model = build(name, scratch, args.hull_res)
        base, t_base = cli_loo(model, scratch / f"{name}-{args.hull_res}-loo")
        m, cams, rgba = load(model)
        views = [int(p["index"]) for p in base["per_view"]]
        rows.append(_row(name, "hull", "-", base, 0.0, moved=0.0, n=len(m.surfels)))
        print(f"{name}: hull  PSNR {base['psnr_mean']:.2f}  SSIM {base['ssim_mean']:.3f}", file=sys.stderr)
        for vname in args.variants.split(","):
            cfg = variants[vname]
            if args.protocol in ("blend", "both"):
                sf, stats, tr, tv = refine(m, cams, rgba, cfg)
                dst = write_copy(model, sf, scratch / f"{name}-{args.hull_res}-{vname}")
                s, _ = cli_loo(dst, dst / "loo")
                rows.append(
                    _row(
                        name,
                        vname,
                        "blend",
                        s,
                        tr,
                        moved=stats["n_moved"] / max(stats["n_surfels"], 1),
                        n=len(sf),
                        conf=stats["n_confident"] / max(stats["n_surfels"], 1),
                        depth_mm=1e3 * stats["mean_depth_moved_m"],
                        vis_s=tv,
                        cost_volume_s=stats["seconds_cost_volume"],
                    )
                )
                print(
                    f"{name}: {vname} blend PSNR {s['psnr_mean']:.2f} SSIM {s['ssim_mean']:.3f} refine {tr:.1f}s "
                    f"moved {rows[-1]['moved']:.2f} conf {rows[-1]['conf']:.2f} depth {rows[-1]['depth_mm']:.2f} mm",
                    file=sys.stderr,
                )
            if args.protocol in ("photo", "both"):
                s, tr = photo_holdout_loo(m, cams, rgba, cfg, views)
                rows.append(_row(name, vname, "photo", s, tr, moved=float("nan"), n=len(m.surfels)))
                print(f"{name}: {vname} photo PSNR {s['psnr_mean']:.2f} SSIM {s['ssim_mean']:.3f}", file=sys.stderr)
    print(json.dumps(rows, indent=1))
    if not args.no_write:
        write_outputs(rows, args)


def _row(name: str, variant: str, protocol: str, loo: dict, refine_s: float, **extra) -> dict:
    """One result row: the set, variant and protocol, the PSNR/SSIM means of the leave-one-out
    summary ``loo``, the refinement seconds, then ``extra`` (moved, n, and the blend's statistics)."""
    return dict(
        set=name,
        variant=variant,
        protocol=protocol,
        psnr=loo["psnr_mean"],
        ssim=loo["ssim_mean"],
        refine_s=refine_s,
        **extra,
    )


def write_outputs(rows, args):
    """Store this run's rows in ``photo_refine.json`` (one entry per command line) and
    regenerate ``photo_refine.md`` / ``.png`` from every stored run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    OUT.mkdir(parents=True, exist_ok=True)
    cmd = (
        f".venv/bin/python benchmarks/photo_refine.py --hull-res {args.hull_res} --sets {args.sets} "
        f"--protocol {args.protocol} --variants {args.variants}"
    )
    store = OUT / "photo_refine.json"
    runs = json.loads(store.read_text()) if store.is_file() else {}
    runs[cmd] = {"hull_res": args.hull_res, "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "rows": rows}
    store.write_text(json.dumps(runs, indent=1))
    lines = [
        "# Photo-consistent surfel refinement (benchmarks/photo_refine.py)",
        "",
        "LOO over every 2nd view (8 of 16) of Middlebury templeSR / dinoSR, PSNR/SSIM in sRGB over black "
        "inside the union of masks (the `eval loo` metrics, default `RenderConfig` of the day). "
        "`hull`: the built model, `opacityhull eval loo MODEL --views every:2 --json`. "
        "`blend`: refinement with all views, written as a model copy, scored by the same CLI command. "
        "`photo`: refinement re-run without the held-out view (`exclude_views=[i]`), rendered in-process "
        "with the renderer call `eval loo` makes and scored with its `loo_metrics`. "
        "The hull and the visibility always include every silhouette (no geometry hold-out). "
        "refine s = `refine_surfels` wall time (shared 2-core VM, contended by other jobs: "
        "indicative only); moved/confident = fractions of surfels; depth = mean inward move of moved surfels.",
        "",
    ]
    for c, run in runs.items():
        lines += [
            f"## hull-res {run['hull_res']} ({run['utc']})",
            "",
            f"`{c}`",
            "",
            "| set | variant | protocol | PSNR dB | SSIM | refine s (cost volume s) | moved | confident | mean depth mm |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in run["rows"]:
            lines.append(
                f"| {r['set']} | {r['variant']} | {r['protocol']} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                f"{r['refine_s']:.1f} ({r.get('cost_volume_s', float('nan')):.1f}) | {r.get('moved', float('nan')):.2f} | "
                f"{r.get('conf', float('nan')):.2f} | {r.get('depth_mm', float('nan')):.2f} |"
            )
        lines.append("")
    (OUT / "photo_refine.md").write_text("\n".join(lines))
    allrows = [(run["hull_res"], r) for run in runs.values() for r in run["rows"]]
    sets = list(dict.fromkeys(r["set"] for _, r in allrows))
    fig, axes = plt.subplots(1, len(sets), figsize=(6 * len(sets), 3.8), squeeze=False)
    for ax, s in zip(axes[0], sets, strict=True):
        rs = [(h, r) for h, r in allrows if r["set"] == s]
        labels = [f"{h}\n{r['variant']}" + ("" if r["protocol"] == "-" else f"\n{r['protocol']}") for h, r in rs]
        ax.bar(
            range(len(rs)),
            [r["psnr"] for _, r in rs],
            color=["grey" if r["protocol"] == "-" else ("C0" if r["protocol"] == "blend" else "C1") for _, r in rs],
        )
        ax.set_xticks(range(len(rs)), labels, fontsize=6)
        ax.set_ylim(min(r["psnr"] for _, r in rs) - 0.5, max(r["psnr"] for _, r in rs) + 0.3)
        ax.set_ylabel("LOO PSNR (dB)")
        ax.set_title(f"{s}: hull (grey), refined blend (blue) / photo hold-out (orange)", fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "photo_refine.png", dpi=110)


if __name__ == "__main__":
    main()
