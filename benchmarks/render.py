"""Renderer benchmark: throughput (ULR-blended EWA surfels per second per core, ms per
frame at 512²) against the memory-bandwidth bound, and accuracy against time
(leave-one-out PSNR vs k, surfel density and splat filter), for both shading modes
(``--shading pixel|surfel|both``: per-pixel deferred ULR, or per-surfel ULR splatted).

    .venv/bin/python benchmarks/render.py [--quick] [--json] [--model MODEL_DIR ...] [--shading both]

Throughput runs on analytic sphere models (100 k – 2 M surfels, 36 views of 256×192)
rendered at 512×512 from a novel viewpoint; timings are warm (the numba compile is
timed separately) and per core (``threads=1``; CPU time of the process, because this
machine is shared and wall time includes other people's work), plus wall time with all
threads; the shading modes alternate frame by frame, so their ratio is measured under the
same load. Accuracy runs leave-one-out on each ``--model`` (built models; repeatable) when
given, else on an analytic sphere, and adds coverage IoU, interior alpha and spill (see
:func:`opacityhull.evaluate.loo.loo_metrics`). Writes ``benchmarks/out/render.md``, ``render_throughput.png``,
``render_accuracy.png`` and ``render.json``.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)


def measure_bandwidth(n_bytes: int = 400_000_000, repeats: int = 5) -> float:
    """Copy bandwidth in GB/s counting read + write (best of ``repeats``)."""
    a = np.ones(n_bytes // 4, np.float32)
    b = np.empty_like(a)
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        np.copyto(b, a)
        best = min(best, time.perf_counter() - t)
    return 2 * a.nbytes / best / 1e9


def bytes_per_surfel(n: int, drawn: int, k: int, n_vis_bytes: int, list_factor: float) -> dict:
    """Estimate of DRAM traffic per input surfel for one frame.

    * setup: read position, normal (12 + 12 B), radius, area (4 + 4 B); write the 80-B
      record and a flag for every surfel (culled ones write only the flag) — per surfel;
    * shading (drawn only): re-read position (12 B) and the visibility bits; per blended
      view (k−1) a bilinear fetch touches 2 rows × 32 B = 2 cache lines = 128 B; write RGBA
      into the record (already in cache: 0);
    * binning: read the record's bbox line (64 B) once, write an 8-B band pair and an 8-B
      list entry per band list entry (``list_factor`` entries per drawn splat);
    * raster: the records are read in place through the lists, 80 B per list entry (the
      second pass finds the band's records in cache); the 16-row band of the 7-channel
      accumulator stays in L2 — the frame buffer costs 512²·(28 + 4) B once.
    """
    per_all = 32 + 1
    per_drawn = 80 + 12 + n_vis_bytes + 128 * max(k - 1, 1) + 64 + 8 + list_factor * (8 + 80)
    frame = 512 * 512 * 32
    total = n * per_all + drawn * per_drawn + frame
    return {"bytes_per_surfel": total / n, "per_drawn_splat": per_drawn, "frame_bytes": frame}


def throughput(sizes, ks, *, reps: int, shadings=("surfel", "pixel")) -> tuple[list[dict], dict]:
    from opacityhull.render.renderer import RenderConfig, render_image, spatially_sorted, surfel_areas
    from opacityhull.render.synthetic import make_sphere_model
    from opacityhull.render.views import prepare_views
    from opacityhull.riggeometry import RigGeometry

    rows = []
    info = {}
    t0 = time.perf_counter()
    tiny = make_sphere_model(300, width=32, height=24, table_step_deg=90)
    render_image(tiny.surfels, tiny.cameras, tiny.views_premul(), tiny.cameras[0])
    info["compile_or_cache_load_s"] = time.perf_counter() - t0
    for n in sizes:
        t = time.perf_counter()
        m = make_sphere_model(n, width=256, height=192, supersample=1)
        S = spatially_sorted(m.surfels)
        ta = time.perf_counter()
        surfel_areas(S)
        t_areas = time.perf_counter() - ta
        pv = prepare_views(m.cameras, m.views_premul())
        t_model = time.perf_counter() - t
        rig = dict(m.rig)
        rig["cameras"] = [{**c, "width": 512, "height": 512, "fov_y_deg": 22.0} for c in rig["cameras"]]
        cam = RigGeometry.view_camera(RigGeometry.from_dict(rig).nominal_cameras()[1], 15.0)
        for k in ks:
            for threads in (1, None):
                cfgs = {sh: RenderConfig(k=k, threads=threads, shading=sh) for sh in shadings}
                for cfg in cfgs.values():
                    render_image(S, m.cameras, pv, cam, config=cfg)  # warm
                best = {sh: [math.inf, math.inf, None, []] for sh in shadings}  # cpu, wall, stats, cpus
                for _ in range(reps):
                    for sh, cfg in cfgs.items():  # alternating: the modes share the load
                        c0, w0 = time.process_time(), time.perf_counter()
                        r = render_image(S, m.cameras, pv, cam, config=cfg)
                        c1, w1 = time.process_time() - c0, time.perf_counter() - w0
                        b = best[sh]
                        b[3].append(c1)
                        if c1 < b[0]:
                            b[0], b[2] = c1, r.stats
                        b[1] = min(b[1], w1)
                # best of the repetitions: this VM's neighbours steal cycles (the same frame
                # measured 110-170 ms minutes apart); the median shows how large that spread is
                for sh, (cpu, wall, stats, cpus) in best.items():
                    row = {
                        "surfels": n,
                        "k": k,
                        "shading": sh,
                        "threads": stats["threads"],
                        "drawn": stats["splats_drawn"],
                        "pixels_shaded": stats.get("pixels_shaded"),
                        "cpu_ms": 1e3 * cpu,
                        "cpu_ms_median": 1e3 * float(np.median(cpus)),
                        "wall_ms": 1e3 * wall,
                        "surfels_per_s_per_core": n / cpu if threads == 1 else None,
                        "surfels_per_s_wall": n / wall,
                        "stage_ms": stats["ms"],
                    }
                    if threads == 1 and sh == "surfel":
                        nb = S.visibility.shape[1]
                        row.update(bytes_per_surfel(n, stats["splats_drawn"], k, nb, 1.25))
                    rows.append(row)
                    print(
                        f"  {n:>8} surfels k={k} {sh:>6} threads={row['threads']}: cpu {row['cpu_ms']:.0f} ms, "
                        f"wall {row['wall_ms']:.0f} ms, {n / cpu / 1e6:.2f} M surfels/s (cpu)",
                        file=sys.stderr,
                    )
        info.setdefault("model_build_s", {})[n] = t_model
        info.setdefault("surfel_areas_s", {})[n] = t_areas
    return rows, info


def accuracy(model_dir: str | None, quick: bool, shadings=("surfel", "pixel")) -> tuple[list[dict], str]:
    from opacityhull.model import OpacityHullModel, Surfels
    from opacityhull.evaluate.loo import leave_one_out, select_views
    from opacityhull.render.renderer import RenderConfig, model_surfels, prepare_model_views
    from opacityhull.render.synthetic import write_sphere_model

    rows = []
    if model_dir is None:
        import tempfile

        tmp = Path(tempfile.mkdtemp(prefix="bench_render_"))
        model_dir = str(write_sphere_model(tmp / "sphere", n_surfels=20000, width=96, height=72)[0])
        source = "analytic sphere (20 k surfels, 36 views of 96×72, exact photographs)"
    else:
        source = f"built model {model_dir}"
    model = OpacityHullModel.open(model_dir)
    pv = prepare_model_views(model)
    n_views = len(model.views)
    views = select_views(model, ("every:3" if quick else None) if n_views > 20 else "every:2")

    def run(knob, value, cfg, surfels=None):
        s = leave_one_out(model, views=views, config=cfg, prepared=pv, surfels=surfels)
        n = len(model_surfels(model) if surfels is None else surfels)
        extra = {
            key[:-5]: s[key]
            for key in (
                "psnr_interior_mean",
                "psnr_band_mean",
                "coverage_iou_mean",
                "interior_alpha_mean",
                "spill_px_mean",
            )
            if key in s
        }
        rows.append(
            {
                "model": source,
                "knob": knob,
                "value": value,
                "shading": cfg.shading,
                "surfels": n,
                "psnr": s["psnr_mean"],
                "ssim": s["ssim_mean"],
                "alpha_mae": s["alpha_mae"],
                "ms_per_view": s["ms_per_view"],
                **extra,
            }
        )
        print(
            f"  {cfg.shading} {knob}={value}: PSNR {s['psnr_mean']:.2f} dB SSIM {s['ssim_mean']:.4f} "
            f"aMAE {s['alpha_mae']:.4f} "
            + " ".join(f"{a} {b:.4g}" for a, b in extra.items())
            + f" ({s['ms_per_view']:.0f} ms/view)",
            file=sys.stderr,
        )

    full = model_surfels(model)
    for sh in shadings:
        leave_one_out(model, views=views[:1], config=RenderConfig(shading=sh), prepared=pv)  # warm
    for sh in shadings:
        base = RenderConfig(shading=sh)
        for k in (1, 2, 4, 8) if quick else (1, 2, 3, 4, 6, 8):
            run("k", k, RenderConfig(k=k, shading=sh), full)
        for f in (0.0, 0.25, 1.0) if quick else (0.0, 0.1, 0.25, 0.5, 1.0):
            run("filter", f, RenderConfig(filter=f, shading=sh), full)
        rng = np.random.default_rng(0)
        for frac in (0.25, 1.0) if quick else (0.125, 0.25, 0.5, 1.0):
            keep = np.sort(rng.choice(len(full), int(len(full) * frac), replace=False))
            sub = full.subset(keep)
            # fewer surfels cover the same surface: radii grow with the spacing
            sub = Surfels(sub.positions, sub.normals, sub.radii / math.sqrt(frac), sub.visibility, sub.n_views)
            run("density", frac, base, sub)
    return rows, source


def plots(tp_rows, acc_rows, source):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    OUT.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    one = [r for r in tp_rows if r["surfels_per_s_per_core"]]
    for k in sorted({r["k"] for r in one}):
        for sh, ls in (("surfel", "o-"), ("pixel", "s--")):
            rr = [r for r in one if r["k"] == k and r.get("shading", "surfel") == sh]
            if not rr:
                continue
            ax[0].plot(
                [r["surfels"] for r in rr], [r["surfels_per_s_per_core"] / 1e6 for r in rr], ls, label=f"k={k} {sh}"
            )
            ax[1].plot([r["surfels"] for r in rr], [r["cpu_ms"] for r in rr], ls, label=f"k={k} {sh}")
    ax[0].axhline(4.0, color="grey", ls="--", label="target 4 M/s")
    ax[0].set(
        xscale="log", xlabel="surfels", ylabel="M surfels / s / core", title="throughput at 512² (1 thread, CPU time)"
    )
    ax[1].set(
        xscale="log", yscale="log", xlabel="surfels", ylabel="ms per frame (CPU, 1 thread)", title="frame time at 512²"
    )
    ax[0].legend(fontsize=8)
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "render_throughput.png", dpi=110)
    plt.close(fig)

    knobs = ["k", "filter", "density"]
    models = list(dict.fromkeys(r["model"] for r in acc_rows))
    fig, ax = plt.subplots(len(models), 3, figsize=(13, 3.8 * len(models)), squeeze=False)
    for row_ax, mname in zip(ax, models, strict=True):
        for a, knob in zip(row_ax, knobs, strict=True):
            b = a.twinx()
            for sh, ls in (("surfel", "-"), ("pixel", "--")):
                rr = [r for r in acc_rows if r["knob"] == knob and r["model"] == mname and r["shading"] == sh]
                if not rr:
                    continue
                a.plot([r["value"] for r in rr], [r["psnr"] for r in rr], "o" + ls, color="C0", label=f"PSNR {sh}")
                b.plot([r["value"] for r in rr], [r["ms_per_view"] for r in rr], "s" + ls, color="C1", label=f"ms {sh}")
            a.set_xlabel(
                {
                    "k": "k (ULR neighbours)",
                    "filter": "EWA prefilter variance (px²)",
                    "density": "surfel fraction kept",
                }[knob]
            )
            a.set_ylabel("LOO PSNR (dB)", color="C0")
            b.set_ylabel("ms per view", color="C1")
            a.legend(fontsize=7, loc="lower left")
            a.set_title(mname[-60:], fontsize=8)
    fig.suptitle(f"accuracy vs time (solid: surfel shading, dashed: pixel) — {source}", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / "render_accuracy.png", dpi=110)
    plt.close(fig)


def main():
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="100 k and 500 k surfels, k in {1, 4, 8}, fewer LOO views")
    ap.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    ap.add_argument(
        "--model",
        action="append",
        default=None,
        help="built model for the accuracy sweep (repeatable; 'sphere' or default: the analytic sphere)",
    )
    ap.add_argument("--shading", choices=("pixel", "surfel", "both"), default="both", help="shading mode(s) to measure")
    ap.add_argument("--skip-accuracy", action="store_true")
    args = ap.parse_args()

    sizes = (100_000, 500_000) if args.quick else (100_000, 500_000, 1_000_000, 2_000_000)
    ks = (1, 4, 8) if args.quick else (1, 2, 4, 6, 8)
    print("bandwidth ...", file=sys.stderr)
    bw = measure_bandwidth()
    print(f"  numpy copy: {bw:.1f} GB/s (read + write)", file=sys.stderr)
    print("throughput ...", file=sys.stderr)
    shadings = ("surfel", "pixel") if args.shading == "both" else (args.shading,)
    tp_rows, info = throughput(sizes, ks, reps=5, shadings=shadings)
    acc_rows, sources = [], []
    for mdir in [None] if not args.model else [None if m == "sphere" else m for m in args.model]:
        if args.skip_accuracy:
            break
        rr, src = accuracy(mdir, args.quick, shadings)
        acc_rows += rr
        sources.append(src)
    source = "; ".join(sources) or "skipped"

    one = [r for r in tp_rows if r["surfels_per_s_per_core"]]
    head_sh = "surfel" if "surfel" in shadings else shadings[0]
    head = max((r for r in one if r["k"] == 4 and r["shading"] == head_sh), key=lambda r: r["surfels"])
    if "bytes_per_surfel" not in head:
        head.update(bytes_per_surfel(head["surfels"], head["drawn"], 4, 1, 1.25))
    bound = bw * 1e9 / head["bytes_per_surfel"]
    summary = {
        "surfels_per_s_per_core": head["surfels_per_s_per_core"],
        "ms_per_frame": head["cpu_ms"],
        "ms_per_frame_median": head["cpu_ms_median"],
        "surfels_per_s_per_core_median": head["surfels"] / (head["cpu_ms_median"] / 1e3),
        "ms_per_frame_wall_all_threads": next(
            r["wall_ms"]
            for r in tp_rows
            if r["surfels"] == head["surfels"]
            and r["k"] == 4
            and r["shading"] == head_sh
            and not r["surfels_per_s_per_core"]
        ),
        "ms_per_frame_by_shading": {
            sh: next(r["cpu_ms"] for r in one if r["surfels"] == head["surfels"] and r["k"] == 4 and r["shading"] == sh)
            for sh in shadings
        },
        "at": {"surfels": head["surfels"], "k": 4, "resolution": "512x512", "drawn": head["drawn"]},
        "target_surfels_per_s_per_core": 4e6,
        "bandwidth_gb_s": bw,
        "bytes_per_surfel_estimate": head["bytes_per_surfel"],
        "bandwidth_bound_surfels_per_s": bound,
        "fraction_of_bandwidth_bound": head["surfels_per_s_per_core"] / bound,
        "compile_or_cache_load_s": info["compile_or_cache_load_s"],
        "surfel_areas_s": info["surfel_areas_s"],
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
        "throughput": tp_rows,
        "accuracy_source": source,
        "accuracy": acc_rows,
    }
    OUT.mkdir(parents=True, exist_ok=True)
    plots(tp_rows, acc_rows, source) if acc_rows else None
    lines = [
        "# Renderer benchmark (`benchmarks/render.py" + (" --quick" if args.quick else "") + "`)",
        "",
        f"Machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} while measuring (shared). "
        f"NumPy copy bandwidth {bw:.1f} GB/s (read + write). numba compile / cache load "
        f"{info['compile_or_cache_load_s']:.1f} s (not in the timings).",
        "",
        "## Throughput at 512×512 (analytic sphere, novel view, warm)",
        "",
        "CPU time is the best of 5 frames (median in brackets); M surfels/s/core from the best. "
        "On this shared VM whole runs an hour apart differed by up to 1.7x (2 M surfels, k = 4: "
        "297 ms against 506 ms per frame, the other tenants' load), so compare rows within one run.",
        "",
        "| surfels | shading | drawn | k | threads | CPU ms/frame | wall ms/frame | M surfels/s/core | setup / shade / raster ms |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in tp_rows:
        st = r["stage_ms"]
        lines.append(
            f"| {r['surfels']:,} | {r['shading']} | {r['drawn']:,} | {r['k']} | {r['threads']} | {r['cpu_ms']:.0f} ({r['cpu_ms_median']:.0f}) | "
            f"{r['wall_ms']:.0f} | {(r['surfels'] / r['cpu_ms'] / 1e3) if r['surfels_per_s_per_core'] else float('nan'):.2f} | "
            f"{st['setup']:.0f} / {st['shade']:.0f} / {st['raster']:.0f} |"
        )
    lines += [
        "",
        "## Memory-bandwidth bound (surfel shading)",
        "",
        f"Estimated DRAM traffic {head['bytes_per_surfel']:.0f} B per input surfel at {head['surfels']:,} "
        f"surfels, k = 4 (see `bytes_per_surfel`); at {bw:.1f} GB/s that bounds the renderer at "
        f"{bound / 1e6:.1f} M surfels/s; measured {head['surfels_per_s_per_core'] / 1e6:.2f} M/s per core = "
        f"{100 * summary['fraction_of_bandwidth_bound']:.0f} % of the bound (target 4 M/s). "
        "The renderer is compute- and latency-bound (ULR search, scattered texel fetches), not "
        "bandwidth-bound.",
        "",
    ]
    if acc_rows:
        lines += [
            f"## Accuracy vs time: leave-one-out on {source}",
            "",
            "Interior/band PSNR, coverage IoU (α > ½ both), interior α (photo opaque, eroded) and spill "
            "(rendered α > ½ outside the photo's mask dilated by 1 px) from `loo_metrics`.",
            "",
            "| model | shading | knob | value | surfels | PSNR dB | interior | band | SSIM | alpha MAE | IoU | "
            "interior α | spill px | ms/view |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        nan = float("nan")
        for r in acc_rows:
            lines.append(
                f"| {Path(r['model'].split()[-1]).name if r['model'].startswith('built') else 'sphere'} | "
                f"{r['shading']} | {r['knob']} | {r['value']} | {r['surfels']:,} | {r['psnr']:.2f} | "
                f"{r.get('psnr_interior', nan):.2f} | {r.get('psnr_band', nan):.2f} | {r['ssim']:.4f} | "
                f"{r['alpha_mae']:.4f} | {r.get('coverage_iou', nan):.4f} | {r.get('interior_alpha', nan):.4f} | "
                f"{r.get('spill_px', nan):.0f} | {r['ms_per_view']:.0f} |"
            )
        lines += ["", "![throughput](render_throughput.png)", "", "![accuracy](render_accuracy.png)"]
    (OUT / "render.md").write_text("\n".join(lines) + "\n")
    (OUT / "render.json").write_text(json.dumps(summary, indent=1, default=float))
    if args.json:
        print(json.dumps({k: v for k, v in summary.items() if k not in ("throughput", "accuracy")}, default=float))
    else:
        print("\n".join(lines))


if __name__ == "__main__":
    main()
