"""Matting shot cost on the simulated rig: the declared matting selection against the
2026-12-01 one, per built-in scene and camera size, on an otherwise idle machine.

One pair = the backdrop shot and the object shot of one display pattern, as a capture
takes them (the object shot's outside pixels come from the backdrop shot). 'before' =
the selection of 2026-12-01: the whole frame at 64 spp, backdrops at 64 spp. 'selected'
= what a declared matting shot of a camera of that size gets now
(``select_effects(pixels=...)``: crop, per-size candidate table). Warm (two pairs of
each first), then ``--rounds`` rounds alternating the two; CPU seconds of this process
(all Mitsuba threads), median. The errors behind the selection are in
``benchmarks/out/sim_matting_candidates.json`` (``sim_effects.py --matting-candidates``).

    .venv/bin/python benchmarks/sim_matting_pairs.py [--scales 1,2] [--rounds 4] [--json]

Writes ``benchmarks/out/sim_matting_pairs.md`` and ``.json``.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace

import numpy as np
from benchkit import out_dir, parser, print_result

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
SCENES = ("diffuse", "sphere", "glass", "glossy", "fuzzy")


def measure(scales, rounds: int) -> list[dict]:
    from opacityhull.sim.effects import select_effects
    from opacityhull.sim.groundtruth import default_geometry
    from opacityhull.sim.render import SimRenderer, SimState
    from opacityhull.sim.scenes import load_scene

    g = default_geometry()
    rng = np.random.default_rng(1)
    rows = []
    for scale in scales:
        cam = g.nominal_cameras()[2]
        cam = cam if scale == 1 else cam.scaled(scale)
        for name in SCENES:
            sc = load_scene(f"builtin:{name}")
            r = SimRenderer(sc, g)
            base = select_effects(sc, "matting", declared=False)
            cands = {
                "before": replace(base, spp=64, crop=False, backdrop_spp=None),
                "selected": select_effects(sc, "matting", pixels=cam.width * cam.height),
            }

            def pair(cfg, seed, *, r=r, cam=cam):  # this iteration's renderer and camera, bound here
                pat = {
                    d.name: rng.integers(0, 256, (d.resolution[1], d.resolution[0], 3), np.uint8) for d in g.displays
                }
                r.clear_radiance_cache()
                c0 = time.process_time()
                r.render(cam, SimState(table_deg=20.0, displays=pat, content="none"), effects=cfg, seed=seed)
                r.render(cam, SimState(table_deg=20.0, displays=pat), effects=cfg, seed=seed + 1)
                return time.process_time() - c0

            for c in cands.values():  # warm: JIT compilation out of the timings
                pair(c, 1)
                pair(c, 2)
            secs: dict = {k: [] for k in cands}
            for rd in range(rounds):
                for k, c in cands.items():
                    secs[k].append(pair(c, 10 + 2 * rd))
            t = {k: float(np.median(v)) for k, v in secs.items()}
            sel = cands["selected"]
            rows.append(
                {
                    "scene": name,
                    "width": cam.width,
                    "height": cam.height,
                    "selected": f"{sel.integrator} d{sel.max_depth} {sel.spp} spp crop",
                    "before_s": t["before"],
                    "selected_s": t["selected"],
                    "speedup": t["before"] / max(t["selected"], 1e-9),
                }
            )
            print(
                f"{name:8s} {cam.width}x{cam.height} {rows[-1]['selected']:24s} pair {t['selected']:.3f}s "
                f"before {t['before']:.3f}s x{rows[-1]['speedup']:.2f}",
                file=sys.stderr,
                flush=True,
            )
    return rows


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--scales", default="1,2", help="camera scales of the default rig (1 = 200x150)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    a = ap.parse_args()
    rows = measure(tuple(float(s) for s in a.scales.split(",")), a.rounds)
    L = [
        "# Matting shot pairs: declared selection vs 2026-12-01",
        "",
        "`benchmarks/sim_matting_pairs.py`: backdrop + object shot of one pattern, camera 2 of the default "
        "rig, table 20 deg; median CPU seconds over alternating rounds after warm-up; 'before' = whole "
        "frame, 64 spp, backdrops at 64 spp.",
        "",
        "| scene | size | selected | pair (s) | before (s) | speed-up |",
        "|---|---|---|---:|---:|---:|",
    ]
    L += [
        f"| {r['scene']} | {r['width']}x{r['height']} | {r['selected']} | {r['selected_s']:.3f} | "
        f"{r['before_s']:.3f} | {r['speedup']:.2f}x |"
        for r in rows
    ]
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "sim_matting_pairs.md").write_text("\n".join(L) + "\n")
    res = {"rows": rows, "min_speedup": min(r["speedup"] for r in rows)}
    (OUT / "sim_matting_pairs.json").write_text(json.dumps(res, indent=1))
    print_result(res, OUT / "sim_matting_pairs.md", as_json=a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
