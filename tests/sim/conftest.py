"""Shared fixtures for the simulator tests: small rigs, loaded scenes, analytic oracles.

Mitsuba scenes are cached per renderer, and Dr.Jit caches compiled kernels on disk, so
the expensive objects are module- or session-scoped.
"""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.camera import Camera
from opacityhull.riggeometry import RigGeometry
from opacityhull.sim.scenes import load_scene
from opacityhull.sim.simrig import sim_rig_config


@pytest.fixture(scope="session")
def small_geometry() -> RigGeometry:
    """The default simulated rig at half resolution (100x75 cameras)."""
    return RigGeometry.from_dict(sim_rig_config(None, scale=0.5)["geometry"])


@pytest.fixture(scope="session")
def sphere_scene():
    return load_scene("builtin:sphere")


def sphere_conic(cam: Camera, centre, radius: float) -> np.ndarray:
    """3x3 conic Q of a sphere's silhouette: pixel x (homogeneous) is inside iff x^T Q x >= 0."""
    c = cam.world_to_cam(np.asarray(centre, dtype=np.float64)[None])[0]
    Kinv = np.linalg.inv(cam.K)
    A = np.outer(c, c) - (c @ c - radius * radius) * np.eye(3)
    return Kinv.T @ A @ Kinv


def conic_area_centre(Q: np.ndarray) -> tuple[float, np.ndarray]:
    """Area (px^2) and centre (px) of the ellipse x^T Q x >= 0."""
    M = Q[:2, :2]
    b = Q[:2, 2]
    centre = -np.linalg.solve(M, b)
    # value at the centre, then the ellipse (x-c)^T M (x-c) <= -k with k = value at centre
    k = centre @ M @ centre + 2 * b @ centre + Q[2, 2]
    area = np.pi * k / np.sqrt(np.linalg.det(M))
    return float(abs(area)), centre


def oracle_coverage(Q: np.ndarray, width: int, height: int, n: int = 16) -> np.ndarray:
    """Slow, obviously correct per-pixel coverage of the conic region: n x n sub-samples
    per pixel (OpenCV pixel centres at integers)."""
    off = (np.arange(n) + 0.5) / n - 0.5
    cov = np.zeros((height, width))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    for dy in off:
        for dx in off:
            x = np.stack([u + dx, v + dy, np.ones_like(u)], axis=-1)
            val = np.einsum("...i,ij,...j->...", x, Q, x)
            cov += val >= 0
    return cov / (n * n)
