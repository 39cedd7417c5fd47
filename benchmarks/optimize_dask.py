"""Does the fit pay on Dask? One gradient step over a batch of B views, on the workers of
a 2-worker ``distributed.LocalCluster`` against in-process numba (issue 29, Build 3:
"The fitting may run on Dask like the other per-view work where that pays; measure it").

    NUMBA_NUM_THREADS=2 .venv/bin/python benchmarks/optimize_dask.py [--model DIR]
        [--batches 1,2,4] [--repeats 5] [--max-surfels 150000] [--json]

The fit (:func:`opacityhull.optimize.fit.fit_params`) renders one training view per
step, forward and backward, with the rasterizer's numba kernels on every thread. A
distributed step would instead send the parameters to the workers, let each render its
share of a batch of B views (SH colour, rasterize, loss, backward, SH backward) and send
back the summed gradients. Measured per step, warm, best of ``--repeats`` (medians in the
JSON), local and cluster alternating:

* ``local 2 thr`` / ``local 1 thr`` — the B views one after the other in this process,
  numba on 2 threads / 1 thread (the fit today, B = 1);
* ``dask 2×1`` — the parameters scattered to both workers (``broadcast=True``, every
  step: the fit changes them every step), ⌈B/2⌉ views per worker (1 thread each, numba
  on 1 thread and malloc tuned by the executor's worker plugin, docs/distributed.md),
  the per-worker gradient sums gathered and added here. The views' photographs and
  cameras are scattered once, before the clock.

Also reported: bytes sent per step (parameters × workers) and received (gradients ×
workers used), the workers' own compute time (so overhead = step − slowest worker), and
the projection to P cores. The model: ``--model`` (default: templeSR imported and built
with the defaults), the ``fast`` preset's start (at most ``--max-surfels`` hull surfels,
SH degree 3) at its training resolution (``train_scale`` 0.5). Writes
``benchmarks/out/optimize_dask.md`` and ``.json``. Figures taken while other work shares
the two cores are slow and noisy by that load.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from benchkit import local_cluster, out_dir, parser, print_result, report_head

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()


def view_grads(params: dict, views: list, which: list[int], cfg: dict) -> dict:
    """Summed gradients of the fit's loss over ``views[which]`` (the task a worker runs;
    also the local step). ``views[j]`` = (RasterCamera, centre (3,), target (H, W, 3),
    matte (H, W)). Returns the gradients (as the fit's names) and ``compute_ms``."""
    from opacityhull.optimize.fit import view_gradient
    from opacityhull.optimize.raster import RasterConfig

    t0, c0 = time.perf_counter(), time.thread_time()
    rc = RasterConfig(lowpass_px2=RasterConfig().lowpass_px2 * cfg["train_scale"] ** 2)
    B = params["sh"].shape[1]
    deg = int(round(B**0.5)) - 1
    total: dict = {"fragments": 0}
    for j in which:
        cam, centre, target, matte = views[j]
        vg = view_gradient(
            params,
            params["sh"],
            cam,
            centre,
            target,
            matte,
            degree=deg,
            raster_config=rc,
            ssim_weight=cfg["ssim_weight"],
            alpha_weight=cfg["alpha_weight"],
        )
        total["fragments"] += int(vg.out.n_fragments)
        for k, v in vg.param_grads().items():
            if k in total:
                total[k] += v
            else:
                total[k] = np.array(v, np.float32)
    total["compute_ms"] = 1e3 * (time.perf_counter() - t0)
    total["compute_cpu_ms"] = 1e3 * (time.thread_time() - c0)  # this thread; numba's pool adds to it locally
    return total


def nbytes(d: dict) -> int:
    return int(sum(v.nbytes for v in d.values() if isinstance(v, np.ndarray)))


def build_temple(tmp: Path) -> Path:
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    src = ROOT / "tests" / "data" / "real" / "templeSR"
    import_colmap(src / "sparse", src / "images", tmp / "s", masks_dir=src / "masks")
    build_model(tmp / "s", tmp / "m", config=BuildConfig(pictures=False))
    return tmp / "m"


def main(argv=None) -> int:
    import numba
    import psutil

    from opacityhull.executor import numba_max_threads, open_executor
    from opacityhull.optimize.config import fit_preset
    from opacityhull.optimize.data import load_fit_data
    from opacityhull.optimize.fit import _raster_camera
    from opacityhull.optimize.surfelparams import start_params, thin_start

    ap = parser(__doc__)
    ap.add_argument("--model", default=None, help="a built model (default: templeSR, built here)")
    ap.add_argument("--batches", default="1,2,4")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--max-surfels", type=int, default=150_000)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    batches = [int(b) for b in a.batches.split(",")]
    if numba_max_threads() < 2:
        print("run with NUMBA_NUM_THREADS=2 (the local baseline uses both cores)", file=sys.stderr)
        return 2
    fc = fit_preset("fast")
    cfg = {"train_scale": fc.train_scale, "ssim_weight": fc.ssim_weight, "alpha_weight": fc.alpha_weight}
    with tempfile.TemporaryDirectory(prefix="optimize_dask_") as td:
        model_dir = Path(a.model) if a.model else build_temple(Path(td))
        from opacityhull.model import OpacityHullModel

        V = len(OpacityHullModel.open(model_dir).views)
        data = load_fit_data(model_dir, list(range(V)), train_scale=fc.train_scale, start_surface=fc.start_surface)
    surf = data.surfels
    keep, grow = thin_start(len(surf), a.max_surfels, seed=0)
    pos = surf.shading_positions() if fc.start_surface == "refined" else surf.positions
    params = start_params(pos[keep], surf.normals[keep], surf.radii[keep] * grow, data.sh_dc[keep], sh_degree=3)
    # a fitted model's SH is not zero beyond DC: some colour variation, as the fit grows it
    params["sh"][:, 1:] = np.random.default_rng(0).normal(0, 0.02, params["sh"][:, 1:].shape).astype(np.float32)
    views = [(_raster_camera(v.camera), v.camera.centre_world, v.target, v.alpha) for v in data.views]
    W, H = data.views[0].camera.width, data.views[0].camera.height
    p_bytes = nbytes(params)
    rng = np.random.default_rng(1)
    picks = {b: [rng.choice(len(views), b, replace=False).tolist() for _ in range(a.repeats)] for b in batches}

    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", "65536")  # what a nanny sets anyway (the plugin undoes it)
    rows: list[dict] = []
    with local_cluster(n_workers=2, threads_per_worker=1) as lc:
        ex = open_executor(lc.scheduler_address, numba_threads=1)
        client = ex.client  # pyright: ignore[reportAttributeAccessIssue]
        workers = sorted(client.scheduler_info(n_workers=-1)["workers"])
        views_f = client.scatter(views, broadcast=True)  # once: the photographs do not change

        me = psutil.Process()
        procs = {w: psutil.Process(pid) for w, pid in client.run(os.getpid).items()}

        def cpu_ms(p) -> float:
            c = p.cpu_times()
            return 1e3 * (c.user + c.system)

        def dask_step(which: list[int]) -> dict:
            c0 = {w: cpu_ms(p) for w, p in procs.items()}
            m0 = cpu_ms(me)
            t0 = time.perf_counter()
            pf = client.scatter(params, broadcast=True, hash=False)  # blocks until both workers hold them
            t_sc = time.perf_counter()
            shares = [which[i :: len(workers)] for i in range(len(workers))]
            futs = [
                client.submit(view_grads, pf, views_f, s, cfg, workers=[w], pure=False, allow_other_workers=False)
                for w, s in zip(workers, shares, strict=True)
                if s
            ]
            got = client.gather(futs)
            for k in got[0]:  # the batch's gradient, as the Adam step would take it
                if isinstance(got[0][k], np.ndarray):
                    np.sum([g[k] for g in got], axis=0)
            t1 = time.perf_counter()
            del pf, futs
            cw = {w: cpu_ms(p) - c0[w] for w, p in procs.items()}
            return {
                "dask": 1e3 * (t1 - t0),
                "dask_scatter": 1e3 * (t_sc - t0),
                "dask_compute": max(g["compute_ms"] for g in got),
                "dask_compute_cpu": max(g["compute_cpu_ms"] for g in got),
                # the client (with the scheduler's thread: serialising, sending, summing) and
                # the busiest worker (receiving, computing, sending back), one after the other:
                # the step's length on idle cores, overlap ignored
                "dask_client_cpu": cpu_ms(me) - m0,
                "dask_worker_cpu": max(cw.values()),
                "sent": p_bytes * len(workers),
                "recv": sum(nbytes(g) for g in got),
            }

        def local_step(which: list[int], threads: int) -> tuple[float, float]:
            numba.set_num_threads(threads)
            c0 = time.process_time()
            t0 = time.perf_counter()
            frags.append(view_grads(params, views, which, cfg)["fragments"] / len(which))
            return 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)

        frags: list[float] = []

        # warm-up: numba caches in both workers and here
        dask_step([0, 1])
        local_step([0], 2)
        local_step([0], 1)
        for b in batches:
            t: dict[str, list[float]] = {}
            sent = recv = 0
            for which in picks[b]:
                w2, c2 = local_step(which, 2)
                d = dask_step(which)
                w1, c1 = local_step(which, 1)
                sent, recv = d.pop("sent"), d.pop("recv")
                d["dask_idle_est"] = d["dask_client_cpu"] + d["dask_worker_cpu"]
                for k, v in {"local2": w2, "local2_cpu": c2, "local1": w1, "local1_cpu": c1, **d}.items():
                    t.setdefault(k, []).append(v)
            # best of the repeats: the least disturbed by the other work on the machine
            best = {f"{k}_ms": round(min(v), 1) for k, v in t.items()}
            med = {f"{k}_ms_median": round(statistics.median(v), 1) for k, v in t.items()}
            rows.append({"batch": b, **best, **med, "sent_B": sent, "recv_B": recv})
            print(f"B={b}: {rows[-1]}", file=sys.stderr)
        ex.close()
    numba.set_num_threads(numba_max_threads())
    res = {
        "model": str(model_dir),
        "surfels": int(len(params["means"])),
        "width": W,
        "height": H,
        "param_bytes": p_bytes,
        "fragments_per_view": float(np.mean(frags)),
        "rows": rows,
        "load_average": os.getloadavg(),
    }
    write_report(res, argv)
    print_result(res, OUT / "optimize_dask.md", as_json=a.json)
    return 0


def write_report(res: dict, argv) -> None:
    rows = res["rows"]
    lines = report_head(
        "Fitting on Dask: one gradient step over B views, 2-worker LocalCluster against local numba",
        f"`benchmarks/optimize_dask.py {' '.join(sys.argv[1:] if argv is None else argv)}` "
        f"(NUMBA_NUM_THREADS=2): {res['surfels']} surfels (the fast preset's start on templeSR, SH degree 3) "
        f"rendered at {res['width']}×{res['height']} (train_scale 0.5, {res['fragments_per_view'] / 1e6:.2f} M "
        "fragments a view), forward + loss + backward per view; "
        f"parameters {res['param_bytes'] / 1e6:.1f} MB. Best of warm steps, local and cluster alternating. "
        f"Load average during the run {', '.join(f'{x:.1f}' for x in res['load_average'])} on 2 cores shared "
        "with other work: absolute times are slow and noisy by that load.",
    )
    lines += [
        "Wall time per step (best of the repeats). Under load these favour Dask falsely: two single-thread "
        "worker processes get more of the contended cores than one process whose numba threads wait for each "
        "other at every parallel stage (local 2 threads is slower than 1 here); see the CPU table.",
        "",
        "| B views / step | local, numba 2 thr (ms) | local, numba 1 thr (ms) | dask 2 workers × 1 thr (ms) "
        "| of which scatter (ms) | slowest worker computing (ms) | dask / local 2 thr | dask / best local |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['batch']} | {r['local2_ms']:.0f} | {r['local1_ms']:.0f} | {r['dask_ms']:.0f} | "
            f"{r['dask_scatter_ms']:.0f} | {r['dask_compute_ms']:.0f} | {r['dask_ms'] / r['local2_ms']:.2f} | "
            f"{r['dask_ms'] / min(r['local1_ms'], r['local2_ms']):.2f} |"
        )
    lines += [
        "",
        "CPU time per step (best of the repeats), which the other work on the machine inflates far less than "
        "wall time: `t1` = one view's forward + loss + backward in a worker (its thread's CPU; numba on 1 "
        "thread); transfer = this process's CPU (client and scheduler: pickling, sending, summing) + the "
        "busiest worker's process CPU − its computing (receiving the parameters, sending the gradients). "
        "Idle estimates: local on 2 threads B·t1 / 1.8 (the rasterizer runs 0.9 efficient on 2 idle threads, "
        "benchmarks/out/optimize_raster.md; the local 2-thread CPU measured here is inflated by the load); "
        "dask transfer + ⌈B/2⌉·t1 (the worker waits for the parameters, the client for the gradients: "
        "they do not overlap).",
        "",
        "| B | t1 per view (ms CPU) | local 1 thr CPU (ms) | local 2 thr CPU (ms) | transfer CPU (ms) "
        "| sent / received per step (MB) | idle estimate local 2 thr (ms) | idle estimate dask (ms) | ratio |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        b = r["batch"]
        per = -(-b // 2)
        t1 = r["dask_compute_cpu_ms"] / per
        xfer = r["dask_client_cpu_ms"] + r["dask_worker_cpu_ms"] - r["dask_compute_cpu_ms"]
        loc, dsk = b * t1 / 1.8, xfer + per * t1
        r["idle_estimate"] = {"t1_ms": t1, "transfer_ms": xfer, "local2_ms": loc, "dask_ms": dsk}
        lines.append(
            f"| {b} | {t1:.0f} | {r['local1_cpu_ms']:.0f} | {r['local2_cpu_ms']:.0f} | {xfer:.0f} | "
            f"{r['sent_B'] / 1e6:.1f} / {r['recv_B'] / 1e6:.1f} | {loc:.0f} | {dsk:.0f} | {dsk / loc:.2f} |"
        )
    e1, e2 = rows[0]["idle_estimate"], rows[-1]["idle_estimate"]
    ratio = [r["idle_estimate"]["dask_ms"] / r["idle_estimate"]["local2_ms"] for r in rows]
    n = res["surfels"]
    lines += [
        "",
        f"Verdict: on 2 cores the fit {'does not pay' if min(ratio) >= 1 else 'pays only for some batches'} on "
        f"Dask. On idle cores the distributed step is estimated at {ratio[0]:.1f}× the local one for "
        f"B = {rows[0]['batch']} (the fit's batch: one view a step, as in 3DGS) and {ratio[-1]:.1f}× for "
        f"B = {rows[-1]['batch']}. One view cannot be split between workers, so at B = 1 Dask adds the transfer "
        f"({e1['transfer_ms']:.0f} ms of CPU) to a one-thread computation ({e1['t1_ms']:.0f} ms) that local numba "
        f"spreads over both threads; at B = {rows[-1]['batch']} the transfer ({e2['transfer_ms']:.0f} ms) costs "
        "more than the second core saves. Nor on one machine with more cores: numba's threads share "
        f"the parameters in memory at about 0.9 efficiency, while every Dask worker must receive all "
        f"{res['param_bytes'] / n:.0f} B a surfel each step (and the client's sending grows with the workers), "
        f"against about {1e3 * e1['t1_ms'] / n:.1f} µs of computing a surfel a view at this resolution. Across "
        f"machines it could pay only when each worker renders at least about "
        f"{max(1.0, e2['transfer_ms'] / e2['t1_ms']):.0f}–{max(1.0, 2 * e2['transfer_ms'] / e2['t1_ms']):.0f} views "
        "per step (batches of several views per machine, which would change the optimizer's rates) or the views "
        "are much larger than the parameters (high resolution, few surfels). The fit stays in-process on numba "
        "threads.",
    ]
    lines.append("")
    (OUT / "optimize_dask.md").parent.mkdir(parents=True, exist_ok=True)
    (OUT / "optimize_dask.md").write_text("\n".join(lines))
    (OUT / "optimize_dask.json").write_text(json.dumps(res, indent=1, default=float))


if __name__ == "__main__":
    sys.exit(main())
