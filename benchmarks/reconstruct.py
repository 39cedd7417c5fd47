"""Reconstruction: matting throughput, visual-hull carving time, and accuracy against time.

1. Matting (:func:`opacityhull.reconstruct.matting.solve_matte`), K = 6 backdrops,
   720×576: Mpx/s end to end and for the solver kernel alone, on 1 thread and on all
   threads, against the memory-bandwidth bound (the kernel streams 2·K·3 float32 = 144 B
   per pixel; bandwidth measured here with a large NumPy copy).
2. Carving a hull 384 voxels along its longest side from 36 views of 720×576 (a sphere
   and a box, analytic silhouettes): octree (:func:`carve_octree`, summed-area tables
   included) vs the dense centre-sampled numba carve; the octree's hull must be no
   fatter (the benchmark checks they are equal voxel for voxel). Open3D is not a
   dependency; if it is importable its ``VoxelGrid.carve_silhouette`` is timed too.
3. Accuracy against time on analytic sessions (tests/reconstruct/rcsynth.py): hull IoU
   and time against hull resolution; alpha MAE and matting time against K; hull IoU
   against the number of views.

    .venv/bin/python benchmarks/reconstruct.py [--quick] [--json]

Writes ``benchmarks/out/reconstruct.md`` and ``benchmarks/out/reconstruct.png``. Timings
are warm (numba compiled first; compile time reported separately), best of N.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, pyplot, report_head, save_figure

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
sys.path.insert(0, str(ROOT / "tests" / "reconstruct"))
sys.path.insert(0, str(ROOT / "tests"))  # helpers, imported by rcsynth


def best_of(fn, n):
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts)


def memory_bandwidth_gbs() -> float:
    """Read+write bandwidth of one large copy (GB/s counted as bytes read + written)."""
    a = np.ones(50_000_000, np.float32)
    b = np.empty_like(a)
    np.copyto(b, a)
    t = best_of(lambda: np.copyto(b, a), 5)
    return 2 * a.nbytes / t / 1e9


# --------------------------------------------------------------------------- matting


def bench_matting(quick: bool) -> dict:
    import numba

    from opacityhull.executor import numba_max_threads
    from opacityhull.reconstruct import matting as m

    K, H, W = 6, 576, 720
    rng = np.random.default_rng(0)
    B = rng.uniform(0.05, 0.95, (K, H, W, 3)).astype(np.float32)
    a = rng.uniform(0, 1, (H, W, 1)).astype(np.float32)
    F = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    C = (a * F)[None] + (1 - a)[None] * B + rng.normal(0, 0.003, B.shape).astype(np.float32)
    t = time.perf_counter()
    m.solve_matte(C[:, :8], B[:, :8])
    compile_s = time.perf_counter() - t
    N = H * W
    reps = 3 if quick else 7
    out = {"K": K, "width": W, "height": H, "compile_s": compile_s}
    Cr, Br = C.reshape(K, N, 3), B.reshape(K, N, 3)
    bufs = [
        np.empty(N, np.float32),
        np.empty((N, 3), np.float32),
        np.empty(N),
        np.empty(N, np.float32),
        np.empty(N, np.float32),
        np.empty(N, np.uint8),
    ]  # as solve_matte allocates them
    inf = np.full(K, np.inf, np.float32)
    threads = numba_max_threads()
    for nt in sorted({1, threads}):
        numba.set_num_threads(nt)
        te = best_of(lambda: m.solve_matte(C, B), reps)
        tk = best_of(lambda: m._matte_kernel(Cr, Br, inf, inf, *bufs), reps)
        out[f"threads_{nt}"] = {
            "end_to_end_s": te,
            "kernel_s": tk,
            "end_to_end_mpx_s": N / te / 1e6,
            "kernel_mpx_s": N / tk / 1e6,
        }
    numba.set_num_threads(threads)
    bw = memory_bandwidth_gbs()
    out["bandwidth_gbs"] = bw
    out["bytes_per_px"] = 2 * K * 3 * 4
    out["bandwidth_bound_mpx_s"] = bw * 1e9 / out["bytes_per_px"] / 1e6
    one = out["threads_1"]["kernel_mpx_s"]
    out["kernel_per_core_mpx_s"] = one
    out["kernel_ratio_to_bound"] = one / out["bandwidth_bound_mpx_s"]
    out["threads"] = threads
    r = m.solve_matte(C, B)
    out["alpha_mae_random_scene"] = float(np.abs(r.alpha - a[..., 0]).mean())
    return out


# --------------------------------------------------------------------------- carving


def ring_cameras(n, W, H, f, dist=1.0, target=(0.0, 0.1, 0.0)):
    from opacityhull.camera import Camera, look_at_world_from_cam

    target = np.asarray(target)
    cams = []
    els = (10.0, 30.0, 50.0)
    for i in range(n):
        el = math.radians(els[i % 3])
        az = 2 * math.pi * i / n
        eye = target + dist * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
        cams.append(Camera(K=K, width=W, height=H, world_from_cam=look_at_world_from_cam(eye, target)))
    return cams


def analytic_silhouette(cam, c=(0.0, 0.1, 0.0), r=0.08, box=((0.04, 0.0, -0.04), (0.13, 0.06, 0.04))):
    """Sphere ∪ box silhouette at pixel centres, computed per image row (memory-light)."""
    c = np.asarray(c)
    H, W = cam.height, cam.width
    out = np.zeros((H, W), bool)
    u = np.arange(W, dtype=np.float64)
    for y in range(0, H, 64):
        ys = np.arange(y, min(H, y + 64), dtype=np.float64)
        uv = np.stack(np.broadcast_arrays(u[None, :], ys[:, None]), -1).reshape(-1, 2)
        o, d = cam.pixel_rays(uv)
        oc = o - c
        b = d @ oc
        hit = b * b - (oc @ oc - r * r) >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (np.asarray(box[0]) - o) / d
            t1 = (np.asarray(box[1]) - o) / d
        tn = np.nanmax(np.minimum(t0, t1), axis=-1)
        tf = np.nanmin(np.maximum(t0, t1), axis=-1)
        hit |= (tf >= tn) & (tf > 0)
        out[y : y + len(ys)] = hit.reshape(len(ys), W)
    return out


def bench_carving(quick: bool) -> dict:
    from opacityhull.reconstruct.hull import HullGrid, carve_dense, carve_octree, carve_reference, hull_bounds

    V, W, H = 36, 720, 576
    f = H / (2 * math.tan(math.radians(12.0)))
    cams = ring_cameras(V, W, H, f)
    t = time.perf_counter()
    sils = [analytic_silhouette(c) for c in cams]
    sil_s = time.perf_counter() - t
    lo, hi = hull_bounds(sils, cams)
    res = 384
    grid = HullGrid.from_bounds(lo, hi, res)
    small = HullGrid.from_bounds(lo, hi, 24)
    t = time.perf_counter()
    carve_octree(sils, cams, small)
    carve_dense(sils, cams, small)
    compile_s = time.perf_counter() - t
    reps = 2 if quick else 5
    occ_o, st = carve_octree(sils, cams, grid, return_stats=True)
    t_oct = best_of(lambda: carve_octree(sils, cams, grid), reps)
    roots = {}
    for rc in (8, 16, 32, 64):
        roots[rc] = best_of(lambda rc=rc: carve_octree(sils, cams, grid, root_cell=rc), 1 if quick else 2)
    occ_d = carve_dense(sils, cams, grid)
    t_dense = best_of(lambda: carve_dense(sils, cams, grid), 1 if quick else 2)
    ref_small = carve_reference(sils, cams, HullGrid.from_bounds(lo, hi, 48))
    oct_small = carve_octree(sils, cams, HullGrid.from_bounds(lo, hi, 48))
    out = {
        "views": V,
        "width": W,
        "height": H,
        "grid": list(grid.shape),
        "voxels": int(np.prod(grid.shape)),
        "occupied": int(occ_o.sum()),
        "silhouettes_s": sil_s,
        "compile_s": compile_s,
        "octree_s": t_oct,
        "octree_root_cell_s": {str(k): v for k, v in roots.items()},
        "octree_cells": st.cells,
        "octree_tests": st.tests,
        "dense_numba_s": t_dense,
        "octree_equals_dense": bool(np.array_equal(occ_o, occ_d)),
        "fatness_octree_over_dense": float(occ_o.sum() / max(occ_d.sum(), 1)),
        "octree_equals_numpy_reference_48": bool(np.array_equal(ref_small, oct_small)),
        "speedup_over_dense": t_dense / t_oct,
    }
    try:  # pragma: no cover - optional
        import open3d  # noqa: F401  # pyright: ignore[reportMissingImports]

        out["open3d"] = "installed but not benchmarked here"
    except ImportError:
        out["open3d"] = "not installed (the issue quotes ~15 s for this grid)"
    return out


# --------------------------------------------------------------------------- accuracy vs time


def bench_accuracy(quick: bool, tmp: Path) -> dict:
    import rcsynth

    from opacityhull.reconstruct.build import BuildConfig, build_model

    rows = {"hull_res": [], "K": [], "views": []}
    base = tmp / "base"
    rcsynth.make_session(base, n_angles=8, n_patterns=3, reflectance=False, width=96, height=72, seed=1)
    build_model(base, tmp / "warm", config=BuildConfig(hull_res=32, pictures=False))  # compile
    for res in (32, 64, 128) if quick else (32, 64, 128, 192, 256):
        r = build_model(base, tmp / f"m_res{res}", config=BuildConfig(hull_res=res, pictures=False), ground_truth=True)
        rows["hull_res"].append(
            {
                "hull_res": res,
                "hull_iou": r.metrics["hull_iou"],
                "object_in_hull": r.metrics["hull_object_in_hull"],
                "surfels": r.surfels,
                "hull_s": r.seconds["hull"],
                "surfels_s": r.seconds["surfels"],
                "visibility_s": r.seconds["visibility"],
                "total_s": r.seconds["total"],
            }
        )
    for npat in (1, 2, 3):
        s = tmp / f"k{npat}"
        rcsynth.make_session(
            s, n_angles=4, n_patterns=npat, reflectance=False, width=96, height=72, seed=2, noise=0.005
        )
        r = build_model(s, tmp / f"m_k{npat}", config=BuildConfig(hull_res=64, pictures=False), ground_truth=True)
        rows["K"].append(
            {
                "K": 2 * npat,
                "alpha_mae": r.metrics["alpha_mae"],
                "matting_s": r.seconds["matting"],
                "matting_s_per_view": r.seconds["matting"] / r.views,
            }
        )
    for n_angles in (2, 4, 8) if quick else (2, 4, 8, 12):
        s = tmp / f"v{n_angles}"
        rcsynth.make_session(s, n_angles=n_angles, n_patterns=1, reflectance=False, width=96, height=72, seed=3)
        r = build_model(s, tmp / f"m_v{n_angles}", config=BuildConfig(hull_res=96, pictures=False), ground_truth=True)
        rows["views"].append(
            {
                "views": r.views,
                "hull_iou": r.metrics["hull_iou"],
                "hull_s": r.seconds["hull"],
                "total_s": r.seconds["total"],
            }
        )
    return rows


# --------------------------------------------------------------------------- report


def write_report(res: dict) -> None:
    plt = pyplot()

    OUT.mkdir(parents=True, exist_ok=True)
    mt, cv, acc = res["matting"], res["carving"], res["accuracy"]
    L = [
        *report_head(
            "Reconstruction benchmark",
            f"Machine: {os.cpu_count()} cores; measured copy bandwidth {mt['bandwidth_gbs']:.1f} GB/s (read + write).",
        ),
        "## Matting (K = 6, 720×576)",
        "",
        "| threads | end to end (ms) | Mpx/s | kernel (ms) | kernel Mpx/s |",
        "|---|---|---|---|---|",
    ]
    for k in sorted(k for k in mt if k.startswith("threads_")):
        v = mt[k]
        L.append(
            f"| {k.split('_')[1]} | {v['end_to_end_s'] * 1e3:.1f} | {v['end_to_end_mpx_s']:.1f} | "
            f"{v['kernel_s'] * 1e3:.1f} | {v['kernel_mpx_s']:.1f} |"
        )
    L += [
        "",
        f"Kernel per core: **{mt['kernel_per_core_mpx_s']:.1f} Mpx/s** (target ≥ 20); bandwidth bound "
        f"{mt['bandwidth_bound_mpx_s']:.0f} Mpx/s at {mt['bytes_per_px']} B/px → "
        f"{100 * mt['kernel_ratio_to_bound']:.0f} % of it. Compile {mt['compile_s']:.1f} s (cached).",
        "",
        f"## Carving ({cv['views']} views of {cv['width']}×{cv['height']}, grid {cv['grid']})",
        "",
        "| carver | seconds |",
        "|---|---|",
        f"| octree (root 32, SATs included) | {cv['octree_s']:.3f} |",
        f"| dense numba, centre-sampled | {cv['dense_numba_s']:.3f} |",
        f"| Open3D | {cv['open3d']} |",
        "",
        f"Octree == dense voxel for voxel: {cv['octree_equals_dense']} (fatness ratio "
        f"{cv['fatness_octree_over_dense']:.4f}); == NumPy reference at 48³: {cv['octree_equals_numpy_reference_48']}. "
        f"Root cell sweep (s): {json.dumps({k: round(v, 3) for k, v in cv['octree_root_cell_s'].items()})}. "
        f"{cv['octree_cells']} cells, {cv['octree_tests']} cell-view tests for {cv['voxels']} voxels.",
        "",
        "## Accuracy against time (analytic sphere, 3 cameras, 96×72)",
        "",
        "| hull res | IoU | object in hull | surfels | hull s | surfels s | visibility s | build s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in acc["hull_res"]:
        L.append(
            f"| {r['hull_res']} | {r['hull_iou']:.3f} | {r['object_in_hull']:.4f} | {r['surfels']} | "
            f"{r['hull_s']:.3f} | {r['surfels_s']:.3f} | {r['visibility_s']:.3f} | {r['total_s']:.2f} |"
        )
    L += ["", "| K | alpha MAE | matting s / view |", "|---|---|---|"]
    for r in acc["K"]:
        L.append(f"| {r['K']} | {r['alpha_mae']:.4f} | {r['matting_s_per_view']:.4f} |")
    L += ["", "| views | IoU | hull s |", "|---|---|---|"]
    for r in acc["views"]:
        L.append(f"| {r['views']} | {r['hull_iou']:.3f} | {r['hull_s']:.3f} |")
    (OUT / "reconstruct.md").write_text("\n".join(L) + "\n")

    fig, ax = plt.subplots(1, 4, figsize=(16, 3.6), dpi=100)
    hr = acc["hull_res"]
    ax[0].plot([r["hull_s"] + r["surfels_s"] for r in hr], [r["hull_iou"] for r in hr], "o-")
    for r in hr:
        ax[0].annotate(str(r["hull_res"]), (r["hull_s"] + r["surfels_s"], r["hull_iou"]))
    ax[0].set_xlabel("hull + surfels time (s)")
    ax[0].set_ylabel("hull IoU")
    ax[0].set_title("IoU vs time (labels: hull res)")
    ax[1].plot([r["K"] for r in acc["K"]], [r["alpha_mae"] for r in acc["K"]], "o-")
    ax[1].set_xlabel("K backdrops")
    ax[1].set_ylabel("alpha MAE")
    ax[1].set_title("alpha MAE vs K (noise 0.005)")
    ax[2].plot([r["views"] for r in acc["views"]], [r["hull_iou"] for r in acc["views"]], "o-")
    ax[2].set_xlabel("views")
    ax[2].set_ylabel("hull IoU")
    ax[2].set_title("IoU vs number of views")
    names = ["octree", "dense numba"]
    ax[3].bar(names, [cv["octree_s"], cv["dense_numba_s"]], color=["#4477aa", "#cc6677"])
    ax[3].set_yscale("log")
    ax[3].set_ylabel("seconds")
    ax[3].set_title(f"carve {cv['grid']} from {cv['views']} views")
    fig.tight_layout()
    save_figure(fig, OUT / "reconstruct.png")


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer repeats and sweep points")
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_reconstruct_"))
    try:
        res = {
            "matting": bench_matting(args.quick),
            "carving": bench_carving(args.quick),
            "accuracy": bench_accuracy(args.quick, tmp),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_report(res)
    if args.json:
        print(json.dumps(res))
    else:
        print((OUT / "reconstruct.md").read_text())


if __name__ == "__main__":
    main()
