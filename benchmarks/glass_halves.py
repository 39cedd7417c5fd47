"""The two halves of a relit glass apart (#30): what limits the display-domain field and
what limits the light array's one-light images, on a model captured with
``builtin:natural`` (or any plan with a natural phase and lamps with area) on
``sim:builtin:glass``.

    .venv/bin/python benchmarks/glass_halves.py MODEL [--envmaps uffizi,grace]
        [--images 30,60,120,200] [--kernels 25,50] [--views 0,1,2,3] [--quick]

1. **Display half, images and kernels.** For each view and display of MODEL, N natural
   images (the plan's kind: probe crops and 1/f noise alternating, from a seed the plan
   does not use) are rendered by Mitsuba exactly as the natural phase shows them (the
   display lit alone, the object on the table), and the field is estimated from the
   first N of them with K kernels, over the pixels MODEL's field covers. Its relit
   display half is compared with the display-lit truth
   (:func:`~opacityhull.evaluate.natural.render_envmap_on_displays`): how N and K move the
   display half, free of the sensor and of the matte.
2. **Display half, the field's pixels.** MODEL's own fields against the truth over the
   object (the truth's coverage >= ``MASK_ALPHA``, as ``eval relight`` scores): the
   error inside the field and the share carried by covered pixels without a field (the
   matte's low-alpha glass at the outline before ``natural_mask`` grew through it).
3. **Light-array half.** The relit array half against its truth under each map and
   under a uniform white map (where a faithful reflectance field of any object has no
   error: what is left is coverage and normalisation, not angular resolution); the
   share of the array's solid angle no lamp's disc covers (seen from the object
   centre); and the truth's own Monte Carlo noise (``eval relight``'s 64 spp against
   1024 spp; ``--quick`` skips it).

Writes benchmarks/out/glass_halves.md and glass_halves.json. CPU-bound (Mitsuba renders
and the NNLS estimate); the figures do not depend on the machine's load.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, print_result, report_head

OUT = out_dir()


def _kind_image(k: int, display, seed: int = 4242) -> np.ndarray:
    from opacityhull.acquire.patterns import natural_image, probe_crop

    w, h = display.resolution
    rng = np.random.default_rng([seed, k, len(display.name)])
    return probe_crop(rng, width=w, height=h)[0] if k % 2 == 0 else natural_image(rng, width=w, height=h)


def display_sweep(model, rig, centre, envs: dict, *, views, images, kernels, work: Path) -> list[dict]:
    from opacityhull.evaluate.natural import render_display_image, render_envmap_on_displays
    from opacityhull.reconstruct.natural import (
        NaturalConfig,
        envmap_display_image,
        estimate_natural,
        load_view_fields,
        relight_natural,
    )

    n_max = max(images)
    rows = []
    cache: dict = {}
    names: dict[int, list[str]] = {}
    for vi in views:
        v = model.views[vi]
        fields = load_view_fields(model.root, v.id)
        names[vi] = sorted(fields)
        for dname, f0 in sorted(fields.items()):
            d = rig.geometry.display(dname)
            pix = np.asarray(f0.pixel_index, np.int64)
            f = work / f"obs_{v.id}_{dname}_{n_max}.npz"
            if f.is_file():
                z = np.load(f)
                L, B = z["L"], z["B"]
            else:
                Ls, Bs = [], []
                for k in range(n_max):
                    p = _kind_image(k, d)
                    img = render_display_image(rig, v.camera_index, v.table_deg, dname, p, seed=100 + k)
                    Ls.append(p.astype(np.float64) / 255.0 * d.max_radiance)
                    Bs.append(np.asarray(img, np.float64)[..., :3].reshape(-1, 3)[pix])
                L, B = np.stack(Ls), np.stack(Bs)
                np.savez(f, L=L, B=B)
            for env_name, env in envs.items():
                t = render_envmap_on_displays(rig, v.camera_index, v.table_deg, env, [dname], centre_m=centre, seed=11)
                cache[(vi, dname, env_name, "truth")] = t.reshape(-1, 3)[pix]
                cache[(vi, dname, env_name, "L")] = envmap_display_image(
                    env, d, v.table_deg, centre_m=centre, supersample=3
                )
            for n in images:
                for K in kernels:
                    if n < K:
                        continue
                    t0 = time.process_time()
                    fld = estimate_natural(L[:n], B[:n], config=NaturalConfig(n_kernels=K))
                    cache[(vi, dname, n, K, "s")] = time.process_time() - t0
                    for env_name in envs:
                        cache[(vi, dname, n, K, env_name)] = relight_natural(fld, cache[(vi, dname, env_name, "L")])[
                            :, :3
                        ]
        print(f"display sweep: view {v.id} done", file=sys.stderr, flush=True)
    for n in images:
        for K in kernels:
            if n < K:
                continue
            row = {"images": n, "kernels": K, "estimate_cpu_s": 0.0}
            for env_name in envs:
                errs = []
                for vi in views:
                    est = sum(cache[(vi, dn, n, K, env_name)] for dn in names[vi])
                    tru = sum(cache[(vi, dn, env_name, "truth")] for dn in names[vi])
                    errs.append(float(np.linalg.norm(est - tru) / np.linalg.norm(tru)))
                row[env_name] = float(np.mean(errs))
                row[f"{env_name}_per_view"] = errs
            row["estimate_cpu_s"] = float(sum(cache[(vi, dn, n, K, "s")] for vi in views for dn in names[vi]))
            rows.append(row)
            print(f"display sweep: {row}", file=sys.stderr, flush=True)
    return rows


def field_pixels(model, nat, truth_fn, envs: dict) -> list[dict]:
    from opacityhull.evaluate.relight import MASK_ALPHA
    from opacityhull.reconstruct.natural import load_view_fields

    rows = []
    for i, v in enumerate(model.views):
        f = next(iter(load_view_fields(model.root, v.id).values()))
        H, W = f.image_hw
        inside = np.zeros(H * W, bool)
        inside[np.asarray(f.pixel_index)] = True
        inside = inside.reshape(H, W)
        for env_name, env in envs.items():
            _, cover = truth_fn(i, env)
            m = cover >= MASK_ALPHA
            td = nat["truth"](i, env) * cover[..., None]
            e = nat["part"](i, env) - td
            out = m & ~inside
            rows.append(
                {
                    "view": v.id,
                    "envmap": env_name,
                    "object_px": int(m.sum()),
                    "without_field_px": int(out.sum()),
                    "display_half": float(np.linalg.norm(e[m]) / np.linalg.norm(td[m])),
                    "inside_field": float(np.linalg.norm(e[m & inside]) / np.linalg.norm(td[m & inside])),
                    "error_share_without_field": float(np.linalg.norm(e[out]) / max(np.linalg.norm(e[m]), 1e-30)),
                }
            )
    return rows


def array_half(model, nat, truth_fn, truth_hi, envs: dict) -> dict:
    from opacityhull.envmap import EnvironmentMap, latlong_solid_angles
    from opacityhull.evaluate.relight import MASK_ALPHA
    from opacityhull.relight.natural_views import field_displays, natural_centre_m
    from opacityhull.relight.relit import Relighter
    from opacityhull.relight.split import _subtexel_directions, sphere_split

    R = Relighter(model)
    maps = dict(envs, white=EnvironmentMap(np.ones((64, 128, 3), np.float32), "uniform white"))
    res: dict = {}
    for name, env in maps.items():
        errs, noise = [], []
        for i in range(len(model.views)):
            arr = R.relight_view(i, envmap=nat["array_env"](i, env))[..., :3]
            ta, cover = truth_fn(i, env)
            m = cover >= MASK_ALPHA
            errs.append(float(np.linalg.norm((arr - ta)[m]) / np.linalg.norm(ta[m])))
            if truth_hi is not None and i == 0:
                th, _ = truth_hi(i, env)
                noise.append(float(np.linalg.norm((ta - th)[m]) / np.linalg.norm(th[m])))
        res[name] = {"array_half": float(np.mean(errs)), "per_view": errs}
        if noise:
            res[name]["truth_64_vs_1024spp_view0"] = noise[0]
    # the array's solid angle and the lamps' discs, seen from the field's centre
    H, W, ss = 90, 180, 2
    D = _subtexel_directions(H, W, ss)
    om = np.broadcast_to(latlong_solid_angles(H, W)[:, None], (H, W))
    centre = natural_centre_m(model)
    geom = model.geometry
    cov = []
    for t in sorted({v.table_deg for v in model.views}):
        sp = sphere_split(H, W, field_displays(model), t, centre_m=centre, supersample=ss)
        P = R.light_positions_object(t)
        dist = np.linalg.norm(P, axis=1)
        rad = np.array([geom.light(int(k)).radius_m or 0.0 for k in R.lights.light_ids])
        cos_r = np.cos(np.arcsin(np.clip(rad / dist, 0.0, 1.0)))
        hit = (np.einsum("hwsc,kc->hwsk", D, P / dist[:, None]) > cos_r).any(-1).mean(-1)
        up = D[..., 1].mean(-1) > 0
        aw = sp.array_weight * om
        cov.append(
            {
                "table_deg": t,
                "array_sr": float(aw.sum()),
                "uncovered_fraction": float(((1 - hit) * aw).sum() / aw.sum()),
                "uncovered_fraction_upper": float(((1 - hit) * aw * up).sum() / (aw * up).sum()),
            }
        )
    res["coverage"] = cov
    return res


def report(res: dict) -> Path:
    envs = res["envmaps"]
    lines = report_head(
        "The two halves of a relit glass (#30)",
        f"`benchmarks/glass_halves.py {res['model']}`: a model captured with `builtin:natural` on "
        "`sim:builtin:glass`. Relative L2 errors against Mitsuba.",
    )
    if res.get("display_sweep"):
        lines += [
            "## Display half: natural images N and kernels K",
            "",
            "Fields estimated offline from N Mitsuba renders of the natural phase (no sensor), "
            "over the pixels the model's field covers; their relit display half against the display-lit truth.",
            "",
            "| N | K | " + " | ".join(envs) + " | estimate CPU (s) |",
            "|---|---|" + "---|" * len(envs) + "---|",
        ]
        for r in res["display_sweep"]:
            lines.append(
                f"| {r['images']} | {r['kernels']} | "
                + " | ".join(f"{r[e]:.3f}" for e in envs)
                + f" | {r['estimate_cpu_s']:.1f} |"
            )
        lines.append("")
    lines += [
        "## Display half: the field's pixels",
        "",
        "The model's own fields over the object (truth coverage >= MASK_ALPHA, as `eval relight` scores).",
        "",
        "| view | map | object px | px without a field | display half | inside the field | error share without a field |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res["field_pixels"]:
        lines.append(
            f"| {r['view']} | {r['envmap']} | {r['object_px']} | {r['without_field_px']} | {r['display_half']:.3f} | "
            f"{r['inside_field']:.3f} | {r['error_share_without_field']:.2f} |"
        )
    a = res["array"]
    lines += [
        "",
        "## Light-array half",
        "",
        "| map | array half | per view | truth noise (64 vs 1024 spp, view 0) |",
        "|---|---|---|---|",
    ]
    for name in [*envs, "white"]:
        x = a[name]
        noise = x.get("truth_64_vs_1024spp_view0")
        lines.append(
            f"| {name} | {x['array_half']:.3f} | {', '.join(f'{v:.3f}' for v in x['per_view'])} | "
            f"{'-' if noise is None else f'{noise:.3f}'} |"
        )
    lines += [
        "",
        "| table (°) | array solid angle (sr) | no lamp covers | of it above the horizon |",
        "|---|---|---|---|",
    ]
    for c in a["coverage"]:
        lines.append(
            f"| {c['table_deg']:g} | {c['array_sr']:.2f} | {c['uncovered_fraction']:.2f} | "
            f"{c['uncovered_fraction_upper']:.2f} |"
        )
    lines += ["", *res.get("notes", [])]
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "glass_halves.md"
    path.write_text("\n".join(lines) + "\n")
    (OUT / "glass_halves.json").write_text(json.dumps(res, indent=1))
    return path


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("model", type=Path)
    ap.add_argument("--envmaps", default="uffizi,grace")
    ap.add_argument("--images", default="30,60,120,200")
    ap.add_argument("--kernels", default="25,50")
    ap.add_argument("--views", default="")
    ap.add_argument("--quick", action="store_true", help="no N/K sweep and no 1024-spp truth")
    ap.add_argument("--json", action="store_true")
    ap.add_argument(
        "--work", type=Path, default=None, help="cache of the offline renders (default: a temporary folder)"
    )
    args = ap.parse_args()
    from opacityhull.evaluate.relight import _natural_eval, _truth_renderer, find_scene
    from opacityhull.evaluate.natural import sim_rig_for_session
    from opacityhull.model import OpacityHullModel
    from opacityhull.relight.natural_views import natural_centre_m
    from opacityhull.relight.runner import builtin_envmap

    model = OpacityHullModel.open(args.model)
    kind, ref = find_scene(model)
    nat = _natural_eval(model, kind, ref)
    if nat is None or ref[1] is None:
        raise SystemExit(f"{args.model}: not a simulated model with a natural-illumination field and its session")
    envs = {e: builtin_envmap(e) for e in args.envmaps.split(",")}
    truth_fn = _truth_renderer(model, kind, ref, spp=64)
    res: dict = {"model": str(args.model), "envmaps": list(envs)}
    import tempfile

    work = args.work or Path(tempfile.mkdtemp(prefix="glass-halves-"))
    work.mkdir(parents=True, exist_ok=True)
    if not args.quick:
        views = [int(x) for x in args.views.split(",")] if args.views else list(range(len(model.views)))
        rig = sim_rig_for_session(ref[1])
        res["display_sweep"] = display_sweep(
            model,
            rig,
            natural_centre_m(model),
            envs,
            views=views,
            images=[int(x) for x in args.images.split(",")],
            kernels=[int(x) for x in args.kernels.split(",")],
            work=work,
        )
    res["field_pixels"] = field_pixels(model, nat, truth_fn, envs)
    truth_hi = None if args.quick else _truth_renderer(model, kind, ref, spp=1024)
    res["array"] = array_half(model, nat, truth_fn, truth_hi, envs)
    print_result(res, report(res), as_json=args.json)


if __name__ == "__main__":
    main()
