"""``opacityhull build``: a session folder in, an opacity-hull model folder out.

Steps (each timed into ``report.json``):

1. **cameras** — object-frame camera of every view, from the first source present:
   the session's ``calibration`` phase (calibrated by :mod:`.calibration`), then its
   ``calibration/<camera>.yaml`` (known rig cameras), then ``cameras/`` (a camera per view,
   imported image sets). Nothing else is used silently: ``BuildConfig.cameras =
   "groundtruth"`` (simulated sessions) or ``"nominal"`` (the rig as designed) are
   debug options, recorded as such in the report. A camera the calibration phase
   cannot calibrate (fewer than three usable board views) is left out with its views,
   and the report says so (``BuildConfig.drop_uncalibrated_cameras``).
2. **matting** — per view, triangulation matting (:mod:`.matting`) over the
   ``matting`` phase: each backdrop pattern shot with the object is paired with the
   same pattern shot with the object absent (the backdrop ``B_k``). Without
   object-absent shots the backdrops are predicted from the patterns through the
   display geometry (:func:`.matting.backdrop_from_displays`), reported as such. An
   imported session's ``mask`` phase is its alpha.
3. **silhouettes** — ``alpha > alpha_threshold``, dilated by half a pixel for rig
   sessions (the quantisation of a matte thresholded at ½; none for imported masks,
   :func:`default_dilate_base_px`) plus the camera's calibration reprojection RMS (×
   ``dilate_rms_factor``), rounded up; conservative. Distorted cameras' silhouettes are
   resampled to pinhole.
4. **hull** — bounds by LP over the silhouettes (clipped at the table top for rig
   sessions: the object stands on the turntable), grown by two voxels, then the octree
   carve (:func:`.hull.carve_octree`). An empty hull raises :class:`.hull.EmptyHullError`.
5. **surfels** — LDC sampling of the hull (:func:`.surfels.sample_hull_surfels`), normals
   at the pixel-footprint scale.
6. **visibility** — z-buffer depth test per view (:func:`.visibility.surfel_visibility`).
7. **views** — the opacity light field sample of each view: alpha from the matte, colour
   from the ``lightfield`` image ``C = alpha F + (1 - alpha) B_off`` (displays off; the
   object-absent lightfield shot is subtracted when there is one, else ``B_off = 0``),
   stored straight: ``F = (C - (1 - alpha) B_off) / alpha`` where alpha > ``alpha_eps``,
   else 0.
8. **reflectance** — per view and light sample (light id, array angle) the
   one-light-at-a-time image as observed over the dark backdrops: premultiplied by
   construction; pixels with alpha <= ``alpha_eps`` are set to 0 (the panels' own
   reflection of the light is not part of the object). Images taken with the light
   dimmed to DMX level ``L`` (``extra["level"]`` of the record, else the plan's level)
   are scaled by ``255 / L``: the model holds radiance at full level.
9. **write** — :func:`opacityhull.model.write_model`, rig cameras as OpenCV YAML in
   ``calibration/``, ``report.json``.
9b. **optimize** (``BuildConfig.optimize``, ``build --optimize none|fast|full``; default
   none) — the written surfels fitted to the training views (:mod:`.steps.optimize`,
   :func:`opacityhull.optimize.fit.fit_model`) into ``MODEL/optimized/``; checkpoints in
   ``MODEL/build/optimize/``; the loss curve and ms per iteration in ``report.json``.
10. **pictures** — matte contact sheet, hull overlays, reprojection histogram.
11. **metrics** (``ground_truth=True``, simulated sessions) — alpha MAE per view inside
    the dilated object region, hull IoU against the voxelised ``groundtruth/object.ply``
    (and, to tell matting/carving error from what no visual hull can recover, the IoU of
    the hull carved from the *true* alphas against the object, and of our hull against
    that one), reprojection RMS, pose errors against ``groundtruth/calibration``.

**Hold-out** (``BuildConfig.hold_out``, ``build --hold-out every:N | VIEW,...``): the
``split`` step names test views; steps 3-6 run on the other views only, the test views'
visibility bits stay clear (never blended), and their cameras and views are still
written, listed in ``model.toml`` ``[split]`` for ``eval test``.

An empty silhouette in any view makes the hull empty; the build stops with an error
naming the views (exclude them with ``BuildConfig.exclude_views``) rather than writing
an empty model.

**Steps on disk.** Cameras, matting (per view), geometry (3-6), the natural field,
write and pictures each leave their product in ``MODEL/build/`` with an entry in
``MODEL/build/manifest.json`` (the digest of the inputs: image sha256s, sizes and
mtimes, the upstream products; and the parameters that shape it). ``build --resume``
(``build_model(resume=True)``) reuses every step whose entry still matches — inputs,
parameters, and each output file's digest as written (:func:`.buildstore.cached`) — and
each view already matted, and ``report.json``'s ``steps`` says which were reused. The
products are a cache of this build, not an interchange format (pickles for cameras and
geometry): ``MODEL/build/`` can be deleted once the model is finished.

**Memory.** Every per-view step reads, processes and writes one view at a time: the
alphas are read back from ``build/mattes`` on access, the silhouettes are kept
bit-packed (:class:`PackedMasks`), the classical carve stacks at most
:data:`CARVE_BATCH_MAX_VIEWS` views at once, the views are written as they are made.
``build_model(memory_gb=...)`` (``build --memory-gb``, default :data:`MEMORY_FRACTION` of
the RAM) caps the views in flight on a local pool and the carve batch
(:class:`MemoryPlan`); ``report.json`` gives ``memory_budget_gb`` and ``peak_rss_mb``.
The photo refinement's (V, H, W) stacks are the one part that still grows with the
views (ARCHITECTURE.md, build memory).
"""

from __future__ import annotations

import time
from pathlib import Path
from collections.abc import Callable

from ..errors import InputError
from ..model import BUILD_DIR
from ..session import Session, require_manifest_ok
from .buildconfig import (
    BACKDROP_SOURCES,
    CAMERA_SOURCES,
    CARVE_TOLERANCE_BY_VIEWS,
    DRIFT_MODES,
    RIG_DILATE_BASE_PX,
    SHADING_TEXTURE_STD,
    BuildConfig,
    BuildReport,
    DriftMode,
    Resolution,
    _Timer,
    choose_resolution,
    default_carve_tolerance,
    default_dilate_base_px,
    pixel_footprint_m,
)
from .buildstore import _StepStore, cached, file_digest
from .geometry import Geometry, build_geometry
from .holes import (
    _extensions_apply,
    _HolesFilled,
    bright_extension_masks,
    fill_shadow_holes,
    hole_masks,
    open_hole_masks,
    shadow_hole_masks,
    strong_silhouette,
)
from .lazyviews import (
    CARVE_BATCH_MAX_VIEWS,
    MEMORY_FRACTION,
    PHOTO_MIN_SLOTS,
    Mattes,
    MemoryPlan,
    PackedMasks,
    check_memory_gb,
    default_memory_gb,
    peak_rss_mb,
)
from .matte_step import load_matting_pairs, matte_for_build, store_matte
from .steps import cameras, geometry, holes, matting, metrics, natural, optimize, pictures, reflectance, split, write
from .steps.base import BuildContext, Step, check_steps
from .steps.cameras import resolve_cameras, step_cameras, view_list
from .steps.geometry import step_geometry
from .steps.matting import step_matting
from .steps.reflectance import step_reflectance
from .steps.write import _storage_metrics

__all__ = [
    "BuildConfig",
    "BuildReport",
    "build_model",
    "build_geometry",
    "choose_resolution",
    "Geometry",
    "Resolution",
    "pixel_footprint_m",
    "view_list",
    "load_matting_pairs",
    "resolve_cameras",
    "matte_for_build",
    "store_matte",
    "step_cameras",
    "step_matting",
    "step_geometry",
    "step_reflectance",
    "Mattes",
    "BUILD_DIR",
    "STEPS",
    "Step",
    "BuildContext",
    "cached",
    "file_digest",
    # re-exported for the modules and tests that import them from here
    "BACKDROP_SOURCES",
    "CAMERA_SOURCES",
    "CARVE_TOLERANCE_BY_VIEWS",
    "CARVE_BATCH_MAX_VIEWS",
    "DRIFT_MODES",
    "DriftMode",
    "MEMORY_FRACTION",
    "PHOTO_MIN_SLOTS",
    "RIG_DILATE_BASE_PX",
    "SHADING_TEXTURE_STD",
    "MemoryPlan",
    "PackedMasks",
    "check_memory_gb",
    "default_carve_tolerance",
    "default_dilate_base_px",
    "default_memory_gb",
    "fill_shadow_holes",
    "hole_masks",
    "open_hole_masks",
    "shadow_hole_masks",
    "bright_extension_masks",
    "strong_silhouette",
    "peak_rss_mb",
    "_HolesFilled",
    "_extensions_apply",
    "_storage_metrics",
]


def _verify(ctx: BuildContext) -> None:
    """What build would otherwise trust: every listed image there, with its size and
    sha256, and no id naming two files (``session.check_manifest``)."""
    t = time.perf_counter()
    require_manifest_ok(ctx.session, hash_files=ctx.config.verify_checksums)
    ctx.timer.seconds["verify"] = time.perf_counter() - t
    if ctx.ground_truth and ctx.session.groundtruth_dir is None:
        raise InputError(f"--ground-truth: {ctx.session.root} has no groundtruth/ folder (only simulated sessions do)")
    if ctx.config.hold_out is not None:  # bad input is refused before anything is written
        from ..riggeometry import view_id
        from .steps.split import resolve_hold_out

        views = view_list(ctx.session, exclude=ctx.config.exclude_views)
        resolve_hold_out(ctx.config.hold_out, [view_id(c, a) for c, a in views])
    if not ctx.config.verify_checksums:
        ctx.notes.append("manifest checksums were not verified (verify_checksums=False): sizes and ids only")


#: The build, in order. Adding a step: a module in ``steps/`` with ``run(ctx)`` and a
#: ``STEP = Step(...)`` naming what it reads and makes, and one line here (ARCHITECTURE.md).
STEPS: tuple[Step, ...] = (
    Step(name="verify", run=_verify, inputs=("session", "config"), params=("verify_checksums", "hold_out")),
    cameras.STEP,
    split.STEP,
    cameras.MEMORY,
    matting.STEP,
    holes.STEP,
    geometry.STEP,
    reflectance.STEP,
    natural.STEP,
    write.STEP,
    optimize.STEP,
    pictures.STEP,
    metrics.STEP,
)
check_steps(STEPS)


def build_model(
    session_dir,
    out_dir,
    *,
    config: BuildConfig = BuildConfig(),
    ground_truth: bool = False,
    progress: Callable[[int, int], None] | None = None,
    on_step: Callable[[str], None] | None = None,
    resume: bool = False,
    executor=None,
    memory_gb: float | None = None,
    steps: tuple[Step, ...] = STEPS,
) -> BuildReport:
    """Build the opacity-hull model of a session (see the module docstring): the
    ordered list ``steps`` (:data:`STEPS`) run over one :class:`.steps.base.BuildContext`.
    Each step's product and manifest entry (:func:`.buildstore.cached`: its inputs'
    digests, parameters, and its output files' digests) go to ``out_dir/build/``; with
    ``resume`` a step whose key matches and whose outputs are as written is reused
    (``BuildReport.steps``). ``model.toml`` is removed first and written last, so an
    interrupted build never looks finished.

    Parameters
    ----------
    session_dir : session folder, or an open :class:`~opacityhull.session.Session`.
    out_dir : model folder (created; files in it are overwritten).
    config : BuildConfig.
    ground_truth : compare with ``groundtruth/`` (simulated sessions) and put the
        metrics in the report.
    progress : callable(done, total) within the current step.
    on_step : callable(step name) when a step starts (CLI progress descriptions).
    resume : reuse an earlier build's unchanged steps (``build --resume``).
    executor : :class:`opacityhull.executor.Executor` for the per-view steps (matting);
        default serial. Every scheduler gives the same model bit for bit.
    memory_gb : the memory budget (``build --memory-gb``; default
        :data:`MEMORY_FRACTION` of the RAM; :class:`MemoryPlan`). The model does not
        depend on it.

    Returns
    -------
    BuildReport (also written to ``out_dir/report.json``).
    """
    budget_gb = check_memory_gb(default_memory_gb() if memory_gb is None else memory_gb)
    out = Path(out_dir)
    ctx = BuildContext(
        session=session_dir if isinstance(session_dir, Session) else Session.open(session_dir),
        out=out,
        config=config,
        store=_StepStore(out, resume=resume),
        timer=_Timer(on_step),
        progress=progress or (lambda done, total: None),
        executor=executor,
        ground_truth=ground_truth,
        budget_gb=budget_gb,
    )
    for step in steps:
        step.run(ctx)
    metrics.report(ctx, steps)
    return ctx.report
