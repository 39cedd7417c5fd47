"""Build step ``metrics``: ground truth (simulated sessions) and the report's metrics."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict

import numpy as np

from ...camera import read_opencv_yaml
from ...errors import InputError
from ..buildconfig import BuildReport
from ..hull import carve_octree, silhouette_from_alpha, undistort_silhouette
from ..lazyviews import peak_rss_mb
from ..lazyviews import _Subset
from .base import Step
from .matting import _drift_summary
from .write import _storage_metrics

log = logging.getLogger(__name__)


def _ground_truth_metrics(session, views, vids, alphas, occ, grid, cams, config, pin, dilations, view_cams) -> dict:
    from ...imageio import read_exr
    from ..metrics import alpha_mae, ground_truth_checks, hull_iou, read_mesh_ply, voxelize_mesh

    gt = session.groundtruth_dir
    m: dict = {}
    per_view = []
    true_sils = []
    for i, ((c, _), vid) in enumerate(zip(views, vids, strict=True)):
        p = gt / "alpha" / f"{vid}.exr"
        if not p.is_file():
            continue
        t = read_exr(p)[..., 0]
        a = alphas[i]
        same = t.shape == a.shape
        if same:
            per_view.append(alpha_mae(a, t, dilate_px=config.ground_truth_dilate_px))
        del a
        if not same:
            continue
        true_sils.append(silhouette_from_alpha(t, threshold=config.alpha_threshold, dilate_px=dilations.get(c, 0)))
    # the hull the same cameras would carve from perfect mattes: separates matting and
    # carving errors from what no visual hull can see (cavities, concavities)
    true_hull = None
    if len(true_sils) == len(vids):
        # the cameras of ``views`` (the training views of a --hold-out build), not every view's
        ts = [undistort_silhouette(s, cam)[0] for s, cam in zip(true_sils, view_cams, strict=True)]
        true_hull = carve_octree(ts, pin, grid, root_cell=config.root_cell)
    if per_view:
        w = np.array([r["pixels"] for r in per_view], dtype=np.float64)
        m["alpha_mae"] = float(np.sum([r["mae"] * r["pixels"] for r in per_view]) / max(w.sum(), 1))
        m["alpha_mae_worst_view"] = float(max(r["mae"] for r in per_view))
        fr = [r for r in per_view if r["fractional_pixels"]]
        if fr:
            nf = np.array([r["fractional_pixels"] for r in fr], dtype=np.float64)
            m["alpha_mae_fractional"] = float(
                np.sum([r["mae_fractional"] * r["fractional_pixels"] for r in fr]) / nf.sum()
            )
            m["alpha_fractional_recovered"] = float(
                np.sum([r["fractional_recovered"] * r["fractional_pixels"] for r in fr]) / nf.sum()
            )
            m["alpha_fractional_pixels"] = int(nf.sum())
        m["alpha_views_compared"] = len(per_view)
    mesh = gt / "object.ply"
    if mesh.is_file():
        Vt, Ft = read_mesh_ply(mesh)
        truth = voxelize_mesh(Vt, Ft, grid)
        h = hull_iou(occ, truth)
        m["hull_iou"] = h["iou"]
        m["hull_object_in_hull"] = h["object_in_hull"]
        if true_hull is not None:
            m["true_alpha_hull_iou"] = hull_iou(true_hull, truth)["iou"]
    if true_hull is not None:
        m["hull_iou_vs_true_alpha_hull"] = hull_iou(occ, true_hull)["iou"]
    if cams.calibration is not None and (gt / "calibration").is_dir():
        from ..calibration import pose_errors

        true_rig = [read_opencv_yaml(gt / "calibration" / f"{s.name}.yaml") for s in session.geometry.cameras]
        try:
            # in the true frame (what the hull is compared in), and after removing the
            # gauge (rotation about / shift along the table axis) calibration cannot see
            pe = pose_errors(cams.calibration, true_rig, align_gauge=False)
            pg = pose_errors(cams.calibration, true_rig, align_gauge=True)
            m["pose_max_rotation_deg"] = pe["max_rotation_deg"]
            m["pose_max_position_mm"] = pe["max_position_mm"]
            m["pose_max_focal_pct"] = pe["max_focal_pct"]
            m["pose_gauge_aligned_max_rotation_deg"] = pg["max_rotation_deg"]
            m["pose_gauge_aligned_max_position_mm"] = pg["max_position_mm"]
            m["pose_gauge_yaw_deg"] = pg["gauge_yaw_deg"]
            m["pose_gauge_dy_mm"] = pg["gauge_dy_mm"]
            m["pose_errors"] = pe
        except InputError as e:
            m["pose_errors_error"] = str(e)
    return m | {"ground_truth_checks": ground_truth_checks(m)}  # bounds and verdicts: metrics.py


def run(ctx) -> None:
    """The report's metrics: calibration, matting drift, ground truth (``ground_truth``,
    timed as ``metrics``), non-finite inputs and storage."""
    session, config, notes = ctx.session, ctx.config, ctx.notes
    cams, mattes = ctx.cameras.cams, ctx.mattes
    metrics: dict = {}
    if cams.calibration is not None:
        cal = cams.calibration
        metrics["reproj_rms_px"] = float(cal.rms_px)
        metrics["reproj_rms_px_per_camera"] = {
            cal.rig_cameras[c].name: float(cal.reproj_rms_px[c]) for c in cal.camera_indices
        }
        if cams.dropped_cameras:
            metrics["uncalibrated_cameras"] = {cal.rig_cameras[c].name: why for c, why in cams.dropped_cameras.items()}
    if mattes.stats:
        drift = _drift_summary(mattes.stats, mattes.drift_mode)
        ctx.geometry.hull_info["matting_drift"] = drift
        metrics["matting_drift_mode"] = drift["mode"]
        if drift["mode"] != "none":
            metrics["matting_drift_gain_max_dev"] = drift["gain_max_dev"]
            metrics["matting_shift_px_max"] = drift["shift_px_max"]
            if drift["shifts_applied"]:
                notes.append(
                    f"matting: {drift['shifts_applied']} backdrop shot(s) were misregistered by >= "
                    f"{config.matting.drift_options.apply_shift_px} px against their object shot and "
                    "were resampled"
                )
        else:
            notes.append(f"matting: photometric drift not corrected ({drift['why']})")
        metrics["matting_unknown_frac"] = float(np.mean([m["unknown_frac"] for m in mattes.stats]))
        metrics["matting_saturated_frac"] = float(np.mean([m["saturated_frac"] for m in mattes.stats]))
        metrics["matting_backdrops_K"] = int(np.median([m["K"] for m in mattes.stats]))
    if ctx.ground_truth:
        g = ctx.geometry.geometry
        with ctx.timer.step("metrics"):
            metrics.update(
                _ground_truth_metrics(
                    session,
                    [ctx.cameras.views[j] for j in ctx.geometry.train],
                    [ctx.cameras.vids[j] for j in ctx.geometry.train],
                    mattes.alphas
                    if len(ctx.geometry.train) == len(ctx.cameras.views)
                    else _Subset(mattes.alphas, ctx.geometry.train),
                    g.occ,
                    g.grid,
                    cams,
                    config,
                    g.pin,
                    ctx.geometry.dilations,
                    [cams.views[j] for j in ctx.geometry.train],
                )
            )
    if ctx.nonfinite:
        nonfinite = ctx.nonfinite
        notes.append(
            f"{len(nonfinite)} image(s) held NaN or Inf pixels, set to 0 (black) where used: "
            + "; ".join(nonfinite[:3])
            + (" ..." if len(nonfinite) > 3 else "")
        )
        metrics["nonfinite_images"] = len(nonfinite)
    metrics["manifest_verified"] = "sha256" if config.verify_checksums else "sizes and ids only"
    metrics.update(_storage_metrics(ctx.out, [v.id for v in ctx.model.view_infos], notes))
    ctx.metrics = metrics


def report(ctx, steps) -> None:
    """``report.json``: the build's figures, with ``steps`` in the order of ``steps``
    (what each did: ran / reused / reused k of n views)."""
    import json

    from ...jsonio import to_jsonable
    from ...imageio import atomic_path

    natural, _ = ctx.natural
    hull = ctx.geometry.hull_info
    timer = ctx.timer
    if "refine" in hull and "refine" in timer.detail:
        hull["refine"] = {**hull["refine"], **timer.detail["refine"]}
    if natural is not None:
        hull["natural"] = {k: v for k, v in natural.items() if k != "files"} | timer.detail.get("natural", {})
    ctx.notes.extend(n for n in ctx.store.notes if n not in ctx.notes)
    g = ctx.geometry.geometry
    rep = BuildReport(
        model_dir=str(ctx.out),
        views=len(ctx.cameras.views),
        surfels=len(g.surfels),
        camera_source=ctx.cameras.cams.source,
        backdrop_source=ctx.model.backdrop_source,
        hull=hull,
        notes=ctx.notes,
    )
    rep.pictures = list(ctx.pictures or [])
    rep.metrics = ctx.metrics
    rep.optimize = dict(ctx.fit or {})
    rep.seconds = {k: round(v, 4) for k, v in timer.seconds.items()}
    rep.seconds["total"] = round(sum(timer.seconds.values()), 4)
    rep.calibration_seconds = {k: round(v, 4) for k, v in timer.detail.get("calibration", {}).items()}
    rep.created_utc = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    rep.steps = {s.name: ctx.store.status[s.name] for s in steps if s.name in ctx.store.status}
    rep.scheduler = getattr(ctx.executor, "scheduler", "serial")
    rep.memory_budget_gb = float(ctx.budget_gb)
    rep.peak_rss_mb = round(peak_rss_mb(), 1)
    rep.memory = {
        **asdict(ctx.plan),
        "silhouettes_packed_bytes": int(getattr(g.sils, "nbytes", 0)),
        "note": "per-view steps hold one view at a time (in_flight views while matting on a local pool); "
        "see ARCHITECTURE.md, build memory",
    }
    with atomic_path(ctx.out / "report.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable(rep.to_dict()), indent=2) + "\n")
    ctx.report = rep


STEP = Step(
    name="metrics",
    run=run,
    inputs=("session", "cameras", "mattes", "geometry", "model", "config", "ground_truth"),
    product="metrics",
    params=("ground_truth_dilate_px",),
)
