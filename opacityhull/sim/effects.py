"""Effect selection: pay only for the light transport a scene and a capture phase need.

:func:`select_effects` looks at the materials the object is made of (their *effect
classes*: diffuse, glossy, transmissive), at fine geometry (fibres thinner than a
pixel) and at the capture phase, and picks

* the integrator and path depth — ``direct`` for opaque Lambertian objects (one
  bounce: light → surface → camera); ``path`` with a few bounces for glossy objects
  (highlights reflect the rest of the object); ``path`` with deep paths for
  dielectrics (a ray crosses at least two interfaces before it reaches a backdrop
  pixel or a light; PITFALLS: ``direct`` leaves glass black, depth 8 matched 16);
  the ``aov`` integrator for ground truth;
* which emitters exist at all — the light array in the lightfield / reflectance
  phases, the displays in the matting / envmatte phases, whatever is switched on in
  calibration; an emitter that is off is left out of the Mitsuba scene, not set to 0,
  and an emitter group that provably adds nothing is not rendered even when it is on
  (``skipped``): point lights seen through an object made only of delta BSDFs (smooth
  glass, polished metal) on black panels, or anything but the displays themselves when
  the table is empty (:func:`backdrop_only_effects`);
* which shapes exist — the object (or, in calibration, the board) and the display
  panels (black absorbers when off, since they still cast shadows); ground truth
  renders the object alone;
* samples per pixel — enough for the quantity the phase consumes (alpha edges,
  sub-pixel fibres, Monte-Carlo noise of area emitters and deep paths);
* ``resolution_scale`` — supersampling factor of the render relative to the camera
  (the capture is box-filtered back to the camera's size); 1 everywhere by default
  since the box pixel filter already integrates the pixel area.

A capture whose rig state has several emitter groups on (the matting phase with the
lights on) is rendered as one pass per group, each with the selection of the phase
that group belongs to — displays with the matting selection, lights with the lightfield
one (light transport is linear; :meth:`opacityhull.sim.render.SimRenderer.passes_for`).

Each selection states the error it promises against a full-effects reference
(``path``, ``max_depth`` 16, high spp) on the quantity its phase consumes
(``error_metric``, ``error_bound``); ``benchmarks/sim_effects.py`` measures it and
``tests/sim/test_sim_effect_bounds.py`` asserts it on a small image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any
from collections.abc import Mapping

from ..errors import ConfigError
from .scenes import SceneSpec

__all__ = [
    "EffectConfig",
    "select_effects",
    "reference_effects",
    "backdrop_only_effects",
    "scene_kind",
    "expected_cost",
    "cheapest_within",
    "MATTING_CANDIDATES",
    "matting_candidates_for",
    "MATTING_SIZES",
    "MATTING_MARGIN",
    "Candidate",
    "MEASURED_COST",
    "ENVMATTE_LARGE",
    "envmatte_spp",
    "BACKDROP_SPP",
    "PHASES",
    "ERROR_METRICS",
    "PHASE_EMITTERS",
]

#: Phases the simulator knows; the first five are capture phases of ``acquire``.
PHASES = ("calibration", "matting", "lightfield", "reflectance", "envmatte", "groundtruth")

#: What each phase consumes and how the error against the reference is measured:
#: ``alpha_mae`` — mean absolute error of triangulation-matting alpha (matting) or of
#: coverage alpha (groundtruth) over the image; ``rel_mae`` — mean absolute radiance
#: error over the pixels the object covers, relative to their mean reference radiance;
#: ``corner_px`` — mean distance between the ChArUco corners OpenCV detects in both.
ERROR_METRICS = {
    "calibration": "corner_px",
    "matting": "alpha_mae",
    "lightfield": "rel_mae",
    "reflectance": "rel_mae",
    "envmatte": "rel_mae",
    "groundtruth": "alpha_mae",
}

#: The emitter groups each phase switches on (what the full-effects reference renders).
PHASE_EMITTERS = {
    "calibration": ("light_array", "displays"),
    "matting": ("displays",),
    "envmatte": ("displays",),
    "lightfield": ("light_array",),
    "reflectance": ("light_array",),
    "groundtruth": (),
}

_INTEGRATORS = ("direct", "path", "aov")
_OVERRIDABLE = (
    "integrator",
    "max_depth",
    "spp",
    "emitters",
    "shapes",
    "resolution_scale",
    "sampler",
    "crop",
    "backdrop_spp",
)

#: Samples per pixel of the backdrop-only shots (nothing on the table) of a selection:
#: depth 1 is exact at any spp; the samples only anti-alias the panels' texel edges.
#: Measured (matting, camera 2 of the default rig, 200x150, 256-spp reference): alpha
#: error 0.0093 / 0.0106 / 0.0150 (sphere) and 0.0095 / 0.0104 / 0.0149 (cup) with the
#: backdrops at 64 / 16 / 4 spp, bounds 0.025.
BACKDROP_SPP = 16


@dataclass(frozen=True)
class EffectConfig:
    """What the simulator renders for one phase of one scene.

    Attributes
    ----------
    integrator : "direct" | "path" | "aov"
    max_depth : int
        Mitsuba path depth (1 = emitters seen directly, 2 = direct lighting, 3 = one
        indirect bounce, ...). ``direct`` is depth 2.
    spp : int
        Samples per pixel.
    emitters : tuple of str
        Emitter groups that may exist: ``"light_array"``, ``"displays"``. Only those
        switched on at capture time are put into the scene.
    shapes : tuple of str
        ``"object"`` (or ``"board"``) and ``"displays"`` (panels as geometry).
    resolution_scale : float
        Render at this multiple of the camera resolution, box-filtered back.
    reasons : tuple of str
        Why, in words (``opacityhull sim explain``).
    sampler : "independent" | "stratified"
    phase : str
    error_metric, error_bound : str, float
        The promise against the full-effects reference (see :data:`ERROR_METRICS`).
    skipped : tuple of str
        Emitter groups that may be switched on in this phase but provably add nothing
        to the image (exactly 0): they are not rendered.
    backdrop_spp : int or None
        Samples per pixel of the backdrop-only shots of this selection
        (:func:`backdrop_only_effects`); None: ``spp``.
    crop : bool
        Render only the window of pixels whose camera rays can meet what stands on the
        table (its projected bounding box plus the pixel filter's support); the rest of
        the frame is exact without it — the backdrop-only render (displays) or black
        (lights). The same estimator inside the window (:mod:`opacityhull.sim.render`).
    """

    integrator: str
    max_depth: int
    spp: int
    emitters: tuple[str, ...]
    shapes: tuple[str, ...]
    resolution_scale: float = 1.0
    reasons: tuple[str, ...] = ()
    sampler: str = "independent"
    phase: str = ""
    error_metric: str = "rel_mae"
    error_bound: float = 0.05
    skipped: tuple[str, ...] = ()
    crop: bool = True
    backdrop_spp: int | None = None

    def key(self) -> tuple:
        """What determines the Mitsuba scene's structure and kernels (cache key)."""
        return (self.integrator, self.max_depth, self.sampler, self.emitters, self.shapes)

    def to_json(self) -> dict[str, Any]:
        return {
            "integrator": self.integrator,
            "max_depth": self.max_depth,
            "spp": self.spp,
            "emitters": list(self.emitters),
            "shapes": list(self.shapes),
            "resolution_scale": self.resolution_scale,
            "sampler": self.sampler,
            "phase": self.phase,
            "error_metric": self.error_metric,
            "error_bound": self.error_bound,
            "skipped": list(self.skipped),
            "crop": self.crop,
            "backdrop_spp": self.backdrop_spp,
            "reasons": list(self.reasons),
        }


def _check_phase(phase: str) -> None:
    if phase not in PHASES:
        raise ConfigError(f"phase {phase!r}: expected one of {list(PHASES)}")


#: scene kind -> (pixels, spp): envmatte shots of cameras above that many pixels take
#: that many samples instead of the table's (:func:`envmatte_spp`)
ENVMATTE_LARGE: dict[str, tuple[int, int]] = {"diffuse": (60_000, 100)}
ENVMATTE_LARGE_WHY = (
    "benchmarks/sim_effects.py, 256-spp reference: diffuse at 64 spp 0.065 / 0.074 / 0.082 at "
    "200x150 / 280x210 / 400x300 against the bound 0.08; at 400x300 100 spp give 0.073 (sphere "
    "0.067), still 5.1x (4.7x) cheaper than the reference at equal error"
)


def envmatte_spp(kind: str, pixels: int | None) -> int:
    """The envmatte selection's samples for a scene kind and camera size (``pixels``
    None: the default rig's 200x150): the table's, or :data:`ENVMATTE_LARGE`'s above its
    size. An undeclared displays-on shot (it may be an envmatte one) takes at least as
    many."""
    spp = int(_TABLE[(kind, "backdrop")][2])
    big = ENVMATTE_LARGE.get(kind)
    if big is not None and pixels is not None and int(pixels) > big[0]:
        spp = max(spp, int(big[1]))
    return spp


def select_effects(
    scene: SceneSpec,
    phase: str,
    *,
    overrides: Mapping[str, Any] | None = None,
    declared: bool = True,
    pixels: int | None = None,
    lamp_radius_m: float | None = None,
) -> EffectConfig:
    """Choose the cheapest rendering that is faithful for ``scene`` in ``phase``.

    Parameters
    ----------
    scene : SceneSpec
    phase : one of :data:`PHASES`
    overrides : mapping, optional
        Force fields (``integrator``, ``max_depth``, ``spp``, ``emitters``, ``shapes``,
        ``resolution_scale``, ``sampler``); each override is recorded in ``reasons``.
    declared : bool
        Matting only: the capture declared its phase (``SimState.phase``). A displays-on,
        lights-off shot whose phase is not declared may be an envmatte shot — the rig
        state is the same — so it is rendered with the matting integrator at the
        envmatte selection's spp (within both bounds, measured); a declared matting
        shot gets the cheapest measured matting candidate (:data:`MATTING_CANDIDATES`).
    pixels : int, optional
        Matting only: pixels of the camera the shot is for. The matte's error falls with
        the resolution (fewer covered pixels are edge pixels), so a declared matting shot
        takes its candidate from the largest measured camera size not above ``pixels``
        (:func:`matting_candidates_for`); without it, from the smallest (the 64x48 test
        camera: the most samples). Envmatte: above :data:`ENVMATTE_LARGE`'s size a
        scene kind takes more samples (:func:`envmatte_spp`).
    lamp_radius_m : float, optional
        The light array's smallest lamp radius (:func:`~opacityhull.sim.render.lamp_radius`);
        ``None``: ideal point lights. Lamps with area are not skipped for a delta-BSDF
        object: a glass shows each lamp as a highlight and a refracted blob.

    Raises
    ------
    ConfigError
        Unknown phase or override key, or an invalid override value.
    """
    _check_phase(phase)
    fine = scene.has_fibres
    board = scene.is_board or phase == "calibration"
    reasons: list[str] = []
    metric = ERROR_METRICS[phase]

    if phase == "groundtruth":
        spp = 64
        reasons.append(
            "ground truth: aov integrator (coverage alpha, depth, normals, shape index) "
            "on the object alone, no emitters, no displays"
        )
        reasons.append("8x8 stratified samples per pixel: coverage error at edges ~1/64")
        if fine:
            reasons.append(
                "fibres thinner than a pixel: stratified sampling keeps their fractional coverage "
                "within ~0.02 per covered pixel at 64 spp (256 spp halves it at 2.5x the time)"
            )
        cfg = EffectConfig(
            "aov", 1, spp, (), ("object",), 1.0, (), "stratified", phase, metric, 0.04 if fine else 0.01, crop=False
        )
        return _apply_overrides(replace(cfg, reasons=tuple(reasons)), overrides)

    # --- emitters and shapes
    if phase == "calibration":
        emitters = ("light_array", "displays")
        shapes = ("board", "displays")
        reasons.append("calibration: the board replaces the object; whatever is switched on lights it")
    elif phase in ("matting", "envmatte"):
        emitters = ("displays",)
        shapes = ("object", "displays")
        reasons.append(f"{phase}: backdrops only — no light-array emitters in the scene")
    else:  # lightfield, reflectance
        emitters = ("light_array",)
        shapes = ("object", "displays")
        reasons.append(
            f"{phase}: light-array "
            + (f"lamps (spheres of radius {lamp_radius_m:g} m)" if lamp_radius_m else "point lights")
            + " only; displays are black panels (kept as geometry: they shadow)"
        )
    reasons.append("emitters that are off are left out of the scene entirely")
    skipped: tuple[str, ...] = ()
    area = lamp_radius_m is not None and lamp_radius_m > 0
    if phase in ("lightfield", "reflectance") and scene.delta_only and not board and area:
        reasons.append(
            f"every material is a delta BSDF, but the lamps have area (radius {lamp_radius_m:g} m, a bulb "
            "behind a diffuser): a camera ray reflected or refracted through the object hits the lamp "
            "sphere, so each one-light image shows the lamp as a highlight and a refracted blob — the "
            "light array is rendered, with the dielectric's path depth"
        )
    elif phase in ("lightfield", "reflectance") and scene.delta_only and not board:
        emitters, skipped = (), ("light_array",)
        reasons.append(
            "every material is a delta BSDF (smooth dielectric or polished conductor) and the panels "
            "are black: no path joins a point light to the camera (a ray cannot hit a point, light "
            "sampling cannot leave a delta surface) — the image is exactly black; nothing is rendered"
        )

    # --- integrator, depth, samples: a table measured by benchmarks/sim_effects.py
    # (errors against path tracing at depth 16, 1024 spp; see _TABLE)
    kind = scene_kind(scene, phase)
    group = "calibration" if phase == "calibration" else ("backdrop" if phase in ("matting", "envmatte") else "lights")
    row = _FIBRES_MATTING if phase == "matting" and kind == "fibres" else _TABLE[kind, group]
    integrator, depth, spp, bound, why = row
    if area and group == "lights" and kind == "transmissive" and scene.delta_only:
        integrator, depth, spp, bound, why = _LAMPS_ON_GLASS
        metric = "rel_energy"
    reasons.extend(why)
    bound = bound[phase] if isinstance(bound, dict) else bound
    if phase in ("matting", "envmatte"):
        env_spp = envmatte_spp(kind, pixels)
        if phase == "envmatte" and env_spp != spp:
            spp = env_spp
            reasons.append(
                f"envmatte on a camera of {pixels} px (> {ENVMATTE_LARGE[kind][0]}): {env_spp} spp — the "
                f"error at the table's spp grows with the camera ({ENVMATTE_LARGE_WHY})"
            )
    if phase == "matting" and kind in MATTING_CANDIDATES:
        if declared:
            (mw, mh), cands = matting_candidates_for(kind, pixels)
            c = cheapest_within(cands, bound)
            integrator, depth, spp = c.integrator, c.max_depth, c.spp
            reasons.append(
                f"matting: the cheapest measured candidate inside the crop whose alpha error is within "
                f"{MATTING_MARGIN:g} x the bound {bound:g} — {c.integrator} d{c.max_depth} {c.spp} spp, measured "
                f"{c.error:.4f} at {c.seconds:.3f} s per object + backdrop shot pair at {mw}x{mh} "
                + ("(the smallest measured camera)" if pixels is None or pixels < mw * mh else f"(<= {pixels} px)")
                + " (candidates: "
                + ", ".join(f"{k.integrator} d{k.max_depth} {k.spp}: {k.error:.4f}, {k.seconds:.3f} s" for k in cands)
                + f"; {MATTING_SOURCE})"
            )
        else:
            spp = max(spp, env_spp)
            reasons.append(
                f"the capture did not declare its phase: an envmatte shot looks the same to the rig "
                f"(displays on, lights off), so the envmatte selection's {env_spp} spp keep it within "
                "the envmatte bound too (benchmarks/sim_effects.py: 'envmatte (captured as matting)')"
            )
    reasons.append(f"stratified samples ({spp} = {int(round(spp**0.5))}x{int(round(spp**0.5))} per pixel)")
    reasons.append(
        "only the pixels whose rays can meet the "
        + ("board" if board else "object")
        + " are rendered (its projected bounding box + the box filter's 0.5 px support; pinhole: no "
        "depth of field); every other ray sees only the panels: the exact backdrop-only render (path "
        "depth 1) where they emit, exactly 0 under the lights"
    )
    if phase in ("matting", "envmatte"):
        reasons.append(
            f"backdrop-only shots (nothing on the table): path depth 1, exact at any spp; "
            f"{BACKDROP_SPP} spp anti-alias the panels' texel edges (measured: the matte error rises "
            f"0.0093 -> 0.0106 from 64 spp, at a quarter of the samples)"
        )
    cfg = EffectConfig(
        integrator,
        depth,
        spp,
        emitters,
        shapes,
        1.0,
        tuple(reasons),
        "stratified",
        phase,
        metric,
        bound,
        skipped,
        backdrop_spp=min(BACKDROP_SPP, spp),
    )
    return _apply_overrides(cfg, overrides)


def scene_kind(scene: SceneSpec, phase: str) -> str:
    """The row of the measured selection table a scene falls in: ``board`` (calibration),
    ``diffuse``, ``transmissive``, ``fibres`` or ``glossy``."""
    classes = scene.effect_classes
    if phase == "calibration":
        return "board"
    if scene.is_board or not ({"transmissive", "glossy"} & classes or scene.has_fibres):
        return "diffuse"  # a board captured outside calibration is diffuse paper
    if "transmissive" in classes:
        return "transmissive"
    if scene.has_fibres:
        return "fibres"
    return "glossy"


def expected_cost(scene: SceneSpec, phase: str, *, lamp_radius_m: float | None = None) -> dict:
    """Expected time of the selection relative to the full-effects reference for
    ``phase``, as measured by ``benchmarks/sim_effects.py`` (:data:`MEASURED_COST`): the
    built-in scene's own figure, else the worst figure among built-ins of the same
    :func:`scene_kind`. Returns ``{"vs_reference": float | None, "measured": str}``."""
    _check_phase(phase)
    if lamp_radius_m and phase in ("lightfield", "reflectance") and scene.delta_only and not scene.is_board:
        return {
            "vs_reference": None,
            "measured": "lamps with area light a delta-BSDF object; the table measured point lights (black there)",
        }
    name = scene.source.split(":", 1)[1] if scene.source.startswith("builtin:") else None
    if name is not None and (name, phase) in MEASURED_COST:
        return {"vs_reference": MEASURED_COST[(name, phase)], "measured": f"{MEASURED_COST_SOURCE}, builtin:{name}"}
    kind = scene_kind(scene, phase)
    same = [v for (n, ph), v in MEASURED_COST.items() if ph == phase and _BUILTIN_KIND.get((n, ph)) == kind]
    if not same:
        return {"vs_reference": None, "measured": f"no built-in scene of kind {kind!r} measured in {phase}"}
    return {"vs_reference": max(same), "measured": f"{MEASURED_COST_SOURCE}, worst built-in of kind {kind!r}"}


def backdrop_only_effects(cfg: EffectConfig) -> EffectConfig:
    """What a capture with nothing on the table needs, from the selection ``cfg`` of the
    phase (the object-absent backdrop shots of matting).

    The only geometry left is the display panels, black except where they emit: a camera
    ray either hits an emitting panel (its radiance, depth 1) or something black, and no
    bounce can add anything, so ``path`` at ``max_depth`` 1 is *exact* — the same
    expected image as any deeper integrator — and the light array adds exactly nothing
    (``skipped``). The sampler stays that of ``cfg``; the samples per pixel are
    ``cfg.backdrop_spp`` (at most ``cfg.spp``; the selections' :data:`BACKDROP_SPP`,
    measured within the matting bounds) — they only anti-alias the panels' texel edges.
    The reference (``backdrop_spp`` None) keeps its own spp.
    """
    if cfg.integrator == "aov":
        return cfg
    reasons = cfg.reasons + (
        "nothing on the table: only the emitting panels are seen (black everywhere else, nothing to bounce "
        "off) — path depth 1 is exact; the light array adds nothing and is not rendered",
    )
    spp = cfg.spp if cfg.backdrop_spp is None else min(cfg.spp, int(cfg.backdrop_spp))
    return replace(
        cfg,
        integrator="path",
        max_depth=1,
        spp=spp,
        crop=False,
        emitters=tuple(e for e in cfg.emitters if e == "displays"),
        shapes=("displays",),
        skipped=tuple(sorted(set(cfg.skipped) | {"light_array"})),
        reasons=reasons,
    )


_WHY_DIRECT_DIFFUSE = (
    "diffuse opaque materials: direct lighting only (light -> surface -> camera); "
    "interreflection in concavities is the error left (about -6% of the energy for the cup)",
)
_WHY_GLASS = (
    "dielectric: rays cross >= 2 interfaces before they reach a backdrop or a light; direct lighting "
    "leaves glass black (needs >= 3); depth 8 matches 16 within noise",
)
_WHY_GLOSSY = (
    "glossy materials: highlights reflect other parts of the object — one indirect bounce (depth 3) "
    "measures the same as depth 6",
)
_WHY_FIBRES = ("fibres: light scatters from fibre to fibre (direct lighting loses ~20% of the energy, depth 6 ~2%)",)

#: (kind, phase group) -> (integrator, max_depth, spp, error bound, reasons). Bounds are
#: the measured errors (benchmarks/out/sim_effects.md) with margin for Monte-Carlo noise,
#: the reference's included.
_TABLE: dict[tuple[str, str], tuple] = {
    ("board", "calibration"): (
        "direct",
        2,
        16,
        0.15,
        (
            "board is printed paper (diffuse, flat): direct lighting only",
            "the corners OpenCV finds move < 0.1 px against the reference at 16 spp",
        ),
    ),
    ("diffuse", "backdrop"): (
        "direct",
        2,
        64,
        {"matting": 0.025, "envmatte": 0.08},
        _WHY_DIRECT_DIFFUSE
        + (
            "the displays are large textured area emitters that also light the object: 64 spp keep the "
            "matte noise near 0.01",
        ),
    ),
    ("diffuse", "lights"): (
        "direct",
        2,
        16,
        0.18,
        _WHY_DIRECT_DIFFUSE
        + ("point lights with direct lighting are noise-free: the samples only anti-alias edges and texture",),
    ),
    ("glossy", "backdrop"): (
        "path",
        3,
        64,
        {"matting": 0.03, "envmatte": 0.1},
        _WHY_GLOSSY + ("backdrops are reflected in the glossy surfaces and light them: 64 spp",),
    ),
    ("glossy", "lights"): ("path", 3, 36, 0.1, _WHY_GLOSSY + ("the indirect bounce is sampled: 36 spp",)),
    ("transmissive", "backdrop"): (
        "path",
        8,
        64,
        {"matting": 0.04, "envmatte": 0.07},
        _WHY_GLASS + ("the backdrop seen through glass (Fresnel reflection/refraction split): 64 spp",),
    ),
    ("transmissive", "lights"): (
        "path",
        8,
        64,
        0.1,
        _WHY_GLASS
        + (
            "point lights seen through smooth glass are delta paths no integrator finds: under the light array "
            "a glass object shows only what it refracts of lit surfaces",
        ),
    ),
    ("fibres", "backdrop"): (
        "path",
        6,
        64,
        {"matting": 0.05, "envmatte": 0.1},
        _WHY_FIBRES + ("sub-pixel fibres: 64 spp resolve their fractional coverage",),
    ),
    ("fibres", "lights"): (
        "path",
        6,
        64,
        0.2,
        _WHY_FIBRES + ("sub-pixel fibres: 64 spp; per-pixel noise stays ~0.15 (their coverage varies within a pixel)",),
    ),
}
#: A delta-BSDF object under lamps with area (lightfield / reflectance): what it shows is
#: the lamps' reflected and refracted images, sub-pixel highlights on a curved glass (a
#: 2.5 cm lamp at 1 m in a 3 cm-radius bottle images to < 1 mm). Per-pixel error is the
#: highlights' sampling noise at any affordable spp (measured on the 64x48 test camera,
#: all lamps on: 1024-spp renders differ from each other by rel_mae 0.67, the selection
#: against the 256-spp reference by 0.85-3.0 over seeds 11-13), so the bound is on the
#: light the image carries (``rel_energy``, :func:`~opacityhull.sim.evaluate.rel_energy`).
#: Even that is the reference's noise at 64x48 (measured 0.38, 1.0, 1.29 over seeds
#: 11-13; two 256-spp references differ by a factor 3): the bound 1.5 only says the
#: selection is within the reference's own spread; tests/sim/test_sim_lamps.py checks
#: that the glass is lit at all.
_LAMPS_ON_GLASS = (
    "path",
    8,
    64,
    1.5,
    _WHY_GLASS
    + (
        "lamps with area: a path camera -> glass interfaces -> lamp is found by BSDF sampling (no light "
        "sampling off a delta surface); depth 8 lets it cross both walls twice",
        "the lamps' images are sub-pixel highlights: their per-pixel error is sampling noise at any spp "
        "(two 1024-spp renders differ by 0.67), so the bound is on the light the image carries (rel_energy)",
    ),
)
_FIBRES_MATTING = (
    "direct",
    2,
    64,
    0.05,
    (
        "fibres in the matting phase: the alpha matte depends on coverage; scattering between fibres changes "
        "the foreground colour alike over both backdrops and measures the same as depth 6 — direct lighting",
        "sub-pixel fibres: 64 spp resolve their fractional coverage",
    ),
)


@dataclass(frozen=True)
class Candidate:
    """One measured way of rendering a phase: integrator, depth, spp, the measured error
    on what the phase consumes and the measured seconds (see :data:`MATTING_CANDIDATES`)."""

    integrator: str
    max_depth: int
    spp: int
    error: float
    seconds: float


def cheapest_within(candidates, bound: float, *, margin: float | None = None) -> Candidate:
    """The cheapest candidate (least measured ``seconds``; fewer spp on a tie) whose
    measured ``error`` is at most ``margin * bound``; the margin (default
    :data:`MATTING_MARGIN`) leaves room for the Monte-Carlo spread of a single
    measurement and for other cameras and seeds. Raises ConfigError if none qualifies or
    the arguments are not finite and positive."""
    margin = MATTING_MARGIN if margin is None else float(margin)
    if not (math.isfinite(bound) and bound > 0 and math.isfinite(margin) and 0 < margin <= 1):
        raise ConfigError(f"cheapest_within: bound {bound!r} must be > 0 and margin {margin!r} in (0, 1]")
    ok = [c for c in candidates if math.isfinite(c.error) and math.isfinite(c.seconds) and c.error <= margin * bound]
    if not ok:
        raise ConfigError(
            f"cheapest_within: no candidate within {margin:g} x bound {bound:g} "
            f"(errors: {[round(c.error, 4) for c in candidates]})"
        )
    return min(ok, key=lambda c: (c.seconds, c.spp))


def matting_candidates_for(kind: str, pixels: int | None = None) -> tuple[tuple[int, int], tuple[Candidate, ...]]:
    """``((width, height), candidates)`` of :data:`MATTING_CANDIDATES` for a camera of
    ``pixels`` pixels: those measured at the largest size not above it — the error of a
    matte falls with the resolution, so a larger camera may use what a smaller one
    measured, never the reverse. Without ``pixels``, or below every measured size, the
    smallest. Raises KeyError for a kind without candidates."""
    sizes = sorted(MATTING_CANDIDATES[kind], key=lambda wh: wh[0] * wh[1])
    fit = [wh for wh in sizes if pixels is not None and wh[0] * wh[1] <= pixels]
    size = fit[-1] if fit else sizes[0]
    return size, MATTING_CANDIDATES[kind][size]


#: Safety factor of :func:`cheapest_within`: a candidate qualifies if its measured error
#: is at most this fraction of the bound — two seeds of the same measurement differ by up
#: to ~10 %.
MATTING_MARGIN = 0.85

#: Where :data:`MATTING_CANDIDATES` comes from.
MATTING_SOURCE = (
    "benchmarks/sim_effects.py --matting-candidates --rounds 2: error = the worst of the kind's built-in "
    "scenes at one camera size (the 64x48 test camera evaluate.eval_camera, camera 2 of the default rig "
    "at 200x150 and at 400x300), table 20 deg, 256-spp reference, mean of 2 seeds; seconds = median CPU "
    "time of an object + backdrop shot pair of the 400x300 rig camera (the ranking; at 200x150 per-call "
    "overheads and their noise reorder near-equal candidates), candidates measured alternately, 2-core machine shared with other jobs (path d2 "
    "and direct d2 are within that noise of each other)"
)
#: camera sizes (width, height) the matting candidates were measured at, smallest first
MATTING_SIZES: tuple[tuple[int, int], ...] = ((64, 48), (200, 150), (400, 300))

#: kind -> (integrator, max_depth, spp, seconds, (error at each of :data:`MATTING_SIZES`))
_MATTING_ROWS: dict[str, tuple[tuple[str, int, int, float, tuple[float, ...]], ...]] = {
    "diffuse": (
        ("direct", 2, 9, 0.190, (0.0369, 0.0231, 0.0200)),
        ("direct", 2, 16, 0.253, (0.0260, 0.0170, 0.0142)),
        ("direct", 2, 25, 0.282, (0.0236, 0.0138, 0.0113)),
        ("direct", 2, 36, 0.381, (0.0196, 0.0120, 0.0097)),
        ("direct", 2, 49, 0.432, (0.0178, 0.0108, 0.0087)),
        ("direct", 2, 64, 0.471, (0.0175, 0.0098, 0.0078)),
        ("path", 2, 16, 0.304, (0.0261, 0.0167, 0.0143)),
        ("path", 2, 36, 0.371, (0.0194, 0.0117, 0.0097)),
    ),
    "transmissive": (
        ("path", 8, 9, 0.181, (0.0653, 0.0445, 0.0363)),
        ("path", 8, 16, 0.238, (0.0483, 0.0319, 0.0253)),
        ("path", 8, 25, 0.284, (0.0390, 0.0251, 0.0207)),
        ("path", 8, 36, 0.358, (0.0341, 0.0230, 0.0182)),
        ("path", 8, 49, 0.423, (0.0322, 0.0210, 0.0163)),
        ("path", 8, 64, 0.451, (0.0310, 0.0192, 0.0152)),
    ),
    "glossy": (
        ("path", 3, 9, 0.246, (0.0408, 0.0292, 0.0227)),
        ("path", 3, 16, 0.287, (0.0312, 0.0205, 0.0175)),
        ("path", 3, 25, 0.377, (0.0286, 0.0163, 0.0141)),
        ("path", 3, 36, 0.467, (0.0251, 0.0147, 0.0120)),
        ("path", 3, 49, 0.543, (0.0231, 0.0131, 0.0107)),
        ("path", 3, 64, 0.618, (0.0219, 0.0121, 0.0098)),
    ),
    "fibres": (
        ("direct", 2, 9, 0.316, (0.0889, 0.0718, 0.0562)),
        ("direct", 2, 16, 0.435, (0.0668, 0.0532, 0.0400)),
        ("direct", 2, 25, 0.627, (0.0552, 0.0417, 0.0312)),
        ("direct", 2, 36, 0.844, (0.0486, 0.0356, 0.0264)),
        ("direct", 2, 49, 1.046, (0.0419, 0.0304, 0.0236)),
        ("direct", 2, 64, 1.278, (0.0381, 0.0281, 0.0217)),
        ("path", 2, 16, 0.438, (0.0670, 0.0521, 0.0398)),
        ("path", 2, 36, 0.816, (0.0494, 0.0353, 0.0265)),
    ),
}

#: kind -> camera size -> the matting candidates measured there (:data:`MATTING_SOURCE`): the
#: worst error among the built-in scenes of that kind and the slowest object + backdrop shot
#: pair. The selection for a declared matting shot is
#: ``cheapest_within(matting_candidates_for(kind, pixels)[1], bound)``; regenerate with
#: ``.venv/bin/python benchmarks/sim_effects.py --matting-candidates`` (its ``table``).
MATTING_CANDIDATES: dict[str, dict[tuple[int, int], tuple[Candidate, ...]]] = {
    kind: {size: tuple(Candidate(i, d, s, e[k], t) for i, d, s, t, e in rows) for k, size in enumerate(MATTING_SIZES)}
    for kind, rows in _MATTING_ROWS.items()
}


def reference_effects(scene: SceneSpec, phase: str, *, spp: int = 512) -> EffectConfig:
    """The full-effects reference for ``phase``: ``path`` tracing, ``max_depth`` 16,
    ``spp`` samples, every emitter group the phase switches on (:data:`PHASE_EMITTERS`,
    also those the selection skips as provably black), the selection's shapes (ground
    truth: the aov integrator at ``spp``)."""
    sel = select_effects(scene, phase)
    if phase == "groundtruth":
        return replace(sel, spp=spp, reasons=("reference: aov at high spp",))
    # every emitter group of the phase, including those the selection proves black
    return replace(
        sel,
        integrator="path",
        max_depth=16,
        spp=spp,
        sampler="independent",
        emitters=PHASE_EMITTERS[phase],
        skipped=(),
        crop=False,
        backdrop_spp=None,
        reasons=(
            "reference: path tracing, max_depth 16, high spp (independent samples), every emitter "
            "group of the phase, the whole frame",
        ),
    )


def _apply_overrides(cfg: EffectConfig, overrides: Mapping[str, Any] | None) -> EffectConfig:
    if not overrides:
        return cfg
    unknown = sorted(set(overrides) - set(_OVERRIDABLE))
    if unknown:
        raise ConfigError(f"effect overrides: unknown key(s) {unknown}; allowed: {list(_OVERRIDABLE)}")
    kw: dict[str, Any] = {}
    for k, v in overrides.items():
        if k == "integrator" and v not in _INTEGRATORS:
            raise ConfigError(f"effect overrides: integrator {v!r}; expected one of {list(_INTEGRATORS)}")
        if k in ("max_depth", "spp", "backdrop_spp") and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"effect overrides: {k} must be a positive integer, got {v!r}")
        if k == "resolution_scale" and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= 8):
            raise ConfigError(f"effect overrides: resolution_scale must be in (0, 8], got {v!r}")
        if k == "sampler" and v not in ("independent", "stratified"):
            raise ConfigError(f"effect overrides: sampler {v!r}; expected 'independent' or 'stratified'")
        if k == "crop" and not isinstance(v, bool):
            raise ConfigError(f"effect overrides: crop must be true or false, got {v!r}")
        if k in ("emitters", "shapes"):
            if isinstance(v, str) or not isinstance(v, (list, tuple)):
                raise ConfigError(f"effect overrides: {k} must be a list of names, got {v!r}")
            v = tuple(v)
        kw[k] = v
    if kw.get("integrator") == "direct" and "max_depth" not in kw:
        kw["max_depth"] = 2
    reasons = cfg.reasons + tuple(f"override: {k} = {v!r}" for k, v in kw.items())
    out = replace(cfg, reasons=reasons, **kw)
    if out.sampler == "stratified" and round(out.spp**0.5) ** 2 != out.spp:
        out = replace(
            out, sampler="independent", reasons=out.reasons + (f"{out.spp} spp is not a square: independent samples",)
        )
    return out


#: Where :data:`MEASURED_COST` comes from.
MEASURED_COST_SOURCE = (
    "benchmarks/out/sim_effects.md (full: 256-spp reference, camera 2 of the default rig at 200x150, "
    "2-core machine with other jobs beside; matting: the declared selection)"
)

#: (built-in scene, phase) -> (scene_kind, time of the selection / time of the reference
#: at the selection's error): the reference configuration (path depth 16, whole frame)
#: at the spp interpolated to the selection's error where it was measured, else at 256
#: spp; CPU seconds, 200x150 (0: nothing is rendered, provably black). The kind lets a
#: scene that is not a built-in inherit the worst figure of its kind. Measured with
#: ``.venv/bin/python benchmarks/sim_effects.py --scenes S --scales 1,1.4,2 --ref-spp 256 --json``
#: one process per scene, merged with ``--merge`` (see the table's notes).
_MEASURED: dict[tuple[str, str], tuple[str, float]] = {
    ("charuco", "calibration"): ("board", 0.054),
    ("charuco", "groundtruth"): ("diffuse", 0.11),
    ("diffuse", "envmatte"): ("diffuse", 0.127),
    ("diffuse", "groundtruth"): ("diffuse", 0.209),
    ("diffuse", "lightfield"): ("diffuse", 1.023),
    ("diffuse", "matting"): ("diffuse", 0.176),
    ("diffuse", "reflectance"): ("diffuse", 0.9),
    ("fuzzy", "envmatte"): ("fibres", 0.469),
    ("fuzzy", "groundtruth"): ("fibres", 0.099),
    ("fuzzy", "lightfield"): ("fibres", 0.47),
    ("fuzzy", "matting"): ("fibres", 0.241),
    ("fuzzy", "reflectance"): ("fibres", 0.493),
    ("glass", "envmatte"): ("transmissive", 0.618),
    ("glass", "groundtruth"): ("transmissive", 0.202),
    ("glass", "lightfield"): ("transmissive", 0.0),
    ("glass", "matting"): ("transmissive", 0.254),
    ("glass", "reflectance"): ("transmissive", 0.0),
    ("glossy", "envmatte"): ("glossy", 0.612),
    ("glossy", "groundtruth"): ("glossy", 0.225),
    ("glossy", "lightfield"): ("glossy", 0.412),
    ("glossy", "matting"): ("glossy", 0.242),
    ("glossy", "reflectance"): ("glossy", 0.315),
    ("sphere", "envmatte"): ("diffuse", 0.129),
    ("sphere", "groundtruth"): ("diffuse", 0.219),
    ("sphere", "lightfield"): ("diffuse", 0.321),
    ("sphere", "matting"): ("diffuse", 0.195),
    ("sphere", "reflectance"): ("diffuse", 0.369),
}
MEASURED_COST: dict[tuple[str, str], float] = {k: v[1] for k, v in _MEASURED.items()}
_BUILTIN_KIND: dict[tuple[str, str], str] = {k: v[0] for k, v in _MEASURED.items()}
