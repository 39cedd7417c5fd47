"""Hybrid point/triangle rendering (PMR, Dey & Hudson 2002) against splats only, at close-up zooms.

``render --primitives hybrid`` (``opacityhull.render.hybrid``) draws a surfel as its
umbrella triangles where the umbrella projects larger than 2 px, and as its EWA splat
elsewhere. Close up, splats show their discs (blobs at the outline, seams where they do
not overlap); triangles do not. Scored against ground truth, per zoom (the focal length
times 1, 2, 4, 8 at the same resolution, about a point of the object's right outline, so
that a close-up holds outline and surface half and half):

* **analytic sphere** (``render.synthetic``, 20 k surfels, views 160 x 120): the exact
  supersampled RGBA of the scene; PSNR of premultiplied RGBA and of alpha;
* **simulated cup** (``--model``, default the demo's model ``out/demo/model`` when it is
  there: ``make demo``; any model built from a ``sim:`` rig works): the simulator's
  coverage alpha and depth (Mitsuba, ``sim.groundtruth.render_ground_truth``, 16 spp) from
  a novel view (captured camera 0 turned to a table angle between the captures); PSNR of
  alpha and the median depth error where both cover (mm). Its colours have no ground
  truth here (the captured lighting is not a render the simulator makes at a novel view).

Also the primitives drawn (splats; triangles + splats) and the warm time per frame
(median of 3, numba threads from NUMBA_NUM_THREADS; the umbrella mesh is built once per
model and reported apart). Writes ``benchmarks/out/hybrid.md``, ``hybrid.json`` and
``hybrid.png`` (``--quick``: 5 k-surfel sphere, zooms 1 and 4, the cup skipped unless
``--model`` is given). Wall times on a shared machine.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, print_result, pyplot, report_head, save_figure

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
ROOT = Path(__file__).resolve().parents[1]
DEMO_MODEL = ROOT / "out" / "demo" / "model"


def zoomed(camera, zoom: float, about=None):
    """``camera`` with its focal length times ``zoom`` (same size), pixel ``about`` (u, v)
    of ``camera`` moved to the image centre (default: the principal point stays)."""
    K = camera.K.copy()
    u0, v0 = (K[0, 2], K[1, 2]) if about is None else about
    K[0, 0] *= zoom
    K[1, 1] *= zoom
    K[0, 2] = zoom * (K[0, 2] - u0) + (camera.width - 1) / 2 if about is not None else K[0, 2]
    K[1, 2] = zoom * (K[1, 2] - v0) + (camera.height - 1) / 2 if about is not None else K[1, 2]
    return replace(camera, K=K)


def outline_point(alpha) -> tuple[float, float]:
    """A pixel on the object's right outline: the rightmost α ≥ ½ of the covered pixels'
    middle row (the zooms look at outline and surface half and half)."""
    ys, xs = np.nonzero(alpha >= 0.5)
    v = int(np.median(ys))
    return float(xs[ys == v].max()), float(v)


def psnr(a, b, mask=None) -> float:
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if mask is not None:
        d = d[mask]
    mse = float(np.mean(d**2)) if d.size else 0.0
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def premul(rgba):
    out = np.array(rgba, np.float64)
    out[..., :3] *= out[..., 3:4]
    return out


def timed(fn, repeats: int):
    res = fn()  # warm: numba kernels, dilated mattes, area cache
    ms = []
    for _ in range(repeats):
        t = time.perf_counter()
        res = fn()
        ms.append(1e3 * (time.perf_counter() - t))
    return res, float(np.median(ms))


def render_pair(surfels, cams, pv, cam, mesh, repeats):
    from opacityhull.render.hybrid import render_hybrid

    s, ms_s = timed(lambda: render_hybrid(surfels, cams, pv, cam, mesh=mesh, threshold_px=np.inf), repeats)
    h, ms_h = timed(lambda: render_hybrid(surfels, cams, pv, cam, mesh=mesh, threshold_px=2.0), repeats)
    return s, ms_s, h, ms_h


def sphere_rows(n: int, zooms, repeats: int) -> tuple[list[dict], dict]:
    from opacityhull.render.cameras import look_at_camera
    from opacityhull.render.hybrid import build_hybrid_mesh
    from opacityhull.render.synthetic import make_sphere_model

    m = make_sphere_model(n, width=160, height=120, table_step_deg=45.0)
    pv = m.views_premul()
    t = time.perf_counter()
    mesh = build_hybrid_mesh(m.surfels)
    ms_mesh = 1e3 * (time.perf_counter() - t)
    base = look_at_camera([0.0, 0.16, 0.45], [0.0, 0.1, 0.0], fov_y_deg=30, width=240, height=180)
    about = outline_point(m.scene.render(base)[..., 3])
    rows, pics = [], {}
    for z in zooms:
        cam = zoomed(base, z, about)
        exact = m.scene.render(cam)
        s, ms_s, h, ms_h = render_pair(m.surfels, m.cameras, pv, cam, mesh, repeats)
        rows.append(
            {
                "scene": f"analytic sphere {n}",
                "zoom": z,
                "splat_psnr_rgba": psnr(premul(s.rgba), premul(exact)),
                "hybrid_psnr_rgba": psnr(premul(h.rgba), premul(exact)),
                "splat_psnr_alpha": psnr(s.rgba[..., 3], exact[..., 3]),
                "hybrid_psnr_alpha": psnr(h.rgba[..., 3], exact[..., 3]),
                "splat_primitives": len(m.surfels),
                "hybrid_triangles": h.stats["triangles"],
                "hybrid_splats": h.stats["splats"],
                "splat_ms": ms_s,
                "hybrid_ms": ms_h,
                "ms_umbrella_mesh": ms_mesh,
            }
        )
        print(rows[-1], file=sys.stderr, flush=True)
        if z == 4:
            pics["sphere"] = (s.rgba, h.rgba, exact)
    return rows, pics


def cup_rows(model_path: Path, zooms, repeats: int) -> tuple[list[dict], dict]:
    from opacityhull.model import OpacityHullModel
    from opacityhull.render.cameras import captured_view_camera
    from opacityhull.render.hybrid import build_hybrid_mesh
    from opacityhull.render.renderer import model_surfels, prepare_model_views
    from opacityhull.sim.groundtruth import render_ground_truth
    from opacityhull.sim.simrig import open_sim_rig

    m = OpacityHullModel.open(model_path)
    rig = open_sim_rig(m.meta["provenance"]["rig_source"], open=False)
    s = model_surfels(m)
    pv = prepare_model_views(m)
    cams = [v.camera for v in m.views]
    t = time.perf_counter()
    mesh = build_hybrid_mesh(s)
    ms_mesh = 1e3 * (time.perf_counter() - t)
    tables = sorted({v.table_deg for v in m.views})
    step = (tables[1] - tables[0]) if len(tables) > 1 else 60.0
    base = captured_view_camera(m.views, m.views[0].camera_index, tables[0] + 0.5 * step)
    K = base.K.copy()
    K[1, 1] = K[0, 0]  # a novel camera with square pixels (Mitsuba's sensor has no other)
    base = replace(base, K=K)
    about = outline_point(render_ground_truth(rig.scene, base, spp=4, renderer=rig.renderer)["alpha"])
    rows, pics = [], {}
    for z in zooms:
        cam = zoomed(base, z, about)
        gt = render_ground_truth(rig.scene, cam, spp=16, renderer=rig.renderer)
        a_gt, d_gt = gt["alpha"], gt["depth"]
        sp, ms_s, h, ms_h = render_pair(s, cams, pv, cam, mesh, repeats)
        row = {
            "scene": f"{Path(model_path).name} (sim {rig.scene.name})",
            "zoom": z,
            "splat_psnr_alpha": psnr(sp.rgba[..., 3], a_gt),
            "hybrid_psnr_alpha": psnr(h.rgba[..., 3], a_gt),
            "splat_primitives": len(s),
            "hybrid_triangles": h.stats["triangles"],
            "hybrid_splats": h.stats["splats"],
            "splat_ms": ms_s,
            "hybrid_ms": ms_h,
            "ms_umbrella_mesh": ms_mesh,
        }
        for k, r in (("splat", sp), ("hybrid", h)):
            both = np.isfinite(d_gt) & np.isfinite(r.depth) & (a_gt > 0.99)
            row[f"{k}_depth_err_mm"] = (
                float(np.median(np.abs(r.depth[both] - d_gt[both])) * 1e3) if both.any() else None
            )
            # interior pixels (ground truth fully covered) left see-through: the splats' seams
            inner = a_gt > 0.99
            row[f"{k}_interior_holes"] = float(np.mean(r.rgba[..., 3][inner] < 0.5)) if inner.any() else None
        rows.append(row)
        print(row, file=sys.stderr, flush=True)
        if z == 4:
            pics["cup"] = (sp.rgba, h.rgba, np.dstack([a_gt, a_gt, a_gt, np.ones_like(a_gt)]))  # α as grey
    return rows, pics


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="small sphere, zooms 1 and 4 (untracked out/quick)")
    ap.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    ap.add_argument("--model", type=Path, default=None, help="a model built from a sim: rig (default: out/demo/model)")
    args = ap.parse_args(argv)
    zooms = [1, 4] if args.quick else [1, 2, 4, 8]
    repeats = 1 if args.quick else 3
    rows, pics = sphere_rows(5000 if args.quick else 20000, zooms, repeats)
    model = args.model if args.model is not None else (None if args.quick or not DEMO_MODEL.is_dir() else DEMO_MODEL)
    if model is not None:
        r, p = cup_rows(model, zooms, repeats)
        rows += r
        pics.update(p)
    res = {"rows": rows, "threshold_px": 2.0, "machine": "shared 2-core, contended wall times"}
    OUT.mkdir(parents=True, exist_ok=True)
    lines = report_head(
        "Hybrid point/triangle rendering (PMR) vs splats, close-ups",
        "Per zoom (focal length x zoom, same resolution): PSNR against ground truth (the analytic "
        "sphere's exact RGBA; the simulator's coverage alpha and depth for a sim model), primitives "
        "drawn and warm ms per frame (median of 3). Hybrid: umbrella triangles where 2 x umbrella "
        "radius projects > 2 px, splats elsewhere. Command: `python benchmarks/hybrid.py [--model M]`. "
        "Machine: shared 2-core, contended (NUMBA_NUM_THREADS as set).",
    )
    lines += [
        "| scene | zoom | PSNR RGBA splats / hybrid (dB) | PSNR α splats / hybrid (dB) | depth err splats / hybrid "
        "(mm) | interior holes splats / hybrid | primitives splats / hybrid (tri + splat) | ms splats / hybrid |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def f(v, fmt):
        return "–" if v is None else format(v, fmt)

    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['zoom']}x | {f(r.get('splat_psnr_rgba'), '.2f')} / {f(r.get('hybrid_psnr_rgba'), '.2f')} | "
            f"{r['splat_psnr_alpha']:.2f} / {r['hybrid_psnr_alpha']:.2f} | "
            f"{f(r.get('splat_depth_err_mm'), '.2f')} / {f(r.get('hybrid_depth_err_mm'), '.2f')} | "
            f"{f(r.get('splat_interior_holes'), '.4f')} / {f(r.get('hybrid_interior_holes'), '.4f')} | "
            f"{r['splat_primitives']} / {r['hybrid_triangles'] + r['hybrid_splats']} "
            f"({r['hybrid_triangles']} + {r['hybrid_splats']}) | {r['splat_ms']:.0f} / {r['hybrid_ms']:.0f} |"
        )
    meshes = {r["scene"]: r["ms_umbrella_mesh"] for r in rows}
    lines += ["", "Umbrella mesh build (once per model): " + ", ".join(f"{k} {v:.0f} ms" for k, v in meshes.items())]
    stem = "hybrid"
    (OUT / f"{stem}.md").write_text("\n".join(lines) + "\n")
    (OUT / f"{stem}.json").write_text(json.dumps(res, indent=1) + "\n")

    plt = pyplot()
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    ncol = 2 + len(pics)
    fig, ax = plt.subplots(1, ncol, figsize=(4.2 * ncol, 3.6))
    for sc in scenes:
        rr = [r for r in rows if r["scene"] == sc]
        z = [r["zoom"] for r in rr]
        for k, ls in (("splat", "--"), ("hybrid", "-")):
            ax[0].plot(z, [r[f"{k}_psnr_alpha"] for r in rr], ls, marker="o", label=f"{sc[:16]} {k}")
            ax[1].plot(z, [r[f"{k}_ms"] for r in rr], ls, marker="o", label=f"{sc[:16]} {k}")
    for a, t in zip(ax[:2], ("alpha PSNR vs ground truth (dB)", "ms per frame"), strict=True):
        a.set_xscale("log", base=2)
        a.set_xlabel("zoom")
        a.set_title(t, fontsize=9)
        a.legend(fontsize=6)
    for a, (name, (s_img, h_img, g_img)) in zip(
        ax[2:], pics.items(), strict=False
    ):  # more axes than pictures when a set is skipped

        def over_grey(x):
            return premul(x)[..., :3] + 0.25 * (1 - x[..., 3:4])

        strip = np.concatenate([over_grey(s_img), over_grey(h_img), over_grey(g_img)], axis=1)
        a.imshow(np.clip(strip, 0, 1) ** (1 / 2.2))
        a.set_title(f"{name} 4x over grey: splats | hybrid | truth" + (" α" if name == "cup" else ""), fontsize=8)
        a.axis("off")
    fig.tight_layout()
    save_figure(fig, OUT / f"{stem}.png", dpi=110)
    print_result(res, OUT / f"{stem}.md", as_json=args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
