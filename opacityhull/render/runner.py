"""File-level runners behind ``opacityhull render`` and ``opacityhull eval loo``: open a
model, choose cameras, render, write images (EXR/PNG), orbits as frames plus an animated
GIF (and an MP4 when an ffmpeg writer is available), and JSON-ready summaries."""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..imageio import write_exr, write_png
from ..model import OpacityHullModel
from ..envmap import EnvironmentMap
from .background import fit_image, load_background
from .cameras import captured_view_camera, look_at_camera, mean_fov_y_deg, orbit_cameras, resize_camera, scene_target
from .renderer import RenderConfig, RenderResult, model_surfels, prepare_model_views, render_image
from .views import PreparedViews

if TYPE_CHECKING:
    from .hybrid import HybridMesh

__all__ = [
    "choose_cameras",
    "check_budget",
    "check_primitives",
    "PRIMITIVES",
    "LodCuts",
    "FrameTask",
    "render_frames",
    "run_render",
    "run_demo_step",
    "write_frame",
]

_SUFFIXES = (".png", ".exr")

log = logging.getLogger(__name__)


LookAt = tuple[np.ndarray, np.ndarray, "float | None"]
"""(eye, target, vertical field of view in degrees or None): :func:`.cameras.parse_look_at`."""


def choose_cameras(
    model: OpacityHullModel,
    *,
    view: tuple[int, float] | None = None,
    look_at: LookAt | None = None,
    orbit: int | None = None,
    width: int | None = None,
    height: int | None = None,
) -> list[Camera]:
    """The cameras to render: captured camera ``view = (camera index, table_deg)``, a
    ``look_at`` camera, or an ``orbit`` of that many frames (at most one of them;
    default: the first captured view), at ``width`` x ``height`` px when given."""
    given = [n for n, v in (("view", view), ("look_at", look_at), ("orbit", orbit)) if v is not None]
    if len(given) > 1:
        raise InputError(f"cameras: give only one of view, look_at, orbit (got {', '.join(given)})")
    cams = [v.camera for v in model.views]
    if orbit is not None:
        fallback = model_surfels(model).positions.mean(axis=0)
        return orbit_cameras(cams, int(orbit), width=width, height=height, target=scene_target(cams, fallback))
    if look_at is not None:
        eye, target, fov = look_at
        ref = cams[0]
        w = int(width) if width else ref.width
        h = int(height) if height else (ref.height if not width else max(1, round(ref.height * w / ref.width)))
        return [
            look_at_camera(eye, target, fov_y_deg=fov if fov is not None else mean_fov_y_deg(cams), width=w, height=h)
        ]
    if view is not None:
        c, a = view
        cam = captured_view_camera(model.views, int(c), float(a))
    else:
        cam = cams[0]
    return [resize_camera(cam, width, height)]


def write_frame(path: Path, result: RenderResult, background) -> Path:
    """EXR: premultiplied RGBA float, the file saying so (:mod:`opacityhull.imageio`'s
    convention), or composited RGB when a background is given. PNG: sRGB-encoded RGBA
    with straight alpha (or composited RGB)."""
    exr = path.suffix.lower() == ".exr"
    img = (result.premul if exr else result.rgba) if background is None else result.over(background)
    if exr:
        write_exr(path, img)
    else:
        write_png(path, img)
    return path


def _animation(u8: list[np.ndarray], out_stem: Path, fps: float) -> dict:
    """Write the orbit's 8-bit sRGB frames as a GIF (and an MP4 when ffmpeg is there)."""
    from ..pictures import write_animation

    out = {"gif": str(write_animation(out_stem.with_suffix(".gif"), u8, fps=fps))}
    if shutil.which("ffmpeg"):
        try:
            out["mp4"] = str(write_animation(out_stem.with_suffix(".mp4"), u8, fps=fps))
        except InputError as e:  # the optional ffmpeg writer plugin is missing: the GIF stands
            log.warning("%s: %s", out_stem.with_suffix(".mp4"), e)
            out["mp4_error"] = str(e)
    return out


def check_budget(budget) -> int | None:
    """A splat budget: None, or a whole number of splats ≥ 1 (else :class:`InputError`)."""
    if budget is None:
        return None
    try:
        ok = not isinstance(budget, bool) and float(budget).is_integer() and int(budget) >= 1
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise InputError(f"splat budget {budget!r}: expected a whole number of splats >= 1")
    return int(budget)


PRIMITIVES = ("splats", "hybrid")


def check_primitives(primitives: str, hybrid_px: float, budget: int | None) -> float | None:
    """The hybrid threshold (px) for ``primitives == "hybrid"``, None for splats; bad
    values are :class:`InputError` naming the flag."""
    if primitives not in PRIMITIVES:
        raise InputError(f"--primitives {primitives!r}: expected one of {', '.join(PRIMITIVES)}")
    if primitives == "splats":
        return None
    try:
        px = float(hybrid_px)
    except (TypeError, ValueError):
        px = float("nan")
    if not px >= 0:
        raise InputError(f"--hybrid-px {hybrid_px!r}: expected a number of pixels >= 0")
    if budget is not None:
        raise InputError("--primitives hybrid draws every surfel (as triangles or splats); drop --budget")
    return px


class LodCuts:
    """The sequential point tree of a model's surfels, cut per camera under a splat
    budget (``render --budget``): the CPU twin of the viewer's level of detail.

    Parameters
    ----------
    surfels : the model's surfels (Morton order, :func:`model_surfels`); the tree is
        built on the first budgeted cut, once per model.
    """

    def __init__(self, surfels):
        self.surfels = surfels
        self.tree = None  # the PointTree, nodes in Morton order (not sequential)
        self.stats = None  # its statistical nodes (spg.NodeStats, same order)
        self.last_cov = None  # radius tensors of the last cut (None: the model's own discs)
        self.ms_build = 0.0

    def _build(self):
        from dataclasses import replace

        from .lod import build_point_tree
        from .morton import morton_codes
        from .renderer import surfel_areas

        t = time.perf_counter()
        tree = build_point_tree(self.surfels, surfel_areas(self.surfels))
        # the same tree with its nodes in Morton order (the cut does not depend on node
        # order): a cut then comes out spatially sorted, and gathering it reads memory
        # in order (in the tree's r_max order the gather cost as much as the render)
        key = morton_codes(tree.positions, bits=16)
        perm = np.argsort(key, kind="stable")
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm))
        par = tree.parent[perm]
        self.tree = replace(
            tree,
            positions=tree.positions[perm],
            normals=tree.normals[perm],
            radii=tree.radii[perm],
            areas=tree.areas[perm],
            visibility=np.ascontiguousarray(tree.visibility[perm]),
            r_min=tree.r_min[perm],
            r_max=tree.r_max[perm],
            parent=np.where(par >= 0, inv[np.maximum(par, 0)], -1),
            is_leaf=tree.is_leaf[perm],
            leaf_index=tree.leaf_index[perm],
        )
        from .spg import node_statistics

        self.stats = node_statistics(self.tree)
        self.ms_build = 1e3 * (time.perf_counter() - t)

    def cut(self, camera: Camera, budget: int | None):
        """(surfels to draw, τ) for ``camera`` under ``budget``.

        With no budget, or a budget ≥ the surfel count, the model's own surfels are
        returned unchanged (τ = 0), so the image is exactly the full render; otherwise
        the finest view-dependent cut with at most ``budget`` nodes, in Morton order,
        each node carrying the area of its subtree (the renderer's edge coverage) and
        drawn as the anisotropic splat of its statistics (:mod:`.spg`; the tensors are
        left in ``last_cov`` for ``render_image``'s ``splat_cov``).
        """
        from .lod import select_cut
        from .spg import statistical_cut

        budget = check_budget(budget)
        self.last_cov = None
        if budget is None or budget >= len(self.surfels):
            return self.surfels, 0.0
        if self.tree is None:
            self._build()
        tree = self.tree
        assert tree is not None  # _build sets it
        tau, mask = select_cut(tree, camera.centre_world, budget)
        assert self.stats is not None  # _build sets it
        s, areas, self.last_cov = statistical_cut(tree, self.stats, mask)
        _seed_surfel_areas(s, areas)
        return s, float(tau)


def _seed_surfel_areas(surfels, areas) -> None:
    """A cut's areas for the renderer (:func:`.frame.seed_surfel_areas`); a test checks
    the renderer picks them up. (Better: an ``areas=`` argument of render_image.)"""
    from .frame import seed_surfel_areas

    seed_surfel_areas(surfels, areas)


class _FrameState:
    """One opened model with its packed views, sorted surfels and LOD tree (or, with
    ``renderer="fitted"``, its fitted splats): what a worker keeps between
    :func:`render_frames` tasks."""

    def __init__(self, model_path, model: OpacityHullModel | None = None, renderer: str = "ulr"):
        import threading

        t0 = time.perf_counter()
        self.model = OpacityHullModel.open(model_path) if model is None else model
        self.splats = None
        if renderer == "fitted":
            from .splats import FittedSplats

            self.splats = FittedSplats.load(Path(self.model.root))
        # the splats draw alone: the captured views the ULR renderer blends are not read
        self.pv = prepare_model_views(self.model) if self.splats is None else cast(PreparedViews, None)
        self.surfels = model_surfels(self.model)
        self.view_cameras = [v.camera for v in self.model.views]
        self.lod = LodCuts(self.surfels)
        self.hybrid_mesh: HybridMesh | None = None  # the umbrella mesh (render --primitives hybrid), built on first use
        self.ms_hybrid_mesh = 0.0
        self.ms_load = 1e3 * (time.perf_counter() - t0)
        self.ms_warmup: float | None = None  # set by the first frame rendered here (_warm_up)
        # threads of one worker share this state; building the LOD tree twice is only waste,
        # but the cut reads the tree while the first builder replaces it
        self.lock = threading.Lock()


def _state_key(model_path, renderer: str = "ulr") -> tuple[str, int, str]:
    p = Path(model_path).resolve()
    try:
        mtime = (p / "model.toml").stat().st_mtime_ns
    except OSError:
        mtime = -1  # OpacityHullModel.open names the missing file
    return str(p), mtime, renderer


# one model per worker process: a rebuilt model (new model.toml mtime) replaces the old one
_STATE: dict = {}
_STATE_LOCK = None


def _worker_state(model_path, renderer: str = "ulr") -> tuple[_FrameState, bool]:
    """The cached state of ``model_path`` in this process, and whether it was loaded now."""
    global _STATE_LOCK
    import threading

    if _STATE_LOCK is None:
        _STATE_LOCK = threading.Lock()
    key = _state_key(model_path, renderer)
    with _STATE_LOCK:
        st = _STATE.get(key)
        if st is not None:
            return st, False
        _STATE.clear()
        st = _FrameState(model_path, renderer=renderer)
        _STATE[key] = st
        return st, True


def _render_chunk(
    st: _FrameState,
    cams: Sequence[Camera],
    *,
    config: RenderConfig,
    exclude: Sequence[int],
    budget: int | None,
    paths: Sequence[str],
    background,
    anim_background,
    progress: Callable[[int, int], None] | None = None,
    hybrid_px: float | None = None,
) -> dict:
    """Render ``cams`` with an opened state, write frame i to ``paths[i]``; the GIF frame
    (8-bit sRGB over ``anim_background``) when that is given."""
    from ..pictures import to_srgb8

    if st.splats is not None:
        return _render_chunk_fitted(
            st, cams, paths=paths, background=background, anim_background=anim_background, progress=progress
        )
    ms, splats, taus, gif, tris = [], [], [], [], []
    ms_tree = 0.0
    ms_warmup = _warm_up(st, cams[0], config=config, exclude=exclude) if cams else 0.0
    for i, (cam, path) in enumerate(zip(cams, paths, strict=True)):
        t = time.perf_counter()
        with st.lock:
            had_tree = st.lod.tree is not None
            drawn, tau = st.lod.cut(cam, budget)
            cov = st.lod.last_cov
            if st.lod.tree is not None and not had_tree:
                ms_tree = st.lod.ms_build
                t += ms_tree / 1e3  # the tree is built once per model, not per frame
        if hybrid_px is not None:
            had_mesh = st.hybrid_mesh is not None
            res = _render_hybrid_frame(st, cam, config=config, exclude=exclude, threshold_px=hybrid_px)
            if not had_mesh:
                t += st.ms_hybrid_mesh / 1e3  # built once per model, not per frame
            splats.append(res.stats["splats"])
            tris.append(res.stats["triangles"])
        else:
            splats.append(len(drawn))
            res = render_image(
                drawn, st.view_cameras, st.pv, cam, config=config, exclude_views=list(exclude), splat_cov=cov
            )
        taus.append(tau)
        ms.append(1e3 * (time.perf_counter() - t))
        write_frame(Path(path), res, background)
        if anim_background is not None:
            gif.append(to_srgb8(res.over(anim_background)))
        if progress:
            progress(i + 1, len(cams))
    return {
        "ms": ms,
        "splats": splats,
        "triangles": tris,
        "taus": taus,
        "gif": gif,
        "ms_lod_tree": ms_tree,
        "ms_hybrid_mesh": st.ms_hybrid_mesh,
        "ms_warmup": ms_warmup,
    }


def _render_hybrid_frame(st: _FrameState, cam: Camera, *, config: RenderConfig, exclude, threshold_px: float):
    """``render --primitives hybrid``: umbrella triangles close up, splats elsewhere
    (:mod:`.hybrid`); the umbrella mesh is built on the first frame, once per model."""
    from .hybrid import build_hybrid_mesh, render_hybrid

    with st.lock:
        mesh = st.hybrid_mesh
        if mesh is None:
            t = time.perf_counter()
            mesh = st.hybrid_mesh = build_hybrid_mesh(st.surfels)
            st.ms_hybrid_mesh = 1e3 * (time.perf_counter() - t)
    return render_hybrid(
        st.surfels,
        st.view_cameras,
        st.pv,
        cam,
        mesh=mesh,
        config=config,
        threshold_px=threshold_px,
        exclude_views=list(exclude),
    )


def _render_chunk_fitted(
    st: _FrameState,
    cams: Sequence[Camera],
    *,
    paths: Sequence[str],
    background,
    anim_background,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """:func:`_render_chunk` for the fitted splats (:mod:`.splats`): every splat, every frame."""
    from ..pictures import to_srgb8
    from .cameras import resize_camera

    assert st.splats is not None
    ms_warmup = 0.0
    with st.lock:
        if st.ms_warmup is None and cams:  # numba loads (or compiles) the rasterizer once
            t = time.perf_counter()
            st.splats.render(resize_camera(cams[0], *WARMUP_SIZE))
            ms_warmup = st.ms_warmup = 1e3 * (time.perf_counter() - t)
    ms, gif = [], []
    for i, (cam, path) in enumerate(zip(cams, paths, strict=True)):
        t = time.perf_counter()
        res = st.splats.render(cam)
        ms.append(1e3 * (time.perf_counter() - t))
        write_frame(Path(path), res, background)
        if anim_background is not None:
            gif.append(to_srgb8(res.over(anim_background)))
        if progress:
            progress(i + 1, len(cams))
    n = len(st.splats)
    return {
        "ms": ms,
        "splats": [n] * len(cams),
        "taus": [0.0] * len(cams),
        "gif": gif,
        "ms_lod_tree": 0.0,
        "ms_warmup": ms_warmup,
    }


#: Size of the warm-up render (px): enough to run every kernel, too small to cost a frame.
WARMUP_SIZE = (16, 12)


def _warm_up(st: _FrameState, camera: Camera, *, config: RenderConfig, exclude: Sequence[int]) -> float:
    """Render ``camera`` shrunk to :data:`WARMUP_SIZE` once per opened state, so the
    frames' timings leave out what only the first render pays (numba compiling or
    loading its kernels, the surfels' area estimate); returns its ms (0 when this
    state was already warm). The frames' pixels do not depend on it."""
    from .cameras import resize_camera

    with st.lock:
        if st.ms_warmup is not None:
            return 0.0
        t = time.perf_counter()
        tiny = resize_camera(camera, *WARMUP_SIZE)
        render_image(st.surfels, st.view_cameras, st.pv, tiny, config=config, exclude_views=list(exclude))
        st.ms_warmup = 1e3 * (time.perf_counter() - t)
        return st.ms_warmup


@dataclass(frozen=True, kw_only=True)
class FrameTask:
    """One executor task of ``render --scheduler`` (:func:`render_frames`): a chunk of
    consecutive frames of one model.

    model_path : the model folder (a path the worker can read).
    cameras : the frames' cameras.
    config : the :class:`RenderConfig`.
    exclude : view indices not to blend.
    budget : the splat budget per frame (None: every surfel).
    paths : one output path per camera (the worker writes them).
    background : what :func:`write_frame` composites over (None, a colour, an image
        fitted to the camera or an :class:`~opacityhull.envmap.EnvironmentMap`).
    anim_background : the GIF frames' background (None: no GIF frames).
    renderer : ``"fitted"`` or ``"ulr"`` (:func:`.splats.resolve_renderer`).
    hybrid_px : the umbrella threshold (px) of ``--primitives hybrid`` (None: splats only).
    """

    model_path: str
    cameras: Sequence[Camera]
    config: RenderConfig
    exclude: Sequence[int]
    budget: int | None
    paths: Sequence[str]
    background: Any = None
    anim_background: Any = None
    renderer: str = "ulr"
    hybrid_px: float | None = None


def render_frames(task: FrameTask) -> dict:
    """One executor task of ``render --scheduler``: render and write a chunk of frames
    (:class:`FrameTask`).

    The model is opened once per worker process and kept (keyed on the model folder
    and ``model.toml``'s mtime), so an orbit's later chunks only render.

    Returns
    -------
    dict with ``ms`` (per frame, warm), ``splats``, ``taus``, ``gif`` (uint8 H x W x 3
    frames), ``ms_load`` (0 when the model was already open here), ``ms_warmup`` (the
    first render in this worker, :func:`_warm_up`; 0 when warm) and ``ms_lod_tree``.
    """
    st, loaded = _worker_state(task.model_path, task.renderer)
    out = _render_chunk(
        st,
        task.cameras,
        config=task.config,
        exclude=task.exclude,
        budget=task.budget,
        paths=task.paths,
        background=task.background,
        anim_background=task.anim_background,
        hybrid_px=task.hybrid_px,
    )
    out["ms_load"] = st.ms_load if loaded else 0.0
    return out


def run_render(
    model_path,
    out,
    *,
    view: tuple[int, float] | None = None,
    look_at: LookAt | None = None,
    orbit: int | None = None,
    width: int | None = None,
    height: int | None = None,
    config: RenderConfig = RenderConfig(),
    background: str | None = None,
    background_kind: str = "auto",
    env_yaw_deg: float | None = None,
    exclude: Sequence[str] = (),
    fps: float = 12.0,
    budget: int | None = None,
    renderer: str = "auto",
    progress: Callable[[int, int], None] | None = None,
    executor=None,
    primitives: str = "splats",
    hybrid_px: float = 2.0,
) -> dict:
    """Render one frame or an orbit of a model folder to ``out`` (``.png`` or ``.exr``).

    ``renderer``: ``"fitted"`` draws the splats of ``build --optimize``
    (:mod:`opacityhull.render.splats`), ``"ulr"`` the hull's surfels blended from the
    captured views, ``"auto"`` the splats when the model has current ones (the summary's
    ``"renderer"`` says which). ``budget`` and ``exclude`` belong to the ULR renderer
    (an :class:`InputError` while the splats draw).

    ``budget``: at most this many splats per frame, from a view-dependent cut of the
    sequential point tree (:mod:`opacityhull.render.lod`, the viewer's LOD); None draws
    every surfel.

    ``primitives``: ``"splats"`` (EWA splats only) or ``"hybrid"`` (:mod:`.hybrid`: a
    surfel whose umbrella projects larger than ``hybrid_px`` pixels is drawn as its
    umbrella triangles, the others as splats; every surfel, so no ``budget``).

    ``executor``: an :class:`opacityhull.executor.Executor` (``render --scheduler``) to
    render the frames on, in chunks of consecutive frames (:func:`render_frames`): each
    worker opens the model from ``model_path`` and writes its frames to ``out``'s
    folder, so both must be at a path the workers see; the GIF is written here. None
    renders here. The frames are the same bit for bit either way (tested).
    """
    out = Path(out)
    if out.suffix.lower() not in _SUFFIXES:
        raise InputError(f"render output {out}: expected a .png or .exr file name")
    budget = check_budget(budget)
    hybrid = check_primitives(primitives, hybrid_px, budget)
    model = OpacityHullModel.open(model_path)
    from .splats import resolve_renderer

    used = resolve_renderer(
        Path(model.root),
        renderer,
        ulr_only=(
            ("--budget", budget is not None),
            ("--exclude-view", bool(list(exclude))),
            ("--primitives hybrid", hybrid is not None),
        ),
    )
    cams = choose_cameras(model, view=view, look_at=look_at, orbit=orbit, width=width, height=height)
    bg = load_background(background, yaw_deg=env_yaw_deg, kind=background_kind) if background is not None else None
    if isinstance(bg, np.ndarray):
        bg = fit_image(bg, cams[0])
    excl = []
    for e in exclude:
        excl.append(int(e) if str(e).isdigit() else model.view_index(str(e)))
    n_surfels = len(model.surfels)  # the fitted splats' count replaces it below
    paths = [str(out if orbit is None else out.with_name(f"{out.stem}_{i:03d}{out.suffix}")) for i in range(len(cams))]
    anim_bg = None if orbit is None else (bg if bg is not None else (0.18, 0.18, 0.18))
    if executor is None:
        st = _FrameState(model_path, model, renderer=used)
        if st.splats is not None:
            n_surfels = len(st.splats)
        parts = [
            _render_chunk(
                st,
                cams,
                config=config,
                exclude=excl,
                budget=budget,
                paths=paths,
                background=bg,
                anim_background=anim_bg,
                progress=progress,
                hybrid_px=hybrid,
            )
        ]
        t_load_ms = st.ms_load
        scheduler = "serial"
    else:
        del model
        # about two chunks per worker slot: few tasks (each ships the cameras and the
        # background), yet a slow worker does not hold up the whole orbit
        per = max(1, -(-len(cams) // max(1, 2 * int(getattr(executor, "n_workers", 1)))))
        tasks = [
            FrameTask(
                model_path=str(Path(model_path).resolve()),
                cameras=cams[i : i + per],
                config=config,
                exclude=excl,
                budget=budget,
                paths=[str(Path(p).resolve()) for p in paths[i : i + per]],
                background=bg,
                anim_background=anim_bg,
                renderer=used,
                hybrid_px=hybrid,
            )
            for i in range(0, len(cams), per)
        ]
        prog = None if progress is None else (lambda done, total: progress(min(done * per, len(cams)), len(cams)))
        parts = executor.map(render_frames, tasks, progress=prog)
        t_load_ms = max(p["ms_load"] for p in parts)
        scheduler = executor.scheduler
        if used == "fitted":
            n_surfels = parts[0]["splats"][0] if parts and parts[0]["splats"] else 0
    ms = [x for p in parts for x in p["ms"]]
    splats = [x for p in parts for x in p["splats"]]
    taus = [x for p in parts for x in p["taus"]]
    summary = {
        "model": str(model_path),
        # which model drew the frames: the fitted splats (build --optimize) or the hull by ULR
        "renderer": used,
        "frames": len(cams),
        "paths": paths,
        "width": cams[0].width,
        "height": cams[0].height,
        "k": config.k,
        "surfels": n_surfels,
        "ms_per_frame": float(np.mean(ms)),  # warm: the warm-up render is ms_warmup
        "ms_first_frame": ms[0],
        "ms_warmup": max(p["ms_warmup"] for p in parts),
        "ms_load": t_load_ms,
        "background": None if background is None else ("envmap" if isinstance(bg, EnvironmentMap) else str(background)),
        "budget": budget,
        "splats_per_frame": splats,
        "lod_tau": taus,
        "ms_lod_tree": max(p["ms_lod_tree"] for p in parts),
        "scheduler": scheduler,
        "primitives": primitives,
    }
    if hybrid is not None:
        summary["hybrid_px"] = hybrid
        summary["triangles_per_frame"] = [x for p in parts for x in p["triangles"]]
        summary["ms_hybrid_mesh"] = max(p["ms_hybrid_mesh"] for p in parts)
    if orbit is not None:
        summary.update(_animation([g for p in parts for g in p["gif"]], out.with_name(out.stem), fps))
    return summary


def run_demo_step(
    model_path,
    out,
    *,
    frames: int = 24,
    background: str = "grey",
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """The renderer's part of ``opacityhull demo``: an orbit of the model (PNG frames +
    GIF) under ``out``. Returns a summary with the paths, ready for the demo's report
    (the demo's leave-one-out score is :func:`opacityhull.evaluate.runner.demo_loo`)."""
    out = Path(out)
    orbit = run_render(model_path, out / "orbit" / "orbit.png", orbit=frames, background=background, progress=progress)
    return {
        "orbit_gif": orbit.get("gif"),
        "orbit_frames": orbit["paths"],
        "ms_per_frame": orbit["ms_per_frame"],
    }
