"""Paper scale: build time and peak memory against views, resolution and light
directions on the analytic synthetic session, per-view matting on serial / threads /
a 2-worker Dask LocalCluster, and disk bytes per view of the model.

Each sweep point writes a synthetic session (:mod:`opacityhull.acquire.synthetic`, the
paper's 6 cameras, 8/24/72 table angles = 48/144/432 views) and runs ``opacityhull build``
as a child process; its peak RSS is the child's own ``ru_maxrss`` from ``os.wait4`` (so
one build's peak never hides behind another's). The scheduler comparison mattes every
view of one session through :func:`opacityhull.reconstruct.perview.matte_view_checksum`
(the workers read the session from disk and send back a checksum: the same work a build
does per view, without shipping pixels), warm (numba caches loaded in every worker first).

    .venv/bin/python benchmarks/scale.py [--quick] [--json]

Quick: views 48/144/432 at 64×48, lights 0/24 at 48 views, the scheduler comparison on
48 views at 320×240 (~3 min on the loaded 2-core VM, ~6 min when it is very loaded).
Full: also 60 lights, 200×150 / 640×480 / 1360×1032 at 48 views, 432 views at 200×150,
and the scheduler comparison on 144 views at 640×480. Writes
``benchmarks/out/scale.md``, ``scale.json`` and ``scale.png``. Timings on the shared
2-core machine are contended (other jobs run beside): compare ratios, not seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
CLI = Path(sys.executable).with_name("opacityhull")


def _env():
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def make_session(root: Path, *, n_table: int, width: int, height: int, lights: int) -> dict:
    from opacityhull.acquire.synthetic import SyntheticSessionConfig, write_synthetic_session

    t = time.perf_counter()
    info = write_synthetic_session(
        root,
        SyntheticSessionConfig(
            n_table=n_table, width_px=width, height_px=height, n_light_dirs=lights, groundtruth=False
        ),
    )
    return {
        "write_s": time.perf_counter() - t,
        "images": info["n_images"],
        "session_bytes": info["bytes"],
        "views": len(info["views"]),
    }


def run_build_rss(session: Path, model: Path, *, reflectance: bool) -> dict:
    """``opacityhull build`` in a child process: wall time, the child's own peak RSS
    (``os.wait4``: not the maximum over every child so far, as ``RUSAGE_CHILDREN`` is), sizes."""
    cmd = [str(CLI), "build", str(session), "--out", str(model), "--no-pictures", "--json"]
    if not reflectance:
        cmd.append("--no-reflectance")
    t = time.perf_counter()
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        p = subprocess.Popen(cmd, stdout=fo, stderr=fe, env=_env())
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    if p.returncode != 0:
        raise RuntimeError(f"build failed ({p.returncode}): {err.decode()[-2000:]}")
    rep = json.loads(out)
    model_bytes = sum(f.stat().st_size for f in model.rglob("*") if f.is_file())
    views_bytes = sum(
        f.stat().st_size for d in ("views", "reflectance") if (model / d).is_dir() for f in (model / d).iterdir()
    )
    return {
        "build_s": wall,
        "peak_rss_mb": ru.ru_maxrss / 1024.0,
        "model_bytes": model_bytes,
        "disk_bytes_per_view": views_bytes / max(rep["views"], 1),
        "surfels": rep["surfels"],
        "steps_s": rep.get("seconds", {}),
    }


def baseline_rss_mb() -> float:
    """Peak RSS of a child that only imports the build (interpreter, NumPy, numba, OpenCV,
    the cached kernels loaded lazily): the floor under every build's peak."""
    p = subprocess.Popen([sys.executable, "-c", "import opacityhull.reconstruct.build, opacityhull.cli"], env=_env())
    _, status, ru = os.wait4(p.pid, 0)
    return ru.ru_maxrss / 1024.0


def run_render_rss(model: Path, out: Path) -> dict:
    """``opacityhull render MODEL`` (the first captured view) in a child: time, peak RSS."""
    t = time.perf_counter()
    with tempfile.TemporaryFile() as fe:
        p = subprocess.Popen(
            [str(CLI), "render", str(model), "--out", str(out), "--json"],
            stdout=subprocess.DEVNULL,
            stderr=fe,
            env=_env(),
        )
        _, status, ru = os.wait4(p.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            fe.seek(0)
            raise RuntimeError(f"render failed: {fe.read().decode()[-2000:]}")
    return {"render_s": time.perf_counter() - t, "render_peak_rss_mb": ru.ru_maxrss / 1024.0}


def sweep_point(tmp: Path, *, n_table: int, width: int, height: int, lights: int, render: bool = False) -> dict:
    name = f"v{6 * n_table}_{width}x{height}_l{lights}"
    s, m = tmp / f"{name}.session", tmp / f"{name}.model"
    row = {"views": 6 * n_table, "width": width, "height": height, "lights": lights}
    row.update(make_session(s, n_table=n_table, width=width, height=height, lights=lights))
    row.update(run_build_rss(s, m, reflectance=lights > 0))
    if render:
        row.update(run_render_rss(m, tmp / f"{name}.png"))
    shutil.rmtree(s, ignore_errors=True)
    shutil.rmtree(m, ignore_errors=True)
    print(
        f"  {name}: write {row['write_s']:.1f} s, build {row['build_s']:.1f} s, "
        f"peak {row['peak_rss_mb']:.0f} MB, {row['disk_bytes_per_view'] / 1e3:.0f} kB/view",
        file=sys.stderr,
    )
    return row


def scheduler_comparison(tmp: Path, *, n_table: int, width: int, height: int, repeats: int) -> dict:
    """Per-view matting of one session: serial, 2 threads, 2 spawn processes, 2-worker
    LocalCluster; warm, best of ``repeats``, alternating."""
    from distributed import LocalCluster

    from opacityhull.executor import open_executor, worker_info
    from opacityhull.reconstruct.perview import matte_view_checksum, view_tasks

    s = tmp / "sched.session"
    make_session(s, n_table=n_table, width=width, height=height, lights=0)
    tasks = view_tasks(s)
    res: dict = {"views": len(tasks), "width": width, "height": height}
    lc = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None, silence_logs=40
    )
    try:
        execs = {
            "serial": open_executor("serial"),
            "threads": open_executor("threads", workers=2),
            "processes": open_executor("processes", workers=2),
            "cluster": open_executor(lc.scheduler_address),
        }
        ref = None
        for name, ex in execs.items():  # warm: numba caches, the session's manifest per worker
            got = ex.map(matte_view_checksum, tasks[:4])
            ref = ref or got
            if got != ref:
                raise RuntimeError(f"{name}: mattes differ from serial")
        # several views per task amortise the scheduler's per-task cost (4 tasks per worker)
        chunk = {"cluster_chunked": max(1, len(tasks) // (4 * execs["cluster"].n_workers))}
        execs["cluster_chunked"] = execs["cluster"]
        times = {k: [] for k in execs}
        for _ in range(repeats):
            for name, ex in execs.items():
                t = time.perf_counter()
                got = ex.map(matte_view_checksum, tasks, chunksize=chunk.get(name, 1))
                times[name].append(time.perf_counter() - t)
                if [g["sha256"] for g in got[:4]] != [r["sha256"] for r in ref]:
                    raise RuntimeError(f"{name}: mattes differ from serial")
        # the build itself: its matting step (one task per view, each writing its matte
        # into MODEL/build/mattes) through serial and the cluster, alternating
        from opacityhull.reconstruct.build import BuildConfig, build_model

        bcfg = BuildConfig(hull_res=32, pictures=False, reflectance=False)
        build_times: dict = {"serial": [], "cluster": []}
        models = {}
        for r in range(repeats):
            for name in ("serial", "cluster"):
                m = tmp / f"sched_{name}_{r}.model"
                rep = build_model(s, m, config=bcfg, executor=execs[name])
                build_times[name].append(rep.seconds["matting"])
                models[name] = m
        from opacityhull.model import OpacityHullModel

        ma, mb = (OpacityHullModel.open(models[k]) for k in ("serial", "cluster"))
        if not all(np.array_equal(ma.load_view_rgba(i), mb.load_view_rgba(i)) for i in range(len(ma.views))):
            raise RuntimeError("cluster build differs from the serial build")
        # per-task cost of the cluster itself: no-op tasks, per worker slot
        noop = list(range(200))
        execs["cluster"].map(worker_info, noop[:10])
        t = time.perf_counter()
        execs["cluster"].map(worker_info, noop)
        overhead_s = (time.perf_counter() - t) / len(noop) * execs["cluster"].n_workers
        for ex in set(execs.values()):
            ex.close()
    finally:
        lc.close()
    shutil.rmtree(s, ignore_errors=True)
    best = {k: min(v) for k, v in times.items()}
    res["build_matting_seconds"] = {k: min(v) for k, v in build_times.items()}
    res["build_matting_speedup_cluster"] = (
        res["build_matting_seconds"]["serial"] / res["build_matting_seconds"]["cluster"]
    )
    res["seconds"] = best
    res["cluster_chunksize"] = chunk["cluster_chunked"]
    res["per_view_ms"] = {k: 1e3 * v / len(tasks) for k, v in best.items()}
    res["speedup_vs_serial"] = {k: best["serial"] / v for k, v in best.items()}
    # 16 workers, from measured costs: the serial per-view cost spread over 16 slots plus
    # the cluster's own per-task cost (scheduling, transfer), measured with no-op tasks
    # (on a loaded machine the 2-worker ratio itself says more about the load than the code)
    res["projected_16_workers_s"] = best["serial"] / 16 + overhead_s * len(tasks) / 16
    res["projected_16_worker_speedup"] = best["serial"] / res["projected_16_workers_s"]
    res["cluster_overhead_ms_per_task"] = 1e3 * overhead_s
    print(f"  schedulers: {json.dumps({k: round(v, 2) for k, v in best.items()})}", file=sys.stderr)
    return res


def plot(rows: list[dict], sched: dict, path: Path, base_mb: float | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    groups = {
        f"views ({rows[0]['width']}x{rows[0]['height']})": [
            r for r in rows if r["lights"] == 0 and r["width"] == rows[0]["width"]
        ],
        "resolution (48 views)": [r for r in rows if r["views"] == 48 and r["lights"] == 0],
        "light directions (48 views)": [r for r in rows if r["views"] == 48 and r["width"] == rows[0]["width"]],
    }
    for a, (title, rr) in zip(ax[:2], [("time", "build_s"), ("peak RSS", "peak_rss_mb")]):
        for g, pts in groups.items():
            if len(pts) < 2:
                continue
            work = [p["views"] * p["width"] * p["height"] * (1 + p["lights"]) / 1e6 for p in pts]
            o = np.argsort(work)
            a.plot(np.array(work)[o], np.array([p[rr] for p in pts])[o], "o-", label=g)
        a.set_xscale("log")
        from matplotlib.ticker import NullFormatter

        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("work: views x Mpx x (1 + light directions)")
        a.set_ylabel("s" if rr == "build_s" else "MB")
        a.set_title(f"build {title} (contended 2-core VM)")
        if rr == "peak_rss_mb" and base_mb:
            a.axhline(base_mb, color="grey", ls="--", lw=1, label="imports only")
        a.legend(fontsize=8)
    if sched:
        names = list(sched["seconds"])
        ax[2].bar(names, [sched["seconds"][n] for n in names], color=["grey", "C0", "C1", "C2", "C3"][: len(names)])
        for i, n in enumerate(names):
            ax[2].text(i, sched["seconds"][n], f"{sched['speedup_vs_serial'][n]:.2f}x", ha="center", va="bottom")
        ax[2].set_ylabel("s")
        ax[2].set_title(f"matting {sched['views']} views {sched['width']}x{sched['height']}: 2 workers")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def table(rows: list[dict], sched: dict, summary: dict, quick: bool) -> str:
    lines = [
        "# Paper scale (benchmarks/scale.py)",
        "",
        f"Mode: {'quick' if quick else 'full'}. Synthetic analytic session (6 cameras, no Mitsuba), "
        "`opacityhull build --no-pictures` in a child process per point; peak RSS = the child's "
        "`ru_maxrss`. The machine is a shared, loaded 2-core VM: timings are contended, "
        "ratios measured in one run are what to compare.",
        "",
        "| views | size | lights | images | session MB | write s | build s | peak RSS MB | model kB/view | surfels |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['views']} | {r['width']}x{r['height']} | {r['lights']} | {r['images']} | "
            f"{r['session_bytes'] / 1e6:.1f} | {r['write_s']:.1f} | {r['build_s']:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {r['disk_bytes_per_view'] / 1e3:.1f} | {r['surfels']} |"
        )
    if "baseline_rss_mb" in summary:
        lines += [
            "",
            f"A child that only imports the build peaks at {summary['baseline_rss_mb']:.0f} MB: the "
            "floor under every row (at 64x48 the views' own data is a few MB).",
        ]
    if summary.get("render_peak_rss_mb_432_views"):
        lines += [
            "",
            "Renderer (`opacityhull render MODEL`, first captured view, child process) peak RSS: "
            f"{summary['render_peak_rss_mb_48_views']:.0f} MB for the 48-view model, "
            f"{summary['render_peak_rss_mb_432_views']:.0f} MB for the 432-view one.",
        ]
    if sched:
        lines += [
            "",
            f"Per-view matting of {sched['views']} views at {sched['width']}x{sched['height']} "
            "(warm, best of repeats, mattes checked equal to serial):",
            "",
            "| scheduler | s | ms/view | speedup |",
            "|---|---:|---:|---:|",
        ]
        for k, v in sched["seconds"].items():
            lines.append(f"| {k} | {v:.2f} | {sched['per_view_ms'][k]:.1f} | {sched['speedup_vs_serial'][k]:.2f} |")
        if "build_matting_seconds" in sched:
            bm = sched["build_matting_seconds"]
            lines += [
                "",
                f"`build_model`'s matting step on the same session (`--scheduler`; each view's matte "
                f"written to MODEL/build/mattes, the models checked equal): serial {bm['serial']:.2f} s, "
                f"2-worker cluster {bm['cluster']:.2f} s, {sched['build_matting_speedup_cluster']:.2f}x.",
            ]
        lines += [
            "",
            f"16 workers (projected: the serial per-view cost over 16 slots plus the cluster's "
            f"own {sched['cluster_overhead_ms_per_task']:.1f} ms per task and slot, measured with no-op tasks): "
            f"{sched['projected_16_workers_s']:.2f} s, {sched['projected_16_worker_speedup']:.1f}x serial "
            "(assumes 16 real cores and a file system that keeps up).",
        ]
    lines += ["", "Summary: `" + json.dumps(summary) + "`", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the small sweep (a few minutes)")
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ap.add_argument("--tmp", default=None, help="scratch folder (default: a temporary one)")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="oh-scale-"))
    tmp.mkdir(parents=True, exist_ok=True)
    small = (64, 48)
    points = [(8, *small, 0), (24, *small, 0), (72, *small, 0), (8, *small, 24)]
    # per-view tasks must cost well above the cluster's few ms per task to show scaling
    sched_pt = (8, 320, 240)
    repeats = 2
    if not args.quick:
        points += [(8, *small, 60), (8, 200, 150, 0), (8, 640, 480, 0), (8, 1360, 1032, 0), (72, 200, 150, 0)]
        sched_pt = (24, 640, 480)
        repeats = 3
    t0 = time.perf_counter()
    load_start = os.getloadavg()[0]
    rows = []
    base_mb = baseline_rss_mb()
    try:
        for n_table, w, h, lights in points:
            rows.append(
                sweep_point(
                    tmp,
                    n_table=n_table,
                    width=w,
                    height=h,
                    lights=lights,
                    render=(w, h) == small and lights == 0 and n_table in (8, 72),
                )
            )
        sched = scheduler_comparison(tmp, n_table=sched_pt[0], width=sched_pt[1], height=sched_pt[2], repeats=repeats)
    finally:
        if args.tmp is None:
            shutil.rmtree(tmp, ignore_errors=True)

    def pick(v, wh=small, lights=0):
        return next(r for r in rows if r["views"] == v and (r["width"], r["height"]) == wh and r["lights"] == lights)

    summary = {
        "peak_rss_ratio_432_vs_48": pick(432)["peak_rss_mb"] / pick(48)["peak_rss_mb"],
        "baseline_rss_mb": base_mb,
        "peak_rss_above_baseline_ratio_432_vs_48": (pick(432)["peak_rss_mb"] - base_mb)
        / max(pick(48)["peak_rss_mb"] - base_mb, 1.0),
        "build_time_ratio_432_vs_48": pick(432)["build_s"] / pick(48)["build_s"],
        "cluster_speedup_2_workers": sched["speedup_vs_serial"]["cluster"],
        "cluster_chunked_speedup_2_workers": sched["speedup_vs_serial"]["cluster_chunked"],
        "build_matting_speedup_cluster_2_workers": sched["build_matting_speedup_cluster"],
        "cluster_chunksize": sched["cluster_chunksize"],
        "processes_speedup_2_workers": sched["speedup_vs_serial"]["processes"],
        "threads_speedup_2_threads": sched["speedup_vs_serial"]["threads"],
        "projected_16_worker_speedup": sched["projected_16_worker_speedup"],
        "disk_bytes_per_view_48_at_64x48": pick(48)["disk_bytes_per_view"],
        "render_peak_rss_mb_432_views": pick(432).get("render_peak_rss_mb"),
        "render_peak_rss_mb_48_views": pick(48).get("render_peak_rss_mb"),
        "seconds_total": time.perf_counter() - t0,
        "resolution_for_view_ratio": f"{small[0]}x{small[1]}",
        "quick": bool(args.quick),
        "contended": True,
        # what the other jobs on the machine did to these figures: parallel speed-ups mean
        # little once the load is above the 2 cores
        "load_average_1m": [load_start, os.getloadavg()[0]],
    }
    if not args.quick:
        big = (200, 150)
        summary["peak_rss_ratio_432_vs_48_at_200x150"] = pick(432, big)["peak_rss_mb"] / pick(48, big)["peak_rss_mb"]
        summary["peak_rss_above_baseline_ratio_432_vs_48_at_200x150"] = (pick(432, big)["peak_rss_mb"] - base_mb) / max(
            pick(48, big)["peak_rss_mb"] - base_mb, 1.0
        )
    res = {"summary": summary, **summary, "rows": rows, "schedulers": sched}
    (OUT / "scale.json").write_text(json.dumps(res, indent=1))
    (OUT / "scale.md").write_text(table(rows, sched, summary, args.quick))
    plot(rows, sched, OUT / "scale.png", base_mb)
    if args.json:
        print(json.dumps(res))
    else:
        print(table(rows, sched, summary, args.quick))


if __name__ == "__main__":
    main()
