"""The fitted splats of a model built with ``--optimize`` in the viewer bundle
(``splats.bin``, the manifest's ``splats``; layout in ``docs/viewer-format.md``).

The page draws them as the fitting's rasterizer does (:mod:`opacityhull.optimize.raster`):
each splat an oriented Gaussian disc, projected with the local affine approximation to
the screen covariance ``J W Σ Wᵀ Jᵀ + lowpass·I``, cut at ``cutoff`` σ, with
``α = min(0.99, o·G)`` (fragments under 1/255 dropped), composited in depth order — on
the GPU back to front with premultiplied blending, which is the CPU's front-to-back sum
without its early stop at transmittance 10⁻⁴. The colour is the fitted SH of the
camera's direction in the display space (3DGS's convention), decoded to linear after
compositing, as :func:`opacityhull.optimize.fit.render_params` does.

What the page would pay for per frame is done here once: the quaternion and the log
scales become the two scaled tangent axes, the opacity logit its sigmoid.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import FormatError

__all__ = ["SPLAT_HEAD", "splat_records", "write_splats", "read_splats"]

#: Floats of a record before the SH coefficients: mean (3), opacity, axis u (3), axis v (3).
SPLAT_HEAD = 10


def splat_records(params: dict[str, np.ndarray]) -> tuple[np.ndarray, int]:
    """(N, 4·T) float32 records and T, the RGBA32F texels per splat: ``mean xyz``,
    ``opacity`` (sigmoid of the logit), ``u xyz`` = σ_u · the first tangent axis, ``v xyz``
    = σ_v · the second (the columns 0 and 1 of the normalised quaternion's rotation, m),
    then the SH coefficients coefficient-major (``10 + 3j + c``: coefficient j of
    channel c), zero-padded to whole texels."""
    q = np.asarray(params["quats"], np.float64)
    n = np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)  # the rasterizer's guard
    w, x, y, z = (q / n).T
    a = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=1)
    b = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], axis=1)
    s = np.exp(np.asarray(params["log_scales"], np.float64))
    sh = np.asarray(params["sh"], np.float32)
    N, B = sh.shape[:2]
    T = -(-(SPLAT_HEAD + 3 * B) // 4)
    rec = np.zeros((N, 4 * T), np.float32)
    rec[:, 0:3] = params["means"]
    rec[:, 3] = 1.0 / (1.0 + np.exp(-np.asarray(params["opacity_logits"], np.float64)))
    rec[:, 4:7] = a * s[:, :1]
    rec[:, 7:10] = b * s[:, 1:2]
    rec[:, SPLAT_HEAD : SPLAT_HEAD + 3 * B] = sh.reshape(N, 3 * B)
    return rec, T


def write_splats(tmp: Path, model_root: Path) -> dict:
    """Write ``splats.bin`` of the model's fitted splats into the bundle folder ``tmp``
    and add ``splats`` to its ``manifest.json``; returns that entry."""
    from ..optimize.raster import RasterConfig
    from ..render.splats import FittedSplats

    fs = FittedSplats.load(Path(model_root))
    rec, T = splat_records(fs.params)
    data = np.ascontiguousarray(rec, "<f4").tobytes()
    (tmp / "splats.bin").write_bytes(data)
    rc = RasterConfig()
    meta = {
        "file": "splats.bin",
        "count": len(rec),
        "bytes": len(data),
        "texels": T,
        "sh_degree": fs.sh_degree,
        "lowpass_px2": rc.lowpass_px2,
        "cutoff_sigma": rc.cutoff_sigma,
        "near_m": rc.near_m,
        "alpha_min": rc.alpha_min,
        "alpha_max": 0.99,
        "encoding": "float32 records of 4*texels: mean xyz (m), opacity, u xyz, v xyz (scaled tangent axes, m), "
        "SH coefficient-major (display space, 3DGS convention)",
    }
    mp = tmp / "manifest.json"
    man = json.loads(mp.read_text())
    man["splats"] = meta
    mp.write_text(json.dumps(man, indent=1) + "\n")
    return meta


def read_splats(bundle_dir) -> tuple[dict, np.ndarray]:
    """(the manifest's ``splats`` entry, (N, 4·texels) float32 records) of a bundle; a
    :class:`FormatError` for a bundle without fitted splats or a damaged ``splats.bin``."""
    root = Path(bundle_dir)
    man = json.loads((root / "manifest.json").read_text())
    meta = man.get("splats")
    if not isinstance(meta, dict):
        raise FormatError(f"{root}/manifest.json: no fitted splats (the model was not built with --optimize)")
    raw = (root / meta["file"]).read_bytes()
    F = 4 * int(meta["texels"])
    if len(raw) != 4 * F * int(meta["count"]):
        raise FormatError(f"{root}/{meta['file']}: {len(raw)} bytes, expected {4 * F * int(meta['count'])}")
    return meta, np.frombuffer(raw, "<f4").reshape(-1, F)
