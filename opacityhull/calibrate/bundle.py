"""Intrinsics, distortion and poses of one or more cameras from ChArUco frames.

1. Per camera, ``cv2.calibrateCameraExtended`` over its own frames (the initial
   intrinsics and board poses; frames reprojecting worse than ``max(2 px, 3 × median)``
   are dropped as misdetections). A camera whose board normals span less than
   ``min_plane_spread_deg`` (one plane: the board never tilted) holds its principal
   point at the image centre and ``fx = fy`` — one plane constrains two intrinsics only.
2. Cameras are chained into the first camera's frame through the instants they share
   (breadth first, most shared instants first); each instant's board pose is the mean of
   what the cameras seeing it say.
3. One bundle adjustment over every camera's intrinsics and pose and every instant's
   board pose (:func:`bundle_adjust`): ``scipy.optimize.least_squares`` (trust region
   reflective) with the analytic Jacobian of ``cv2.projectPoints`` ∘ ``cv2.composeRT``
   (assembled block-sparse: a board pose touches only its own instant's rows; solved
   with the exact dense trust-region step — the sparse LSMR step stalled at 100
   evaluations on caliscope's set). Why scipy and not nlopt or pycolmap: it is a small
   nonlinear least squares, and the same Jacobian gives the per-parameter standard
   deviations (σ² (JᵀJ)⁻¹).
   pycolmap's bundle adjuster has no ChArUco board (a rigid 2-D point set with its own
   pose), and nlopt would need the same Jacobian assembled by hand for no gain.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Literal
from collections.abc import Mapping, Sequence

import numpy as np

from ..errors import InputError
from ..se3 import invert_rigid, mean_pose, rigid, rodrigues

log = logging.getLogger(__name__)

__all__ = ["DistModel", "DIST_MODELS", "CameraFit", "BundleResult", "init_camera", "chain_cameras", "bundle_adjust"]

DistModel = Literal["none", "k1", "k1k2", "k1k2p", "k1k2pk3"]
#: OpenCV distortion terms each model frees (k1, k2, p1, p2, k3).
DIST_MODELS: dict[str, tuple[str, ...]] = {
    "none": (),
    "k1": ("k1",),
    "k1k2": ("k1", "k2"),
    "k1k2p": ("k1", "k2", "p1", "p2"),
    "k1k2pk3": ("k1", "k2", "p1", "p2", "k3"),
}
_JCOL = {"fx": 6, "fy": 7, "cx": 8, "cy": 9, "k1": 10, "k2": 11, "p1": 12, "p2": 13, "k3": 14}
TR_SOLVER = "exact"
_DIST_I = {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4}


@dataclass(frozen=True, kw_only=True)
class Obs:
    """Corners one camera saw at one instant."""

    camera: int
    instant: str
    where: str
    object_points: np.ndarray  # (N, 3) board, metres
    image_points: np.ndarray  # (N, 2) pixels


@dataclass(frozen=True, kw_only=True)
class CameraInit:
    """Step-1 result for one camera."""

    index: int
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    free: tuple[str, ...]
    cam_from_board: dict[str, np.ndarray]
    notes: list[str] = field(default_factory=list)
    dropped: dict[str, str] = field(default_factory=dict)


def _dist_flags(free: Sequence[str]) -> int:
    import cv2

    f = cv2.CALIB_USE_INTRINSIC_GUESS
    for nm, fl in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
        if nm not in free:
            f |= fl
    if "p1" not in free:
        f |= cv2.CALIB_ZERO_TANGENT_DIST
    if "cx" not in free:
        f |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if "f" in free:
        f |= cv2.CALIB_FIX_ASPECT_RATIO
    return f


def n_intrinsics(free: Sequence[str]) -> int:
    return len(free)


def init_camera(
    obs: Sequence[Obs],
    *,
    index: int,
    size: tuple[int, int],
    dist_model: str = "k1k2pk3",
    min_plane_spread_deg: float = 10.0,
    max_view_rms_px: float = 2.0,
    fix_principal_point: bool = False,
    fix_aspect_ratio: bool = False,
) -> CameraInit:
    """Step 1 for one camera (``obs``: its frames, at least 3, checked by the caller)."""
    import cv2

    w, h = size
    objs = [o.object_points.astype(np.float32) for o in obs]
    imgs = [o.image_points.astype(np.float32) for o in obs]
    K0 = np.asarray(cv2.initCameraMatrix2D(objs, imgs, (w, h), aspectRatio=1.0), dtype=np.float64)
    K0[0, 2], K0[1, 2] = (w - 1) / 2.0, (h - 1) / 2.0
    normals = []
    for o in obs:
        ok, rv, _ = cv2.solvePnP(o.object_points, o.image_points, K0, None, flags=cv2.SOLVEPNP_IPPE)
        if ok:
            normals.append(rodrigues(rv)[:, 2])
    N = np.array(normals) if normals else np.zeros((0, 3))
    spread = 0.0
    if len(N):
        m = N.mean(axis=0)
        m /= np.linalg.norm(m)
        spread = float(np.degrees(np.arccos(np.clip(N @ m, -1, 1))).max() * 2.0)
    notes = []
    free: list[str] = ["f"] if fix_aspect_ratio else ["fx", "fy"]
    if not fix_principal_point:
        free += ["cx", "cy"]
    if spread < min_plane_spread_deg:
        free = ["f"]
        notes.append(
            f"camera {index}: board normals span {spread:.1f} deg (< {min_plane_spread_deg}): one plane constrains "
            "two intrinsics only; principal point held at the image centre and fx = fy"
        )
    free += list(DIST_MODELS[dist_model])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)

    def fit(sel):
        out = cv2.calibrateCameraExtended(
            [objs[i] for i in sel],
            [imgs[i] for i in sel],
            (w, h),
            K0.copy(),
            np.zeros(5),
            flags=_dist_flags(free),
            criteria=crit,
        )
        return out[1], out[2], out[3], out[4], np.asarray(out[7]).ravel()

    sel = list(range(len(obs)))
    K, dist, rv, tv, pv = fit(sel)
    lim = max(max_view_rms_px, 3.0 * float(np.median(pv)))
    bad = [i for i, e in zip(sel, pv, strict=True) if e > lim]
    dropped = {}
    if bad and len(obs) - len(bad) >= 3:
        for i in bad:
            dropped[obs[i].where] = f"reprojection RMS {pv[sel.index(i)]:.2f} px > {lim:.2f} px: misdetection"
        sel = [i for i in sel if i not in bad]
        K, dist, rv, tv, pv = fit(sel)
    poses = {obs[i].instant: rigid(rodrigues(r), np.asarray(t).ravel()) for i, r, t in zip(sel, rv, tv, strict=True)}
    return CameraInit(
        index=index,
        size=size,
        K=np.asarray(K, dtype=np.float64),
        dist=np.asarray(dist, dtype=np.float64).ravel()[:5],
        free=tuple(free),
        cam_from_board=poses,
        notes=notes,
        dropped=dropped,
    )


def chain_cameras(
    inits: Mapping[int, CameraInit],
) -> tuple[dict[int, np.ndarray], dict[str, np.ndarray], dict[int, str]]:
    """Initial ``cam_from_world`` per camera (world = the first camera's frame), the
    board pose ``world_from_board`` per instant, and the cameras left out (no instant
    shared with the chained ones) with the reason."""
    cams = sorted(inits)
    ref = cams[0]
    cam_from_world = {ref: np.eye(4)}
    left = [c for c in cams if c != ref]
    while left:
        best = None
        for c in left:
            shared = [(k, t) for k in cam_from_world for t in inits[c].cam_from_board if t in inits[k].cam_from_board]
            if shared and (best is None or len(shared) > len(best[1])):
                best = (c, shared)
        if best is None:
            break
        c, shared = best
        cands = [
            inits[c].cam_from_board[t] @ invert_rigid(inits[k].cam_from_board[t]) @ cam_from_world[k] for k, t in shared
        ]
        cam_from_world[c] = mean_pose(cands)
        left.remove(c)
    out = {
        c: (
            f"camera {c} never sees the board at an instant another calibrated camera sees it; "
            "its pose cannot be chained (left out)"
        )
        for c in left
    }
    world_from_board: dict[str, np.ndarray] = {}
    instants = sorted({t for c in cam_from_world for t in inits[c].cam_from_board})
    for t in instants:
        cands = [
            invert_rigid(cam_from_world[c]) @ inits[c].cam_from_board[t]
            for c in cam_from_world
            if t in inits[c].cam_from_board
        ]
        world_from_board[t] = mean_pose(cands)
    return cam_from_world, world_from_board, out


@dataclass(frozen=True, kw_only=True)
class CameraFit:
    """One calibrated camera (OpenCV pixel convention)."""

    index: int
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    cam_from_world: np.ndarray
    free: tuple[str, ...]
    std: dict[str, float]
    rms_px: float
    n_frames: int
    n_points: int
    intrinsic_rms_px: float = float("nan")  # the camera calibrated alone (its own frames)
    intrinsic_frames: int = 0  # frames of that (with --sync, out-of-sync ones too)


@dataclass(frozen=True, kw_only=True)
class BundleResult:
    cameras: dict[int, CameraFit]
    world_from_board: dict[str, np.ndarray]
    residuals_px: np.ndarray  # (M, 2)
    residual_obs: np.ndarray  # (M,) index into observations
    observations: list[Obs]
    per_frame_rms_px: dict[str, float]  # where → RMS
    rms_px: float
    info: dict


class _Problem:
    def __init__(self, inits: Mapping[int, CameraInit], cam_from_world, world_from_board, obs: Sequence[Obs], ref: int):
        import cv2

        self.cams = sorted(inits)
        self.inits = inits
        self.ref = ref
        self.obs = [o for o in obs if o.camera in inits and o.instant in world_from_board]
        self.instants = sorted({o.instant for o in self.obs})
        off = 0
        self.intr_off: dict[int, int] = {}
        for c in self.cams:
            self.intr_off[c] = off
            off += len(inits[c].free)
        self.pose_off: dict[int, int] = {}
        for c in self.cams:
            if c != ref:
                self.pose_off[c] = off
                off += 6
        self.board_off: dict[str, int] = {}
        for t in self.instants:
            self.board_off[t] = off
            off += 6
        self.n = off
        x = np.zeros(off)
        for c in self.cams:
            ini = inits[c]
            vals = {"f": ini.K[1, 1], "fx": ini.K[0, 0], "fy": ini.K[1, 1], "cx": ini.K[0, 2], "cy": ini.K[1, 2]}
            vals.update({k: ini.dist[i] for k, i in _DIST_I.items()})
            x[self.intr_off[c] : self.intr_off[c] + len(ini.free)] = [vals[k] for k in ini.free]
            if c != ref:
                T = cam_from_world[c]
                x[self.pose_off[c] : self.pose_off[c] + 3] = cv2.Rodrigues(T[:3, :3])[0].ravel()
                x[self.pose_off[c] + 3 : self.pose_off[c] + 6] = T[:3, 3]
        for t in self.instants:
            T = world_from_board[t]
            x[self.board_off[t] : self.board_off[t] + 3] = cv2.Rodrigues(T[:3, :3])[0].ravel()
            x[self.board_off[t] + 3 : self.board_off[t] + 6] = T[:3, 3]
        self.x0 = x
        self.m = 2 * sum(len(o.object_points) for o in self.obs)

    def intrinsics(self, c: int, x: np.ndarray):
        ini = self.inits[c]
        K = ini.K.copy()
        dist = ini.dist.copy()
        p = dict(zip(ini.free, x[self.intr_off[c] : self.intr_off[c] + len(ini.free)], strict=True))
        if "f" in p:
            K[0, 0] = K[1, 1] = p["f"]
        for nm, (r, col) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            if nm in p:
                K[r, col] = p[nm]
        for nm, i in _DIST_I.items():
            if nm in p:
                dist[i] = p[nm]
        return K, dist

    def pose(self, c: int, x: np.ndarray):
        if c == self.ref:
            return np.zeros(3), np.zeros(3)
        o = self.pose_off[c]
        return x[o : o + 3], x[o + 3 : o + 6]

    def evaluate(self, x: np.ndarray, *, jac: bool):
        import cv2
        from scipy.sparse import csr_matrix

        res = []
        rows, cols, vals = [], [], []
        r0 = 0
        for o in self.obs:
            K, dist = self.intrinsics(o.camera, x)
            rc, tc = self.pose(o.camera, x)
            ob = self.board_off[o.instant]
            rb, tb = x[ob : ob + 3], x[ob + 3 : ob + 6]
            r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(rb, tb, rc, tc)
            uv, J = cv2.projectPoints(o.object_points, r3, t3, K, dist)
            res.append((uv.reshape(-1, 2) - o.image_points).ravel())
            n2 = 2 * len(o.object_points)
            if jac:
                Jr, Jt = J[:, 0:3], J[:, 3:6]
                blocks = []
                ini = self.inits[o.camera]
                ci = []
                for nm in ini.free:
                    ci.append(J[:, 6] + J[:, 7] if nm == "f" else J[:, _JCOL[nm]])
                if ci:
                    blocks.append((self.intr_off[o.camera], np.column_stack(ci)))
                if o.camera != self.ref:
                    Jp = np.hstack([Jr @ dr3dr2 + Jt @ dt3dr2, Jr @ dr3dt2 + Jt @ dt3dt2])
                    blocks.append((self.pose_off[o.camera], Jp))
                Jb = np.hstack([Jr @ dr3dr1 + Jt @ dt3dr1, Jr @ dr3dt1 + Jt @ dt3dt1])
                blocks.append((ob, Jb))
                rr = np.arange(r0, r0 + n2)
                for c0, B in blocks:
                    k = B.shape[1]
                    rows.append(np.repeat(rr, k))
                    cols.append(np.tile(np.arange(c0, c0 + k), n2))
                    vals.append(B.ravel())
            r0 += n2
        r = np.concatenate(res)
        if not jac:
            return r, None
        Jm = csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(self.m, self.n))
        return r, Jm


def _jac(prob: _Problem, x: np.ndarray):
    J = prob.evaluate(x, jac=True)[1]
    assert J is not None
    return J.toarray() if TR_SOLVER == "exact" else J


def bundle_adjust(
    inits: Mapping[int, CameraInit],
    cam_from_world: Mapping[int, np.ndarray],
    world_from_board: Mapping[str, np.ndarray],
    observations: Sequence[Obs],
    *,
    max_nfev: int = 100,
) -> BundleResult:
    """Refine every camera's intrinsics and pose and every instant's board pose together.

    The gauge is the first camera (its pose is the identity); the cameras in ``inits``
    must all have a ``cam_from_world``. Returns the per-parameter standard deviations
    ``σ √diag((JᵀJ)⁻¹)`` with ``σ² = Σr² / (m − n)`` (as OpenCV's
    ``stdDeviationsIntrinsics``).
    """
    from scipy.optimize import least_squares

    cams = sorted(inits)
    ref = cams[0]
    prob = _Problem(inits, dict(cam_from_world), dict(world_from_board), observations, ref)
    if prob.m <= prob.n:
        raise InputError(
            f"{prob.m} corner coordinates for {prob.n} parameters ({len(cams)} camera(s), {len(prob.instants)} "
            "board poses): fewer frames than the parameters need; give more frames"
        )
    sol = least_squares(
        lambda x: prob.evaluate(x, jac=False)[0],
        prob.x0,
        jac=lambda x: _jac(prob, x),  # pyright: ignore[reportArgumentType]  (a callable is documented)
        method="trf",
        x_scale="jac",
        tr_solver=TR_SOLVER,
        ftol=1e-12,
        xtol=1e-12,
        gtol=1e-12,
        max_nfev=max_nfev,
    )
    x = sol.x
    r, J = prob.evaluate(x, jac=True)
    assert J is not None
    dof = prob.m - prob.n
    sigma2 = float(r @ r) / dof
    JtJ = (J.T @ J).toarray()
    d = np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    try:
        cov = np.linalg.inv(JtJ / np.outer(d, d)) / np.outer(d, d) * sigma2
        var = np.diag(cov)
    except np.linalg.LinAlgError:
        var = np.full(prob.n, np.inf)
    res2 = r.reshape(-1, 2)
    obs_of_row = np.concatenate([np.full(len(o.object_points), i) for i, o in enumerate(prob.obs)])
    fits: dict[int, CameraFit] = {}
    for c in cams:
        K, dist = prob.intrinsics(c, x)
        rc, tc = prob.pose(c, x)
        sel = np.array([prob.obs[i].camera == c for i in obs_of_row])
        std = {}
        for k, nm in enumerate(inits[c].free):
            std[nm] = float(math.sqrt(max(var[prob.intr_off[c] + k], 0.0)))
        if c != ref:
            o = prob.pose_off[c]
            std["rotation_deg"] = float(math.degrees(math.sqrt(max(var[o : o + 3].sum(), 0.0))))
            std["translation_m"] = float(math.sqrt(max(var[o + 3 : o + 6].sum(), 0.0)))
        rr = res2[sel]
        fits[c] = CameraFit(
            index=c,
            size=inits[c].size,
            K=K,
            dist=dist,
            cam_from_world=rigid(rodrigues(rc), tc),
            free=inits[c].free,
            std=std,
            rms_px=float(np.sqrt(np.mean(np.sum(rr**2, axis=1)))) if len(rr) else float("nan"),
            n_frames=sum(1 for o in prob.obs if o.camera == c),
            n_points=int(sel.sum()),
        )
    per_frame = {}
    for i, o in enumerate(prob.obs):
        rr = res2[obs_of_row == i]
        per_frame[o.where] = float(np.sqrt(np.mean(np.sum(rr**2, axis=1))))
    wfb = {}
    for t in prob.instants:
        ob = prob.board_off[t]
        wfb[t] = rigid(rodrigues(x[ob : ob + 3]), x[ob + 3 : ob + 6])
    return BundleResult(
        cameras=fits,
        world_from_board=wfb,
        residuals_px=res2,
        residual_obs=obs_of_row,
        observations=list(prob.obs),
        per_frame_rms_px=per_frame,
        rms_px=float(np.sqrt(np.mean(np.sum(res2**2, axis=1)))),
        info={"nfev": int(sol.nfev), "status": int(sol.status), "cost": float(sol.cost), "dof": dof},
    )
