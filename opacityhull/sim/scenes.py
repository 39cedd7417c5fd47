"""Scene specs: which object, made of which materials, sits on the simulated rig.

A scene is a TOML file (or a built-in, ``builtin:NAME``, shipped in
``opacityhull/sim/data/scenes/NAME.toml``)::

    [scene]
    name = "diffuse"
    description = "textured Lambertian cup with concavities"

    [materials.clay]
    type = "diffuse"                     # see MATERIAL_TYPES
    texture = { type = "cells", counts = [12, 6], seed = 3 }   # or reflectance = [r, g, b]

    [[objects]]
    name = "cup"
    shape = "cup"                        # see SHAPE_KEYS
    material = "clay"
    radius_m = 0.06

Geometry is in the object frame (= rig frame at table angle 0): metres, +Y up, the
object resting on the table plane ``y = 0`` and fitting a ~0.2 m cube centred 0.08 m
above it. Everything is procedural or read from a PLY next to the TOML; nothing is
downloaded. Unknown tables, keys, material types or shapes raise
:class:`~opacityhull.errors.ConfigError` naming the file and the key.

This module is pure NumPy; :mod:`opacityhull.sim.render` turns a :class:`SceneSpec`
into Mitsuba objects.
"""

from __future__ import annotations

import functools
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar
from collections.abc import Callable, Mapping

import numpy as np

from ..charuco import CharucoSpec
from ..errors import ConfigError, InputError
from . import shapes as S

__all__ = [
    "SceneSpec",
    "parts_bounds",
    "MaterialSpec",
    "ObjectSpec",
    "TextureSpec",
    "Part",
    "load_scene",
    "builtin_names",
    "board_parts",
    "MATERIAL_TYPES",
    "DELTA_TYPES",
    "SHAPE_KEYS",
    "DATA_DIR",
]

_T = TypeVar("_T")

DATA_DIR = Path(__file__).parent / "data"
_SCENES_DIR = DATA_DIR / "scenes"

#: material type -> (effect class, allowed keys). Effect classes drive effect selection:
#: "diffuse" (Lambertian, opaque), "glossy" (rough or smooth reflection, opaque),
#: "transmissive" (light passes through: dielectrics).
MATERIAL_TYPES: dict[str, tuple[str, frozenset]] = {
    "diffuse": ("diffuse", frozenset({"reflectance", "texture"})),
    "plastic": ("glossy", frozenset({"diffuse", "texture", "ior"})),
    "roughplastic": ("glossy", frozenset({"diffuse", "texture", "ior", "roughness"})),
    "conductor": ("glossy", frozenset({"conductor", "specular"})),
    "roughconductor": ("glossy", frozenset({"conductor", "specular", "roughness"})),
    "dielectric": ("transmissive", frozenset({"ior", "tint"})),
    "roughdielectric": ("transmissive", frozenset({"ior", "tint", "roughness"})),
    "thindielectric": ("transmissive", frozenset({"ior", "tint"})),
}

#: Material types whose BSDF is a Dirac delta (smooth glass, polished metal): a ray meets
#: them only in one or two directions, so a *point* light can never be reached through
#: them — neither by a ray (the light has no area) nor by light sampling (the BSDF has no
#: spread). Effect selection uses this to leave the light array out of scenes made of
#: them alone.
DELTA_TYPES = frozenset({"dielectric", "thindielectric", "conductor"})

_COMMON_OBJECT_KEYS = frozenset({"name", "shape", "material"})
#: shape -> allowed parameter keys (besides name, shape, material)
SHAPE_KEYS: dict[str, frozenset] = {
    "sphere": frozenset({"radius_m", "centre_m"}),
    "disk": frozenset({"radius_m", "centre_m"}),
    "ellipsoid": frozenset({"radii_m", "centre_m"}),
    "cup": frozenset({"radius_m", "height_m", "wall_m", "flutes", "flute_depth", "segments"}),
    "dome": frozenset({"radius_m", "height_m", "segments"}),
    "bottle": frozenset({"radius_m", "height_m", "neck_radius_m", "segments"}),
    "torus": frozenset({"major_m", "minor_m", "centre_m"}),
    "fibres": frozenset(
        {"count", "length_m", "radius_m", "core_radii_m", "core_centre_m", "droop", "points_per_fibre", "seed"}
    ),
    "mesh": frozenset({"file", "scale", "offset_m"}),
    "board": frozenset(CharucoSpec.__dataclass_fields__),
}

_TEXTURE_KEYS = {
    "checker": frozenset({"type", "colours", "counts", "resolution"}),
    "cells": frozenset({"type", "counts", "seed", "lo", "hi", "line", "resolution"}),
    "image": frozenset({"type", "file"}),
}

_CONDUCTORS = ("Ag", "Al", "Au", "Cu", "CuZn", "Cr", "Hg", "Ni", "Pt", "Ti", "W", "none")


# --------------------------------------------------------------------------- specs


@dataclass(frozen=True)
class TextureSpec:
    """A procedural or image texture; :meth:`image` gives linear RGB (rows, cols, 3).

    Row 0 of the image is texture v = 1 (the top, as images are stored); the renderer
    flips rows for Mitsuba, whose bitmap row 0 is v = 0.
    """

    type: str
    params: Mapping[str, Any]
    base_dir: Path | None = None

    def image(self) -> np.ndarray:
        p = self.params
        if self.type == "checker":
            res = int(p.get("resolution", 512))
            nu, nv = (int(v) for v in p.get("counts", (8, 8)))
            ca, cb = (np.asarray(c, dtype=np.float32) for c in p.get("colours", ([0.8, 0.8, 0.8], [0.1, 0.1, 0.1])))
            v, u = np.mgrid[0:res, 0:res]
            m = ((u * nu // res) + (v * nv // res)) % 2 == 0
            return np.where(m[..., None], ca, cb).astype(np.float32)
        if self.type == "cells":
            res = int(p.get("resolution", 512))
            nu, nv = (int(v) for v in p.get("counts", (12, 6)))
            rng = np.random.default_rng(int(p.get("seed", 0)))
            lo, hi = float(p.get("lo", 0.15)), float(p.get("hi", 0.85))
            colours = lo + (hi - lo) * rng.random((nv, nu, 3))
            v, u = np.mgrid[0:res, 0:res]
            cu, cv = u * nu // res, v * nv // res
            img = colours[cv, cu].astype(np.float32)
            line = float(p.get("line", 0.08))  # dark grout lines, fraction of a cell
            fu = (u * nu / res) % 1.0
            fv = (v * nv / res) % 1.0
            grout = (fu < line) | (fv < line)
            img[grout] *= 0.25
            return img
        if self.type == "image":
            from ..imageio import read_image

            path = Path(p["file"])
            if not path.is_absolute() and self.base_dir is not None:
                path = self.base_dir / path
            img = read_image(path)
            return np.ascontiguousarray(img[:, :, :3] if img.shape[2] >= 3 else np.repeat(img[:, :, :1], 3, 2))
        raise ConfigError(f"texture type {self.type!r} unknown")  # validated at load; defensive


@dataclass(frozen=True)
class MaterialSpec:
    """A named material; ``type`` is a key of :data:`MATERIAL_TYPES`."""

    name: str
    type: str
    params: Mapping[str, Any] = field(default_factory=dict)
    texture: TextureSpec | None = None

    @property
    def effect_class(self) -> str:
        return MATERIAL_TYPES[self.type][0]

    @property
    def is_delta(self) -> bool:
        """The BSDF is a Dirac delta (see :data:`DELTA_TYPES`)."""
        return self.type in DELTA_TYPES


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    shape: str
    material: str | None
    params: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Part:
    """One renderable piece of the object, built from an :class:`ObjectSpec`.

    ``kind`` is ``"mesh"`` (``mesh``), ``"sphere"`` (analytic: ``centre_m``,
    ``radius_m``), ``"curves"`` (``fibres``) or ``"board"`` (``charuco``: a textured
    rectangle, placed by ``CharucoSpec.object_from_board``).
    """

    name: str
    kind: str
    material: MaterialSpec | None
    mesh: S.TriMesh | None = None
    centre_m: np.ndarray | None = None
    radius_m: float | None = None
    fibres: S.Fibres | None = None
    charuco: CharucoSpec | None = None

    def need(self, value: _T | None, what: str) -> _T:
        """``value`` (a field of this part that its ``kind`` requires), or a ConfigError
        naming the part and the missing field."""
        if value is None:
            raise ConfigError(f"part {self.name!r} (kind {self.kind!r}): {what} is missing")
        return value

    def triangle_mesh(self) -> S.TriMesh:
        """This part as triangles (spheres tessellated, fibres as thin tubes, the board as
        two triangles), object frame."""
        if self.kind == "mesh":
            return self.need(self.mesh, "mesh")
        if self.kind == "sphere":
            return S.uv_sphere_mesh(
                radius_m=self.need(self.radius_m, "radius_m"),
                centre_m=self.need(self.centre_m, "centre_m"),
                segments=128,
                rings=64,
            )
        if self.kind == "curves":
            return S.tube_mesh(self.need(self.fibres, "fibres"))
        if self.kind == "disk":
            n = 128
            t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
            V = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([np.sin(t), np.zeros(n), np.cos(t)], 1)])
            V = V * self.need(self.radius_m, "radius_m") + self.need(self.centre_m, "centre_m")
            F = np.array([[0, i + 1, (i + 1) % n + 1] for i in range(n)], dtype=np.int32)
            N = np.tile([0.0, 1.0, 0.0], (n + 1, 1))
            return S.TriMesh(V, F, N, np.zeros((n + 1, 2)))
        if self.kind == "board":
            charuco = self.need(self.charuco, "charuco")
            w, h = charuco.size_m
            T = charuco.object_from_board()
            local = np.array([[0, 0, 0, 1], [w, 0, 0, 1], [w, h, 0, 1], [0, h, 0, 1]], dtype=np.float64)
            V = (T @ local.T).T[:, :3]
            F = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int32)  # normal = -board z = +Y
            N = np.tile(-T[:3, 2], (4, 1))
            uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=np.float64)
            return S.TriMesh(V, F, N, uv)
        raise ConfigError(f"part {self.name!r}: unknown kind {self.kind!r}")


@dataclass(frozen=True)
class SceneSpec:
    """A parsed scene: materials and objects.

    Attributes
    ----------
    name, description : str
    source : str
        ``builtin:NAME`` or the TOML path it was read from.
    materials : tuple of MaterialSpec
    objects : tuple of ObjectSpec
    raw : dict
        The parsed TOML (for copying into ground truth).
    """

    name: str
    description: str
    source: str
    materials: tuple[MaterialSpec, ...]
    objects: tuple[ObjectSpec, ...]
    raw: dict = field(default_factory=dict, compare=False, repr=False)
    base_dir: Path | None = field(default=None, compare=False, repr=False)

    def material(self, name: str) -> MaterialSpec:
        for m in self.materials:
            if m.name == name:
                return m
        raise ConfigError(f"{self.source}: material {name!r} not defined (have {[m.name for m in self.materials]})")

    @property
    def effect_classes(self) -> frozenset:
        """Effect classes of the materials the objects actually use."""
        return frozenset(p.material.effect_class for p in self.parts if p.material is not None)

    @property
    def delta_only(self) -> bool:
        """Every part is made of a delta-BSDF material (smooth glass, polished metal):
        under point lights and black panels such an object shows nothing at all."""
        return bool(self.parts) and all(p.material is not None and p.material.is_delta for p in self.parts)

    @property
    def has_fibres(self) -> bool:
        return any(p.kind == "curves" for p in self.parts)

    @property
    def is_board(self) -> bool:
        return bool(self.parts) and all(p.kind == "board" for p in self.parts)

    @functools.cached_property
    def parts(self) -> tuple[Part, ...]:
        """The built geometry (computed once per spec)."""
        return tuple(_build_part(self, o) for o in self.objects)

    def triangle_mesh(self) -> S.TriMesh:
        """All parts as one triangle mesh in the object frame (ground truth ``object.ply``)."""
        return S.merge_meshes(p.triangle_mesh() for p in self.parts)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the object, metres, object frame."""
        return parts_bounds(self.parts)

    def to_toml_dict(self) -> dict:
        """A TOML-ready copy with file paths made absolute (for ``groundtruth/scene.toml``)."""
        d: dict = _deepcopy(self.raw)
        for o in d.get("objects", []):
            if "file" in o and self.base_dir is not None and not Path(o["file"]).is_absolute():
                o["file"] = str((self.base_dir / o["file"]).resolve())
        for m in d.get("materials", {}).values():
            t = m.get("texture") if isinstance(m, dict) else None
            if isinstance(t, dict) and "file" in t and self.base_dir is not None and not Path(t["file"]).is_absolute():
                t["file"] = str((self.base_dir / t["file"]).resolve())
        d.setdefault("scene", {})["source"] = self.source
        return d


def parts_bounds(parts) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) of ``parts`` (metres, object frame): exact for
    spheres, disks and meshes, fibre polylines padded by their radius.

    Raises
    ------
    InputError
        No parts (nothing has bounds).
    """
    if not parts:
        raise InputError("parts_bounds(): no parts")
    lo, hi = [], []
    for p in parts:
        if p.kind == "sphere":
            lo.append(p.centre_m - p.radius_m)
            hi.append(p.centre_m + p.radius_m)
        elif p.kind == "disk":
            lo.append(p.centre_m - np.array([p.radius_m, 0.0, p.radius_m]))
            hi.append(p.centre_m + np.array([p.radius_m, 0.0, p.radius_m]))
        elif p.kind == "curves":
            P = p.fibres.points.reshape(-1, 3)
            lo.append(P.min(0) - p.fibres.radius_m)
            hi.append(P.max(0) + p.fibres.radius_m)
        else:
            m = p.triangle_mesh()
            lo.append(m.vertices.min(0))
            hi.append(m.vertices.max(0))
    return np.min(lo, axis=0), np.max(hi, axis=0)


def _deepcopy(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _deepcopy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_deepcopy(v) for v in x]
    return x


# --------------------------------------------------------------------------- parsing


def builtin_names() -> list[str]:
    """Names of the built-in scenes (``builtin:NAME``)."""
    return sorted(p.stem for p in _SCENES_DIR.glob("*.toml"))


def load_scene(spec: str | Path) -> SceneSpec:
    """Load a scene from ``builtin:NAME`` or a TOML path.

    Raises
    ------
    ConfigError
        Unknown built-in, unreadable TOML, unknown table/key, unknown material type or
        shape, an object naming an undefined material, bad values. The message names
        the file and the key.
    """
    s = str(spec)
    if s.startswith("builtin:"):
        name = s[len("builtin:") :]
        path = _SCENES_DIR / f"{name}.toml"
        if not path.is_file():
            raise ConfigError(f"scene {s!r}: no built-in scene {name!r} (built-ins: {builtin_names()})")
        source = s
    else:
        path = Path(s)
        if not path.is_file():
            raise ConfigError(
                f"scene file {path} not found (give a TOML path or builtin:NAME, built-ins: {builtin_names()})"
            )
        source = str(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid TOML ({e})") from None
    return parse_scene(raw, where=str(path), source=source, base_dir=path.parent)


def _check_keys(where: str, d: Mapping, allowed) -> None:
    unknown = sorted(set(d) - set(allowed))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _rgb(where: str, v) -> tuple[float, float, float]:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v, v, v]
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected a number or [r, g, b], got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ConfigError(f"{where}: expected a number or [r, g, b] of finite values >= 0, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _number(where: str, v, *, lo=None, hi=None, integer=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{where}: expected a number, got {v!r}")
    if integer and int(v) != v:
        raise ConfigError(f"{where}: expected an integer, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{where}: must be in [{lo}, {hi}], got {v}")
    return int(v) if integer else float(v)


def _vec3(where: str, v) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected [x, y, z], got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{where}: expected [x, y, z] of finite numbers, got {v!r}")
    return a


def _parse_material(where: str, name: str, d: Mapping, base_dir: Path | None) -> MaterialSpec:
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where}: expected a table")
    if "type" not in d:
        raise ConfigError(f"{where}.type: missing (one of {sorted(MATERIAL_TYPES)})")
    mtype = d["type"]
    if mtype not in MATERIAL_TYPES:
        raise ConfigError(f"{where}.type: unknown material type {mtype!r}; expected one of {sorted(MATERIAL_TYPES)}")
    allowed = MATERIAL_TYPES[mtype][1] | {"type"}
    _check_keys(where, d, allowed)
    params: dict[str, Any] = {}
    texture = None
    for k, v in d.items():
        w = f"{where}.{k}"
        if k == "type":
            continue
        if k in ("reflectance", "diffuse", "specular", "tint"):
            params[k] = _rgb(w, v)
            if max(params[k]) > 1.0 and k != "specular":
                raise ConfigError(f"{w}: a reflectance above 1 creates energy, got {v!r}")
        elif k == "roughness":
            params[k] = _number(w, v, lo=1e-3, hi=1.0)
        elif k == "ior":
            params[k] = _number(w, v, lo=1.0, hi=4.0)
        elif k == "conductor":
            if v not in _CONDUCTORS:
                raise ConfigError(f"{w}: unknown conductor {v!r}; expected one of {list(_CONDUCTORS)}")
            params[k] = v
        elif k == "texture":
            texture = _parse_texture(w, v, base_dir)
    if "texture" in d and ("reflectance" in d or "diffuse" in d):
        raise ConfigError(f"{where}: give either texture or a constant reflectance/diffuse colour, not both")
    return MaterialSpec(name=name, type=mtype, params=params, texture=texture)


def _parse_texture(where: str, v, base_dir) -> TextureSpec:
    if not isinstance(v, Mapping) or "type" not in v:
        raise ConfigError(f"{where}: expected a table with a 'type' (one of {sorted(_TEXTURE_KEYS)})")
    t = v["type"]
    if t not in _TEXTURE_KEYS:
        raise ConfigError(f"{where}.type: unknown texture type {t!r}; expected one of {sorted(_TEXTURE_KEYS)}")
    _check_keys(where, v, _TEXTURE_KEYS[t])
    p = dict(v)
    if "counts" in p:
        c = p["counts"]
        if not (isinstance(c, list) and len(c) == 2 and all(isinstance(x, int) and x >= 1 for x in c)):
            raise ConfigError(f"{where}.counts: expected [nu, nv] positive integers, got {c!r}")
    if "resolution" in p:
        _number(f"{where}.resolution", p["resolution"], lo=2, hi=8192, integer=True)
    if "colours" in p:
        cs = p["colours"]
        if not (isinstance(cs, list) and len(cs) == 2):
            raise ConfigError(f"{where}.colours: expected two [r, g, b] colours")
        for i, c in enumerate(cs):
            _rgb(f"{where}.colours[{i}]", c)
    if t == "image":
        f = Path(p.get("file", ""))
        full = f if f.is_absolute() or base_dir is None else base_dir / f
        if not full.is_file():
            raise ConfigError(f"{where}.file: texture image {full} not found")
    return TextureSpec(type=t, params=p, base_dir=base_dir)


def parse_scene(raw: Mapping, *, where: str = "scene", source: str = "", base_dir: Path | None = None) -> SceneSpec:
    """Validate a parsed scene TOML table (see the module docstring) into a :class:`SceneSpec`."""
    _check_keys(where, raw, {"scene", "materials", "objects"})
    head = raw.get("scene", {})
    if not isinstance(head, Mapping):
        raise ConfigError(f"{where}: [scene] must be a table")
    _check_keys(f"{where}: scene", head, {"name", "description", "source"})
    mats_raw = raw.get("materials", {})
    if not isinstance(mats_raw, Mapping):
        raise ConfigError(f"{where}: [materials] must be a table of named materials")
    materials = tuple(_parse_material(f"{where}: materials.{n}", n, m, base_dir) for n, m in mats_raw.items())
    names = {m.name for m in materials}
    objs_raw = raw.get("objects", [])
    if not isinstance(objs_raw, list) or not objs_raw:
        raise ConfigError(f"{where}: at least one [[objects]] entry is required")
    objects = []
    seen = set()
    for i, o in enumerate(objs_raw):
        w = f"{where}: objects[{i}]"
        if not isinstance(o, Mapping):
            raise ConfigError(f"{w}: expected a table")
        shape = o.get("shape")
        if shape not in SHAPE_KEYS:
            raise ConfigError(f"{w}.shape: unknown shape {shape!r}; expected one of {sorted(SHAPE_KEYS)}")
        _check_keys(w, o, _COMMON_OBJECT_KEYS | SHAPE_KEYS[shape])
        oname = str(o.get("name", f"object{i}"))
        if oname in seen:
            raise ConfigError(f"{w}.name: duplicate object name {oname!r}")
        seen.add(oname)
        mat = o.get("material")
        if shape == "board":
            if mat is not None:
                raise ConfigError(
                    f"{w}.material: a board is printed paper (diffuse, from its ChArUco image); remove the material key"
                )
        elif mat is None:
            raise ConfigError(f"{w}.material: missing (one of {sorted(names)})")
        elif mat not in names:
            raise ConfigError(
                f"{w}.material: material {mat!r} is not defined under [materials] (defined: {sorted(names)})"
            )
        params = {k: v for k, v in o.items() if k not in _COMMON_OBJECT_KEYS}
        objects.append(ObjectSpec(name=oname, shape=shape, material=mat, params=params))
    spec = SceneSpec(
        name=str(head.get("name", Path(where).stem)),
        description=str(head.get("description", "")),
        source=source or where,
        materials=materials,
        objects=tuple(objects),
        raw=_deepcopy(dict(raw)),
        base_dir=base_dir,
    )
    # build now so bad shape parameters fail at load time, naming the key
    for i, o in enumerate(spec.objects):
        try:
            _build_part(spec, o)
        except ConfigError:
            raise
        except (ValueError, TypeError) as e:
            raise ConfigError(f"{where}: objects[{i}] ({o.name}): {e}") from None
    return spec


# --------------------------------------------------------------------------- building


_BOARD_MATERIAL = MaterialSpec(name="board_paper", type="diffuse", params={"reflectance": (0.8, 0.8, 0.8)})


def _build_part(scene: SceneSpec, o: ObjectSpec) -> Part:
    cache = scene.__dict__.setdefault("_part_cache", {})
    if o.name in cache:
        return cache[o.name]
    part = _build_part_uncached(scene, o)
    cache[o.name] = part
    return part


_SEGMENTS = {"lo": 8, "hi": 1024, "integer": True}

#: shape -> (mesh builder, its parameters: key, default, bounds checked by ``_number``)
_SOLIDS: dict[str, tuple[Callable[..., S.TriMesh], tuple[tuple[str, float, dict], ...]]] = {
    "cup": (
        S.cup_mesh,
        (
            ("radius_m", 0.06, {"lo": 1e-3}),
            ("height_m", 0.15, {"lo": 1e-3}),
            ("wall_m", 0.012, {"lo": 1e-4}),
            ("flutes", 7, {"lo": 0, "hi": 64, "integer": True}),
            ("flute_depth", 0.12, {"lo": 0.0, "hi": 0.5}),
            ("segments", 112, _SEGMENTS),
        ),
    ),
    "dome": (
        S.dome_mesh,
        (("radius_m", 0.065, {"lo": 1e-3}), ("height_m", 0.16, {"lo": 1e-3}), ("segments", 96, _SEGMENTS)),
    ),
    "bottle": (
        S.bottle_mesh,
        (
            ("radius_m", 0.055, {"lo": 1e-3}),
            ("height_m", 0.17, {"lo": 1e-3}),
            ("neck_radius_m", 0.022, {"lo": 1e-4}),
            ("segments", 96, _SEGMENTS),
        ),
    ),
}


def _build_part_uncached(scene: SceneSpec, o: ObjectSpec) -> Part:
    where = f"{scene.source}: objects.{o.name}"
    p = o.params
    mat = scene.material(o.material) if o.material is not None else None

    def num(k, default, **kw) -> Any:  # an int where integer=True: typed Any for both uses
        return _number(f"{where}.{k}", p[k], **kw) if k in p else default

    if o.shape == "sphere":
        r = num("radius_m", 0.08, lo=1e-4)
        c = _vec3(f"{where}.centre_m", p["centre_m"]) if "centre_m" in p else np.array([0.0, r, 0.0])
        return Part(o.name, "sphere", mat, centre_m=c, radius_m=r)
    if o.shape == "disk":
        r = num("radius_m", 0.1, lo=1e-4)
        c = _vec3(f"{where}.centre_m", p["centre_m"]) if "centre_m" in p else np.zeros(3)
        return Part(o.name, "disk", mat, centre_m=c, radius_m=r)
    if o.shape == "ellipsoid":
        radii = _vec3(f"{where}.radii_m", p.get("radii_m", [0.07, 0.08, 0.07]))
        if np.any(radii <= 0):
            raise ConfigError(f"{where}.radii_m: must be > 0, got {radii.tolist()}")
        c = _vec3(f"{where}.centre_m", p["centre_m"]) if "centre_m" in p else np.array([0.0, radii[1], 0.0])
        return Part(o.name, "mesh", mat, mesh=S.ellipsoid_mesh(radii_m=radii, centre_m=c, segments=96, rings=48))
    if o.shape in _SOLIDS:
        make, keys = _SOLIDS[o.shape]
        m = make(**{k: num(k, default, **bounds) for k, default, bounds in keys})
        return Part(o.name, "mesh", mat, mesh=m)
    if o.shape == "torus":
        c = _vec3(f"{where}.centre_m", p.get("centre_m", [0.0, 0.01, 0.0]))
        m = S.torus_mesh(major_m=num("major_m", 0.07, lo=1e-4), minor_m=num("minor_m", 0.01, lo=1e-5), centre_m=c)
        return Part(o.name, "mesh", mat, mesh=m)
    if o.shape == "fibres":
        f = S.fibre_tuft(
            count=num("count", 1500, lo=1, hi=200000, integer=True),
            length_m=num("length_m", 0.05, lo=1e-4),
            radius_m=num("radius_m", 0.0003, lo=1e-6),
            core_radii_m=tuple(_vec3(f"{where}.core_radii_m", p.get("core_radii_m", [0.04, 0.035, 0.04]))),
            core_centre_m=tuple(_vec3(f"{where}.core_centre_m", p.get("core_centre_m", [0.0, 0.035, 0.0]))),
            droop=num("droop", 0.5, lo=0.0, hi=10.0),
            points_per_fibre=num("points_per_fibre", 6, lo=2, hi=64, integer=True),
            seed=num("seed", 0, lo=0, integer=True),
        )
        return Part(o.name, "curves", mat, fibres=f)
    if o.shape == "mesh":
        if "file" not in p:
            raise ConfigError(f"{where}.file: missing (a triangle PLY, relative to the scene file)")
        path = Path(p["file"])
        if not path.is_absolute() and scene.base_dir is not None:
            path = scene.base_dir / path
        if not path.is_file():
            raise ConfigError(f"{where}.file: mesh {path} not found")
        m = S.read_ply_mesh(path)
        T = np.eye(4)
        T[:3, :3] *= num("scale", 1.0, lo=1e-9)
        if "offset_m" in p:
            T[:3, 3] = _vec3(f"{where}.offset_m", p["offset_m"])
        return Part(o.name, "mesh", mat, mesh=m.transformed(T))
    if o.shape == "board":
        try:
            spec = CharucoSpec.from_dict(dict(p), where=where)
        except TypeError as e:
            raise ConfigError(f"{where}: {e}") from None
        return Part(o.name, "board", _BOARD_MATERIAL, charuco=spec)
    raise ConfigError(f"{where}.shape: unknown shape {o.shape!r}")  # unreachable after validation


def board_parts(charuco: CharucoSpec) -> tuple[Part, ...]:
    """The parts of a ChArUco board placed on the table (``operator("place_board")``)."""
    return (Part("charuco_board", "board", _BOARD_MATERIAL, charuco=charuco),)
