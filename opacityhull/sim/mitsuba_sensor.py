"""The Mitsuba perspective sensor of a :class:`~opacityhull.camera.Camera`: one dict for
the simulated rig (:mod:`.render`) and the synthetic training set
(``benchmarks/synthetic_set.py``).

The pose, field of view and principal point come from
:func:`opacityhull.camera.mitsuba_sensor_params` (pinned against Mitsuba's own rays by
``tests/sim/test_sim_render.py``); the film is an RGBA ``hdrfilm`` of the camera's size
with a box filter one pixel wide and ``sample_border`` off, so a pixel's value depends on
its own samples only.
"""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera, mitsuba_sensor_params

__all__ = ["NEAR_CLIP_M", "FAR_CLIP_M", "sensor_dict"]

#: Near clip plane of the simulated cameras (z, metres). Mitsuba starts camera rays on
#: this plane, so the aov ``depth`` (ray distance) is measured from it.
NEAR_CLIP_M = 0.005
#: Far clip plane of the simulated cameras (metres): beyond the rig's walls.
FAR_CLIP_M = 100.0


def sensor_dict(
    mi,
    cam: Camera,
    *,
    spp: int,
    sampler: str = "stratified",
    clip_m: tuple[float, float] | None = (NEAR_CLIP_M, FAR_CLIP_M),
) -> dict:
    """A ``mi.load_dict`` description of ``cam`` as a Mitsuba ``perspective`` sensor.

    Parameters
    ----------
    mi : the ``mitsuba`` module, its variant set.
    cam : the camera (its distortion is ignored: a pinhole).
    spp : samples per pixel; the ``stratified`` sampler (jittered) rounds it to a
        square (``round(√spp)²``), any other name is Mitsuba's ``independent`` with ``spp``.
    clip_m : (near, far) clip planes in metres; None leaves Mitsuba's defaults.
    """
    p = mitsuba_sensor_params(cam)
    if sampler == "stratified":
        side = max(1, int(round(math.sqrt(spp))))
        smp = {"type": "stratified", "sample_count": side * side, "jitter": True}
    else:
        smp = {"type": "independent", "sample_count": int(spp)}
    clip = {} if clip_m is None else {"near_clip": float(clip_m[0]), "far_clip": float(clip_m[1])}
    return {
        "type": "perspective",
        "fov": p["fov"],
        "fov_axis": "y",
        "principal_point_offset_x": p["principal_point_offset_x"],
        "principal_point_offset_y": p["principal_point_offset_y"],
        **clip,
        "to_world": mi.ScalarTransform4f(np.asarray(p["to_world"])),
        "film": {
            "type": "hdrfilm",
            "width": cam.width,
            "height": cam.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgba",
            "sample_border": False,
        },
        "sampler": smp,
    }
