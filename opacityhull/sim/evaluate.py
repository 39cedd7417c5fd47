"""Measuring an effect selection against the full-effects reference.

For a scene and a phase, :func:`phase_error` renders what that phase captures twice —
with :func:`~opacityhull.sim.effects.select_effects` and with
:func:`~opacityhull.sim.effects.reference_effects` (path tracing, depth 16, high spp) —
and compares what the phase *consumes*:

* matting: the alpha matte from triangulation matting (Smith & Blinn) of two captures
  over complementary random backdrops and the two backdrop-only captures;
* lightfield (all lights on), reflectance (one light), envmatte (stripes on the
  displays): radiance, relative mean absolute error over the object's pixels;
* calibration: the ChArUco corners OpenCV finds in a render of the board under all
  lights, mean distance (px) between the corners found in both images;
* groundtruth: coverage alpha at the selection's spp against 1024 spp.

Errors are measured on the pixels the object covers (dilated by one pixel); the
reference's own Monte-Carlo noise is part of the measured error. Used by
``benchmarks/sim_effects.py`` and ``tests/sim/test_effect_bounds.py``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from collections.abc import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..charuco import CharucoSpec
from ..riggeometry import CameraSpec, RigGeometry
from .effects import EffectConfig, reference_effects, select_effects
from .render import SimRenderer, SimState, lamp_radius
from .scenes import SceneSpec, board_parts

__all__ = [
    "PhaseError",
    "phase_error",
    "eval_camera",
    "triangulation_alpha",
    "coverage_mask",
    "rel_mae",
    "lamp_change",
    "point_geometry",
]


@dataclass(frozen=True)
class PhaseError:
    scene: str
    phase: str
    metric: str
    error: float
    bound: float
    seconds_selected: float
    seconds_reference: float
    selected: EffectConfig
    reference: EffectConfig
    #: (configuration, error, seconds) of further configurations measured against the
    #: same reference images (``phase_error(also=...)``), e.g. the reference at low spp
    also: tuple = field(default=())

    @property
    def within_bound(self) -> bool:
        return bool(self.error <= self.bound)

    def to_json(self) -> dict:
        return {
            "scene": self.scene,
            "phase": self.phase,
            "metric": self.metric,
            "error": self.error,
            "bound": self.bound,
            "within_bound": self.within_bound,
            "seconds_selected": self.seconds_selected,
            "seconds_reference": self.seconds_reference,
            "speedup": self.seconds_reference / max(self.seconds_selected, 1e-9),
            "selected": self.selected.to_json(),
            "reference": {
                "integrator": self.reference.integrator,
                "max_depth": self.reference.max_depth,
                "spp": self.reference.spp,
            },
            "also": [
                {
                    "integrator": c.integrator,
                    "max_depth": c.max_depth,
                    "spp": c.spp,
                    "crop": c.crop,
                    "error": e,
                    "seconds": t,
                }
                for c, e, t in self.also
            ],
        }


def eval_camera(
    width: int = 64,
    height: int = 48,
    *,
    elevation_deg: float = 30.0,
    distance_m: float = 0.6,
    fov_y_deg: float = 26.0,
    target_m=(0.0, 0.08, 0.0),
) -> Camera:
    """A small camera framing the ~0.2 m object volume (rig frame)."""
    f = height / (2.0 * np.tan(np.radians(fov_y_deg) / 2.0))
    spec = CameraSpec(
        name="eval",
        width=width,
        height=height,
        distance_m=distance_m,
        elevation_deg=elevation_deg,
        azimuth_deg=0.0,
        focal_px=f,
    )
    return spec.nominal_camera(np.asarray(target_m, dtype=np.float64))


def calibration_camera(width: int = 320, height: int = 240) -> Camera:
    """A camera seeing the whole calibration board at 45° (rig frame)."""
    return eval_camera(width, height, elevation_deg=45.0, distance_m=0.8, fov_y_deg=32.0, target_m=(0.0, 0.0, 0.0))


def detect_corners(img: np.ndarray, charuco: CharucoSpec) -> dict[int, np.ndarray]:
    """ChArUco corners (id → (x, y) px) OpenCV finds in a linear render."""
    import cv2

    from ..imageio import srgb_encode

    g = img.mean(axis=2)
    peak = float(np.percentile(g, 99.5)) or 1.0
    g8 = np.round(srgb_encode(np.clip(g / peak, 0, 1)) * 255).astype(np.uint8)
    params = cv2.aruco.DetectorParameters()
    params.minMarkerPerimeterRate = 0.01
    det = cv2.aruco.CharucoDetector(charuco.board(), detectorParams=params)
    corners, ids, _, _ = det.detectBoard(g8)
    if ids is None:
        return {}
    return {int(i): c.reshape(2) for i, c in zip(ids.ravel(), corners, strict=True)}


def corner_error(img: np.ndarray, ref: np.ndarray, charuco: CharucoSpec) -> float:
    """Mean distance (px) between ChArUco corners found in both images; inf if fewer
    than 4 are found in both."""
    a, b = detect_corners(img, charuco), detect_corners(ref, charuco)
    common = sorted(set(a) & set(b))
    if len(common) < 4:
        return float("inf")
    return float(np.mean([np.linalg.norm(a[i] - b[i]) for i in common]))


def triangulation_alpha(
    c1: np.ndarray, c2: np.ndarray, b1: np.ndarray, b2: np.ndarray, *, eps: float = 1e-6
) -> np.ndarray:
    """Smith–Blinn triangulation matting: ``alpha = 1 - <C1 - C2, B1 - B2> / |B1 - B2|^2``
    per pixel, clipped to [0, 1]; (H, W, 3) inputs → (H, W). Where the backdrops agree
    (``|B1 - B2|^2 < eps``) alpha is undefined and returned as 1 if the captures differ
    from the backdrop, else 0."""
    d = (c1 - c2).astype(np.float64)
    db = (b1 - b2).astype(np.float64)
    den = np.sum(db * db, axis=2)
    num = np.sum(d * db, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = 1.0 - num / den
    fallback = (np.abs(c1 - b1).sum(axis=2) > 1e-6).astype(np.float64)
    a = np.where(den >= eps, a, fallback)
    return np.clip(a, 0.0, 1.0).astype(np.float32)


def coverage_mask(alpha: np.ndarray, *, dilate_px: int = 1) -> np.ndarray:
    """Pixels with coverage > 0, dilated by ``dilate_px`` (boolean (H, W))."""
    m = alpha > 1e-4
    if dilate_px > 0:
        import cv2

        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        m = cv2.dilate(m.astype(np.uint8), k) > 0
    return m


def rel_mae(a: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    """``sum |a - ref| / sum |ref|`` over ``mask`` (all channels); the absolute mean error
    if the reference is black there (e.g. glass under point lights)."""
    d = np.abs(a - ref)[mask]
    s = float(np.abs(ref[mask]).sum())
    if d.size == 0:
        return 0.0
    if s < 1e-9:
        return float(d.mean())
    return float(d.sum() / s)


def rel_energy(a: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    """``|sum a - sum ref| / sum ref`` over ``mask`` (all channels): the error in the light
    an image carries, for images of sub-pixel highlights whose per-pixel error is noise
    (a glass under lamps with area); the absolute difference of the sums if the
    reference is black there."""
    sa, sr = float(a[mask].sum()), float(ref[mask].sum())
    return abs(sa - sr) / sr if sr > 1e-9 else abs(sa - sr)


_clock: Callable[[], float] = time.perf_counter


def _timed(fn):
    t0 = _clock()
    out = fn()
    return out, _clock() - t0


def phase_error(
    scene: SceneSpec,
    phase: str,
    *,
    geometry: RigGeometry,
    camera: Camera | None = None,
    ref_spp: int = 256,
    seed: int = 0,
    table_deg: float = 20.0,
    renderer: SimRenderer | None = None,
    warm: bool = False,
    selected: EffectConfig | None = None,
    also: Sequence[EffectConfig] = (),
    clock: Callable[[], float] | None = None,
) -> PhaseError:
    """Error of the effect selection for ``phase`` against the reference (see module doc).

    Parameters
    ----------
    scene, phase : what to measure.
    geometry : RigGeometry — lights and displays.
    camera : rig-frame camera (default :func:`eval_camera`; the calibration phase
        widens it to frame the board).
    ref_spp : reference samples per pixel (groundtruth: coverage reference uses 4× this).
    warm : render each configuration before timing (keeps JIT compilation out).
    selected : measure this configuration instead of the selection (default
        ``select_effects(pixels=...)`` of the camera: what a capture with it gets).
    also : further configurations measured against the same reference images (warm
        like the selection when ``warm``); their errors and times land in ``.also``.
    clock : what the seconds are measured with (default wall time,
        ``time.perf_counter``; ``time.process_time`` gives the CPU time of this process,
        all of Mitsuba's threads — steadier on a machine shared with other jobs).
    """
    global _clock
    previous, _clock = _clock, (clock or time.perf_counter)
    try:
        return _phase_error(
            scene,
            phase,
            geometry=geometry,
            camera=camera,
            ref_spp=ref_spp,
            seed=seed,
            table_deg=table_deg,
            renderer=renderer,
            warm=warm,
            selected=selected,
            also=also,
        )
    finally:
        _clock = previous


def _phase_error(
    scene, phase, *, geometry, camera, ref_spp, seed, table_deg, renderer, warm, selected, also
) -> PhaseError:
    from .groundtruth import render_ground_truth

    r = renderer or SimRenderer(scene, geometry)
    if camera is None:
        camera = calibration_camera() if phase == "calibration" else eval_camera()
    # the selection a capture with this camera gets (matting samples depend on its size)
    sel = selected or select_effects(
        scene, phase, pixels=camera.width * camera.height, lamp_radius_m=lamp_radius(r.geometry)
    )
    ref = reference_effects(scene, phase, spp=ref_spp)
    view = RigGeometry.view_camera(camera, table_deg)
    ids = [L.id for L in geometry.lights]
    rng = np.random.default_rng(seed)

    if phase == "groundtruth":
        ref_a = render_ground_truth(scene, view, spp=4 * ref_spp, renderer=r, seed=seed + 7)["alpha"]
        mask = coverage_mask(ref_a)

        def gt_err(cfg, s0):
            if warm:
                render_ground_truth(scene, view, spp=cfg.spp, renderer=r, seed=s0 + 1)
            a, t = _timed(lambda: render_ground_truth(scene, view, spp=cfg.spp, renderer=r, seed=s0)["alpha"])
            return (float(np.abs(a - ref_a)[mask].mean()) if mask.any() else 0.0), t

        err, t_sel = gt_err(sel, seed)
        _, t_ref = _timed(lambda: render_ground_truth(scene, view, spp=4 * ref_spp, renderer=r, seed=seed + 3))
        extra = tuple((c, *gt_err(c, seed + 50 + i)) for i, c in enumerate(also))
        return PhaseError(scene.source, phase, sel.error_metric, err, sel.error_bound, t_sel, t_ref, sel, ref, extra)

    if phase == "calibration":
        boards = [p.charuco for p in scene.parts if p.kind == "board"]
        charuco = boards[0] if boards else CharucoSpec()
        parts = board_parts(charuco)
        base = SimState(table_deg=table_deg, light_levels={i: 255 for i in ids}, content="board", charuco=charuco)
        states = [base]
    else:
        parts = scene.parts
        if phase == "lightfield":
            states = [SimState(table_deg=table_deg, light_levels={i: 255 for i in ids})]
        elif phase == "reflectance":
            mid = ids[len(ids) // 2] if ids else None
            states = [SimState(table_deg=table_deg, light_levels={} if mid is None else {mid: 255})]
        elif phase == "envmatte":
            disp = {}
            for d in geometry.displays:
                w, h = d.resolution
                u = np.arange(w)
                stripes = (((u * 6) // w) % 2 * 255).astype(np.uint8)
                disp[d.name] = np.repeat(np.tile(stripes, (h, 1))[:, :, None], 3, axis=2)
            states = [SimState(table_deg=table_deg, displays=disp)]
        elif phase == "matting":
            p1 = {
                d.name: rng.integers(0, 256, (d.resolution[1], d.resolution[0], 3), dtype=np.uint8)
                for d in geometry.displays
            }
            p2 = {k: (255 - v).astype(np.uint8) for k, v in p1.items()}
            states = [
                SimState(table_deg=table_deg, displays=p1),
                SimState(table_deg=table_deg, displays=p2),
                SimState(table_deg=table_deg, displays=p1, content="none"),
                SimState(table_deg=table_deg, displays=p2, content="none"),
            ]
        else:
            raise ValueError(f"phase {phase!r}")

    cov = render_ground_truth(scene, view, spp=64, renderer=r, parts=parts, seed=seed + 11)["alpha"]
    mask = coverage_mask(cov)

    def run(cfg: EffectConfig, s0: int):
        # As a capture runs: backdrop-only shots first, each state rendered once from an
        # empty radiance cache, so the only reuse is what a capture reuses too — a
        # cropped object shot takes its outside pixels from the backdrop shot of the
        # same displays (sim/render.py, "Crop"). Every render is timed.
        r.clear_radiance_cache()
        order = sorted(range(len(states)), key=lambda k: states[k].content != "none")
        out: list = [None] * len(states)
        for k in order:
            out[k] = r.render(camera, states[k], effects=cfg, seed=s0 + k, use_cache=True)
        r.clear_radiance_cache()
        return out

    if warm:
        # the reference's kernels compiled first, the selection's launched twice right
        # before it is timed: the first launch after another configuration's kernels costs
        # ~0.1 s more (measured on the diffuse lightfield: 0.16 against 0.07 CPU s), which
        # a capture — the same configuration shot after shot — does not pay; the
        # reference (seconds) and the ``also`` candidates (each warmed right before its
        # timing) are measured in the same steady state
        run(ref, seed + 200)
        run(sel, seed + 100)
        run(sel, seed + 101)
    out_sel, t_sel = _timed(lambda: run(sel, seed))
    out_ref, t_ref = _timed(lambda: run(ref, seed + 1000))

    def error(out) -> float:
        if phase == "matting":
            a_ref = triangulation_alpha(*out_ref)
            return float(np.abs(triangulation_alpha(*out) - a_ref)[mask].mean()) if mask.any() else 0.0
        if phase == "calibration":
            return corner_error(out[0], out_ref[0], charuco)
        if sel.error_metric == "rel_energy":
            return rel_energy(out[0], out_ref[0], mask)
        return rel_mae(out[0], out_ref[0], mask)

    extra = []
    for i, c in enumerate(also):
        if warm:
            run(c, seed + 300 + i)
        out_c, t_c = _timed(lambda c=c, i=i: run(c, seed + 2000 + 10 * i))
        extra.append((c, error(out_c), t_c))
    return PhaseError(
        scene.source, phase, sel.error_metric, error(out_sel), sel.error_bound, t_sel, t_ref, sel, ref, tuple(extra)
    )


def point_geometry(g: RigGeometry) -> RigGeometry:
    """``g`` with every lamp an ideal point light (``radius_m`` None): the old light model."""
    return replace(g, lights=tuple(replace(L, radius_m=None) for L in g.lights))


def lamp_change(p1: np.ndarray, p2: np.ndarray, a1: np.ndarray, a2: np.ndarray) -> dict:
    """Independent renders under point lights (``p1``, ``p2``) and lamps (``a1``, ``a2``):
    ``change`` = ‖a2 − p1‖ / ‖p1‖; ``noise_floor`` = what ``change`` is when the two
    differ only by noise, √((‖p1 − p2‖² + ‖a1 − a2‖²) / 2) / ‖p1‖; ``excess`` = the part
    of ``change`` beyond that, √max(0, change² − floor²) (the lamps' systematic effect)."""
    n = float(np.linalg.norm(p1))
    if n == 0:
        nan = float("nan")
        return {"change": nan, "noise_floor": nan, "excess": nan}
    change = float(np.linalg.norm(a2 - p1)) / n
    floor = float(np.sqrt((np.sum((p1 - p2) ** 2.0) + np.sum((a1 - a2) ** 2.0)) / 2.0)) / n
    return {"change": change, "noise_floor": floor, "excess": float(np.sqrt(max(0.0, change**2 - floor**2)))}
