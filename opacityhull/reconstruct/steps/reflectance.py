"""Build step ``reflectance``: which one-light images go into the model."""

from __future__ import annotations

import logging

import numpy as np

from ...errors import FormatError
from ...model import LightSample, light_key
from ...session import Session
from ..buildconfig import BuildConfig
from ..buildstore import _digest, _records_digest
from ..matte_step import _rgb
from .base import Step
from .cameras import _plan_reflectance_level

log = logging.getLogger(__name__)


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


def run(ctx) -> None:
    with ctx.timer.step("reflectance"):
        ctx.reflectance = step_reflectance(
            ctx.session, ctx.cameras.views, ctx.cameras.vids, ctx.mattes.alphas, ctx.config, ctx.notes, ctx.finite
        )


STEP = Step(
    name="reflectance",
    run=run,
    inputs=("session", "cameras", "mattes", "config"),
    product="reflectance",
    params=("reflectance", "alpha_eps"),
)
