"""Procedural geometry for the built-in scenes: pure NumPy, no Mitsuba.

Every generator returns geometry in the object frame (metres, +Y up, resting on the
table plane ``y = 0``). Meshes are :class:`TriMesh` (vertices, triangles, per-vertex
normals and texture coordinates); fibres are :class:`Fibres` (polylines with a
radius), rendered by Mitsuba's ``linearcurve`` and turned into thin triangle tubes for
the ground-truth mesh.

Lathe profiles are (r, y) polylines from the axis at the bottom, around the outside,
to the axis at the top (or back down inside, for a cup); revolving them gives a closed,
outward-oriented surface — dielectrics need that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = [
    "TriMesh",
    "Fibres",
    "lathe",
    "cup_mesh",
    "dome_mesh",
    "bottle_mesh",
    "torus_mesh",
    "uv_sphere_mesh",
    "ellipsoid_mesh",
    "fibre_tuft",
    "tube_mesh",
    "merge_meshes",
    "write_ply_mesh",
    "read_ply_mesh",
    "write_curves_txt",
]


@dataclass(frozen=True)
class TriMesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : (V, 3) float64, metres.
    faces : (F, 3) int32, counter-clockwise seen from outside.
    normals : (V, 3) float64 unit vertex normals (outward).
    uv : (V, 2) float64 texture coordinates in [0, 1].
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uv: np.ndarray

    def transformed(self, T: np.ndarray) -> TriMesh:
        """The mesh moved by the 4×4 rigid (or uniformly scaled) transform ``T``."""
        T = np.asarray(T, dtype=np.float64)
        V = self.vertices @ T[:3, :3].T + T[:3, 3]
        N = self.normals @ np.linalg.inv(T[:3, :3])  # inverse transpose, row vectors
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
        return TriMesh(V, self.faces, N, self.uv)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def signed_volume(self) -> float:
        """Volume enclosed (positive when faces are oriented outward)."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


@dataclass(frozen=True)
class Fibres:
    """Hair-like fibres: ``points`` (N, K, 3) polyline control points, ``radius_m``."""

    points: np.ndarray
    radius_m: float

    @property
    def count(self) -> int:
        return int(self.points.shape[0])


# --------------------------------------------------------------------------- helpers


def _vertex_normals(V: np.ndarray, F: np.ndarray, weld_decimals: int = 9) -> np.ndarray:
    """Area-weighted vertex normals, averaged over vertices at the same position (seams,
    poles), so duplicated seam vertices shade identically."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    fn = np.cross(b - a, c - a)  # length = 2 * area
    N = np.zeros_like(V)
    for i in range(3):
        np.add.at(N, F[:, i], fn)
    key = np.round(V, weld_decimals)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    acc = np.zeros((inv.max() + 1, 3))
    np.add.at(acc, inv, N)
    N = acc[inv]
    n = np.linalg.norm(N, axis=1, keepdims=True)
    return N / np.where(n > 0, n, 1.0)


def _grid_faces(rows: int, cols: int) -> np.ndarray:
    """Two triangles per quad of a (rows × cols) vertex grid (row-major)."""
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    i00 = (r * cols + c).ravel()
    i01 = i00 + 1
    i10 = i00 + cols
    i11 = i10 + 1
    return np.concatenate([np.stack([i00, i10, i11], 1), np.stack([i00, i11, i01], 1)]).astype(np.int32)


def _drop_degenerate(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    return F[area2 > 1e-14]


def lathe(r: np.ndarray, y: np.ndarray, *, segments: int = 96, radial=None) -> TriMesh:
    """Revolve the (r, y) profile about +Y.

    Parameters
    ----------
    r, y : (P,) arrays
        Profile, metres. Points with ``r == 0`` lie on the axis (poles). The surface is
        oriented outward when the profile runs bottom → outside → top, i.e. with the
        solid on the left of the direction of travel in the (r, y) plane.
    segments : int
        Angular subdivisions.
    radial : callable, optional
        ``radial(phi (S,), k (P,)) -> (P, S)`` factor multiplying the radius, for
        flutes and lobes; ``k`` is the profile index.

    Returns
    -------
    TriMesh with u = φ / 2π and v = normalised arc length along the profile.
    """
    r = np.asarray(r, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if r.shape != y.shape or r.ndim != 1 or r.size < 2:
        raise InputError(f"lathe profile: r and y must be equal-length 1-D arrays, got {r.shape}, {y.shape}")
    if segments < 3:
        raise InputError(f"lathe: segments must be >= 3, got {segments}")
    phi = np.linspace(0.0, 2 * math.pi, segments + 1)
    R = np.repeat(r[:, None], segments + 1, axis=1)
    if radial is not None:
        R = R * radial(phi, np.arange(r.size))
    # phi measured from +Z towards +X (right-handed about +Y)
    X = R * np.sin(phi)[None, :]
    Z = R * np.cos(phi)[None, :]
    Y = np.repeat(y[:, None], segments + 1, axis=1)
    V = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    seg = np.hypot(np.diff(r), np.diff(y))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s /= max(s[-1], 1e-30)
    U, Vv = np.meshgrid(phi / (2 * math.pi), s)
    uv = np.stack([U.ravel(), Vv.ravel()], axis=1)
    F = _grid_faces(r.size, segments + 1)
    # grid order (profile down the rows, phi along columns) with r-outward, y-up travel
    # gives faces whose normals point inward; flip them.
    F = F[:, [0, 2, 1]]
    F = _drop_degenerate(V, F)
    N = _vertex_normals(V, F)
    return TriMesh(V, F, N, uv)


def _arc(cx, cy, rad, a0, a1, n):
    t = np.linspace(a0, a1, n)
    return cx + rad * np.cos(t), cy + rad * np.sin(t)


def _profile(*pieces):
    rs, ys = [], []
    for pr, py in pieces:
        pr, py = np.atleast_1d(pr), np.atleast_1d(py)
        if rs and np.hypot(rs[-1][-1] - pr[0], ys[-1][-1] - py[0]) < 1e-12:
            pr, py = pr[1:], py[1:]
        rs.append(pr)
        ys.append(py)
    return np.concatenate(rs), np.concatenate(ys)


# --------------------------------------------------------------------------- shapes


def cup_mesh(
    *,
    radius_m: float = 0.06,
    height_m: float = 0.15,
    wall_m: float = 0.012,
    flutes: int = 7,
    flute_depth: float = 0.12,
    segments: int = 112,
) -> TriMesh:
    """An open fluted cup: outer wall with ``flutes`` vertical grooves (concave between
    the lobes), rounded rim, an inner cavity — concavities no visual hull recovers."""
    if not (0 < wall_m < radius_m and radius_m > 0 and height_m > 2 * wall_m):
        raise InputError(
            f"cup: need 0 < wall_m < radius_m and height_m > 2*wall_m, got "
            f"radius_m={radius_m}, height_m={height_m}, wall_m={wall_m}"
        )
    R, H, w = radius_m, height_m, wall_m
    fr = min(0.25 * R, 0.3 * H)  # foot fillet
    n_out = 2
    prof = _profile(
        (np.linspace(0.0, R - fr, 8), np.zeros(8)),
        _arc(R - fr, fr, fr, -math.pi / 2, 0.0, 8),
        (np.full(16, R), np.linspace(fr, H - w / 2, 16)),
        _arc(R - w / 2, H - w / 2, w / 2, 0.0, math.pi, 9),  # rounded rim
        (np.full(14, R - w), np.linspace(H - w / 2, w + fr, 14)),
        _arc(R - w - fr, w + fr, fr, 0.0, -math.pi / 2, 8),
        (np.linspace(R - w - fr, 0.0, 6), np.full(6, w)),
    )
    r, y = prof
    # outer wall points (the first part of the profile, up to the rim top) get flutes;
    # the inner wall stays round so the cup's wall thickness varies like a carved pot.
    rim_idx = int(np.argmax(y))
    outer = np.arange(r.size) <= rim_idx
    del n_out

    def radial(phi, k):
        f = 1.0 - flute_depth * 0.5 * (1.0 - np.cos(flutes * phi))  # grooves between lobes
        taper = np.clip(r / R, 0.0, 1.0) ** 2  # no flutes at the bottom centre
        fac = 1.0 + (f[None, :] - 1.0) * (taper * outer)[:, None]
        return fac

    return lathe(r, y, segments=segments, radial=radial)


def dome_mesh(*, radius_m: float = 0.065, height_m: float = 0.16, segments: int = 96) -> TriMesh:
    """A closed onion-dome solid (smooth, convex-concave profile) for glossy materials."""
    t = np.linspace(0.0, 1.0, 48)
    # bulb radius profile: wide belly, narrowing neck, pointed top
    rr = radius_m * np.sin(np.pi * np.clip(t, 0, 1) ** 0.8) * (1.0 - 0.35 * t**3)
    rr[0] = 0.0
    rr[-1] = 0.0
    yy = height_m * t
    foot = 0.012 * radius_m / 0.065
    rr = np.maximum(rr, 0.0)
    rr[1] = max(rr[1], foot)
    return lathe(rr, yy, segments=segments)


def bottle_mesh(
    *, radius_m: float = 0.055, height_m: float = 0.17, neck_radius_m: float = 0.022, segments: int = 96
) -> TriMesh:
    """A closed solid glass bottle (rounded base, shoulder, neck, rounded lip)."""
    R, H, n = radius_m, height_m, neck_radius_m
    if not 0 < n < R:
        raise InputError(f"bottle: need 0 < neck_radius_m < radius_m, got {n}, {R}")
    fr = 0.2 * R
    body_h = 0.55 * H
    prof = _profile(
        (np.linspace(0.0, R - fr, 6), np.zeros(6)),
        _arc(R - fr, fr, fr, -math.pi / 2, 0.0, 8),
        (np.full(10, R), np.linspace(fr, body_h, 10)),
    )
    t = np.linspace(0.0, 1.0, 14)[1:]
    shoulder_r = n + (R - n) * 0.5 * (1 + np.cos(np.pi * t))
    shoulder_y = body_h + (0.25 * H) * t
    lip = 0.01 * H / 0.17
    r = np.concatenate(
        [
            prof[0],
            shoulder_r,
            np.full(6, n)[1:],
            _arc(n - lip, H - lip, lip, 0.0, math.pi / 2, 6)[0],
            np.linspace(n - lip, 0.0, 5)[1:],
        ]
    )
    y = np.concatenate(
        [
            prof[1],
            shoulder_y,
            np.linspace(body_h + 0.25 * H, H - lip, 6)[1:],
            _arc(n - lip, H - lip, lip, 0.0, math.pi / 2, 6)[1],
            np.full(4, H),
        ]
    )
    return lathe(r, y, segments=segments)


def torus_mesh(
    *, major_m: float, minor_m: float, centre_m=(0.0, 0.0, 0.0), segments: int = 96, sides: int = 32
) -> TriMesh:
    """A torus about +Y (ring in the XZ plane) centred at ``centre_m``."""
    if not 0 < minor_m < major_m:
        raise InputError(f"torus: need 0 < minor_m < major_m, got {minor_m}, {major_m}")
    a = np.linspace(0, 2 * math.pi, sides + 1)
    r = major_m + minor_m * np.cos(a)
    y = minor_m * np.sin(a)
    # a closed circle profile: lathe expects the solid on the left; the circle run
    # counter-clockwise in (r, y) has the solid on its left.
    m = lathe(r, y, segments=segments)
    T = np.eye(4)
    T[:3, 3] = centre_m
    return m.transformed(T)


def uv_sphere_mesh(*, radius_m: float, centre_m=(0.0, 0.0, 0.0), segments: int = 64, rings: int = 32) -> TriMesh:
    """A UV sphere (for ground-truth meshes of analytic spheres)."""
    return ellipsoid_mesh(radii_m=(radius_m, radius_m, radius_m), centre_m=centre_m, segments=segments, rings=rings)


def ellipsoid_mesh(*, radii_m, centre_m=(0.0, 0.0, 0.0), segments: int = 64, rings: int = 32) -> TriMesh:
    rx, ry, rz = (float(v) for v in radii_m)
    if min(rx, ry, rz) <= 0:
        raise InputError(f"ellipsoid: radii must be > 0, got {radii_m}")
    t = np.linspace(-math.pi / 2, math.pi / 2, rings + 1)
    m = lathe(np.cos(t), np.sin(t), segments=segments)
    T = np.diag([rx, ry, rz, 1.0])
    T[:3, 3] = centre_m
    V = m.vertices @ T[:3, :3].T + T[:3, 3]
    return TriMesh(V, m.faces, _vertex_normals(V, m.faces), m.uv)


def fibre_tuft(
    *,
    count: int = 1500,
    length_m: float = 0.07,
    radius_m: float = 0.0003,
    core_radii_m=(0.045, 0.035, 0.045),
    core_centre_m=(0.0, 0.035, 0.0),
    droop: float = 0.5,
    points_per_fibre: int = 6,
    seed: int = 0,
) -> Fibres:
    """Fibres rooted on the upper part of an ellipsoidal core, leaving along the surface
    normal and drooping under gravity: a fur tuft whose silhouette is mostly sub-pixel
    strands (fractional alpha)."""
    if count < 1 or points_per_fibre < 2:
        raise InputError(f"fibres: count >= 1 and points_per_fibre >= 2 required, got {count}, {points_per_fibre}")
    rng = np.random.default_rng(seed)
    rx, ry, rz = core_radii_m
    c = np.asarray(core_centre_m, dtype=np.float64)
    # roots uniformly over directions with y > -0.2 (not under the core, which rests on the table)
    d = rng.normal(size=(count * 3, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 1] > -0.2][:count]
    while d.shape[0] < count:  # pragma: no cover - astronomically unlikely
        e = rng.normal(size=(count, 3))
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        d = np.concatenate([d, e[e[:, 1] > -0.2]])[:count]
    root = c + d * np.array([rx, ry, rz])
    n = d / np.array([rx, ry, rz]) ** 2
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    L = length_m * (0.7 + 0.6 * rng.random(count))
    t = np.linspace(0.0, 1.0, points_per_fibre)
    jitter = rng.normal(scale=0.15, size=(count, 3))
    direction = n + jitter
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    pts = root[:, None, :] + (L[:, None, None] * t[None, :, None]) * direction[:, None, :]
    pts[:, :, 1] -= droop * (L[:, None] * t[None, :]) ** 2 / max(length_m, 1e-9)
    pts[:, :, 1] = np.maximum(pts[:, :, 1], radius_m)  # stay above the table
    return Fibres(points=pts, radius_m=float(radius_m))


def tube_mesh(fibres: Fibres, *, sides: int = 3) -> TriMesh:
    """Closed-ish triangle tubes around each fibre polyline (ground truth for voxelising)."""
    P = fibres.points
    N, K, _ = P.shape
    tang = np.gradient(P, axis=1)
    tang /= np.maximum(np.linalg.norm(tang, axis=2, keepdims=True), 1e-30)
    ref = np.where(np.abs(tang[..., 1:2]) < 0.9, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    b1 = np.cross(tang, ref)
    b1 /= np.linalg.norm(b1, axis=2, keepdims=True)
    b2 = np.cross(tang, b1)
    ang = np.linspace(0, 2 * math.pi, sides, endpoint=False)
    ring = np.cos(ang)[None, None, :, None] * b1[:, :, None, :] + np.sin(ang)[None, None, :, None] * b2[:, :, None, :]
    V = (P[:, :, None, :] + fibres.radius_m * ring).reshape(-1, 3)
    faces = []
    for k in range(K - 1):
        for s in range(sides):
            a = k * sides + s
            b = k * sides + (s + 1) % sides
            c = (k + 1) * sides + s
            d = (k + 1) * sides + (s + 1) % sides
            faces += [(a, b, d), (a, d, c)]
    f0 = np.array(faces, dtype=np.int64)
    offs = (np.arange(N) * K * sides)[:, None, None]
    F = (f0[None] + offs).reshape(-1, 3).astype(np.int32)
    Nn = (ring.reshape(-1, 3)).copy()
    uv = np.zeros((V.shape[0], 2))
    return TriMesh(V, F, Nn, uv)


def merge_meshes(meshes) -> TriMesh:
    meshes = list(meshes)
    if not meshes:
        raise InputError("merge_meshes: no meshes")
    V, F, N, UV = [], [], [], []
    off = 0
    for m in meshes:
        V.append(m.vertices)
        F.append(m.faces + off)
        N.append(m.normals)
        UV.append(m.uv)
        off += m.vertices.shape[0]
    return TriMesh(np.concatenate(V), np.concatenate(F).astype(np.int32), np.concatenate(N), np.concatenate(UV))


# --------------------------------------------------------------------------- files


def write_ply_mesh(path, mesh: TriMesh, *, with_attributes: bool = True) -> None:
    """Binary little-endian PLY (x y z [nx ny nz u v], vertex_indices), written atomically.

    Mitsuba's ``ply`` plugin reads the normals and the ``u``/``v`` texture coordinates.
    """
    from plyfile import PlyData, PlyElement

    from ..imageio import atomic_path

    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if with_attributes:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4"), ("u", "f4"), ("v", "f4")]
    vert = np.empty(mesh.vertices.shape[0], dtype=fields)
    vert["x"], vert["y"], vert["z"] = mesh.vertices.T
    if with_attributes:
        vert["nx"], vert["ny"], vert["nz"] = mesh.normals.T
        vert["u"], vert["v"] = mesh.uv.T
    face = np.empty(mesh.faces.shape[0], dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = mesh.faces
    data = PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")], byte_order="<")
    with atomic_path(path) as tmp:
        data.write(str(tmp))


def read_ply_mesh(path) -> TriMesh:
    """Read a triangle PLY (positions required; normals and u/v optional)."""
    from plyfile import PlyData

    from ..errors import FormatError

    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        f = ply["face"].data
    except Exception as e:  # noqa: BLE001  plyfile raises PlyParseError, KeyError, ValueError, numpy errors...: re-raised, named
        raise FormatError(f"{path}: not a readable triangle PLY ({e})") from None
    V = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    key = "vertex_indices" if "vertex_indices" in f.dtype.names else f.dtype.names[0]
    faces = [np.asarray(x) for x in f[key]]
    if any(len(x) != 3 for x in faces):
        raise FormatError(f"{path}: only triangle faces are supported")
    F = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
    names = v.dtype.names
    if all(k in names for k in ("nx", "ny", "nz")):
        N = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float64)
    else:
        N = _vertex_normals(V, F)
    if "u" in names and "v" in names:
        UV = np.stack([v["u"], v["v"]], axis=1).astype(np.float64)
    else:
        UV = np.zeros((V.shape[0], 2))
    return TriMesh(V, F, N, UV)


def write_curves_txt(path, fibres: Fibres) -> None:
    """Mitsuba ``linearcurve`` text file: ``x y z radius`` per control point, a blank
    line between curves; written atomically."""
    from ..imageio import atomic_path

    P = fibres.points
    lines = []
    for fib in P:
        for p in fib:
            lines.append(f"{p[0]:.7g} {p[1]:.7g} {p[2]:.7g} {fibres.radius_m:.7g}")
        lines.append("")
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write("\n".join(lines))
