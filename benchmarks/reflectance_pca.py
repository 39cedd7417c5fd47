"""Reflectance stored as a PCA (``write_model(reflectance_storage="pca")``), one per
view or one per pixel block, against one EXR layer per light: disk bytes per view, rank,
the stored stack's relative Frobenius error, the relit error against the layered model,
write and load time.

The model is the analytic Lambertian sphere of :mod:`opacityhull.relight.synthetic`
(4 lights × 15 array angles = the paper's 60 light directions, 8 views, ``--size``
pixels), written with half pixels as ``build`` does by default, then copied with
:func:`opacityhull.model.copy_model` into a PCA model per block size, fixed rank and
error target; with ``--noise S`` also the same data with multiplicative Gaussian noise
of relative std S per value, as a merged HDR capture has (measured at 96x72 with 0.5 %:
bytes and errors within a few % of the exact case, so the default is 0). The relit
error is ‖relit_pca − relit_layers‖ / ‖relit_layers‖ over every view's matte pixels
under the shipped probes grace, uffizi (and pisa) at yaw 0 and 180°.

    .venv/bin/python benchmarks/reflectance_pca.py [--quick] [--json] [--size 320x240] [--noise 0.005]

Writes ``benchmarks/out/reflectance_pca.md``, ``.json`` and ``.png``.
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchkit import out_dir, parser, print_result, pyplot, save_figure  # noqa: E402

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)


def _bytes_per_view(root: Path) -> float:
    files = list((root / "reflectance").glob("*.exr"))
    return sum(f.stat().st_size for f in files) / max(1, len(files))


def _relit(model, envs):
    from opacityhull.relight.relit import Relighter

    R = Relighter(model)
    return [[R.relight_view(i, envmap=e) for i in range(len(model.views))] for e in envs]


def _relit_error(ref, got) -> float:
    num = den = 0.0
    for re_, ge in zip(ref, got, strict=True):
        for a, b in zip(re_, ge, strict=True):
            m = a[..., 3] > 0
            num += float(np.sum((a[..., :3][m].astype(np.float64) - b[..., :3][m]) ** 2))
            den += float(np.sum(a[..., :3][m].astype(np.float64) ** 2))
    return float(np.sqrt(num / den))


def _stack_error(ref_model, model) -> float:
    num = den = 0.0
    for i in range(len(ref_model.views)):
        a, b = ref_model.load_reflectance(i), model.load_reflectance(i)
        for k in a:
            num += float(np.sum((a[k].astype(np.float64) - b[k]) ** 2))
            den += float(np.sum(a[k].astype(np.float64) ** 2))
    return float(np.sqrt(num / den))


def _load_seconds(model) -> float:
    t = time.perf_counter()
    for i in range(len(model.views)):
        model.load_reflectance(i)
    return (time.perf_counter() - t) / len(model.views)


def _noisy(base, dst: Path, sigma: float, seed: int = 0):
    """``base`` written again (float32) with each one-light value times (1 + sigma N(0, 1))."""
    from opacityhull.model import copy_model

    rng = np.random.default_rng(seed)

    def images(i):
        return {
            k: (v * (1 + sigma * rng.standard_normal(v.shape))).astype(np.float32)
            for k, v in base.load_reflectance(i).items()
        }

    return copy_model(base, dst, storage="float", reflectance_storage="layers", reflectance_images=images)


def run(*, quick: bool, size: tuple[int, int], noise: float) -> dict:
    from opacityhull.model import OpacityHullModel
    from opacityhull.relight.synthetic import write_sphere_model

    W, H = size
    tmp = Path(tempfile.mkdtemp(prefix="refl_pca_"))
    try:
        src = write_sphere_model(tmp / "float", width=W, height=H, table_degs=(0.0, 90.0, 180.0, 270.0))
        base = OpacityHullModel.open(src)
        out = {"exact": _sweep(base, tmp / "exact", quick=quick)}
        if noise > 0:
            out[f"noise {noise:g}"] = _sweep(_noisy(base, tmp / "noisy", noise), tmp / "noisy_sweep", quick=quick)
        return {
            "model": f"analytic Lambertian sphere, {len(base.views)} views of {W}x{H}, "
            f"{len(base.light_samples)} light samples, half pixels",
            "cases": out,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _sweep(base, tmp: Path, *, quick: bool) -> dict:
    from opacityhull.data import PROBES_DIR
    from opacityhull.model import copy_model
    from opacityhull.relight.envmap import load_envmap

    tmp.mkdir(parents=True, exist_ok=True)
    if True:
        t = time.perf_counter()
        layers = copy_model(base, tmp / "layers", storage="half", reflectance_storage="layers")
        layers_write = (time.perf_counter() - t) / len(base.views)
        K = len(layers.light_samples)
        probes = ("grace", "uffizi") if quick else ("grace", "uffizi", "pisa")
        envs = [load_envmap(PROBES_DIR / f"{p}.hdr", yaw_deg=y) for p in probes for y in (0.0, 180.0)]
        ref = _relit(layers, envs)
        layers_bytes = _bytes_per_view(layers.root)
        rows = [
            {
                "mode": "layers",
                "rank": K,
                "bytes_per_view": layers_bytes,
                "ratio_bytes": 1.0,
                "stack_rel_error": _stack_error(base, layers),
                "relit_rel_error": 0.0,
                "write_s_per_view": layers_write,
                "load_s_per_view": _load_seconds(layers),
            }
        ]
        # (block px or None = per view, "rank" | "error", value)
        grid = [(None, "rank", r) for r in ((2, 6, 16) if quick else (2, 4, 6, 9, 16))]
        grid += [(None, "error", e) for e in (0.01,)]
        grid += [(8, "rank", r) for r in ((2, 4) if quick else (1, 2, 3, 4, 6))]
        grid += [(8, "error", e) for e in ((0.01, 0.03) if quick else (0.005, 0.01, 0.02, 0.03, 0.05))]
        grid += [(16, "error", e) for e in ((0.01,) if quick else (0.01, 0.03))]
        for block, kind, v in grid:
            if True:
                d = tmp / f"pca_{block}_{kind}_{v}"
                t = time.perf_counter()
                m = copy_model(
                    layers,
                    d,
                    storage="half",
                    reflectance_storage="pca",
                    pca_block=block,
                    pca_rank=int(v) if kind == "rank" else None,
                    pca_error=float(v) if kind == "error" else None,
                )
                wsec = (time.perf_counter() - t) / len(base.views)
                r = m.meta["reflectance"]
                b = _bytes_per_view(d)
                rows.append(
                    {
                        "mode": f"pca {'view' if block is None else f'block {block}'} {kind}={v}",
                        "block": block,
                        "rank": int(r["rank_max"]),
                        "rank_mean": float(np.mean([x["rank_mean"] for x in r["pca_views"]])),
                        "bytes_per_view": b,
                        "ratio_bytes": layers_bytes / b,
                        "values_ratio": float(r["values_ratio"]),
                        "stack_rel_error_reported_max": float(r["rel_error_max"]),
                        "stack_rel_error": _stack_error(base, m),
                        "relit_rel_error": _relit_error(ref, _relit(m, envs)),
                        "write_s_per_view": wsec,
                        "load_s_per_view": _load_seconds(m),
                    }
                )
                shutil.rmtree(d, ignore_errors=True)
        pca = [r for r in rows if r["mode"] != "layers"]
        return {
            "probes": [f"{p} yaw {y:g}" for p in probes for y in (0.0, 180.0)],
            "rows": rows,
            "best_ratio_relit_below_1pct": max(
                (r["ratio_bytes"] for r in pca if r["relit_rel_error"] < 0.01), default=None
            ),
            "best_ratio_stack_below_1pct": max(
                (r["ratio_bytes"] for r in pca if r["stack_rel_error"] <= 0.0101), default=None
            ),
            "default_block8_error1pct": next((r for r in pca if r["mode"] == "pca block 8 error=0.01"), None),
        }


def _markdown(res: dict) -> str:
    lines = [
        "# Reflectance as a PCA per view or per pixel block (`--reflectance-storage pca`)",
        "",
        f"Model: {res['model']}.",
        "Stack error: ‖stack_pca − stack_float‖_F / ‖stack_float‖_F over every view (includes half rounding);",
        "`reported` is the largest per-view error written in model.toml. Bytes: the ZIP-compressed EXR on disk,",
        "× smaller against the layered half model. Rank: the largest block rank (mean over pixels in brackets).",
        "",
    ]
    for name, case in res["cases"].items():
        lines += [
            f"## {name}",
            "",
            f"Relit error against the layered model under {', '.join(case['probes'])}.",
            "",
            "| mode | rank max (mean) | bytes/view | × smaller | stack error | reported | relit error | write s/view | load s/view |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in case["rows"]:
            rep = r.get("stack_rel_error_reported_max")
            mean = r.get("rank_mean")
            lines.append(
                f"| {r['mode']} | {r['rank']}{'' if mean is None else f' ({mean:.1f})'} | {r['bytes_per_view']:.0f} | "
                f"{r['ratio_bytes']:.1f} | {r['stack_rel_error']:.2e} | {'' if rep is None else f'{rep:.2e}'} | "
                f"{r['relit_rel_error']:.2e} | {r['write_s_per_view']:.3f} | {r['load_s_per_view']:.3f} |"
            )
        f = lambda x: "none" if x is None else f"{x:.1f}×"  # noqa: E731
        lines += [
            "",
            f"Largest byte ratio with stack error ≤ 1 %: {f(case['best_ratio_stack_below_1pct'])}; "
            f"with relit error < 1 %: {f(case['best_ratio_relit_below_1pct'])}.",
            "",
        ]
    lines += ["Reproduce: `.venv/bin/python benchmarks/reflectance_pca.py` (see the script's docstring).", ""]
    return "\n".join(lines)


def _plot(res: dict, path: Path) -> None:
    plt = pyplot()
    cases = list(res["cases"].items())
    fig, ax = plt.subplots(len(cases), 2, figsize=(10, 4 * len(cases)), squeeze=False)
    for row, (name, case) in enumerate(cases):
        layers = case["rows"][0]["bytes_per_view"]
        for block, style in ((None, "o-"), (8, "s-")):
            rows = [r for r in case["rows"] if r["mode"] != "layers" and r["block"] == block and " rank=" in r["mode"]]
            rk = [r["rank"] for r in rows]
            lab = "per view" if block is None else f"block {block}"
            ax[row, 0].semilogy(rk, [r["stack_rel_error"] for r in rows], style, label=f"{lab}: stack")
            ax[row, 0].semilogy(
                rk, [max(r["relit_rel_error"], 1e-7) for r in rows], style, mfc="none", label=f"{lab}: relit"
            )
            ax[row, 1].plot(rk, [r["bytes_per_view"] / 1e3 for r in rows], style, label=lab)
        ax[row, 0].axhline(0.01, color="grey", ls=":", label="1 %")
        ax[row, 0].set_xlabel("rank")
        ax[row, 0].set_ylabel("relative error")
        ax[row, 0].set_title(name, fontsize=9)
        ax[row, 0].legend(fontsize=7)
        ax[row, 1].axhline(layers / 1e3, color="C3", ls="--", label="layers")
        ax[row, 1].axhline(layers / 10e3, color="grey", ls=":", label="layers / 10")
        ax[row, 1].set_xlabel("rank")
        ax[row, 1].set_ylabel("kB per view (reflectance)")
        ax[row, 1].set_title(name, fontsize=9)
        ax[row, 1].legend(fontsize=7)
    fig.suptitle(res["model"], fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--size", default="320x240", help="view size WxH (default 320x240)")
    ap.add_argument("--noise", type=float, default=0.0, help="relative noise of a second case (0: none)")
    a = ap.parse_args()
    W, H = (int(x) for x in a.size.lower().split("x"))
    res = run(quick=a.quick, size=(W, H), noise=a.noise)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "reflectance_pca.json").write_text(json.dumps(res, indent=2) + "\n")
    (OUT / "reflectance_pca.md").write_text(_markdown(res))
    _plot(res, OUT / "reflectance_pca.png")
    print_result(res, OUT / "reflectance_pca.md", as_json=a.json)


if __name__ == "__main__":
    main()
