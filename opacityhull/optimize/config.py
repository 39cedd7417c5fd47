"""The fitting's options: one frozen, keyword-only :class:`FitConfig` with presets."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

from ..errors import ConfigError

__all__ = ["FitMode", "FIT_MODES", "FitConfig", "fit_preset", "position_rates", "SPARSE_VIEWS"]

FitMode = Literal["none", "fast", "full"]
FIT_MODES: tuple[str, ...] = ("none", "fast", "full")


@dataclass(frozen=True, kw_only=True)
class FitConfig:
    """Options of :func:`opacityhull.optimize.fit.fit_model`.

    mode : ``"none"`` (no fitting: the hull model as built), ``"fast"`` or ``"full"``;
        :func:`fit_preset` fills the iteration count and schedule of each.
    iterations : optimizer steps (one training view each).
    time_budget_s : stop after this many seconds of fitting (None: no limit); the
        report says whether the budget or the iteration count ended the fit.
    seed : the random view order (same inputs and seed give the same bytes).
    lr_position : position learning rate as a fraction of the scene extent (the
        bounding-sphere radius of the start surfels, 3DGS practice), decayed
        exponentially to ``lr_position_final`` over the iterations. None (the default):
        :func:`position_rates` by the number of training views, since how far the start
        has to move depends on how loose the hull is, and a hull of few views is loose.
    lr_position_final : the decayed end of the position rate (None: with ``lr_position``).
    lr_sh_dc, lr_sh_rest : SH colour coefficients (DC, higher degrees).
    lr_opacity, lr_scale, lr_rotation : opacity logits, log tangent scales, quaternions.
    ssim_weight : λ of (1 − λ)·D + λ·D-SSIM on the display (sRGB-encoded) colour.
    color_loss : D, ``"l1"`` (mean absolute error, 3DGS) or ``"l2"`` (mean squared error,
        what PSNR scores: where the views disagree, the mean rather than the median).
    alpha_weight : weight of the L1 between rendered α and each view's matte.
    sh_degree : final SH degree (0..3); the degree grows by one every
        ``sh_degree_every`` iterations from 0 (3DGS practice), or starts at the final
        degree when ``sh_degree_every`` is 0.
    densify_from, densify_until, densify_every : the densification window (iterations).
    densify_grad_threshold : mean |∂L/∂(2-D mean)| per view, in NDC-equivalent units
        (pixel gradient × W/2, the 3DGS convention), above which a surfel is cloned or
        split.
    densify_scale_fraction : a surfel whose largest tangent std-dev is above this
        fraction of the scene extent is split, below it cloned.
    prune_opacity : surfels with opacity below this are removed at each densification.
    prune_scale_fraction : surfels larger than this fraction of the extent are removed.
    max_surfels : densification stops adding past this count.
    start_surface : ``"hull"`` starts the means on the hull's surfels; ``"refined"`` (the
        default) at their photo-consistent depth (``Surfels.depth_m``, where the renderer
        shades; the hull where a model has none): templeSR's start +0.44 dB held out.
    max_start_surfels : the start keeps a seeded subset of at most this many hull
        surfels, their radii grown to cover the same area (None: all).
    train_scale : the training views are fitted at this fraction of their resolution
        (intrinsics scaled to match); 1 fits at full resolution.
    checkpoint_every : iterations between checkpoints (0: none).
    """

    mode: FitMode = "fast"
    iterations: int = 600
    time_budget_s: float | None = None
    seed: int = 0
    lr_position: float | None = None
    lr_position_final: float | None = None
    lr_sh_dc: float = 1e-2
    lr_sh_rest: float = 5e-4
    lr_opacity: float = 5e-2
    lr_scale: float = 1e-2
    lr_rotation: float = 1e-3
    ssim_weight: float = 0.2
    color_loss: Literal["l1", "l2"] = "l1"
    alpha_weight: float = 0.5
    sh_degree: int = 3
    sh_degree_every: int = 150
    densify_from: int = 100
    densify_until: int = 450
    densify_every: int = 100
    densify_grad_threshold: float = 1e-3
    densify_scale_fraction: float = 0.01
    prune_opacity: float = 0.005
    prune_scale_fraction: float = 0.1
    max_surfels: int = 1_000_000
    start_surface: Literal["hull", "refined"] = "refined"
    max_start_surfels: int | None = 150_000
    train_scale: float = 1.0
    checkpoint_every: int = 200

    def __post_init__(self):
        if self.mode not in FIT_MODES:
            raise ConfigError(f"optimize mode {self.mode!r}: expected one of {', '.join(FIT_MODES)}")
        if int(self.iterations) < 0 or (self.mode != "none" and int(self.iterations) == 0):
            raise ConfigError(f"optimize iterations {self.iterations!r}: expected a count > 0")
        if self.time_budget_s is not None and not (math.isfinite(self.time_budget_s) and self.time_budget_s > 0):
            raise ConfigError(f"optimize time budget {self.time_budget_s!r} s: expected a number of seconds > 0")
        if not 0 <= int(self.sh_degree) <= 3:
            raise ConfigError(f"optimize sh_degree {self.sh_degree!r}: expected 0..3")
        if not 0.0 <= self.ssim_weight <= 1.0:
            raise ConfigError(f"optimize ssim_weight {self.ssim_weight!r}: expected 0..1")
        if not 0.0 < self.train_scale <= 1.0:
            raise ConfigError(f"optimize train_scale {self.train_scale!r}: expected 0 < scale <= 1")
        for name in (
            "lr_position",
            "lr_position_final",
            "lr_sh_dc",
            "lr_sh_rest",
            "lr_opacity",
            "lr_scale",
            "lr_rotation",
            "alpha_weight",
            "densify_grad_threshold",
            "prune_opacity",
        ):
            v = getattr(self, name)
            if v is None:  # lr_position / lr_position_final: position_rates chooses
                continue
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"optimize {name} {v!r}: expected a finite number >= 0")
        if self.color_loss not in ("l1", "l2"):
            raise ConfigError(f"optimize color_loss {self.color_loss!r}: expected l1 or l2")
        if self.start_surface not in ("hull", "refined"):
            raise ConfigError(f"optimize start_surface {self.start_surface!r}: expected hull or refined")
        if int(self.checkpoint_every) < 0 or int(self.max_surfels) < 1:
            raise ConfigError("optimize checkpoint_every must be >= 0 and max_surfels >= 1")


def fit_preset(mode: FitMode, *, iterations: int | None = None, **overrides) -> FitConfig:
    """The :class:`FitConfig` of a mode (``none``, ``fast``, ``full``), with ``overrides``.

    ``fast`` is 900 steps at half resolution, densifying every 75 through step 600 (about
    two minutes of steps on templeSR, 12 views of 640×480, on a loaded 2-core machine);
    ``full`` runs 3000 steps with densification through step 1500 and the
    SH degree grown to 3.

    ``iterations`` (``build --optimize-iterations``) shortens or lengthens the preset to
    that many steps and keeps its schedules inside them: densification from at most
    ¼ through at most ¾ of the steps, at least every ¼, each SH degree grown within
    ``iterations / (sh_degree + 1)`` steps, a checkpoint at least halfway. ``overrides``
    apply after that (a given field wins; ``dataclasses.replace`` of the preset sets
    ``iterations`` alone, schedules untouched). Mode ``none`` has no steps to set.
    """
    if mode not in FIT_MODES:
        raise ConfigError(f"optimize mode {mode!r}: expected one of {', '.join(FIT_MODES)}")
    if iterations is not None and mode == "none":
        raise ConfigError(f"optimize mode 'none' with {iterations} iterations: the mode fits nothing")
    if mode == "none":
        base = FitConfig(mode="none", iterations=0)
    elif mode == "fast":
        # half resolution: templeSR held out 17.50 dB after 300 steps (56 s), 19.87 after
        # 900 (115 s), against 16.92 after 400 full-resolution steps (1240 s, heavier load)
        base = FitConfig(
            mode="fast",
            iterations=900,
            train_scale=0.5,
            sh_degree_every=75,
            densify_from=75,
            densify_until=600,
            densify_every=75,
        )
    else:
        base = FitConfig(
            mode="full",
            iterations=3000,
            sh_degree_every=500,
            densify_from=200,
            densify_until=1500,
            densify_every=100,
            checkpoint_every=500,
        )
    if iterations is not None:
        n = int(iterations)
        base = replace(
            base,
            iterations=n,
            densify_from=min(base.densify_from, n // 4),
            densify_until=min(base.densify_until, (3 * n) // 4),
            densify_every=max(1, min(base.densify_every, n // 4)),
            sh_degree_every=min(base.sh_degree_every, max(1, n // (base.sh_degree + 1))),
            checkpoint_every=min(base.checkpoint_every, max(1, n // 2)) if base.checkpoint_every else 0,
        )
    return replace(base, **overrides)


#: up to this many training views the fit takes the sparse-view position rate
SPARSE_VIEWS = 24


def position_rates(config: FitConfig, n_train_views: int) -> tuple[float, float]:
    """The position rate's start and end (fractions of the scene extent) for a fit of
    ``n_train_views`` views: the config's when given, otherwise 1e-2 → 1e-3 up to
    :data:`SPARSE_VIEWS` views and 3e-3 → 3e-4 above.

    Measured on held-out views, ``fast`` preset (mask union unless said):

    ============================  =====  =============  =============
    set                           views  1e-2 → 1e-3    3e-3 → 3e-4
    ============================  =====  =============  =============
    templeSR, every 4th out       12     21.98 dB       20.37 dB
    dinoSR, every 4th out         12     21.13 dB       18.63 dB
    demo cup, every 8th out       42     22.66 dB       23.01 dB (200 steps)
    synthetic, every 10th, white  90     29.31 dB       31.50 dB
    ============================  =====  =============  =============

    A loose hull (few views) needs its surfels moved further than a tight one; with
    many views the larger step only shakes a surface that is already close. The cut
    between 12 and 42 views is not measured in between (24 is the middle)."""
    if config.lr_position is not None:
        start = float(config.lr_position)
        final = float(config.lr_position_final) if config.lr_position_final is not None else 0.1 * start
        return start, final
    sparse = int(n_train_views) <= SPARSE_VIEWS
    start = 1e-2 if sparse else 3e-3
    final = float(config.lr_position_final) if config.lr_position_final is not None else 0.1 * start
    return start, final
