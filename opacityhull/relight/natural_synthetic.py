"""Synthetic light transport with exact ground truth for :mod:`.natural`.

Transport rows ``T_i`` over an ``H_d × W_d`` display domain, of the kinds Pfister's
"Kernel Subdivisions" slide shows:

* ``"boxes"`` — one or two quad-tree-aligned boxes of ½ … ⅛ of the display per axis
  (at most 12 splits isolate them, so the K = 25 subdivision can represent them exactly);
* ``"diffuse"`` — a broad smooth lobe (σ ≈ ⅓ of the display) plus a constant floor;
* ``"glossy"`` — a narrow lobe (σ ≈ 1/16 of the display) on a weak diffuse floor;
* ``"refraction"`` — a very narrow lobe (σ ≈ 0.6 display px, most energy in a 2×2 px
  spot) displaced from where the pixel "looks" (it is a shifted glass-like path);
* ``"shadowed"`` — a diffuse lobe with a rectangular region (an occluder) set to zero.

Each row sums to an albedo in (0, 1] (the fraction of the display's mean radiance that
reaches the pixel). Illumination images: random-phase 1/f noise
(:func:`opacityhull.acquire.patterns.natural_image`) and crops / rotations of the
shipped HDR probes exposed and clipped to the display's [0, 1]; and the moving white bar.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = [
    "KINDS",
    "transport_row",
    "transport_rows",
    "noise_images",
    "probe_crops",
    "natural_images",
    "glass_scene",
    "white_bar",
    "apply_transport",
]

KINDS = ("boxes", "diffuse", "glossy", "refraction", "shadowed")


def _gauss(H, W, cx, cy, sigma):
    y, x = np.mgrid[0:H, 0:W] + 0.5
    return np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))


def _dyadic_box(rng, H, W, min_level=1, max_level=4):
    lx, ly = rng.integers(min_level, max_level + 1, size=2)
    w, h = max(W >> int(lx), 1), max(H >> int(ly), 1)
    x0 = int(rng.integers(0, W // w)) * w
    y0 = int(rng.integers(0, H // h)) * h
    return x0, y0, x0 + w, y0 + h


def transport_row(kind: str, rng: np.random.Generator, *, height: int, width: int) -> np.ndarray:
    """One transport row of a given kind, float64 (height, width), non-negative.

    ``T.sum()`` is the pixel's response to a uniform display of radiance 1.
    """
    H, W = int(height), int(width)
    if kind not in KINDS:
        raise InputError(f"unknown transport kind {kind!r}; choose one of {', '.join(KINDS)}")
    if kind == "boxes":
        T = np.zeros((H, W))
        for _ in range(int(rng.integers(1, 3))):
            x0, y0, x1, y1 = _dyadic_box(rng, H, W, 1, 3)
            T[y0:y1, x0:x1] += rng.uniform(0.2, 1.0) / ((x1 - x0) * (y1 - y0))
    elif kind == "diffuse":
        cx, cy = rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * H
        T = _gauss(H, W, cx, cy, rng.uniform(0.25, 0.4) * max(H, W)) + 0.2
    elif kind == "glossy":
        cx, cy = rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * H
        g = _gauss(H, W, cx, cy, max(H, W) / 16)
        T = g / g.sum() * 0.6 + 0.1 / (H * W)
    elif kind == "refraction":
        cx, cy = rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * H
        g = _gauss(H, W, cx, cy, 0.6)
        T = g / g.sum() * 0.9
    else:  # shadowed
        cx, cy = rng.uniform(0.3, 0.7) * W, rng.uniform(0.3, 0.7) * H
        T = _gauss(H, W, cx, cy, rng.uniform(0.25, 0.4) * max(H, W)) + 0.1
        x0, y0 = int(rng.integers(0, W // 2)), int(rng.integers(0, H // 2))
        T[y0 : y0 + H // 2, x0 : x0 + W // 2] = 0.0
    T = T / T.sum() * (rng.uniform(0.3, 0.9) if kind != "refraction" else 0.9)
    return T


def transport_rows(kinds, rng: np.random.Generator, *, height: int, width: int) -> np.ndarray:
    """Rows for a sequence of kinds: float64 (P, height, width)."""
    return np.stack([transport_row(k, rng, height=height, width=width) for k in kinds])


def noise_images(n: int, rng: np.random.Generator, *, height: int, width: int) -> np.ndarray:
    """n 1/f noise images, linear float64 (n, height, width, 3), mean ≈ 0.5."""
    from ..acquire.patterns import natural_image

    if n < 0:
        raise InputError(f"n={n} images: expected ≥ 0")
    out = np.empty((n, height, width, 3))
    for j in range(n):
        out[j] = natural_image(rng, width=width, height=height) / 255.0
    return out


def probe_crops(n: int, rng: np.random.Generator, *, height: int, width: int) -> np.ndarray:
    """n random crops (random probe, position, scale, quarter rotation, mirror) of the
    shipped HDR probes, linear float64 (n, height, width, 3), as a display shows them:
    exposed so the crop's mean is 0.4 of the display's white, then clipped to [0, 1]
    (a display cannot show the sun; unclipped, a few crops with peaks of 50× white
    dominate the least squares)."""
    import cv2

    from ..data import PROBE_NAMES, probe_path
    from ..imageio import read_hdr

    probes = [np.asarray(read_hdr(probe_path(p)), dtype=np.float32) for p in PROBE_NAMES]
    out = np.empty((n, height, width, 3))
    for j in range(n):
        img = probes[int(rng.integers(len(probes)))]
        if rng.integers(2):
            img = img[:, ::-1]
        img = np.rot90(img, int(rng.integers(4)))
        ph, pw = img.shape[:2]
        s = rng.uniform(0.25, 0.9)
        ch, cw = max(int(ph * s), 2), max(int(pw * s * width / max(height, 1) * ph / pw), 2)
        cw = min(cw, pw)
        y0, x0 = int(rng.integers(0, ph - ch + 1)), int(rng.integers(0, pw - cw + 1))
        crop = np.ascontiguousarray(img[y0 : y0 + ch, x0 : x0 + cw])
        crop = cv2.resize(crop, (width, height), interpolation=cv2.INTER_AREA).astype(np.float64)
        out[j] = np.clip(crop / max(float(crop.mean()), 1e-12) * 0.4, 0.0, 1.0)
    return out


def natural_images(
    n: int, rng: np.random.Generator, *, height: int, width: int, probe_fraction: float = 0.5
) -> np.ndarray:
    """A shuffled mix of 1/f noise and probe crops, float64 (n, height, width, 3)."""
    n_probe = int(round(n * probe_fraction))
    imgs = np.concatenate(
        [
            noise_images(n - n_probe, rng, height=height, width=width),
            probe_crops(n_probe, rng, height=height, width=width),
        ]
    )
    return imgs[rng.permutation(n)]


def white_bar(
    position: int, n_positions: int, *, height: int, width: int, bar_fraction: float = 0.125, value: float = 1.0
) -> np.ndarray:
    """The moving white bar: a vertical bar ``bar_fraction`` of the width on black, at
    step ``position`` of ``n_positions`` evenly spaced from the left to the right edge.

    Returns float64 (height, width, 3).
    """
    if n_positions < 1 or not (0 <= position < n_positions):
        raise InputError(f"bar position {position} of {n_positions}: expected 0 ≤ position < n_positions")
    bw = max(int(round(width * bar_fraction)), 1)
    span = width - bw
    x0 = int(round(position * span / max(n_positions - 1, 1)))
    img = np.zeros((height, width, 3))
    img[:, x0 : x0 + bw] = value
    return img


def apply_transport(T: np.ndarray, images: np.ndarray) -> np.ndarray:
    """``B = T L`` per channel: T (P, H, W), images (N, H, W, C) → (N, P, C)."""
    return np.einsum("phw,nhwc->npc", T, images, optimize=True)


def glass_scene(rng: np.random.Generator, *, height: int = 24, width: int = 32, domain_hw=(32, 32)) -> np.ndarray:
    """A camera image of a glass ball in front of the display, as transport rows.

    Pixels outside the ball see the display directly (a 1-pixel spot: the backdrop);
    inside, a ball of radius ⅓ of the image height refracts an inverted, magnified
    spot (σ = 0.6 display px, transmittance 0.85) plus a 4 % Fresnel reflection of a
    glossy patch near the display's top; the bottom sixth is a diffuse table lit by the
    whole lower display. Returns float64 (height·width, H_d, W_d).
    """
    Hd, Wd = (int(v) for v in domain_hw)
    T = np.zeros((height, width, Hd, Wd))
    cy, cx, r = height * 0.45, width * 0.5, height / 3
    table = int(round(height * 5 / 6))
    for y in range(height):
        for x in range(width):
            px, py = x + 0.5, y + 0.5
            dx, dy = (px - cx) / r, (py - cy) / r
            if y >= table:
                g = _gauss(Hd, Wd, px / width * Wd, Hd * 0.9, Wd * 0.35)
                T[y, x] = g / g.sum() * 0.5
            elif dx * dx + dy * dy < 1.0:
                # refraction: inverted and magnified about the centre of the display
                sx = Wd * 0.5 - 1.6 * dx * Wd * 0.25
                sy = Hd * 0.5 - 1.6 * dy * Hd * 0.25
                g = _gauss(Hd, Wd, sx, sy, 0.6)
                T[y, x] = g / g.sum() * 0.85
                g = _gauss(Hd, Wd, Wd * (0.5 + 0.3 * dx), Hd * 0.12, Wd / 16)
                T[y, x] += g / g.sum() * 0.04
            else:
                T[y, x, min(int(py / height * Hd), Hd - 1), min(int(px / width * Wd), Wd - 1)] = 1.0
    return T.reshape(height * width, Hd, Wd)
