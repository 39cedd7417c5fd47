"""Statistical point geometry (Kalaiah & Varshney 2003) against the isotropic point tree.

On the analytic sphere (50 k surfels, 128×96 views every 30°), for splat budgets N/64 …
N and three captured cameras (views 4, 13, 20), PSNR of premultiplied RGB and α against
the full model's render (the CPU renderer, default per-pixel shading) of:

* **isotropic** — today's sequential point tree: each inner node a disc of radius √Σr²;
* **statistical** — each inner node one anisotropic EWA splat from its position PCA
  (``opacityhull.render.spg``), float statistics;
* **packed** — the same from the packed records the viewer bundle stores: 17-byte inner
  nodes (k-means codebooks of σ_p and σ_n), 8-byte leaves, the visibility dictionary, and
  the leaves' positions from the bundle's octree code with 3 offset bits. At budget N
  this is the whole bundle against the exact model.

Also: bytes per inner node and per leaf record, bytes per surfel of the whole geometry
(records + codebooks + dictionary + octree position code, raw and deflated), the node
statistics' build time; the viewer bundle's bytes per surfel and, in headless Chromium
(when installed; ``--no-browser`` skips it), the first-picture time. Writes ``benchmarks/out/lod.md``, ``lod.json`` and ``lod.png``
(``--quick``: 20 k surfels, one view, ``lod_quick.*``, untracked). Timings are wall
times on a shared machine.
"""

from __future__ import annotations

import json
import sys
import time
import zlib
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, print_result, pyplot, report_head, save_figure

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
FRACS = (1 / 64, 1 / 16, 1 / 4, 1.0)


def _psnr(a, b) -> float:
    sel = (a.rgba[..., 3] > 0.01) | (b.rgba[..., 3] > 0.01)
    d = np.concatenate(
        [
            (a.rgba[..., :3] * a.rgba[..., 3:] - b.rgba[..., :3] * b.rgba[..., 3:])[sel].ravel(),
            (a.rgba[..., 3] - b.rgba[..., 3])[sel],
        ]
    )
    return float("inf") if not d.any() else float(10 * np.log10(1 / np.mean(d**2)))


def packed_geometry(tree, stats, *, offset_bits: int = 3) -> dict:
    """The bundle's geometry of ``tree``: packed records, codebooks, visibility dictionary
    and the leaves' octree position code; the decoded tree and statistics."""
    from opacityhull.errors import InputError
    from opacityhull.render.spg import pack_nodes, unpack_nodes
    from opacityhull.view.octree_code import (
        apply_offsets,
        decode_positions,
        encode_offsets,
        encode_positions,
        median_spacing,
        pack,
    )

    t = time.perf_counter()
    pk = pack_nodes(tree, stats)
    pack_s = time.perf_counter() - t
    P = tree.positions[pk.leaf_ids].astype(np.float64)
    cell = median_spacing(P)
    oc = None
    for _ in range(8):
        try:
            oc = encode_positions(P, cell_m=cell)
            break
        except InputError:  # a cell over 255 points: refine
            cell *= 0.5
    assert oc is not None
    _, codes_z, counts_z = pack(oc)
    h = oc.size / 2**oc.depth
    C = decode_positions(oc)
    nrm_q = unpack_nodes(pk)[0].normals[pk.leaf_ids][oc.order]
    q = encode_offsets(P[oc.order], C, nrm_q, h, offset_bits)
    off_z = zlib.compress(q.tobytes(), 9)
    dec = np.empty_like(P)
    dec[oc.order] = apply_offsets(C, nrm_q, q, h, offset_bits)
    t2, s2 = unpack_nodes(pk, leaf_positions=dec)
    n = len(pk.leaf_ids)
    nb = pk.nbytes()
    raw = sum(nb.values()) + len(codes_z) + len(counts_z) + len(off_z)
    deflated = (
        len(zlib.compress(pk.inner.tobytes(), 9))
        + len(zlib.compress(pk.leaves.tobytes(), 9))
        + nb["codebooks"]
        + len(zlib.compress(pk.vis_dict.tobytes(), 9))
        + len(codes_z)
        + len(counts_z)
        + len(off_z)
    )
    return {
        "tree": t2,
        "stats": s2,
        "inner_record_bytes": int(pk.inner.itemsize),
        "leaf_record_bytes": int(pk.leaves.itemsize),
        "inner_nodes": len(pk.inner),
        "leaves": n,
        "codebook_p": len(pk.codebook_p.centres),
        "codebook_n": len(pk.codebook_n.centres),
        "visibility_patterns": len(pk.vis_dict),
        "bytes": {**nb, "positions": len(codes_z) + len(counts_z), "offsets": len(off_z)},
        "bytes_per_surfel": raw / n,
        "bytes_per_surfel_deflated": deflated / n,
        "position_error_max_over_cell": float(np.linalg.norm(dec - P, axis=1).max() / h),
        "pack_s": pack_s,
    }


def measure(n_surfels: int, views: tuple, width: int, height: int) -> dict:
    from opacityhull.model import Surfels
    from opacityhull.render.config import RenderConfig
    from opacityhull.render.lod import build_point_tree, select_cut
    from opacityhull.render.renderer import render_image, surfel_areas
    from opacityhull.render.runner import _seed_surfel_areas
    from opacityhull.render.spg import node_statistics, statistical_cut
    from opacityhull.render.synthetic import make_sphere_model
    from opacityhull.render.views import prepare_views

    m = make_sphere_model(n_surfels, width=width, height=height, table_step_deg=30.0)
    tree = build_point_tree(m.surfels, surfel_areas(m.surfels))
    t = time.perf_counter()
    stats = node_statistics(tree)
    stats_s = time.perf_counter() - t
    geo = packed_geometry(tree, stats)
    cams = [v.camera for v in m.views]
    pv = prepare_views(cams, m.views_premul())
    cfg = RenderConfig(threads=1)
    rows = []
    for vi in views:
        cam = m.views[vi].camera
        full = render_image(m.surfels, cams, pv, cam, config=cfg)
        for f in FRACS:
            b = max(1, int(round(n_surfels * f)))
            row = {"view": vi, "budget_fraction": f, "budget": b}
            _, mask = select_cut(tree, cam.centre_world, b)
            idx = np.flatnonzero(mask)
            iso = Surfels(tree.positions[idx], tree.normals[idx], tree.radii[idx], tree.visibility[idx], tree.n_views)
            _seed_surfel_areas(iso, tree.areas[idx])
            r = render_image(iso, cams, pv, cam, config=cfg)
            row.update(splats=int(idx.size), isotropic_db=_psnr(r, full), isotropic_ms=r.stats["ms"]["total"])
            s, areas, cov = statistical_cut(tree, stats, mask)
            _seed_surfel_areas(s, areas)
            r = render_image(s, cams, pv, cam, config=cfg, splat_cov=cov)
            row.update(statistical_db=_psnr(r, full), statistical_ms=r.stats["ms"]["total"])
            t2, s2 = geo["tree"], geo["stats"]
            _, mask2 = select_cut(t2, cam.centre_world, b)
            s, areas, cov = statistical_cut(t2, s2, mask2)
            _seed_surfel_areas(s, areas)
            r = render_image(s, cams, pv, cam, config=cfg, splat_cov=cov)
            row.update(packed_splats=int(mask2.sum()), packed_db=_psnr(r, full))
            print(row, file=sys.stderr, flush=True)
            rows.append(row)
    geo = {k: v for k, v in geo.items() if k not in ("tree", "stats")}
    return {
        "surfels": n_surfels,
        "nodes": len(tree),
        "views": list(views),
        "image": [width, height],
        "stats_s": stats_s,
        "geometry": geo,
        "rows": rows,
    }


def browser_row(n_surfels: int) -> dict:
    """The viewer bundle (format 3: packed statistical nodes) of the analytic sphere: bytes
    per surfel, and in headless Chromium the first-picture and loaded times (median of
    three loads, ``benchmarks/viewer.py``'s ``browser_timings``), canvas fitted to the
    default 800×600 window."""
    import shutil
    import tempfile

    from opacityhull.render.synthetic import write_sphere_model
    from opacityhull.view.browser import close_browser, find_chromium, open_browser
    from opacityhull.view.bundle import write_bundle
    from viewer import browser_timings

    tmp = Path(tempfile.mkdtemp(prefix="opacityhull-bench-lod-"))
    try:
        root, _ = write_sphere_model(tmp / "m", n_surfels=n_surfels, width=128, height=96, table_step_deg=30.0)
        t = time.perf_counter()
        s = write_bundle(root, tmp / "b")
        row = {
            "surfels": n_surfels,
            "bundle_bytes_per_surfel": s["bytes_per_surfel"],
            "bundle_bytes": s["bytes"],
            "bundle_write_s": time.perf_counter() - t,
        }
        b, _, why = find_chromium()
        if b is None:
            row["browser"] = f"skipped: {why}"
            return row
        drv = open_browser()
        try:
            row.update(browser_timings(tmp / "b", drv))
            row["canvas"] = drv.execute_script(
                "const c = document.getElementById('canvas'); return [c.width, c.height]"
            )
        finally:
            close_browser(drv)
        return row
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def report(res: dict, stem: str) -> Path:
    g = res["geometry"]
    lines = report_head(
        "Statistical point geometry: level of detail",
        f"Analytic sphere, {res['surfels']} surfels ({res['nodes']} tree nodes), views {res['views']} at "
        f"{res['image'][0]}×{res['image'][1]}; PSNR (dB) against the full model's CPU render. "
        "Machine: shared 2-core, contended (times are indicative). "
        "Command: `python benchmarks/lod.py` (`--quick`: 20 k surfels, one view).",
    )
    lines += [
        "| bytes | value |",
        "|---|---|",
        f"| inner-node record | {g['inner_record_bytes']} |",
        f"| leaf record | {g['leaf_record_bytes']} |",
        f"| codebooks σ_p / σ_n (centres) | {g['codebook_p']} / {g['codebook_n']} |",
        f"| distinct visibility patterns | {g['visibility_patterns']} |",
        f"| geometry per surfel (raw) | {g['bytes_per_surfel']:.1f} |",
        f"| geometry per surfel (deflated) | {g['bytes_per_surfel_deflated']:.1f} |",
        f"| parts (raw bytes) | {', '.join(f'{k} {v}' for k, v in g['bytes'].items())} |",
        f"| node statistics build | {res['stats_s']:.2f} s |",
        "",
        "| view | budget | splats | isotropic dB | statistical dB | packed dB | Δ (stat − iso) |",
        "|---|---|---|---|---|---|---|",
    ]
    br = res.get("browser")
    if br:
        lines = (
            lines[:-3]
            + [
                f"| viewer bundle (format 3) per surfel | {br['bundle_bytes_per_surfel']:.1f} (format 2: 70) |",
                f"| first picture / loaded (Chromium, SwiftShader, canvas {br.get('canvas')}) | "
                f"{br.get('first_frame_ms', float('nan')):.0f} / {br.get('loaded_ms', float('nan')):.0f} ms "
                "(format 2 at 128×96: 1315 / 1964 ms) |",
            ]
            + lines[-3:]
        )
    for r in res["rows"]:
        fr = "N" if r["budget_fraction"] == 1 else f"N/{round(1 / r['budget_fraction'])}"
        lines.append(
            f"| {r['view']} | {fr} | {r['splats']} | {r['isotropic_db']:.1f} | {r['statistical_db']:.1f} "
            f"| {r['packed_db']:.1f} | {r['statistical_db'] - r['isotropic_db']:+.1f} |"
        )
    path = OUT / f"{stem}.md"
    path.write_text("\n".join(lines) + "\n")
    plt = pyplot()
    fig, ax = plt.subplots(1, 1, figsize=(6, 4))
    for key, lab in (("isotropic_db", "isotropic nodes"), ("statistical_db", "statistical"), ("packed_db", "packed")):
        xs = sorted({r["splats"] for r in res["rows"]})
        fr = sorted({r["budget_fraction"] for r in res["rows"]})
        ys = [np.mean([min(r[key], 80) for r in res["rows"] if r["budget_fraction"] == f]) for f in fr]
        ax.semilogx([f * res["surfels"] for f in fr], ys, "o-", label=lab)
        del xs
    ax.axhline(38, color="grey", ls=":", lw=1)
    ax.set_xlabel("splat budget")
    ax.set_ylabel("PSNR vs full model (dB, capped at 80, mean over views)")
    ax.set_title(f"sphere {res['surfels']} surfels; bundle {g['bytes_per_surfel']:.1f} B/surfel")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, OUT / f"{stem}.png", dpi=120)
    (OUT / f"{stem}.json").write_text(json.dumps(res, indent=1) + "\n")
    return path


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="20 k surfels, one view (untracked lod_quick.*)")
    ap.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    ap.add_argument("--no-browser", action="store_true", help="skip the viewer bundle's browser timings")
    args = ap.parse_args(argv)
    res = measure(20_000, (4,), 64, 48) if args.quick else measure(50_000, (4, 13, 20), 128, 96)
    if not args.no_browser:
        res["browser"] = browser_row(res["surfels"])
        print(res["browser"], file=sys.stderr)
    OUT.mkdir(parents=True, exist_ok=True)
    path = report(res, "lod_quick" if args.quick else "lod")
    print_result(res, path, as_json=args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
