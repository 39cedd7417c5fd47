"""Reading an EXR the way a user's tools do (the OpenEXR package, not opacityhull's
reader) and compositing it under the file's stated alpha convention (#33)."""

from __future__ import annotations

import numpy as np

from opacityhull.imageio import srgb_encode


def read_rgba_openexr(path) -> tuple[np.ndarray, dict]:
    """(H, W, 4) float32 RGBA and the header of an EXR, through OpenEXR itself."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = {k: np.asarray(v.pixels, np.float32) for k, v in f.channels().items()}
        header = dict(f.header())
    assert set("RGBA") <= set(ch), f"{path}: channels {sorted(ch)}, expected an RGBA file"
    return np.stack([ch[c] for c in "RGBA"], axis=-1), header


def over_premultiplied(path, background) -> np.ndarray:
    """The EXR at ``path`` composited over ``background`` (RGB or (H, W, 3)), as a
    compositor does for a file that states ``opacityhull:alpha = "premultiplied"``
    (the assertion fails for a file without it)."""
    rgba, header = read_rgba_openexr(path)
    assert header.get("opacityhull:alpha") == "premultiplied", f"{path}: header {sorted(header)}"
    return rgba[..., :3] + (1.0 - rgba[..., 3:4]) * np.asarray(background, np.float32)


def srgb8(linear) -> np.ndarray:
    """Linear [0, 1] → sRGB codes 0..255 as float (what an 8-bit PNG stores)."""
    return np.round(srgb_encode(np.clip(linear, 0.0, 1.0)) * 255.0)
