"""Render options (no heavy imports: the CLI reads the defaults for ``--help``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from ..errors import InputError

__all__ = ["RenderConfig", "KMAX", "Shading", "ShadingSurface", "default_threads"]

Shading = Literal["pixel", "surfel"]
ShadingSurface = Literal["refined", "hull"]
Align = Literal["none", "flow"]
#: leave-one-out: hold a view's coincident twins out with it, or keep them in the model
Twins = Literal["together", "keep"]

KMAX = 16
"""Largest supported ULR k (the kernels keep per-surfel candidate lists on the stack)."""


def default_threads() -> int:
    """CPUs this process may run on (its affinity mask; all CPUs off Linux), at least 1."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # sched_getaffinity exists only on Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True, kw_only=True)
class RenderConfig:
    """Options of :func:`render_image`.

    Attributes
    ----------
    k : int, 1..16
        ULR neighbourhood: the k nearest visible views by angle; the k-th is the
        threshold, so k−1 views blend (k = 1: nearest view only). Fewer than k visible
        views: all of them blend with the threshold at 180°.
    filter : float, px²
        Variance of the EWA low-pass prefilter ``H = filter·I`` (Zwicker: identity).
        0 disables the prefilter (minified splats may then miss pixel centres). The
        default 0.1 was best or within 0.25 dB of the best in a leave-one-out sweep
        over 0.05, 0.1, 0.15 and 0.25 on every model measured (analytic sphere 29.8 dB
        vs 28.1 at 0.25; simulated cup, 48 views, 25.1 vs 24.0, 25.3 at 0.05; fuzzy
        tuft 23.3 vs 22.5; the textbook 1.0 loses 2.4 dB on the CI-plan cup): rendered
        at the photographs' resolution the splats are seldom minified, so a wide
        prefilter mostly blurs; 0.05 starts to let minified splats fall between pixel
        centres (sphere 28.8 dB).
    sigma_radius : float
        Standard deviation of the surfel's tangent-plane Gaussian as a fraction of its
        radius (0.5: the disc edge is at 2σ).
    cutoff_sigma : float
        The resampling kernel is evaluated where the Mahalanobis distance
        ``√(dᵀM⁻¹d) ≤ cutoff_sigma``.
    epsilon_z : float, relative
        ε-z-buffer tolerance **in units of the surfel radius**: a fragment blends when
        its depth is within ``epsilon_z · r`` of the front-most fragment at that pixel
        (r of that front-most splat); farther fragments belong to a surface behind
        and are discarded. Relative, so the same value works at any model scale.
    edge_coverage : bool
        Edge antialiasing (Zwicker 2001): besides the normalised colour Σw·c/Σw, each
        pixel accumulates the area-weighted kernel sum Σw·A (A = surface area per
        surfel), which is ≈ 1 where the surface covers the pixel's filter footprint and
        falls to 0 across the silhouette. The normalised RGBA is scaled by that
        coverage, so the kernels' tails beyond the silhouette fade out instead of being
        normalised to full opacity (a 1–2 px opaque halo without it).
    coverage_threshold : float in (0, 1]
        Coverage counts as full from this fraction of the expected interior sum, so that
        the ripple of the kernel sum inside the surface does not dim it.
    backface_cull : bool
        Skip surfels whose normal faces away from the camera (they are on the far side
        of the hull and would only be discarded by the ε-z test).
    band_rows : int
        Rows per band of the rasteriser (bands are dealt to threads round-robin).
    threads : int or None
        Worker threads (None: the CPUs this process may use). 1 runs everything on the
        calling thread.
    background : None, colour, image or :class:`~opacityhull.envmap.EnvironmentMap`
        Default background of :meth:`RenderResult.over`.
    shading : "pixel" or "surfel"
        ``"surfel"``: ULR-blended RGBA per surfel, splatted and normalised (alpha scaled
        by the EWA edge coverage). ``"pixel"`` (deferred, :mod:`opacityhull.render.deferred`):
        the EWA pass yields depth, coverage and the winning surfel per pixel; each
        covered pixel is shaded at its back-projected surface point from the k nearest
        views the winner is visible in — colour *and* alpha are the blended mattes'
        (α clipped to the coverage), so silhouettes are the photographs' and texture is
        not bounded by the surfel density. The default: leave-one-out (every 2nd view,
        k = 4) measured pixel / surfel 19.28 / 18.71 dB, SSIM 0.586 / 0.540 on the
        templeSR ring (hull-res 384), 19.16 / 18.87 dB, SSIM 0.675 / 0.618 on dinoSR,
        20.55 / 20.55 dB, SSIM 0.773 / 0.763 on the simulated diffuse cup (CI plan),
        28.15 / 28.54 dB on the analytic sphere (20 k surfels) — and 27.4 / 18.4 dB with
        a quarter of its surfels. Per-pixel cost grows with the pixels covered, per-surfel
        with the surfels: at 512², k = 4, one thread, pixel shading took 48 / 15 ms CPU
        at 100 k surfels and 77 / 57 ms at 500 k (``benchmarks/out/render.md``).
    min_coverage : float in [0, 1]
        Pixel shading only: pixels whose EWA coverage is below this are outside the
        hull's projection and get α = 0 (0: every pixel any front fragment reaches).
    coverage_clip : bool
        Pixel shading only: α = min(blended matte α, EWA coverage), colour unchanged.
        The coverage is the hull's own antialiased silhouette: beyond the hull's limb
        the back-projected point lies on the extrapolated tangent plane and projects
        *inside* the neighbouring views' mattes (spill), while inside the hull the
        coverage is 1 and the mattes decide alone.
    min_view_cos : float in [-1, 1]
        Pixel shading only: a view blends at a pixel only if it sees the winning
        surfel's tangent plane at cos > this (X sits on a grazing view's silhouette,
        where its matte is part backdrop); when no visible view passes, all of them
        are kept. −1 disables the test.
    close_holes : bool
        Pixel shading only: fill pinholes of the geometry pass (grey closing of the
        coverage, empty pixels take their heaviest neighbour's depth and surfel), see
        :func:`opacityhull.render.deferred.close_gbuffer`.
    fallback_views : bool
        Pixel shading only: a pixel whose winning surfel no allowed view sees is shaded
        from the allowed views in front of its tangent plane (occlusion ignored) instead
        of being left transparent (see :func:`opacityhull.render.deferred.backproject`).
        Off by default: measured +0.2 dB on the temple ring but −0.1 dB and +40 % spill
        on the dino ring (occluded views draw where the hull overhangs).
    shading_surface : "refined" or "hull"
        Pixel shading only: where colour is fetched from the views. "refined"
        (default): on the photo-consistent surface inside the hull when the surfels
        carry ``depth_m`` (a build with ``refine="shading"``): each pixel is
        back-projected onto a second geometry pass of the surfels displaced to
        ``positions − depth_m·normals``. Coverage, opacity and the winning surfel's
        visibility still come from the hull, whose outline is exact. Measured on
        templeSR (blend holdout): +0.7 and +1.0 dB on two views, interior +0.8 / +2.9 dB.
        "hull" (or surfels without ``depth_m``): on the hull. Surfel shading always
        shades on the hull (displaced centres measured −0.3 dB there: their visibility
        bits belong to the hull positions).
    align : "flow" or "none"
        Pixel shading only: "flow" (default) aligns the chosen views by optical flow
        before blending (floating textures, :mod:`opacityhull.render.floating`), which
        removes ghosting the hull's depth errors leave; "none" blends them as they
        project. Measured (leave-one-out, every 4th view, geometry / blend holdout):
        dinoSR +0.30 / +0.35 dB and SSIM +0.035; templeSR +0.05 / +0.03 dB, SSIM +0.014 /
        +0.006; at +0.14–0.5 s per 640×480 frame. At a captured camera (one view) it
        does nothing.
    opaque_interior : bool
        Pixel shading only: inside the hull's projection (the covered pixels, closed by a
        1-px disc and eroded by ``interior_px``; :func:`~opacityhull.render.renderer.hull_interior`)
        the coverage does not clip α (its dips there are the splats' sampling seams,
        not a silhouette), and α is raised to the blend of the views' mattes dilated by
        ``matte_tolerance_px`` (the hull was carved from silhouettes dilated that much,
        so a hull point on a crease lands up to that far outside a view's matte, and that
        view's 0 there is no evidence of a hole). The outline is left to the coverage and
        the undilated mattes. Measured (every 4th view held out, against the
        photographs' masks, blend / geometry holdout): templeSR interior α 0.982 → 0.985 /
        0.981 → 0.984 (0.995 → 0.998 where the hull draws), coverage IoU +0.002 / +0.002,
        PSNR −0.006 / −0.016 dB; dinoSR interior α 0.983 → 0.986 / 0.982 → 0.986 (0.994 →
        0.997), IoU +0.0003, PSNR +0.03 / +0.02 dB. Eroding only 2 px lost 0.07 dB on the
        temple's geometry holdout (the rebuilt hull's spill got opaquer near its outline).
    interior_px : int ≥ 0
        Erosion (px) of the hull's projection that bounds ``opaque_interior``.
    matte_tolerance_px : int ≥ 0
        Dilation (px) of the views' mattes for ``opaque_interior`` (the build's default
        silhouette dilation is 1 px).
    """

    k: int = 4
    filter: float = 0.1
    sigma_radius: float = 0.5
    cutoff_sigma: float = 2.0
    epsilon_z: float = 2.0
    edge_coverage: bool = True
    coverage_threshold: float = 0.8
    backface_cull: bool = True
    band_rows: int = 16
    threads: int | None = None
    background: object = None
    shading: Shading = "pixel"
    min_coverage: float = 0.0
    coverage_clip: bool = True
    min_view_cos: float = -1.0
    close_holes: bool = True
    fallback_views: bool = False
    shading_surface: ShadingSurface = "refined"
    align: Align = "flow"
    opaque_interior: bool = True
    interior_px: int = 4
    matte_tolerance_px: int = 1

    @property
    def n_threads(self) -> int:
        if self.threads is not None:
            return int(self.threads)
        return default_threads()

    def __post_init__(self):
        if not (isinstance(self.k, (int, np.integer)) and 1 <= int(self.k) <= KMAX):
            raise InputError(f"RenderConfig.k = {self.k!r}: expected an integer in [1, {KMAX}]")
        for name, lo in (("filter", 0.0), ("epsilon_z", 0.0)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and v >= lo):
                raise InputError(f"RenderConfig.{name} = {v!r}: expected a finite number >= {lo}")
        for name in ("sigma_radius", "cutoff_sigma"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and v > 0):
                raise InputError(f"RenderConfig.{name} = {v!r}: expected a finite number > 0")
        if not (isinstance(self.coverage_threshold, (int, float, np.number)) and 0 < self.coverage_threshold <= 1):
            raise InputError(
                f"RenderConfig.coverage_threshold = {self.coverage_threshold!r}: expected a number in (0, 1]"
            )
        if self.threads is not None and not (isinstance(self.threads, (int, np.integer)) and self.threads >= 1):
            raise InputError(f"RenderConfig.threads = {self.threads!r}: expected None or an integer >= 1")
        if not (isinstance(self.min_coverage, (int, float, np.number)) and 0 <= self.min_coverage <= 1):
            raise InputError(f"RenderConfig.min_coverage = {self.min_coverage!r}: expected a number in [0, 1]")
        if not (isinstance(self.min_view_cos, (int, float, np.number)) and -1 <= self.min_view_cos <= 1):
            raise InputError(f"RenderConfig.min_view_cos = {self.min_view_cos!r}: expected a number in [-1, 1]")
        if self.shading not in get_args(Shading):
            raise InputError(f"RenderConfig.shading = {self.shading!r}: expected one of {', '.join(get_args(Shading))}")
        if self.shading_surface not in get_args(ShadingSurface):
            raise InputError(
                f"RenderConfig.shading_surface = {self.shading_surface!r}: expected one of "
                f"{', '.join(get_args(ShadingSurface))}"
            )
        if self.align not in get_args(Align):
            raise InputError(f"RenderConfig.align = {self.align!r}: expected one of {', '.join(get_args(Align))}")
        for name in ("interior_px", "matte_tolerance_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 0 <= v <= 64):
                raise InputError(f"RenderConfig.{name} = {v!r}: expected an integer in [0, 64]")
        if not (isinstance(self.band_rows, (int, np.integer)) and self.band_rows >= 1):
            raise InputError(f"RenderConfig.band_rows = {self.band_rows!r}: expected an integer >= 1")
