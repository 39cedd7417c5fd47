"""The paper's tests of natural-illumination fields against the simulator (Mitsuba).

For a model whose session was captured on ``sim:...``, and for one view (camera c,
table angle a):

* (a) **held-out natural images** — images the estimate never saw (other seeds),
  shown on one display: the simulator's render of the view vs
  :func:`~opacityhull.relight.natural.relight_natural`, per pixel;
* (b) **the moving white bar** — 1/8 of the display's width on black, swept across
  it in ``n_positions`` steps: the error per position;
* (c) **an environment map** — the relit view
  (:func:`~opacityhull.relight.natural.relight_view_natural`) vs Mitsuba's render of the
  object under the same map *restricted to the displays' solid angles* (seen from the
  object centre) with the panels removed: that is the light a display-domain field can
  reproduce, so the difference measures the estimate and the distant-light mapping
  (parallax over the object's size), not the missing rest of the sphere.

Metrics over a mask (default: the field's pixels): PSNR with the truth's peak in the
mask (``relight.evaluate.relight_metrics``), relative L2 error.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["sim_rig_for_session", "render_display_image", "held_out_images", "bar_patterns", "masked_envmap",
           "compare"]


def sim_rig_for_session(session):
    """The (unopened) simulated rig a session was captured on: ``rig_source = sim:...``."""
    from ..sim.simrig import open_sim_rig

    src = session.source if hasattr(session, "source") else ""
    if not str(src).startswith("sim:"):
        raise InputError(f"{session.root}: captured on {src!r}, not a simulated rig (sim:...): no Mitsuba truth")
    return open_sim_rig(str(src), open=False)


def render_display_image(rig, camera: int, table_deg: float, display: str, pattern_u8: np.ndarray, *,
                         seed: int = 0) -> np.ndarray:
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
    from .natural_synthetic import white_bar

    w, h = display.resolution
    return [np.round(white_bar(k, n_positions, height=h, width=w, bar_fraction=bar_fraction) * 255).astype(np.uint8)
            for k in range(n_positions)]


def masked_envmap(envmap, geometry, table_deg: float, *, centre_m, displays: Sequence[str] | None = None):
    """``envmap`` with every direction that misses the displays (from ``centre_m``,
    object frame at ``table_deg``) set to 0: what a display-domain field can reproduce."""
    from .envmap import EnvironmentMap
    from .natural import display_hit_mask

    dirs = envmap.directions()
    hit = np.zeros(dirs.shape[:2], bool)
    for d in geometry.displays:
        if displays is None or d.name in displays:
            hit |= display_hit_mask(d, table_deg, dirs, centre_m=centre_m)
    rad = np.where(hit[..., None], envmap.radiance, 0.0).astype(np.float32)
    return EnvironmentMap(rad, source=f"{envmap.source} (display solid angles only)")


def compare(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """PSNR (truth's peak in the mask) and relative L2 error of (H, W, 3) images."""
    from .evaluate import relight_metrics

    m = np.ones(truth.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    return relight_metrics(est[..., :3], truth[..., :3], m)
