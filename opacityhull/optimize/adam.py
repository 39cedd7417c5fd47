"""Adam (Kingma & Ba 2015) over named per-surfel parameter arrays, each with its own
learning rate, and the row operations densification needs (keep, append)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..errors import InputError

__all__ = ["Adam", "exp_decay"]


def exp_decay(step: int, total: int, *, start: float, final: float) -> float:
    """Log-linear interpolation from ``start`` (step 0) to ``final`` (step ``total``)."""
    if total <= 0 or start <= 0 or final <= 0:
        return float(start)
    t = min(max(step / total, 0.0), 1.0)
    return float(np.exp((1 - t) * np.log(start) + t * np.log(final)))


@njit(parallel=True, cache=True, fastmath=False)
def _adam_rows(p, g, m, v, lr_cols, n_cols, b1, b2, c1, c2, eps):  # pragma: no cover - compiled
    # one fused pass over (N, C) rows, the first n_cols columns (the rest are inactive:
    # zero gradient and zero moments, so their update is exactly zero)
    for i in prange(p.shape[0]):
        for j in range(n_cols):
            gj = g[i, j]
            mj = b1 * m[i, j] + (1.0 - b1) * gj
            vj = b2 * v[i, j] + (1.0 - b2) * gj * gj
            m[i, j] = mj
            v[i, j] = vj
            p[i, j] -= lr_cols[j] * (mj / c1) / (np.sqrt(vj / c2) + eps)


class Adam:
    """Adam with bias correction over ``{name: (N, ...) float32 array}``.

    ``step(params, grads, lrs)`` updates ``params`` in place: for each name,
    m ← β1 m + (1−β1) g, v ← β2 v + (1−β2) g², p ← p − lr · m̂ / (√v̂ + ε), with
    m̂ = m / (1 − β1ᵗ), v̂ = v / (1 − β2ᵗ), t the number of steps taken (shared by
    every row, as in the 3DGS practice of resetting rows only through densification).
    ε defaults to 1e-15 (3DGS): gradients here are small per-surfel means.
    """

    def __init__(self, params: dict[str, np.ndarray], *, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15):
        self.beta1, self.beta2, self.eps = float(beta1), float(beta2), float(eps)
        self.t = 0
        self.m = {k: np.zeros_like(v, dtype=np.float32) for k, v in params.items()}
        self.v = {k: np.zeros_like(v, dtype=np.float32) for k, v in params.items()}

    def step(
        self,
        params: dict[str, np.ndarray],
        grads: dict[str, np.ndarray],
        lrs: dict[str, float | np.ndarray],
        *,
        active_cols: dict[str, int] | None = None,
    ) -> None:
        """One step; a learning rate is a float or an array broadcasting against one
        row of its parameter (per SH coefficient, say). ``active_cols[k]``: only the
        first so many entries of each flattened row of ``k`` are stepped (SH degrees not
        yet grown, whose gradients and moments are zero, so skipping them changes
        nothing)."""
        self.t += 1
        b1, b2 = self.beta1, self.beta2
        c1 = 1.0 - b1**self.t
        c2 = 1.0 - b2**self.t
        for k, p in params.items():
            g = grads.get(k)
            if g is None:
                continue
            if g.shape != p.shape:
                raise InputError(f"Adam: gradient of {k!r} is {g.shape}, parameter {p.shape}")
            if not (p.flags.c_contiguous and p.dtype == np.float32):
                raise InputError(f"Adam: parameter {k!r} must be C-contiguous float32")
            n = p.shape[0]
            p2 = p.reshape(n, -1)
            C = p2.shape[1]
            lr = (
                np.broadcast_to(np.asarray(lrs[k], np.float32), p.shape[1:]).reshape(-1)
                if p.ndim > 1
                else (np.asarray(lrs[k], np.float32).reshape(1))
            )
            n_cols = C if active_cols is None or k not in active_cols else int(active_cols[k])
            _adam_rows(
                p2,
                np.ascontiguousarray(g, np.float32).reshape(n, -1),
                self.m[k].reshape(n, -1),
                self.v[k].reshape(n, -1),
                np.ascontiguousarray(lr, np.float32),
                n_cols,
                np.float32(b1),
                np.float32(b2),
                np.float32(c1),
                np.float32(c2),
                np.float32(self.eps),
            )

    def keep(self, rows: np.ndarray) -> None:
        """Keep the rows ``rows`` selects: a boolean mask (pruning) or indices (a new order)."""
        for d in (self.m, self.v):
            for k in d:
                d[k] = np.ascontiguousarray(d[k][rows])

    def append(self, n: int) -> None:
        """Add ``n`` rows of zero moments (new surfels start with a fresh state)."""
        for d in (self.m, self.v):
            for k in d:
                d[k] = np.concatenate([d[k], np.zeros((n, *d[k].shape[1:]), np.float32)])

    def state(self) -> dict[str, np.ndarray]:
        """The moments and step count as flat arrays (for a checkpoint)."""
        out: dict[str, np.ndarray] = {"adam_t": np.array(self.t, np.int64)}
        for k in self.m:
            out[f"adam_m_{k}"] = self.m[k]
            out[f"adam_v_{k}"] = self.v[k]
        return out

    def load(self, state: dict[str, np.ndarray]) -> None:
        self.t = int(state["adam_t"])
        for k in self.m:
            self.m[k] = np.asarray(state[f"adam_m_{k}"], np.float32).copy()
            self.v[k] = np.asarray(state[f"adam_v_{k}"], np.float32).copy()
