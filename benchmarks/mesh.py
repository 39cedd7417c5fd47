"""Mesh export (PMR umbrella mesh, Dey & Hudson 2002) against scikit-image's marching cubes.

For each model — the analytic sphere (20 k surfels) always, plus ``--models`` folders — the
umbrella mesh of the surfels (``opacityhull.render.pmr``, what ``export --format mesh``
writes) and marching cubes of the surfels' signed distance (``export.mesh.marching_cubes_mesh``,
grid = the surfel spacing) are scored on the same metric (``pmr.mesh_quality``): manifold
edges, boundary loops (holes), non-manifold edges, and the Chamfer distance to the surfels
in units of the surfel spacing ("voxel"; the hull's surfels are one per surface voxel),
plus build time. Writes ``benchmarks/out/mesh.md``, ``mesh.json`` and ``mesh.png``
(``--quick``: 5 k surfels, ``mesh_quick.*``, untracked). Wall times on a shared machine.

For a model built from a ``sim:`` rig (its ``model.toml`` names the rig; ``--models
out/demo/model`` after ``make demo``) the simulator's ground-truth mesh of the object is
there too: the Chamfer distance of each mesh (and of the surfels) to it, and the
voxelised IoU against it of the umbrella mesh, the marching-cubes mesh and the hull (the
surfels): each shape's surface sampled finer than half a voxel, marked on a grid of one
surfel spacing, the shell dilated by one voxel, its enclosed voxels filled
(``scipy.ndimage.binary_fill_holes``) and eroded back by one; the same for every shape.
templeSR (``--temple``, imported from ``../shared/data/real/templeSR`` and built as
``tests/e2e/test_real_sets_split.py`` does, without the hold-out) has no ground-truth
shape: its rows score against the surfels only. The hybrid renderer is measured by
``benchmarks/hybrid.py``.
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


def label(model: str) -> str:
    """A row's model name: the folder, with its parent when it is just ``model``."""
    p = Path(model)
    return "/".join(p.parts[-2:]) if p.name == "model" else p.name


def surface_samples(V, F, step: float) -> np.ndarray:
    """Points on every triangle on a barycentric grid finer than ``step`` (m)."""
    from opacityhull.render.pmr import sample_faces

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    T = V[F]
    edge = np.linalg.norm(T - np.roll(T, 1, axis=1), axis=2).max(axis=1)
    k = np.maximum(1, np.ceil(edge / step)).astype(int)
    out = [V]
    for kk in np.unique(k):
        out.append(sample_faces(V, F[k == kk], k=int(kk)))
    return np.concatenate(out)


def solid(points, lo, voxel: float, shape) -> np.ndarray:
    """Voxels enclosed by the surface points (see the module docstring)."""
    from scipy import ndimage

    g = np.zeros(shape, bool)
    q = np.floor((np.asarray(points) - lo) / voxel).astype(int)
    ok = np.all((q >= 0) & (q < np.array(shape)), axis=1)
    g[tuple(q[ok].T)] = True
    g = ndimage.binary_dilation(g)
    return ndimage.binary_erosion(ndimage.binary_fill_holes(g))


def iou(a, b) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def ground_truth_mesh(model) -> tuple[np.ndarray, np.ndarray] | None:
    """The simulator's object mesh (object frame) of a model built from a ``sim:`` rig."""
    rig = model.meta.get("provenance", {}).get("rig_source", "")
    if not str(rig).startswith("sim:"):
        return None
    from opacityhull.sim.simrig import open_sim_rig

    m = open_sim_rig(rig, open=False).scene.triangle_mesh()
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def truth_scores(sp: float, P, meshes: dict, gt) -> dict:
    """Chamfer (spacings) of every shape to the ground-truth mesh, and voxel IoU."""
    from scipy.spatial import KDTree

    Vg, Fg = gt
    G = surface_samples(Vg, Fg, 0.5 * sp)
    shapes = {k: surface_samples(V, F, 0.5 * sp) if len(F) else V for k, (V, F) in meshes.items()}
    shapes["hull"] = np.asarray(P, np.float64)
    lo = np.minimum(G.min(axis=0), P.min(axis=0)) - 4 * sp
    hi = np.maximum(G.max(axis=0), P.max(axis=0)) + 4 * sp
    shape = tuple(np.ceil((hi - lo) / sp).astype(int) + 1)
    g_solid = solid(G, lo, sp, shape)
    tg = KDTree(G)
    out: dict = {"gt_faces": int(len(Fg))}
    for k, X in shapes.items():
        d1, _ = tg.query(X)
        d2, _ = KDTree(X).query(G)
        out[k] = {
            "chamfer_gt_voxels": float(0.5 * (d1.mean() + d2.mean()) / sp),
            "iou_gt": iou(solid(X, lo, sp, shape), g_solid),
        }
    return out


def measure_model(name: str, positions, normals, gt=None) -> dict:
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
    if gt is not None:
        row["truth"] = truth_scores(sp, P, {"umbrella": (P, u.triangles), "marching_cubes": (V, F)}, gt)
    print(row, file=sys.stderr, flush=True)
    return row


def build_temple() -> Path:
    """templeSR imported and built (no hold-out, no pictures) under benchmarks/out/quick/ (untracked)."""
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.reconstruct.build import BuildConfig, build_model

    src = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "templeSR"
    if not src.is_dir():
        src = Path("/work/shared/data/real/templeSR")
    tmp = Path(__file__).resolve().parent / "out" / "quick" / "templeSR"
    if not (tmp / "model" / "model.toml").is_file():
        import_colmap(src / "sparse", src / "images", tmp / "session", masks_dir=src / "masks")
        build_model(tmp / "session", tmp / "model", config=BuildConfig(pictures=False))
    return tmp / "model"


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="5 k surfels only (untracked mesh_quick.*)")
    ap.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    ap.add_argument(
        "--models", nargs="*", default=[], help="model folders to add (sim: models score against the truth)"
    )
    ap.add_argument("--temple", type=Path, default=None, help="templeSR model folder, or 'build' to build one here")
    args = ap.parse_args(argv)
    from opacityhull.model import OpacityHullModel
    from opacityhull.render.synthetic import fibonacci_sphere

    n = 5000 if args.quick else 20000
    d = fibonacci_sphere(n)
    rows = [measure_model(f"analytic sphere {n}", 0.08 * d, d)]
    models = list(args.models)
    if args.temple is not None:
        models.append(build_temple() if str(args.temple) == "build" else args.temple)
    for path in models:
        m = OpacityHullModel.open(path)
        s = m.surfels
        rows.append(measure_model(str(path), s.positions, s.normals, gt=ground_truth_mesh(m)))
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
                f"| {label(r['model'])} | {r['surfels']} | {lab} | {q['faces']} | "
                f"{100 * q['manifold_edge_fraction']:.2f} % | {q['nonmanifold_edges']} | {q['holes']} | "
                f"{q['chamfer_voxels']:.3f} | {q['s']:.1f} |"
            )
    truth = [r for r in rows if "truth" in r]
    if truth:
        lines += [
            "",
            "Against the simulator's ground-truth mesh (Chamfer in surfel spacings; voxel IoU on a grid of one "
            "spacing; the goal: the export's IoU within 0.01 of the hull's):",
            "",
            "| model | shape | Chamfer to truth (spacings) | voxel IoU |",
            "|---|---|---|---|",
        ]
        for r in truth:
            for k, lab in (
                ("hull", "hull (surfels)"),
                ("umbrella", "umbrella (PMR)"),
                ("marching_cubes", "marching cubes"),
            ):
                t = r["truth"][k]
                lines.append(f"| {label(r['model'])} | {lab} | {t['chamfer_gt_voxels']:.3f} | {t['iou_gt']:.4f} |")
        lines += [
            "",
            "The low IoU is the hull's, not the meshes': the visual hull fills the cup's open cavity (12 mm "
            "walls) and overshoots its rim, so every shape scores against the truth about as the hull does.",
        ]
    (OUT / f"{stem}.md").write_text("\n".join(lines) + "\n")
    (OUT / f"{stem}.json").write_text(json.dumps(res, indent=1) + "\n")
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    names = [label(r["model"])[:18] for r in rows]
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
