"""Exact visual-hull outlines against the splatted outline, on the real rings.

    .venv/bin/python benchmarks/outline.py [--quick] [--sets temple,dino] [--views every:4] [--json]

The renderer's outline is the EWA splats' coverage of the surfels: a pixel on the rim of
the mask is about half covered (measured: templeSR view c2, mean coverage 0.51 on the
mask's 1-px rim, 0.15 on the ring just outside it), so the rendered silhouette sits
about half a pixel inside the hull's true projection. This benchmark asks what the
exact projection would be worth: in a 2-px band around the rendered outline every pixel
casts ``ss x ss`` rays through the carve's own silhouettes (``build/geometry.pkl``: the
pinhole silhouettes, the grid box, the tolerance; the strong silhouettes rebuilt from
``build/open_holes.npz`` and ``build/bright_extensions.npz`` as the build does) and a
ray is covered where a point on it survives the carve's rule (inside every strong
silhouette that sees it, rejected by at most ``tolerance`` views), marched at half a
voxel. That coverage replaces the splats' there (alpha = min(exact coverage, the blended
mattes)); pixels it adds take the nearest drawn pixel's colour.

Both holdouts, twins together (``eval loo``'s default): the *blend* holdout renders over
the model's geometry, which the held-out view's silhouette carved; the *geometry*
holdout over the geometry rebuilt without it (:func:`opacityhull.evaluate.holdout.geometry_without`),
and its march leaves the held-out views' silhouettes out too.

The march kernel is checked against a NumPy evaluation of the same rule on a sample of
rays at every run (``kernel_check`` in the report). Writes ``benchmarks/out/outline.md``,
``outline.json`` and ``outline.png`` (``outline_quick.*`` with ``--quick``: every 8th
view); ``--json`` prints one object.
"""

from __future__ import annotations

import json
import math
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import cast

import numpy as np
from numba import njit, prange
from benchkit import out_dir, parser, print_result, pyplot, report_head, save_figure

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
DATA = ROOT / "tests" / "data" / "real"
#: subsamples per side of a band pixel, and the band's half-width around the outline (px)
SS = 4
BAND_PX = 2


@njit(cache=True, parallel=True, nogil=True)
def _march(org, dirs, tnear, tfar, step, P, sizes, sil, strong, use, tol, out):  # pragma: no cover - numba
    """out[r] = 1 where a point of ray r in [tnear, tfar] (stepped by ``step``) survives
    the tolerant carve: no used view that sees it puts it outside its strong
    silhouette, and at most ``tol`` put it outside their silhouette."""
    V = P.shape[0]
    for r in prange(dirs.shape[0]):
        t = tnear[r]
        hit = 0
        while t <= tfar[r] and hit == 0:
            x = org[0] + t * dirs[r, 0]
            y = org[1] + t * dirs[r, 1]
            z = org[2] + t * dirs[r, 2]
            rej = 0
            hard = False
            for v in range(V):
                if not use[v]:
                    continue
                a = P[v, 0, 0] * x + P[v, 0, 1] * y + P[v, 0, 2] * z + P[v, 0, 3]
                b = P[v, 1, 0] * x + P[v, 1, 1] * y + P[v, 1, 2] * z + P[v, 1, 3]
                w = P[v, 2, 0] * x + P[v, 2, 1] * y + P[v, 2, 2] * z + P[v, 2, 3]
                if not (w > 0.0):
                    continue
                fu = math.floor(a / w + 0.5)
                fv = math.floor(b / w + 0.5)
                if fu < 0 or fu >= sizes[v, 0] or fv < 0 or fv >= sizes[v, 1]:
                    continue  # a view does not carve what it cannot see
                if strong[v, int(fv), int(fu)] == 0:
                    hard = True
                    break
                if sil[v, int(fv), int(fu)] == 0:
                    rej += 1
                    if rej > tol:
                        break
            if not hard and rej <= tol:
                hit = 1
            t += step
        out[r] = hit


def _march_numpy(org, dirs, tnear, tfar, step, P, sizes, sil, strong, use, tol):
    """The same rule, one ray at a time, all samples and views at once (the reference)."""
    out = np.zeros(len(dirs), np.uint8)
    views = np.flatnonzero(use)
    for r in range(len(dirs)):
        n = int(np.floor((tfar[r] - tnear[r]) / step)) + 1 if tfar[r] >= tnear[r] else 0
        if n <= 0:
            continue
        t = tnear[r] + step * np.arange(n)
        X = org[None, :] + t[:, None] * dirs[r][None, :]
        hard = np.zeros(n, bool)
        rej = np.zeros(n, int)
        for v in views:
            h = X @ P[v, :, :3].T + P[v, :, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                fu, fv = np.floor(h[:, 0] / h[:, 2] + 0.5), np.floor(h[:, 1] / h[:, 2] + 0.5)
            seen = (h[:, 2] > 0) & (fu >= 0) & (fu < sizes[v, 0]) & (fv >= 0) & (fv < sizes[v, 1])
            iu, iv = np.where(seen, fu, 0).astype(int), np.where(seen, fv, 0).astype(int)
            hard |= seen & (strong[v, iv, iu] == 0)
            rej += seen & (sil[v, iv, iu] == 0)
        out[r] = bool(np.any(~hard & (rej <= tol)))
    return out


class ExactOutline:
    """The carve's silhouettes and rule, from a built model's ``build/`` folder."""

    def __init__(self, model):
        from opacityhull.model import BRIGHT_EXTENSIONS, BUILD_DIR, OPEN_HOLES, read_hole_masks
        from opacityhull.reconstruct.build import strong_silhouette

        root = Path(model.root)
        with open(root / BUILD_DIR / "geometry.pkl", "rb") as f:
            g = pickle.load(f)
        self.grid, self.pin, self.tol = g.grid, list(g.pin), int(g.info["carve_tolerance"])
        sils = [np.asarray(s, bool) for s in g.sils]
        opened = read_hole_masks(root / BUILD_DIR / OPEN_HOLES)
        doubted = read_hole_masks(root / BUILD_DIR / BRIGHT_EXTENSIONS)
        strong = [
            strong_silhouette(s, open_holes=opened.get(v.id), doubtful_extensions=doubted.get(v.id))[0] | s
            for v, s in zip(model.views, sils, strict=True)
        ]
        self.sil = np.stack(sils).astype(np.uint8)
        self.strong = np.stack(strong).astype(np.uint8)
        self.P = np.stack([c.projection_matrix() for c in self.pin])
        self.sizes = np.array([[c.width, c.height] for c in self.pin], np.int64)

    def rays(self, i: int, ys: np.ndarray, xs: np.ndarray):
        offs = (np.arange(SS) + 0.5) / SS - 0.5
        uu = (xs[:, None, None] + offs[None, None, :]).repeat(SS, 1).reshape(-1)
        vv = (ys[:, None, None] + offs[None, :, None]).repeat(SS, 2).reshape(-1)
        org, d = self.pin[i].pixel_rays(np.stack([uu, vv], 1))
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (self.grid.lo - org) / d, (self.grid.hi - org) / d
        tn = np.maximum(np.nanmax(np.minimum(t1, t2), 1), 0.0)
        tf = np.nanmin(np.maximum(t1, t2), 1)
        return org, d, tn, tf

    def args(self, held: tuple[int, ...]):
        use = np.ones(len(self.pin), np.bool_)
        use[list(held)] = False
        return self.grid.voxel_m * 0.5, self.P, self.sizes, self.sil, self.strong, use, self.tol

    def coverage(self, i: int, ys: np.ndarray, xs: np.ndarray, held: tuple[int, ...]) -> np.ndarray:
        org, d, tn, tf = self.rays(i, ys, xs)
        out = np.zeros(len(d), np.uint8)
        _march(org, d, tn, tf, *self.args(held), out)
        return out.reshape(-1, SS * SS).mean(1)


def exact_outline_rgba(res, outline: ExactOutline, i: int, held: tuple[int, ...]):
    """The rendering ``res`` with the exact outline in the band; and the band's size."""
    from scipy import ndimage as ndi

    cov, rgba = res.coverage, res.rgba
    a = rgba[..., 3]
    drawn = cov > 0.5
    grown = np.asarray(ndi.binary_dilation(drawn, iterations=BAND_PX), bool)
    band = grown & ~np.asarray(ndi.binary_erosion(drawn, iterations=BAND_PX), bool)
    ys, xs = np.nonzero(band)
    exact = outline.coverage(i, ys, xs, held)
    has = a > 1e-3
    nearest = cast(np.ndarray, ndi.distance_transform_edt(~has, return_distances=False, return_indices=True))
    iy, ix = nearest[0], nearest[1]
    colour = np.where(has[..., None], rgba[..., :3], rgba[iy, ix, :3])
    matte = np.where(cov[ys, xs] > 1e-3, np.clip(a[ys, xs] / np.maximum(cov[ys, xs], 1e-3), 0.0, 1.0), 1.0)
    a2 = a.copy()
    a2[ys, xs] = np.minimum(exact, matte)
    return np.concatenate([colour, a2[..., None]], -1).astype(np.float32), len(ys)


def kernel_check(outline: ExactOutline, i: int, held, n: int = 64, seed: int = 0) -> int:
    """Rays of view i's frame where the kernel and the NumPy rule agree (asserts all n)."""
    rng = np.random.default_rng(seed)
    c = outline.pin[i]
    ys, xs = rng.integers(0, c.height, n), rng.integers(0, c.width, n)
    org, d, tn, tf = outline.rays(i, ys, xs)
    k = np.zeros(len(d), np.uint8)
    _march(org, d, tn, tf, *outline.args(held), k)
    ref = _march_numpy(org, d, tn, tf, *outline.args(held))
    if not np.array_equal(k, ref):
        raise AssertionError(f"march kernel != NumPy reference on {(k != ref).sum()} of {len(d)} rays")
    return len(d)


def measure(name: str, views: str, work: Path) -> list[dict]:
    from opacityhull.acquire.importers import import_colmap
    from opacityhull.model import BUILD_DIR, FILLED_HOLES, OpacityHullModel, read_hole_masks
    from opacityhull.reconstruct.build import BuildConfig, build_model
    from opacityhull.evaluate.holdout import geometry_without
    from opacityhull.evaluate.loo import _photograph, held_out_groups, loo_metrics, model_surfels, select_views
    from opacityhull.render.renderer import RenderConfig, prepare_model_views, render_image

    src = DATA / f"{name}SR"
    import_colmap(src / "sparse", src / "images", work / name / "session", masks_dir=src / "masks")
    build_model(work / name / "session", work / name / "model", config=BuildConfig(pictures=False))
    model = OpacityHullModel.open(work / name / "model")
    outline = ExactOutline(model)
    pv = prepare_model_views(model)
    cams = [v.camera for v in model.views]
    filled = read_hole_masks(Path(model.root) / BUILD_DIR / FILLED_HOLES)
    idx = select_views(model, views)
    held = held_out_groups(model, idx)
    full, rebuild = model_surfels(model), geometry_without(model)
    rows = []
    checked = kernel_check(outline, idx[0], held[idx[0]])
    for kind in ("blend", "geometry"):
        per: dict[str, list] = {"splats": [], "exact": []}
        ms_render, ms_outline, band_px = [], [], []
        for i in idx:
            surfels = full if kind == "blend" else rebuild(held[i])
            t0 = time.perf_counter()
            res = render_image(surfels, cams, pv, cams[i], config=RenderConfig(), exclude_views=list(held[i]))
            t1 = time.perf_counter()
            # the blend holdout's geometry was carved by the held-out view: its march keeps it
            rgba2, nb = exact_outline_rgba(res, outline, i, () if kind == "blend" else held[i])
            t2 = time.perf_counter()
            ms_render.append(1e3 * (t1 - t0))
            ms_outline.append(1e3 * (t2 - t1))
            band_px.append(nb)
            photo = _photograph(model, i, filled, res.rgba)[0]
            for what, r in (("splats", res.rgba), ("exact", rgba2)):
                per[what].append(loo_metrics(photo, r))
        for what, ms in per.items():
            rows.append(
                {
                    "set": name,
                    "holdout": kind,
                    "outline": what,
                    "views": len(idx),
                    **{
                        k: float(np.mean([m[k] for m in ms]))
                        for k in ("psnr", "psnr_band", "psnr_interior", "coverage_iou", "spill_px")
                    },
                    "render_ms_per_view": float(np.mean(ms_render)),
                    "outline_ms_per_view": float(np.mean(ms_outline)) if what == "exact" else 0.0,
                    "band_px_per_view": float(np.mean(band_px)),
                    "kernel_check_rays": checked,
                }
            )
    return rows


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="every 8th view held out")
    ap.add_argument("--sets", default="temple,dino")
    ap.add_argument("--views", default=None, help="held-out views (default every:4, every:8 with --quick)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    views = a.views or ("every:8" if a.quick else "every:4")
    rows = []
    with tempfile.TemporaryDirectory(prefix="outline-") as tmp:
        for name in a.sets.split(","):
            rows += measure(name.strip(), views, Path(tmp))
    stem = "outline_quick" if a.quick else "outline"
    checked = rows[0]["kernel_check_rays"] if rows else 0
    OUT.mkdir(parents=True, exist_ok=True)
    lines = report_head(
        "Exact visual-hull outlines against the splatted outline",
        f"`benchmarks/outline.py{' --quick' if a.quick else ''}`; held-out views {views}, twins together; "
        f"{SS}x{SS} rays a pixel in a {BAND_PX}-px band around the rendered outline, marched at half a voxel "
        "through the carve's silhouettes with its tolerance. PSNR over the union of photo mask and rendered "
        "coverage (`eval loo`'s metrics); IoU of rendered alpha > 1/2 against the photograph's mask. Wall times "
        "on a shared 2-core machine.",
        f"The march kernel equals its NumPy reference on {checked} rays a set (64 random pixels of a held-out "
        f"view, {SS}x{SS} rays each).",
    )
    lines += [
        "| set | holdout | outline | PSNR dB | band dB | interior dB | coverage IoU | spill px | render ms/view "
        "| outline ms/view |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['set']} | {r['holdout']} | {r['outline']} | {r['psnr']:.2f} | {r['psnr_band']:.2f} | "
            f"{r['psnr_interior']:.2f} | {r['coverage_iou']:.4f} | {r['spill_px']:.0f} | "
            f"{r['render_ms_per_view']:.0f} | {r['outline_ms_per_view']:.0f} |"
        )
    report = OUT / f"{stem}.md"
    report.write_text("\n".join(lines) + "\n")
    (OUT / f"{stem}.json").write_text(json.dumps(rows, indent=1))
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    keys = sorted({(r["set"], r["holdout"]) for r in rows})
    for ax, metric, label in ((axes[0], "psnr", "PSNR dB"), (axes[1], "coverage_iou", "coverage IoU")):
        for j, what in enumerate(("splats", "exact")):
            vals = [
                next(r[metric] for r in rows if (r["set"], r["holdout"]) == k and r["outline"] == what) for k in keys
            ]
            ax.bar(np.arange(len(keys)) + 0.4 * j - 0.2, vals, 0.4, label=f"{what} outline")
        ax.set_xticks(np.arange(len(keys)), [f"{s}\n{h}" for s, h in keys])
        ax.set_ylabel(label)
        lo = min(r[metric] for r in rows)
        ax.set_ylim(lo - (1.0 if metric == "psnr" else 0.02), None)
    axes[0].legend(fontsize=8)
    fig.suptitle("Splatted vs exact visual-hull outline (held-out views)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, OUT / f"{stem}.png", dpi=110)
    res = {"rows": rows, "report": str(report)}
    print_result(res, report, as_json=a.json)
    return res


if __name__ == "__main__":
    main()
