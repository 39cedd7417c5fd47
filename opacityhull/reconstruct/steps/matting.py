"""Build step ``matting``: one alpha per view, each stored as it finishes."""

from __future__ import annotations

import logging
from dataclasses import asdict, replace

import numpy as np

from ...model import BUILD_DIR
from ...riggeometry import view_id
from ...session import Session
from ..buildconfig import BuildConfig
from ..buildstore import _camera_digest, _digest, _files_digest, _records_digest, _StepStore, cached
from ..lazyviews import Mattes, _MatteFiles
from ..matte_step import _stored_matte
from .base import Step
from .cameras import _Cameras

log = logging.getLogger(__name__)


def _drift_mode(session: Session, config: BuildConfig) -> str:
    """The matting drift correction to use: ``config.matting_drift`` unless "auto".
    Auto corrects ("field") every session except the simulated rig without a sensor
    drift model, whose backdrop and object shots are photometrically identical by
    construction (the correction would cost ~0.3 s per 200×150 view for nothing)."""
    if config.matting_drift != "auto":
        return config.matting_drift
    src = str(session.source)
    if src.startswith(("sim:", "synthetic:")) and "drift" not in src:
        return "none"
    return "field"


def _drift_summary(matte_stats: list, mode: str) -> dict:
    """The matting drift and registration of the build, for ``report.json``."""
    out = {"mode": mode, "per_view": {}}
    if mode == "none":
        out["why"] = "simulated rig without sensor drift (shots photometrically identical) or matting_drift='none'"
        return out
    devs, shifts, applied = [0.0], [0.0], 0
    for m in matte_stats:
        d = m.get("drift")
        if not d:
            continue
        out["per_view"][m["view"]] = d
        for sh in d["shots"]:
            devs.append(float(np.max(np.abs(np.asarray(sh["gain"], float) - 1.0))))
            if sh.get("shift_px") is not None:
                shifts.append(float(np.hypot(*sh["shift_px"])))
            applied += bool(sh.get("shift_applied"))
    out.update({"gain_max_dev": max(devs), "shift_px_max": max(shifts), "shifts_applied": applied})
    return out


def step_matting(
    session: Session,
    views,
    cams: _Cameras,
    config: BuildConfig,
    store: _StepStore,
    *,
    executor=None,
    progress=None,
    in_flight: int | None = None,
) -> Mattes:
    """Step 2: one alpha per view (triangulation matting, or the imported mask), each
    written to ``build/mattes/<view>.npy`` with its own key as it finishes, so a build
    killed mid-way keeps the views already matted. Views run through ``executor``
    (:mod:`opacityhull.executor`; local schedulers get this Session, process and Dask
    workers open the session from its path). ``in_flight``: at most this many views
    are matted at once on a local pool (the memory budget's share, :class:`MemoryPlan`);
    None = the pool's size. The returned alphas are read back from the files on access
    (:class:`_MatteFiles`), never all held."""
    from ...executor import SerialExecutor
    from ..perview import BuildMatteTask, build_matte, run_build_matte

    ex = executor or SerialExecutor()
    phases = session.phases()
    use_masks = "mask" in phases and "matting" not in phases
    drift_mode = _drift_mode(session, config)
    mopts = replace(config.matting, drift=drift_mode)
    params = {"matting": asdict(mopts), "backdrops": config.backdrops, "use_masks": use_masks}
    patterns = _digest(_files_digest(session.root / "patterns")) if config.backdrops != "object-absent" else ""
    mdir = store.model_dir / BUILD_DIR / "mattes"
    vids = [view_id(c, a) for c, a in views]
    tasks, keys, metas = [], [], {}
    for i, ((c, a), cam) in enumerate(zip(views, cams.views, strict=True)):
        recs = session.select(phase="mask" if use_masks else "matting", camera=c, table_deg=a, kind=None)
        k = _digest(
            {
                "images": _records_digest(session, recs),
                "camera": _camera_digest(cam),
                "patterns": patterns,
                "params": params,
            }
        )
        keys.append(k)
        path = mdir / f"{vids[i]}.npy"
        got = _stored_matte(path, k, (cam.height, cam.width)) if store.resume else None
        if got is not None:
            metas[i] = got[1]  # checked against its hash; read again when used
            del got
            continue
        tasks.append(
            (
                i,
                BuildMatteTask(
                    session_dir=str(session.root),
                    camera=c,
                    table_deg=a,
                    view_camera=cam,
                    use_masks=use_masks,
                    backdrops=config.backdrops,
                    matting=mopts,
                    alpha_path=str(path),
                    key=k,
                ),
            )
        )

    def mat():
        if tasks:
            mdir.mkdir(parents=True, exist_ok=True)
            if ex.scheduler in ("serial", "threads"):
                # in this process: the Session already open, not its path
                from functools import partial

                fn = partial(run_build_matte, session)
            else:
                fn = build_matte
            items = [tk for _, tk in tasks]
            wave = len(items)
            if in_flight is not None and ex.scheduler in ("threads", "processes") and in_flight < ex.n_workers:
                wave = max(1, int(in_flight))  # a larger pool would hold more views than the budget allows
            done: list = []
            for w0 in range(0, len(items), wave):
                off = w0
                sub = None if progress is None else (lambda d, t, off=off, p=progress: p(off + d, len(items)))
                done.extend(ex.map(fn, items[w0 : w0 + wave], progress=sub))
            for (i, _), meta in zip(tasks, done, strict=True):
                metas[i] = meta
        return len(tasks)

    reused = len(views) - len(tasks)
    cached(
        store,
        "matting",
        inputs={"views": dict(zip(vids, keys, strict=True))},
        params=params,
        run=mat,
        outputs=[f"{BUILD_DIR}/mattes/{v}.npy" for v in vids],
        reuse=False,  # each view is reused on its own (its sidecar key and hash)
        status=lambda _: (
            "ran" if reused == 0 else ("reused" if not tasks else f"reused {reused} of {len(views)} views")
        ),
        key=_digest(keys),
    )
    key = _digest(keys)
    ordered = [metas[i] for i in range(len(views))]
    content = _digest([m["sha256"] for m in ordered])
    return Mattes(
        alphas=_MatteFiles([mdir / f"{v}.npy" for v in vids], [(cam.height, cam.width) for cam in cams.views], vids),
        content=content,
        stats=[m["stats"] for m in ordered if m.get("stats")],
        sources={m["source"] for m in ordered},
        nonfinite=[n for m in ordered for n in m.get("nonfinite", [])],
        key=key,
        use_masks=use_masks,
        drift_mode=drift_mode,
    )


def run(ctx) -> None:
    with ctx.timer.step("matting"):
        mattes = step_matting(
            ctx.session,
            ctx.cameras.views,
            ctx.cameras.cams,
            ctx.config,
            ctx.store,
            executor=ctx.executor,
            progress=ctx.progress,
            in_flight=ctx.plan.in_flight,
        )
    ctx.nonfinite.extend(mattes.nonfinite[:1000])
    if any("display geometry" in s for s in mattes.sources):
        ctx.notes.append(
            "backdrops predicted from the display geometry (no object-absent captures): an "
            "approximation without display falloff or blur"
        )
    ctx.mattes = mattes


STEP = Step(
    name="matting",
    run=run,
    inputs=("session", "cameras", "plan", "config", "store"),
    product="mattes",
    params=("matting", "backdrops", "matting_drift"),
)
