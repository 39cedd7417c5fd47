"""Point lights against lamps with area (#30): how much a diffuse or glossy one-light
image changes when the light array's point lights become spheres of the same intensity,
measured against the Monte-Carlo noise of the render itself; and what a glass shows.

    .venv/bin/python benchmarks/sim_lamps.py [--scale 0.5] [--radius-m 0.025] [--quick]

The built-in rig's lamps are points; ``--radius-m`` gives them the radius measured
(2.5 cm by default). Per scene and view (one light on, reflectance selection, crop on): ``change`` =
‖area − point‖ / ‖point‖ over the frame, ``noise`` = ‖area(seed a) − area(seed b)‖ /
‖point‖ / √2 (one render's noise), and ``change / noise``. Writes
benchmarks/out/sim_lamps.json. Figures taken on a shared, loaded machine are CPU times
only in the "seconds" fields; the ratios do not depend on load.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace

import numpy as np
from benchkit import out_dir, parser

from opacityhull.riggeometry import RigGeometry
from opacityhull.sim.evaluate import lamp_change, point_geometry
from opacityhull.sim.render import SimRenderer, SimState
from opacityhull.sim.scenes import load_scene
from opacityhull.sim.simrig import sim_rig_config

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)


def compare(
    scene_name: str, *, scale: float = 0.5, radius_m: float = 0.025, views=((1, 80.0, 1), (3, 200.0, 2))
) -> list[dict]:
    g = RigGeometry.from_dict(sim_rig_config(None, scale=scale)["geometry"])
    g = replace(g, lights=tuple(replace(L, radius_m=radius_m) for L in g.lights))
    scene = load_scene(f"builtin:{scene_name}")
    area = SimRenderer(scene, g)
    point = SimRenderer(scene, point_geometry(g))
    rows = []
    for cam_i, table, lid in views:
        cam = g.nominal_cameras()[cam_i]
        st = SimState(table_deg=table, light_levels={lid: 255})
        t0 = time.perf_counter()
        p = point.render(cam, st, seed=1, use_cache=False)
        t1 = time.perf_counter()
        p2 = point.render(cam, st, seed=3, use_cache=False)
        a1 = area.render(cam, st, seed=1, use_cache=False)
        t2 = time.perf_counter()
        a2 = area.render(cam, st, seed=2, use_cache=False)
        n = float(np.linalg.norm(p))
        rows.append(
            {
                "scene": scene_name,
                "camera": cam_i,
                "table_deg": table,
                "light": lid,
                "point_norm": n,
                "area_norm": float(np.linalg.norm(a1)),
                **lamp_change(p, p2, a1, a2),
                "area_mean": float(a1.mean()),
                "area_lit_pixels": int((a1.max(axis=2) > 0).sum()),
                "mean_ratio": float(a1.mean() / p.mean()) if p.mean() > 0 else float("nan"),
                "seconds_point": t1 - t0,
                "seconds_area": t2 - t1,
            }
        )
        r = rows[-1]
        print(
            f"{scene_name:8s} cam{cam_i} t{table:5.1f} L{lid}: change {r['change']:.4f} noise floor "
            f"{r['noise_floor']:.4f} excess {r['excess']:.4f} mean ratio {r['mean_ratio']:.4f} area mean "
            f"{r['area_mean']:.4g} lit px {r['area_lit_pixels']} ({r['seconds_point']:.2f} s / {r['seconds_area']:.2f} s)",
            flush=True,
        )
    return rows


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--radius-m", type=float, default=0.025)
    ap.add_argument("--scenes", default="diffuse,glossy,glass")
    ap.add_argument("--quick", action="store_true", help="quarter scale, the diffuse scene only")
    args = ap.parse_args()
    scale, scenes = (0.25, "diffuse") if args.quick else (args.scale, args.scenes)
    rows = []
    for s in scenes.split(","):
        rows += compare(s, scale=scale, radius_m=args.radius_m)
    out = OUT / "sim_lamps.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"scale": scale, "radius_m": args.radius_m, "rows": rows}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
