"""Simulator effect selection against the full-effects reference, and render throughput.

For each built-in scene and phase, renders what the phase captures with the selected
configuration and with the reference (path tracing, max_depth 16, high spp), and
compares what the phase consumes (matting: triangulation alpha; lightfield, reflectance,
envmatte, calibration: radiance over the object; groundtruth: coverage alpha) — see
:mod:`opacityhull.sim.evaluate`. The camera is camera 2 of the default simulated rig
(200x150, the object as a capture sees it) at ``--scales`` (1, 1.4, 2: 1x, 1.96x and 4x
the pixels); calibration uses a 320x240 camera seeing the whole board, scaled alike.
Timings are warm (each configuration is rendered once first so Dr.Jit's JIT compilation
is not counted; compile time is reported separately in the throughput section).

Equal error: besides the reference at ``ref_spp``, the reference configuration (path
depth 16, whole frame) is measured at low spp against the same reference images; the
spp at which it would reach the selection's error is interpolated (error ~ spp^-k,
k fitted, time linear in spp) and its time reported: the speed-up at equal error.

Throughput: capture times of one camera of the default rig in the reflectance,
lightfield and matting states, for each Mitsuba variant (``llvm_ad_rgb`` and
``scalar_rgb``, each in its own process since the variant is process-global), at 1x and
2x the rig resolution (200x150, 400x300); the matting object shot with the crop (its
backdrop shot taken first, as a capture does) against the full frame (``crop`` off),
measured alternately in one process.

Matting candidates: each built-in scene's matting shot inside the crop at 9..64 spp and
the 2026-12-01 selection ('before'), measured alternately round by round on the 64x48
test camera and on the rig camera at 200x150 and 400x300 — the tables, one per camera
size, the selection picks from
(``opacityhull.sim.effects.MATTING_CANDIDATES``; ``--matting-candidates`` prints it).

    .venv/bin/python benchmarks/sim_effects.py [--quick] [--json] [--scales 1,1.4,2]
    .venv/bin/python benchmarks/sim_effects.py --matting-candidates [--rounds 4]

Writes ``benchmarks/out/sim_effects.md`` (tables), ``benchmarks/out/sim_effects.png``
(error vs time per scene and phase) and ``benchmarks/out/sim_effects.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)

#: What seconds are: CPU time of this process (all Mitsuba threads; steadier on a machine
#: shared with other jobs) by default, or wall time (--clock wall).
CLOCK = time.process_time
sys.path.insert(0, str(ROOT))


def throughput(n: int, scales=(1.0, 2.0)) -> dict:
    """Warm capture times at the default rig resolution and multiples, in this process's
    variant; the matting object shot with and without the crop, alternately."""
    from opacityhull.sim.groundtruth import default_geometry
    from opacityhull.sim.render import SimRenderer, SimState
    from opacityhull.sim.scenes import load_scene
    from opacityhull.sim.variants import use_mitsuba

    mi = use_mitsuba()
    g = default_geometry()
    rng = np.random.default_rng(0)
    pats = [
        {d.name: rng.integers(0, 256, (d.resolution[1], d.resolution[0], 3), dtype=np.uint8) for d in g.displays}
        for _ in range(n + 1)
    ]
    cases = [
        ("diffuse", "reflectance", SimState(table_deg=10, light_levels={1: 255})),
        ("diffuse", "lightfield", SimState(table_deg=10, light_levels={i: 255 for i in range(4)})),
        ("diffuse", "matting", SimState(table_deg=10, displays=pats[0])),
        ("glossy", "reflectance", SimState(table_deg=10, light_levels={1: 255})),
        ("sphere", "matting", SimState(table_deg=10, displays=pats[0])),
        ("glass", "matting", SimState(table_deg=10, displays=pats[0])),
        ("fuzzy", "matting", SimState(table_deg=10, displays=pats[0])),
    ]
    out = {"variant": mi.variant(), "cases": []}
    for scale in scales:
        cam = g.nominal_cameras()[2]
        cam = cam if scale == 1 else cam.scaled(scale)
        for name, phase, st in cases:
            sc = load_scene(f"builtin:{name}")
            modes = {"crop": SimRenderer(sc, g), "full frame": SimRenderer(sc, g, overrides={"crop": False})}
            t_first, t_obj, t_bg = {}, {}, {}
            for mode, r in modes.items():
                t0 = CLOCK()
                if phase == "matting":
                    r.render(cam, replace(st, content="none"), seed=0)
                r.render(cam, st, seed=0)  # load + JIT compile
                t_first[mode] = CLOCK() - t0
                t_obj[mode], t_bg[mode] = [], []
                r.pixels_rendered = r.pixels_framed = 0
            for k in range(n):
                for mode, r in modes.items():  # alternately: contention hits both alike
                    # consecutive shots of one table angle, as a capture takes them (a new table
                    # angle moves the back display: the scene's BVH is rebuilt once per angle)
                    s_k = replace(st, array_deg=5.0 * (k + 1), displays=pats[k + 1] if st.displays else {})
                    if phase == "matting":
                        t0 = CLOCK()
                        r.render(cam, replace(s_k, content="none"), seed=k + 1)
                        t_bg[mode].append(CLOCK() - t0)
                    t0 = CLOCK()
                    r.render(cam, s_k, seed=k + 1)
                    t_obj[mode].append(CLOCK() - t0)
            for mode, r in modes.items():
                eff = r.effects_for(st)
                passes = len(st.lights_on()) + (1 if st.displays_on() else 0)
                dt = float(np.median(t_obj[mode]))
                out["cases"].append(
                    {
                        "scene": name,
                        "phase": phase,
                        "mode": mode,
                        "width": cam.width,
                        "height": cam.height,
                        "integrator": eff.integrator,
                        "max_depth": eff.max_depth,
                        "spp": eff.spp,
                        "passes": passes,
                        "first_render_s": t_first[mode],
                        "warm_render_s": dt,
                        "warm_render_min_s": float(np.min(t_obj[mode])),
                        "backdrop_shot_s": float(np.median(t_bg[mode])) if t_bg[mode] else None,
                        "renders_per_s": 1.0 / dt,
                        "pixel_fraction": r.pixels_rendered / max(r.pixels_framed, 1),
                        "samples_per_s": cam.width * cam.height * eff.spp * passes / dt,
                    }
                )
                print(
                    f"throughput {mi.variant()} {cam.width}x{cam.height} {name} {phase} {mode}: {dt:.3f} s",
                    file=sys.stderr,
                )
    return out


def equal_error(err_sel: float, points: list[tuple[int, float, float]], ref_spp: int, t_ref: float) -> dict:
    """The reference's spp and time at the selection's error, from (spp, error, seconds)
    of the reference configuration at low spp: error ~ c spp^-k between the two measured
    spp that bracket the selection's error (log-log interpolation), else extrapolated
    from the nearest two (k clamped to [0.25, 1]; 1/2 with one point); time ~ a + b spp
    (least squares with the ``ref_spp`` run)."""
    pts = sorted((s_, e, t) for s_, e, t in points if e > 0)
    if not pts or not np.isfinite(err_sel) or err_sel <= 0:
        return {"ref_spp_equal_error": None, "t_ref_equal_error": None}

    def exponent(a, b) -> float:
        (s1, e1, _), (s2, e2, _) = a, b
        return float(np.clip(np.log(e1 / e2) / np.log(s2 / s1), 0.25, 1.0)) if e1 > e2 else 0.5

    if len(pts) == 1:
        s1, e1, k = pts[0][0], pts[0][1], 0.5
    elif err_sel >= pts[0][1]:  # at or above the fewest spp's error: extrapolate down
        s1, e1, k = pts[0][0], pts[0][1], exponent(pts[0], pts[1])
    elif err_sel <= pts[-1][1]:  # below the most spp's error: extrapolate up
        s1, e1, k = pts[-1][0], pts[-1][1], exponent(pts[-2], pts[-1])
    else:
        i = next(j for j in range(len(pts) - 1) if pts[j][1] >= err_sel >= pts[j + 1][1])
        s1, e1, k = pts[i][0], pts[i][1], exponent(pts[i], pts[i + 1])
    spp_eq = float(max(1.0, s1 * (e1 / err_sel) ** (1.0 / k)))
    S = np.array([p[0] for p in pts] + [ref_spp], float)
    T = np.array([p[2] for p in pts] + [t_ref], float)
    b, a = np.polyfit(S, T, 1)
    t_eq = float(a + b * spp_eq)
    if not t_eq > 0:  # a negative intercept from noise: proportional to the fewest spp's time
        t_eq = float(T[np.argmin(S)] * spp_eq / S.min())
    return {"ref_spp_equal_error": spp_eq, "t_ref_equal_error": t_eq, "error_exponent": k}


def accuracy(quick: bool, scales=(1.0,), *, scenes=None, phases=None, ref_spp: int | None = None) -> list[dict]:
    from opacityhull.sim.effects import PHASES, reference_effects, select_effects
    from opacityhull.sim.evaluate import calibration_camera, phase_error
    from opacityhull.sim.groundtruth import default_geometry
    from opacityhull.sim.render import SimRenderer
    from opacityhull.sim.scenes import builtin_names, load_scene

    g = default_geometry()
    ref_spp = ref_spp or (256 if quick else 1024)
    # the reference at low spp, for the equal-error interpolation: bias-limited selections
    # (direct lighting's lost interreflection) meet a path tracer at a few spp, so 4 spp
    # is measured rather than extrapolated to
    low_spps = (4, 16) if quick else (4, 16, 64)
    rows = []
    for name in scenes or builtin_names():
        scene = load_scene(f"builtin:{name}")
        r = SimRenderer(scene, g)
        for phase in phases or PHASES:
            if name == "charuco" and phase != "calibration" and phase != "groundtruth":
                continue  # the board scene is only ever captured for calibration
            if name != "charuco" and phase == "calibration":
                continue  # calibration renders the board, whatever the object: measured once on charuco
            for scale in scales:
                base = calibration_camera() if phase == "calibration" else g.nominal_cameras()[2]
                cam = base if scale == 1 else base.scaled(scale)
                also = (
                    ()
                    if phase in ("calibration", "groundtruth")
                    else tuple(reference_effects(scene, phase, spp=s_) for s_ in low_spps)
                )
                # the selection as it was before crop rendering, cheaper backdrops and the
                # declared-matting candidates (2026-12-01): whole frame, the undeclared spp
                before = replace(select_effects(scene, phase, declared=False), crop=False, backdrop_spp=None)
                if phase != "groundtruth":
                    also = also + (before,)
                # the same camera, reference and seed for the selection and every candidate
                measure = partial(
                    phase_error, geometry=g, camera=cam, ref_spp=ref_spp, renderer=r, warm=True, seed=1, clock=CLOCK
                )
                t0 = time.perf_counter()
                e = measure(scene, phase, also=also)
                row = {
                    **e.to_json(),
                    "wall_s": time.perf_counter() - t0,
                    "width": cam.width,
                    "height": cam.height,
                    "scale": scale,
                    "ref_spp": ref_spp,
                }
                refs = [(c.spp, err, t) for c, err, t in e.also if c.max_depth == 16 and not c.crop]
                row.update(equal_error(e.error, refs, ref_spp, e.seconds_reference))
                prev = [(err, t) for c, err, t in e.also if c == before]
                row["error_before"], row["seconds_before"] = prev[0] if prev else (None, None)
                row["speedup_over_before"] = prev[0][1] / max(e.seconds_selected, 1e-9) if prev else None
                row["speedup_equal_error"] = (
                    row["t_ref_equal_error"] / max(e.seconds_selected, 1e-9) if row["t_ref_equal_error"] else None
                )
                rows.append(row)
                eq = (
                    f" equal-error ref {row['ref_spp_equal_error']:.0f}spp {row['t_ref_equal_error']:.3f}s"
                    if row["t_ref_equal_error"]
                    else ""
                )
                print(
                    f"{name:8s} {phase:12s} {cam.width}x{cam.height} {e.metric:9s} err {e.error:.4f} "
                    f"(bound {e.bound}) sel {e.seconds_selected:.3f}s ref {e.seconds_reference:.3f}s{eq}",
                    file=sys.stderr,
                    flush=True,
                )
                if phase == "envmatte":
                    # the rig cannot tell an envmatte capture from a matting one (same emitters):
                    # SimCamera renders it with the matting selection — measure that too
                    mat = select_effects(scene, "matting", declared=False)  # what an undeclared shot gets
                    env = select_effects(scene, "envmatte")
                    if mat.key() != env.key() or mat.spp != env.spp:
                        as_captured = replace(
                            mat, phase="envmatte", error_metric=env.error_metric, error_bound=env.error_bound
                        )
                        e2 = measure(scene, phase, selected=as_captured)
                        rows.append(
                            {
                                **e2.to_json(),
                                "phase": "envmatte (captured as matting)",
                                "wall_s": 0.0,
                                "width": cam.width,
                                "height": cam.height,
                                "scale": scale,
                                "ref_spp": ref_spp,
                                "ref_spp_equal_error": None,
                                "t_ref_equal_error": None,
                                "speedup_equal_error": None,
                                "error_before": None,
                                "seconds_before": None,
                                "speedup_over_before": None,
                            }
                        )
    return rows


def matting_candidates(scenes=None, *, rounds: int = 4, ref_spp: int = 256, scales=(1.0, 2.0)) -> list[dict]:
    """The measurement behind :data:`opacityhull.sim.effects.MATTING_CANDIDATES`: for each
    built-in scene, matting with the crop at 9..64 spp (and ``path`` d2 where the
    selection is ``direct``) and the selection as of 2026-12-01 ('before': whole frame,
    64 spp, backdrops at 64 spp); every round renders each candidate once, alternately
    (contention hits all alike): alpha error against one ``ref_spp`` reference (mean over
    rounds, a new seed each) and CPU seconds per object + backdrop shot pair (median), on
    the 64x48 test camera (``evaluate.eval_camera``, which the bound test uses) and on
    camera 2 of the default rig at each of ``scales`` (1: 200x150, 2: the demo's
    400x300). The error falls with the resolution (fewer of the covered pixels are
    edge pixels, whose coverage is what the samples estimate), so the selection keeps one
    candidate list per measured size (``candidates_table``)."""
    from opacityhull.riggeometry import RigGeometry
    from opacityhull.sim.effects import reference_effects, scene_kind, select_effects
    from opacityhull.sim.evaluate import coverage_mask, eval_camera, triangulation_alpha
    from opacityhull.sim.groundtruth import default_geometry, render_ground_truth
    from opacityhull.sim.render import SimRenderer, SimState
    from opacityhull.sim.scenes import load_scene

    g = default_geometry()
    rig_cam = g.nominal_cameras()[2]
    cams = [("test", eval_camera())] + [("rig", rig_cam if s == 1 else rig_cam.scaled(s)) for s in scales]
    table = 20.0
    rows = []
    for name, (cam_name, cam) in [
        (n, c) for n in scenes or ("diffuse", "sphere", "glass", "glossy", "fuzzy") for c in cams
    ]:
        sc = load_scene(f"builtin:{name}")
        r = SimRenderer(sc, g)
        sel = select_effects(sc, "matting")
        rng = np.random.default_rng(1)
        p1 = {d.name: rng.integers(0, 256, (d.resolution[1], d.resolution[0], 3), dtype=np.uint8) for d in g.displays}
        p2 = {k: (255 - v).astype(np.uint8) for k, v in p1.items()}
        st = [SimState(table_deg=table, displays=p) for p in (p1, p2)]

        def run(cfg, s0, *, r=r, st=st, cam=cam):  # this iteration's renderer and camera, bound here
            # per pattern: the backdrop shot, then the object shot (its outside pixels
            # from the backdrop pass), as a capture takes them; each pair timed
            r.clear_radiance_cache()
            imgs, secs = {}, []
            for k, s_ in enumerate(st):
                t0 = CLOCK()
                imgs[("b", k)] = r.render(cam, replace(s_, content="none"), effects=cfg, seed=s0 + 2 * k)
                imgs[("c", k)] = r.render(cam, s_, effects=cfg, seed=s0 + 2 * k + 1)
                secs.append(CLOCK() - t0)
            r.clear_radiance_cache()
            return triangulation_alpha(imgs[("c", 0)], imgs[("c", 1)], imgs[("b", 0)], imgs[("b", 1)]), secs

        a_ref, _ = run(reference_effects(sc, "matting", spp=ref_spp), 1000)
        mask = coverage_mask(
            render_ground_truth(sc, RigGeometry.view_camera(cam, table), spp=64, renderer=r, seed=12)["alpha"]
        )
        base = select_effects(sc, "matting", declared=False)  # the integrator of the kind's matting row
        cands = {"before": replace(base, spp=64, crop=False, backdrop_spp=None)}
        for spp in (9, 16, 25, 36, 49, 64):
            cands[f"{base.integrator} d{base.max_depth} {spp}"] = replace(
                base, spp=spp, crop=True, backdrop_spp=min(16, spp)
            )
        if base.integrator == "direct":
            for spp in (16, 36):
                cands[f"path d2 {spp}"] = replace(
                    base, integrator="path", max_depth=2, spp=spp, crop=True, backdrop_spp=min(16, spp)
                )
        for c in cands.values():
            run(c, 5)  # warm: JIT compilation out of the timings
        errs: dict = {k: [] for k in cands}
        secs: dict = {k: [] for k in cands}
        for rd in range(rounds):
            for k, c in cands.items():
                a, t = run(c, 100 * rd + 10)
                errs[k].append(float(np.abs(a - a_ref)[mask].mean()))
                secs[k] += t
        t_before = float(np.median(secs["before"]))
        for k, c in cands.items():
            t = float(np.median(secs[k]))
            rows.append(
                {
                    "scene": name,
                    "kind": scene_kind(sc, "matting"),
                    "camera": cam_name,
                    "width": cam.width,
                    "height": cam.height,
                    "candidate": k,
                    "integrator": c.integrator,
                    "max_depth": c.max_depth,
                    "spp": c.spp,
                    "crop": c.crop,
                    "error": float(np.mean(errs[k])),
                    "error_max": float(np.max(errs[k])),
                    "bound": sel.error_bound,
                    "pair_s": t,
                    "speedup_over_before": t_before / max(t, 1e-9),
                    "rounds": rounds,
                    "ref_spp": ref_spp,
                }
            )
            print(
                f"candidates {name:8s} {k:16s} err {rows[-1]['error']:.4f} (bound {sel.error_bound}) "
                f"pair {t:.3f}s x{rows[-1]['speedup_over_before']:.2f} over before",
                file=sys.stderr,
                flush=True,
            )
    return rows


def candidates_table(rows: list[dict]) -> dict:
    """``"kind WxH"`` -> the Candidate tuples for MATTING_CANDIDATES at that camera size:
    per candidate, the worst error among the built-in scenes of that kind, and the
    slowest pair time of the scenes at the largest rig-camera size (the same time for
    every size: the ranking is what the selection uses; the largest camera's renders are
    the least dominated by per-call overheads, whose noise reorders the small ones)."""
    rig_px = max((r["width"] * r["height"] for r in rows if r.get("camera") == "rig"), default=0)
    times: dict = {}
    for r in rows:
        if r["crop"] and r["width"] * r["height"] == rig_px:
            key = (r["kind"], r["integrator"], r["max_depth"], r["spp"])
            times[key] = max(times.get(key, 0.0), r["pair_s"])
    out: dict = {}
    for r in rows:
        if not r["crop"]:
            continue
        key = (r["integrator"], r["max_depth"], r["spp"])
        size = f"{r['kind']} {r['width']}x{r['height']}"
        e = out.setdefault(size, {}).get(key, 0.0)
        out[size][key] = max(e, r["error"])
    return {
        size: sorted(
            (i, d, s, round(e, 4), round(times.get((size.split()[0], i, d, s), float("nan")), 3))
            for (i, d, s), e in v.items()
        )
        for size, v in sorted(out.items())
    }


def refresh_bounds(rows: list[dict]) -> list[dict]:
    """Earlier measurements against the bounds the selection states now."""
    from opacityhull.sim.effects import select_effects
    from opacityhull.sim.scenes import load_scene

    out = []
    for r in rows:
        phase = r["phase"].split(" ")[0]
        b = select_effects(load_scene(r["scene"]), phase).error_bound
        out.append({**r, "bound": b, "within_bound": r["error"] <= b})
    return out


def _f(v, fmt="{:.3f}"):
    return "—" if v is None else fmt.format(v)


def write_outputs(
    rows: list[dict],
    tput: list[dict],
    quick: bool,
    notes: list[str] | None = None,
    candidates: list[dict] | None = None,
) -> dict:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Simulator effect selection vs full-effects reference",
        "",
        f"Mode: {'quick' if quick else 'full'}; reference = path tracing, max_depth 16, whole frame, "
        f"{rows[0]['ref_spp'] if rows else '?'} spp; camera 2 of the default rig (calibration: a camera seeing "
        "the whole board) at each size; warm timings (JIT compile excluded); selections crop to the object's "
        "footprint. 'equal-error ref' = the reference configuration at the spp where its own noise equals the "
        "selection's error (interpolated from its error at low spp).",
        "",
        f"Timings: {'CPU seconds of the benchmark process (all Mitsuba threads)' if CLOCK is time.process_time else 'wall seconds'}"
        "; 2-core machine shared with other jobs (contended); ratios are measured in one process. Each "
        "configuration is timed right after a warm-up run of its own (the first launch after another "
        "configuration's kernels costs ~0.1 s more, which a capture, shot after shot of one configuration, "
        "does not pay).",
        "",
        "'before' = the same selection rendered as on 2026-12-01 (whole frame, backdrops at the shot's spp; "
        "matting: 64 spp, what a shot whose capture does not declare its phase still gets).",
        "",
        "matting rows are the *declared* matting selection (SimState.phase = 'matting', set by "
        "SimRig.note_phase): the cheapest measured candidate inside the crop within 0.85 x the bound (see "
        "'Matting candidates' below). 'envmatte (captured as matting)' is what an undeclared displays-on shot "
        "gets. The speed-ups of the first table come from single sequential runs on a contended machine "
        "(up to ~2x apart run to run); the candidates table's speed-ups over 'before' are measured alternately.",
        "",
        "| scene | phase | size | selected | metric | error | bound | ok | t selected (s) | t reference (s) | "
        "speed-up | equal-error ref (spp, s) | speed-up at equal error | before: error, t (s) | "
        "speed-up over before |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s = r["selected"]
        eq = f"{r['ref_spp_equal_error']:.0f}, {r['t_ref_equal_error']:.3f}" if r.get("t_ref_equal_error") else "—"
        lines.append(
            f"| {r['scene']} | {r['phase']} | {r['width']}x{r['height']} | {s['integrator']} d{s['max_depth']} "
            f"{s['spp']}spp{' crop' if s.get('crop') else ''} | {r['metric']} | {r['error']:.4f} | {r['bound']} | "
            f"{'yes' if r['within_bound'] else '**NO**'} | {r['seconds_selected']:.3f} | "
            f"{r['seconds_reference']:.3f} | {r['speedup']:.1f}x | {eq} | "
            f"{_f(r.get('speedup_equal_error'), '{:.1f}x')} | "
            + (f"{r['error_before']:.4f}, {r['seconds_before']:.3f}" if r.get("seconds_before") else "—")
            + f" | {_f(r.get('speedup_over_before'), '{:.1f}x')} |"
        )
    lines += [
        "",
        "# Capture times per shot (warm, median)",
        "",
        "One capture = one Mitsuba render per light switched on plus one for the displays (x passes). "
        "'crop' and 'full frame' were measured alternately in one process; a matting object shot takes "
        "its outside pixels from the backdrop shot of the same patterns, taken first (as a capture does).",
        "",
        "| variant | size | scene | phase | config | mode | pixels rendered | first capture (s, incl. load+JIT) | "
        "warm object shot (s) | backdrop shot (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in tput:
        for c in t.get("cases", []):
            lines.append(
                f"| {t['variant']} | {c['width']}x{c['height']} | {c['scene']} | {c['phase']} | "
                f"{c['integrator']} d{c['max_depth']} {c['spp']}spp x{c.get('passes', 1)} | {c['mode']} | "
                f"{100 * c['pixel_fraction']:.0f}% | {c['first_render_s']:.2f} | {c['warm_render_s']:.3f} | "
                f"{_f(c.get('backdrop_shot_s'))} |"
            )
        if "error" in t:
            lines.append(f"| {t['variant']} | — | — | — | failed: {t['error']} | | | | | |")
    if candidates:
        lines += [
            "",
            "# Matting candidates inside the crop (what the selection picks from)",
            "",
            "Each round renders every candidate once, alternately; error = alpha MAE against one reference "
            "(mean over rounds, new seeds), time = CPU seconds per object + backdrop shot pair (median). "
            "'before' = the 2026-12-01 selection (whole frame, 64 spp, backdrops at 64 spp). The selection "
            "(opacityhull.sim.effects.MATTING_CANDIDATES, worst built-in of each kind) takes the cheapest "
            "candidate whose error is within MATTING_MARGIN x the bound.",
            "",
            "| scene | camera | candidate | error (mean, max) | bound | pair (s) | speed-up over before |",
            "|---|---|---|---|---|---|---|",
        ]
        for c in candidates:
            lines.append(
                f"| {c['scene']} | {c.get('camera', 'rig')} {c['width']}x{c['height']} | {c['candidate']} | "
                f"{c['error']:.4f}, "
                f"{c['error_max']:.4f} | {c['bound']} | {c['pair_s']:.3f} | {c['speedup_over_before']:.2f}x |"
            )
    lines += [
        "",
        "Machine: 2 cores shared with other jobs; Mitsuba renders are compute-bound (ray "
        "traversal and shading), not memory-bound, so the 10 GB/s bandwidth limit is not the bound here.",
    ]
    lines += [""] + list(notes or [])
    (OUT / "sim_effects.md").write_text("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    ax = axes[0]
    phases = sorted({r["phase"] for r in rows})
    markers = dict(zip(phases, "osD^vP*X", strict=False))  # fewer phases than markers: the rest go unused
    for r in rows:
        y = max(r["error"], 1e-5)
        ax.scatter(
            r["seconds_selected"],
            y,
            marker=markers[r["phase"]],
            s=40,
            color="tab:green" if r["within_bound"] else "tab:red",
        )
        if r.get("t_ref_equal_error"):
            ax.scatter(
                r["t_ref_equal_error"], y, marker=markers[r["phase"]], s=30, facecolors="none", edgecolors="tab:blue"
            )
            ax.plot([r["seconds_selected"], r["t_ref_equal_error"]], [y, y], color="tab:blue", lw=0.4)
        for a in r.get("also", []):
            ax.scatter(a["seconds"], max(a["error"], 1e-5), marker=markers[r["phase"]], s=12, color="tab:gray")
        ax.annotate(f"{r['scene'].split(':')[-1]} {r['width']}", (r["seconds_selected"], y), fontsize=5)
    for ph, m in markers.items():
        ax.scatter([], [], marker=m, color="k", label=ph)
    ax.scatter([], [], s=30, facecolors="none", edgecolors="tab:blue", label="reference at equal error")
    ax.scatter([], [], s=12, color="tab:gray", label="reference at 16/64 spp")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per phase measurement (s, contended 2-core machine)")
    ax.set_ylabel("error vs reference (green: selection within bound)")
    ax.legend(fontsize=6)
    ax.set_title("error vs time: selection (filled) and reference")
    ax = axes[1]
    labels = [f"{r['scene'].split(':')[-1]} {r['phase'][:5]} {r['width']}" for r in rows]
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["error"] / r["bound"] for r in rows], 0.4, label="error / bound")
    ax.bar(
        x + 0.2,
        [np.log10(max(r.get("speedup_equal_error") or r["speedup"], 1.0)) for r in rows],
        0.4,
        label="log10 speed-up (at equal error where measured)",
    )
    ax.axhline(1.0, color="r", lw=0.8)
    ax.axhline(np.log10(3.0), color="k", lw=0.6, ls="--")
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=4, rotation=90)
    ax.legend(fontsize=7)
    ax.set_title("error relative to the stated bound, and speed-up (dashed: 3x)")
    fig.tight_layout()
    fig.savefig(OUT / "sim_effects.png", dpi=120)
    plt.close(fig)
    summary = {
        "accuracy": rows,
        "throughput": tput,
        "matting_candidates": candidates or [],
        "all_within_bounds": all(r["within_bound"] for r in rows),
        "table": str(OUT / "sim_effects.md"),
        "plot": str(OUT / "sim_effects.png"),
    }
    (OUT / "sim_effects.json").write_text(json.dumps(summary, indent=1))
    return summary


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument(
        "--quick", action="store_true", help="256-spp reference, default size only, fewer throughput renders"
    )
    ap.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    ap.add_argument(
        "--scales",
        default=None,
        help="camera scales for the accuracy table (default 1,1.4,2: 1x, ~2x, 4x pixels, sizes that keep square pixels; quick: 1)",
    )
    ap.add_argument("--ref-spp", type=int, default=None, help="reference spp (default 1024; quick 256)")
    ap.add_argument("--scenes", default=None, help="comma-separated built-in scenes (default: all)")
    ap.add_argument("--phases", default=None, help="comma-separated phases (default: all)")
    ap.add_argument("--variants", default="llvm_ad_rgb,scalar_rgb", help="Mitsuba variants for the throughput")
    ap.add_argument(
        "--clock",
        choices=("cpu", "wall"),
        default="cpu",
        help="seconds as CPU time of this process (default; steadier when the machine is shared) or wall",
    )
    ap.add_argument("--throughput-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument(
        "--matting-candidates",
        action="store_true",
        help="only measure the matting candidates (the table behind MATTING_CANDIDATES) and print them "
        "as JSON; writes nothing",
    )
    ap.add_argument("--skip-candidates", action="store_true", help="leave the matting candidates out")
    ap.add_argument("--rounds", type=int, default=None, help="rounds of the matting candidates (default 4; quick 2)")
    ap.add_argument("--skip-throughput", action="store_true", help="only the accuracy table")
    ap.add_argument("--skip-accuracy", action="store_true", help="only the throughput table")
    ap.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=None,
        help="write the outputs from earlier --json summaries (or --throughput-only lines) measured in "
        "parts, e.g. one process per scale; nothing is measured",
    )
    ap.add_argument(
        "--notes",
        type=Path,
        default=None,
        help="with --merge: a text file whose lines are appended to the table (how the parts were measured)",
    )
    ap.add_argument(
        "--accuracy-from",
        type=Path,
        default=None,
        help="reuse the accuracy rows of an earlier sim_effects.json (bounds refreshed from the current "
        "selection) and measure only the throughput",
    )
    args = ap.parse_args()
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    n = 3 if args.quick else 5
    rounds = args.rounds or (2 if args.quick else 4)
    if args.matting_candidates:
        cand = matting_candidates(
            args.scenes.split(",") if args.scenes else None, rounds=rounds, ref_spp=args.ref_spp or 256
        )
        print(json.dumps({"matting_candidates": cand, "table": candidates_table(cand)}))
        return 0
    if args.throughput_only:
        print(json.dumps(throughput(n, (1.0,) if args.quick else (1.0, 2.0))))
        return 0
    if args.merge:
        rows, tput, cand = [], [], []
        for f in args.merge:
            d = json.loads(f.read_text().strip().splitlines()[-1])
            if "cases" in d:
                tput.append(d)
            else:
                rows += d.get("accuracy", [])
                tput += d.get("throughput", [])
                cand += d.get("matting_candidates", [])
        notes = args.notes.read_text().splitlines() if args.notes else None
        summary = write_outputs(rows, tput, args.quick, notes=notes, candidates=cand)
        print(json.dumps(summary) if args.json else (OUT / "sim_effects.md").read_text())
        return 0
    scales = tuple(float(v) for v in (args.scales or ("1" if args.quick else "1,1.4,2")).split(","))
    if args.accuracy_from is not None:
        rows = refresh_bounds(json.loads(args.accuracy_from.read_text())["accuracy"])
    elif args.skip_accuracy:
        rows = []
    else:
        rows = accuracy(
            args.quick,
            scales,
            scenes=args.scenes.split(",") if args.scenes else None,
            phases=args.phases.split(",") if args.phases else None,
            ref_spp=args.ref_spp,
        )
    cand = (
        []
        if args.skip_candidates or args.accuracy_from is not None
        else matting_candidates(args.scenes.split(",") if args.scenes else None, rounds=rounds, ref_spp=256)
    )
    tput = []
    if not args.skip_throughput:
        for variant in args.variants.split(","):
            env = dict(os.environ, OPACITYHULL_MITSUBA_VARIANT=variant)
            cmd = [sys.executable, str(Path(__file__).resolve()), "--throughput-only", "--clock", args.clock]
            cmd += ["--quick"] if args.quick else []
            res = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if res.returncode != 0:
                tput.append({"variant": variant, "error": (res.stderr.strip().splitlines() or ["?"])[-1]})
            else:
                tput.append(json.loads(res.stdout.strip().splitlines()[-1]))
    summary = write_outputs(rows, tput, args.quick, candidates=cand)
    if args.json:
        print(json.dumps(summary))
    else:
        print((OUT / "sim_effects.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
