"""The demo job: the whole pipeline on the built-in simulated rig.

capture (``builtin:demo`` plan on ``sim:builtin:diffuse``, real drivers over ptys to the
emulators, Mitsuba cameras) → build (calibration from the ChArUco phase, matting,
hull, surfels, opacity light field, reflectance; measured against the simulator's
ground truth) → render (an orbit and a leave-one-out evaluation) → relight (the model
under a shipped light probe, an orbit over it, and a comparison with Mitsuba's own
render under the same probe) → view (the WebGL2 viewer bundle in ``out/web`` and the
command that serves it). Each step reuses what an earlier run left in ``out``: the
capture resumes, a finished model is not rebuilt.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from .cliutil import console, emit, progress

DEFAULT_RIG = "sim:builtin:diffuse?scale=2"  # 400x300 cameras: crop rendering made it affordable
DEFAULT_PLAN = "builtin:demo"


def _step(title: str) -> None:
    console().rule(f"[bold]{title}")


VIEW_PORT = 8765


def view_step(model, out_web, *, envmap: str | None = None, progress=None) -> dict:
    """The viewer's part of the demo: write the static WebGL2 bundle of ``model`` to
    ``out_web`` (an earlier bundle there is replaced) and say how to serve it.

    Returns the bundle summary of :func:`opacityhull.view.bundle.write_bundle` plus
    ``serve`` (the ``opacityhull view`` command, which serves the model on
    127.0.0.1:8765) and ``serve_static`` (serving the written bundle with Python's
    http.server).
    """
    import shlex

    from .view.bundle import write_bundle

    out_web = Path(out_web)
    summary = write_bundle(model, out_web, envmap=envmap, progress=progress)
    summary["serve"] = f"opacityhull view {shlex.quote(str(model))} --port {VIEW_PORT}"
    summary["serve_static"] = (f"python3 -m http.server -b 127.0.0.1 -d "
                               f"{shlex.quote(str(out_web))} {VIEW_PORT}")
    summary["url"] = f"http://127.0.0.1:{VIEW_PORT}/"
    return summary


def print_view_summary(v: dict) -> None:
    """The demo's closing lines (stderr): where the bundle is and the command that serves it."""
    from rich.markup import escape

    c = console()
    c.print(f"viewer: {v['surfels']} surfels, {v['bytes'] / 1e6:.1f} MB bundle in [cyan]{escape(v['out'])}[/]. "
            "Open it with", highlight=False)
    c.print(f"  [bold]{escape(v['serve'])}[/]   (then {v['url']} in a browser; Ctrl-C stops)", highlight=False)
    c.print(f"  or serve the written bundle: {v['serve_static']}", highlight=False, markup=False)


def run_demo(out: Path, *, as_json: bool = False, rig: str = DEFAULT_RIG, plan: str = DEFAULT_PLAN,
             probe: str = "grace", orbit_frames: int = 24) -> dict:
    """Run every stage into ``out`` and print where the pictures are.

    Returns the summary (also written to ``out/demo.json``).
    """
    from .acquire.plan import load_plan
    from .acquire.runner import resume_mismatch, run_capture
    from .imageio import atomic_path
    from .reconstruct.build import BuildConfig, build_model
    from .relight.runner import demo_step as relight_step
    from .render.runner import run_demo_step as render_step
    from .sim.simrig import open_sim_rig

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    session, model = out / "session", out / "model"
    t0 = time.monotonic()
    seconds: dict[str, float] = {}
    summary: dict = {"out": str(out), "rig": rig, "plan": plan}

    # 1. capture -------------------------------------------------------------------
    _step(f"1/5 capture {plan} on {rig}")
    t = time.monotonic()
    plan_obj = load_plan(plan)
    sim_rig = open_sim_rig(rig)
    try:
        why = resume_mismatch(session, plan_obj, sim_rig.geometry)
        if why:
            # an earlier demo with another plan or rig (e.g. before an upgrade changed
            # builtin:demo): keep it, renamed, and start afresh rather than fail
            stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
            for d in (session, model):
                if d.exists():
                    d.rename(d.with_name(f"{d.name}.old-{stamp}"))
            console().print(f"[yellow]earlier demo output does not match ({why}); kept it as "
                            f"{session.name}.old-{stamp} / {model.name}.old-{stamp} and capturing afresh[/yellow]")
        resume = (session / "session.toml").is_file()
        with progress(f"capture {plan}") as cb:
            cap = run_capture(sim_rig, plan_obj, session, resume=resume, progress=cb, rig_source=rig)
    finally:
        sim_rig.close()
    seconds["capture"] = time.monotonic() - t
    summary["capture"] = {"images": getattr(cap, "images", None), "session": str(session)}

    # 2. build ---------------------------------------------------------------------
    _step("2/5 build the opacity hull")
    t = time.monotonic()
    if (model / "model.toml").is_file() and (model / "report.json").is_file():
        report = json.loads((model / "report.json").read_text())
        metrics = report.get("metrics", {})
        console().print(f"model already built in {model}; reusing it")
    else:
        with progress("build") as cb:
            rep = build_model(session, model, config=BuildConfig(), ground_truth=True, progress=cb,
                              on_step=lambda s: console().print(f"  build: {s}"))
        metrics = rep.metrics
        report = rep.to_dict()
    seconds["build"] = time.monotonic() - t
    summary["build"] = {
        "model": str(model),
        "views": report.get("views"),
        "surfels": report.get("surfels"),
        "metrics": {k: metrics.get(k) for k in ("alpha_mae", "hull_iou", "hull_iou_vs_true_alpha_hull",
                                                "reproj_rms_px", "pose_max_rotation_deg") if k in metrics},
        "pictures": str(model / "pictures"),
    }

    # 3. render --------------------------------------------------------------------
    _step("3/5 render: orbit and leave-one-out")
    t = time.monotonic()
    with progress("orbit") as cb:
        r = render_step(model, out / "render", frames=orbit_frames, progress=cb)
    seconds["render"] = time.monotonic() - t
    summary["render"] = r

    # 4. relight -------------------------------------------------------------------
    _step(f"4/5 relight under the {probe} probe")
    t = time.monotonic()
    with progress("relight") as cb:
        rl = relight_step(model, out / "relight", probe=probe, orbit=orbit_frames, progress=cb)
    seconds["relight"] = time.monotonic() - t
    summary["relight"] = rl

    # 5. view ----------------------------------------------------------------------
    _step("5/5 viewer bundle")
    t = time.monotonic()
    with progress("viewer bundle") as cb:
        vw = view_step(model, out / "web", envmap=f"builtin:{probe}", progress=cb)
    seconds["view"] = time.monotonic() - t
    summary["view"] = vw

    seconds["total"] = time.monotonic() - t0
    summary["seconds"] = seconds
    summary["pictures"] = {
        "matte contact sheet and hull overlays": str(model / "pictures"),
        "orbit of the captured model": r.get("orbit_gif"),
        "leave-one-out photo | render | error": r.get("loo_sheet"),
        f"relit orbit under {probe}": rl.get("gif"),
        "relit vs Mitsuba": (rl.get("eval") or {}).get("sheet"),
        "viewer bundle (WebGL2, open through a server)": vw.get("index"),
    }
    from .cliutil import to_jsonable

    with atomic_path(out / "demo.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable(summary), indent=1))

    def human(s: dict) -> None:
        c = console()
        c.rule("[bold green]demo finished")
        b = s["build"]["metrics"]
        loo = s["render"].get("loo", {})
        ev = s["relight"].get("eval") or {}
        c.print(f"captured {s['capture']['images']} images in {seconds['capture']:.0f} s; "
                f"built {s['build']['surfels']} surfels over {s['build']['views']} views in {seconds['build']:.0f} s")
        if b:
            c.print("build vs ground truth: " + ", ".join(f"{k} {v:.3g}" for k, v in b.items() if isinstance(v, float)))
        if loo:
            c.print(f"leave-one-out: PSNR {loo.get('psnr_mean', float('nan')):.1f} dB, SSIM {loo.get('ssim_mean', float('nan')):.3f}, "
                    f"alpha MAE {loo.get('alpha_mae', float('nan')):.3f}")
        if "rel_err_mean" in ev:
            c.print(f"relit vs Mitsuba under {probe}: relative error {ev['rel_err_mean']:.3f}, PSNR {ev['psnr_mean']:.1f} dB")
        c.print(f"total {seconds['total']:.0f} s. Pictures:")
        for what, path in s["pictures"].items():
            if path:
                c.print(f"  {what}: [cyan]{path}[/]")
        c.print(f"  summary: [cyan]{out / 'demo.json'}[/]")
        print_view_summary(s["view"])

    emit(summary, as_json, human)
    return summary
