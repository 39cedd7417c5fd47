"""Backdrop patterns shown on the plasma displays, generated from the plan's seeds.

* Matting: K random colour patterns and their complements (``255 - p``). Triangulation
  matting degenerates where two backdrops are alike at a pixel, and its alpha noise
  scales as 1/‖B₁ − B₂‖ (PITFALLS.md); a pattern and its complement differ at every
  pixel, and drawing each channel from [0, 63] ∪ [192, 255] keeps that difference at
  least 129 of 255 per channel. Pattern j (1-based) has id ``2j - 1``, its complement
  ``2j``. "Backdrops off" is not a pattern: the displays are blanked.
* Natural illumination (``[phases.natural]``, older name ``envmatte``): N images per
  illumination domain — crops / rotations / mirrors of the shipped HDR probes, exposed
  so the crop's mean is 0.4 of white and clipped to the display's range (a display
  cannot show the sun), random-phase 1/f noise (whose amplitude spectrum matches that
  of natural scenes), and images the plan points at. Each display is its own domain:
  pattern ``first + i·N + k`` is image k on display i and black on every other display,
  so one id shown "on every display" (what the runner does) lights one domain only.

Every pattern exists once per display, at the display's pattern resolution
(``geometry.displays[].resolution``), as uint8 ``(rows, cols, 3)`` drive values —
exactly the bytes uploaded and saved as ``patterns/<display>/p<id>.png``.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..riggeometry import RigGeometry
from .plan import CapturePlan
from .schedule import natural_pattern_ids

__all__ = [
    "Pattern",
    "random_pattern",
    "complement",
    "natural_image",
    "probe_crop",
    "plan_patterns",
    "save_patterns",
    "check_saved_patterns",
    "pattern_path",
    "natural_domain",
]


@dataclass(frozen=True)
class Pattern:
    """One pattern id: what it is and its image per display."""

    id: int
    kind: str  # "random" | "complement" | "natural"
    phase: str
    images: dict = field(default_factory=dict, compare=False)  # display -> uint8 (rows, cols, 3)
    of: int | None = None  # complement of this id
    seed: int | None = None
    source: str = ""


def _rng(seed: int, *keys) -> np.random.Generator:
    return np.random.default_rng([int(seed), *[int(k) for k in keys]])


def _display_key(name: str) -> int:
    return zlib.crc32(name.encode())


def random_pattern(rng: np.random.Generator, *, width: int, height: int, cell_px: int = 1) -> np.ndarray:
    """Random colour cells, uint8 (height, width, 3).

    Each ``cell_px`` × ``cell_px`` cell gets one colour whose channels are drawn
    uniformly from [0, 63] ∪ [192, 255], so the pattern and its complement differ by
    at least 129 per channel everywhere.
    """
    if width < 1 or height < 1 or cell_px < 1:
        raise InputError(f"pattern size {width}x{height} and cell_px {cell_px} must be positive")
    cw, ch = -(-width // cell_px), -(-height // cell_px)
    low = rng.integers(0, 64, size=(ch, cw, 3))
    high = rng.integers(0, 2, size=(ch, cw, 3)).astype(bool)
    cells = np.where(high, 255 - low, low).astype(np.uint8)
    img = np.repeat(np.repeat(cells, cell_px, axis=0), cell_px, axis=1)
    return np.ascontiguousarray(img[:height, :width])


def complement(pattern: np.ndarray) -> np.ndarray:
    """``255 - p`` (uint8)."""
    p = np.asarray(pattern)
    if p.dtype != np.uint8:
        raise InputError(f"complement needs a uint8 pattern, got {p.dtype}")
    return (255 - p).astype(np.uint8)


def natural_image(rng: np.random.Generator, *, width: int, height: int, beta: float = 1.0) -> np.ndarray:
    """A random natural-looking colour image, uint8 (height, width, 3).

    Random phase with amplitude ∝ 1/f^beta (natural images have beta ≈ 1), a shared
    luminance field plus weaker independent chroma fields, stretched to the 1st–99th
    percentile.
    """
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.rfftfreq(width)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    amp = 1.0 / f**beta
    amp[0, 0] = 0.0

    def field():
        phase = rng.uniform(0, 2 * np.pi, size=amp.shape)
        g = np.fft.irfft2(amp * np.exp(1j * phase), s=(height, width))
        return (g - g.mean()) / (g.std() + 1e-12)

    lum = field()
    img = np.stack([lum + 0.5 * field() for _ in range(3)], axis=-1)
    lo, hi = np.percentile(img, 1), np.percentile(img, 99)
    img = np.clip((img - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return np.round(img * 255).astype(np.uint8)


def _load_natural(path: str, width: int, height: int) -> np.ndarray:
    import cv2

    q = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    if q is None:
        raise FormatError(f"natural image {path}: not a readable image")
    if q.dtype != np.uint8:
        scale = 65535.0 if q.dtype == np.uint16 else 1.0
        q = np.clip(q.astype(np.float64) / scale * 255, 0, 255).round().astype(np.uint8)
    q = cv2.resize(q, (width, height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(q[:, :, ::-1])


_PROBES: list | None = None


def _probes() -> list:
    global _PROBES
    if _PROBES is None:
        from ..data import PROBE_NAMES, probe_path
        from ..imageio import read_hdr

        _PROBES = [(name, np.asarray(read_hdr(probe_path(name)), dtype=np.float32)) for name in PROBE_NAMES]
    return _PROBES


def probe_crop(rng: np.random.Generator, *, width: int, height: int, mean: float = 0.4) -> tuple[np.ndarray, str]:
    """A random crop of a shipped HDR probe as a display shows it, uint8 (height, width, 3).

    Random probe, mirror, quarter rotation, crop scale (¼ … 0.9 of the probe) and
    position; exposed so the crop's mean is ``mean`` of the display's white, then clipped
    to [0, 1] and quantised (linear drive). Returns the image and a description.
    """
    import cv2

    probes = _probes()
    name, img = probes[int(rng.integers(len(probes)))]
    mirror, rot = int(rng.integers(2)), int(rng.integers(4))
    if mirror:
        img = img[:, ::-1]
    img = np.rot90(img, rot)
    ph, pw = img.shape[:2]
    s = rng.uniform(0.25, 0.9)
    ch = max(int(ph * s), 2)
    cw = min(max(int(ch * width / max(height, 1)), 2), pw)
    y0, x0 = int(rng.integers(0, ph - ch + 1)), int(rng.integers(0, pw - cw + 1))
    crop = cv2.resize(
        np.ascontiguousarray(img[y0 : y0 + ch, x0 : x0 + cw]), (width, height), interpolation=cv2.INTER_AREA
    ).astype(np.float64)
    crop = np.clip(crop / max(float(crop.mean()), 1e-12) * mean, 0.0, 1.0)
    return (
        np.round(crop * 255).astype(np.uint8),
        f"probe:{name}:mirror={mirror}:rot={rot * 90}:crop={x0},{y0},{cw}x{ch}",
    )


def _natural_image_for(e, k: int, d, domain_index: int) -> tuple[np.ndarray, str]:
    w, h = d.resolution
    src = e.image_sources()[k]
    rng = _rng(e.seed, k, _display_key(d.name))
    if src.startswith("user:"):
        return _load_natural(src[5:], w, h), src
    if src == "probes":
        return probe_crop(rng, width=w, height=h)
    return natural_image(rng, width=w, height=h), "noise:1/f"


def plan_patterns(plan: CapturePlan, geometry: RigGeometry) -> dict[int, Pattern]:
    """Every pattern the plan shows, per display, generated from the plan's seeds."""
    out: dict[int, Pattern] = {}
    if plan.matting is not None and geometry.displays:
        m = plan.matting
        for j in range(1, m.patterns + 1):
            imgs, comps = {}, {}
            for d in geometry.displays:
                w, h = d.resolution
                imgs[d.name] = random_pattern(
                    _rng(m.seed, j, _display_key(d.name)), width=w, height=h, cell_px=m.cell_px
                )
                comps[d.name] = complement(imgs[d.name])
            out[2 * j - 1] = Pattern(2 * j - 1, "random", "matting", imgs, seed=m.seed)
            out[2 * j] = Pattern(2 * j, "complement", "matting", comps, of=2 * j - 1, seed=m.seed)
    if plan.envmatte is not None and geometry.displays:
        e = plan.envmatte
        by_name = {d.name: d for d in geometry.displays}
        for i, (dname, ids) in enumerate(natural_pattern_ids(plan, geometry).items()):
            for k, pid in enumerate(ids):
                img, src = _natural_image_for(e, k, by_name[dname], i)
                imgs = {
                    d.name: (img if d.name == dname else np.zeros((d.resolution[1], d.resolution[0], 3), np.uint8))
                    for d in geometry.displays
                }
                out[pid] = Pattern(
                    pid,
                    "natural",
                    "envmatte",
                    imgs,
                    seed=None if src.startswith("user:") else e.seed,
                    source=f"{dname}:{src}",
                )
    return out


def natural_domain(session, pattern_id: int) -> str | None:
    """The display a natural pattern of a session lights (the one display whose image is
    not black), from its ``[patterns]`` source (``"<display>:..."``) or, for sessions
    without it, the saved pattern images; None if it lights several (older envmatte)."""
    entry = session.patterns.get(f"p{int(pattern_id):03d}", {})
    files = entry.get("files", {})
    src = str(entry.get("source", ""))
    head = src.split(":", 1)[0]
    if head in files:
        return head
    lit = [d for d in files if np.any(session.pattern_image(d, pattern_id) > 0)]
    return lit[0] if len(lit) == 1 else None


def pattern_path(display: str, pattern_id: int) -> str:
    return f"patterns/{display}/p{int(pattern_id):03d}.png"


def _png_bytes(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:  # pragma: no cover
        raise FormatError("OpenCV could not encode a pattern PNG")
    return buf.tobytes()


def save_patterns(root, patterns: dict[int, Pattern]) -> dict:
    """Write ``patterns/<display>/p<id>.png`` (atomically) and return the
    ``session.toml [patterns]`` table."""
    from ..imageio import atomic_path

    root = Path(root)
    table = {}
    for pid, p in sorted(patterns.items()):
        for dname, img in p.images.items():
            data = _png_bytes(img)
            with atomic_path(root / pattern_path(dname, pid)) as tmp:
                tmp.write_bytes(data)
        table[f"p{pid:03d}"] = pattern_entry(pid, p)
    return table


def pattern_entry(pid: int, p: Pattern, **tables: dict) -> dict:
    """The ``session.toml [patterns]`` entry of pattern ``pid``: its files, ``tables``
    (e.g. ``device_ids``), the SHA-256 of each image's pixels and its provenance."""
    import hashlib

    entry = {
        "id": pid,
        "kind": p.kind,
        "phase": p.phase,
        "files": {d: pattern_path(d, pid) for d in p.images},
        **tables,
        "pixels_sha256": {d: hashlib.sha256(img.tobytes()).hexdigest() for d, img in p.images.items()},
    }
    if p.of is not None:
        entry["of"] = p.of
    if p.seed is not None:
        entry["seed"] = p.seed
    if p.source:
        entry["source"] = p.source
    return entry


def check_saved_patterns(root, patterns: dict[int, Pattern]) -> list[str]:
    """Pattern files of a session that are missing or differ from ``patterns`` (pixel by pixel)."""
    import cv2

    root = Path(root)
    bad = []
    for pid, p in patterns.items():
        for dname, img in p.images.items():
            path = root / pattern_path(dname, pid)
            q = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
            if q is None or q.ndim != 3 or q.shape != img.shape or not np.array_equal(q[:, :, ::-1], img):
                bad.append(pattern_path(dname, pid))
    return bad
