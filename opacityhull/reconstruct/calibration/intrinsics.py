"""Step 2 of the calibration: intrinsics of one camera (``cv2.calibrateCamera`` over its views).

A board lying flat on a turntable shows every camera *one plane* only — turning the
board inside its own plane adds no information about ``K`` — and one plane constrains
just two intrinsic parameters (Zhang 2000; Sturm & Maybank 1999): with ``fx, fy, cx,
cy`` all free the problem is degenerate (measured: fy off by 40 %, cx by 30 px at 0.1 px
noise). So by default the principal point and the aspect ratio are held at the nominal
values whenever the board normals seen by a camera span less than
``min_plane_spread_deg``; a board tilted on a wedge (normals precessing as the table
turns) frees them. ``k2`` is likewise held at 0 when the corners never reach
``min_k2_coverage`` of the image half-diagonal (an r⁴ term fitted on the centre alone
extrapolates wildly towards the corners). These choices are made again once
misdetected views are dropped (one wrong view's pose can fake a spread of normals). The
distortion model is chosen by BIC among the nested models the configuration allows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from ...se3 import rigid, rodrigues
from .config import CalibrationConfig
from .detect import CharucoObservation

__all__ = ["IntrinsicsFit", "fit_intrinsics", "plane_spread_deg"]


@dataclass(frozen=True, kw_only=True)
class IntrinsicsFit:
    """Outcome of :func:`fit_intrinsics` for one camera.

    Attributes
    ----------
    K : (3, 3) array or None
        Calibrated camera matrix (px); None when fewer than three views survived the
        outlier screening (``n_views``).
    dist : (5,) array or None
        OpenCV distortion ``(k1, k2, p1, p2, k3)``; None with ``K``.
    poses : list of (CharucoObservation, (4, 4) array)
        The views kept, sorted by table angle, with their ``cam_from_board``.
    n_views : int
        Number of views kept.
    fixed : tuple of str
        Intrinsics held (``cx``, ``cy``, ``fx/fy``, distortion terms).
    notes : tuple of str
        Decisions worth telling the user, prefixed with the camera's name.
    dropped : dict view id → str
        Views dropped as misdetections, with the reason.
    """

    K: np.ndarray | None
    dist: np.ndarray | None
    poses: list[tuple[CharucoObservation, np.ndarray]]
    n_views: int
    fixed: tuple[str, ...]
    notes: tuple[str, ...]
    dropped: dict[str, str]


def plane_spread_deg(normals: Sequence[np.ndarray]) -> float:
    """Full angular spread (degrees) of (3,) unit board normals: twice the largest angle
    to their mean direction."""
    N = np.array(normals)
    m = N.mean(axis=0)
    m /= np.linalg.norm(m)
    return float(np.degrees(np.arccos(np.clip(N @ m, -1, 1))).max() * 2.0)


@dataclass(frozen=True, kw_only=True)
class _Choice:
    """What a camera's views can constrain (see :func:`_choose_model`)."""

    flags: int  # cv2.calibrateCamera flags of the held intrinsics
    held: tuple[str, ...]  # cx, cy, fx/fy
    chain: list[tuple[str, tuple[str, ...]]]  # nested distortion models, smallest first
    n_intr: int  # free intrinsics besides distortion
    notes: tuple[str, ...]


def _dist_flags(flags: int, free_dist: tuple[str, ...]) -> int:
    """``flags`` plus OpenCV's flags holding the distortion terms not in ``free_dist`` at 0."""
    import cv2

    f = flags
    for nm, fl in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
        if nm not in free_dist:
            f |= fl
    if "p1" not in free_dist:
        f |= cv2.CALIB_ZERO_TANGENT_DIST
    return f


def _choose_model(
    views: Sequence[CharucoObservation], *, K0: np.ndarray, size: tuple[int, int], config: CalibrationConfig, name: str
) -> _Choice:
    """Which intrinsics ``views`` can constrain (principal point, aspect ratio, k2) and
    the distortion models to try, with the notes saying why."""
    import cv2

    w, h = size
    notes: list[str] = []
    normals = []
    for o in views:
        ok, rv, _ = cv2.solvePnP(o.object_points, o.image_points, K0, None, flags=cv2.SOLVEPNP_IPPE)
        if ok:
            normals.append(rodrigues(rv)[:, 2])
    spread = plane_spread_deg(normals) if normals else 0.0
    single_plane = spread < config.min_plane_spread_deg
    fov_diag_deg = 2.0 * math.degrees(math.atan(0.5 * math.hypot(w, h) / float(K0[0, 0])))
    narrow = fov_diag_deg < config.min_fov_free_principal_point_deg
    fix_pp = (single_plane or narrow) if config.fix_principal_point is None else bool(config.fix_principal_point)
    if narrow and not single_plane and config.fix_principal_point is None:
        notes.append(
            f"{name}: diagonal field of view {fov_diag_deg:.1f} deg (< "
            f"{config.min_fov_free_principal_point_deg}): principal point held at nominal"
        )
    fix_ar = single_plane if config.fix_aspect_ratio is None else bool(config.fix_aspect_ratio)
    if single_plane and (config.fix_principal_point is None or config.fix_aspect_ratio is None):
        notes.append(
            f"{name}: board normals span {spread:.1f} deg (< {config.min_plane_spread_deg}): "
            "one plane constrains only two intrinsics; principal point and aspect ratio held at nominal"
        )
    allpts = np.concatenate([o.image_points for o in views])
    r_cov = float(np.max(np.hypot(allpts[:, 0] - K0[0, 2], allpts[:, 1] - K0[1, 2]))) / (0.5 * math.hypot(w, h))
    fix_k2 = (r_cov < config.min_k2_coverage) if config.fix_k2 is None else bool(config.fix_k2)
    if config.fix_k2 is None and fix_k2:
        notes.append(
            f"{name}: corners reach {r_cov:.2f} of the image half-diagonal (< {config.min_k2_coverage}); k2 held at 0"
        )
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    held: list[str] = []
    if fix_pp:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        held += ["cx", "cy"]
    if fix_ar:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
        held += ["fx/fy"]
    # Nested distortion models, smallest first, up to what the config allows.
    chain: list[tuple[str, tuple[str, ...]]] = [("none", ()), ("k1", ("k1",))]
    if not fix_k2:
        chain.append(("k1k2", ("k1", "k2")))
    if not config.fix_tangential:
        chain.append((chain[-1][0] + "p", chain[-1][1] + ("p1", "p2")))
    if not config.fix_k3 and not fix_k2:
        chain.append((chain[-1][0] + "k3", chain[-1][1] + ("k3",)))
    n_intr = (1 if fix_ar else 2) + (0 if fix_pp else 2)

    return _Choice(flags=flags, held=tuple(held), chain=chain, n_intr=n_intr, notes=tuple(notes))


def fit_intrinsics(
    observations: Sequence[CharucoObservation],
    *,
    size: tuple[int, int],
    K0: np.ndarray | None,
    config: CalibrationConfig,
    name: str,
) -> IntrinsicsFit:
    """Calibrate one camera's intrinsics and board poses from its usable views.

    Parameters
    ----------
    observations : sequence of CharucoObservation
        The camera's screened views (at least three).
    size : (width, height)
        Image size in pixels.
    K0 : (3, 3) array or None
        Nominal camera matrix (initial guess, and the principal point / aspect ratio
        when held). None: OpenCV's homography initialisation with the principal point
        at the image centre.
    config : CalibrationConfig
    name : str
        Camera name for the notes and reasons.

    Returns
    -------
    IntrinsicsFit
        With ``K = None`` when the outlier screening leaves fewer than three views.
    """
    import cv2

    w, h = size
    views = sorted(observations, key=lambda o: o.table_deg)
    if K0 is None:
        objs = [o.object_points.astype(np.float32) for o in views]
        imgs = [o.image_points.astype(np.float32) for o in views]
        K0 = np.asarray(cv2.initCameraMatrix2D(objs, imgs, (w, h), aspectRatio=1.0))
        K0[0, 2], K0[1, 2] = (w - 1) / 2.0, (h - 1) / 2.0
    else:
        K0 = np.array(K0, dtype=np.float64)
    dropped: dict[str, str] = {}
    choice = _choose_model(views, K0=K0, size=size, config=config, name=name)

    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)

    def fit(views_, free_dist, choice_):
        objs_ = [o.object_points.astype(np.float32) for o in views_]
        imgs_ = [o.image_points.astype(np.float32) for o in views_]
        out = cv2.calibrateCameraExtended(
            objs_, imgs_, (w, h), K0.copy(), np.zeros(5), flags=_dist_flags(choice_.flags, free_dist), criteria=crit
        )
        rms_, K_, dist_, rv_, tv_, _, _, pv_ = out
        return rms_, K_, dist_, rv_, tv_, np.asarray(pv_).ravel()

    # Misdetections first, with the largest model (a wrong view must not choose it).
    rms, K, dist, rvecs, tvecs, per_view = fit(views, choice.chain[-1][1], choice)
    lim = max(config.max_view_rms_px, 3.0 * float(np.median(per_view)))
    bad = [i for i, e in enumerate(per_view) if e > lim]
    if bad:
        for i in bad:
            dropped[views[i].view] = (
                f"reprojection RMS {per_view[i]:.2f} px after calibrating {name} alone (> {lim:.2f} px): misdetection"
            )
        views = [v for i, v in enumerate(views) if i not in bad]
        if len(views) < 3:
            return IntrinsicsFit(
                K=None,
                dist=None,
                poses=[],
                n_views=len(views),
                fixed=choice.held,
                notes=choice.notes + (f"{name}: dropped {len(bad)} outlier view(s)",),
                dropped=dropped,
            )
        # What the views constrain is decided again without the misdetections: a wrong
        # view's PnP normal alone can widen the board normals past min_plane_spread_deg.
        choice = _choose_model(views, K0=K0, size=size, config=config, name=name)
        notes = list(choice.notes) + [f"{name}: dropped {len(bad)} outlier view(s)"]
    else:
        notes = list(choice.notes)
    if config.select_distortion and len(choice.chain) > 1:
        # BIC over the nested models: a coefficient must pay for itself. Spurious
        # distortion trades off against the focal length (measured: k1 = -0.35 and a
        # 6 % focal error on a distortion-free 24 deg camera).
        n_res = 2 * sum(len(o) for o in views)
        scored = []
        for label, free_dist in choice.chain:
            r_ = fit(views, free_dist, choice)
            ssr = max(r_[0] ** 2 * n_res / 2.0, 1e-300)
            k = choice.n_intr + len(free_dist) + 6 * len(views)
            scored.append((n_res * math.log(ssr / n_res) + k * math.log(n_res), label, free_dist, r_))
        _, model_name, free_dist, (rms, K, dist, rvecs, tvecs, per_view) = min(scored, key=lambda t: t[0])
        notes.append(
            f"{name}: distortion model '{model_name}' chosen by BIC ("
            + ", ".join(f"{nm} {b:.1f}" for b, nm, _, _ in scored)
            + ")"
        )
    else:
        free_dist = choice.chain[-1][1]
        if bad:
            rms, K, dist, rvecs, tvecs, per_view = fit(views, free_dist, choice)
    held = list(choice.held)
    held += [nm for nm in ("k1", "k2", "p1", "p2", "k3") if nm not in free_dist]
    poses = [(o, rigid(rodrigues(rv), np.asarray(tv).ravel())) for o, rv, tv in zip(views, rvecs, tvecs, strict=True)]
    return IntrinsicsFit(
        K=np.asarray(K, dtype=np.float64),
        dist=np.asarray(dist, dtype=np.float64).ravel()[:5],
        poses=poses,
        n_views=len(views),
        fixed=tuple(held),
        notes=tuple(notes),
        dropped=dropped,
    )
