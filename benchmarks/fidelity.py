"""Fidelity benchmark: leave-one-out on real photographs made by others, each new
feature on and off, against the time it costs.

    .venv/bin/python benchmarks/fidelity.py [--quick] [--json] [--sets temple,dino] [--model NAME=DIR ...]

For each real set (Middlebury templeSR / dinoSR, vendored in ``tests/data/real``) the
set is imported (``import colmap``), then for each configuration built and scored by
``eval loo`` with both holdouts (blending only; hull, surfels and visibility rebuilt
without the held-out view), every 2nd view held out (every 4th with ``--quick``), as the
plain baseline was (17.9 dB temple, 17.6 dB dino, geometry holdout). ``--model NAME=DIR``
adds built models (e.g. ``out/demo/model``) scored with the blending holdout under each
render configuration. Configurations:

* ``res384-classic-surfel`` — today's best before this round (hull-res 384, classical
  carve, per-surfel ULR);
* ``auto-classic-surfel`` — resolution from the pixel footprint;
* ``auto-robust-surfel`` — + confidence-weighted robust carving;
* ``auto-robust-pixel`` — + per-pixel (deferred) ULR shading;
* ``auto-robust-pixel-movesurfels`` — + photo-consistent refinement that moves the surfels;
* ``auto-robust-pixel-shadingdepth`` — instead, the surfels stay on the hull and carry the
  refined depth, where pixel shading fetches colour;
* ... each later feature of the default build on top (see :func:`configurations`);
* ``defaults`` — today's defaults, coincident views held out together (``eval loo``'s
  default), and ``defaults-twinskept`` — the same with each view held out alone, the
  baseline's protocol (the temple's first viewpoint is photographed twice).

Writes ``benchmarks/out/fidelity.md`` (table), ``fidelity.png`` (geometry-holdout PSNR
against build + render time) and ``fidelity.json`` (``fidelity_quick.*`` with
``--quick``); ``--json`` prints one object.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path
from benchkit import out_dir, parser

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
DATA = ROOT / "tests" / "data" / "real"
BASELINE = {"temple": {"psnr": 17.9, "ssim": 0.59}, "dino": {"psnr": 17.6, "ssim": 0.67}}

KEYS = (
    "psnr_mean",
    "ssim_mean",
    "psnr_interior_mean",
    "psnr_band_mean",
    "coverage_iou_mean",
    "interior_alpha_mean",
    "interior_alpha_covered_mean",
    "spill_px_mean",
    "ms_per_view",
    "rebuild_ms_per_view",
)


def configurations():
    """(name, BuildConfig overrides, RenderConfig overrides[, twins]), each adding one
    feature; ``twins`` (default "together") is how ``eval loo`` treats coincident views."""
    surfel, pixel = {"shading": "surfel"}, {"shading": "pixel", "align": "none", "opaque_interior": False}
    return [
        ("res384-classic-surfel", {"hull_res": 384, "carve_tolerance": 0, "refine": "none"}, surfel),
        ("auto-classic-surfel", {"carve_tolerance": 0, "refine": "none"}, surfel),
        ("auto-robust-surfel", {"refine": "none"}, surfel),
        ("auto-robust-pixel", {"refine": "none"}, pixel),
        ("auto-robust-pixel-movesurfels", {"refine": "surfels"}, pixel),
        # every enclosed hole doubtful (no see-through gap trusted; nothing filled)
        (
            "auto-robust-pixel-shadingdepth-fillholes",
            {"refine": "shading", "backdrop_holes": False, "fill_shadow_holes": False},
            pixel,
        ),
        ("auto-robust-pixel-shadingdepth", {"refine": "shading", "fill_shadow_holes": False}, pixel),
        (
            "auto-robust-pixel-shadingdepth-flow",
            {"refine": "shading", "fill_shadow_holes": False},
            {**pixel, "align": "flow"},
        ),
        # the shadow holes of the masks opaque in the views' alpha
        ("auto-robust-pixel-shadingdepth-flow-shadowfill", {"refine": "shading"}, {**pixel, "align": "flow"}),
        # the hull's interior opaque where the (tolerance-dilated) mattes say so
        (
            "auto-robust-pixel-shadingdepth-flow-shadowfill-opaqueinterior",
            {"refine": "shading", "carve_tolerance": 1, "doubt_bright_extensions": False},
            {**pixel, "align": "flow", "opaque_interior": True},
        ),
        # thick bright parts just outside a mask's outline doubted like shadow holes
        (
            "auto-robust-pixel-shadingdepth-flow-shadowfill-opaqueinterior-brightext",
            {"refine": "shading", "carve_tolerance": 1},
            {**pixel, "align": "flow", "opaque_interior": True},
        ),
        # today's defaults: carve tolerance 2 from 16 imported views (build.default_carve_tolerance)
        ("defaults", {}, {}),
        # the same, each view held out alone even where its twin stays (the baseline's protocol)
        ("defaults-twinskept", {}, {}, "keep"),
        # the imported masks dilated by half a pixel (one, rounded up) like a rig's mattes
        ("defaults-dilate1px", {"dilate_base_px": 0.5}, {}),
    ]


def run_set(name: str, tmp: Path, views: str, configs) -> list[dict]:
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model
    from opacityhull.evaluate.holdout import run_loo_holdouts
    from opacityhull.render.config import RenderConfig

    src = DATA / f"{name}SR"
    session = tmp / f"{name}_session"
    if not session.exists():
        import_colmap(src / "sparse", src / "images", session, masks_dir=src / "masks")
    rows = []
    for label, build_kw, render_kw, *rest in configs:
        twins = rest[0] if rest else "together"
        model = tmp / f"{name}_{label}"
        t0 = time.perf_counter()
        rep = build_model(session, model, config=BuildConfig(pictures=False, **build_kw))
        build_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        loo = run_loo_holdouts(
            model,
            views=views,
            config=RenderConfig(**render_kw),
            holdout="both",
            twins=twins,
            out=tmp / f"{name}_{label}_loo",
        )
        loo_s = time.perf_counter() - t0
        row = {
            "set": name,
            "config": label,
            "surfels": rep.surfels,
            "build_s": round(build_s, 2),
            "build_steps_s": rep.seconds,
            "loo_s": round(loo_s, 1),
            "hull_res": rep.hull.get("resolution", {}).get("hull_res"),
            "carve_tolerance": rep.hull.get("carve_tolerance"),
            "twins": twins,
        }
        for kind, h in loo["holdouts"].items():
            row[kind] = {k: h.get(k) for k in KEYS}
        rows.append(row)
        print(
            f"{name:7s} {label:26s} surfels {rep.surfels:8d}  geometry {row['geometry']['psnr_mean']:.2f} dB "
            f"(blend {row['blend']['psnr_mean']:.2f})  build {build_s:.1f} s  loo {loo_s:.0f} s",
            file=sys.stderr,
        )
    return rows


def run_model(name: str, model_dir: Path, views: str, configs, tmp: Path) -> list[dict]:
    from opacityhull.render.config import RenderConfig
    from opacityhull.evaluate.runner import run_loo

    rows, seen = [], set()
    for label, _, render_kw, *_ in configs:
        key = json.dumps(render_kw, sort_keys=True)
        if key in seen:
            continue
        seen.add(key)
        t0 = time.perf_counter()
        loo = run_loo(model_dir, views=views, config=RenderConfig(**render_kw), out=tmp / f"{name}_{label}")
        rows.append(
            {
                "set": name,
                "config": "render:" + (render_kw.get("shading", "default")),
                "loo_s": round(time.perf_counter() - t0, 1),
                "blend": {k: loo.get(k) for k in KEYS},
            }
        )
    return rows


def table(rows) -> str:
    L = [
        "| set | configuration | twins | surfels | hull res | tol | geometry-holdout PSNR / SSIM | interior / band dB | "
        "coverage IoU | interior α | blend-holdout PSNR | build s | ms per view | rebuild ms per view |",
        "|---|---|---|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        g = r.get("geometry") or {}
        b = r.get("blend") or {}

        def f(d, k, fmt="{:.2f}"):
            v = d.get(k)
            return fmt.format(v) if isinstance(v, (int, float)) and v == v else "–"

        L.append(
            f"| {r['set']} | {r['config']} | {r.get('twins', 'keep')} | {r.get('surfels', '–')} | {r.get('hull_res', '–')} | "
            f"{r.get('carve_tolerance', '–')} | {f(g, 'psnr_mean')} / {f(g, 'ssim_mean', '{:.3f}')} | "
            f"{f(g, 'psnr_interior_mean')} / {f(g, 'psnr_band_mean')} | {f(g or b, 'coverage_iou_mean', '{:.3f}')} | "
            f"{f(g or b, 'interior_alpha_mean', '{:.3f}')} | {f(b, 'psnr_mean')} | {r.get('build_s', '–')} | "
            f"{f(g or b, 'ms_per_view', '{:.0f}')} | {f(g, 'rebuild_ms_per_view', '{:.0f}')} |"
        )
    return "\n".join(L)


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for s in sorted({r["set"] for r in rows if "geometry" in r}):
        rs = [r for r in rows if r["set"] == s and "geometry" in r]
        x = [r["build_s"] + r["geometry"]["ms_per_view"] / 1e3 for r in rs]
        y = [r["geometry"]["psnr_mean"] for r in rs]
        ax.plot(x, y, "o-", label=s)
        for xi, yi, r in zip(x, y, rs, strict=True):
            ax.annotate(r["config"], (xi, yi), fontsize=6)
        if s in BASELINE:
            ax.axhline(BASELINE[s]["psnr"], ls=":", lw=0.8, color=ax.lines[-1].get_color())
            ax.axhline(BASELINE[s]["psnr"] + 3.0, ls="--", lw=0.8, color=ax.lines[-1].get_color())
    ax.set_xlabel("build + one rendered view (s)")
    ax.set_ylabel("geometry-holdout LOO PSNR (dB)")
    ax.set_title("fidelity on real photographs vs time (dotted: baseline, dashed: goal)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="every 4th view held out")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--sets", default="temple,dino")
    ap.add_argument("--configs", default=None, help="comma list of configuration names (default all)")
    ap.add_argument("--model", action="append", default=[], help="NAME=DIR of a built model (blend holdout)")
    ap.add_argument("--append", action="store_true", help="keep the rows of the earlier run (other configurations)")
    a = ap.parse_args(argv)
    views = "every:4" if a.quick else "every:2"
    configs = configurations()
    if a.configs:
        want = set(a.configs.split(","))
        configs = [c for c in configs if c[0] in want]
    rows = []
    with tempfile.TemporaryDirectory(prefix="fidelity_") as td:
        tmp = Path(td)
        for s in [x for x in a.sets.split(",") if x]:
            rows += run_set(s, tmp, views, configs)
        for spec in a.model:
            name, _, d = spec.partition("=")
            rows += run_model(name, Path(d), "every:2", configs, tmp)
    OUT.mkdir(parents=True, exist_ok=True)
    stem = "fidelity_quick" if a.quick else "fidelity"
    if a.append and (OUT / f"{stem}.json").is_file():
        done = {(r["set"], r["config"]) for r in rows}
        # rows from before coincident views were detected held each view out alone
        old = [r for r in json.loads((OUT / f"{stem}.json").read_text()) if (r["set"], r["config"]) not in done]
        rows = sorted(old + rows, key=lambda r: (r["set"] != "temple", r["set"]))
    md = [
        "# Fidelity on real photographs",
        "",
        f"`benchmarks/fidelity.py{' --quick' if a.quick else ''}`; held-out views: {views}; PSNR/SSIM over the "
        "union of photo mask and rendered coverage, colour over black, sRGB (as the baseline). Plain baseline "
        "(geometry holdout): temple 17.9 dB / 0.59, dino 17.6 dB / 0.67; goal baseline + 3 dB. Times are wall "
        "seconds on a shared 2-core machine.",
        "",
        "`twins`: `keep` holds each view out alone (the baseline's protocol, and every row measured before "
        "coincident views were detected); `together` holds a view out with its coincident twins "
        "(`camera.coincident_views`: the temple photographs its first viewpoint twice, c0 = c10), `eval loo`'s "
        "default. The dino has no twins: its rows are the same under both. The baseline itself under both "
        "protocols: `benchmarks/out/baseline.md`.",
        "",
        table(rows),
        "",
    ]
    # the quick and the full run keep separate files: the full one compares with the baseline
    (OUT / f"{stem}.md").write_text("\n".join(md))
    (OUT / f"{stem}.json").write_text(json.dumps(rows, indent=1))
    plot(rows, OUT / f"{stem}.png")
    if a.json:
        print(json.dumps({"rows": rows, "table": str(OUT / f"{stem}.md"), "plot": str(OUT / f"{stem}.png")}))
    else:
        print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
