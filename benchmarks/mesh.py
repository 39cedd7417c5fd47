"""Mesh export (PMR umbrella mesh, Dey & Hudson 2002) against scikit-image's marching cubes.

For each model — the analytic sphere (20 k surfels) always, plus ``--models`` folders — the
umbrella mesh of the surfels (``opacityhull.render.pmr``, what ``export --format mesh``
writes) and marching cubes of the surfels' signed distance (``export.mesh.marching_cubes_mesh``,
grid = the surfel spacing) are scored on the same metric (``pmr.mesh_quality``): manifold
edges, boundary loops (holes), non-manifold edges, and the Chamfer distance to the surfels
in units of the surfel spacing ("voxel"; the hull's surfels are one per surface voxel),
plus build time. Writes ``benchmarks/out/mesh.md``, ``mesh.json`` and ``mesh.png``
(``--quick``: 5 k surfels, ``mesh_quick.*``, untracked). Wall times on a shared machine.

Not measured here (not built): the hybrid point/triangle renderer and the voxelised IoU
against the simulator's ground-truth mesh.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, print_result, pyplot, report_head, save_figure

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)


def measure_model(name: str, positions, normals) -> dict:
    from opacityhull.export.mesh import marching_cubes_mesh, surfel_spacing
    from opacityhull.render.pmr import mesh_quality, umbrella_triangulation

    P = np.asarray(positions, np.float64)
    sp = surfel_spacing(P)
    t = time.perf_counter()
    u = umbrella_triangulation(P, normals)
    t_u = time.perf_counter() - t
    q_u = mesh_quality(P, u.triangles, P, voxel_m=sp)
    t = time.perf_counter()
    V, F = marching_cubes_mesh(P, normals, voxel_m=sp)
    t_mc = time.perf_counter() - t
    q_mc = mesh_quality(V, F, P, voxel_m=sp)
    row = {
        "model": name,
        "surfels": len(P),
        "spacing_m": sp,
        "umbrella": {**q_u, "s": t_u, "leaves": u.leaves, "feature_median": float(np.nanmedian(u.feature))},
        "marching_cubes": {**q_mc, "s": t_mc},
    }
    print(row, file=sys.stderr, flush=True)
    return row


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="5 k surfels only (untracked mesh_quick.*)")
    ap.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    ap.add_argument("--models", nargs="*", default=[], help="model folders to add")
    args = ap.parse_args(argv)
    from opacityhull.model import OpacityHullModel
    from opacityhull.render.synthetic import fibonacci_sphere

    n = 5000 if args.quick else 20000
    d = fibonacci_sphere(n)
    rows = [measure_model(f"analytic sphere {n}", 0.08 * d, d)]
    for path in args.models:
        s = OpacityHullModel.open(path).surfels
        rows.append(measure_model(str(path), s.positions, s.normals))
    res = {"rows": rows, "machine": "shared 2-core, contended wall times"}
    stem = "mesh_quick" if args.quick else "mesh"
    OUT.mkdir(parents=True, exist_ok=True)
    lines = report_head(
        "Mesh export: umbrella mesh (PMR) vs marching cubes",
        "Same metric for both (`opacityhull.render.pmr.mesh_quality`): Chamfer distance to the surfels "
        "in surfel spacings (mean of surfels → mesh and mesh → surfels, mesh sampled 15 points a "
        "triangle). Command: `python benchmarks/mesh.py [--models M ...]`. Machine: shared 2-core, contended.",
    )
    lines += [
        "| model | surfels | mesh | faces | manifold edges | non-manifold edges | holes | Chamfer (spacings) | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for k, lab in (("umbrella", "umbrella (PMR)"), ("marching_cubes", "marching cubes (skimage)")):
            q = r[k]
            lines.append(
                f"| {Path(r['model']).name} | {r['surfels']} | {lab} | {q['faces']} | "
                f"{100 * q['manifold_edge_fraction']:.2f} % | {q['nonmanifold_edges']} | {q['holes']} | "
                f"{q['chamfer_voxels']:.3f} | {q['s']:.1f} |"
            )
    (OUT / f"{stem}.md").write_text("\n".join(lines) + "\n")
    (OUT / f"{stem}.json").write_text(json.dumps(res, indent=1) + "\n")
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    names = [Path(r["model"]).name[:18] for r in rows]
    x = np.arange(len(rows))
    for j, (k, lab) in enumerate((("umbrella", "umbrella"), ("marching_cubes", "marching cubes"))):
        ax[0].bar(x + 0.4 * j, [100 * r[k]["manifold_edge_fraction"] for r in rows], 0.4, label=lab)
        ax[1].bar(x + 0.4 * j, [r[k]["chamfer_voxels"] for r in rows], 0.4, label=lab)
    for a, t in zip(ax, ("manifold edges (%)", "Chamfer to surfels (spacings)"), strict=True):
        a.set_xticks(x + 0.2, names, fontsize=7)
        a.set_title(t)
    ax[0].axhline(99, color="grey", ls=":")
    ax[1].axhline(0.5, color="grey", ls=":")
    ax[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, OUT / f"{stem}.png", dpi=120)
    print_result(res, OUT / f"{stem}.md", as_json=args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
