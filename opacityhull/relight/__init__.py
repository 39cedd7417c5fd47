"""Relighting: surface reflectance fields from one-light-at-a-time captures.

Modules (imported lazily by the CLI; import them directly)::

    envmap     EnvironmentMap, load_envmap (EXR/HDR, latlong/angular/mirror, yaw,
               NaN/Inf/negative/half-overflow checks), solid angles, lookups
    basis      LightSet (captured light directions per table angle, calibrated
               output), KernelConfig, integrate_envmap (vmf/linear/voronoi partitions
               of unity), directional_light_weights, parse_lights
    relit      Relighter (relit premultiplied RGBA per captured view), relight_stack
               (numba kernel) and its reference, near-light correction,
               compress_reflectance (per-view PCA)
    runner     relight_model (``opacityhull relight``), demo_step (``eval relight`` is
               opacityhull.evaluate.relight)
    natural_views  the display-domain part of each view under an environment map, from
               the natural-illumination fields (estimated in reconstruct/natural.py)
    synthetic  an analytic Lambertian-sphere model with exact ground truth
"""
