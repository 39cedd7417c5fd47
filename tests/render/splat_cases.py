"""Small cameras, random surfels and the fast splat setup shared by the kernel tests."""

from __future__ import annotations

import math

import numpy as np

from opacityhull.camera import Camera, look_at_world_from_cam
from opacityhull.model import Surfels
from opacityhull.render import kernels as K
from opacityhull.render.views import pack_camera


def make_cam(eye, target=(0.0, 0.1, 0.0), size=(40, 30), fov_deg=30.0, dist=None):
    """A pinhole camera at ``eye`` looking at ``target``, principal point slightly off centre."""
    W, H = size
    f = H / (2 * math.tan(math.radians(fov_deg) / 2))
    Km = np.array([[f, 0, (W - 1) / 2 + 0.3], [0, f * 1.01, (H - 1) / 2 - 0.2], [0, 0, 1.0]])
    return Camera(
        K=Km,
        width=W,
        height=H,
        world_from_cam=look_at_world_from_cam(eye, target),
        dist=np.zeros(5) if dist is None else dist,
    )


def random_surfels(rng, n, centre=(0.0, 0.1, 0.0), spread=0.08, n_views=3):
    """``n`` surfels in a cube of half-side ``spread``, random normals, 2-10 mm radii."""
    pos = np.asarray(centre) + rng.uniform(-spread, spread, size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rad = rng.uniform(0.002, 0.01, size=n)
    return Surfels.from_bool(pos, nrm, rad, rng.random((n, n_views)) < 0.7)


def setup_fast(surfels, cam, cfg, areas):
    """:func:`~opacityhull.render.kernels.splat_setup` over all surfels: (valid, records)."""
    N = len(surfels)
    rec = np.empty((N, K.SPLAT_FIELDS), np.float32)
    valid = np.empty(N, bool)
    K.splat_setup(
        surfels.positions,
        surfels.normals,
        surfels.radii,
        areas,
        pack_camera(cam),
        cam.width,
        cam.height,
        cfg.sigma_radius,
        cfg.filter,
        cfg.cutoff_sigma,
        cfg.epsilon_z,
        cfg.backface_cull,
        K.NO_COV,
        rec,
        valid,
        0,
        N,
    )
    return valid, rec
