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
10. **pictures** — matte contact sheet, hull overlays, reprojection histogram.
11. **metrics** (``ground_truth=True``, simulated sessions) — alpha MAE per view inside
    the dilated object region, hull IoU against the voxelised ``groundtruth/object.ply``
    (and, to tell matting/carving error from what no visual hull can recover, the IoU of
    the hull carved from the *true* alphas against the object, and of our hull against
    that one), reprojection RMS, pose errors against ``groundtruth/calibration``.

An empty silhouette in any view makes the hull empty; the build stops with an error
naming the views (exclude them with ``BuildConfig.exclude_views``) rather than writing
an empty model.

**Steps on disk.** Cameras, matting (per view), geometry (3-6), the natural field,
write and pictures each leave their product in ``MODEL/build/`` with an entry in
``MODEL/build/manifest.json`` (the digest of the inputs: image sha256s, sizes and
mtimes, the upstream products; and the parameters that shape it). ``build --resume``
(``build_model(resume=True)``) reuses every step whose entry still matches and each
view already matted, and ``report.json``'s ``steps`` says which were reused. The
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

import json
import logging
import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Literal, Sequence, cast

import numpy as np

from ..camera import Camera, read_colmap_text, read_opencv_yaml
from ..errors import ConfigError, FormatError, InputError
from ..model import (
    BRIGHT_EXTENSIONS,
    BUILD_DIR,
    FILLED_HOLES,
    OPEN_HOLES,
    REFLECTANCE_STORAGES,
    STORAGE_TYPES,
    LightSample,
    ReflectanceStorage,
    Storage,
    Surfels,
    ViewInfo,
    light_key,
    write_hole_masks,
    write_model,
)
from ..riggeometry import RigGeometry, view_id
from ..session import Session, check_finite, require_manifest_ok
from .hull import (
    EmptyHullError,
    HullGrid,
    backdrop_holes,
    bright_extensions,
    carve_octree,
    enclosed_holes,
    hull_bounds,
    silhouette_from_alpha,
    carve_robust,
    undistort_silhouette,
    view_rejections,
)
from .matting import MattingOptions, straight_from_premul
from .matte_step import _jsonable, _load_matte, _rgb, _stored_matte, load_matting_pairs, matte_for_build, store_matte
from .surfels import sample_hull_surfels
from .visibility import surfel_visibility

log = logging.getLogger(__name__)

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
]

CAMERA_SOURCES = ("auto", "groundtruth", "nominal")
DriftMode = Literal["auto", "none", "gain", "affine", "field"]
DRIFT_MODES: tuple[DriftMode, ...] = ("auto", "none", "gain", "affine", "field")
BACKDROP_SOURCES = ("auto", "object-absent", "geometry")
STEPS = (
    "verify",
    "cameras",
    "matting",
    "holes",
    "silhouettes",
    "hull",
    "surfels",
    "visibility",
    "refine",
    "views",
    "reflectance",
    "natural",
    "write",
    "pictures",
    "metrics",
)


@dataclass(frozen=True, kw_only=True)
class BuildConfig:
    """Options of :func:`build_model`.

    Parameters
    ----------
    hull_res : voxels along the longest side of the hull's bounding box, or None (the
        default): chosen from the photographs' pixel footprint on the object so there is
        one surfel per projected pixel or finer (:func:`choose_resolution`).
    max_hull_res : cap of the automatic grid (memory grows with its cube); past it the
        LDC rays are oversampled to keep the surfel spacing.
    surfels_per_pixel : automatic resolution: surfel spacing = footprint / this.
    carve_tolerance : robust carving under imperfect masks (:func:`.hull.carve_robust`):
        a voxel seen as background through a view's outer contour is removed; one seen
        through enclosed holes survives up to this many such views. None (default):
        :func:`default_carve_tolerance` (0 for rig sessions, whose triangulation mattes
        have no shadow holes; for imported image sets 1 from 8 views, 2 from 16).
    backdrop_holes : with a tolerant carve, mask holes whose photograph shows the
        backdrop (:func:`open_hole_masks`) carve like the outer contour (see-through
        gaps); False treats every enclosed hole as doubtful.
    fill_shadow_holes : with imported masks, a tolerant carve and ``backdrop_holes``, the
        other enclosed holes — brighter than the backdrop, so shadows on the object that
        a threshold lost (:func:`shadow_hole_masks`) — are opaque in the views' alpha,
        the opacity the blending uses; where they were filled is kept in
        ``MODEL/build/filled_holes.npz`` so that ``eval loo`` still compares with the
        photograph's own mask.
    doubt_bright_extensions : with imported masks and a tolerant carve, the thick
        bright extensions of a mask's outline (:func:`bright_extension_masks`: a
        shadowed part that sticks out past the outline, which the threshold lost) are
        doubtful like shadow holes: no single view carves through them, only the
        tolerant count (``report.json`` hull ``bright_extensions``; the pixels in
        ``MODEL/build/bright_extensions.npz``, which the geometry holdout reuses). Rig
        sessions (tolerance 0) never use it. Measured (every 4th / 2nd view held out):
        dino geometry holdout 17.95 -> 18.39 / 18.28 -> 18.88 dB, interior alpha 0.986
        -> 0.992; temple 19.04 -> 19.01 / 18.97 -> 18.89 dB.
    matting_drift : photometric drift and registration correction of the backdrops
        (:func:`.matting.correct_photometric_drift`; reported per shot in
        ``report.json``): "auto" = "field" except for the simulated rig without a sensor
        drift model (identical by construction).
    refine : photo-consistent depth inside the hull (:func:`.photo.refine_surfels`).
        "shading" (default): the surfels stay on the hull, whose outline and opacity
        are exact in every view, and carry the refined depth (``Surfels.depth_m``, the
        ``depth`` property of ``surfels.ply``) at which the renderer fetches colour.
        "surfels": the surfels themselves move there (their outline shrinks; measured
        +0.1 dB on the Middlebury rings). "none": hull only. ``True``/``False`` mean
        "surfels"/"none". Figures: ``benchmarks/out/fidelity.md``.
    natural, natural_kernels : estimate the natural-illumination reflectance field
        (:mod:`.natural_field`, K box kernels per pixel) when the session has the
        natural (``envmatte``) phase.
    verify_checksums : check every manifest record's sha256 before building (sizes and
        duplicate ids are always checked); the report says which was done.
    alpha_threshold : silhouette = alpha > threshold.
    matting : MattingOptions of the triangulation matting.
    dilate_base_px, dilate_rms_factor : silhouettes are dilated by a disc of radius
        ``ceil(dilate_base_px + dilate_rms_factor * reprojection RMS)`` px; the RMS term
        absorbs calibration error. ``dilate_base_px`` None (default):
        :func:`default_dilate_base_px`, half a pixel for rig sessions (the quantisation of
        a matte thresholded at ½: measured, 6 % of a sphere's voxels were cut without it)
        and 0 for imported masks.
    surfel_oversample : LDC rays per voxel column and transverse axis.
    bisection_iters : bisection steps per surfel (precision voxel / 2**iters).
    radius_scale : multiplies the hole-free surfel radius.
    depth_tol_m : visibility z-buffer tolerance (None: the largest surfel radius).
    facing_cos : visibility back-face limit (cosine between normal and view direction).
    bounds_m : ((x0, y0, z0), (x1, y1, z1)) object-frame box for the hull, or None (LP).
    bounds_min_component_frac : the LP box ignores silhouette components smaller than this
        fraction of the largest (matting specks); the carve uses every pixel.
    clip_below_table : for rig sessions, no hull below the table top (y < 0).
    cameras : "auto" (calibration phase → calibration/ → cameras/), or the debug
        sources "groundtruth" and "nominal".
    backdrops : "auto" (object-absent captures, else the display geometry),
        "object-absent" (required) or "geometry" (always predicted; for comparisons).
    exclude_views : view ids left out of the model.
    drop_uncalibrated_cameras : with a calibration phase, a camera that cannot be
        calibrated (fewer than three usable board views) is left out with its views and a
        note in the report; False makes it an error.
    root_cell : octree root cell edge (voxels, power of two).
    alpha_eps : below this alpha the straight colour is 0.
    reflectance : attach one-light-at-a-time images when the session has them.
    pictures : write the PNG pictures.
    ground_truth_dilate_px : dilation of the object region for ``alpha_mae``.
    storage : pixel type of the model's ``views/`` and ``reflectance/`` EXRs (same values,
        no scale): "half" (default: half the bytes per view; leave-one-out and relighting
        figures unchanged, ``benchmarks/out/scale.md``) or "float" (32-bit). Values
        beyond the half range are clamped and listed in the report.
    reflectance_storage : how ``reflectance/`` holds the one-light images: "layers" (one
        EXR layer per light sample, the default) or "pca"
        (:mod:`opacityhull.reflectance_pca`; readers get the same layers back, rebuilt):
        one PCA per ``pca_block``-pixel block of each view (None: one for the view), rank
        ``pca_rank`` in every block or, when None, the fewest components over the view's
        blocks whose relative Frobenius error is at most ``pca_error``; ranks, measured
        errors and the ratio go to ``model.toml`` and the report. Measured on the
        analytic sphere (60 lights, 320x240): 6.4x fewer bytes at 1 %, 11.9x at 3 %
        (relit error 1.1 %), ``benchmarks/out/reflectance_pca.md``. Not the default: at
        1 % the saving is below the paper's 10x.
    """

    hull_res: int | None = None
    max_hull_res: int = 640
    surfels_per_pixel: float = 1.0
    carve_tolerance: int | None = None
    backdrop_holes: bool = True
    fill_shadow_holes: bool = True
    doubt_bright_extensions: bool = True
    matting_drift: DriftMode = "auto"
    verify_checksums: bool = True
    refine: Literal["shading", "surfels", "none"] | bool = "shading"
    natural: bool = True
    natural_kernels: int = 25
    alpha_threshold: float = 0.5
    matting: MattingOptions = MattingOptions()
    dilate_base_px: float | None = None
    dilate_rms_factor: float = 1.0
    surfel_oversample: int = 1
    bisection_iters: int = 10
    radius_scale: float = 1.0
    depth_tol_m: float | None = None
    facing_cos: float = -0.1
    bounds_m: tuple | None = None
    bounds_min_component_frac: float = 0.02
    clip_below_table: bool = True
    cameras: str = "auto"
    backdrops: str = "auto"
    exclude_views: tuple[str, ...] = ()
    drop_uncalibrated_cameras: bool = True
    root_cell: int = 32
    alpha_eps: float = 1e-3
    reflectance: bool = True
    pictures: bool = True
    ground_truth_dilate_px: int = 3
    storage: Storage = "half"
    reflectance_storage: ReflectanceStorage = "layers"
    pca_rank: int | None = None
    pca_error: float = 0.01
    pca_block: int | None = 8

    def __post_init__(self):
        if isinstance(self.refine, bool):
            object.__setattr__(self, "refine", "surfels" if self.refine else "none")
        if self.refine not in ("shading", "surfels", "none"):
            raise ConfigError(f"refine must be 'shading', 'surfels' or 'none', got {self.refine!r}")
        if self.hull_res is not None and not (4 <= int(self.hull_res) <= 2048):
            raise ConfigError(f"hull_res must be in [4, 2048], got {self.hull_res}")
        if not (8 <= int(self.max_hull_res) <= 2048):
            raise ConfigError(f"max_hull_res must be in [8, 2048], got {self.max_hull_res}")
        if not (isinstance(self.surfels_per_pixel, (int, float)) and 0.1 <= self.surfels_per_pixel <= 8):
            raise ConfigError(f"surfels_per_pixel must be in [0.1, 8], got {self.surfels_per_pixel}")
        if self.carve_tolerance is not None and not (
            isinstance(self.carve_tolerance, int) and self.carve_tolerance >= 0
        ):
            raise ConfigError(f"carve_tolerance must be None or an integer >= 0, got {self.carve_tolerance!r}")
        if self.matting_drift not in DRIFT_MODES:
            raise ConfigError(f"matting_drift must be auto, none, gain, affine or field, got {self.matting_drift!r}")
        if not (isinstance(self.natural_kernels, int) and 1 <= self.natural_kernels <= 256):
            raise ConfigError(f"natural_kernels must be an integer in [1, 256], got {self.natural_kernels!r}")
        if int(self.surfel_oversample) < 1:
            raise ConfigError(f"surfel_oversample must be >= 1, got {self.surfel_oversample}")
        if not (0.0 <= self.alpha_threshold < 1.0):
            raise ConfigError(f"alpha_threshold must be in [0, 1), got {self.alpha_threshold}")
        if self.cameras not in CAMERA_SOURCES:
            raise ConfigError(f"cameras must be one of {CAMERA_SOURCES}, got {self.cameras!r}")
        if self.backdrops not in BACKDROP_SOURCES:
            raise ConfigError(f"backdrops must be one of {BACKDROP_SOURCES}, got {self.backdrops!r}")
        if self.dilate_rms_factor < 0 or (self.dilate_base_px is not None and self.dilate_base_px < 0):
            raise ConfigError("dilate_rms_factor and dilate_base_px must be >= 0")
        if self.bounds_m is not None:
            b = np.asarray(self.bounds_m, dtype=np.float64)
            if b.shape != (2, 3) or not np.all(b[1] > b[0]):
                raise ConfigError(
                    f"bounds_m must be ((x0, y0, z0), (x1, y1, z1)) with x1 > x0 ..., got {self.bounds_m}"
                )
        if self.storage not in STORAGE_TYPES:
            raise ConfigError(f"storage must be one of {', '.join(map(repr, STORAGE_TYPES))}, got {self.storage!r}")
        if self.reflectance_storage not in REFLECTANCE_STORAGES:
            raise ConfigError(
                f"reflectance_storage must be one of {', '.join(map(repr, REFLECTANCE_STORAGES))}, "
                f"got {self.reflectance_storage!r}"
            )
        if self.pca_rank is not None and (
            isinstance(self.pca_rank, bool) or not isinstance(self.pca_rank, int) or self.pca_rank < 1
        ):
            raise ConfigError(f"pca_rank must be None or an integer >= 1, got {self.pca_rank!r}")
        if not (isinstance(self.pca_error, (int, float)) and 0.0 < float(self.pca_error) < 1.0):
            raise ConfigError(f"pca_error must be a relative error in (0, 1), got {self.pca_error!r}")
        if self.pca_block is not None and (
            isinstance(self.pca_block, bool) or not isinstance(self.pca_block, int) or self.pca_block < 2
        ):
            raise ConfigError(f"pca_block must be None (one PCA per view) or an integer >= 2, got {self.pca_block!r}")
        object.__setattr__(self, "exclude_views", tuple(self.exclude_views))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["matting"] = asdict(self.matting)
        return d


@dataclass
class BuildReport:
    """What :func:`build_model` did: counts, timings per step (s), metrics, decisions."""

    model_dir: str
    views: int
    surfels: int
    seconds: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    camera_source: str = ""
    backdrop_source: str = ""
    hull: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    pictures: list = field(default_factory=list)
    #: step name -> "ran" | "reused" | "reused k of n views" (``build --resume``)
    steps: dict = field(default_factory=dict)
    scheduler: str = "serial"
    #: the ``--memory-gb`` budget the build planned with, and this process's peak RSS
    memory_budget_gb: float = 0.0
    peak_rss_mb: float = 0.0
    #: how the budget was spent (:class:`MemoryPlan`) and what each stage held
    memory: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> dict:
        """The ``--json`` object: views, surfels, seconds, metrics (+ where and how)."""
        return {
            "views": self.views,
            "surfels": self.surfels,
            "seconds": dict(self.seconds),
            "metrics": dict(self.metrics),
            "model": self.model_dir,
            "camera_source": self.camera_source,
            "backdrop_source": self.backdrop_source,
            "resolution": self.hull.get("resolution"),
            "carve_tolerance": self.hull.get("carve_tolerance"),
            "views_disagreeing_with_hull": self.hull.get("views_disagreeing_with_hull", []),
            "steps": dict(self.steps),
            "scheduler": self.scheduler,
            "memory_budget_gb": self.memory_budget_gb,
            "peak_rss_mb": self.peak_rss_mb,
        }


# --------------------------------------------------------------------------- helpers


class _Timer:
    def __init__(self, on_step):
        self.seconds: dict[str, float] = {}
        self.on_step = on_step

    @contextmanager
    def step(self, name: str):
        if self.on_step is not None:
            self.on_step(name)
        t = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t


def view_list(session: Session, *, exclude: Sequence[str] = ()) -> list[tuple[int, float]]:
    """The views of the model: (camera, table_deg) of the lightfield phase, else of the
    matting or mask phase; minus ``exclude`` (view ids)."""
    phases = session.phases()
    for ph in ("lightfield", "matting", "mask"):
        if ph in phases:
            views = session.views(ph)
            break
    else:
        raise FormatError(f"{session.root}: no lightfield, matting or mask images: nothing to build from")
    ex = set(exclude)
    unknown = ex - {view_id(c, a) for c, a in views}
    if unknown:
        raise InputError(f"exclude_views: {sorted(unknown)[:5]} are not views of {session.root}")
    out = [(c, a) for c, a in views if view_id(c, a) not in ex]
    if not out:
        raise InputError(f"{session.root}: every view is excluded")
    return out


def _read_yaml_number(path: Path, key: str) -> float | None:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode(key)
        return None if node.empty() else float(node.real())
    finally:
        fs.release()


@dataclass
class _Cameras:
    views: list[Camera]
    #: rig cameras by index, None for a camera that could not be calibrated
    rig: Sequence[Camera | None] | None
    rms_px: dict[int, float]
    source: str
    calibration: Any = None  # the CalibrationResult when calibrated here
    #: the views these cameras belong to (``views`` minus those of uncalibrated cameras)
    kept: list | None = None
    #: camera index → why it was left out (its views dropped)
    dropped_cameras: dict = field(default_factory=dict)


def resolve_cameras(
    session: Session,
    views: Sequence[tuple[int, float]],
    *,
    source: str = "auto",
    progress=None,
    drop_uncalibrated: bool = True,
) -> _Cameras:
    """Object-frame cameras of ``views`` (see the module docstring for the order).

    Returns an object with ``views`` (Camera per kept view, named by view id), ``kept``
    (the kept views: all of ``views`` unless a camera could not be calibrated),
    ``dropped_cameras`` (camera index → reason), ``rig`` (rig cameras or None; None
    entries for uncalibrated cameras), ``rms_px`` (camera index → reprojection RMS),
    ``source`` and ``calibration`` (the CalibrationResult when calibrated here).

    ``drop_uncalibrated``: with a calibration phase, a camera without three usable
    board views is left uncalibrated and its views are dropped (``kept``); False makes
    it an error (:class:`.calibration.CalibrationError`).
    """
    views = list(views)
    vids = [view_id(c, a) for c, a in views]
    if source == "groundtruth":
        gt = session.groundtruth_dir
        if gt is None or not (gt / "cameras" / "images.txt").is_file():
            raise InputError(f"--cameras groundtruth: {session.root} has no groundtruth/cameras (not simulated?)")
        cams = dict(read_colmap_text(gt / "cameras"))
        missing = [v for v in vids if v not in cams]
        if missing:
            raise FormatError(f"{gt / 'cameras'}: no true camera for views {missing[:5]}")
        rig = None
        if (gt / "calibration").is_dir():
            rig = [read_opencv_yaml(gt / "calibration" / f"{s.name}.yaml") for s in session.geometry.cameras]
        return _Cameras([cams[v].with_name(v) for v in vids], rig, {}, "groundtruth (debug)")
    if source == "nominal":
        g = session.geometry
        rig = g.nominal_cameras()
        return _Cameras(
            [RigGeometry.view_camera(rig[c], a, name=view_id(c, a)) for c, a in views],
            rig,
            {},
            "nominal (debug: the rig as designed, not calibrated)",
        )
    # auto
    if "calibration" in session.phases():
        from .calibration import CalibrationConfig, CalibrationError, calibrate_session, view_cameras

        try:
            result = calibrate_session(
                session, progress=progress, config=CalibrationConfig(skip_unusable_cameras=drop_uncalibrated)
            )
        except CalibrationError as e:
            # never fall back silently to another camera source: say what to do instead
            raise CalibrationError(
                f"{e} — the session's calibration phase could not be used; fix the "
                "calibration captures, or (debugging only) build with --cameras "
                "groundtruth|nominal"
            ) from None
        ok = set(result.camera_indices)
        kept = [(c, a) for c, a in views if c in ok]
        dropped = {}
        for c in sorted({c for c, _ in views} - ok):
            dropped[c] = result.uncalibrated.get(c, "not calibrated")
        if not kept:
            raise CalibrationError(
                f"{session.root}: no camera could be calibrated from the calibration phase ("
                + "; ".join(f"camera {c}: {why}" for c, why in dropped.items())
                + ") — nothing to build. Fix the calibration captures, or (debugging only) build with "
                "--cameras groundtruth|nominal"
            )
        cams = view_cameras(result, kept)
        # only calibrated cameras have an RMS (uncalibrated ones report NaN)
        rms = {
            c: float(result.reproj_rms_px[c])
            for c in result.camera_indices
            if math.isfinite(float(result.reproj_rms_px[c]))
        }
        rig = [rc if i in ok else None for i, rc in enumerate(result.rig_cameras)]
        return _Cameras(list(cams), rig, rms, "calibration phase (calibrated)", result, kept, dropped)
    known = session.calibration_cameras()
    if known:
        missing = sorted({c for c, _ in views} - set(known))
        if missing:
            raise FormatError(f"{session.root / 'calibration'}: no YAML for camera(s) {missing}")
        rms = {}
        for i, spec in enumerate(session.geometry.cameras):
            p = session.root / "calibration" / f"{spec.name}.yaml"
            if p.is_file():
                r = _read_yaml_number(p, "reproj_rms_px")
                if r is not None:
                    if not (math.isfinite(r) and r >= 0):
                        # the silhouettes are dilated by this: an unknown RMS cannot size that
                        raise FormatError(
                            f"{p}: reproj_rms_px is {r}; expected a finite number >= 0 (or no "
                            "such key when the calibration error is unknown)"
                        )
                    rms[i] = r
        rig = [known.get(i) for i in range(len(session.geometry.cameras))]
        return _Cameras(
            [RigGeometry.view_camera(known[c], a, name=view_id(c, a)) for c, a in views],
            rig,
            rms,
            "calibration/ (known rig cameras)",
        )
    per_view = session.view_cameras()
    if per_view:
        missing = [v for v in vids if v not in per_view]
        if missing:
            raise FormatError(f"{session.root / 'cameras'}: no camera for views {missing[:5]}")
        return _Cameras([per_view[v] for v in vids], None, {}, "cameras/ (per-view, imported)")
    raise FormatError(
        f"{session.root}: no cameras — the session has no calibration phase, no calibration/<camera>.yaml and "
        "no cameras/ model. Capture the ChArUco board, add calibration files, or (debugging only) use "
        "--cameras groundtruth|nominal"
    )


def _colour_shot(session: Session, camera: int, table_deg: float) -> tuple[str | None, str | None]:
    """(object shot, object-absent shot) giving the view's colour."""
    lf = session.select(phase="lightfield", camera=camera, table_deg=table_deg, kind=None)
    obj = sorted({r.shot for r in lf if r.object_present})
    bg = sorted({r.shot for r in lf if not r.object_present})
    if obj:
        return obj[0], (bg[0] if bg else None)
    mt = session.select(phase="matting", camera=camera, table_deg=table_deg, kind=None, pattern=None)
    obj = sorted({r.shot for r in mt if r.object_present})
    bg = sorted({r.shot for r in mt if not r.object_present})
    if obj:
        return obj[0], (bg[0] if bg else None)
    return None, None


def _plan_reflectance_level(session: Session):
    """The reflectance phase's DMX level from the plan recorded in the session (None if
    not recorded)."""
    plan = session.meta.get("plan", {})
    ph = plan.get("phases", {}).get("reflectance", {}) if isinstance(plan, dict) else {}
    return ph.get("level") if isinstance(ph, dict) else None


def _camera_names(session: Session) -> dict[int, str]:
    if "rig" not in session.meta:  # an imported session: no rig, no camera names
        return {}
    return {i: c.name for i, c in enumerate(session.geometry.cameras)}


def _rig_volume(geo: RigGeometry | None) -> tuple[np.ndarray, np.ndarray] | None:
    """A generous box above the table (for unbounded LPs): the bottom display's extent."""
    if geo is None:
        return None
    bottom = [d for d in geo.displays if d.rotates_with_table]
    if bottom:
        w, h = bottom[0].size_m
        r = 0.5 * math.hypot(w, h)
    else:
        r = 2.0 * float(np.linalg.norm(geo.target_m)) + 0.5
    top = 2.0 * r
    return np.array([-r, 0.0, -r]), np.array([r, top, r])


def _drift_mode(session: Session, config: "BuildConfig") -> str:
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


def _is_rig_session(session: Session) -> bool:
    return not str(session.source).startswith("import:") and "mask" not in session.phases()


SHADING_TEXTURE_STD = 0.003
"""``PhotoConfig.texture_std`` of the shading-depth refinement (``refine="shading"``): a
third of the surfel refinement's 0.01. Only the colour is looked up at the found depth
(the surfels stay on the hull), so a faint texture's depth is worth taking. Measured on the
Middlebury rings (every 4th view held out, geometry rebuilt without it, carve tolerance
2): dinoSR 18.68 -> 18.90 dB (interior 23.59 -> 24.04), templeSR 19.03 -> 19.02 dB; at
tolerance 1 dinoSR 18.38 -> 18.62, templeSR 19.01 -> 19.00. Deeper candidates
(``d_max_px`` 12 -> 40) gained 0.17 dB on the dino but lost 0.47 dB on the temple."""


CARVE_TOLERANCE_BY_VIEWS = ((16, 2), (8, 1))
"""(at least this many views, tolerance) of imported image sets, first match wins (see
:func:`default_carve_tolerance`)."""


RIG_DILATE_BASE_PX = 0.5
"""``BuildConfig.dilate_base_px`` of rig sessions (see :func:`default_dilate_base_px`)."""


def default_dilate_base_px(config: "BuildConfig", *, rig_session: bool) -> float:
    """``config.dilate_base_px``, or when None the default: :data:`RIG_DILATE_BASE_PX` for
    rig sessions, 0 for imported masks.

    A rig's triangulation matte thresholded at ½ can put the true outline up to half a
    pixel outside the silhouette. Imported masks are the other tool's thresholds, and a
    low one already reaches past the object's edge (the Middlebury masks: 0.19 of the
    brightest channel on a black backdrop), so half a pixel more, which the disc rounds up
    to one, only fattens the hull. Measured on the Middlebury rings (every 4th view held
    out, coincident views together; 1 px -> 0 px): templeSR geometry holdout 16.38 ->
    16.89 dB, blend 18.50 -> 19.37 dB; dinoSR 18.90 -> 19.29 dB, blend 21.26 -> 21.97 dB,
    coverage IoU 0.967 -> 0.967."""
    if config.dilate_base_px is not None:
        return float(config.dilate_base_px)
    return RIG_DILATE_BASE_PX if rig_session else 0.0


def default_carve_tolerance(config: "BuildConfig", *, rig_session: bool, n_views: int) -> int:
    """``config.carve_tolerance``, or when None the default: 0 for rig sessions
    (triangulation mattes) and for imported sets under 8 views; 1 from 8 views, 2 from 16.

    Why it grows with the views: every extra thresholded mask is one more chance that a
    shadow hole or a lost dark rim doubts a voxel, so the count that a real gap needs must
    grow too. Measured on the 16-view Middlebury rings (every 4th view held out, geometry
    rebuilt without it, tolerance 1 -> 2 -> 3): dinoSR 18.38 -> 18.68 -> 18.88 dB, coverage
    IoU 0.930 -> 0.933 -> 0.934; templeSR 19.01 -> 19.03 -> 19.00 dB. 3 gains a little
    more on the dino, loses on the temple and doubts more of every mask: 2. The outer
    contour carves at any tolerance, so the outlines stay the masks'."""
    if config.carve_tolerance is not None:
        return int(config.carve_tolerance)
    if rig_session:
        return 0
    for views, tol in CARVE_TOLERANCE_BY_VIEWS:
        if n_views >= views:
            return tol
    return 0


# --------------------------------------------------------------------------- geometry


@dataclass(frozen=True, kw_only=True)
class Resolution:
    """The hull grid and surfel spacing :func:`choose_resolution` picked, and why."""

    hull_res: int
    oversample: int
    pixel_footprint_m: float
    voxel_m: float
    surfel_spacing_m: float
    reason: str

    def to_dict(self) -> dict:
        return asdict(self)


def pixel_footprint_m(cameras: Sequence[Camera], centre) -> float:
    """Median over the views of the size of one pixel on the object, metres: the
    distance from the camera centre to ``centre`` over the focal length in pixels."""
    c = np.asarray(centre, dtype=np.float64)
    fp = [float(np.linalg.norm(cam.centre_world - c)) / max(min(cam.fx, cam.fy), 1e-12) for cam in cameras]
    return float(np.median(fp))


def choose_resolution(lo, hi, cameras: Sequence[Camera], *, config: "BuildConfig") -> Resolution:
    """Hull resolution and surfel oversampling from the photographs' pixel footprint.

    By default (``config.hull_res is None``) a voxel is the pixel footprint divided by
    ``config.surfels_per_pixel`` along the box's longest side, so surfels are one per
    projected pixel or finer: the model is never coarser than the capture. Above
    ``config.max_hull_res`` the grid is capped (memory grows with its cube) and the LDC
    rays are oversampled instead, which keeps the surfel spacing at the footprint.
    ``config.hull_res`` (``--hull-res``) overrides; a coarser-than-capture result is then
    stated in the reason, never silent.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    ext = float(np.max(hi - lo))
    fp = pixel_footprint_m(cameras, 0.5 * (lo + hi))
    target = fp / float(config.surfels_per_pixel)
    if config.hull_res is not None:
        res = int(config.hull_res)
        over = int(config.surfel_oversample)
        spacing = ext / res / over
        why = f"--hull-res {res} (override)"
        if spacing > 1.5 * fp:
            why += f": surfel spacing {spacing * 1e3:.3g} mm is coarser than the pixel footprint {fp * 1e3:.3g} mm"
        return Resolution(
            hull_res=res, oversample=over, pixel_footprint_m=fp, voxel_m=ext / res, surfel_spacing_m=spacing, reason=why
        )
    want = max(8, int(math.ceil(ext / target - 1e-9)))
    res = min(want, int(config.max_hull_res))
    over = max(int(config.surfel_oversample), int(math.ceil(want / res - 1e-9)))
    why = (
        f"auto: one surfel per {1.0 / config.surfels_per_pixel:.3g} projected pixel (footprint "
        f"{fp * 1e3:.3g} mm over a {ext * 1e3:.3g} mm box)"
    )
    if res < want:
        why += f"; grid capped at {res} (max_hull_res), LDC rays oversampled {over}x to keep the spacing"
    return Resolution(
        hull_res=res,
        oversample=over,
        pixel_footprint_m=fp,
        voxel_m=ext / res,
        surfel_spacing_m=ext / res / over,
        reason=why,
    )


@dataclass(frozen=True, kw_only=True)
class Geometry:
    """What :func:`build_geometry` made: pinhole silhouettes and cameras, the carved
    grid, the surfels with visibility, and what to report."""

    #: pinhole silhouettes per view (:class:`PackedMasks`; a list in geometry pickled before)
    sils: Sequence
    pin: list
    dilations: list
    occ: np.ndarray
    grid: HullGrid
    surfels: Surfels
    info: dict
    notes: list


#: :func:`bright_extension_masks`: how far beyond the outline to look, as a fraction of
#: the object's size in pixels (the square root of its mask area; the dino's plates
#: stick out 5-16 px at ~250 px), the opening's radius (px: the glow's width) and the
#: brightness limit between backdrop (0) and object (1). Measured on the dino at every
#: 4th view: margin 0.15 / 0.2 / 0.25 / 0.35 -> geometry holdout 18.32 / 18.39 / 18.36 /
#: 18.06 dB (17.95 without); 0.08 doubts the whole glow band (147 k px) and loses 0.17 dB
BRIGHT_REACH_FRAC = 0.06
BRIGHT_OPEN_PX = 3
BRIGHT_MARGIN = 0.2


def hole_masks(alpha: np.ndarray, photo_rgb: np.ndarray, *, threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """``(open, shadow)``, (H, W) bool each: a view's mask's enclosed holes (α ≤
    ``threshold``) split by the raw photograph's luminance in display values
    (:func:`.hull.backdrop_holes`): those that show the backdrop (see-through gaps, to
    carve) and the others (shadows as dark as the backdrop, which a threshold lost).
    Neither depends on the other holes being filled: the judgement is each hole's own
    brightness against the backdrop outside the outer contour."""
    sil = np.asarray(alpha) > threshold
    lum = _display_luminance(photo_rgb)
    filled = enclosed_holes(sil)
    open_ = filled & ~backdrop_holes(sil, lum)
    return open_, filled & ~sil & ~open_


def _display_luminance(photo_rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 luminance in display values (0-1) of a linear RGB photograph."""
    rgb = np.nan_to_num(np.asarray(photo_rgb, np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32), 0.0, None) ** (1.0 / 2.2)


def bright_extension_masks(
    alpha: np.ndarray,
    photo_rgb: np.ndarray,
    *,
    threshold: float = 0.5,
    reach_frac: float = BRIGHT_REACH_FRAC,
    open_px: int = BRIGHT_OPEN_PX,
    margin: float = BRIGHT_MARGIN,
) -> np.ndarray:
    """(H, W) bool: the thick bright extensions of a view's mask (α > ``threshold``;
    :func:`.hull.bright_extensions` on the raw photograph's display luminance), looked for
    within ``ceil(reach_frac * sqrt(A))`` px of an object of A mask pixels (holes
    filled). A tolerant carve doubts them like the shadow holes
    (``BuildConfig.doubt_bright_extensions``)."""
    sil = np.asarray(alpha) > threshold
    if not reach_frac >= 0:
        raise InputError(f"bright_extension_masks: reach_frac must be >= 0, got {reach_frac}")
    r = int(math.ceil(reach_frac * math.sqrt(float(enclosed_holes(sil).sum())) - 1e-9))
    return bright_extensions(sil, _display_luminance(photo_rgb), reach_px=r, open_px=open_px, margin=margin)


def open_hole_masks(alpha: np.ndarray, photo_rgb: np.ndarray, *, threshold: float = 0.5) -> np.ndarray:
    """The see-through holes of :func:`hole_masks`: carved like the outer contour."""
    return hole_masks(alpha, photo_rgb, threshold=threshold)[0]


def shadow_hole_masks(alpha: np.ndarray, photo_rgb: np.ndarray, *, threshold: float = 0.5) -> np.ndarray:
    """The shadow holes of :func:`hole_masks`: the enclosed holes that do *not* show the
    backdrop."""
    return hole_masks(alpha, photo_rgb, threshold=threshold)[1]


def strong_silhouette(
    silhouette: np.ndarray, *, open_holes: np.ndarray | None = None, doubtful_extensions: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """The strong silhouette of a tolerant carve (:func:`.hull.carve_robust`), outside which a
    rejection is trusted: the silhouette with its enclosed holes filled, minus the holes
    that show the backdrop (``open_holes``), plus the outline's bright extensions
    (``doubtful_extensions``: doubted, not trusted). Returns it ((H, W) bool) and the
    number of extension pixels it added. The build applies it to each view's dilated
    silhouette before undistorting; ``benchmarks/outline.py`` to the stored pinhole ones."""
    t = enclosed_holes(np.asarray(silhouette, bool))
    if open_holes is not None:
        t &= ~np.asarray(open_holes, bool)
    n_ext = 0
    if doubtful_extensions is not None:
        db = np.asarray(doubtful_extensions, bool) & ~t
        n_ext = int(db.sum())
        t |= db
    return t, n_ext


class _HolesFilled(Sequence):
    """``alphas`` with each view's ``fill`` mask (:class:`PackedMasks`, entries may be
    None) set to 1 on access; one view at a time, like the alphas it wraps."""

    def __init__(self, alphas: Sequence, fill: "PackedMasks"):
        if len(alphas) != len(fill):
            raise InputError(f"_HolesFilled: {len(fill)} fill masks for {len(alphas)} alphas")
        self.alphas, self.fill = alphas, fill

    def __len__(self) -> int:
        return len(self.alphas)

    def __getitem__(self, i):
        if isinstance(i, slice):
            raise TypeError("_HolesFilled does not slice")
        a = self.alphas[i]
        m = cast("np.ndarray | None", self.fill[int(i)])
        if m is None or not m.any():
            return a
        a = np.array(a, np.float32, copy=True) if not (isinstance(a, np.ndarray) and a.flags.writeable) else a
        a[m] = 1.0
        return a

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[i] for i in range(len(self)))


def fill_shadow_holes(
    session: Session,
    mattes: "Mattes",
    colour: Sequence,
    vids: Sequence[str],
    config: "BuildConfig",
    store: "_StepStore",
) -> tuple["Mattes", dict, "PackedMasks | None", "PackedMasks | None"]:
    """The matting step's alphas with the shadow holes of imported masks filled
    (``BuildConfig.fill_shadow_holes``; :func:`hole_masks` on each view's colour
    photograph), one view at a time, ``{"views", "px"}`` filled, and the open holes and
    (``BuildConfig.doubt_bright_extensions``) the bright extensions found on the way (for :func:`step_geometry`,
    which would otherwise load every photograph again; None when the rule does not
    apply). Writes :data:`FILLED_HOLES` (removes a stale one when nothing is filled); the
    returned :class:`Mattes` has a new ``content`` digest, so later steps see the change."""
    import hashlib

    rig = _is_rig_session(session)
    tolerant = default_carve_tolerance(config, rig_session=rig, n_views=len(vids))
    path = store.dir / FILLED_HOLES
    none = {"views": 0, "px": 0}
    if not (config.fill_shadow_holes and config.backdrop_holes and tolerant and mattes.use_masks):
        path.unlink(missing_ok=True)
        return mattes, none, None, None
    fill, opened = PackedMasks(), PackedMasks()
    extensions = PackedMasks() if _extensions_apply(config, bool(tolerant), mattes.use_masks) else None
    h = hashlib.sha256(mattes.content.encode())
    n_px = n_views = 0
    for i, shot in enumerate(colour):
        rgb = None if shot[0] is None else _rgb(session.load_radiance(shot[0]))
        o, m = (None, None) if rgb is None else hole_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
        if extensions is not None:
            extensions.append(
                None if rgb is None else bright_extension_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
            )
        del rgb
        opened.append(o)
        fill.append(m)
        if m is not None and m.any():
            n_px += int(m.sum())
            n_views += 1
            h.update(vids[i].encode() + np.packbits(m, axis=1).tobytes())
    if n_px == 0:
        path.unlink(missing_ok=True)
        return mattes, none, opened, extensions
    write_hole_masks(path, {vids[i]: m for i, m in enumerate(fill) if m is not None and m.any()})
    filled = replace(mattes, alphas=_HolesFilled(mattes.alphas, fill), content=h.hexdigest())
    return filled, {"views": n_views, "px": n_px}, opened, extensions


def _extensions_apply(config: "BuildConfig", tolerant: bool, use_masks: bool) -> bool:
    """Whether the bright-extension rule applies: asked for, a tolerant carve (something to
    doubt with) and imported masks (a rig's triangulation mattes are no thresholds)."""
    return bool(config.doubt_bright_extensions and tolerant and use_masks)


def _nullstep(name):
    from contextlib import nullcontext

    return nullcontext()


def build_geometry(
    alphas: Sequence[np.ndarray],
    cameras: Sequence[Camera],
    rms_px: Sequence[float],
    view_ids: Sequence[str],
    *,
    config: "BuildConfig",
    rig_session: bool = False,
    fallback_box=None,
    step=None,
    progress=None,
    images=None,
    open_holes=None,
    doubtful_extensions=None,
    carve_batch: int | None = None,
    photo_slots: int | None = None,
) -> Geometry:
    """Silhouettes → hull → surfels → visibility from per-view alphas and cameras.

    The build runs this once over all views; ``eval loo --holdout geometry`` runs it
    again without the held-out view. ``rms_px`` is each view's calibration RMS (the
    silhouette dilation), ``fallback_box`` a box for unbounded LPs (the rig volume),
    ``rig_session`` clips the hull at the table top. ``step`` is the build's step timer
    (a context-manager factory taking the step name). ``images``: per-view linear RGB
    (callable ``i → (H, W, 3)`` or a sequence), needed by ``config.refine``.
    ``open_holes``: per view None or an (H, W) bool mask of the enclosed mask holes that
    show the backdrop (:func:`open_hole_masks`); a tolerant carve trusts rejections
    through them like those of the outer contour. ``doubtful_extensions``: per view None or an
    (H, W) bool mask of the outline's thick bright extensions
    (:func:`bright_extension_masks`); a tolerant carve doubts rejections through them like those
    through shadow holes (the counts go to ``info["bright_extensions"]``).
    """
    step = step or _nullstep
    prog = progress or (lambda done, total: None)
    notes: list[str] = []
    V = len(cameras)
    with step("silhouettes"):
        # one view at a time: its alpha read, thresholded, undistorted and bit-packed
        sils, strong_in = PackedMasks(), PackedMasks()
        pin, dil, covers, empty, full = [], [], [], [], []
        base_px = default_dilate_base_px(config, rig_session=rig_session)
        ext_px = ext_views = 0
        for i, cam in enumerate(cameras):
            alpha = alphas[i]
            d = base_px + config.dilate_rms_factor * float(rms_px[i])
            dil.append(int(math.ceil(d - 1e-9)))
            s = silhouette_from_alpha(alpha, threshold=config.alpha_threshold, dilate_px=d)
            del alpha
            oh = None if open_holes is None else open_holes[i]
            db = None if doubtful_extensions is None else doubtful_extensions[i]
            for what, m in (("open_holes", oh), ("doubtful_extensions", db)):
                if m is not None and np.shape(m) != s.shape:
                    raise InputError(f"{what} of view {view_ids[i]}: {np.shape(m)}, expected {s.shape}")
            if oh is not None or db is not None:
                t, n_ext = strong_silhouette(s, open_holes=oh, doubtful_extensions=db)
                if n_ext:
                    ext_px += n_ext
                    ext_views += 1
                strong_in.append(undistort_silhouette(t, cam)[0])
                del t
            else:
                strong_in.append(None)
            del oh, db
            s, pc = undistort_silhouette(s, cam)
            covers.append(float(s.mean()))
            if not s.any():
                empty.append(view_ids[i])
            elif s.all():
                full.append(view_ids[i])
            sils.append(s)
            pin.append(pc)
            del s
        cover = float(np.median(covers))
        if cover > 0.8:
            notes.append(
                f"the silhouettes cover {100 * cover:.0f} % of the images (median): the mattes are nearly "
                "all opaque — were the backdrops lit in the object-present matting shots?"
            )
        if empty:
            raise EmptyHullError(
                f"empty silhouette (alpha <= {config.alpha_threshold} everywhere) in view(s) {', '.join(empty[:10])}"
                f"{' ...' if len(empty) > 10 else ''}: the visual hull would be empty. Check those images, lower "
                "--alpha-threshold, or leave the views out with --exclude-view"
            )
        if full:
            notes.append(f"view(s) {', '.join(full[:10])} are opaque everywhere (full mask): they carve nothing")
    tol = default_carve_tolerance(config, rig_session=rig_session, n_views=V)
    if tol >= V:
        raise ConfigError(f"carve_tolerance {tol} >= the {V} views: every voxel would survive")
    with step("hull"):
        if config.bounds_m is not None:
            lo, hi = (np.asarray(x, dtype=np.float64) for x in config.bounds_m)
        else:
            fb = fallback_box
            if fb is not None and not config.clip_below_table:
                fb = (fb[0] - np.array([0.0, fb[1][1], 0.0]), fb[1])
            lo, hi = hull_bounds(sils, pin, fallback=fb, min_component_frac=config.bounds_min_component_frac)
        res = choose_resolution(lo, hi, pin, config=config)
        pad = 2.0 * float(np.max(hi - lo)) / res.hull_res
        lo_p, hi_p = lo - pad, hi + pad
        if rig_session and config.clip_below_table and config.bounds_m is None:
            lo_p[1] = max(lo_p[1], 0.0)
        grid = HullGrid.from_bounds(lo_p, hi_p, res.hull_res)
        strong = None
        carve_batches = 1
        if tol > 0:
            # a tolerant carve counts rejections over every view at once: unpacked
            sils_l = list(sils)
            # return_stats=True: (occupancy, stats, strong silhouettes)
            occ, ostats, strong = cast(
                "tuple[np.ndarray, Any, Any]",
                carve_robust(
                    sils_l,
                    pin,
                    grid,
                    tolerance=tol,
                    root_cell=config.root_cell,
                    return_stats=True,
                    strong_silhouettes=(
                        None
                        if all(t is None for t in strong_in)
                        else [enclosed_holes(sl) if t is None else t for t, sl in zip(strong_in, sils_l)]
                    ),
                ),
            )
        else:
            occ, ostats, carve_batches = _carve_batched(
                sils, pin, grid, root_cell=config.root_cell, batch=carve_batch or CARVE_BATCH_MAX_VIEWS
            )
        n_occ = int(occ.sum())
        if n_occ == 0:
            raise EmptyHullError(
                "the visual hull is empty: the silhouettes have no common volume (inconsistent cameras or mattes?)"
            )
        info = {
            "dilate_base_px": base_px,
            "dilate_px_per_view": dict(zip(view_ids, dil)),
            "grid_shape": list(grid.shape),
            "voxel_m": grid.voxel_m,
            "lo_m": grid.lo.tolist(),
            "hi_m": grid.hi.tolist(),
            "occupied_voxels": n_occ,
            "octree_cells": ostats.cells,
            "octree_tests": ostats.tests,
            "resolution": res.to_dict(),
            "carve_tolerance": tol,
            # bright extensions doubted by the tolerant carve (none for a classical one: nothing to doubt)
            "bright_extensions": {"views": ext_views, "px": ext_px} if tol > 0 else {"views": 0, "px": 0},
            "carve_batches": carve_batches,
            "silhouettes_packed_bytes": sils.nbytes,
        }
        # where a view's mask disagrees with the hull (shadow holes, lit cloth, frame
        # edges): the share of the kept voxels it would have carved on its own
        idx = np.argwhere(occ)
        if len(idx) > 200_000:
            idx = idx[np.random.default_rng(0).choice(len(idx), 200_000, replace=False)]
        rej = view_rejections(grid.centres(idx), sils_l, pin).mean(axis=0) if tol > 0 else np.zeros(V)
        info["view_disagreement"] = {view_ids[i]: round(float(rej[i]), 5) for i in range(V)}
        bad = [(view_ids[i], float(rej[i])) for i in np.argsort(-rej) if rej[i] > 0.01]
        info["views_disagreeing_with_hull"] = [v for v, _ in bad]
        if bad:
            notes.append(
                "mask(s) disagree with the hull the other views agree on (tolerant carve kept what "
                "they alone rejected): "
                + ", ".join(f"{v} ({100 * f:.1f} % of the hull)" for v, f in bad[:8])
                + (" ..." if len(bad) > 8 else "")
            )
    with step("surfels"):
        sample = sample_hull_surfels(
            occ,
            grid,
            sils,
            pin,
            oversample=res.oversample,
            bisection_iters=config.bisection_iters,
            radius_scale=config.radius_scale,
            normal_scale_vox=max(1.0, res.pixel_footprint_m / grid.voxel_m),
            tolerance=tol,
            strong_silhouettes=strong,
        )
        if tol > 0:
            del sils_l, strong
        info.update({"pixel_footprint_m": res.pixel_footprint_m, "surfel_spacing_m": sample.spacing_m})
        if sample.spacing_m > 1.5 * res.pixel_footprint_m:
            notes.append(
                f"surfel spacing {sample.spacing_m * 1e3:.2f} mm is coarser than the pixel footprint "
                f"{res.pixel_footprint_m * 1e3:.2f} mm (--hull-res {res.hull_res}): drop --hull-res "
                "for full capture resolution"
            )
    with step("visibility"):
        vis = cast(
            np.ndarray,
            surfel_visibility(
                sample.positions,
                sample.normals,
                sample.radii,
                pin,
                depth_tol_m=config.depth_tol_m,
                facing_cos=config.facing_cos,
            ),
        )
        surfels = Surfels.from_bool(sample.positions, sample.normals, sample.radii, vis)
        info["visible_views_per_surfel"] = float(vis.sum(1).mean()) if len(vis) else 0.0
        info["surfels_seen_by_no_view"] = int((~vis.any(1)).sum()) if len(vis) else 0
        prog(V, V)
    if config.refine != "none":
        if images is None:
            raise ConfigError(f"refine={config.refine!r} needs the views' images (build_geometry(images=...))")
        with step("refine"):
            from .photo import PhotoConfig, refine_surfels

            # deferred: refine_surfels packs each view's grey and alpha into its stacks as it
            # reads it, so only one photograph is alive at a time here
            src = images
            imgs = [_Deferred((lambda i=i: src(i)) if callable(src) else (lambda i=i: src[i])) for i in range(V)]
            alps = [_Deferred(lambda i=i: alphas[i]) for i in range(V)]
            move = config.refine == "surfels"
            # shading depth only: coverage and radii stay the hull's, so neither the outline
            # restoration nor the radius growth of moved surfels is needed
            pc = (
                PhotoConfig()
                if move
                else PhotoConfig(keep_coverage=False, radius_neighbours=0, texture_std=SHADING_TEXTURE_STD)
            )
            if photo_slots is not None:  # the memory plan's share (MemoryPlan.photo_slots)
                pc = replace(pc, max_views_in_memory=max(int(photo_slots), pc.n_views))
            pos, nrm, rad, st = refine_surfels(
                sample.positions, sample.normals, sample.radii, vis, pin, imgs, alps, config=pc
            )
            if move:
                vis = cast(
                    np.ndarray,
                    surfel_visibility(pos, nrm, rad, pin, depth_tol_m=config.depth_tol_m, facing_cos=config.facing_cos),
                )
                surfels = Surfels.from_bool(pos, nrm, rad, vis)
            else:
                surfels.depth_m = np.ascontiguousarray(st["depth_m"], np.float32)
            info["refine"] = {"mode": config.refine, **{k: v for k, v in st.items() if np.ndim(v) == 0}}
    return Geometry(sils=sils, pin=pin, dilations=dil, occ=occ, grid=grid, surfels=surfels, info=info, notes=notes)


def _carve_batched(sils: Sequence, pin: Sequence[Camera], grid: HullGrid, *, root_cell: int, batch: int):
    """The classical (tolerance 0) octree carve over at most ``batch`` views at a time,
    the batches' hulls intersected: a voxel survives the carve iff no view carves its
    centre, so this is voxel for voxel :func:`.hull.carve_octree` over all views, with
    only ``batch`` views' unpacked silhouettes and summed-area tables alive. Returns
    (occupancy, OctreeStats summed over the batches, number of batches)."""
    from .hull import OctreeStats

    V = len(pin)
    b = max(1, int(batch))
    occ, cells, tests, n = None, 0, 0, 0
    for b0 in range(0, V, b):
        part = sils[b0 : b0 + b]
        o, st = cast(
            "tuple[np.ndarray, Any]",
            carve_octree(part, list(pin[b0 : b0 + b]), grid, root_cell=root_cell, return_stats=True),
        )
        del part
        occ = o if occ is None else (occ & o)
        cells, tests, n = cells + st.cells, tests + st.tests, n + 1
        if not occ.any():
            break  # empty already: the caller says so
    assert occ is not None
    return occ, OctreeStats(cells, tests, int(root_cell)), n


# --------------------------------------------------------------------------- steps on disk

#: the build's own products, inside the model folder (reused by ``build --resume``)
BUILD_FORMAT = "opacityhull.build/1"

#: BuildConfig fields that do not change a step's product (everything else does: a
#: step is stale when any other field differs, which errs on the side of redoing)
_NOT_GEOMETRY = (
    "reflectance",
    "pictures",
    "natural",
    "natural_kernels",
    "verify_checksums",
    "ground_truth_dilate_px",
    "alpha_eps",
    "storage",  # the pixel type of the written files: only the write step depends on it
    "reflectance_storage",  # likewise how the reflectance files are written
    "pca_rank",
    "pca_error",
    "pca_block",
)


def _digest(obj) -> str:
    """SHA-256 of a JSON-able structure (sorted keys): the identity of a step's inputs."""
    import hashlib

    return hashlib.sha256(json.dumps(_jsonable(obj), sort_keys=True, default=repr).encode()).hexdigest()


def _camera_digest(cam: Camera) -> str:
    import hashlib

    h = hashlib.sha256()
    for a in (cam.K, cam.dist, cam.world_from_cam):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    h.update(f"{cam.width}x{cam.height}".encode())
    return h.hexdigest()


def _records_digest(session: Session, recs) -> list:
    """What identifies the images a step read: manifest id, sha256 and size, and the
    file's size and mtime (a file replaced behind the manifest's back is stale too)."""
    out = []
    for r in recs:
        try:
            st = (session.root / r.path).stat()
            fs = [st.st_size, st.st_mtime_ns]
        except OSError:
            fs = None
        out.append([r.id, r.sha256, r.bytes, fs])
    return out


def _files_digest(root: Path) -> list:
    if not root.is_dir():
        return []
    out = []
    for p in sorted(root.rglob("*")):
        if p.is_file():
            st = p.stat()
            out.append([str(p.relative_to(root)), st.st_size, st.st_mtime_ns])
    return out


class _StepStore:
    """The build's step manifest (``MODEL/build/manifest.json``): per finished step, the
    digest of its inputs (images' sha256/mtimes, upstream steps) and parameters, and its
    outputs. With ``resume`` a step whose key and outputs are still there is reused."""

    def __init__(self, model_dir: Path, *, resume: bool):
        self.model_dir = model_dir
        self.dir = model_dir / BUILD_DIR
        self.path = self.dir / "manifest.json"
        self.resume = resume
        self.steps: dict = {}
        #: step name -> "ran" | "reused" | "reused k of n views" (the report's ``steps``)
        self.status: dict[str, str] = {}
        if resume and self.path.is_file():
            try:
                d = json.loads(self.path.read_text())
            except (OSError, ValueError) as e:
                raise FormatError(
                    f"{self.path}: unreadable build manifest ({e}); delete {self.dir} or build without --resume"
                ) from None
            if not isinstance(d, dict) or d.get("format") != BUILD_FORMAT or not isinstance(d.get("steps"), dict):
                raise FormatError(
                    f"{self.path}: not an {BUILD_FORMAT} manifest (format "
                    f"{d.get('format') if isinstance(d, dict) else d!r}); delete {self.dir} or build "
                    "without --resume"
                )
            self.steps = dict(d["steps"])

    def fresh(self, name: str, key: str) -> bool:
        e = self.steps.get(name)
        return bool(
            self.resume
            and isinstance(e, dict)
            and e.get("key") == key
            and all((self.model_dir / o).exists() for o in e.get("outputs", []))
        )

    def record(
        self,
        name: str,
        key: str,
        *,
        inputs: dict,
        params: dict,
        outputs: Sequence[str],
        seconds: float,
        status: str = "ran",
    ) -> None:
        from ..imageio import atomic_path

        self.steps[name] = {
            "key": key,
            "inputs": inputs,
            "params": params,
            "outputs": list(outputs),
            "seconds": round(float(seconds), 4),
        }
        self.status[name] = status
        self.dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.path) as tmp:
            tmp.write_text(json.dumps(_jsonable({"format": BUILD_FORMAT, "steps": self.steps}), indent=1) + "\n")

    def reuse(self, name: str, status: str = "reused") -> None:
        self.status[name] = status

    def save(self, rel: str, obj) -> str:
        import pickle

        from ..imageio import atomic_path

        # streamed: a hull grid and silhouettes of hundreds of views are not copied into
        # one bytes object first
        with atomic_path(self.model_dir / rel) as tmp:
            with open(tmp, "wb") as f:
                pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)
        return rel

    def load(self, rel: str):
        """The pickled product, or None when it cannot be read back (then the step runs)."""
        import pickle

        try:
            with open(self.model_dir / rel, "rb") as f:
                return pickle.load(f)
        except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError, TypeError) as e:
            log.warning("%s: cannot reuse (%s); the step runs again", self.model_dir / rel, e)
            return None


@dataclass(frozen=True, kw_only=True)
class Mattes:
    """The matting step's product: alphas in view order, per-view stats, where the
    backdrops came from, NaN/Inf notes, and the step key."""

    #: per view (H, W) float32, read from ``build/mattes`` on access (:class:`_MatteFiles`)
    alphas: Sequence
    stats: list
    sources: set
    nonfinite: list
    key: str
    #: SHA-256 over the alphas' bytes: what the later steps depend on (a re-matted view
    #: whose alpha came out the same leaves them fresh)
    content: str
    use_masks: bool
    drift_mode: str


class _LazyViews(Sequence):
    """``[view_rgba(i) for i in range(n)]`` computed on access: the writer streams the
    views one at a time instead of holding them all."""

    def __init__(self, fn: Callable[[int], np.ndarray], n: int):
        self.fn, self.n = fn, int(n)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):  # int only: the writer iterates
        if isinstance(i, slice):
            raise TypeError("_LazyViews does not slice")
        if not -self.n <= i < self.n:
            raise IndexError(i)
        return self.fn(i % self.n)

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self.fn(i) for i in range(self.n))


class PackedMasks(Sequence):
    """Per-view (H, W) bool masks held bit-packed (:func:`numpy.packbits` along rows, 1 bit
    a pixel): ``masks[i]`` unpacks view ``i`` alone. The build keeps its silhouettes this
    way between the stages, so that holding every view's mask costs V·H·W/8 bytes; an
    entry may be None (no mask for that view)."""

    def __init__(self, masks: Sequence | None = None):
        self._bits: list = []
        for m in masks or ():
            self.append(m)

    def append(self, mask) -> None:
        if mask is None:
            self._bits.append(None)
            return
        m = np.asarray(mask, bool)
        if m.ndim != 2:
            raise InputError(f"PackedMasks: a mask is (H, W), got shape {m.shape}")
        self._bits.append((np.packbits(m, axis=1), m.shape))

    def __len__(self) -> int:
        return len(self._bits)

    def __getitem__(self, i):
        if isinstance(i, slice):
            out = PackedMasks()
            out._bits = self._bits[i]
            return out
        e = self._bits[i]
        if e is None:
            return None
        bits, (h, w) = e
        return np.unpackbits(bits, axis=1, count=w).view(bool)

    def __iter__(self) -> Iterator:
        return (self[i] for i in range(len(self)))

    @property
    def nbytes(self) -> int:
        return sum(e[0].nbytes for e in self._bits if e is not None)


class _MatteFiles(Sequence):
    """The matting step's alphas, read from ``build/mattes/<view>.npy`` on access (one
    view at a time; nothing cached): ``alphas[i]`` is view ``i``'s (H, W) float32 matte,
    registered with :data:`.perview.LIVE_VIEWS`."""

    def __init__(self, paths: Sequence[Path], shapes: Sequence[tuple[int, int]], vids: Sequence[str]):
        self.paths, self.shapes, self.vids = list(paths), [tuple(x) for x in shapes], list(vids)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i):
        if isinstance(i, slice):
            raise TypeError("_MatteFiles does not slice")
        from .liveviews import LIVE_VIEWS

        i = range(len(self.paths))[i]
        return LIVE_VIEWS.track(self.vids[i], _load_matte(self.paths[i], self.shapes[i]))

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[i] for i in range(len(self)))


class _Deferred:
    """An array computed when NumPy asks for it (``np.asarray``), not before: a list of
    these stands for a list of per-view images without holding them (the photo
    refinement packs its inputs one view at a time)."""

    __slots__ = ("fn",)

    def __init__(self, fn: Callable[[], np.ndarray]):
        self.fn = fn

    def __array__(self, dtype=None, copy=None):
        a = np.asarray(self.fn())
        return a if dtype is None else a.astype(dtype, copy=False)


#: the default ``--memory-gb``: this fraction of the machine's RAM
MEMORY_FRACTION = 0.25
#: views the classical carve stacks at once (its silhouettes and summed-area tables cost
#: 5 bytes a pixel a view): more are carved in batches whose hulls are intersected,
#: voxel for voxel the same hull
CARVE_BATCH_MAX_VIEWS = 48
#: the fewest view slots the memory plan gives the photo refinement (at least its
#: ``n_views``, 5: one surfel's views are scored together)
PHOTO_MIN_SLOTS = 8


def total_ram_bytes() -> int:
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def default_memory_gb() -> float:
    """``build --memory-gb`` when not given: :data:`MEMORY_FRACTION` of the RAM."""
    return MEMORY_FRACTION * total_ram_bytes() / 2**30


def check_memory_gb(memory_gb) -> float:
    """``memory_gb`` as a float > 0, else a ConfigError naming ``--memory-gb``."""
    try:
        g = float(memory_gb)
    except (TypeError, ValueError):
        g = float("nan")
    if not (math.isfinite(g) and g > 0):
        raise ConfigError(f"--memory-gb {memory_gb!r}: expected a number of GB > 0 (the build's memory budget)")
    return g


@dataclass(frozen=True)
class MemoryPlan:
    """How the ``--memory-gb`` budget is spent: views in flight in the per-view steps
    (matting on threads/processes), views stacked per carve batch."""

    budget_gb: float
    view_bytes: int
    in_flight: int
    carve_batch: int
    #: views whose grey image and matte the photo refinement holds at once
    #: (:attr:`opacityhull.reconstruct.photo.PhotoConfig.max_views_in_memory`)
    photo_slots: int = 32

    @classmethod
    def for_build(cls, budget_gb: float, *, pixels: int, images_per_view: int, workers: int, views: int):
        budget = budget_gb * 2**30
        # one view being matted: its matting shots and backdrops as float32 RGB, plus
        # the solver's working arrays (~4 more images) and its alpha
        view_bytes = int((images_per_view + 4) * pixels * 12 + 4 * pixels)
        in_flight = int(max(1, min(max(1, workers), (0.5 * budget) // max(view_bytes, 1))))
        carve = int(max(1, min(CARVE_BATCH_MAX_VIEWS, views, (0.25 * budget) // max(5 * pixels, 1))))
        # the refinement's slots cost 8 bytes a pixel (float32 grey + matte); a quarter of
        # the budget, never fewer than one surfel's scored views nor more than the views
        # (its result does not depend on the number: fewer slots only re-read photographs)
        slots = int(max(PHOTO_MIN_SLOTS, min(max(views, PHOTO_MIN_SLOTS), (0.25 * budget) // max(8 * pixels, 1))))
        return cls(budget_gb, view_bytes, in_flight, carve, slots)


def peak_rss_mb() -> float:
    """This process's peak resident set so far (``ru_maxrss``), MB."""
    import resource
    import sys

    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (2**20 if sys.platform == "darwin" else 1024.0)


def step_cameras(session: Session, config: BuildConfig, store: _StepStore, *, progress=None):
    """Step 1: (views kept, cameras, key, notes). Inputs: the calibration phase's images,
    ``calibration/``, ``cameras/``, the rig table and the view list."""
    params = {
        "cameras": config.cameras,
        "drop_uncalibrated_cameras": config.drop_uncalibrated_cameras,
        "exclude_views": list(config.exclude_views),
    }
    phases = session.phases()
    inputs = {
        "calibration_images": _digest(
            _records_digest(session, session.select(phase="calibration", kind=None)) if "calibration" in phases else []
        ),
        "calibration_dir": _digest(_files_digest(session.root / "calibration")),
        "cameras_dir": _digest(_files_digest(session.root / "cameras")),
        "groundtruth_cameras": _digest(
            _files_digest(session.root / "groundtruth" / "cameras") if config.cameras == "groundtruth" else []
        ),
        "rig": _digest(session.meta.get("rig")),
        "views": _digest({ph: session.views(ph) for ph in ("lightfield", "matting", "mask") if ph in phases}),
    }
    key = _digest({"inputs": inputs, "params": params})
    rel = f"{BUILD_DIR}/cameras.pkl"
    got = store.load(rel) if store.fresh("cameras", key) else None
    if got is not None:
        views, cams = got
        store.reuse("cameras")
    else:
        t = time.perf_counter()
        views = view_list(session, exclude=config.exclude_views)
        cams = resolve_cameras(
            session, views, source=config.cameras, progress=progress, drop_uncalibrated=config.drop_uncalibrated_cameras
        )
        store.save(rel, (views, cams))
        store.record("cameras", key, inputs=inputs, params=params, outputs=[rel], seconds=time.perf_counter() - t)
    notes = []
    if cams.kept is not None and len(cams.kept) < len(views):
        names = _camera_names(session)
        for c, why in cams.dropped_cameras.items():
            n = sum(1 for cc, _ in views if cc == c)
            notes.append(
                f"camera {names.get(c, c)} could not be calibrated ({why}): its {n} view(s) were left out of the model"
            )
        views = cams.kept
    return list(views), cams, key, notes


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
    from ..executor import SerialExecutor
    from .perview import BuildMatteTask, build_matte, run_build_matte

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
    for i, ((c, a), cam) in enumerate(zip(views, cams.views)):
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
    key = _digest(keys)
    t = time.perf_counter()
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
            sub = (
                None if progress is None else (lambda d, t, off=off: progress(off + d, len(items)))  # noqa: B023 (bound by default)
            )
            done.extend(ex.map(fn, items[w0 : w0 + wave], progress=sub))
        for (i, _), meta in zip(tasks, done):
            metas[i] = meta
    reused = len(views) - len(tasks)
    status = "ran" if reused == 0 else ("reused" if not tasks else f"reused {reused} of {len(views)} views")
    store.record(
        "matting",
        key,
        inputs={"views": dict(zip(vids, keys))},
        params=params,
        outputs=[f"{BUILD_DIR}/mattes/{v}.npy" for v in vids],
        seconds=time.perf_counter() - t,
        status=status,
    )
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


def step_geometry(
    session: Session,
    views,
    cams: _Cameras,
    mattes: Mattes,
    cameras_key: str,
    config: BuildConfig,
    store: _StepStore,
    *,
    colour=None,
    step=None,
    progress=None,
    carve_batch: int | None = None,
    photo_slots: int | None = None,
    open_holes: "PackedMasks | None" = None,
    extensions: "PackedMasks | None" = None,
) -> tuple[Geometry, str]:
    """Steps 3-6 (silhouettes, hull, surfels, visibility, refine): :func:`build_geometry`
    over the mattes, stored as ``build/geometry.pkl``. ``open_holes`` and ``extensions``: the
    see-through holes and the bright extensions per view if already judged
    (:func:`fill_shadow_holes`), else judged here."""
    vids = [view_id(c, a) for c, a in views]
    rig_session = _is_rig_session(session)
    # imported sessions have no [rig] table; a corrupt one is a FormatError, not "no rig"
    geo = session.geometry if "rig" in session.meta else None
    fallback = _rig_volume(geo) if rig_session else None
    rms_per_view = [cams.rms_px.get(c, 0.0) for c, _ in views]
    params = {k: v for k, v in config.to_dict().items() if k not in _NOT_GEOMETRY}
    inputs = {
        "mattes": mattes.content,
        "cameras": cameras_key,
        "rig_session": rig_session,
        "colour": (
            _digest([_records_digest(session, session.select(shot=s, kind=None)) for s, _ in colour])
            if (config.refine != "none" or config.carve_tolerance != 0) and colour
            else ""
        ),
    }
    key = _digest({"inputs": inputs, "params": params})
    rel = f"{BUILD_DIR}/geometry.pkl"
    g = store.load(rel) if store.fresh("geometry", key) else None
    if isinstance(g, Geometry):
        store.reuse("geometry")
        return g, key
    t = time.perf_counter()
    images: Callable[[int], np.ndarray] | None = None
    if config.refine != "none":
        shots = list(colour or [])

        def view_rgb(i: int) -> np.ndarray:
            from .liveviews import LIVE_VIEWS

            rgba = _view_rgba(
                session, shots[i], mattes.alphas[i], use_masks=mattes.use_masks, alpha_eps=config.alpha_eps
            )
            return LIVE_VIEWS.track(vids[i], rgba[..., :3])

        images = view_rgb
    holes = None
    tolerant = default_carve_tolerance(config, rig_session=rig_session, n_views=len(vids))
    want_holes = bool(tolerant and colour and config.backdrop_holes)
    want_ext = bool(colour) and _extensions_apply(config, bool(tolerant), mattes.use_masks)
    holes = open_holes if want_holes and open_holes is not None else None
    doubtful = extensions if want_ext and extensions is not None else None
    if (want_holes and holes is None) or (want_ext and doubtful is None):
        # one photograph at a time, the masks bit-packed
        new_holes = PackedMasks() if want_holes and holes is None else None
        new_ext = PackedMasks() if want_ext and doubtful is None else None
        for i, shot in enumerate(colour or []):
            rgb = None if shot[0] is None else _rgb(session.load_radiance(shot[0]))
            if new_holes is not None:
                new_holes.append(
                    None if rgb is None else open_hole_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
                )
            if new_ext is not None:
                new_ext.append(
                    None
                    if rgb is None
                    else bright_extension_masks(mattes.alphas[i], rgb, threshold=config.alpha_threshold)
                )
            del rgb
        holes = new_holes if new_holes is not None else holes
        doubtful = new_ext if new_ext is not None else doubtful
    g = build_geometry(
        mattes.alphas,
        cams.views,
        rms_per_view,
        vids,
        config=config,
        rig_session=rig_session,
        fallback_box=fallback,
        step=step,
        progress=progress,
        images=images,
        open_holes=holes,
        doubtful_extensions=doubtful,
        carve_batch=carve_batch,
        photo_slots=photo_slots,
    )
    # a stale file from an earlier build would make the geometry holdout carve differently
    for name, masks in ((OPEN_HOLES, holes), (BRIGHT_EXTENSIONS, doubtful)):
        if masks is not None:
            write_hole_masks(store.dir / name, {v: h for v, h in zip(vids, masks) if h is not None})
        else:
            (store.dir / name).unlink(missing_ok=True)
    store.save(rel, g)
    store.record("geometry", key, inputs=inputs, params=params, outputs=[rel], seconds=time.perf_counter() - t)
    return g, key


def _view_rgba(
    session: Session, shots: tuple, alpha: np.ndarray, *, use_masks: bool, alpha_eps: float, finite=None
) -> np.ndarray:
    """Step 7 for one view: straight RGBA from its colour shot (minus the object-absent
    one) and its alpha."""
    finite = finite or (lambda img, where: img)
    obj, bg = shots
    Cimg = finite(_rgb(session.load_radiance(obj)), f"view colour shot {obj}")
    if bg is not None:
        prem = Cimg - (1.0 - alpha)[..., None] * _rgb(session.load_radiance(bg))
    elif use_masks:
        prem = Cimg * alpha[..., None]  # external images: colour seen through the mask
    else:
        prem = Cimg
    F = straight_from_premul(np.dstack([prem, alpha]), alpha_floor=alpha_eps)[..., :3]  # imageio's one conversion
    return np.concatenate([np.maximum(F, 0.0), alpha[..., None]], axis=-1).astype(np.float32)


def step_reflectance(session: Session, views, vids, alphas, config: BuildConfig, notes: list, finite) -> tuple:
    """Step 8: which one-light images go into the model, and a lazy per-view loader of
    them (read while writing, one view at a time). Returns (reflectance or None, digest
    of the images used)."""
    refl = session.select(phase="reflectance", kind=None) if config.reflectance else []
    if not refl:
        return None, ""
    per_view: dict[tuple, dict[str, str]] = {}
    samples: dict[str, LightSample] = {}
    levels: dict[str, float] = {}
    plan_level = _plan_reflectance_level(session)
    unknown_level = 0
    for r in refl:
        if not r.object_present or r.light is None:
            continue
        arr = float(r.lights_deg or 0.0)
        key = light_key(r.light, arr)
        samples.setdefault(key, LightSample(key, int(r.light), arr))
        per_view.setdefault((r.camera, round(r.table_deg % 360.0, 6)), {}).setdefault(key, r.shot)
        lv = (r.extra or {}).get("level", plan_level)
        if lv is None:
            unknown_level += 1
            lv = 255
        try:
            lv = float(lv)
        except (TypeError, ValueError):
            lv = float("nan")
        if not (0 < lv <= 255):
            raise FormatError(
                f"{session.root}: reflectance shot {r.shot} was taken at DMX level {lv!r}; "
                "expected 1..255 (the one-light image is normalised to full level)"
            )
        levels.setdefault(r.shot, lv)
    if unknown_level:
        notes.append(f"reflectance: {unknown_level} one-light image(s) record no DMX level; taken as full level (255)")
    if any(v != 255 for v in levels.values()):
        notes.append(
            "reflectance: one-light images taken below full DMX level were scaled by 255/level "
            "(the model stores radiance at full level)"
        )
    common = set(samples)
    for c, a in views:
        common &= set(per_view.get((c, round(a % 360.0, 6)), {}))
    dropped = set(samples) - common
    if dropped:
        notes.append(f"reflectance: {len(dropped)} light sample(s) missing in some views were left out")
    if not common:
        notes.append("reflectance: no light sample present in every view; none attached")
        return None, ""
    lights = [samples[k] for k in sorted(common, key=lambda k: (samples[k].array_deg, samples[k].light_id))]

    def images(i: int) -> dict[str, np.ndarray]:
        c, a = views[i]
        shots = per_view[(c, round(a % 360.0, 6))]
        mask = (alphas[i] > config.alpha_eps)[..., None]
        outd = {}
        for L in lights:
            shot = shots[L.key]
            # radiance at full DMX level: a light dimmed to `level` emits level/255
            img = finite(_rgb(session.load_radiance(shot)), f"view {vids[i]} one-light shot {shot}") * np.float32(
                255.0 / levels[shot]
            )
            outd[L.key] = np.where(mask, np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0), 0.0).astype(np.float32)
        return outd

    used = [r for r in refl if r.shot in levels]
    return {"lights": lights, "images": images}, _digest([_records_digest(session, used), levels])


# --------------------------------------------------------------------------- runner


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
) -> BuildReport:
    """Build the opacity-hull model of a session (see the module docstring).

    The build is a chain of steps (:func:`step_cameras`, :func:`step_matting`,
    :func:`step_geometry`, :func:`step_reflectance`, natural field, write, pictures,
    metrics). Each step's product and a manifest entry (its inputs' digests: image
    sha256s and mtimes, upstream step keys, and its parameters) go to ``out_dir/build/``.
    With ``resume`` a step whose key matches and whose outputs are there is reused, and
    the matting step reuses each view matted before; ``BuildReport.steps`` says what was
    reused. ``model.toml`` is still written last, and removed first when the model is
    rewritten, so an interrupted build never looks finished.

    Parameters
    ----------
    session_dir : session folder, or an open :class:`~opacityhull.session.Session`.
    out_dir : model folder (created; files in it are overwritten).
    config : BuildConfig.
    ground_truth : compare with ``groundtruth/`` (simulated sessions) and put the
        metrics in the report.
    progress : callable(done, total) within the current step.
    on_step : callable(step name) when a step starts (CLI progress descriptions).
    resume : reuse the products of an earlier build into ``out_dir`` whose inputs and
        parameters are unchanged (``build --resume``).
    executor : :class:`opacityhull.executor.Executor` for the per-view steps (matting);
        default serial. Every scheduler gives the same model bit for bit.
    memory_gb : the memory budget (``build --memory-gb``; default
        :data:`MEMORY_FRACTION` of the RAM): it caps the views matted at once on a
        local pool and the views the classical carve stacks at once
        (:class:`MemoryPlan`). Every per-view step streams one view at a time whatever
        the budget; the model does not depend on it.

    Returns
    -------
    BuildReport (also written to ``out_dir/report.json``).
    """
    budget_gb = check_memory_gb(default_memory_gb() if memory_gb is None else memory_gb)
    session = session_dir if isinstance(session_dir, Session) else Session.open(session_dir)
    out = Path(out_dir)
    timer0 = time.perf_counter()
    # what build would otherwise trust: every listed image there, with its size and
    # sha256, and no id naming two files (session.check_manifest)
    require_manifest_ok(session, hash_files=config.verify_checksums)
    verify_s = time.perf_counter() - timer0
    if ground_truth and session.groundtruth_dir is None:
        raise InputError(f"--ground-truth: {session.root} has no groundtruth/ folder (only simulated sessions do)")
    timer = _Timer(on_step)
    timer.seconds["verify"] = verify_s
    store = _StepStore(out, resume=resume)
    notes: list[str] = (
        []
        if config.verify_checksums
        else ["manifest checksums were not verified (verify_checksums=False): sizes and ids only"]
    )
    nonfinite: list[str] = []

    def finite(img, where):
        n = check_finite(img, where=where)
        if n and len(nonfinite) < 1000:
            nonfinite.append(n)
        return img

    prog = progress or (lambda done, total: None)

    with timer.step("cameras"):
        views, cams, cameras_key, cam_notes = step_cameras(session, config, store, progress=prog)
        notes.extend(cam_notes)
    vids = [view_id(c, a) for c, a in views]
    V = len(views)
    plan = MemoryPlan.for_build(
        budget_gb,
        pixels=max(c.width * c.height for c in cams.views),
        images_per_view=len(
            session.select(
                phase="mask" if ("mask" in session.phases() and "matting" not in session.phases()) else "matting",
                camera=views[0][0],
                table_deg=views[0][1],
                kind=None,
            )
        ),
        workers=int(getattr(executor, "n_workers", 1)),
        views=V,
    )

    with timer.step("matting"):
        mattes = step_matting(
            session, views, cams, config, store, executor=executor, progress=prog, in_flight=plan.in_flight
        )
    alphas = mattes.alphas
    nonfinite.extend(mattes.nonfinite[:1000])
    backdrop_source = ", ".join(sorted(mattes.sources))
    if any("display geometry" in s for s in mattes.sources):
        notes.append(
            "backdrops predicted from the display geometry (no object-absent captures): an "
            "approximation without display falloff or blur"
        )

    view_infos = [ViewInfo(i, vids[i], c, float(a), cams.views[i]) for i, (c, a) in enumerate(views)]
    colour_shots = [_colour_shot(session, c, a) for c, a in views]
    missing_colour = [vids[i] for i, (s, _) in enumerate(colour_shots) if s is None]
    if missing_colour:
        raise FormatError(
            f"{session.root}: no lightfield (or displays-off matting) image for views "
            f"{missing_colour[:5]}: nothing to colour the model with"
        )
    with timer.step("holes"):
        mattes, shadow_filled, open_holes, extensions = fill_shadow_holes(
            session, mattes, colour_shots, vids, config, store
        )
    alphas = mattes.alphas
    if shadow_filled["px"]:
        notes.append(
            f"mask holes: {shadow_filled['px']} px in {shadow_filled['views']} view(s) show no backdrop "
            "(shadows a threshold lost) and are opaque in the views' alpha (build/filled_holes.npz)"
        )

    def view_rgba(i: int) -> np.ndarray:
        from .liveviews import LIVE_VIEWS

        return LIVE_VIEWS.track(
            vids[i],
            _view_rgba(
                session,
                colour_shots[i],
                alphas[i],
                use_masks=mattes.use_masks,
                alpha_eps=config.alpha_eps,
                finite=lambda img, where: finite(img, f"view {vids[i]} {where.removeprefix('view ')}"),
            ),
        )

    g, geometry_key = step_geometry(
        session,
        views,
        cams,
        mattes,
        cameras_key,
        config,
        store,
        colour=colour_shots,
        step=timer.step,
        progress=prog,
        carve_batch=plan.carve_batch,
        photo_slots=plan.photo_slots,
        open_holes=open_holes,
        extensions=extensions,
    )
    notes.extend(g.notes)
    sils, pin, occ, grid, surfels = g.sils, g.pin, g.occ, g.grid, g.surfels
    hull_info = dict(g.info)
    dilations = {c: g.dilations[i] for i, (c, _) in enumerate(views)}
    hull_info["dilate_px_per_camera"] = {str(k): v for k, v in sorted(dilations.items())}
    hull_info["shadow_holes_filled"] = shadow_filled

    with timer.step("reflectance"):
        reflectance, refl_digest = step_reflectance(session, views, vids, alphas, config, notes, finite)

    # 8b. natural-illumination reflectance field (Matusik, Loper & Pfister 2004)
    natural = None
    natural_key = ""
    with timer.step("natural"):
        if config.natural and ("envmatte" in session.phases() or "natural" in session.phases()):
            from .natural_field import estimate_session_natural

            nat_recs = [
                r
                for ph in ("envmatte", "natural")
                if ph in session.phases()
                for r in session.select(phase=ph, kind=None)
            ]
            nat_in = {
                "images": _digest(_records_digest(session, nat_recs)),
                "mattes": mattes.content,
                "cameras": cameras_key,
            }
            nat_p = {"n_kernels": config.natural_kernels}
            natural_key = _digest({"inputs": nat_in, "params": nat_p})
            rel = f"{BUILD_DIR}/natural.pkl"
            natural = store.load(rel) if store.fresh("natural", natural_key) else None
            if natural is not None:
                store.reuse("natural")
            else:
                t = time.perf_counter()
                out.mkdir(parents=True, exist_ok=True)
                natural = estimate_session_natural(
                    session, views, cams.views, alphas, out, n_kernels=config.natural_kernels, progress=prog
                )
                store.save(rel, natural)
                store.record(
                    "natural",
                    natural_key,
                    inputs=nat_in,
                    params=nat_p,
                    outputs=[rel, "natural"],
                    seconds=time.perf_counter() - t,
                )

    report = BuildReport(
        model_dir=str(out),
        views=V,
        surfels=len(surfels),
        camera_source=cams.source,
        backdrop_source=backdrop_source,
        hull=hull_info,
        notes=notes,
    )
    provenance = {
        "session": str(session.root.resolve()),
        "rig_source": session.source,
        "camera_source": cams.source,
        "backdrop_source": backdrop_source,
        "reflectance_units": "radiance at full DMX level (one-light images scaled by 255/level)",
        "build_config": _jsonable(config.to_dict()),  # a TOML table (model.py: build_config_none)
    }
    write_in = {
        "geometry": geometry_key,
        "mattes": mattes.content,
        "cameras": cameras_key,
        "natural": natural_key,
        "colour": _digest(
            [
                _records_digest(session, session.select(shot=s, kind=None))
                for pair in colour_shots
                for s in pair
                if s is not None
            ]
        ),
        "reflectance": refl_digest,
        "provenance": _digest(provenance),
    }
    write_key = _digest({"inputs": write_in})
    with timer.step("write"):
        if store.fresh("write", write_key) and (out / "model.toml").is_file():
            store.reuse("write")
        else:
            t = time.perf_counter()
            out.mkdir(parents=True, exist_ok=True)
            # an earlier model's model.toml would make a half-rewritten folder look finished
            (out / "model.toml").unlink(missing_ok=True)
            extra = None
            if natural is not None:
                extra = {
                    "natural": {
                        "present": True,
                        "format": "opacityhull.natural/1",
                        "dir": "natural",
                        "n_kernels": int(natural["n_kernels"]),
                        "weights_dtype": str(natural.get("weights_dtype", "float16")),
                        "displays": {
                            n: {"domain_hw": list(d["domain_hw"]), "images": int(d["images"])}
                            for n, d in natural["displays"].items()
                        },
                    }
                }
            outputs = ["model.toml"]
            if cams.rig:
                from ..camera import write_opencv_yaml

                for i, rc in enumerate(cams.rig):
                    if rc is None:
                        continue
                    yx = {"reproj_rms_px": cams.rms_px[i]} if i in cams.rms_px else None
                    name = session.geometry.cameras[i].name if i < len(session.geometry.cameras) else f"cam{i}"
                    write_opencv_yaml(out / "calibration" / f"{name}.yaml", rc.with_name(name), extra=yx)
                    outputs.append(f"calibration/{name}.yaml")
            write_model(
                out,
                views=view_infos,
                surfels=surfels,
                view_rgba=_LazyViews(view_rgba, V),
                rig=session.meta.get("rig"),
                provenance=provenance,
                reflectance=reflectance,
                extra_meta=extra,
                progress=prog,
                storage=config.storage,
                reflectance_storage=config.reflectance_storage,
                pca_rank=config.pca_rank,
                pca_error=config.pca_error,
                pca_block=config.pca_block,
            )
            store.record(
                "write", write_key, inputs=write_in, params={}, outputs=outputs, seconds=time.perf_counter() - t
            )
    if natural is not None:
        report.hull["natural"] = {k: v for k, v in natural.items() if k != "files"}

    with timer.step("pictures"):
        if config.pictures:
            pic_key = _digest({"write": write_key})
            prev = store.steps.get("pictures", {})
            if store.fresh("pictures", pic_key):
                report.pictures = list(prev.get("outputs", []))
                store.reuse("pictures")
            else:
                t = time.perf_counter()
                report.pictures = _pictures(out, session, views, vids, alphas, sils, pin, surfels, cams, colour_shots)
                store.record(
                    "pictures",
                    pic_key,
                    inputs={"write": write_key},
                    params={},
                    outputs=report.pictures,
                    seconds=time.perf_counter() - t,
                )

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
        report.hull["matting_drift"] = drift
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
    if ground_truth:
        with timer.step("metrics"):
            metrics.update(_ground_truth_metrics(session, views, vids, alphas, occ, grid, cams, config, pin, dilations))
    if nonfinite:
        notes.append(
            f"{len(nonfinite)} image(s) held NaN or Inf pixels, set to 0 (black) where used: "
            + "; ".join(nonfinite[:3])
            + (" ..." if len(nonfinite) > 3 else "")
        )
        metrics["nonfinite_images"] = len(nonfinite)
    metrics["manifest_verified"] = "sha256" if config.verify_checksums else "sizes and ids only"
    metrics.update(_storage_metrics(out, [v.id for v in view_infos], notes))
    report.metrics = metrics
    report.seconds = {k: round(v, 4) for k, v in timer.seconds.items()}
    report.seconds["total"] = round(sum(timer.seconds.values()), 4)
    report.steps = dict(store.status)
    report.scheduler = getattr(executor, "scheduler", "serial")
    report.memory_budget_gb = float(budget_gb)
    report.peak_rss_mb = round(peak_rss_mb(), 1)
    report.memory = {
        **asdict(plan),
        "silhouettes_packed_bytes": int(getattr(sils, "nbytes", 0)),
        "note": "per-view steps hold one view at a time (in_flight views while matting on a local pool); "
        "see ARCHITECTURE.md, build memory",
    }
    from ..imageio import atomic_path
    from ..cliutil import to_jsonable

    with atomic_path(out / "report.json") as tmp:
        tmp.write_text(json.dumps(to_jsonable(report.to_dict()), indent=2) + "\n")
    return report


def _storage_metrics(out: Path, view_ids: Sequence[str], notes: list) -> dict:
    """Pixel type and bytes per view of the written model (read back from the folder, so a
    reused write step reports the same), and the values clamped to the half range (a note
    naming the files: they are not lost silently)."""
    from ..tomlio import read_toml

    meta = read_toml(out / "model.toml", error=FormatError, what="model.toml")
    st = meta.get("storage", {})
    sizes = {}
    for d in ("views", "reflectance"):
        files = [out / d / f"{vid}.exr" for vid in view_ids]
        sizes[d] = sum(f.stat().st_size for f in files if f.is_file()) / max(len(view_ids), 1)
    m = {
        "storage_pixel_type": st.get("pixel_type", "float"),
        "disk_bytes_per_view": sizes["views"] + sizes["reflectance"],
        "disk_bytes_per_view_views": sizes["views"],
        "disk_bytes_per_view_reflectance": sizes["reflectance"],
        "storage_clamped_values": int(st.get("clamped_values", 0)),
    }
    refl = meta.get("reflectance", {})
    if refl.get("present"):
        m["reflectance_storage"] = refl.get("storage", "layers")
    if refl.get("storage") == "pca":
        pv = list(refl.get("pca_views", []))
        m["reflectance_pca"] = {
            "rank": refl.get("pca_rank"),
            "error_target": refl.get("pca_error_target"),
            "block_px": int(refl.get("pca_block", 0)),
            "rank_per_view": {d["id"]: int(d["rank"]) for d in pv},
            "rank_mean_per_view": {d["id"]: float(d.get("rank_mean", d["rank"])) for d in pv},
            "rel_error_per_view": {d["id"]: float(d["rel_error"]) for d in pv},
            "rank_max": int(refl.get("rank_max", 0)),
            "rel_error_max": float(refl.get("rel_error_max", 0.0)),
            # values of the layers / values stored; the bytes: disk_bytes_per_view_reflectance
            "values_ratio": float(refl.get("values_ratio", 1.0)),
        }
    clamped = list(st.get("clamped", []))
    if m["storage_clamped_values"]:
        m["storage_clamped_files"] = clamped
        notes.append(
            f"storage half: {m['storage_clamped_values']} value(s) beyond ±65504 clamped in "
            f"{len(clamped)} file(s): "
            + "; ".join(f"{c['file']} ({c['values']}, max |v| {c['max_abs']:.4g})" for c in clamped[:3])
            + (" ..." if len(clamped) > 3 else "")
            + " (build with --storage float to keep them)"
        )
    return m


def _pictures(out: Path, session, views, vids, alphas, sils, pin, surfels, cams, colour_shots) -> list[str]:
    from .pictures import hull_overlays, matte_contact_sheet, reprojection_histogram, surfel_mask

    pics = out / "pictures"
    made = [matte_contact_sheet(alphas, vids, pics / "mattes.png")]
    pick = sorted(set(np.linspace(0, len(views) - 1, min(8, len(views))).round().astype(int).tolist()))
    imgs, ss, ms, names = [], [], [], []
    for i in pick:
        obj, _ = colour_shots[i]
        imgs.append(_rgb(session.load_radiance(obj)))
        ss.append(sils[i])
        ms.append(surfel_mask(surfels.positions, surfels.radii, pin[i]))
        names.append(vids[i])
    made.append(hull_overlays(imgs, ss, ms, names, pics / "hull_overlay.png"))
    cal = cams.calibration
    p = None
    if cal is not None:
        p = reprojection_histogram(
            pics / "reprojection.png",
            residuals_px=cal.residuals_px,
            rms_per_camera={cal.rig_cameras[c].name: cal.reproj_rms_px[c] for c in cal.camera_indices},
        )
    elif cams.rms_px and cams.rig:
        p = reprojection_histogram(
            pics / "reprojection.png", rms_per_camera={f"cam{i}": r for i, r in cams.rms_px.items()}
        )
    if p is not None:
        made.append(p)
    return [str(Path(m).relative_to(out)) for m in made]


def _ground_truth_metrics(session, views, vids, alphas, occ, grid, cams, config, pin, dilations) -> dict:
    from ..imageio import read_exr
    from .metrics import alpha_mae, ground_truth_checks, hull_iou, read_mesh_ply, voxelize_mesh

    gt = session.groundtruth_dir
    m: dict = {}
    per_view = []
    true_sils = []
    for i, ((c, _), vid) in enumerate(zip(views, vids)):
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
        ts = [undistort_silhouette(s, cam)[0] for s, cam in zip(true_sils, [c for c in cams.views])]
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
        from .calibration import pose_errors

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
