"""CLI commands of `opacityhull.acquire` (registered by :mod:`opacityhull.cli`).

``capture``, ``session verify|info|hdr``, ``import colmap|nerfstudio``, ``rig bringup`` (the
walk of :mod:`opacityhull.rigs.bringup` with a plan's board and exposures, and the simulated
cameras that only this module may build).
"""

from __future__ import annotations

import logging
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer

from ..cliutil import JsonFlag, SessionDirArg, cli_errors, console, emit, out_console, progress
from ..errors import CaptureInterrupted, ConfigError, OpacityHullError
from ..rigs.commands import FAULT_HELP
from ..tomlio import read_toml

__all__ = ["register", "resolve_rig", "rig_static"]

# options every ``import`` subcommand takes alike
_IMPORT_OUT = typer.Option(..., "--out", help="New session folder (absent after any failure).")
_ALLOW_FULL_MASKS = typer.Option(
    False, "--allow-full-masks", help="Keep masks without background (close-ups) instead of refusing them."
)


def _run_import(run, json_out: bool, source) -> None:
    """``run(progress_callback)`` under a progress bar, then its report: JSON, or one line
    naming the counts, ``source(report)`` and the new session."""
    with progress("import", enabled=not json_out) as cb:
        rep = run(cb)
    emit(
        rep,
        json_out,
        lambda r: console().print(
            f"imported {r['images']} images ({r['masks']} masks){source(r)} into {r['session']}", highlight=False
        ),
    )


log = logging.getLogger(__name__)


def resolve_rig(spec: str, *, assume_ready: bool = False):
    """The :class:`~opacityhull.rigs.interfaces.Rig` named by ``--rig``, opened: a rig
    TOML path (hardware, or emulators started by ``opacityhull rig emulate``), or
    ``sim:SCENE[@RIG.toml][?opts]`` for the simulated rig. ``assume_ready`` lets a
    hardware rig run without a terminal, taking every manual step as done."""
    if spec.startswith("sim:"):
        from ..sim.simrig import open_sim_rig

        return open_sim_rig(spec)
    path = Path(spec)
    if not path.is_file():
        raise ConfigError(f"--rig {spec}: no such rig TOML (give a path, or sim:SCENE for the simulated rig)")
    from ..rigs.rig import open_rig

    return open_rig(path, assume_ready=assume_ready)


def rig_static(spec: str):
    """Geometry and ``[devices]`` table of ``--rig`` without touching any device
    (dry runs): read from the rig TOML, or asked of the simulator's scene spec."""
    from ..riggeometry import RigGeometry

    if spec.startswith("sim:"):
        from ..sim import simrig
        from ..sim.scenes import load_scene

        # the scene too, as the capture will read it: a dry run blessed sim:builtin:nosuch
        load_scene(simrig.parse_sim_spec(spec)[0])
        if hasattr(simrig, "sim_rig_config"):
            cfg = simrig.sim_rig_config(spec)
        else:  # the simulator offers no static description: build its rig but do not open it
            rig = simrig.open_sim_rig(spec)
            try:
                return rig.geometry, (rig.describe() or {}).get("devices", {})
            finally:
                close = getattr(rig, "close", None)
                if close is not None:
                    close()
        return RigGeometry.from_dict(cfg["geometry"], where=f"--rig {spec}: geometry"), cfg.get("devices", {})
    path = Path(spec)
    if not path.is_file():
        raise ConfigError(f"--rig {spec}: no such rig TOML (give a path, or sim:SCENE for the simulated rig)")
    d = read_toml(path, error=ConfigError, what="rig TOML")
    if "geometry" not in d:
        raise ConfigError(f"{path}: no [geometry] table")
    # the whole rig TOML is checked as `rig check` and a real capture check it (devices
    # against the geometry), so a dry run cannot bless a rig the capture would refuse
    from ..rigs.config import load_rig_config

    load_rig_config(path)
    return RigGeometry.from_dict(d["geometry"], where=f"{path}: geometry"), d.get("devices", {})


def _calibration_forecast(plan, geometry) -> list[str]:
    """What the plan's calibration views can determine (``acquire.calibration_forecast``): a warning
    per camera whose focal length (and so its distance) the views leave uncertain by > 1 %."""
    from .calibration_forecast import forecast_warnings, plan_forecast

    return forecast_warnings(plan_forecast(plan, geometry))


def _print_estimate(summary: dict) -> None:
    from rich.table import Table

    from .schedule import human_bytes, human_seconds

    est = summary["estimate"]
    t = Table(title=f"dry run: plan {summary['plan']} on {summary['rig']}")
    for col in ("phase", "shots", "images", "bytes", "time"):
        t.add_column(col, justify="right" if col != "phase" else "left")
    for p, v in est["per_phase"].items():
        t.add_row(p, str(v["shots"]), str(v["images"]), human_bytes(v["bytes"]), human_seconds(v["seconds"]))
    t.add_row(
        "[bold]total",
        "",
        f"[bold]{est['images']}",
        f"[bold]{human_bytes(est['bytes'])}",
        f"[bold]{human_seconds(est['seconds'])}",
    )
    c = console()
    c.print(t)
    b = est["breakdown_s"]
    c.print(
        f"time: moves {human_seconds(b['moves'])}, exposure {human_seconds(b['exposure'])}, per-image overhead "
        f"{human_seconds(b['overhead'])}, pattern upload {human_seconds(b['pattern_upload'])}, "
        f"{est['operator_steps']} manual step(s) {human_seconds(b['operator'])}",
        highlight=False,
    )
    for w in summary.get("warnings", []):
        c.print(f"[yellow]warning:[/] {w}", highlight=False, markup=True, soft_wrap=True)
    for n in summary.get("notes", []):
        c.print(f"note: {n}", highlight=False, markup=False, soft_wrap=True)


@contextmanager
def _stdout_to_stderr():
    """Route file descriptor 1 to stderr while devices and renderers run, so that
    ``--json`` leaves exactly one JSON object on stdout whatever a library prints
    (Mitsuba logs "Received interrupt signal" to stdout from C++). C stdio buffers are
    flushed before fd 1 comes back, or their bytes would still land on stdout."""
    import ctypes

    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):  # no real fd 1 (embedded, test runners): nothing to do
        yield
        return
    libc = None
    try:
        libc = ctypes.CDLL(None)
    except OSError as e:  # C-level buffers then stay unflushed: output order may mix, nothing is lost
        log.debug("no libc for fflush: %s", e)
    os.dup2(2, 1)
    try:
        yield
    finally:
        try:
            sys.stdout.flush()
        except ValueError:  # sys.stdout was closed inside the block: nothing left to flush
            log.debug("stdout closed before the fd was restored")
        if libc is not None:
            libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


def _manifest_count(out: Path) -> int | None:
    """Raw images recorded in ``out`` so far; None (JSON null: unknown) when the session
    cannot be read — the error being reported already says why, and 0 would be a lie."""
    from ..session import Session

    if not (out / "session.toml").is_file():
        return 0  # stopped before the session was started: nothing recorded
    try:
        return sum(1 for r in Session.open(out).records if r.kind == "raw")
    except (OpacityHullError, OSError) as e:
        log.warning("%s: cannot count the recorded images: %s", out, e)
        return None


def register(app, groups) -> None:
    """Add this stage's commands to the root app and the subcommand groups."""

    @app.command("capture")
    @cli_errors
    def capture(
        rig: str = typer.Option(
            ..., "--rig", help="Rig TOML path, or sim:SCENE (or sim:SCENE@RIG.toml) for the simulated rig."
        ),
        plan: str = typer.Option(..., "--plan", help="Plan TOML path or builtin:tiny|demo|paper."),
        out: Path | None = typer.Option(None, "--out", help="Session folder (new/empty, or existing with --resume)."),
        resume: bool = typer.Option(
            False,
            "--resume",
            help="Continue the session in --out: verify what is there, take only what is missing or corrupt.",
        ),
        dry_run: bool = typer.Option(
            False, "--dry-run", help="Print counts, bytes and estimated time per phase; touch no device, write nothing."
        ),
        assume_ready: bool = typer.Option(
            False,
            "--assume-ready",
            help="Hardware rigs without a terminal: take every manual step (board, object) as done.",
        ),
        allow_display_drift: bool = typer.Option(
            False,
            "--allow-display-drift",
            help="Start matting even when a backdrop panel's auto-brightness or dynamic contrast is on.",
        ),
        json_out: JsonFlag = False,
    ):
        """Capture a session: run a plan on a rig, resumably (exit 5 = stopped early, resumable; 130 = Ctrl-C)."""
        from .plan import load_plan
        from .schedule import MotionRates, estimate, expected_counts, lamps_for_plan, natural_view_note, schedule

        the_plan = load_plan(plan)
        if dry_run:
            geometry, devices = rig_static(rig)
            # the simulator fits the plan's lamps; a rig TOML must already say them
            geometry = lamps_for_plan(the_plan, geometry, can_fit=rig.startswith("sim:"))
            stages = schedule(the_plan, geometry)
            est = estimate(the_plan, geometry, MotionRates.from_devices(devices), stages)
            summary = {
                "complete": False,
                "images": 0,
                "session": str(out) if out else None,
                "dry_run": True,
                "plan": the_plan.name,
                "rig": rig,
                "planned_per_phase": expected_counts(stages),
                "estimate": est.to_dict(),
                "warnings": _calibration_forecast(the_plan, geometry),
            }
            note = natural_view_note(the_plan)
            if note:
                summary["notes"] = [note]
            emit(summary, json_out, _print_estimate)
            return
        if out is None:
            raise ConfigError("--out: a session folder is required (except with --dry-run)")
        from ..outputs import check_output

        files = {"--rig": rig.split("@", 1)[-1].split("?", 1)[0] if rig.startswith("sim:") else rig, "--plan": plan}
        check_output(out, {k: v for k, v in files.items() if not v.startswith("builtin:") and Path(v).is_file()})
        from rich.markup import escape

        from .runner import run_capture

        summary = {"complete": False, "images": 0, "session": str(out)}
        try:
            with _stdout_to_stderr():
                the_rig = resolve_rig(rig, assume_ready=assume_ready)
                try:
                    the_rig.open()
                    with progress(f"capture {the_plan.name}") as cb:
                        res = run_capture(
                            the_rig,
                            the_plan,
                            out,
                            resume=resume,
                            progress=cb,
                            rig_source=rig,
                            allow_display_drift=allow_display_drift,
                            log=lambda m: console().print(f"[cyan]{escape(m)}", highlight=False),
                        )
                finally:
                    the_rig.close()
        except (OpacityHullError, KeyboardInterrupt) as e:
            if json_out:
                summary.update(images=_manifest_count(out), error=str(e) or type(e).__name__)
                emit(summary, True)
            raise
        summary = res.to_dict()

        def human(s):
            state = "complete" if s["complete"] else "INCOMPLETE"
            console().print(
                f"capture {state}: {s['images']}/{s['planned']} images in {s['session']} "
                f"({s['taken']} taken now, {s['seconds']:.1f} s)",
                highlight=False,
            )

        emit(summary, json_out, human)
        if not res.complete:
            raise CaptureInterrupted(
                f"capture incomplete: {res.images} of {res.planned} images; run again with --resume"
            )

    session = groups["session"]

    @session.command("verify")
    @cli_errors
    def verify(
        directory: SessionDirArg,
        json_out: JsonFlag = False,
    ):
        """Check every manifest entry exists with its sha256 and no image is unlisted (exit 4 if not ok)."""
        from .verify import verify_session

        with progress("verify", enabled=not json_out) as cb:
            rep = verify_session(directory, progress=cb)

        def human(r):
            c = console()
            c.print(
                f"{'OK' if r['ok'] else 'NOT OK'}: {r['images']} images; missing {len(r['missing'])}, "
                f"corrupt {len(r['corrupt'])}, unlisted {len(r['unlisted'])}, invalid records "
                f"{len(r.get('invalid', []))}",
                highlight=False,
            )
            for k in ("missing", "corrupt", "unlisted", "invalid"):
                for p in r.get(k, [])[:10]:
                    c.print(f"  {k}: {p}", highlight=False, markup=False)
            for ph, n in r["per_phase"].items():
                want = (r["planned_per_phase"] or {}).get(ph)
                c.print(f"  {ph}: {n}" + (f" / {want} planned" if want is not None else ""), highlight=False)

        emit(rep, json_out, human)
        if not rep["ok"]:
            raise typer.Exit(code=4)

    @session.command("info")
    @cli_errors
    def info(
        directory: SessionDirArg,
        json_out: JsonFlag = False,
    ):
        """Phases, views, image counts and bytes of a session."""
        from .schedule import human_bytes
        from .verify import session_info

        rep = session_info(directory)

        def human(r):
            c = out_console()
            c.print(
                f"session {r['session']}: plan {r['plan']}, rig {r['rig_source'] or '?'}, {r['images']} images, "
                f"{human_bytes(r['bytes'])}, {r['views']} views",
                highlight=False,
            )
            for ph, v in r["phases"].items():
                c.print(
                    f"  {ph}: {v['images']} images ({v['hdr']} hdr), {v['views']} views, "
                    f"{human_bytes(v['bytes'])}, exposures {v['exposures_s']}",
                    highlight=False,
                )

        emit(rep, json_out, human, primary=True)

    @session.command("hdr")
    @cli_errors
    def hdr(
        directory: SessionDirArg,
        phase: list[str] | None = typer.Option(None, "--phase", help="Only this phase (repeatable)."),
        method: str = typer.Option("auto", "--method", help="auto | linear | debevec."),
        saturation: float = typer.Option(0.98, "--saturation", help="Clipped above this fraction of white."),
        force: bool = typer.Option(False, "--force", help="Merge again even if up to date."),
        json_out: JsonFlag = False,
    ):
        """Merge exposure brackets into linear radiance (kind = "hdr" records; raw brackets stay)."""
        from .hdr import hdr_session

        with progress("hdr merge", enabled=not json_out) as cb:
            rep = hdr_session(
                directory, phases=phase or None, method=method, saturation=saturation, force=force, progress=cb
            )
        emit(
            rep,
            json_out,
            lambda r: console().print(
                f"merged {r['merged']} of {r['shots']} bracketed shots ({r['skipped']} up to date); "
                f"{r['saturated_px']} pixels clipped in every exposure",
                highlight=False,
            ),
        )

    imp = groups["import"]

    @imp.command("colmap")
    @cli_errors
    def import_colmap_cmd(
        model: Path = typer.Option(
            ...,
            "--model",
            help="COLMAP model folder: binary (cameras.bin, images.bin, ...; "
            "wins, as in COLMAP) or text (cameras.txt, images.txt).",
        ),
        images: Path = typer.Option(..., "--images", help="Folder of the images (PNG/JPG/EXR)."),
        masks: Path | None = typer.Option(
            None, "--masks", help="Folder of masks named like the images (default: the images' own alpha, if any)."
        ),
        out: Path = _IMPORT_OUT,
        allow_full_masks: bool = _ALLOW_FULL_MASKS,
        json_out: JsonFlag = False,
    ):
        """Turn a COLMAP-calibrated image set into a session that `build` accepts."""
        from .importers import import_colmap

        _run_import(
            lambda cb: import_colmap(
                model, images, out, masks_dir=masks, allow_full_masks=allow_full_masks, progress=cb
            ),
            json_out,
            lambda r: f" from a {r['model_format']} COLMAP model",
        )

    @imp.command("nerfstudio")
    @cli_errors
    def import_nerfstudio_cmd(
        transforms: Path = typer.Option(
            ..., "--transforms", help="nerfstudio / instant-ngp / Blender transforms.json (images relative to it)."
        ),
        out: Path = _IMPORT_OUT,
        allow_full_masks: bool = _ALLOW_FULL_MASKS,
        json_out: JsonFlag = False,
    ):
        """Turn a nerfstudio transforms.json (RGBA images or mask_path mattes) into a session that `build` accepts."""
        from .importers import import_nerfstudio

        _run_import(
            lambda cb: import_nerfstudio(transforms, out, allow_full_masks=allow_full_masks, progress=cb),
            json_out,
            lambda r: "",
        )

    _register_bringup(groups["rig"])


def _register_bringup(rig) -> None:
    """``opacityhull rig bringup``: here, not in rigs/commands.py, because it reads a capture
    plan and builds simulated cameras (rigs/ imports neither acquire/ nor sim/)."""

    @rig.command("bringup")
    @cli_errors
    def bringup(
        config: Annotated[Path, typer.Option("--config", help="Rig TOML (emulator: URLs are started here).")],
        plan: Annotated[
            str, typer.Option("--plan", help="Plan whose calibration board and exposures the walk uses.")
        ] = "builtin:demo",
        state: Annotated[
            Path | None, typer.Option("--state", help="Progress file (default: RIG.bringup.json beside the TOML).")
        ] = None,
        restart: Annotated[bool, typer.Option("--restart", help="Forget earlier passed steps.")] = False,
        scene: Annotated[
            str, typer.Option("--scene", help='Scene the simulated cameras see (driver = "sim" cameras).')
        ] = "builtin:diffuse",
        spp: Annotated[int, typer.Option("--spp", min=1, help="Samples per pixel of simulated cameras.")] = 4,
        fault: Annotated[list[str], typer.Option("--fault", help=FAULT_HELP)] = [],  # noqa: B006  typer hands the body a fresh list; the body only reads it
        json_out: Annotated[bool, typer.Option("--json", help='Print {"ok", "steps": [...]}.')] = False,
    ):
        """Walk the rig device by device: every device answers, the turntable turns 90 deg and back and a camera
        sees the board turn, each lamp lights, each display shows white and black (with its contrast), the exposure
        bracket is unclipped. Resumable: passed steps are skipped the next time. Exit 3 names the failed steps."""
        from ..errors import DeviceError
        from ..rigs.commands import parse_faults
        from ..rigs.config import load_rig_config
        from .bringup import bringup_rig, bringup_summary
        from .plan import load_plan

        the_plan = load_plan(plan)
        cfg = load_rig_config(config)
        faults = parse_faults(fault)
        state_path = state if state is not None else config.with_name(config.stem + ".bringup.json")

        def simulated(c):
            from ..sim.simrig import bringup_sim_rig

            return bringup_sim_rig(c, scene=scene, spp=spp)

        def emit_step(r):
            typer.echo(r.line(), err=True)

        results = bringup_rig(
            cfg,
            plan=the_plan,
            state_path=state_path,
            restart=restart,
            faults=faults,
            simulated=simulated,
            emit=emit_step,
        )
        summary = bringup_summary(results, config=config, state_path=state_path)

        def human(s):
            n_ok = sum(1 for r in s["steps"] if r["verdict"] == "pass")
            typer.echo(f"bring-up: {n_ok} of {len(s['steps'])} steps pass (progress in {s['state']})", err=True)

        emit(summary, json_out, human)
        if not summary["ok"]:
            bad = [r for r in results if r.verdict == "fail"]
            raise DeviceError("bring-up failed: " + "; ".join(f"{r.step}: {r.what_to_check}" for r in bad))
