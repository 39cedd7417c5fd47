"""Two-backdrop (or K-backdrop) matting of image files: the runner of ``opacityhull matte``.

Reads K object shots and the K backdrop shots (same view, object absent) as images
(JPEG/PNG are sRGB-decoded to linear, EXR/HDR are linear), corrects photometric drift
(:func:`.matting.correct_photometric_drift`), solves the matte and writes:

- ``alpha.png`` — 16-bit, linear alpha;
- ``foreground_premul.png`` (16-bit, sRGB-encoded) and ``foreground_premul.exr`` (float
  linear RGBA, the alpha in its A channel): the premultiplied foreground ``alpha F``;
- ``composite.png`` — ``alpha F + (1 - alpha) over`` when a new background is given;
- ``matte.json`` — statistics, the drift and the registration per shot; written last, so
  a folder without it is an unfinished run.

Everything is computed before the first file is written.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..errors import FormatError, InputError

log = logging.getLogger(__name__)

__all__ = ["matte_files", "load_rgb", "matte_stats", "IDENTICAL_BACKDROP_LEVEL"]

#: backdrops whose per-pixel spread (RMS over shots and channels, linear radiance) stays
#: below this at the 99th percentile are "identical": alpha is unobservable everywhere
IDENTICAL_BACKDROP_LEVEL = 2e-3


#: The files ``matte`` writes into ``--out``.
MATTE_FILES = ("alpha.png", "foreground_premul.png", "foreground_premul.exr", "composite.png", "matte.json")


def load_rgb(path, flag: str) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an image file; errors name the flag and the file."""
    from ..imageio import read_image

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{flag} {p}: no such file")
    try:
        a = read_image(p)
    except FormatError as e:
        raise InputError(f"{flag} {p}: not a readable image ({e})") from None
    except InputError as e:
        raise InputError(f"{flag} {p}: {e}") from None
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[2] in (1, 2):
        a = np.repeat(a[..., :1], 3, axis=2)
    return np.ascontiguousarray(a[..., :3], dtype=np.float32)


def matte_stats(alpha) -> dict:
    """Fractions of clear (alpha < 0.05), opaque (> 0.95) and fractional pixels."""
    a = np.asarray(alpha)
    clear = float(np.mean(a < 0.05))
    opaque = float(np.mean(a > 0.95))
    return {"clear_fraction": clear, "opaque_fraction": opaque, "fractional_fraction": 1.0 - clear - opaque}


def matte_files(
    object_paths, backdrop_paths, out_dir, *, over=None, drift: str = "field", max_alpha_std: float | None = None
) -> dict:
    """Matte K (object, backdrop) image pairs and write the results to ``out_dir``.

    Parameters
    ----------
    object_paths, backdrop_paths : sequences of K >= 2 paths, pair k = (object k, backdrop k).
    out_dir : folder to write (created).
    over : optional path of a new background; resized (area) to the shots' size if it differs.
    drift : "none" | "gain" | "affine" | "field" (see :class:`.matting.MattingOptions`).
    max_alpha_std : see :class:`.matting.MattingOptions` (None: its default).

    Returns
    -------
    dict, the content of ``matte.json``.
    """
    import cv2

    from ..imageio import write_exr, write_png
    from .matting import MattingOptions, solve_matte

    t0 = time.perf_counter()
    obj, back = [Path(p) for p in object_paths], [Path(p) for p in backdrop_paths]
    if len(obj) != len(back):
        raise InputError(
            f"--object got {len(obj)} images but --backdrop got {len(back)}: pair k is "
            "(object k, backdrop k), the counts must match"
        )
    if len(obj) < 2:
        raise InputError(f"triangulation matting needs at least 2 (object, backdrop) pairs, got {len(obj)}")
    from ..outputs import check_output

    inputs = {f"--object {p}": p for p in obj} | {f"--backdrop {p}": p for p in back} | {"--over": over}
    check_output(out_dir, inputs, writes=MATTE_FILES)
    # MattingOptions checks drift against DriftMode (ConfigError naming the value)
    opts = MattingOptions(
        drift=cast(Any, drift), max_alpha_std=MattingOptions().max_alpha_std if max_alpha_std is None else max_alpha_std
    )
    C = [load_rgb(p, "--object") for p in obj]
    B = [load_rgb(p, "--backdrop") for p in back]
    ref_shape = C[0].shape
    for flag, paths, ims in (("--object", obj, C), ("--backdrop", back, B)):
        for p, im in zip(paths, ims, strict=True):
            if im.shape != ref_shape:
                raise InputError(
                    f"{flag} {p}: size {im.shape[1]}x{im.shape[0]} differs from {obj[0]} "
                    f"({ref_shape[1]}x{ref_shape[0]}); every shot must be the same view"
                )
    C, B = np.stack(C), np.stack(B)
    spread = np.sqrt(np.mean((B - B.mean(axis=0)) ** 2, axis=(0, 3)))
    p99 = float(np.percentile(spread, 99))
    if not p99 > IDENTICAL_BACKDROP_LEVEL:
        raise InputError(
            f"--backdrop {', '.join(map(str, back))}: the backdrops are identical (99th percentile "
            f"of their per-pixel spread {p99:.2e} <= {IDENTICAL_BACKDROP_LEVEL:g}); alpha is "
            "unobservable, shoot the object in front of backdrops that differ"
        )
    bg = None
    notes = []
    if over is not None:
        bg = load_rgb(over, "--over")
        if bg.shape != ref_shape:
            notes.append(f"--over {over}: resized from {bg.shape[1]}x{bg.shape[0]} to {ref_shape[1]}x{ref_shape[0]}")
            bg = cv2.resize(bg, (ref_shape[1], ref_shape[0]), interpolation=cv2.INTER_AREA)
    r = solve_matte(C, B, options=opts)
    comp = None if bg is None else r.fg_premul + (1.0 - r.alpha[..., None]) * bg
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "alpha": out / "alpha.png",
        "foreground_premul_png": out / "foreground_premul.png",
        "foreground_premul_exr": out / "foreground_premul.exr",
    }
    write_png(files["alpha"], r.alpha, bits=16, linear=True)
    write_png(files["foreground_premul_png"], np.clip(r.fg_premul, 0.0, 1.0), bits=16)
    write_exr(files["foreground_premul_exr"], np.concatenate([r.fg_premul, r.alpha[..., None]], axis=-1))
    if comp is not None:
        files["composite"] = out / "composite.png"
        write_png(files["composite"], np.clip(comp, 0.0, 1.0))
    summary = {
        "out": str(out),
        "width": int(ref_shape[1]),
        "height": int(ref_shape[0]),
        "pairs": len(obj),
        "objects": [str(p) for p in obj],
        "backdrops": [str(p) for p in back],
        **matte_stats(r.alpha),
        "unknown_fraction": float(np.mean(r.unknown)),
        "noise_sigma": float(r.noise_sigma),
        "drift": None if r.drift is None else r.drift.to_dict(),
        "registration_px": [s.shift_px for s in r.drift.shots] if r.drift else [None] * len(obj),
        "files": {k: str(v) for k, v in files.items()},
        "notes": notes,
        "seconds": time.perf_counter() - t0,
    }
    from ..jsonio import to_jsonable
    from ..imageio import atomic_path

    files_json = out / "matte.json"
    with atomic_path(files_json) as tmp:
        tmp.write_text(json.dumps(to_jsonable(summary), indent=1) + "\n")
    summary["files"]["stats"] = str(files_json)
    log.info("matte of %d pairs written to %s (%.1f s)", len(obj), out, summary["seconds"])
    return summary
