"""Evaluation of a calibration: errors against ground truth, and an exact board renderer.

:func:`pose_errors` compares calibrated rig cameras with true ones (rotation, position,
focal length, principal point, and the reprojection difference over the working volume,
optionally after removing the rig frame's gauge). :func:`render_charuco_view` is an
independent ray-cast renderer of the board through a known (distorted) camera, used by
tests and the benchmark as exact ground truth (it uses none of the calibration's code).
"""

from __future__ import annotations

import functools
import math
from contextlib import suppress
from collections.abc import Sequence

import numpy as np

from ...camera import Camera, rot_y
from ...charuco import CharucoSpec
from ...errors import InputError
from ...se3 import invert_rigid, rigid, rotation_angle_deg
from .result import CalibrationResult

__all__ = ["pose_errors", "render_charuco_view"]


def pose_errors(
    result: CalibrationResult | Sequence[Camera],
    true_rig_cameras: Sequence[Camera],
    *,
    align_gauge: bool = False,
    volume_m: float | None = 0.2,
) -> dict:
    """Errors of calibrated rig cameras against ground truth.

    Parameters
    ----------
    result : CalibrationResult or list of Camera (rig frame)
    true_rig_cameras : list of Camera
        True ``rig_from_cam`` and intrinsics (e.g. the simulator's
        ``groundtruth/calibration/<name>.yaml`` read with ``camera.read_opencv_yaml``),
        one per rig camera; only the calibrated ones (``result.camera_indices``) are
        compared.
    align_gauge : bool
        First remove the rig frame's gauge freedom — a rotation about +Y and a shift
        along +Y, which calibration fixes from the board's nominal yaw and height: the
        yaw from the camera orientations, then (with ``volume_m``) yaw and shift that
        minimise the working volume's reprojection differences (nlopt BOBYQA), else the
        shift from the camera heights. The fitted gauge is reported.
    volume_m : float or None
        Side of the working volume (a cube standing on the table centre) whose points
        (a 5×5×5 grid) are projected with the estimated and the true camera:
        ``volume_reproj_px`` is the RMS pixel distance per camera — what silhouettes
        and hulls see. The focal length and the camera distance are poorly separated by
        a flat board (their errors largely cancel in this number).

    Returns
    -------
    dict with ``cameras`` (indices compared: the calibrated ones), per-camera lists
    ``rotation_deg``, ``position_mm``, ``focal_pct`` (mean of fx, fy),
    ``principal_point_px``, ``volume_reproj_px``, their maxima ``max_*``, and
    ``gauge_yaw_deg``, ``gauge_dy_mm`` (0 unless ``align_gauge``).
    """
    true = list(true_rig_cameras)
    if isinstance(result, CalibrationResult):
        if len(true) != len(result.rig_cameras):
            raise InputError(f"pose_errors: {len(result.rig_cameras)} rig cameras vs {len(true)} true cameras")
        idx = list(result.camera_indices)
        est = [result.rig_cameras[c] for c in idx]
        true = [true[c] for c in idx]
    else:
        est = list(result)
        idx = list(range(len(est)))
        if len(est) != len(true):
            raise InputError(f"pose_errors: {len(est)} calibrated cameras vs {len(true)} true cameras")
    X = None
    if volume_m:
        g = (np.arange(5) / 4.0 - 0.5) * float(volume_m)
        X = np.stack(np.meshgrid(g, g + 0.5 * float(volume_m), g, indexing="ij"), axis=-1).reshape(-1, 3)
    G = np.eye(4)
    yaw = dy = 0.0
    if align_gauge:
        # true ≈ G·est with G = rot_y(ψ) + (0, dy, 0). ψ first from the camera axes
        # (orientations are accurate; positions are not, along each optical axis).
        Re = np.concatenate([c.world_from_cam[:3, :3].T for c in est])
        Rt = np.concatenate([c.world_from_cam[:3, :3].T for c in true])
        psi = math.atan2(
            np.sum(Re[:, 2] * Rt[:, 0] - Re[:, 0] * Rt[:, 2]), np.sum(Re[:, 0] * Rt[:, 0] + Re[:, 2] * Rt[:, 2])
        )
        dy = float(np.mean([t.centre_world[1] - e.centre_world[1] for e, t in zip(est, true, strict=True)]))
        if X is not None:
            # Then (ψ, dy) minimising the working volume's reprojection differences.
            import nlopt

            uv_true = [t.project(X)[0] for t in true]

            def f(p, grad):
                Gp = rigid(rot_y(p[0]), [0.0, p[1], 0.0])
                tot = 0.0
                for e, ut in zip(est, uv_true, strict=True):
                    d = e.with_pose(Gp @ e.world_from_cam).project(X)[0] - ut
                    tot += float(np.nansum(d * d))
                return tot

            opt = nlopt.opt(nlopt.LN_BOBYQA, 2)
            opt.set_min_objective(f)
            opt.set_initial_step([math.radians(0.5), 0.005])
            opt.set_xtol_abs([1e-9, 1e-9])
            opt.set_maxeval(400)
            with suppress(nlopt.RoundoffLimited):
                psi, dy = (float(v) for v in opt.optimize([psi, dy]))
        G = rigid(rot_y(psi), [0.0, dy, 0.0])
        yaw = math.degrees(psi)
    rot, pos, foc, pp, vol = [], [], [], [], []
    for e, t in zip(est, true, strict=True):
        Te = G @ e.world_from_cam
        if volume_m:
            uv_e, _ = e.with_pose(Te).project(X)
            uv_t, _ = t.project(X)
            vol.append(float(np.sqrt(np.nanmean(np.sum((uv_e - uv_t) ** 2, axis=1)))))
        rot.append(rotation_angle_deg(Te[:3, :3].T @ t.world_from_cam[:3, :3]))
        pos.append(float(np.linalg.norm(Te[:3, 3] - t.world_from_cam[:3, 3]) * 1000.0))
        foc.append(float(100.0 * abs((e.fx + e.fy) - (t.fx + t.fy)) / (t.fx + t.fy)))
        pp.append(float(math.hypot(e.cx - t.cx, e.cy - t.cy)))
    return {
        "cameras": idx,
        "rotation_deg": rot,
        "position_mm": pos,
        "focal_pct": foc,
        "principal_point_px": pp,
        "max_rotation_deg": max(rot),
        "max_position_mm": max(pos),
        "max_focal_pct": max(foc),
        "max_principal_point_px": max(pp),
        "volume_reproj_px": vol,
        "max_volume_reproj_px": max(vol) if vol else float("nan"),
        "gauge_yaw_deg": yaw,
        "gauge_dy_mm": dy * 1000.0,
    }


def _lattice_offsets(n: int) -> np.ndarray:
    """(n, 2) sub-pixel offsets in (-0.5, 0.5): a rank-1 (Fibonacci-like) lattice, so that
    x and y each take n distinct values — an axis-aligned edge is resolved to 1/n px
    instead of the 1/√n of a regular grid."""
    phi = (math.sqrt(5.0) - 1.0) / 2.0
    g = min((c for c in range(1, max(n, 2)) if math.gcd(c, n) == 1), key=lambda c: abs(c / n - phi))
    k = np.arange(n)
    return np.stack([(k + 0.5) / n - 0.5, ((k * g) % n + 0.5) / n - 0.5], axis=1)


@functools.lru_cache(maxsize=4)
def _sample_rays(K_bytes: bytes, dist_bytes: bytes, W: int, H: int, n: int) -> np.ndarray:
    """Undistorted normalised coordinates (n, H·W, 1, 2) float32 of n samples in every
    pixel (cached: undistortion is the costly part and the same for every board pose)."""
    cam = Camera(K=np.frombuffer(K_bytes).reshape(3, 3), dist=np.frombuffer(dist_bytes), width=W, height=H)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.empty((n, H * W, 1, 2), np.float32)
    for k, (dx, dy) in enumerate(_lattice_offsets(n)):
        xyd = np.stack([(u.ravel() + dx - cam.cx) / cam.fx, (v.ravel() + dy - cam.cy) / cam.fy], axis=1)
        out[k, :, 0, :] = cam.undistort_normalized(xyd, iterations=30)
    out.setflags(write=False)
    return out


def render_charuco_view(
    camera: Camera,
    *,
    world_from_board: np.ndarray,
    charuco: CharucoSpec,
    samples: int = 9,
    px_per_square: int = 96,
    margin_squares: float = 0.5,
    albedo: tuple[float, float] = (0.04, 0.85),
    background: float = 0.2,
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Ray-cast the ChArUco board through a known camera: exact ground truth for tests.

    Independent of the calibration code: each of ``samples`` samples per pixel is
    undistorted with the camera's model, cast as a ray, intersected with the board plane
    and looks up the OpenCV board image (``CharucoSpec.image``, bilinear) surrounded by a
    white paper margin; everything else is a uniform table of reflectance
    ``background``.

    Parameters
    ----------
    camera : Camera
        Intrinsics, distortion, size and ``world_from_cam``.
    world_from_board : (4, 4) array
        Board pose in the same world frame (board frame as OpenCV defines it).
    charuco : CharucoSpec
    samples : int
        Samples per pixel (box filter over a rank-1 lattice).
    px_per_square : int
        Resolution of the board texture.
    margin_squares : float
        White margin around the printed squares.
    albedo : (black, white) linear reflectances of the print.
    background : linear reflectance of the table.
    noise_sigma : float
        Standard deviation of additive Gaussian noise (linear units).
    rng : numpy Generator, required when ``noise_sigma > 0``.

    Returns
    -------
    (H, W, 3) float32 linear image.
    """
    import cv2

    if noise_sigma > 0 and rng is None:
        raise InputError("render_charuco_view: noise_sigma > 0 needs an explicit rng (numpy Generator)")
    n = int(samples)
    if n < 1:
        raise InputError(f"render_charuco_view: samples={samples} must be >= 1")
    tex = charuco.image(px_per_square).astype(np.float32) / 255.0
    tex = albedo[0] + (albedo[1] - albedo[0]) * tex
    m = int(round(margin_squares * px_per_square))
    tex = cv2.copyMakeBorder(tex, m, m, m, m, cv2.BORDER_CONSTANT, value=float(albedo[1]))
    board_from_cam = invert_rigid(np.asarray(world_from_board, dtype=np.float64)) @ camera.world_from_cam
    R, o = board_from_cam[:3, :3], board_from_cam[:3, 3]
    W, H = camera.width, camera.height
    if o[2] >= 0:  # camera on the back side of (or in) the board plane: the print is invisible
        img = np.full((H, W), float(background))
    else:
        # A ray r = (x, y, 1) meets the board plane z = 0 at
        #   X = (o_x R_2 − o_z R_0)·r / R_2·r,  Y = (o_y R_2 − o_z R_1)·r / R_2·r,
        # in front of the camera iff R_2·r > 0: a homography from undistorted normalised
        # coordinates to board metres, then to texture pixels (pixel i covers
        # [i, i+1)·square/pps, centre at i + 0.5; plus the margin).
        Hb = np.stack([o[0] * R[2] - o[2] * R[0], o[1] * R[2] - o[2] * R[1], R[2]])
        sc = px_per_square / charuco.square_m
        A = np.array([[sc, 0.0, m - 0.5], [0.0, sc, m - 0.5], [0.0, 0.0, 1.0]])
        Hm = A @ Hb
        rays = _sample_rays(camera.K.tobytes(), camera.dist.tobytes(), W, H, n)
        acc = np.zeros((H, W), np.float32)
        for k in range(n):
            xy = rays[k]
            maps = cv2.perspectiveTransform(xy, Hm).reshape(H, W, 2)
            w = (Hm[2, 0] * xy[:, 0, 0] + Hm[2, 1] * xy[:, 0, 1] + Hm[2, 2]).reshape(H, W)
            maps[w <= 0] = -1e4
            # map2=None: ``maps`` holds both coordinates (the stub wrongly requires map2).
            acc += cv2.remap(
                tex,
                maps,
                None,  # pyright: ignore[reportCallIssue, reportArgumentType]
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=float(background),
            )
        img = acc / n
    if noise_sigma > 0 and rng is not None:  # rng is checked above; this narrows its type
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.repeat(img[:, :, None], 3, axis=2).astype(np.float32)
