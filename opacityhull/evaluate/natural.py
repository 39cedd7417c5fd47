"""The paper's tests of natural-illumination fields against the simulator (Mitsuba).

For a model whose session was captured on ``sim:...``, and for one view (camera c,
table angle a):

* (a) **held-out natural images** — images the estimate never saw (other seeds),
  shown on one display: the simulator's render of the view vs
  :func:`~opacityhull.reconstruct.natural.relight_natural`, per pixel;
* (b) **the moving white bar** — 1/8 of the display's width on black, swept across
  it in ``n_positions`` steps: the error per position;
* (c) **an environment map** — the relit view
  (:func:`~opacityhull.reconstruct.natural.relight_view_natural`) vs Mitsuba's render of the
  object under the same map *restricted to the displays' solid angles* (seen from the
  object centre) with the panels removed: that is the light a display-domain field can
  reproduce, so the difference measures the estimate and the distant-light mapping
  (parallax over the object's size), not the missing rest of the sphere.

Metrics over a mask (default: the field's pixels): PSNR with the truth's peak in the
mask (``evaluate.metrics.relight_metrics``), relative L2 error.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "sim_rig_for_session",
    "render_display_image",
    "held_out_images",
    "bar_patterns",
    "masked_envmap",
    "compare",
    "envmap_display_layers",
    "render_envmap_on_displays",
    "natural_part_of_view",
]


def sim_rig_for_session(session):
    """The (unopened) simulated rig a session was captured on: ``rig_source = sim:...``."""
    from ..sim.simrig import open_sim_rig

    src = session.source if hasattr(session, "source") else ""
    if not str(src).startswith("sim:"):
        raise InputError(f"{session.root}: captured on {src!r}, not a simulated rig (sim:...): no Mitsuba truth")
    return open_sim_rig(str(src), open=False)


def render_display_image(
    rig, camera: int, table_deg: float, display: str, pattern_u8: np.ndarray, *, seed: int = 0
) -> np.ndarray:
    """Mitsuba radiance (H, W, 3) of camera ``camera`` at ``table_deg`` with
    ``pattern_u8`` (uint8 (rows, cols, 3)) on ``display`` and every other display black,
    the object on the table, lights off — a capture of the natural phase without the
    sensor."""
    from ..sim.render import SimState

    displays = {d.name: (pattern_u8 if d.name == display else None) for d in rig.geometry.displays}
    state = SimState(table_deg=float(table_deg), displays=displays, content="object")
    return rig.renderer.render(rig.true_cameras[camera], state, seed=seed, use_cache=False)


def held_out_images(display, n: int, *, seed: int = 987_654) -> list[np.ndarray]:
    """``n`` natural images (probe crops and 1/f noise alternating) from a seed the plan
    never uses, uint8 (rows, cols, 3) at the display's resolution."""
    from ..acquire.patterns import natural_image, probe_crop

    w, h = display.resolution
    out = []
    for k in range(n):
        rng = np.random.default_rng([seed, k])
        out.append(probe_crop(rng, width=w, height=h)[0] if k % 2 == 0 else natural_image(rng, width=w, height=h))
    return out


def bar_patterns(display, n_positions: int = 16, *, bar_fraction: float = 0.125) -> list[np.ndarray]:
    """The moving white bar: uint8 patterns, a vertical white bar ``bar_fraction`` of the
    display's width on black at ``n_positions`` evenly spaced positions."""
    from ..relight.natural_synthetic import white_bar

    w, h = display.resolution
    return [
        np.round(white_bar(k, n_positions, height=h, width=w, bar_fraction=bar_fraction) * 255).astype(np.uint8)
        for k in range(n_positions)
    ]


def masked_envmap(envmap, geometry, table_deg: float, *, centre_m, displays: Sequence[str] | None = None):
    """``envmap`` with every direction that misses the displays (from ``centre_m``,
    object frame at ``table_deg``) set to 0: what a display-domain field can reproduce."""
    from ..envmap import EnvironmentMap
    from ..reconstruct.natural import display_hit_mask

    dirs = envmap.directions()
    hit = np.zeros(dirs.shape[:2], bool)
    for d in geometry.displays:
        if displays is None or d.name in displays:
            hit |= display_hit_mask(d, table_deg, dirs, centre_m=centre_m)
    rad = np.where(hit[..., None], envmap.radiance, 0.0).astype(np.float32)
    return EnvironmentMap(rad, source=f"{envmap.source} (display solid angles only)")


def compare(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """PSNR (truth's peak in the mask) and relative L2 error of (H, W, 3) images."""
    from .metrics import relight_metrics

    m = np.ones(truth.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    return relight_metrics(est[..., :3], truth[..., :3], m)


def envmap_display_layers(
    envmap, display, table_deg: float, *, centre_m, supersample: int = 3, layers: int = 2
) -> list[tuple[np.ndarray, float]]:
    """What a display shows to stand in for ``envmap`` over its solid angle, as 8-bit
    layers: ``[(pattern uint8 (rows, cols, 3), to_env), ...]`` whose emitted radiance,
    each times its ``to_env``, sums to :func:`~opacityhull.reconstruct.natural.envmap_display_image`
    to within 1/2 of the last layer's step (255^-layers of the peak).

    One 8-bit image scaled to its peak loses everything below 1/255 of a bright probe's
    peak (a lamp in the solid angle leaves the rest at 0 or 1), which relight keeps: the
    truth would then score quantisation. Light transport is linear, so the truth renders
    each layer and sums (the first layer floors, the residual goes to the next, scaled
    by 255; the last rounds). An all-black solid angle gives no layer."""
    from ..reconstruct.natural import envmap_display_image

    if layers < 1:
        raise InputError(f"layers must be >= 1, got {layers}")
    L = envmap_display_image(envmap, display, table_deg, centre_m=centre_m, supersample=supersample)
    peak = float(np.max(L)) if L.size else 0.0
    if not np.isfinite(peak) or peak <= 0:
        return []
    out = []
    rest = np.maximum(np.asarray(L, np.float64), 0.0)
    scale = 255.0 / peak
    for j in range(layers):
        q = np.round(rest * scale) if j == layers - 1 else np.floor(rest * scale)
        pat = np.clip(q, 0, 255).astype(np.uint8)
        if pat.any():
            out.append((pat, 255.0 / (scale * float(display.max_radiance))))
        rest = rest - pat.astype(np.float64) / scale
        scale *= 255.0
    return out


def render_envmap_on_displays(
    rig,
    camera: int,
    table_deg: float,
    envmap,
    displays: Sequence[str],
    *,
    centre_m,
    seed: int = 0,
    supersample: int = 3,
    layers: int = 2,
) -> np.ndarray:
    """Mitsuba radiance (H, W, 3), in the map's units, of camera ``camera`` at
    ``table_deg`` with each display in ``displays`` showing ``envmap`` over its solid
    angle (:func:`envmap_display_layers`) and the others black: the display-lit half of
    the truth of a relit view, which the display-domain field reproduces (relight adds
    :func:`~opacityhull.reconstruct.natural.relight_view_natural` with the same mapping).

    Each display (and each 8-bit layer) is rendered alone and the results summed (light
    transport is linear): that is also how the field was captured, one illumination
    domain at a time."""
    out = None
    for name in displays:
        d = rig.geometry.display(name)
        for pat, to_env in envmap_display_layers(
            envmap, d, table_deg, centre_m=centre_m, supersample=supersample, layers=layers
        ):
            img = np.asarray(render_display_image(rig, camera, table_deg, name, pat, seed=seed), np.float64)[..., :3]
            img = img * to_env
            out = img if out is None else out + img
    if out is None:
        cam = rig.true_cameras[camera]
        out = np.zeros((cam.height, cam.width, 3))
    return out.astype(np.float32)


def natural_part_of_view(model, index: int, envmap, *, centre_m, supersample: int = 3) -> np.ndarray | None:
    """The display-domain part of captured view ``index`` under ``envmap`` (premultiplied
    float32 (H, W, 3)), exactly as ``relight`` adds it; None without fields."""
    from ..reconstruct.natural import load_view_fields, relight_view_natural

    v = model.views[index]
    fields = load_view_fields(model.root, v.id)
    if not fields:
        return None
    return relight_view_natural(fields, envmap, model.geometry, v.table_deg, centre_m=centre_m, supersample=supersample)
