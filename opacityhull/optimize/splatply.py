"""The fitted surfels on disk: a binary PLY in the 3DGS/2DGS layout.

Per vertex, float32: ``x y z`` (m), ``nx ny nz`` (the unit normal, column 2 of the
frame), ``f_dc_0..2`` (SH DC per channel), ``f_rest_*`` (the other coefficients,
channel-major: ``f_rest_{c·(B−1) + j}`` is coefficient j+1 of channel c, as 3DGS writes
them), ``opacity`` (logit), ``scale_0 scale_1`` (log tangent std-devs, m: 2DGS's two
scales), ``rot_0..3`` (quaternion wxyz). Colours are in the display (sRGB-encoded)
space with the 3DGS ½ offset, so a splat viewer opens the file as it is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..imageio import atomic_path
from .surfelparams import normals_of

__all__ = ["write_splat_ply", "read_splat_ply"]


def write_splat_ply(path: Path, params: dict[str, np.ndarray]) -> None:
    """Write ``params`` (:data:`~opacityhull.optimize.surfelparams.PARAM_NAMES`) to ``path``."""
    from plyfile import PlyData, PlyElement

    means = params["means"]
    N = len(means)
    sh = params["sh"]
    cols: list[tuple[str, np.ndarray]] = [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
    nrm = normals_of(params["quats"])
    cols += [("nx", nrm[:, 0]), ("ny", nrm[:, 1]), ("nz", nrm[:, 2])]
    cols += [(f"f_dc_{c}", sh[:, 0, c]) for c in range(3)]
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(N, -1)
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    cols += [("opacity", params["opacity_logits"])]
    cols += [(f"scale_{i}", params["log_scales"][:, i]) for i in range(2)]
    cols += [(f"rot_{i}", params["quats"][:, i]) for i in range(4)]
    arr = np.empty(N, dtype=[(n, "<f4") for n, _ in cols])
    for n, v in cols:
        arr[n] = v
    with atomic_path(Path(path)) as tmp:
        PlyData([PlyElement.describe(arr, "vertex")], text=False).write(str(tmp))


def read_splat_ply(path: Path) -> dict[str, np.ndarray]:
    """The parameters written by :func:`write_splat_ply` (a :class:`FormatError` naming
    the file and the missing property otherwise)."""
    from plyfile import PlyData

    path = Path(path)
    try:
        v = PlyData.read(str(path))["vertex"].data
    except (OSError, ValueError, KeyError) as e:
        raise FormatError(f"{path}: not a splat PLY ({e})") from None
    names = set(v.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1"] + [
        f"rot_{i}" for i in range(4)
    ]
    missing = [n for n in need if n not in names]
    if missing:
        raise FormatError(f"{path}: splat PLY lacks {', '.join(missing)}")
    n_rest = sum(1 for n in names if n.startswith("f_rest_"))
    if n_rest % 3 or int(round(np.sqrt(n_rest // 3 + 1))) ** 2 != n_rest // 3 + 1:
        raise FormatError(f"{path}: {n_rest} f_rest_* properties is not 3·((d+1)²−1) for an SH degree d ≤ 3")
    N = len(v)
    B = n_rest // 3 + 1
    sh = np.zeros((N, B, 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = v[f"f_dc_{c}"]
    if B > 1:
        rest = np.stack([v[f"f_rest_{i}"] for i in range(n_rest)], axis=1).reshape(N, 3, B - 1)
        sh[:, 1:, :] = np.transpose(rest, (0, 2, 1))
    f = np.float32
    return {
        "means": np.stack([v["x"], v["y"], v["z"]], axis=1).astype(f),
        "quats": np.stack([v[f"rot_{i}"] for i in range(4)], axis=1).astype(f),
        "log_scales": np.stack([v["scale_0"], v["scale_1"]], axis=1).astype(f),
        "opacity_logits": np.asarray(v["opacity"], f),
        "sh": sh,
    }
