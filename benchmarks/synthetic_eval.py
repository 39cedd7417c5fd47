"""The first goal of issue 29 measured on the Mitsuba-rendered synthetic set
(``benchmarks/synthetic_set.py``: a detailed toy bulldozer, 100 RGBA views of 400×400 on
the hemisphere): every 10th view held out, PSNR / SSIM over the whole image on white
(the NeRF papers' protocol) and over the mask union, and the build time per step.

    .venv/bin/python benchmarks/synthetic_eval.py [--quick] [--modes none,fast,full] [--work DIR] [--redraw] [--json]

Per mode it runs the user's commands (the CLI, in a subprocess, so the times are a
build's own):

    opacityhull import nerfstudio --transforms SET/transforms.json --out WORK/session
    opacityhull build WORK/session --out WORK/model_MODE --hold-out every:10 [--optimize MODE] --no-pictures
    opacityhull eval test WORK/model_MODE --background white --json

Each mode is passed as ``--optimize MODE`` (``none``: no fit; ``fast`` is the default
build). ``--append`` keeps the rows of modes not run from the previous ``synthetic.json``
(so one mode can be re-measured alone). The set is rendered
first when missing (``--quick``: the 24-view 160×160 version, ``--modes none``). Writes
``benchmarks/out/synthetic.md``, ``synthetic.json`` and ``synthetic_sheet.png`` (three
held-out views on white: ground truth, each mode's render, the error). The goal: ≥ 30 dB on white with a build of ≤ 15 min on 2 cores. Figures taken
while other jobs share the two cores are slow by that load.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from collections.abc import Sequence

import numpy as np
from benchkit import out_dir, parser, print_result, report_head

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
GOAL_DB, GOAL_MIN = 30.0, 15.0
_CLI = "import sys; from opacityhull.cli import main; sys.exit(main())"


def cli(*args: str, log=True) -> dict:
    """Run ``opacityhull ARGS --json`` in a subprocess (this interpreter, this checkout
    first on the path); the printed JSON object, plus ``wall_s``."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-c", _CLI, *args, "--json"],
        stdout=subprocess.PIPE,
        stderr=None if log else subprocess.DEVNULL,
        text=True,
        env=env,
    )
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"opacityhull {' '.join(args)} exited {r.returncode}")
    lines = [ln for ln in r.stdout.splitlines() if ln.strip().startswith("{")]
    out = json.loads(lines[-1]) if lines else {}
    out["wall_s"] = wall
    return out


def build_and_test(
    session: Path, model: Path, *, hold_out: str, extra: tuple[str, ...] = (), backgrounds=("white",)
) -> dict:
    """``build SESSION --out MODEL --hold-out HOLD_OUT EXTRA`` then ``eval test`` per
    background: ``{"build": build summary, "white": eval summary, ...}``."""
    if model.exists():
        shutil.rmtree(model)
    b = cli("build", str(session), "--out", str(model), "--hold-out", hold_out, "--no-pictures", *extra)
    res = {"build": b}
    for bg in backgrounds:
        out = model / "eval" / f"test_{bg}"
        res[bg] = cli("eval", "test", str(model), "--background", bg, "--out", str(out))
    return res


def _row(mode: str, r: dict) -> dict:
    b, w = r["build"], r["white"]
    secs = b.get("seconds", {})
    opt = b.get("optimize", {}) or {}
    return {
        "mode": mode,
        "psnr_white": w["psnr_mean"],
        "ssim_white": w["ssim_mean"],
        "psnr_mask": w["psnr_mask_mean"],
        "ssim_mask": w["ssim_mask_mean"],
        "coverage_iou": w["coverage_iou_mean"],
        "alpha_mae": w["alpha_mae"],
        "renderer": w.get("renderer"),
        "build_s": b["wall_s"],
        "steps_s": {k: round(float(v), 1) for k, v in secs.items()},
        "iterations": opt.get("iterations"),
        "surfels_end": opt.get("n_surfels_end"),
        "surfels": b.get("surfels"),
        "carve_tolerance": b.get("carve_tolerance"),
        "train_views": w.get("train_views"),
        "test_views": len(w.get("views", [])),
        "per_view_white": [round(p["psnr"], 2) for p in w["per_view"]],
        "sheet": w.get("sheet"),
    }


def _test_render(model_dir: Path, i: int) -> np.ndarray:
    """Held-out view ``i`` of a model as ``eval test --renderer auto`` renders it
    (straight linear RGBA)."""
    from opacityhull.evaluate.heldout import fitted_state
    from opacityhull.model import OpacityHullModel
    from opacityhull.render.renderer import RenderConfig, model_surfels, prepare_model_views, render_image

    m = OpacityHullModel.open(model_dir)
    cams = [v.camera for v in m.views]
    if fitted_state(model_dir) == "fitted":
        from opacityhull.optimize.fit import load_fitted, render_params

        return render_params(load_fitted(model_dir), cams[i])
    pv = prepare_model_views(m)
    return render_image(model_surfels(m), cams, pv, cams[i], config=RenderConfig()).rgba


def write_sheet(work: Path, modes: Sequence[str], path: Path) -> Path:
    """The first, middle and last test views (rows) on white: ground truth | each mode's render | |error| ×4 of the
    last mode, cropped to the object, at full resolution (a PNG)."""
    import cv2

    from opacityhull.imageio import srgb_encode, write_png
    from opacityhull.model import OpacityHullModel

    def on_white(rgba):
        a = np.clip(np.nan_to_num(rgba[..., 3:4]), 0, 1)
        return srgb_encode(np.clip(np.nan_to_num(rgba[..., :3]), 0, 1) * a + (1 - a))

    from opacityhull.evaluate.heldout import held_out_views

    crops_per_row = []
    first = OpacityHullModel.open(work / f"model_{modes[0]}")
    hv = held_out_views(first)
    for i in sorted({hv[0], hv[len(hv) // 2], hv[-1]}):
        gt = first.load_view_rgba(i)
        tiles = [on_white(gt)] + [on_white(_test_render(work / f"model_{m}", i)) for m in modes]
        err = np.clip(4 * np.abs(tiles[-1] - tiles[0]).mean(axis=2, keepdims=True), 0, 1)
        tiles.append(np.repeat(1 - err, 3, axis=2))
        ys, xs = np.nonzero(gt[..., 3] > 0.01)
        pad = 6
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, gt.shape[0])
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, gt.shape[1])
        crops_per_row.append([t[y0:y1, x0:x1] for t in tiles])
    tile_w = max(c[0].shape[1] for c in crops_per_row) + 4
    rows = []
    for crops in crops_per_row:
        row = np.concatenate(
            [np.pad(c, ((0, 4), (0, tile_w - c.shape[1]), (0, 0)), constant_values=1.0) for c in crops], axis=1
        )
        rows.append(row)
    img = np.concatenate(rows, axis=0)
    head = np.full((22, img.shape[1], 3), 255, np.uint8)
    names = ["ground truth"] + [("no fit" if m == "none" else m) for m in modes] + [f"|err| x4 ({modes[-1]})"]
    for k, name in enumerate(names):
        cv2.putText(head, name, (4 + k * tile_w, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    # the image is sRGB-encoded already: write it as data
    write_png(path, np.concatenate([head.astype(np.float32) / 255, img], axis=0), linear=True)
    return path


def error_budget(work: Path, mode: str, *, band_px: int = 2) -> dict:
    """Where the held-out error on white is: the share of the squared error (sRGB, every
    test view) within ``band_px`` px of the true silhouette's outline, that band's share of
    the pixels, and the PSNR the views would have with the band's error removed."""
    import cv2

    from opacityhull.evaluate.heldout import held_out_views
    from opacityhull.imageio import srgb_encode
    from opacityhull.model import OpacityHullModel

    def on_white(rgba):
        a = np.clip(np.nan_to_num(rgba[..., 3:4]), 0, 1)
        return srgb_encode(np.clip(np.nan_to_num(rgba[..., :3]), 0, 1) * a + (1 - a))

    m = OpacityHullModel.open(work / f"model_{mode}")
    k = np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8)
    sse_band = sse_all = 0.0
    n_band = n_all = 0
    for i in held_out_views(m):
        gt = m.load_view_rgba(i)
        err = ((on_white(_test_render(work / f"model_{mode}", i)) - on_white(gt)) ** 2).mean(axis=2)
        sil = (np.nan_to_num(gt[..., 3]) > 0.5).astype(np.uint8)
        band = (cv2.dilate(sil, k) - cv2.erode(sil, k)) > 0
        sse_band += float(err[band].sum())
        sse_all += float(err.sum())
        n_band += int(band.sum())
        n_all += err.size
    rest = (sse_all - sse_band) / n_all
    return {
        "band_px": band_px,
        "edge_error_share": sse_band / sse_all,
        "edge_pixel_share": n_band / n_all,
        "psnr_without_edge_error": float(10 * np.log10(1.0 / rest)) if rest > 0 else float("inf"),
    }


def write_report(res: dict, *, quick: bool) -> Path:
    from synthetic_set import HOLD_OUT_EVERY

    info, rows = res["set"], res["rows"]
    lines = report_head(
        "Synthetic set: held-out PSNR of the default build (issue 29, first goal)",
        f"Set: `benchmarks/synthetic_set.py{' --quick' if quick else ''}` — {info['views']} RGBA views of "
        f"{info['size_px']}×{info['size_px']} ({info['spp']} spp, Mitsuba `{info['variant']}`, {info['parts']} meshes, "
        f"{info['triangles']} triangles, rendered in {info['seconds']:.0f} s). Every {HOLD_OUT_EVERY}th view held out "
        f"({rows[0]['test_views'] if rows else '?'} test views, {rows[0]['train_views'] if rows else '?'} to build from).",
        "Commands: `benchmarks/synthetic_eval.py --modes none,fast,full`, which runs `opacityhull import nerfstudio "
        "--transforms SET/transforms.json --out S`; `opacityhull build S "
        f"--out M --hold-out every:{HOLD_OUT_EVERY} --no-pictures [--optimize MODE]`; `opacityhull eval test M "
        "--background white --json`. Times are wall seconds of the build subprocess (NUMBA_NUM_THREADS=1) on 2 cores "
        "shared with other jobs (slow by that load); `steps` are report.json's seconds per step.",
        f"Goal: ≥ {GOAL_DB:.0f} dB on white over the whole image, build ≤ {GOAL_MIN:.0f} min.",
    )
    lines += [
        "| build | renderer | PSNR white (dB) | SSIM white | PSNR mask (dB) | SSIM mask | coverage IoU | alpha MAE "
        "| build (min) | iterations | surfels (end) | edge error share | PSNR w/o edge error |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        eb = r.get("error_budget") or {}
        lines.append(
            f"| --optimize {r['mode']}{' (default)' if r['mode'] == 'fast' else ''} | {r['renderer']} "
            f"| {r['psnr_white']:.2f} | {r['ssim_white']:.3f} | {r['psnr_mask']:.2f} | {r['ssim_mask']:.3f} "
            f"| {r['coverage_iou']:.3f} | {r['alpha_mae']:.4f} | {r['build_s'] / 60:.1f} | {r.get('iterations') or 0} "
            f"| {r.get('surfels_end') or r['surfels']} "
            f"| {eb.get('edge_error_share', float('nan')):.2f} | {eb.get('psnr_without_edge_error', float('nan')):.2f} |"
        )
    eb0 = (rows[0].get("error_budget") or {}) if rows else {}
    lines += [
        "",
        f"Edge error share: the share of the squared error (whole image on white, all test views) within "
        f"{eb0.get('band_px', 2)} px of the true silhouette's outline, a band of "
        f"{100 * eb0.get('edge_pixel_share', float('nan')):.1f} % of the pixels; `PSNR w/o edge error` is what the views "
        f"would score with that band's error removed. Carve tolerance {rows[0]['carve_tolerance'] if rows else '?'} "
        f"(the default for {rows[0]['train_views'] if rows else '?'} imported views).",
        "",
    ]
    for r in rows:
        steps = ", ".join(f"{k} {v:.0f} s" for k, v in sorted(r["steps_s"].items(), key=lambda kv: -kv[1]) if v >= 1)
        lines.append(f"- {r['mode']}: steps {steps}; per test view (white) {r['per_view_white']}")
    lines += [
        "",
        "![test views](synthetic_sheet.png) `synthetic_sheet.png`: the first, middle and last test views "
        "on white — ground truth, each build's render, the last one's error ×4 (eval test's own sheets of every test view "
        "with the alpha error are in WORK/model_MODE/eval/test_white/).",
        "",
    ]
    report = OUT / "synthetic.md"
    report.write_text("\n".join(lines) + "\n")
    return report


def analyse(res: dict, work: Path) -> None:
    """Add the error budget to each row and draw the sheet (renders the test views again)."""
    for r in res["rows"]:
        r["error_budget"] = error_budget(work, r["mode"])
        rep = work / f"model_{r['mode']}" / "report.json"
        if r.get("surfels_end") is None and rep.is_file():
            r["surfels_end"] = (json.loads(rep.read_text()).get("optimize") or {}).get("n_surfels_end")
    res["sheet"] = str(write_sheet(work, [r["mode"] for r in res["rows"]], OUT / "synthetic_sheet.png"))


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="the 24-view 160x160 set, default build only")
    ap.add_argument("--modes", default=None, help="comma list of none, fast, full (default none,fast; quick: none)")
    ap.add_argument("--work", type=Path, help="keep the session and models here (default: a folder under OUT)")
    ap.add_argument(
        "--redraw",
        action="store_true",
        help="only redo the sheet, error budget and report from synthetic.json and --work",
    )
    ap.add_argument("--append", action="store_true", help="keep the previous rows of modes not run")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from synthetic_set import HOLD_OUT_EVERY, ensure_set

    modes = (a.modes or ("none" if a.quick else "none,fast")).split(",")
    work = a.work or OUT / "synthetic_work"
    if a.redraw:
        res = json.loads((OUT / "synthetic.json").read_text())
    else:
        transforms = ensure_set(a.quick, log=lambda *x, **k: print(*x, file=sys.stderr))
        info = json.loads((transforms.parent / "synthetic_set.json").read_text())
        work.mkdir(parents=True, exist_ok=True)
        session = work / "session"
        if session.exists():
            shutil.rmtree(session)
        imp = cli("import", "nerfstudio", "--transforms", str(transforms), "--out", str(session))
        rows = []
        for mode in modes:
            extra = ("--optimize", mode)
            r = build_and_test(session, work / f"model_{mode}", hold_out=f"every:{HOLD_OUT_EVERY}", extra=extra)
            row = _row(mode, r)
            rows.append(row)
            print(f"{mode}: {row['psnr_white']:.2f} dB white, {row['build_s']:.0f} s", file=sys.stderr)
        if a.append and (OUT / "synthetic.json").is_file():
            kept = [r for r in json.loads((OUT / "synthetic.json").read_text())["rows"] if r["mode"] not in modes]
            order = {"none": 0, "fast": 1, "full": 2}
            rows = sorted(kept + rows, key=lambda r: order.get(r["mode"], 3))
        res = {"set": info, "import_s": imp["wall_s"], "hold_out": f"every:{HOLD_OUT_EVERY}", "rows": rows}
    OUT.mkdir(parents=True, exist_ok=True)
    analyse(res, work)
    (OUT / "synthetic.json").write_text(json.dumps(res, indent=1))
    report = write_report(res, quick=a.quick)
    print_result(res, report, as_json=a.json)
    return res


if __name__ == "__main__":
    main()
