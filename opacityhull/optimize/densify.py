"""Adaptive density control (3DGS practice, on surfels): clone small surfels and split
large ones where the view-space positional gradient is large, prune transparent and
oversized ones."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .adam import Adam
from .surfelparams import quat_to_rotmat, sigmoid

__all__ = ["GradStats", "DensifyResult", "densify_and_prune"]

SPLIT_COPIES = 2
SPLIT_SHRINK = 1.6  # a split surfel's copies are 1/1.6 its size (3DGS)


class GradStats:
    """Running sum of each surfel's |∂L/∂(2-D mean)| over the views that saw it."""

    def __init__(self, n: int):
        self.accum = np.zeros(n, np.float64)
        self.count = np.zeros(n, np.int64)

    def add(self, grad_ndc: np.ndarray, visible: np.ndarray) -> None:
        self.accum[visible] += grad_ndc[visible]
        self.count[visible] += 1

    def mean(self) -> np.ndarray:
        return self.accum / np.maximum(self.count, 1)


@dataclass(frozen=True)
class DensifyResult:
    n_cloned: int
    n_split: int
    n_pruned: int
    n_after: int


def densify_and_prune(
    params: dict[str, np.ndarray],
    adam: Adam,
    stats: GradStats,
    *,
    grad_threshold: float,
    scale_limit_m: float,
    prune_opacity: float,
    prune_scale_m: float,
    max_surfels: int,
    rng: np.random.Generator,
) -> tuple[dict[str, np.ndarray], DensifyResult]:
    """One densification: returns the new parameters (the optimizer's rows follow).

    A surfel whose mean gradient is ≥ ``grad_threshold`` is cloned (an identical copy,
    which the next steps pull apart) if its largest std-dev is ≤ ``scale_limit_m``, or
    else split into two copies drawn from its own tangent Gaussian, each
    1/1.6 its size. Then surfels with opacity < ``prune_opacity`` or a std-dev above
    ``prune_scale_m`` are removed (never the last one). New surfels are only added
    while the count stays ≤ ``max_surfels``.
    """
    N = len(params["means"])
    g = stats.mean()
    scale = np.exp(params["log_scales"].astype(np.float64)).max(axis=1)
    hot = g >= grad_threshold
    room = max(0, int(max_surfels) - N)
    hot_idx = np.flatnonzero(hot)
    if hot_idx.size > room:  # the strongest gradients first, ties by index
        order = np.lexsort((hot_idx, -g[hot_idx]))
        hot_idx = np.sort(hot_idx[order[:room]])
    clone = hot_idx[scale[hot_idx] <= scale_limit_m]
    split = hot_idx[scale[hot_idx] > scale_limit_m]
    if split.size and room < clone.size + split.size * SPLIT_COPIES:
        split = split[: max(0, (room - clone.size) // SPLIT_COPIES)]
    new: dict[str, list[np.ndarray]] = {k: [v] for k, v in params.items()}
    for k, v in params.items():
        new[k].append(v[clone])
    if split.size:
        R = quat_to_rotmat(params["quats"][split])
        s = np.exp(params["log_scales"][split].astype(np.float64))
        for _ in range(SPLIT_COPIES):
            z = rng.standard_normal((split.size, 2)) * s
            off = R[:, :, 0] * z[:, :1] + R[:, :, 1] * z[:, 1:2]
            for k, v in params.items():
                if k == "means":
                    new[k].append((v[split] + off).astype(np.float32))
                elif k == "log_scales":
                    new[k].append((v[split] - np.float32(np.log(SPLIT_SHRINK))).astype(np.float32))
                else:
                    new[k].append(v[split])
    out = {k: np.concatenate(v) for k, v in new.items()}
    n_new = len(out["means"]) - N
    adam.append(n_new)
    keep = np.ones(len(out["means"]), bool)
    keep[split] = False  # a split surfel is replaced by its copies
    alpha = sigmoid(out["opacity_logits"])
    big = np.exp(out["log_scales"].astype(np.float64)).max(axis=1) > prune_scale_m
    keep &= ~((alpha < prune_opacity) | big)
    if not keep.any():
        keep[np.argmax(alpha)] = True
    out = {k: v[keep] for k, v in out.items()}
    adam.keep(keep)
    n_pruned = int(N + n_new - keep.sum() - split.size)
    return out, DensifyResult(int(clone.size), int(split.size), n_pruned, len(out["means"]))
