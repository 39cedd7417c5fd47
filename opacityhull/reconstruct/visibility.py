"""Per-surfel visibility over the captured views, by a depth test.

For each view the surfels are splatted into a z-buffer as discs: every pixel whose
ray meets a surfel's disc (centre, normal, radius) gets the depth of the disc's plane
there, and a disc seen edge-on still writes its centre depth into its own pixel; the
minimum wins. A surfel is visible in the view when

* its centre is in front of the camera and projects inside the image,
* it faces the camera: ``n · (c - p) / |c - p| >= facing_cos`` (a small negative slack
  keeps rim surfels, whose normals are perpendicular to the ray),
* and its depth is at most the z-buffer's at its pixel plus a tolerance: ``depth_tol_m``
  (default the largest surfel radius: the discs of the front surface overlap, so a
  surfel's own neighbours can be up to a radius closer) plus ``slope_px`` pixels of
  depth slope for surfaces seen obliquely.

This is the "visibility vector" of the opacity-hull paper, computed with occlusion —
a surfel on the far side of the object, or hidden behind another part, is not visible
even though it is in the frustum.

:func:`surfel_visibility` is numba (parallel over views); :func:`surfel_visibility_reference`
(``surfel_visibility(..., oracle=True)``: one signature, one argument check) is the same rule
in plain NumPy (a loop over surfels, array maths over each footprint) for tests.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from ..errors import InputError, ShapeError
from .hull import projection_matrices

__all__ = ["surfel_visibility", "surfel_visibility_reference", "depth_maps"]


def _inputs(positions, normals, radii, cameras):
    pos = np.ascontiguousarray(np.asarray(positions, dtype=np.float64))
    nrm = np.ascontiguousarray(np.asarray(normals, dtype=np.float64))
    rad = np.ascontiguousarray(np.asarray(radii, dtype=np.float64).reshape(-1))
    n = pos.shape[0] if pos.ndim == 2 else -1
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ShapeError(f"positions have shape {pos.shape}, expected (N, 3)")
    if nrm.shape != pos.shape:
        raise ShapeError(f"normals have shape {nrm.shape}, expected {pos.shape}")
    if rad.shape != (n,):
        raise ShapeError(f"radii have shape {rad.shape}, expected ({n},)")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(nrm)) and np.all(np.isfinite(rad))):
        raise InputError("surfel positions, normals or radii contain NaN/Inf")
    P = projection_matrices(cameras)
    C = np.array([c.centre_world for c in cameras], dtype=np.float64).reshape(-1, 3)
    sizes = np.array([(c.width, c.height) for c in cameras], dtype=np.int64).reshape(-1, 2)
    f = np.array([min(c.fx, c.fy) for c in cameras], dtype=np.float64)
    return pos, nrm, rad, P, C, sizes, f


def _frames(cameras):
    R = np.array([c.cam_from_world[:3, :3] for c in cameras], dtype=np.float64).reshape(-1, 3, 3)
    t = np.array([c.cam_from_world[:3, 3] for c in cameras], dtype=np.float64).reshape(-1, 3)
    Kinv = np.array([np.linalg.inv(c.K) for c in cameras], dtype=np.float64).reshape(-1, 3, 3)
    return R, t, Kinv


@njit(cache=True, nogil=True)
def _splat_view(P, R, t_cam, v, Kinv, pos, nrm, rad, f, W, H, zbuf):
    """Elliptical-disc z-buffer of view v: every pixel whose ray meets a surfel's disc
    gets the depth of the disc's plane there (min over surfels); a disc seen edge-on
    still writes its centre depth into its own pixel."""
    for y in range(H):
        for x in range(W):
            zbuf[y, x] = np.inf
    for n in range(pos.shape[0]):
        # camera-frame centre and normal
        pcx = R[v, 0, 0] * pos[n, 0] + R[v, 0, 1] * pos[n, 1] + R[v, 0, 2] * pos[n, 2] + t_cam[v, 0]
        pcy = R[v, 1, 0] * pos[n, 0] + R[v, 1, 1] * pos[n, 1] + R[v, 1, 2] * pos[n, 2] + t_cam[v, 1]
        pcz = R[v, 2, 0] * pos[n, 0] + R[v, 2, 1] * pos[n, 1] + R[v, 2, 2] * pos[n, 2] + t_cam[v, 2]
        if not (pcz > 0.0):
            continue
        ncx = R[v, 0, 0] * nrm[n, 0] + R[v, 0, 1] * nrm[n, 1] + R[v, 0, 2] * nrm[n, 2]
        ncy = R[v, 1, 0] * nrm[n, 0] + R[v, 1, 1] * nrm[n, 1] + R[v, 1, 2] * nrm[n, 2]
        ncz = R[v, 2, 0] * nrm[n, 0] + R[v, 2, 1] * nrm[n, 1] + R[v, 2, 2] * nrm[n, 2]
        a = P[v, 0, 0] * pos[n, 0] + P[v, 0, 1] * pos[n, 1] + P[v, 0, 2] * pos[n, 2] + P[v, 0, 3]
        b = P[v, 1, 0] * pos[n, 0] + P[v, 1, 1] * pos[n, 1] + P[v, 1, 2] * pos[n, 2] + P[v, 1, 3]
        u = a / pcz
        t = b / pcz
        r = rad[n]
        rho = f * r / pcz
        x0 = int(math.floor(u - rho + 0.5))
        x1 = int(math.floor(u + rho + 0.5))
        y0 = int(math.floor(t - rho + 0.5))
        y1 = int(math.floor(t + rho + 0.5))
        if x1 < 0 or y1 < 0 or x0 >= W or y0 >= H:
            continue
        x0 = max(x0, 0)
        y0 = max(y0, 0)
        x1 = min(x1, W - 1)
        y1 = min(y1, H - 1)
        npc = ncx * pcx + ncy * pcy + ncz * pcz
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                # pixel ray d = K^-1 [x, y, 1] (z = 1), so the plane hit is at depth lam
                dx = Kinv[v, 0, 0] * x + Kinv[v, 0, 1] * y + Kinv[v, 0, 2]
                dy = Kinv[v, 1, 0] * x + Kinv[v, 1, 1] * y + Kinv[v, 1, 2]
                den = ncx * dx + ncy * dy + ncz
                if abs(den) < 1e-9:
                    continue
                lam = npc / den
                if not (lam > 0.0):
                    continue
                ex = lam * dx - pcx
                ey = lam * dy - pcy
                ez = lam - pcz
                if ex * ex + ey * ey + ez * ez > r * r:
                    continue
                if lam < zbuf[y, x]:
                    zbuf[y, x] = lam
        xc = int(math.floor(u + 0.5))
        yc = int(math.floor(t + 0.5))
        if xc >= 0 and xc < W and yc >= 0 and yc < H and pcz < zbuf[yc, xc]:
            zbuf[yc, xc] = pcz


@njit(cache=True, parallel=True, nogil=True)
def _visibility_kernel(
    P, R, t_cam, Kinv, C, sizes, f, pos, nrm, rad, tol, slope_px, facing_cos, Hm, Wm, vis, zbufs, keep_depth
):
    V = P.shape[0]
    N = pos.shape[0]
    for v in prange(V):
        W = sizes[v, 0]
        H = sizes[v, 1]
        zbuf = zbufs[v] if keep_depth else np.empty((Hm, Wm))
        _splat_view(P, R, t_cam, v, Kinv, pos, nrm, rad, f[v], W, H, zbuf)
        for n in range(N):
            ok = _visible(P, C, v, W, H, f[v], pos, nrm, n, zbuf, tol, slope_px, facing_cos)
            vis[n, v] = ok


@njit(cache=True, nogil=True)
def _visible(P, C, v, W, H, f, pos, nrm, n, zbuf, tol, slope_px, facing_cos):
    a = P[v, 0, 0] * pos[n, 0] + P[v, 0, 1] * pos[n, 1] + P[v, 0, 2] * pos[n, 2] + P[v, 0, 3]
    b = P[v, 1, 0] * pos[n, 0] + P[v, 1, 1] * pos[n, 1] + P[v, 1, 2] * pos[n, 2] + P[v, 1, 3]
    z = P[v, 2, 0] * pos[n, 0] + P[v, 2, 1] * pos[n, 1] + P[v, 2, 2] * pos[n, 2] + P[v, 2, 3]
    if not (z > 0.0):
        return False
    x = math.floor(a / z + 0.5)
    y = math.floor(b / z + 0.5)
    if not (x >= 0 and x < W and y >= 0 and y < H):
        return False
    dx = C[v, 0] - pos[n, 0]
    dy = C[v, 1] - pos[n, 1]
    dz = C[v, 2] - pos[n, 2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    cosang = (nrm[n, 0] * dx + nrm[n, 1] * dy + nrm[n, 2] * dz) / dist
    if cosang < facing_cos:
        return False
    # depth of a tilted surface changes by (pixel footprint) * tan(angle) per pixel
    c = abs(cosang)
    tan = math.sqrt(max(1.0 - c * c, 0.0)) / max(c, 0.25)
    tol_n = tol + slope_px * (z / f) * tan
    return z <= zbuf[int(y), int(x)] + tol_n


def _default_tol(rad: np.ndarray, depth_tol_m) -> float:
    if depth_tol_m is not None:
        if not depth_tol_m >= 0:
            raise InputError(f"depth_tol_m must be >= 0, got {depth_tol_m}")
        return float(depth_tol_m)
    return float(rad.max()) if rad.size else 0.0


def surfel_visibility(
    positions,
    normals,
    radii,
    cameras,
    *,
    depth_tol_m: float | None = None,
    slope_px: float = 1.0,
    facing_cos: float = -0.1,
    return_depth: bool = False,
    oracle: bool = False,
):
    """Visibility of every surfel in every view by a z-buffer depth test (numba).

    Parameters
    ----------
    positions : (N, 3) metres, object frame. normals : (N, 3) unit outward.
    radii : (N,) metres. cameras : list of pinhole Camera (object frame).
    depth_tol_m : base z-buffer tolerance along the optical axis; default the largest
        surfel radius.
    slope_px : extra tolerance, in pixels of depth slope: a surfel at angle θ to the
        ray gets ``slope_px * (z / f) * tan θ`` more (tan capped at ~4), since its own
        pixel's depth in the z-buffer may come from a neighbouring disc that far away.
    facing_cos : minimum cosine between normal and direction to the camera.
    return_depth : also return the (V, Hmax, Wmax) z-buffers.
    oracle : compute with the kernel's NumPy twin instead (:func:`surfel_visibility_reference`).

    Returns
    -------
    (N, V) bool visibility (and the depth maps, inf where empty).
    """
    pos, nrm, rad, P, C, sizes, f = _inputs(positions, normals, radii, cameras)
    tol = _default_tol(rad, depth_tol_m)
    V = P.shape[0]
    Hm = int(sizes[:, 1].max()) if V else 1
    Wm = int(sizes[:, 0].max()) if V else 1
    vis = np.zeros((pos.shape[0], V), np.bool_)
    zb = np.full((V, Hm, Wm) if return_depth else (1, 1, 1), np.inf)
    if pos.shape[0] and V:
        R, t, Kinv = _frames(cameras)
        (_visibility_reference if oracle else _visibility_kernel)(
            P,
            R,
            t,
            Kinv,
            C,
            sizes,
            f,
            pos,
            nrm,
            rad,
            tol,
            float(slope_px),
            float(facing_cos),
            Hm,
            Wm,
            vis,
            zb,
            return_depth,
        )
    return (vis, zb) if return_depth else vis


surfel_visibility_reference = functools.partial(surfel_visibility, oracle=True)
"""NumPy oracle of :func:`surfel_visibility`: the same arguments, the same rule written per
surfel with array maths over its footprint (small inputs)."""


def depth_maps(positions, radii, cameras) -> np.ndarray:
    """Surfel z-buffers (V, Hmax, Wmax), inf where no surfel covers a pixel."""
    n = np.zeros_like(np.asarray(positions, dtype=np.float64))
    return surfel_visibility(positions, n, radii, cameras, return_depth=True)[1]


def _visibility_reference(
    P, R, tc, Kinv, C, sizes, f, pos, nrm, rad, tol, slope_px, facing_cos, Hm, Wm, vis, zbufs, keep_depth
):
    """NumPy twin of :func:`_visibility_kernel` (the same arguments; writes ``vis`` and,
    with ``keep_depth``, ``zbufs``)."""
    N, V = pos.shape[0], P.shape[0]
    for v in range(V):
        W, H = sizes[v]
        pc = pos @ R[v].T + tc[v]
        nc = nrm @ R[v].T
        Ph = np.concatenate([pos, np.ones((N, 1))], axis=1) @ P[v].T
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = Ph[:, 0] / z
            t = Ph[:, 1] / z
        zbuf = np.full((H, W), np.inf)
        for n in np.nonzero(z > 0)[0]:
            rho = f[v] * rad[n] / z[n]
            x0, x1 = int(np.floor(u[n] - rho + 0.5)), int(np.floor(u[n] + rho + 0.5))
            y0, y1 = int(np.floor(t[n] - rho + 0.5)), int(np.floor(t[n] + rho + 0.5))
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W - 1), min(y1, H - 1)
            if x0 <= x1 and y0 <= y1:
                yy, xx = np.mgrid[y0 : y1 + 1, x0 : x1 + 1].astype(np.float64)
                d = np.stack([xx, yy, np.ones_like(xx)], -1) @ Kinv[v].T
                den = d @ nc[n]
                with np.errstate(divide="ignore", invalid="ignore"):
                    lam = (nc[n] @ pc[n]) / den
                hitp = lam[..., None] * d - pc[n]
                ok = (np.abs(den) >= 1e-9) & (lam > 0) & ((hitp**2).sum(-1) <= rad[n] ** 2)
                region = zbuf[y0 : y1 + 1, x0 : x1 + 1]
                region[ok] = np.minimum(region[ok], lam[ok])
            xc, yc = int(np.floor(u[n] + 0.5)), int(np.floor(t[n] + 0.5))
            if 0 <= xc < W and 0 <= yc < H:
                zbuf[yc, xc] = min(zbuf[yc, xc], z[n])
        if keep_depth:
            zbufs[v, :H, :W] = zbuf
        with np.errstate(invalid="ignore"):
            px = np.floor(u + 0.5)
            py = np.floor(t + 0.5)
        inimg = (z > 0) & (px >= 0) & (px < W) & (py >= 0) & (py < H)
        d = C[v] - pos
        cosang = (nrm * d).sum(1) / np.linalg.norm(d, axis=1)
        c = np.abs(cosang)
        tan = np.sqrt(np.maximum(1 - c * c, 0)) / np.maximum(c, 0.25)
        idx = np.nonzero(inimg)[0]
        zz = zbuf[py[idx].astype(int), px[idx].astype(int)]
        tol_n = tol + slope_px * (z[idx] / f[v]) * tan[idx]
        vis[idx, v] = (cosang[idx] >= facing_cos) & (z[idx] <= zz + tol_n)
