"""A fast analytic session writer: a textured Lambertian sphere on the turntable in front
of the rig's two displays, ray-cast in NumPy (no Mitsuba), written through the real
:class:`opacityhull.session.SessionWriter` with the paper plan's view count (6 cameras ×
72 table angles) at any resolution. For scale tests and benchmarks: hours of path
tracing become seconds to minutes of vectorised NumPy.

What a session holds (every pixel known):

- ``calibration/<camera>.yaml``: the rig's nominal cameras (exact), so ``build`` needs
  no ChArUco phase;
- ``matting``: ``n_pattern_pairs`` random backdrop patterns and their complements, each
  shot with the object and with the object absent (triangulation matting runs on them);
- ``lightfield``: the object under a fixed key light plus ambient, displays dark;
- ``reflectance``: one-light images for ``n_light_dirs`` light directions (4 lights ×
  ``n_light_dirs / 4`` array angles, as the paper's 4 × 15 = 60; else that many lights at
  array angle 0), displays dark, Lambertian ``albedo · 0.85 · max(n·l, 0)``;
- ``groundtruth/`` (optional): the true cameras and coverage alphas.

Images use ``supersample²`` rays per pixel: each ray sees the sphere or, behind it, the
display texel it hits (the bottom panel turns with the table, the back one is fixed), so
the composites and the coverage alpha come from the same rays and the matte is exact up
to the added noise. The ray geometry of a view is computed once and reused by every
pattern and light (a gather and a dot product each). ``tests/reconstruct/rcsynth.py``
builds its richer test scenes (halo, calibration board, hidden views) on the same
functions.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable, Mapping

import numpy as np

from ..camera import Camera, object_from_rig, write_colmap_text, write_opencv_yaml
from ..errors import InputError
from ..imageio import read_png, write_exr, write_png
from ..riggeometry import DisplaySpec, RigGeometry, back_display, bottom_display, view_id
from ..session import SessionWriter, shot_key

log = logging.getLogger(__name__)

__all__ = [
    "SyntheticSessionConfig",
    "write_synthetic_session",
    "sphere_hit_t",
    "sphere_albedo",
    "pixel_rays",
    "panel_hits",
    "panel_texels",
    "record_shot_key",
    "synthetic_rig",
    "CORE_R_M",
    "CENTRE_M",
]

#: Sphere radius and centre (object frame, metres): the analytic object.
CORE_R_M = 0.04
CENTRE_M = np.array([0.0, 0.06, 0.0])


def synthetic_rig(
    n_cams: int = 3,
    width: int = 64,
    height: int = 48,
    *,
    fov_y_deg: float = 20.0,
    distance_m: float = 0.8,
    elevations=(15.0, 55.0),
    n_lights: int = 2,
    display_res: tuple[int, int] = (32, 32),
) -> dict:
    """The ``[rig]`` geometry table of the synthetic rig: ``n_cams`` cameras on an arc of
    ``elevations`` (degrees), ``width × height`` px, two displays (bottom turning with the
    table, back fixed) of ``display_res`` texels (the back one 9/16 as tall), ``n_lights``
    lights on the array (2: the test rig's; otherwise spread in elevation 30–75° and
    azimuth)."""
    els = np.linspace(elevations[0], elevations[1], n_cams) if n_cams > 1 else np.array([elevations[0]])
    cams = [
        {
            "name": f"cam{i}",
            "width": int(width),
            "height": int(height),
            "distance_m": distance_m,
            "elevation_deg": float(e),
            "azimuth_deg": 0.0,
            "fov_y_deg": fov_y_deg,
        }
        for i, e in enumerate(els)
    ]
    if n_lights == 2:
        lights = [
            {"id": 0, "elevation_deg": 40.0, "azimuth_deg": 90.0, "distance_m": 1.0},
            {"id": 1, "elevation_deg": 70.0, "azimuth_deg": -60.0, "distance_m": 1.0},
        ]
    else:
        lights = [
            {
                "id": i,
                "elevation_deg": float(30.0 + 45.0 * i / max(n_lights - 1, 1)),
                "azimuth_deg": float(-180.0 + 360.0 * (i + 0.5) / n_lights),
                "distance_m": 1.0,
            }
            for i in range(n_lights)
        ]
    dw, dh = display_res
    return {
        "target_m": [0.0, 0.06, 0.0],
        "cameras": cams,
        "lights": lights,
        "displays": [
            bottom_display([1.0, 1.0], [int(dw), int(dh)], max_radiance=1.0),
            back_display(
                [0.0, 0.28, -0.4],
                [1.0, 0.56],
                [int(dw), max(1, int(round(dh * 0.5625)))],
                rotates_with_table=False,
                max_radiance=1.0,
            ),
        ],
    }


def pixel_rays(cam: Camera, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (H·W·ss², 3) of ``ss × ss`` stratified rays per pixel,
    pixel-major (the ss² samples of a pixel are contiguous)."""
    return cam.supersampled_rays(ss)


def sphere_hit_t(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """Ray parameter of the first hit of rays (o, d) with the sphere (c, r); inf on a miss."""
    oc = o - c
    b = d @ oc
    cc = oc @ oc - r * r
    disc = b * b - cc
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def sphere_albedo(n: np.ndarray) -> np.ndarray:
    """A smooth colour texture on the sphere, from the object-frame normal (N, 3)."""
    return np.stack(
        [0.35 + 0.25 * np.sin(5 * n[:, 0]), 0.35 + 0.25 * np.cos(4 * n[:, 1]), 0.3 + 0.2 * np.sin(3 * n[:, 2] + 1)],
        axis=1,
    )


@dataclass(frozen=True)
class _DisplayHits:
    """Which display texel each ray sees: per display (ray indices, rows, cols)."""

    hits: dict = field(default_factory=dict)

    def radiance(self, geo: RigGeometry, patterns: dict | None, n: int) -> np.ndarray:
        out = np.zeros((n, 3))
        if patterns is None:
            return out
        for disp in geo.displays:
            pat = patterns.get(disp.name)
            if pat is None or disp.name not in self.hits:
                continue
            idx, row, col = self.hits[disp.name]
            out[idx] = disp.max_radiance * pat[row, col]
        return out


def record_shot_key(phase: str, camera: int, table_deg: float, record: Mapping[str, Any]) -> str:
    """:func:`~opacityhull.session.shot_key` of an image whose record carries ``record``
    (the keyword fields of the manifest entry: ``light``, ``pattern``, ...); fields that
    are not part of the key (``extra``) are ignored, missing ones take its defaults."""
    return shot_key(phase, camera, table_deg, **{k: record[k] for k in _SHOT_KEY_FIELDS if k in record})


_SHOT_KEY_FIELDS = ("lights_deg", "light", "pattern", "object_present")


def panel_hits(
    o: np.ndarray, d: np.ndarray, disp: DisplaySpec, Robj: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where rays (o, d) (object frame) meet the plane of display ``disp``.

    ``Robj`` (3, 3) is :func:`~opacityhull.camera.object_from_rig` at the view's table
    angle: a display fixed in the rig turns by -angle in the object frame, one that
    rotates with the table does not move.

    Returns
    -------
    t : (N,) ray parameter of the plane hit (inf/nan for rays parallel to it).
    x, y : (N,) metres from the panel centre along its right and up axes.
    inside : (N,) bool, a hit in front of the ray origin inside the panel.
    """
    F = disp.frame()
    right, up, nrm, ctr = F[:3, 0], F[:3, 1], F[:3, 2], F[:3, 3]
    if not disp.rotates_with_table:  # fixed in the rig: turns by -a in the object frame
        right, up, nrm, ctr = Robj @ right, Robj @ up, Robj @ nrm, Robj @ ctr
    den = d @ nrm
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((ctr - o) @ nrm) / den
    X = o + t[:, None] * d
    x = (X - ctr) @ right
    y = (X - ctr) @ up
    w, h = disp.size_m
    inside = np.isfinite(t) & (t > 0) & (np.abs(x) < w / 2) & (np.abs(y) < h / 2)
    return t, x, y, inside


def panel_texels(x: np.ndarray, y: np.ndarray, size_m, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) texel indices of panel points ``x, y`` (metres from the centre, see
    :func:`panel_hits`) on a ``rows × cols`` image covering a ``size_m = (w, h)`` panel;
    row 0 is the top edge."""
    w, h = size_m
    row = np.clip(((h / 2 - y) / h * rows).astype(int), 0, rows - 1)
    col = np.clip(((x + w / 2) / w * cols).astype(int), 0, cols - 1)
    return row, col


def display_hits(o: np.ndarray, d: np.ndarray, table_deg: float, geo: RigGeometry) -> _DisplayHits:
    """The display texel (nearest display along the ray) each ray (object frame) meets."""
    n = d.shape[0]
    best = np.full(n, np.inf)
    which = np.full(n, -1)
    rc = np.zeros((len(geo.displays), 2, n), np.int64)
    Robj = object_from_rig(table_deg)[:3, :3]
    for k, disp in enumerate(geo.displays):
        t, x, y, inside = panel_hits(o, d, disp, Robj)
        hit = inside & (t < best)
        cols, rows = disp.resolution
        rc[k, 0, hit], rc[k, 1, hit] = panel_texels(x[hit], y[hit], disp.size_m, rows, cols)
        which[hit] = k
        best[hit] = t[hit]
    out = {}
    for k, disp in enumerate(geo.displays):
        idx = np.flatnonzero(which == k)
        out[disp.name] = (idx, rc[k, 0, idx], rc[k, 1, idx])
    return _DisplayHits(out)


@dataclass(frozen=True, kw_only=True)
class SyntheticSessionConfig:
    """What :func:`write_synthetic_session` writes.

    n_cameras, n_table : cameras on the arc × table angles (paper: 6 × 72 = 432 views).
    width_px, height_px : image size (paper: 1360 × 1032).
    n_light_dirs : one-light images per view (0 = no reflectance phase; paper: 60).
    n_pattern_pairs : backdrop patterns, each with its complement (≥ 1: K = 2·pairs).
    supersample : rays per pixel side (1: binary coverage; 3: fractional edges).
    noise : Gaussian noise (radiance units) added to every image; 0 = exact.
    half : store images as half floats (half the disk).
    groundtruth : write ``groundtruth/`` (true cameras and alphas).
    display_res : display texels (cols, rows) of the bottom panel.
    seed : patterns and noise.
    fsync : fsync the manifest after each record (the images are always fsynced).
    threads : writer threads (image encode and fsync overlap; the result does not depend on it).
    """

    n_cameras: int = 6
    n_table: int = 72
    width_px: int = 200
    height_px: int = 150
    n_light_dirs: int = 0
    n_pattern_pairs: int = 1
    supersample: int = 1
    noise: float = 0.002
    half: bool = False
    groundtruth: bool = True
    display_res: tuple[int, int] = (64, 64)
    seed: int = 0
    fsync: bool = False
    threads: int = 4

    def __post_init__(self):
        for k in ("n_cameras", "n_table", "width_px", "height_px", "n_pattern_pairs", "supersample"):
            v = getattr(self, k)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise InputError(f"synthetic session: {k} = {v!r}, expected an integer >= 1")
        if not (isinstance(self.n_light_dirs, (int, np.integer)) and self.n_light_dirs >= 0):
            raise InputError(f"synthetic session: n_light_dirs = {self.n_light_dirs!r}, expected an integer >= 0")
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise InputError(f"synthetic session: noise = {self.noise!r}, expected a finite value >= 0")

    @property
    def n_views(self) -> int:
        return self.n_cameras * self.n_table

    def light_layout(self) -> tuple[int, list[float]]:
        """(number of lights, array angles in degrees) giving ``n_light_dirs`` directions."""
        n = self.n_light_dirs
        if n == 0:
            return 2, []
        if n % 4 == 0:
            steps = n // 4
            return 4, [360.0 * j / steps / 4.0 for j in range(steps)]  # the array turns a quarter turn
        return n, [0.0]


def write_synthetic_session(
    root,
    config: SyntheticSessionConfig = SyntheticSessionConfig(),
    *,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Write the analytic sphere session of ``config`` into the empty folder ``root``.

    Returns
    -------
    dict with ``views`` [(camera, table_deg)], ``n_images``, ``bytes`` (images on disk),
    ``geometry`` (RigGeometry) and ``true_alpha_sum`` {view id: sum of the coverage alpha}.
    """
    cfg = config
    root = Path(root)
    rng = np.random.default_rng(cfg.seed)
    n_lights, array_degs = cfg.light_layout()
    rig = synthetic_rig(cfg.n_cameras, cfg.width_px, cfg.height_px, n_lights=n_lights, display_res=cfg.display_res)
    geo = RigGeometry.from_dict(rig)
    rig_cams = geo.nominal_cameras()
    angles = [360.0 * i / cfg.n_table for i in range(cfg.n_table)]
    views = [(c, a) for c in range(cfg.n_cameras) for a in angles]
    exposure_s, white_level = 1.0, 4.0
    meta = {
        "session": {
            "rig_source": "synthetic:sphere",
            "plan_name": "synthetic-paper",
            "white_level": white_level,
            "seed": cfg.seed,
        },
        "rig": rig,
    }
    w = SessionWriter(root, fsync=cfg.fsync).create(meta)
    for cam in rig_cams:  # known rig cameras: build needs no calibration phase
        write_opencv_yaml(root / "calibration" / f"{cam.name}.yaml", cam, extra={"reproj_rms_px": 0.1})
    pats = {}
    for k in range(cfg.n_pattern_pairs):
        base = {}
        for d in geo.displays:
            cols, rows = d.resolution
            # channels in [0.05, 0.3] ∪ [0.7, 0.95]: a pair differs by >= 0.4 everywhere
            lo = rng.uniform(0.05, 0.3, (rows, cols, 3))
            base[d.name] = np.where(rng.random((rows, cols, 3)) < 0.5, lo, 1.0 - lo).astype(np.float32)
        for pid, imgs in ((2 * k + 1, base), (2 * k + 2, {n: 1.0 - x for n, x in base.items()})):
            for name, img in imgs.items():
                write_png(root / "patterns" / name / f"p{pid:03d}.png", img, linear=True)
            # what the display shows is the 8-bit pattern, not the float one
            pats[pid] = {
                d.name: read_png(root / "patterns" / d.name / f"p{pid:03d}.png", linear=True) for d in geo.displays
            }
    H, W, ss = cfg.height_px, cfg.width_px, cfg.supersample
    S = ss * ss
    key_light = np.array([0.5, 0.8, 0.4]) / np.linalg.norm([0.5, 0.8, 0.4])
    n_images = 0
    nbytes = 0
    alpha_sum = {}
    vcams = [RigGeometry.view_camera(rig_cams[c], a, name=view_id(c, a)) for c, a in views]

    def pix(x):  # (H·W·S, C) samples -> (H, W, C) pixel means
        return x.reshape(H, W, S, -1).mean(2).astype(np.float32)

    def render(i: int) -> tuple[list, float]:
        """Ray-cast and write (atomically) every image of view i; the records are appended
        by the caller, in view order. Runs in a worker thread: the EXR encode and the two
        fsyncs per image release the GIL, and they, not the arithmetic, bound the writer."""
        c, a = views[i]
        vrng = np.random.default_rng([cfg.seed, i])  # per view: the same images whatever the thread order
        made = []

        def add(img, phase, **kw):
            key = record_shot_key(phase, c, a, kw)
            if cfg.noise > 0:
                img = img + vrng.normal(0.0, cfg.noise, img.shape).astype(np.float32)
            val = np.clip(img * exposure_s, 0.0, white_level).astype(np.float32)
            rel = f"images/{key}_e0.exr"
            write_exr(root / rel, val, half=cfg.half)
            made.append(
                (rel, dict(id=f"{key}/e0", shot=key, phase=phase, camera=c, table_deg=a, exposure_s=exposure_s, **kw))
            )

        o, d = pixel_rays(vcams[i], ss)
        t = sphere_hit_t(o, d, CENTRE_M, CORE_R_M)
        core = np.isfinite(t)
        X = o + np.where(core, t, 0.0)[:, None] * d
        nrm = (X - CENTRE_M) / CORE_R_M
        alb = np.where(core[:, None], sphere_albedo(nrm), 0.0)
        hits = display_hits(o, d, a, geo)
        alpha = pix(core.astype(np.float64)[:, None])[..., 0]
        lf = alb * (0.15 + 0.85 * np.clip(nrm @ key_light, 0, None))[:, None]
        for pid, p in pats.items():
            back = hits.radiance(geo, p, len(t))
            add(pix(back), "matting", pattern=pid, object_present=False)
            add(pix(np.where(core[:, None], lf, back)), "matting", pattern=pid)
        add(pix(lf), "lightfield")
        for b in array_degs:
            for lid in range(n_lights):
                L = geo.light_direction_object(lid, a, b)
                add(
                    pix(alb * (0.85 * np.clip(nrm @ L, 0, None))[:, None]),
                    "reflectance",
                    light=lid,
                    lights_deg=float(b),
                    extra={"level": 255},
                )
        if cfg.groundtruth:
            write_exr(root / "groundtruth" / "alpha" / f"{view_id(c, a)}.exr", alpha)
        return made, float(alpha.sum())

    import concurrent.futures as cf

    n_threads = max(1, int(cfg.threads))
    try:
        with cf.ThreadPoolExecutor(max_workers=n_threads, thread_name_prefix="synthetic") as pool:
            pending: dict[int, cf.Future] = {}
            nxt = 0
            for i in range(len(views)):
                # at most 2 views per thread in flight: memory stays bounded at any size
                while nxt < len(views) and len(pending) < 2 * n_threads:
                    pending[nxt] = pool.submit(render, nxt)
                    nxt += 1
                made, asum = pending.pop(i).result()
                for rel, fields in made:
                    rec = w.add_file(root / rel, **fields)
                    n_images += 1
                    nbytes += rec.bytes
                alpha_sum[view_id(*views[i])] = asum
                if progress:
                    progress(i + 1, len(views))
    finally:
        w.close()
    if cfg.groundtruth:
        gt = root / "groundtruth"
        write_colmap_text(gt / "cameras", vcams, [v.name for v in vcams], share_intrinsics=[c for c, _ in views])
        for cam in rig_cams:
            write_opencv_yaml(gt / "calibration" / f"{cam.name}.yaml", cam)
    return {"views": views, "n_images": n_images, "bytes": nbytes, "geometry": geo, "true_alpha_sum": alpha_sum}
