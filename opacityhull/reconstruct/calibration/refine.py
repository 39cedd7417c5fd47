"""Step 4 of the calibration: joint refinement of the turntable rig model with nlopt.

``LD_LBFGS`` on the sum of squared reprojection errors, with the analytic gradient from
``cv2.projectPoints``' Jacobian and the variables whitened by the Gauss–Newton Hessian
at the start, so that L-BFGS takes Newton-like steps. The variables are per-camera
intrinsics (those not held), per-camera ``cam_from_rig`` (6 DoF), the board's placement
on the table (centre x, z and two tilts; yaw and height are the gauge) and optionally a
table-angle scale. Every observation (c, a) is predicted as
``cam_from_rig(c) · rig_from_object(s·a) · object_from_board`` — a view never gets its
own pose.
"""

from __future__ import annotations

import math
from contextlib import suppress
from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

from ...charuco import CharucoSpec
from ...se3 import rodrigues, rvec_from_matrix
from .board import board_pose

__all__ = ["CamBlock", "RigModel", "refine_nlopt"]


@dataclass(kw_only=True)
class CamBlock:
    """One camera's share of the rig model: its current parameters (which intrinsics are
    free) and every corner it observed (board frame, pixels, table angle)."""

    index: int
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    cam_from_rig: np.ndarray
    free: tuple[str, ...]  # free intrinsics: f | fx, fy; cx, cy; k1, k2, p1, p2, k3
    aspect: float  # fx / fy when "f" is the parameter
    obj: np.ndarray  # (N, 3) board points of all its views
    img: np.ndarray  # (N, 2)
    angle: np.ndarray  # (N,) table degrees per point
    view_of_point: np.ndarray  # (N,) index into views
    views: list[str]
    offset: int = 0  # start of its parameters in x

    @property
    def n_params(self) -> int:
        return len(self.free) + 6


class RigModel:
    """Parameter packing, residuals and Jacobian of the turntable rig model."""

    def __init__(
        self,
        blocks: list[CamBlock],
        spec: CharucoSpec,
        board: np.ndarray,
        *,
        fit_tilt: bool,
        fit_scale: bool,
        scale: float = 1.0,
    ):
        self.blocks = blocks
        self.spec = spec
        self.fit_tilt = fit_tilt
        self.fit_scale = fit_scale
        off = 0
        for b in blocks:
            b.offset = off
            off += b.n_params
        self.board_offset = off
        self.board_names = (["tilt_x", "tilt_z"] if fit_tilt else []) + ["centre_x", "centre_z"]
        off += len(self.board_names)
        self.scale_offset = off if fit_scale else None
        self.n = off + (1 if fit_scale else 0)
        self.board0 = np.asarray(board, dtype=np.float64)  # (tilt_x, tilt_z, cx, cz)
        self.scale0 = scale

    # ---- packing
    def pack(self) -> np.ndarray:
        x = np.zeros(self.n)
        for b in self.blocks:
            vals = {
                "f": b.K[1, 1],
                "fx": b.K[0, 0],
                "fy": b.K[1, 1],
                "cx": b.K[0, 2],
                "cy": b.K[1, 2],
                "k1": b.dist[0],
                "k2": b.dist[1],
                "p1": b.dist[2],
                "p2": b.dist[3],
                "k3": b.dist[4],
            }
            for i, nm in enumerate(b.free):
                x[b.offset + i] = vals[nm]
            k = b.offset + len(b.free)
            x[k : k + 3] = rvec_from_matrix(b.cam_from_rig[:3, :3])
            x[k + 3 : k + 6] = b.cam_from_rig[:3, 3]
        bp = self.board0 if self.fit_tilt else self.board0[2:]
        x[self.board_offset : self.board_offset + len(bp)] = bp
        if self.fit_scale:
            x[self.scale_offset] = self.scale0
        return x

    def camera_params(self, b: CamBlock, x: np.ndarray):
        K = b.K.copy()
        dist = b.dist.copy()
        p = dict(zip(b.free, x[b.offset : b.offset + len(b.free)], strict=True))
        if "f" in p:
            K[1, 1] = p["f"]
            K[0, 0] = p["f"] * b.aspect
        for nm, (r, c) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            if nm in p:
                K[r, c] = p[nm]
        for i, nm in enumerate(("k1", "k2", "p1", "p2", "k3")):
            if nm in p:
                dist[i] = p[nm]
        k = b.offset + len(b.free)
        return K, dist, x[k : k + 3].copy(), x[k + 3 : k + 6].copy()

    def board_params(self, x: np.ndarray) -> np.ndarray:
        v = x[self.board_offset : self.board_offset + len(self.board_names)]
        return v.copy() if self.fit_tilt else np.concatenate([self.board0[:2], v])

    def scale(self, x: np.ndarray) -> float:
        return float(x[self.scale_offset]) if self.fit_scale else self.scale0

    def object_from_board(self, x: np.ndarray) -> np.ndarray:
        return board_pose(self.spec, *self.board_params(x))

    def _rig_points(self, b: CamBlock, bp: np.ndarray, s: float) -> np.ndarray:
        T = board_pose(self.spec, *bp)
        P = b.obj @ T[:3, :3].T + T[:3, 3]
        th = np.radians(s * b.angle)
        c, sn = np.cos(th), np.sin(th)
        return np.stack([c * P[:, 0] + sn * P[:, 2], P[:, 1], -sn * P[:, 0] + c * P[:, 2]], axis=1)

    # ---- residuals
    def _project(self, b: CamBlock, x: np.ndarray, bp: np.ndarray, s: float):
        """Predicted pixels (N, 2) of block ``b``, ``cv2.projectPoints``' Jacobian (2N, 15)
        and the camera's rotation vector."""
        import cv2

        K, dist, rv, tv = self.camera_params(b, x)
        uv, J = cv2.projectPoints(self._rig_points(b, bp, s), rv, tv, K, dist)
        return uv.reshape(-1, 2), J, rv

    def residuals(self, x: np.ndarray) -> list[np.ndarray]:
        """Per camera block, (N, 2) predicted − observed pixels."""
        bp, s = self.board_params(x), self.scale(x)
        return [self._project(b, x, bp, s)[0] - b.img for b in self.blocks]

    @overload
    def cost_grad_hessian(
        self, x: np.ndarray, *, want_hessian: Literal[True]
    ) -> tuple[float, np.ndarray, np.ndarray]: ...

    @overload
    def cost_grad_hessian(self, x: np.ndarray, *, want_hessian: Literal[False]) -> tuple[float, np.ndarray, None]: ...

    def cost_grad_hessian(self, x: np.ndarray, *, want_hessian: bool) -> tuple[float, np.ndarray, np.ndarray | None]:
        """Cost Σr², gradient 2Jᵀr (n,) and (optionally) Gauss–Newton Hessian 2JᵀJ (n, n)."""
        bp, s = self.board_params(x), self.scale(x)
        # d(rig points)/d(board & scale params) by central differences (5 cheap evaluations).
        ext_idx = list(range(self.board_offset, self.n))
        cost = 0.0
        g = np.zeros(self.n)
        H = np.zeros((self.n, self.n) if want_hessian else (0, 0))
        for b in self.blocks:
            uv, J, rv = self._project(b, x, bp, s)
            r = (uv - b.img).ravel()
            cost += float(r @ r)
            N = b.obj.shape[0]
            cols = []
            for nm in b.free:
                if nm == "f":
                    cols.append(J[:, 6] * b.aspect + J[:, 7])
                else:
                    cols.append(
                        J[:, {"fx": 6, "fy": 7, "cx": 8, "cy": 9, "k1": 10, "k2": 11, "p1": 12, "p2": 13, "k3": 14}[nm]]
                    )
            Jc = np.column_stack(cols + [J[:, 0:6]]) if cols else J[:, 0:6]
            # extra (board/scale) columns: dUV/dXcam · R · dXrig/dθ
            R = rodrigues(rv)
            Jt = J[:, 3:6].reshape(N, 2, 3)
            dX = self._rig_point_derivs(b, bp, s)  # (N, 3, m)
            Je = np.einsum("nij,jk,nkm->nim", Jt, R, dX).reshape(2 * N, -1)
            sl = slice(b.offset, b.offset + b.n_params)
            g[sl] += 2.0 * Jc.T @ r
            g[ext_idx] += 2.0 * Je.T @ r
            if want_hessian:
                H[sl, sl] += 2.0 * Jc.T @ Jc
                cross = 2.0 * Jc.T @ Je
                H[sl, ext_idx] += cross
                H[ext_idx, sl] += cross.T
                H[np.ix_(ext_idx, ext_idx)] += 2.0 * Je.T @ Je
        return cost, g, (H if want_hessian else None)

    def _rig_point_derivs(self, b: CamBlock, bp: np.ndarray, s: float) -> np.ndarray:
        m = len(self.board_names) + (1 if self.fit_scale else 0)
        out = np.empty((b.obj.shape[0], 3, m))
        h = 1e-6
        names = list(range(4)) if self.fit_tilt else [2, 3]
        for k, idx in enumerate(names):
            e = np.zeros(4)
            e[idx] = h
            out[:, :, k] = (self._rig_points(b, bp + e, s) - self._rig_points(b, bp - e, s)) / (2 * h)
        if self.fit_scale:
            out[:, :, m - 1] = (self._rig_points(b, bp, s + h) - self._rig_points(b, bp, s - h)) / (2 * h)
        return out


def refine_nlopt(model: RigModel, x0: np.ndarray, *, max_iter: int, restarts: int) -> tuple[np.ndarray, dict]:
    """Minimise Σ r² with nlopt L-BFGS in variables whitened by the Gauss–Newton Hessian.

    Returns the best parameters seen (n,) and ``{"evaluations", "runs", "cost_start",
    "cost_end"}``; the variables are re-whitened and L-BFGS restarted (at most
    ``restarts`` times) while a run lowers the cost by more than 1e-9 relative.
    """
    import nlopt
    from scipy.linalg import solve_triangular

    x_best = x0.copy()
    f_best = model.cost_grad_hessian(x0, want_hessian=False)[0]
    info = {"evaluations": 0, "runs": 0, "cost_start": f_best}
    for _ in range(restarts + 1):
        _, _, H = model.cost_grad_hessian(x_best, want_hessian=True)
        d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        Hs = H / np.outer(d, d) + 1e-9 * np.eye(model.n)  # Jacobi scaling, then a tiny ridge
        L = np.linalg.cholesky(Hs)
        # x = x_ref + D⁻¹ L⁻ᵀ δ  ⇒  the Hessian in δ is the identity at x_ref.
        x_ref = x_best.copy()

        def to_x(delta, x_ref=x_ref, L=L, d=d):
            return x_ref + solve_triangular(L.T, delta, lower=False) / d

        state = {"f": f_best, "x": x_best.copy()}

        def objective(delta, grad, L=L, d=d, state=state, to_x=to_x):
            x = to_x(delta)
            f, gx, _ = model.cost_grad_hessian(x, want_hessian=False)
            info["evaluations"] += 1
            if not math.isfinite(f):
                f = 1e300
                gx = np.zeros_like(gx)
            if grad.size:
                grad[:] = solve_triangular(L, gx / d, lower=True)
            if f < state["f"]:
                state["f"], state["x"] = f, x
            return f

        opt = nlopt.opt(nlopt.LD_LBFGS, model.n)
        opt.set_min_objective(objective)
        opt.set_maxeval(int(max_iter))
        opt.set_ftol_rel(1e-13)
        opt.set_xtol_rel(1e-12)
        opt.set_vector_storage(min(model.n, 30))
        # L-BFGS hit the floating-point floor: the best point seen is kept
        with suppress(nlopt.RoundoffLimited, RuntimeError, ValueError):
            opt.optimize(np.zeros(model.n))
        info["runs"] += 1
        improved = (f_best - state["f"]) > 1e-9 * max(f_best, 1e-300)
        if state["f"] < f_best:
            f_best, x_best = state["f"], state["x"]
        if not improved:
            break
    info["cost_end"] = f_best
    return x_best, info
