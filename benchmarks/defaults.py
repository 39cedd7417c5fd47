"""Defaults that generalise (issue 29, item 6): held-out PSNR of the carve-tolerance
default against fixed tolerances, on every set the project can score under a train/test
split.

    .venv/bin/python benchmarks/defaults.py [--quick] [--sets temple,dino,synthetic] [--tolerances 0,1,2] [--json]

The rule under test (``build.default_carve_tolerance``) grows the tolerance of imported
image sets with their view count (0 under 8 views, 1 from 8, 2 from 16; rig sessions 0).
Each set is built with ``--carve-tolerance T`` for each ``T`` and once with the default
(the rule), every view of the split held out (``build --hold-out every:N``), and scored
by ``eval test`` (white background):

* ``temple``, ``dino``: the Middlebury rings (``tests/data/real``), ``import colmap``
  with their masks, every 4th view held out (12 views to build from: the rule gives 1);
  the figure of merit is the mask-union PSNR (``eval loo``'s metric);
* ``synthetic``: ``benchmarks/synthetic_set.py`` (100 RGBA views of 400×400, true
  alpha), ``import nerfstudio``, every 10th view held out (90 views: the rule gives 2);
  figure of merit the whole image on white (the NeRF protocol), mask union beside it;
* ``demo`` (``--sets ...,demo``): the simulated diffuse cup, captured with
  ``capture --rig sim:builtin:diffuse?scale=2 --plan tests/render/data/demo_views.toml``
  (48 views; minutes), built with ``--cameras groundtruth``, every 8th view held out; a
  rig session, so the rule gives 0; merit the mask union.

A rule tolerance equal to a measured fixed one is not built twice. ``--quick``: the
24-view synthetic set only. Rows of sets not named by ``--sets`` are kept from the last
``defaults.json``. Writes ``benchmarks/out/defaults.md`` and
``defaults.json``. Builds run as CLI subprocesses (``synthetic_eval.cli``) with the
default options otherwise (``--optimize none``, ``--no-pictures``).
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from benchkit import out_dir, parser, print_result, report_head

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
DATA = ROOT / "tests" / "data" / "real"
EVERY = {"temple": 4, "dino": 4, "synthetic": 10, "demo": 8}
#: the figure of merit per set: the key of eval test's summary
MERIT = {"temple": "psnr_mask_mean", "dino": "psnr_mask_mean", "synthetic": "psnr_mean", "demo": "psnr_mask_mean"}
#: the simulated demo scene: the diffuse cup under the demo plan's 48 views (as benchmarks/optimize.py)
DEMO_RIG = "sim:builtin:diffuse?scale=2"
DEMO_PLAN = ROOT / "tests" / "render" / "data" / "demo_views.toml"
#: per set, build options besides the split and the tolerance
EXTRA = {"demo": ("--cameras", "groundtruth")}


def import_set(name: str, session: Path, *, quick: bool, demo_session: Path | None = None) -> Path:
    """The session of a set: imported (the rings, the synthetic set) or captured on the
    simulated rig (``demo``; ``demo_session`` reuses an earlier capture)."""
    from synthetic_eval import cli
    from synthetic_set import ensure_set

    if name == "demo" and demo_session is not None:
        return demo_session
    if session.exists():
        shutil.rmtree(session)
    if name == "demo":
        cli("capture", "--rig", DEMO_RIG, "--plan", str(DEMO_PLAN), "--out", str(session))
    elif name == "synthetic":
        t = ensure_set(quick, log=lambda *x, **k: print(*x, file=sys.stderr))
        cli("import", "nerfstudio", "--transforms", str(t), "--out", str(session))
    else:
        src = DATA / f"{name}SR"
        cli(
            "import",
            "colmap",
            "--model",
            str(src / "sparse"),
            "--images",
            str(src / "images"),
            "--masks",
            str(src / "masks"),
            "--out",
            str(session),
        )
    return session


def measure_set(
    name: str, work: Path, tolerances: list[int], *, quick: bool, demo_session: Path | None = None
) -> list[dict]:
    """Rows ``{"set", "tolerance", "rule", "psnr_white", "psnr_mask", ...}``: the rule's
    build first, then each fixed tolerance it did not already give."""
    from synthetic_eval import build_and_test

    session = import_set(name, work / f"{name}_session", quick=quick, demo_session=demo_session)
    hold = f"every:{EVERY[name]}"
    rows = []

    def run(tol: int | None) -> dict:
        extra = EXTRA.get(name, ()) + (() if tol is None else ("--carve-tolerance", str(tol)))
        r = build_and_test(session, work / f"{name}_model", hold_out=hold, extra=extra)
        b, w = r["build"], r["white"]
        row = {
            "set": name,
            "hold_out": hold,
            "tolerance": int(b["carve_tolerance"]),
            "rule": tol is None,
            "psnr_white": w["psnr_mean"],
            "ssim_white": w["ssim_mean"],
            "psnr_mask": w["psnr_mask_mean"],
            "ssim_mask": w["ssim_mask_mean"],
            "coverage_iou": w["coverage_iou_mean"],
            "merit": w[MERIT[name]],
            "build_s": b["wall_s"],
            "train_views": w["train_views"],
        }
        print(
            f"{name} tol {row['tolerance']}{' (rule)' if tol is None else ''}: {row['merit']:.2f} dB", file=sys.stderr
        )
        return row

    rule = run(None)
    rows.append(rule)
    for t in tolerances:
        if t == rule["tolerance"]:
            continue
        rows.append(run(t))
    shutil.rmtree(work / f"{name}_model", ignore_errors=True)
    return sorted(rows, key=lambda r: (r["tolerance"], not r["rule"]))


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="the 24-view synthetic set only")
    ap.add_argument(
        "--sets",
        default=None,
        help="comma list of temple, dino, synthetic, demo (default the first three; quick: synthetic)",
    )
    ap.add_argument("--demo-session", type=Path, help="a captured demo session to reuse (else demo captures one)")
    ap.add_argument("--tolerances", default="0,1,2")
    ap.add_argument("--work", type=Path, help="scratch folder (default OUT/defaults_work)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    sets = (a.sets or ("synthetic" if a.quick else "temple,dino,synthetic")).split(",")
    tolerances = [int(t) for t in a.tolerances.split(",")]
    work = a.work or OUT / "defaults_work"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in sets:
        rows += measure_set(name, work, tolerances, quick=a.quick, demo_session=a.demo_session)
    prev = OUT / "defaults.json"
    if prev.is_file():  # keep the rows of the sets not measured this time (e.g. --sets demo)
        rows = [r for r in json.loads(prev.read_text())["rows"] if r["set"] not in sets] + rows
    res: dict = {"rows": rows, "best": {}}
    for name in dict.fromkeys(r["set"] for r in rows):
        mine = [r for r in rows if r["set"] == name]
        best = max(mine, key=lambda r: r["merit"])
        rule = next(r for r in mine if r["rule"])
        res["best"][name] = {
            "tolerance": best["tolerance"],
            "merit": best["merit"],
            "rule_loses_db": best["merit"] - rule["merit"],
        }
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "defaults.json").write_text(json.dumps(res, indent=1))
    lines = report_head(
        "Defaults that generalise: the carve tolerance (issue 29, item 6)",
        "Held-out PSNR (`eval test`, white background) per set and carve tolerance; `rule` is the default "
        "(`build.default_carve_tolerance`: imported sets 0 under 8 views, 1 from 8, 2 from 16; rig sessions 0). "
        "Merit: mask-union PSNR on the real rings (every 4th view held out, 12 to build from) and the simulated "
        "demo cup (rig capture, every 8th held out, `--cameras groundtruth`), whole image on white on the "
        "synthetic set (every 10th held out). Commands: `benchmarks/defaults.py"
        f"{' --quick' if a.quick else ''} [--sets demo]` (import colmap / import nerfstudio / capture, then "
        "`build --hold-out every:N [--carve-tolerance T] --no-pictures` and `eval test --background white`). "
        "Build times under load (2 cores shared with other jobs, NUMBA_NUM_THREADS=1).",
    )
    lines += [
        "| set | split | tolerance | PSNR mask (dB) | SSIM mask | PSNR white (dB) | SSIM white | coverage IoU | build (s) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        tol = f"{r['tolerance']} (rule)" if r["rule"] else str(r["tolerance"])
        lines.append(
            f"| {r['set']} | {r['hold_out']} ({r['train_views']} train) | {tol} | {r['psnr_mask']:.2f} | "
            f"{r['ssim_mask']:.3f} | {r['psnr_white']:.2f} | {r['ssim_white']:.3f} | {r['coverage_iou']:.3f} | "
            f"{r['build_s']:.0f} |"
        )
    lines.append("")
    for name, b in res["best"].items():
        lines.append(
            f"- {name}: best tolerance {b['tolerance']} ({b['merit']:.2f} dB); the rule is {b['rule_loses_db']:.2f} dB below it"
        )
    lines.append("")
    report = OUT / "defaults.md"
    report.write_text("\n".join(lines) + "\n")
    print_result(res, report, as_json=a.json)
    return res


if __name__ == "__main__":
    main()
