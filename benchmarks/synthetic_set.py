"""A Blender-synthetic-style test set rendered with Mitsuba 3 (issue 29, item 6 and the
first goal): a detailed procedural object — a toy bulldozer of 60-odd meshes: a textured
chassis plate and body, studs, an open cab of thin posts, a boom with a bucket and teeth,
four wheels with six spokes each on thin axles, a ladder, an antenna — seen from ``--views``
cameras on the upper hemisphere, written as RGBA PNGs (straight alpha, sRGB, the true
coverage alpha of the object) with a nerfstudio/Blender ``transforms.json`` that
``opacityhull import nerfstudio`` reads.

    .venv/bin/python benchmarks/synthetic_set.py [--quick] [--views 100] [--size 400] [--spp 64] [--out DIR] [--json]

Full run: 100 views of 400×400 at 64 spp into ``benchmarks/out/synthetic_set/`` (git
ignores the images; a few minutes on 2 cores); ``--quick``: 24 views of 160×160 at 8 spp
under ``benchmarks/out/quick/synthetic_set/``. Besides ``transforms.json`` (every view),
``transforms_train.json`` / ``transforms_test.json`` give the Blender-style split that
``build --hold-out every:10`` makes (views 0, 10, 20, ... are test views).

Deterministic: the geometry and textures are built from ``--seed``, the cameras are a
Fibonacci spiral on the hemisphere turned by a seeded angle, and every view renders with
its index as Mitsuba's seed (same variant → same pixels).

Scene: the object in metres, +Y up, centred on its bounding box; a constant environment
(hidden: the background is transparent) plus two directional lights; a ``path``
integrator of depth 4; diffuse-and-a-little-gloss materials (``roughplastic``), brushed
metal rods (``roughconductor``). The film's alpha is 1 where a camera ray hits the
object, box-filtered: the coverage alpha a matting would give.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
FOV_X_DEG = 39.6  # the Blender synthetic sets' camera_angle_x (0.6911 rad)
HOLD_OUT_EVERY = 10

# ------------------------------------------------------------------------ geometry


@dataclass(frozen=True)
class Part:
    """One mesh of the object with its material name."""

    name: str
    material: str
    vertices: np.ndarray  # (V, 3) metres
    faces: np.ndarray  # (F, 3) int32, counter-clockwise from outside
    normals: np.ndarray  # (V, 3)
    uv: np.ndarray  # (V, 2)


def _orient(V: np.ndarray, F: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """Flip the triangles whose geometric normal points against ``outward`` (per face)."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    bad = np.einsum("ij,ij->i", n, outward) < 0
    F = F.copy()
    F[bad] = F[bad][:, [0, 2, 1]]
    return F


def box(name: str, material: str, centre, size, *, R: np.ndarray | None = None) -> Part:
    """An axis-aligned (then rotated by ``R`` about its centre) box, flat-shaded, each face
    mapped to the whole texture."""
    c = np.asarray(centre, np.float64)
    h = 0.5 * np.asarray(size, np.float64)
    R = np.eye(3) if R is None else np.asarray(R, np.float64)
    V, N, UV, F = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_ax, v_ax = [a for a in range(3) if a != axis]
            n = np.zeros(3)
            n[axis] = sign
            quad = []
            for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u_ax], p[v_ax] = sign * h[axis], su * h[u_ax], sv * h[v_ax]
                quad.append(p)
            base = len(V)
            V += quad
            N += [n] * 4
            UV += [(0, 0), (1, 0), (1, 1), (0, 1)]
            F += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    Vl = np.array(V) @ R.T + c
    Nl = np.array(N) @ R.T
    Fa = np.array(F, np.int32)
    Fa = _orient(Vl, Fa, Nl[Fa[:, 0]])
    return Part(name, material, Vl, Fa, Nl, np.array(UV, np.float64))


def _frame(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = np.cross(d, ref)
    a /= np.linalg.norm(a)
    return a, np.cross(d, a)


def cylinder(name: str, material: str, p0, p1, radius: float, *, segments: int = 20) -> Part:
    """A capped cylinder from ``p0`` to ``p1`` (smooth side, flat caps)."""
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    d = p1 - p0
    L = float(np.linalg.norm(d))
    d /= L
    a, b = _frame(d)
    t = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    ring = np.cos(t)[:, None] * a + np.sin(t)[:, None] * b  # (S, 3)
    S = segments
    V = [p0 + radius * ring, p1 + radius * ring]
    N = [ring, ring]
    UV = [np.stack([t / (2 * math.pi), np.zeros(S)], 1), np.stack([t / (2 * math.pi), np.ones(S)], 1)]
    F, out = [], []
    for s in range(S):
        i, j = s, (s + 1) % S
        F += [(i, j, S + j), (i, S + j, S + i)]
        mid = 0.5 * (ring[i] + ring[j])
        out += [mid, mid]
    for k, (p, sgn) in enumerate(((p0, -1.0), (p1, 1.0))):
        base = 2 * S + k * (S + 1)
        V.append(np.vstack([p[None], p + radius * ring]))
        N.append(np.tile(sgn * d, (S + 1, 1)))
        UV.append(np.vstack([[0.5, 0.5], 0.5 + 0.5 * np.stack([np.cos(t), np.sin(t)], 1)]))
        for s in range(S):
            F.append((base, base + 1 + s, base + 1 + (s + 1) % S))
            out.append(sgn * d)
    Vl = np.vstack(V)
    Fa = np.array(F, np.int32)
    Fa = _orient(Vl, Fa, np.array(out))
    return Part(name, material, Vl, Fa, np.vstack(N), np.vstack(UV))


def torus(name: str, material: str, centre, axis, major: float, minor: float, *, segments=40, sides=14) -> Part:
    """A torus around ``axis`` through ``centre``."""
    ax = np.asarray(axis, np.float64)
    ax /= np.linalg.norm(ax)
    a, b = _frame(ax)
    u = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    v = np.linspace(0, 2 * math.pi, sides, endpoint=False)
    U, Vv = np.meshgrid(u, v, indexing="ij")
    radial = np.cos(U)[..., None] * a + np.sin(U)[..., None] * b
    n = np.cos(Vv)[..., None] * radial + np.sin(Vv)[..., None] * ax
    P = np.asarray(centre, np.float64) + major * radial + minor * n
    F = []
    for i in range(segments):
        for j in range(sides):
            i2, j2 = (i + 1) % segments, (j + 1) % sides
            q = (i * sides + j, i2 * sides + j, i2 * sides + j2, i * sides + j2)
            F += [(q[0], q[1], q[2]), (q[0], q[2], q[3])]
    Vl, Nl = P.reshape(-1, 3), n.reshape(-1, 3)
    Fa = np.array(F, np.int32)
    Fa = _orient(Vl, Fa, Nl[Fa].mean(axis=1))
    uv = np.stack([U / (2 * math.pi), Vv / (2 * math.pi)], -1).reshape(-1, 2)
    return Part(name, material, Vl, Fa, Nl, uv)


def sphere(name: str, material: str, centre, radius: float, *, segments=16, rings=10) -> Part:
    th = np.linspace(0, math.pi, rings + 1)
    ph = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    n = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
    F = []
    for i in range(rings):
        for j in range(segments):
            j2 = (j + 1) % segments
            q = (i * segments + j, i * segments + j2, (i + 1) * segments + j2, (i + 1) * segments + j)
            F += [(q[0], q[1], q[2]), (q[0], q[2], q[3])]
    V = np.asarray(centre, np.float64) + radius * n
    Fa = np.array(F, np.int32)
    # the pole rows repeat one point: drop the zero-area triangles
    area = np.linalg.norm(np.cross(V[Fa[:, 1]] - V[Fa[:, 0]], V[Fa[:, 2]] - V[Fa[:, 0]]), axis=1)
    Fa = Fa[area > 1e-14]
    Fa = _orient(V, Fa, n[Fa].mean(axis=1))
    uv = np.stack([P / (2 * math.pi), T / math.pi], -1).reshape(-1, 2)
    return Part(name, material, V, Fa, n, uv)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def bulldozer_parts(seed: int = 0) -> list[Part]:
    """The object: a toy bulldozer in metres, +Y up, centred on its bounding box.

    Thin parts (what a hull loses and a fit must recover): axles r = 3 mm, spokes 2.5 mm,
    cab posts 3 mm, ladder rungs 1.8 mm, antenna 1.5 mm; see-through gaps between the
    spokes, in the cab and the ladder. ``seed`` moves the teeth and studs slightly."""
    rng = np.random.default_rng(seed)
    P: list[Part] = []
    wheel_y, wheel_r = 0.045, 0.046
    for ix, x in enumerate((-0.10, 0.10)):
        P.append(cylinder(f"axle{ix}", "metal", (x, wheel_y, -0.105), (x, wheel_y, 0.105), 0.003))
        for iz, z in enumerate((-0.092, 0.092)):
            c = np.array([x, wheel_y, z])
            P.append(torus(f"tyre{ix}{iz}", "rubber", c, (0, 0, 1), wheel_r - 0.009, 0.009))
            P.append(torus(f"rim{ix}{iz}", "red", c, (0, 0, 1), 0.029, 0.003, segments=32, sides=8))
            P.append(cylinder(f"hub{ix}{iz}", "yellow", c - (0, 0, 0.008), c + (0, 0, 0.008), 0.011))
            for k in range(6):
                a = 2 * math.pi * k / 6 + 0.3 * ix + 0.17 * iz
                d = np.array([math.cos(a), math.sin(a), 0.0])
                P.append(cylinder(f"spoke{ix}{iz}{k}", "metal", c + 0.009 * d, c + 0.028 * d, 0.0025, segments=10))
    P.append(box("plate", "plate_tex", (0.0, 0.075, 0.0), (0.30, 0.012, 0.15)))
    P.append(box("body", "body_tex", (-0.035, 0.125, 0.0), (0.16, 0.088, 0.13)))
    top = 0.125 + 0.044
    for i in range(4):
        for j in range(3):
            jit = rng.uniform(-0.001, 0.001, size=2)
            x, z = -0.095 + 0.028 * i + jit[0], -0.035 + 0.035 * j + jit[1]
            if i >= 2 and j == 1:
                continue  # room for the cab
            P.append(cylinder(f"stud{i}{j}", "yellow", (x, top, z), (x, top + 0.007, z), 0.0075, segments=16))
    # the open cab: four posts and a roof
    for i, (x, z) in enumerate(((0.005, -0.04), (0.005, 0.04), (0.035, -0.04), (0.035, 0.04))):
        P.append(cylinder(f"post{i}", "metal", (x, top, z), (x, top + 0.07, z), 0.003, segments=10))
    P.append(box("roof", "red", (0.02, top + 0.075, 0.0), (0.05, 0.01, 0.095)))
    P.append(box("seat", "red", (0.02, top + 0.012, 0.0), (0.025, 0.024, 0.04)))
    # the boom: two arms, a cross bar, the bucket and its teeth
    for s in (-1, 1):
        P.append(cylinder(f"arm{s}", "yellow", (0.05, 0.14, s * 0.045), (0.19, 0.19, s * 0.045), 0.005, segments=12))
    P.append(cylinder("crossbar", "metal", (0.16, 0.18, -0.05), (0.16, 0.18, 0.05), 0.003))
    P.append(box("bucket_back", "body_tex", (0.205, 0.165, 0.0), (0.008, 0.07, 0.12), R=_rot_z(-0.25)))
    P.append(box("bucket_floor", "body_tex", (0.225, 0.128, 0.0), (0.045, 0.006, 0.12)))
    for k in range(6):
        z = -0.05 + 0.02 * k + rng.uniform(-0.001, 0.001)
        P.append(cylinder(f"tooth{k}", "metal", (0.245, 0.128, z), (0.262, 0.126, z), 0.0022, segments=8))
    # ladder on the side, an exhaust and an antenna
    zl = 0.068
    for s, x in enumerate((-0.105, -0.085)):
        P.append(cylinder(f"rail{s}", "metal", (x, 0.082, zl), (x, 0.18, zl), 0.0018, segments=8))
    for k in range(6):
        y = 0.092 + 0.016 * k
        P.append(cylinder(f"rung{k}", "metal", (-0.105, y, zl), (-0.085, y, zl), 0.0018, segments=8))
    P.append(cylinder("exhaust", "rubber", (-0.09, top, -0.045), (-0.09, top + 0.055, -0.045), 0.007))
    P.append(cylinder("antenna", "metal", (-0.1, top, 0.045), (-0.1, top + 0.11, 0.045), 0.0015, segments=8))
    P.append(sphere("antenna_tip", "red", (-0.1, top + 0.11, 0.045), 0.005))
    # a tilted light bar on the roof
    P.append(box("lightbar", "plate_tex", (0.02, top + 0.084, 0.0), (0.012, 0.008, 0.07), R=_rot_x(0.2)))
    lo = np.min([p.vertices.min(0) for p in P], axis=0)
    hi = np.max([p.vertices.max(0) for p in P], axis=0)
    c = 0.5 * (lo + hi)
    return [Part(p.name, p.material, p.vertices - c, p.faces, p.normals, p.uv) for p in P]


def _textures(seed: int, size: int = 256) -> dict[str, np.ndarray]:
    """Procedural textures (linear RGB, top row first): the plate a checker with coloured
    stripes and random glyph blocks, the body yellow panels with dark seams and markings."""
    rng = np.random.default_rng(seed + 1)
    v, u = np.mgrid[0:size, 0:size] / size
    check = ((np.floor(u * 8) + np.floor(v * 8)) % 2)[..., None]
    plate = 0.08 + 0.6 * check * np.array([0.9, 0.9, 0.85])
    stripes = (np.floor(u * 16) % 4 == 0)[..., None] & (v > 0.7)[..., None]
    plate = np.where(stripes, np.array([0.7, 0.05, 0.03]), plate)
    glyph = rng.random((16, 16)) > 0.55
    g = np.kron(glyph, np.ones((size // 64, size // 64)))  # 64 px of glyphs
    plate[16 : 16 + g.shape[0], 24 : 24 + g.shape[1]] = np.where(
        g[..., None] > 0, np.array([0.02, 0.1, 0.5]), plate[16 : 16 + g.shape[0], 24 : 24 + g.shape[1]]
    )
    body = np.broadcast_to(np.array([0.75, 0.5, 0.02]), (size, size, 3)).copy()
    seam = (np.abs(((u * 4) % 1) - 0.5) > 0.47) | (np.abs(((v * 3) % 1) - 0.5) > 0.47)
    body[seam] = (0.05, 0.04, 0.02)
    noise = rng.random((32, 32))
    body *= (0.85 + 0.3 * np.kron(noise, np.ones((size // 32, size // 32))))[..., None]
    mark = np.kron(rng.random((8, 12)) > 0.5, np.ones((6, 6)))
    body[150 : 150 + mark.shape[0], 100 : 100 + mark.shape[1]] = np.where(
        mark[..., None] > 0, np.array([0.02, 0.02, 0.02]), body[150 : 150 + mark.shape[0], 100 : 100 + mark.shape[1]]
    )
    return {"plate_tex": np.clip(plate, 0, 1), "body_tex": np.clip(body, 0, 1)}


def _bsdf(mi, material: str, tex: dict[str, np.ndarray]) -> dict:
    def bitmap(img):
        return {
            "type": "bitmap",
            "data": mi.TensorXf(np.ascontiguousarray(img[::-1], np.float32)),  # row 0 is v = 0
            "raw": True,
            "filter_type": "bilinear",
        }

    plastic = {"type": "roughplastic", "alpha": 0.18, "distribution": "ggx", "int_ior": 1.49}
    if material in tex:
        return {**plastic, "diffuse_reflectance": bitmap(tex[material])}
    colours = {"yellow": (0.8, 0.55, 0.02), "red": (0.6, 0.04, 0.02), "rubber": (0.04, 0.04, 0.045)}
    if material == "metal":
        return {"type": "roughconductor", "material": "Al", "alpha": 0.3}
    if material == "rubber":
        return {
            "type": "roughplastic",
            "alpha": 0.5,
            "diffuse_reflectance": {"type": "rgb", "value": colours[material]},
        }
    return {**plastic, "diffuse_reflectance": {"type": "rgb", "value": colours[material]}}


# ------------------------------------------------------------------------ cameras


def hemisphere_cameras(
    n: int, *, size_px: int, radius_m: float, fov_x_deg: float = FOV_X_DEG, seed: int = 0, min_elev_deg: float = 5.0
):
    """``n`` cameras looking at the origin from a Fibonacci spiral on the upper hemisphere
    (+Y up; elevations ``min_elev_deg``–85°), the spiral turned by a seeded angle.
    Square pixels, principal point at the image centre, no distortion."""
    from opacityhull.camera import Camera, look_at_world_from_cam

    rng = np.random.default_rng(seed)
    turn = rng.uniform(0, 2 * math.pi)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    s_lo, s_hi = math.sin(math.radians(min_elev_deg)), math.sin(math.radians(85.0))
    f = 0.5 * size_px / math.tan(0.5 * math.radians(fov_x_deg))
    K = np.array([[f, 0, 0.5 * size_px - 0.5], [0, f, 0.5 * size_px - 0.5], [0, 0, 1]])
    cams = []
    for i in range(n):
        y = s_lo + (s_hi - s_lo) * (i + 0.5) / n  # uniform in sin(elevation): uniform area
        r = math.sqrt(1 - y * y)
        az = turn + golden * i
        eye = radius_m * np.array([r * math.cos(az), y, r * math.sin(az)])
        cams.append(Camera(K=K, width=size_px, height=size_px, world_from_cam=look_at_world_from_cam(eye, (0, 0, 0))))
    # interleave so that every 10th view is spread over the elevations, not the lowest ones
    order = np.argsort((np.arange(n) * 0.618034) % 1.0, kind="stable")
    return [cams[i].with_name(f"r_{k}") for k, i in enumerate(order)]


# ------------------------------------------------------------------------ rendering


@dataclass(frozen=True, kw_only=True)
class SetConfig:
    """What :func:`render_set` renders."""

    views: int = 100
    size_px: int = 400
    spp: int = 64
    seed: int = 0
    max_depth: int = 4
    #: the object's bounding sphere fills this fraction of the half-frame
    fill: float = 0.8


def object_radius_m(parts: list[Part]) -> float:
    return float(max(np.linalg.norm(p.vertices, axis=1).max() for p in parts))


def scene_dict(mi, parts: list[Part], folder: Path, seed: int, *, max_depth: int = 4) -> dict:
    """The Mitsuba scene (no sensor): one PLY per part under ``folder``."""
    from opacityhull.sim.shapes import TriMesh, write_ply_mesh

    tex = _textures(seed)
    d: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": True},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.55, 0.58, 0.62]}},
        "sun": {"type": "directional", "direction": [-0.45, -0.8, -0.35], "irradiance": {"type": "rgb", "value": 2.6}},
        "fill": {"type": "directional", "direction": [0.6, -0.3, 0.7], "irradiance": {"type": "rgb", "value": 0.7}},
    }
    bsdfs = {m: _bsdf(mi, m, tex) for m in sorted({p.material for p in parts})}
    for p in parts:
        path = folder / f"{p.name}.ply"
        write_ply_mesh(path, TriMesh(p.vertices, p.faces, p.normals, p.uv))
        d[p.name] = {"type": "ply", "filename": str(path), "bsdf": bsdfs[p.material], "face_normals": False}
    return d


def render_set(out: Path, cfg: SetConfig, *, log=print) -> dict:
    """Render the set into ``out`` (images ``train/r_i.png``, ``transforms*.json``).

    Returns ``{"out", "views", "size_px", "spp", "seconds", "variant", "radius_m"}``."""
    from opacityhull.camera import nerfstudio_transform_matrix
    from opacityhull.imageio import straight_from_premul, write_png
    from opacityhull.sim.mitsuba_sensor import sensor_dict
    from opacityhull.sim.variants import use_mitsuba

    mi = use_mitsuba()
    parts = bulldozer_parts(cfg.seed)
    R = object_radius_m(parts)
    dist = R / (cfg.fill * math.tan(0.5 * math.radians(FOV_X_DEG)))
    cams = hemisphere_cameras(cfg.views, size_px=cfg.size_px, radius_m=dist, seed=cfg.seed)
    out.mkdir(parents=True, exist_ok=True)
    (out / "train").mkdir(exist_ok=True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        scene = mi.load_dict(scene_dict(mi, parts, Path(tmp), cfg.seed, max_depth=cfg.max_depth))
        frames = []
        for i, cam in enumerate(cams):
            # Mitsuba's default clip planes (0.01, 1e4 m), as the published set was rendered
            sensor = mi.load_dict(sensor_dict(mi, cam, sampler="independent", spp=int(cfg.spp), clip_m=None))
            img = mi.render(scene, sensor=sensor, spp=int(cfg.spp), seed=i)  # pyright: ignore[reportArgumentType]
            img = np.array(img, dtype=np.float32)
            rgba = straight_from_premul(np.clip(img, 0.0, None))
            write_png(out / "train" / f"{cam.name}.png", rgba)
            frames.append({"file_path": f"./train/{cam.name}", "transform_matrix": nerfstudio_transform_matrix(cam)})
            if (i + 1) % 10 == 0 or i + 1 == len(cams):
                log(f"  view {i + 1}/{len(cams)}  {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    seconds = time.perf_counter() - t0
    head = {"camera_angle_x": math.radians(FOV_X_DEG), "w": cfg.size_px, "h": cfg.size_px}
    for name, sel in (
        ("transforms.json", frames),
        ("transforms_train.json", [f for i, f in enumerate(frames) if i % HOLD_OUT_EVERY]),
        ("transforms_test.json", frames[::HOLD_OUT_EVERY]),
    ):
        (out / name).write_text(json.dumps({**head, "frames": sel}, indent=1))
    info = {
        "out": str(out),
        "views": cfg.views,
        "size_px": cfg.size_px,
        "spp": cfg.spp,
        "seed": cfg.seed,
        "seconds": round(seconds, 1),
        "variant": mi.variant(),
        "radius_m": round(dist, 4),
        "object_radius_m": round(R, 4),
        "parts": len(parts),
        "triangles": int(sum(p.faces.shape[0] for p in parts)),
    }
    (out / "synthetic_set.json").write_text(json.dumps(info, indent=1))
    return info


def quick_config() -> SetConfig:
    return SetConfig(views=24, size_px=160, spp=8)


def ensure_set(quick: bool, *, log=print) -> Path:
    """The set's ``transforms.json`` under :data:`OUT` (``OUT/synthetic_set``), rendered
    first when missing or made with other settings."""
    cfg = quick_config() if quick else SetConfig()
    out = OUT / "synthetic_set"
    info = out / "synthetic_set.json"
    if info.is_file():
        got = json.loads(info.read_text())
        if all(
            got.get(k) == v
            for k, v in (("views", cfg.views), ("size_px", cfg.size_px), ("spp", cfg.spp), ("seed", cfg.seed))
        ):
            return out / "transforms.json"
    render_set(out, cfg, log=log)
    return out / "transforms.json"


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="24 views of 160x160 at 8 spp")
    ap.add_argument("--views", type=int)
    ap.add_argument("--size", type=int)
    ap.add_argument("--spp", type=int)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="the set's folder (default OUT/synthetic_set)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    base = quick_config() if a.quick else SetConfig()
    cfg = SetConfig(
        views=a.views or base.views,
        size_px=a.size or base.size_px,
        spp=a.spp or base.spp,
        seed=a.seed,
    )
    out = a.out or OUT / "synthetic_set"
    info = render_set(out, cfg)
    if a.json:
        print(json.dumps(info))
    else:
        print(json.dumps(info, indent=1))
    return info


if __name__ == "__main__":
    main()
