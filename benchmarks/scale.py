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

    .venv/bin/python benchmarks/scale.py [--quick] [--json] [--storage-only] [--memory-only] [--paper-only]

The goal point (``--paper-only``, merged into the existing scale.json/md): 432 views at
1360x1032 without reflectance, the build's defaults, wall time and peak RSS, then the
renderer's peak RSS on that model, and the same at 48 views (~35 GB of scratch; ~15 min).

Memory against views (also ``--memory-only``, merged into the existing scale.json/md):
48/144/432 views at 320×240, where the views' data dominates the interpreter's import
floor (432 views of 320×240 RGBA float32 = 530 MB): the build's peak RSS with the default
options and with ``--refine none``, and the renderer's. ``--compare-pythonpath DIR`` also
runs every point with another copy of the package first on ``PYTHONPATH`` (e.g. the
tree before a change) and puts its figures beside.

Model storage (also ``--storage-only``, merged into the existing scale.json/md): the
same models written with half and float32 pixels (``write_model(storage=...)``) and one
synthetic build both ways (``build --storage``): disk bytes per view, leave-one-out PSNR,
relit error against the exact quadrature, and the stored values' error.

Quick: views 48/144/432 at 64×48, lights 0/24 at 48 views, the scheduler comparison on
48 views at 320×240 (~3 min on the loaded 2-core VM, ~6 min when it is very loaded).
Full: also 60 lights, 200×150 / 640×480 / 1360×1032 at 48 views, 432 views at 200×150,
and the scheduler comparison on 144 views at 640×480. Writes
``benchmarks/out/scale.md``, ``scale.json`` and ``scale.png``. Timings on the shared
2-core machine are contended (other jobs run beside): compare ratios, not seconds.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from benchkit import local_cluster, out_dir, parser

if TYPE_CHECKING:
    from opacityhull.model import Storage

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
CLI = Path(sys.executable).with_name("opacityhull")


def _env(pythonpath: str | None = None, *, single_thread: bool = False):
    """The children's environment: ``pythonpath`` first on PYTHONPATH; ``single_thread``
    (the memory sweep) also one numba thread, so that runs beside other benchmarks stay
    light (the peak RSS does not depend on it)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    if single_thread:
        env["NUMBA_NUM_THREADS"] = "1"
    return env


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


def run_build_rss(
    session: Path,
    model: Path,
    *,
    reflectance: bool,
    storage: str | None = None,
    extra: tuple[str, ...] = (),
    pythonpath: str | None = None,
    single_thread: bool = False,
) -> dict:
    """``opacityhull build`` in a child process: wall time, the child's own peak RSS
    (``os.wait4``: not the maximum over every child so far, as ``RUSAGE_CHILDREN`` is), sizes."""
    cmd = [str(CLI), "build", str(session), "--out", str(model), "--no-pictures", "--json", *extra]
    if not reflectance:
        cmd.append("--no-reflectance")
    if storage is not None:
        cmd += ["--storage", storage]
    t = time.perf_counter()
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        p = subprocess.Popen(cmd, stdout=fo, stderr=fe, env=_env(pythonpath, single_thread=single_thread))
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
        "storage": rep.get("metrics", {}).get("storage_pixel_type", "float"),
        "report_disk_bytes_per_view": rep.get("metrics", {}).get("disk_bytes_per_view"),
        "surfels": rep["surfels"],
        "steps_s": rep.get("seconds", {}),
        "report_peak_rss_mb": rep.get("peak_rss_mb"),
        "memory_budget_gb": rep.get("memory_budget_gb"),
    }


def baseline_rss_mb() -> float:
    """Peak RSS of a child that only imports the build (interpreter, NumPy, numba, OpenCV,
    the cached kernels loaded lazily): the floor under every build's peak."""
    p = subprocess.Popen([sys.executable, "-c", "import opacityhull.reconstruct.build, opacityhull.cli"], env=_env())
    _, status, ru = os.wait4(p.pid, 0)
    return ru.ru_maxrss / 1024.0


def run_render_rss(model: Path, out: Path, *, pythonpath: str | None = None, single_thread: bool = False) -> dict:
    """``opacityhull render MODEL`` (the first captured view) in a child: time, peak RSS."""
    t = time.perf_counter()
    with tempfile.TemporaryFile() as fe:
        p = subprocess.Popen(
            [str(CLI), "render", str(model), "--out", str(out), "--json"],
            stdout=subprocess.DEVNULL,
            stderr=fe,
            env=_env(pythonpath, single_thread=single_thread),
        )
        _, status, ru = os.wait4(p.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            fe.seek(0)
            raise RuntimeError(f"render failed: {fe.read().decode()[-2000:]}")
    return {"render_s": time.perf_counter() - t, "render_peak_rss_mb": ru.ru_maxrss / 1024.0}


def sweep_point(
    tmp: Path, *, n_table: int, width: int, height: int, lights: int, render: bool = False, report: bool = False
) -> dict:
    """One synthetic session written, built (and rendered with ``render``) in child
    processes, then deleted; ``report`` adds the build report's memory plan, chosen
    resolution and refinement counts."""
    name = f"v{6 * n_table}_{width}x{height}_l{lights}"
    s, m = tmp / f"{name}.session", tmp / f"{name}.model"
    row: dict = {"views": 6 * n_table, "width": width, "height": height, "lights": lights}
    row.update(make_session(s, n_table=n_table, width=width, height=height, lights=lights))
    row.update(run_build_rss(s, m, reflectance=lights > 0))
    if report:
        rep = json.loads((m / "report.json").read_text())
        hull = rep.get("hull", {})
        row["memory_plan"] = rep.get("memory", {})
        row["resolution"] = hull.get("resolution")
        row["refine"] = {k: v for k, v in hull.get("refine", {}).items() if not isinstance(v, (list, dict))}
    if render:
        row.update(run_render_rss(m, tmp / f"{name}.png"))
    shutil.rmtree(s, ignore_errors=True)
    shutil.rmtree(m, ignore_errors=True)
    print(
        f"  {name}: write {row['write_s']:.1f} s, build {row['build_s']:.1f} s, peak {row['peak_rss_mb']:.0f} MB"
        + (f", render peak {row['render_peak_rss_mb']:.0f} MB" if render else "")
        + f", {row['disk_bytes_per_view'] / 1e3:.0f} kB/view",
        file=sys.stderr,
    )
    return row


MEMORY_SIZE = (320, 240)
MEMORY_TABLES = (8, 24, 72)  # 48, 144, 432 views


def memory_sweep(tmp: Path, *, compare_pythonpath: str | None = None, compare_label: str | None = None) -> dict:
    """Peak RSS of the build (default options and ``--refine none``) and of the renderer
    against the views at :data:`MEMORY_SIZE`; with ``compare_pythonpath`` the same with
    that copy of the package."""
    w, h = MEMORY_SIZE
    variants: dict[str, str | None] = {"now": None}
    if compare_pythonpath:
        variants["compare"] = compare_pythonpath
    rows = []
    for n_table in MEMORY_TABLES:
        s = tmp / f"mem_v{6 * n_table}.session"
        row: dict = {"views": 6 * n_table, "width": w, "height": h}
        row.update(make_session(s, n_table=n_table, width=w, height=h, lights=0))
        for name, pp in variants.items():
            m = tmp / f"mem_v{6 * n_table}_{name}.model"
            b = run_build_rss(s, m, reflectance=False, pythonpath=pp, single_thread=True)
            row[f"{name}_build_peak_rss_mb"] = b["peak_rss_mb"]
            row[f"{name}_build_s"] = b["build_s"]
            row[f"{name}_steps_s"] = b["steps_s"]
            row[f"{name}_memory_budget_gb"] = b["memory_budget_gb"]
            row[f"{name}_render_peak_rss_mb"] = run_render_rss(
                m, tmp / f"mem_{name}.png", pythonpath=pp, single_thread=True
            )["render_peak_rss_mb"]
            shutil.rmtree(m, ignore_errors=True)
            m2 = tmp / f"mem_v{6 * n_table}_{name}_norefine.model"
            b2 = run_build_rss(s, m2, reflectance=False, extra=("--refine", "none"), pythonpath=pp, single_thread=True)
            row[f"{name}_norefine_build_peak_rss_mb"] = b2["peak_rss_mb"]
            shutil.rmtree(m2, ignore_errors=True)
            print(
                f"  memory {6 * n_table} views {w}x{h} [{name}]: build {b['peak_rss_mb']:.0f} MB, "
                f"--refine none {b2['peak_rss_mb']:.0f} MB, render {row[f'{name}_render_peak_rss_mb']:.0f} MB",
                file=sys.stderr,
            )
        shutil.rmtree(s, ignore_errors=True)
        rows.append(row)
    return {"size": f"{w}x{h}", "rows": rows, "compare_pythonpath": compare_pythonpath, "compare_label": compare_label}


def _memory_summary(mem: dict) -> dict:
    r48 = next(r for r in mem["rows"] if r["views"] == 48)
    r432 = next(r for r in mem["rows"] if r["views"] == 432)
    size = mem["size"]
    out = {}
    for name in ("now", "compare"):
        if f"{name}_build_peak_rss_mb" not in r48:
            continue
        tag = "" if name == "now" else "_compare"
        out[f"peak_rss_ratio_432_vs_48_at_{size}{tag}"] = (
            r432[f"{name}_build_peak_rss_mb"] / r48[f"{name}_build_peak_rss_mb"]
        )
        out[f"peak_rss_ratio_432_vs_48_at_{size}_refine_none{tag}"] = (
            r432[f"{name}_norefine_build_peak_rss_mb"] / r48[f"{name}_norefine_build_peak_rss_mb"]
        )
        out[f"render_peak_rss_ratio_432_vs_48_at_{size}{tag}"] = (
            r432[f"{name}_render_peak_rss_mb"] / r48[f"{name}_render_peak_rss_mb"]
        )
        out[f"render_peak_rss_mb_432_views_at_{size}{tag}"] = r432[f"{name}_render_peak_rss_mb"]
    return out


def memory_table(mem: dict, summary: dict) -> list[str]:
    size = mem["size"]
    cmp_ = mem.get("compare_pythonpath")
    lines = [
        "",
        f"## Peak RSS against views at {size}",
        "",
        "`opacityhull build --no-pictures --no-reflectance` (default options, and `--refine none`) and "
        "`opacityhull render MODEL` in child processes (`ru_maxrss`), `--memory-gb` at its default; "
        f"`benchmarks/scale.py --memory-only{' --compare-pythonpath ' + cmp_ if cmp_ else ''}`."
        + (
            f" Columns *before*: the same with the package copy on that PYTHONPATH ({mem.get('compare_label') or 'unlabelled'})."
            if cmp_
            else ""
        )
        + " Build seconds are contended and include numba compiling a kernel whose source changed on its first run.",
        "",
    ]
    has_cmp = "compare_build_peak_rss_mb" in mem["rows"][0]
    if has_cmp:
        lines += [
            "| views | build MB | before | `--refine none` MB | before | render MB | before | build s | before |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
    else:
        lines += ["| views | build MB | `--refine none` MB | render MB | build s |", "|---:|---:|---:|---:|---:|"]
    for r in mem["rows"]:
        if has_cmp:
            lines.append(
                f"| {r['views']} | {r['now_build_peak_rss_mb']:.0f} | {r['compare_build_peak_rss_mb']:.0f} | "
                f"{r['now_norefine_build_peak_rss_mb']:.0f} | {r['compare_norefine_build_peak_rss_mb']:.0f} | "
                f"{r['now_render_peak_rss_mb']:.0f} | {r['compare_render_peak_rss_mb']:.0f} | "
                f"{r['now_build_s']:.1f} | {r['compare_build_s']:.1f} |"
            )
        else:
            lines.append(
                f"| {r['views']} | {r['now_build_peak_rss_mb']:.0f} | {r['now_norefine_build_peak_rss_mb']:.0f} | "
                f"{r['now_render_peak_rss_mb']:.0f} | {r['now_build_s']:.1f} |"
            )
    k = f"peak_rss_ratio_432_vs_48_at_{size}"
    lines += [
        "",
        f"432 / 48 views: build {summary.get(k, float('nan')):.2f}x, `--refine none` "
        f"{summary.get(k + '_refine_none', float('nan')):.2f}x, render "
        f"{summary.get(f'render_peak_rss_ratio_432_vs_48_at_{size}', float('nan')):.2f}x"
        + (
            f" (before: {summary[k + '_compare']:.2f}x, {summary[k + '_refine_none_compare']:.2f}x, "
            f"{summary[f'render_peak_rss_ratio_432_vs_48_at_{size}_compare']:.2f}x)"
            if k + "_compare" in summary
            else ""
        )
        + ". The photo refinement (`photo.refine_surfels`) streams its views: at most "
        "`MemoryPlan.photo_slots` views' grey image and matte (8 B a pixel; a quarter of `--memory-gb`) in "
        "memory, the silhouettes bit-packed, so it no longer holds (V, H, W) stacks; the surfel "
        "bisection reads bit-packed silhouettes and a 4x4-pooled distance floor "
        "(`surfels.packed_bisection_stacks`, 0.31 B a pixel a view). What still grows with the views "
        "is the bit-packed masks (1/8 B a pixel a view each) and the per-surfel visibility "
        "(1 B a surfel a view); see ARCHITECTURE.md, build memory.",
    ]
    return lines


def scheduler_comparison(tmp: Path, *, n_table: int, width: int, height: int, repeats: int) -> dict:
    """Per-view matting of one session: serial, 2 threads, 2 spawn processes, 2-worker
    LocalCluster; warm, best of ``repeats``, alternating."""
    from opacityhull.executor import open_executor, worker_info
    from opacityhull.reconstruct.perview import matte_view_checksum, view_tasks

    s = tmp / "sched.session"
    make_session(s, n_table=n_table, width=width, height=height, lights=0)
    tasks = view_tasks(s)
    res: dict = {"views": len(tasks), "width": width, "height": height}
    with local_cluster(n_workers=2, threads_per_worker=1) as lc:
        execs = {
            "serial": open_executor("serial"),
            "threads": open_executor("threads", workers=2),
            "processes": open_executor("processes", workers=2),
            "cluster": open_executor(lc.scheduler_address),
        }
        ref = execs["serial"].map(matte_view_checksum, tasks[:4])
        for name, ex in execs.items():  # warm: numba caches, the session's manifest per worker
            got = ex.map(matte_view_checksum, tasks[:4])
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


def _dir_bytes_per_view(model, sub: str) -> float:
    files = [model.root / sub / f"{v.id}.exr" for v in model.views]
    return sum(f.stat().st_size for f in files if f.is_file()) / len(model.views)


def _copy_model(m, dst: Path, storage: Storage):
    """``m`` rewritten through ``write_model`` in ``storage`` (both copies of a pair go
    through the same path, so they differ only in the pixel type)."""
    from opacityhull.model import copy_model

    return copy_model(m, dst, storage=storage)


def storage_comparison(tmp: Path, *, quick: bool) -> dict:
    """Half against float32 pixels in the model: disk bytes per view (views and
    reflectance), leave-one-out PSNR of the analytic sphere (render/synthetic), relit
    error against the exact quadrature (relight/synthetic), and the relative error of
    the stored values. Each model pair is written from the same data, differing only in
    ``write_model(storage=...)``."""
    from opacityhull.model import OpacityHullModel
    from opacityhull.envmap import EnvironmentMap
    from opacityhull.relight.envmap import downsample_latlong, load_envmap
    from opacityhull.relight.relit import Relighter
    from opacityhull.relight.synthetic import SphereScene, sphere_groundtruth
    from opacityhull.relight.synthetic import write_sphere_model as write_relight_sphere
    from opacityhull.evaluate.loo import leave_one_out
    from opacityhull.render.renderer import RenderConfig
    from opacityhull.render.synthetic import write_sphere_model as write_render_sphere
    from opacityhull.data import PROBES_DIR

    w, h = (96, 72) if quick else (200, 150)
    res: dict = {"loo_size": f"{w}x{h}"}
    # a real build of the synthetic session, both ways (`opacityhull build --storage`)
    n_table, bw, bh, lights = (8, 64, 48, 24) if quick else (8, 200, 150, 24)
    s = tmp / "st_build.session"
    make_session(s, n_table=n_table, width=bw, height=bh, lights=lights)
    builds = {}
    for st in ("float", "half"):
        b = run_build_rss(s, tmp / f"st_build_{st}.model", reflectance=True, storage=st)
        if b["storage"] != st:
            raise RuntimeError(f"build --storage {st} wrote a {b['storage']} model")
        builds[st] = {k: b[k] for k in ("disk_bytes_per_view", "report_disk_bytes_per_view", "build_s")}
    res["build"] = {"views": 6 * n_table, "size": f"{bw}x{bh}", "lights": lights, **builds}
    res["build_bytes_per_view_ratio_half_vs_float"] = (
        builds["half"]["disk_bytes_per_view"] / builds["float"]["disk_bytes_per_view"]
    )
    fm, hm = (OpacityHullModel.open(tmp / f"st_build_{st}.model") for st in ("float", "half"))
    d = [np.max(np.abs(a - b)) for a, b in zip(fm.load_views_premul(), hm.load_views_premul(), strict=True)]
    res["build_views_max_abs_err"] = float(max(d))
    for p in (s, tmp / "st_build_float.model", tmp / "st_build_half.model"):
        shutil.rmtree(p, ignore_errors=True)
    # leave-one-out on the ULR renderer (views only)
    src, _ = write_render_sphere(tmp / "st_loo_src", width=w, height=h, table_step_deg=30.0, n_surfels=20000)
    src_m = OpacityHullModel.open(src)
    loo_m = {st: _copy_model(src_m, tmp / f"st_loo_{st}", st) for st in ("float", "half")}
    pick = list(range(0, len(src_m.views), 3))
    loo = {st: leave_one_out(m, views=pick, config=RenderConfig()) for st, m in loo_m.items()}
    res["loo_views"] = len(pick)
    res["loo_psnr_db"] = {st: loo[st]["psnr_mean"] for st in loo}
    res["loo_psnr_delta_db"] = loo["half"]["psnr_mean"] - loo["float"]["psnr_mean"]
    pv = {st: np.concatenate([p.ravel() for p in m.load_views_premul()]) for st, m in loo_m.items()}
    res["views_max_abs_err"] = float(np.max(np.abs(pv["half"] - pv["float"])))
    res["views_max_value"] = float(np.nanmax(pv["float"]))
    res["views_bytes_per_view"] = {st: _dir_bytes_per_view(m, "views") for st, m in loo_m.items()}
    # relighting from the one-light images (views + reflectance)
    rw, rh = (40, 32) if quick else (96, 80)
    rsrc = OpacityHullModel.open(write_relight_sphere(tmp / "st_rl_src", width=rw, height=rh))
    rl_m = {st: _copy_model(rsrc, tmp / f"st_rl_{st}", st) for st in ("float", "half")}
    res["relight_size"] = f"{rw}x{rh}"
    res["relight_lights"] = len(rsrc.light_samples)
    env = EnvironmentMap(downsample_latlong(load_envmap(PROBES_DIR / "grace.hdr", yaw_deg=180).radiance, 4))
    errs: dict = {"float": [], "half": []}
    vs_float = []
    rel_val = []
    for i in range(len(rsrc.views)):
        truth = sphere_groundtruth(rsrc.views[i].camera, SphereScene(), env, upper_only=True)
        relit = {st: Relighter(m).relight_view(i, envmap=env) for st, m in rl_m.items()}
        msk = relit["float"][..., 3] > 0.99
        for st in errs:
            errs[st].append(float(np.linalg.norm(relit[st][..., :3][msk] - truth[msk]) / np.linalg.norm(truth[msk])))
        vs_float.append(
            float(
                np.linalg.norm(relit["half"][..., :3][msk] - relit["float"][..., :3][msk])
                / np.linalg.norm(relit["float"][..., :3][msk])
            )
        )
        a, b = rl_m["float"].load_reflectance(i), rl_m["half"].load_reflectance(i)
        for k in a:
            big = np.abs(a[k]) > 6.2e-5  # normal half range: relative precision 2**-11
            if big.any():
                rel_val.append(float(np.max(np.abs(b[k][big] - a[k][big]) / np.abs(a[k][big]))))
    res["relight_rel_err_vs_truth_max"] = {st: max(v) for st, v in errs.items()}
    res["relight_rel_err_half_vs_float_max"] = max(vs_float)
    res["reflectance_max_rel_err"] = max(rel_val)
    res["bytes_per_view"] = {
        st: {"views": _dir_bytes_per_view(m, "views"), "reflectance": _dir_bytes_per_view(m, "reflectance")}
        for st, m in rl_m.items()
    }
    tot = {st: sum(v.values()) for st, v in res["bytes_per_view"].items()}
    res["bytes_per_view_ratio_half_vs_float"] = tot["half"] / tot["float"]
    for d in (tmp / n for n in ("st_loo_src", "st_rl_src", *(f"st_{k}_{st}" for k in ("loo", "rl") for st in tot))):
        shutil.rmtree(d, ignore_errors=True)
    print(f"  storage: {json.dumps(res)}", file=sys.stderr)
    return res


def _storage_summary(st: dict) -> dict:
    return {
        "storage_bytes_per_view_ratio_half_vs_float": st["bytes_per_view_ratio_half_vs_float"],
        "storage_build_bytes_per_view_ratio_half_vs_float": st["build_bytes_per_view_ratio_half_vs_float"],
        "storage_bytes_per_view": {k: sum(v.values()) for k, v in st["bytes_per_view"].items()},
        "storage_loo_psnr_delta_db": st["loo_psnr_delta_db"],
        "storage_relight_rel_err_half_vs_float": st["relight_rel_err_half_vs_float_max"],
    }


def storage_table(st: dict) -> list[str]:
    bpv, b = st["bytes_per_view"], st["build"]
    return [
        "",
        "## Model storage: half against float32 pixels",
        "",
        f"`write_model(storage=...)`, the same data written both ways (`benchmarks/scale.py --storage-only`). "
        f"Relit sphere (relight/synthetic, {st['relight_size']}, {st['relight_lights']} light samples), "
        "disk bytes per view (ZIP-compressed EXR):",
        "",
        "| storage | views B/view | reflectance B/view | total B/view |",
        "|---|---:|---:|---:|",
        *(
            f"| {k} | {v['views']:.0f} | {v['reflectance']:.0f} | {v['views'] + v['reflectance']:.0f} |"
            for k, v in bpv.items()
        ),
        "",
        f"`opacityhull build --storage float|half` of the synthetic session ({b['views']} views, {b['size']}, "
        f"{b['lights']} light directions): {b['float']['disk_bytes_per_view']:.0f} B/view float, "
        f"{b['half']['disk_bytes_per_view']:.0f} B/view half ({st['build_bytes_per_view_ratio_half_vs_float']:.3f}); "
        f"views differ by at most {st['build_views_max_abs_err']:.2e} (premultiplied).",
        "",
        f"Half / float bytes per view: {st['bytes_per_view_ratio_half_vs_float']:.3f}. "
        f"Leave-one-out PSNR of the ULR sphere ({st['loo_size']}, {st['loo_views']} views): "
        f"float {st['loo_psnr_db']['float']:.3f} dB, half {st['loo_psnr_db']['half']:.3f} dB "
        f"(delta {st['loo_psnr_delta_db']:+.4f} dB). Relit error against the exact quadrature, worst view: "
        f"float {st['relight_rel_err_vs_truth_max']['float']:.5f}, half "
        f"{st['relight_rel_err_vs_truth_max']['half']:.5f}; half against float relit "
        f"{st['relight_rel_err_half_vs_float_max']:.2e}. Stored values: views max abs error "
        f"{st['views_max_abs_err']:.2e} (premultiplied, values up to {st.get('views_max_value', 1.0):.3g}), reflectance max relative error "
        f"{st['reflectance_max_rel_err']:.2e} (half's step is 2^-11 = 4.9e-4, rounding half of it).",
    ]


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
    for a, (title, rr) in zip(ax[:2], [("time", "build_s"), ("peak RSS", "peak_rss_mb")], strict=True):
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


PAPER_POINT = (72, 1360, 1032)  # 432 views at the paper's camera resolution


def paper_points(tmp: Path) -> dict:
    """:func:`paper_point` at 48 views, then at 432 (the goal point), and their ratios."""
    n_table, w, h = PAPER_POINT
    small = paper_point(tmp, n_table=8, width=w, height=h)
    big = paper_point(tmp, n_table=n_table, width=w, height=h)
    return {
        **big,
        "views_48": small,
        "peak_rss_ratio_432_vs_48": big["peak_rss_mb"] / small["peak_rss_mb"],
        "render_peak_rss_ratio_432_vs_48": big["render_peak_rss_mb"] / small["render_peak_rss_mb"],
    }


def paper_point(tmp: Path, *, n_table: int, width: int, height: int) -> dict:
    """A build without reflectance at the paper's resolution, the build's defaults
    (``--memory-gb`` at its default, numba on every core), then the renderer's peak RSS
    on the model; wall seconds of the child."""
    row = sweep_point(tmp, n_table=n_table, width=width, height=height, lights=0, render=True, report=True)
    return {**row, "cpu_count": os.cpu_count(), "load_average_1m_after": os.getloadavg()[0]}


def paper_table(row: dict) -> list[str]:
    steps = ", ".join(f"{k} {v:.0f} s" for k, v in row["steps_s"].items() if k != "total" and v >= 0.5)
    plan = row.get("memory_plan", {})
    rows = [r for r in (row.get("views_48"), row) if r]
    return [
        "",
        f"## The goal point: {row['views']} views at {row['width']}x{row['height']}, no reflectance",
        "",
        "`benchmarks/scale.py --paper-only`: the synthetic session written through `SessionWriter`, then "
        "`opacityhull build SESSION --out MODEL --no-pictures --no-reflectance --json` with every default "
        "(numba on both cores, `--memory-gb` its default), wall time of the child; then `opacityhull render MODEL`.",
        "",
        "| views | size | images | session GB | write s | build s | build peak RSS MB | render peak RSS MB | surfels | model GB |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        *(
            f"| {r['views']} | {r['width']}x{r['height']} | {r['images']} | {r['session_bytes'] / 1e9:.1f} | "
            f"{r['write_s']:.0f} | {r['build_s']:.0f} ({r['build_s'] / 60:.1f} min) | {r['peak_rss_mb']:.0f} | "
            f"{r['render_peak_rss_mb']:.0f} | {r['surfels']} | {r['model_bytes'] / 1e9:.2f} |"
            for r in rows
        ),
        "",
        (
            f"432 / 48 views at {row['width']}x{row['height']}: build peak RSS {row['peak_rss_ratio_432_vs_48']:.2f}x, "
            f"render {row['render_peak_rss_ratio_432_vs_48']:.2f}x."
            if "peak_rss_ratio_432_vs_48" in row
            else ""
        ),
        "",
        f"Steps at {row['views']} views: {steps}. Memory plan: {json.dumps({k: plan[k] for k in plan if not isinstance(plan[k], dict)})}. "
        f"Resolution chosen: {(row.get('resolution') or {}).get('reason', '?')}.",
    ]


def table(
    rows: list[dict],
    sched: dict,
    summary: dict,
    quick: bool,
    storage: dict | None = None,
    memory: dict | None = None,
    paper: dict | None = None,
) -> str:
    lines = [
        "# Paper scale (benchmarks/scale.py)",
        "",
        f"Mode: {'quick' if quick else 'full'}. Synthetic analytic session (6 cameras, no Mitsuba), "
        "`opacityhull build --no-pictures` in a child process per point; peak RSS = the child's "
        "`ru_maxrss`. The machine is a shared, loaded 2-core VM: timings are contended, "
        "ratios measured in one run are what to compare.",
        "",
        "| views | size | lights | images | session MB | write s | build s | peak RSS MB | model kB/view | pixels | surfels |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:  # rows measured before `build --storage` existed have no "storage": float32
        lines.append(
            f"| {r['views']} | {r['width']}x{r['height']} | {r['lights']} | {r['images']} | "
            f"{r['session_bytes'] / 1e6:.1f} | {r['write_s']:.1f} | {r['build_s']:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {r['disk_bytes_per_view'] / 1e3:.1f} | {r.get('storage', 'float')} | "
            f"{r['surfels']} |"
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
    if paper:
        lines += paper_table(paper)
    if memory:
        lines += memory_table(memory, summary)
    if storage:
        lines += storage_table(storage)
    lines += ["", "Summary: `" + json.dumps(summary) + "`", ""]
    return "\n".join(lines)


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="the small sweep (a few minutes)")
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ap.add_argument("--tmp", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument(
        "--storage-only",
        action="store_true",
        help="only the half/float model storage comparison, merged into the existing scale.json/md",
    )
    ap.add_argument(
        "--memory-only",
        action="store_true",
        help="only the peak RSS against views at 320x240 (build and renderer), merged into the existing scale.json/md",
    )
    ap.add_argument(
        "--paper-only",
        action="store_true",
        help="only the 48- and 432-view 1360x1032 builds (~35 GB of scratch), merged into the existing scale.json/md",
    )
    ap.add_argument("--compare-label", default=None, help="what the --compare-pythonpath copy is (for the table)")
    ap.add_argument(
        "--compare-pythonpath",
        default=None,
        help="with the memory sweep: also run each point with this package copy first on PYTHONPATH",
    )
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="oh-scale-"))
    tmp.mkdir(parents=True, exist_ok=True)
    if args.memory_only or args.storage_only or args.paper_only:
        # one part measured anew, merged into the earlier scale.json/md
        try:
            if args.paper_only:
                part, made = "paper", paper_points(tmp)
            elif args.memory_only:
                part, made = (
                    "memory",
                    memory_sweep(tmp, compare_pythonpath=args.compare_pythonpath, compare_label=args.compare_label),
                )
            else:
                part, made = "storage", storage_comparison(tmp, quick=args.quick)
        finally:
            if args.tmp is None:
                shutil.rmtree(tmp, ignore_errors=True)
        prev = json.loads((OUT / "scale.json").read_text()) if (OUT / "scale.json").is_file() else {}
        kept = prev.get("summary", {})
        if part == "memory":  # a new memory part replaces the old one's comparison too
            kept = {k: v for k, v in kept.items() if not k.endswith("_compare")}
            prev = {k: v for k, v in prev.items() if not k.endswith("_compare")}
        if part == "paper":
            summary = {
                **kept,
                "paper_432_views_1360x1032_build_s": made["build_s"],
                "paper_432_views_1360x1032_peak_rss_mb": made["peak_rss_mb"],
                "paper_432_views_1360x1032_render_peak_rss_mb": made["render_peak_rss_mb"],
                "peak_rss_ratio_432_vs_48_at_1360x1032": made["peak_rss_ratio_432_vs_48"],
            }
        else:
            summary = {**kept, **(_memory_summary if part == "memory" else _storage_summary)(made)}
        res = {**prev, "summary": summary, **summary, part: made}
        (OUT / "scale.json").write_text(json.dumps(res, indent=1))
        text = table(
            prev.get("rows", []),
            prev.get("schedulers", {}),
            summary,
            summary.get("quick", True),
            res.get("storage"),
            res.get("memory"),
            res.get("paper"),
        )
        (OUT / "scale.md").write_text(text)
        print(json.dumps(res) if args.json else text)
        return
    small = (64, 48)
    points = [(8, *small, 0), (24, *small, 0), (72, *small, 0), (8, *small, 24)]
    # per-view tasks must cost well above the cluster's few ms per task to show scaling
    sched_pt = (8, 640, 480)  # 48 views; at 320x240 a view is 17 ms, 4x the cluster's cost per task
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
        # the children's peak RSS first: a child's ru_maxrss includes this process's RSS
        # at fork, which the in-process scheduler comparison (640x480 views) raises
        memory = memory_sweep(tmp, compare_pythonpath=args.compare_pythonpath, compare_label=args.compare_label)
        storage = storage_comparison(tmp, quick=args.quick)
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
        **_storage_summary(storage),
        **_memory_summary(memory),
    }
    if not args.quick:
        big = (200, 150)
        summary["peak_rss_ratio_432_vs_48_at_200x150"] = pick(432, big)["peak_rss_mb"] / pick(48, big)["peak_rss_mb"]
        summary["peak_rss_above_baseline_ratio_432_vs_48_at_200x150"] = (pick(432, big)["peak_rss_mb"] - base_mb) / max(
            pick(48, big)["peak_rss_mb"] - base_mb, 1.0
        )
    prev = json.loads((OUT / "scale.json").read_text()) if (OUT / "scale.json").is_file() else {}
    paper = prev.get("paper")  # measured on its own (--paper-only): kept
    res = {"summary": summary, **summary, "rows": rows, "schedulers": sched, "storage": storage, "memory": memory}
    if paper:
        res["paper"] = paper
    (OUT / "scale.json").write_text(json.dumps(res, indent=1))
    (OUT / "scale.md").write_text(table(rows, sched, summary, args.quick, storage, memory, paper))
    plot(rows, sched, OUT / "scale.png", base_mb)
    if args.json:
        print(json.dumps(res))
    else:
        print(table(rows, sched, summary, args.quick, storage, memory))


if __name__ == "__main__":
    main()
