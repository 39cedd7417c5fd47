"""The simulated rig (Mitsuba 3): scenes, effect selection, renders, ground truth.

Modules (Mitsuba is imported only when something renders):

* :mod:`~opacityhull.sim.scenes` — scene specs (TOML, ``builtin:NAME``), ``load_scene``;
* :mod:`~opacityhull.sim.shapes` — procedural geometry (NumPy);
* :mod:`~opacityhull.sim.effects` — ``select_effects``: integrator, depth, emitters,
  shapes, samples per scene and capture phase, with reasons and error bounds;
* :mod:`~opacityhull.sim.render` — ``SimRenderer``: the rig state rendered in the object
  frame with cached Mitsuba scenes;
* :mod:`~opacityhull.sim.groundtruth` — coverage alpha, depth, normals, renders under
  environment maps, the ``groundtruth/`` folder of a session;
* :mod:`~opacityhull.sim.simrig` — ``open_sim_rig``: real drivers on emulators, Mitsuba
  cameras;
* :mod:`~opacityhull.sim.sensor` — shot/read noise, clipping, quantisation;
* :mod:`~opacityhull.sim.variants` — ``choose_variant`` (LLVM probed in a subprocess);
* :mod:`~opacityhull.sim.evaluate` — selections measured against the full-effects
  reference.
"""
