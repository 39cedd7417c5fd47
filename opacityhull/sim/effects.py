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

from dataclasses import dataclass, replace
from typing import Any, Mapping

from ..errors import ConfigError
from .scenes import SceneSpec

__all__ = ["EffectConfig", "select_effects", "reference_effects", "backdrop_only_effects", "PHASES",
           "ERROR_METRICS", "PHASE_EMITTERS"]

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
_OVERRIDABLE = ("integrator", "max_depth", "spp", "emitters", "shapes", "resolution_scale", "sampler")


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
            "reasons": list(self.reasons),
        }


def _check_phase(phase: str) -> None:
    if phase not in PHASES:
        raise ConfigError(f"phase {phase!r}: expected one of {list(PHASES)}")


def select_effects(scene: SceneSpec, phase: str, *, overrides: Mapping[str, Any] | None = None) -> EffectConfig:
    """Choose the cheapest rendering that is faithful for ``scene`` in ``phase``.

    Parameters
    ----------
    scene : SceneSpec
    phase : one of :data:`PHASES`
    overrides : mapping, optional
        Force fields (``integrator``, ``max_depth``, ``spp``, ``emitters``, ``shapes``,
        ``resolution_scale``, ``sampler``); each override is recorded in ``reasons``.

    Raises
    ------
    ConfigError
        Unknown phase or override key, or an invalid override value.
    """
    _check_phase(phase)
    classes = scene.effect_classes
    transmissive = "transmissive" in classes
    glossy = "glossy" in classes
    fine = scene.has_fibres
    board = scene.is_board or phase == "calibration"
    reasons: list[str] = []
    metric = ERROR_METRICS[phase]

    if phase == "groundtruth":
        spp = 64
        reasons.append("ground truth: aov integrator (coverage alpha, depth, normals, shape index) "
                       "on the object alone, no emitters, no displays")
        reasons.append("8x8 stratified samples per pixel: coverage error at edges ~1/64")
        if fine:
            reasons.append("fibres thinner than a pixel: stratified sampling keeps their fractional coverage "
                           "within ~0.02 per covered pixel at 64 spp (256 spp halves it at 2.5x the time)")
        cfg = EffectConfig("aov", 1, spp, (), ("object",), 1.0, (), "stratified", phase, metric,
                           0.04 if fine else 0.01)
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
        reasons.append(f"{phase}: light-array point lights only; displays are black panels "
                       "(kept as geometry: they shadow)")
    reasons.append("emitters that are off are left out of the scene entirely")
    skipped: tuple[str, ...] = ()
    if phase in ("lightfield", "reflectance") and scene.delta_only and not board:
        emitters, skipped = (), ("light_array",)
        reasons.append("every material is a delta BSDF (smooth dielectric or polished conductor) and the panels "
                       "are black: no path joins a point light to the camera (a ray cannot hit a point, light "
                       "sampling cannot leave a delta surface) — the image is exactly black; nothing is rendered")

    # --- integrator, depth, samples: a table measured by benchmarks/sim_effects.py
    # (errors against path tracing at depth 16, 1024 spp; see _TABLE)
    if phase == "calibration":
        kind = "board"
    elif board or not (transmissive or fine or glossy):
        kind = "diffuse"  # a board captured outside calibration is diffuse paper
    elif transmissive:
        kind = "transmissive"
    elif fine:
        kind = "fibres"
    else:
        kind = "glossy"
    group = "calibration" if phase == "calibration" else ("backdrop" if phase in ("matting", "envmatte") else "lights")
    if phase == "matting" and kind == "fibres":
        row = _FIBRES_MATTING
    else:
        row = _TABLE[(kind, group)]
    integrator, depth, spp, bound, why = row
    reasons.extend(why)
    reasons.append(f"stratified samples ({spp} = {int(round(spp ** 0.5))}x{int(round(spp ** 0.5))} per pixel)")
    cfg = EffectConfig(integrator, depth, spp, emitters, shapes, 1.0, tuple(reasons), "stratified", phase,
                       metric, bound[phase] if isinstance(bound, dict) else bound, skipped)
    return _apply_overrides(cfg, overrides)


def backdrop_only_effects(cfg: EffectConfig) -> EffectConfig:
    """What a capture with nothing on the table needs, from the selection ``cfg`` of the
    phase (the object-absent backdrop shots of matting).

    The only geometry left is the display panels, black except where they emit: a camera
    ray either hits an emitting panel (its radiance, depth 1) or something black, and no
    bounce can add anything, so ``path`` at ``max_depth`` 1 is *exact* — the same
    expected image as any deeper integrator — and the light array adds exactly nothing
    (``skipped``). The samples per pixel and the sampler stay those of ``cfg``, so the
    panel's pixel edges are anti-aliased like the backdrop around the object in the
    object-present shot.
    """
    if cfg.integrator == "aov":
        return cfg
    reasons = cfg.reasons + (
        "nothing on the table: only the emitting panels are seen (black everywhere else, nothing to bounce "
        "off) — path depth 1 is exact; the light array adds nothing and is not rendered",)
    return replace(cfg, integrator="path", max_depth=1, emitters=tuple(e for e in cfg.emitters if e == "displays"),
                   shapes=("displays",), skipped=tuple(sorted(set(cfg.skipped) | {"light_array"})),
                   reasons=reasons)


_WHY_DIRECT_DIFFUSE = ("diffuse opaque materials: direct lighting only (light -> surface -> camera); "
                       "interreflection in concavities is the error left (about -6% of the energy for the cup)",)
_WHY_GLASS = ("dielectric: rays cross >= 2 interfaces before they reach a backdrop or a light; direct lighting "
              "leaves glass black (needs >= 3); depth 8 matches 16 within noise",)
_WHY_GLOSSY = ("glossy materials: highlights reflect other parts of the object — one indirect bounce (depth 3) "
               "measures the same as depth 6",)
_WHY_FIBRES = ("fibres: light scatters from fibre to fibre (direct lighting loses ~20% of the energy, "
               "depth 6 ~2%)",)

#: (kind, phase group) -> (integrator, max_depth, spp, error bound, reasons). Bounds are
#: the measured errors (benchmarks/out/sim_effects.md) with margin for Monte-Carlo noise,
#: the reference's included.
_TABLE: dict[tuple[str, str], tuple] = {
    ("board", "calibration"): ("direct", 2, 16, 0.15, (
        "board is printed paper (diffuse, flat): direct lighting only",
        "the corners OpenCV finds move < 0.1 px against the reference at 16 spp")),
    ("diffuse", "backdrop"): ("direct", 2, 64, {"matting": 0.025, "envmatte": 0.08}, _WHY_DIRECT_DIFFUSE + (
        "the displays are large textured area emitters that also light the object: 64 spp keep the "
        "matte noise near 0.01",)),
    ("diffuse", "lights"): ("direct", 2, 16, 0.18, _WHY_DIRECT_DIFFUSE + (
        "point lights with direct lighting are noise-free: the samples only anti-alias edges and texture",)),
    ("glossy", "backdrop"): ("path", 3, 64, {"matting": 0.03, "envmatte": 0.1}, _WHY_GLOSSY + (
        "backdrops are reflected in the glossy surfaces and light them: 64 spp",)),
    ("glossy", "lights"): ("path", 3, 36, 0.1, _WHY_GLOSSY + ("the indirect bounce is sampled: 36 spp",)),
    ("transmissive", "backdrop"): ("path", 8, 64, {"matting": 0.04, "envmatte": 0.07}, _WHY_GLASS + (
        "the backdrop seen through glass (Fresnel reflection/refraction split): 64 spp",)),
    ("transmissive", "lights"): ("path", 8, 64, 0.1, _WHY_GLASS + (
        "point lights seen through smooth glass are delta paths no integrator finds: under the light array "
        "a glass object shows only what it refracts of lit surfaces",)),
    ("fibres", "backdrop"): ("path", 6, 64, {"matting": 0.05, "envmatte": 0.1}, _WHY_FIBRES + (
        "sub-pixel fibres: 64 spp resolve their fractional coverage",)),
    ("fibres", "lights"): ("path", 6, 64, 0.2, _WHY_FIBRES + (
        "sub-pixel fibres: 64 spp; per-pixel noise stays ~0.15 (their coverage varies within a pixel)",)),
}
_FIBRES_MATTING = ("direct", 2, 64, 0.05, (
    "fibres in the matting phase: the alpha matte depends on coverage; scattering between fibres changes "
    "the foreground colour alike over both backdrops and measures the same as depth 6 — direct lighting",
    "sub-pixel fibres: 64 spp resolve their fractional coverage"))


def reference_effects(scene: SceneSpec, phase: str, *, spp: int = 512) -> EffectConfig:
    """The full-effects reference for ``phase``: ``path`` tracing, ``max_depth`` 16,
    ``spp`` samples, every emitter group the phase switches on (:data:`PHASE_EMITTERS`,
    also those the selection skips as provably black), the selection's shapes (ground
    truth: the aov integrator at ``spp``)."""
    sel = select_effects(scene, phase)
    if phase == "groundtruth":
        return replace(sel, spp=spp, reasons=("reference: aov at high spp",))
    # every emitter group of the phase, including those the selection proves black
    return replace(sel, integrator="path", max_depth=16, spp=spp, sampler="independent",
                   emitters=PHASE_EMITTERS[phase], skipped=(),
                   reasons=("reference: path tracing, max_depth 16, high spp (independent samples), every emitter "
                            "group of the phase",))


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
        if k in ("max_depth", "spp") and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"effect overrides: {k} must be a positive integer, got {v!r}")
        if k == "resolution_scale" and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= 8):
            raise ConfigError(f"effect overrides: resolution_scale must be in (0, 8], got {v!r}")
        if k == "sampler" and v not in ("independent", "stratified"):
            raise ConfigError(f"effect overrides: sampler {v!r}; expected 'independent' or 'stratified'")
        if k in ("emitters", "shapes"):
            v = tuple(v)
        kw[k] = v
    if kw.get("integrator") == "direct" and "max_depth" not in kw:
        kw["max_depth"] = 2
    reasons = cfg.reasons + tuple(f"override: {k} = {v!r}" for k, v in kw.items())
    out = replace(cfg, reasons=reasons, **kw)
    if out.sampler == "stratified" and round(out.spp ** 0.5) ** 2 != out.spp:
        out = replace(out, sampler="independent",
                      reasons=out.reasons + (f"{out.spp} spp is not a square: independent samples",))
    return out
