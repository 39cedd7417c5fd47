"""The opacity-hull model on disk: written by ``reconstruct``, read by ``render`` and
``relight``.

Layout of a model folder::

    model.toml              [model] format, units, software version (no time:
                            report.json records when it was built, #35);
                            [provenance] session, rig source, build options
                            ([provenance.build_config] a table, the options that
                            were None listed in build_config_none; before: a JSON
                            string, still read: OpacityHullModel.build_config);
                            [rig] rig geometry table (riggeometry schema);
                            [[views]] id, camera, table_deg, image (in views order);
                            [reflectance] present, lights = [{key, light_id, array_deg}],
                            storage ("layers" | "pca"; absent: layers), with pca:
                            pca_error_target or pca_rank, pca_block (px, 0: per
                            view), rank_max, rel_error_max, values_ratio,
                            [[reflectance.pca_views]] {id, rank (max over blocks),
                            rank_mean, rel_error, box};
                            [storage] pixel_type ("half" | "float"), clamped_values,
                            clamped = [{file, values, max_abs}] (absent: float)
    surfels.ply             binary PLY, element vertex: x y z nx ny nz radius (float32)
                            and vis_000 .. vis_NNN (uint8): the visibility bit vector,
                            bit v of byte v // 8 (LSB first) set when view v sees the
                            surfel (depth-tested, not just in the frustum)
    cameras/                COLMAP text model of all views; image NAME = view id; the
                            order of images.txt is the order of the views (bit index)
    views/<view id>.exr     opacity light field sample of that view: RGBA (half or
                            float32 pixels, ``[storage] pixel_type``),
                            alpha from the matte; colour premultiplied by alpha
                            (OpenEXR's convention; format 1 stored straight colour),
                            header ``chromaticities`` = Rec.709 primaries, D65 white
    reflectance/<view id>.exr   one layer per light sample (``<key>.R/G/B``): the
                            one-light-at-a-time radiance as observed over black
                            backdrops, i.e. premultiplied by alpha; header attributes
                            ``view``, ``tableAngleDeg``, ``chromaticities`` and per layer
                            ``<key>.lightId`` (int), ``<key>.arrayAngleDeg`` (float),
                            ``<key>.lightIntensity`` (float, calibrated relative output),
                            ``<key>.lightOutputRGB`` (v3f, intensity × colour) and, when
                            the model has a rig, ``<key>.lightDirection`` (v3f, unit,
                            object frame at this view's table angle, towards the light)
                            and ``<key>.lightPosition`` (v3f, metres, same frame);
                            pixels half or float32 like the views. With
                            ``[reflectance] storage = "pca"`` the file holds instead a
                            blockwise PCA of the view's stack, two parts: ``basis``
                            (layers ``pc000 .. pc<R-1>`` over the data window = the
                            stack's non-zero box) and ``coefficients`` (a pixel per
                            block, channels ``<key>.c<j>``);
                            :mod:`opacityhull.reflectance_pca` describes it
    calibration/<camera>.yaml   rig cameras (OpenCV YAML, world_from_cam = rig_from_cam)
    report.json             metrics and timings of the build
    pictures/               contact sheets, overlays, plots

World frame = object frame (rig frame at table angle 0), metres.

Storage: ``views/`` and ``reflectance/`` hold one pixel type, ``[storage] pixel_type``.
The values are the same in both: linear premultiplied RGBA, and radiance at full DMX
level; there is no extra scale or offset, a reader widens half to float32 and uses the
numbers as they are. Half keeps 11 significant bits (relative step 2**-11 ≈ 4.9e-4,
absolute 6e-8 below 6.1e-5) and tops out at 65504: finite values beyond it are clamped to
±65504 with a :class:`~opacityhull.imageio.HalfOverflowWarning` naming the file, and
listed in ``[storage] clamped``; NaN and ±Inf are stored as they are, as in float32.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args
from collections.abc import Callable, Sequence

import numpy as np

from . import __version__
from .camera import Camera, read_colmap_text, write_colmap_text
from .errors import FormatError, InputError, ShapeError, check_shape
from .reflectance_pca import (
    DEFAULT_PCA_BLOCK,
    DEFAULT_PCA_ERROR,
    PCA_FORMAT,
    REFLECTANCE_STORAGES,
    ReflectanceStorage,
    check_pca_options,
    read_reflectance_pca,
    write_reflectance_pca,
)
from .riggeometry import RigGeometry
from .tomlio import read_toml

log = logging.getLogger(__name__)

__all__ = [
    "BUILD_DIR",
    "FILLED_HOLES",
    "OPEN_HOLES",
    "read_hole_masks",
    "write_hole_masks",
    "MODEL_FORMAT",
    "READABLE_FORMATS",
    "Surfels",
    "ViewInfo",
    "LightSample",
    "OpacityHullModel",
    "write_surfels_ply",
    "read_surfels_ply",
    "write_model",
    "copy_model",
    "light_key",
    "Storage",
    "STORAGE_TYPES",
    "ReflectanceStorage",
    "REFLECTANCE_STORAGES",
]

MODEL_FORMAT = "opacityhull-model/2"
#: Formats :meth:`OpacityHullModel.open` reads. 1: views store straight colour; 2: views
#: store premultiplied colour with a chromaticities attribute, reflectance layers carry
#: their light's metadata.
READABLE_FORMATS = ("opacityhull-model/1", MODEL_FORMAT)

#: Below this alpha a premultiplied view texel has no recoverable straight colour (0 is
#: returned): ``premul / alpha`` would only amplify rounding.


#: Pixel type of ``views/`` and ``reflectance/``: 16-bit half or 32-bit float EXR.
Storage = Literal["half", "float"]
STORAGE_TYPES: tuple[str, ...] = get_args(Storage)
#: ``[storage] clamped`` lists at most this many files (the count covers them all).
MAX_CLAMPED_LISTED = 100


def light_key(light_id: int, array_deg: float) -> str:
    """Layer name of a light sample in ``reflectance/<view>.exr``: ``a045p000_l2``
    (array angle with ``p`` for the decimal point, since EXR layer names use dots)."""
    return f"a{float(array_deg) % 360.0:07.3f}".replace(".", "p") + f"_l{int(light_id)}"


# --------------------------------------------------------------------------- surfels


@dataclass
class Surfels:
    """Surfel set of the opacity hull.

    Attributes
    ----------
    positions : (N, 3) float32, metres, object frame.
    normals : (N, 3) float32, unit, pointing out of the hull.
    radii : (N,) float32, metres; discs of this radius cover the surface without holes.
    visibility : (N, ceil(V / 8)) uint8, packed bits (view v → byte v // 8, bit v % 8).
    n_views : V.
    depth_m : (N,) float32 ≥ 0 or None, metres: the photo-consistent surface lies this far
        inside the hull along −normal (:func:`opacityhull.reconstruct.photo.refine_surfels`).
        The surfels themselves stay on the hull, whose outline and opacity are exact in
        every captured view; the renderer fetches colour at ``positions − depth_m·normals``
        (the "shading surface"), which is where the views' colours agree.
    """

    positions: np.ndarray
    normals: np.ndarray
    radii: np.ndarray
    visibility: np.ndarray
    n_views: int
    depth_m: np.ndarray | None = None

    def __post_init__(self):
        self.positions = np.ascontiguousarray(self.positions, dtype=np.float32)
        n = self.positions.shape[0]
        check_shape("positions", self.positions, (n, 3))
        self.normals = np.ascontiguousarray(self.normals, dtype=np.float32)
        check_shape("normals", self.normals, (n, 3))
        self.radii = np.ascontiguousarray(self.radii, dtype=np.float32).reshape(-1)
        check_shape("radii", self.radii, (n,))
        nb = (int(self.n_views) + 7) // 8
        self.visibility = np.ascontiguousarray(self.visibility, dtype=np.uint8)
        if self.visibility.ndim == 2 and self.visibility.shape[1] == self.n_views and self.n_views != nb:
            raise ShapeError("visibility looks unpacked (N, V); use Surfels.from_bool()")
        check_shape("visibility", self.visibility, (n, nb))
        if self.depth_m is not None:
            self.depth_m = np.ascontiguousarray(self.depth_m, dtype=np.float32).reshape(-1)
            check_shape("depth_m", self.depth_m, (n,))
            if not (np.isfinite(self.depth_m).all() and (self.depth_m >= 0).all()):
                raise ShapeError("depth_m must be finite and >= 0 (metres inside the hull along -normal)")

    def shading_positions(self) -> np.ndarray:
        """(N, 3) float32 points where colour is fetched: on the photo-consistent surface
        when ``depth_m`` is set, else the surfel centres."""
        if self.depth_m is None:
            return self.positions
        return np.ascontiguousarray(self.positions - self.depth_m[:, None] * self.normals, dtype=np.float32)

    def __len__(self) -> int:
        return self.positions.shape[0]

    @classmethod
    def from_bool(cls, positions, normals, radii, visible_bool) -> Surfels:
        vb = np.asarray(visible_bool, dtype=bool)
        check_shape("visible_bool", vb, (np.shape(positions)[0], None))
        return cls(positions, normals, radii, pack_visibility(vb), vb.shape[1])

    def visible_bool(self) -> np.ndarray:
        """(N, V) bool visibility matrix."""
        return unpack_visibility(self.visibility, self.n_views)

    def visible_in(self, view: int) -> np.ndarray:
        """(N,) bool: surfels seen by ``view``."""
        if not 0 <= view < self.n_views:
            raise InputError(f"view index {view} out of range [0, {self.n_views})")
        return (self.visibility[:, view // 8] >> (view % 8)) & 1 == 1

    def subset(self, mask) -> Surfels:
        return Surfels(
            self.positions[mask],
            self.normals[mask],
            self.radii[mask],
            self.visibility[mask],
            self.n_views,
            None if self.depth_m is None else self.depth_m[mask],
        )


def pack_visibility(visible_bool: np.ndarray) -> np.ndarray:
    return np.packbits(np.asarray(visible_bool, dtype=bool), axis=1, bitorder="little")


def unpack_visibility(packed: np.ndarray, n_views: int) -> np.ndarray:
    return np.unpackbits(packed, axis=1, count=n_views, bitorder="little").astype(bool)


def write_surfels_ply(path, surfels: Surfels) -> None:
    """Binary little-endian PLY with the visibility bit vector (atomic)."""
    from plyfile import PlyData, PlyElement

    from .imageio import atomic_path

    nb = surfels.visibility.shape[1]
    dtype = [(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz", "radius")] + [
        (f"vis_{i:03d}", "u1") for i in range(nb)
    ]
    if surfels.depth_m is not None:
        dtype.append(("depth", "f4"))
    arr = np.empty(len(surfels), dtype=dtype)
    if surfels.depth_m is not None:
        arr["depth"] = surfels.depth_m
    for i, k in enumerate("xyz"):
        arr[k] = surfels.positions[:, i]
        arr["n" + k] = surfels.normals[:, i]
    arr["radius"] = surfels.radii
    for i in range(nb):
        arr[f"vis_{i:03d}"] = surfels.visibility[:, i]
    el = PlyElement.describe(arr, "vertex", comments=[f"opacityhull surfels; n_views {surfels.n_views}"])
    with atomic_path(path) as tmp:
        PlyData([el], text=False, byte_order="<", comments=[f"n_views {surfels.n_views}"]).write(str(tmp))


def read_ply(path, *, what: str, elements: Sequence[str]):
    """The PLY at ``path`` and the data of its ``elements``.

    Raises :class:`~opacityhull.errors.FormatError` naming ``what`` (e.g. "surfel file") and
    the path when the file is missing, or the path and the reason when it is not a PLY or
    lacks an element.
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{what} {path} not found")
    try:
        ply = PlyData.read(str(path))
        return ply, [ply[e].data for e in elements]
    except Exception as e:  # noqa: BLE001  plyfile raises PlyParseError, KeyError, ValueError, numpy errors...: re-raised, named
        has = f"a {elements[0]} element" if len(elements) == 1 else f"{' and '.join(elements)} elements"
        raise FormatError(f"{path}: not a readable PLY with {has} ({e})") from None


def read_surfels_ply(path) -> Surfels:
    path = Path(path)
    ply, (v,) = read_ply(path, what="surfel file", elements=("vertex",))
    n_views = None
    for c in ply.comments:
        if c.startswith("n_views "):
            try:
                n_views = int(c.split()[1])
            except (ValueError, IndexError):
                raise FormatError(f"{path}: header comment {c!r}: expected 'n_views N'") from None
    names = v.dtype.names
    for k in ("x", "y", "z", "nx", "ny", "nz", "radius"):
        if k not in names:
            raise FormatError(f"{path}: vertex property {k!r} missing")
    vis_cols = sorted(n for n in names if n.startswith("vis_"))
    if n_views is None:
        n_views = 8 * len(vis_cols)
    pos = np.stack([v["x"], v["y"], v["z"]], axis=1)
    nrm = np.stack([v["nx"], v["ny"], v["nz"]], axis=1)
    vis = np.stack([v[c] for c in vis_cols], axis=1) if vis_cols else np.zeros((len(v), 0), np.uint8)
    depth = None
    if "depth" in names:
        depth = np.asarray(v["depth"], np.float32)
        if not (np.isfinite(depth).all() and (depth >= 0).all()):
            raise FormatError(f"{path}: vertex property 'depth' must be finite and >= 0 (metres inside the hull)")
    try:
        return Surfels(pos, nrm, v["radius"], vis, n_views, depth)
    except InputError as e:  # a damaged header (a property's type or count): name the file (#35 fuzzing)
        raise FormatError(f"{path}: {e}") from None


# --------------------------------------------------------------------------- views


@dataclass(frozen=True)
class ViewInfo:
    """One captured view (c, a) of the model."""

    index: int
    id: str
    camera_index: int
    table_deg: float
    camera: Camera


@dataclass(frozen=True)
class LightSample:
    """One light direction of the reflectance field: light ``light_id`` at array angle ``array_deg``."""

    key: str
    light_id: int
    array_deg: float


class OpacityHullModel:
    """A model folder opened for reading. Use :meth:`open`."""

    def __init__(self, root: Path, meta: dict, views: list[ViewInfo]):
        self.root = root
        self.meta = meta
        self.views = views
        self._surfels: Surfels | None = None

    @classmethod
    def open(cls, root) -> OpacityHullModel:
        root = Path(root)
        p = root / "model.toml"
        if not p.is_file():
            raise FormatError(f"{root} is not a model: {p} not found")
        meta = read_toml(p, error=FormatError, what="model.toml")
        fmt = meta.get("model", {}).get("format")
        if fmt not in READABLE_FORMATS:
            raise FormatError(f"{p}: model format {fmt!r}, expected one of {', '.join(map(repr, READABLE_FORMATS))}")
        cams = dict(read_colmap_text(root / "cameras"))
        views = []
        for i, v in enumerate(meta.get("views", [])):
            vid = v["id"]
            if vid not in cams:
                raise FormatError(f"{root / 'cameras' / 'images.txt'}: view {vid!r} listed in model.toml is missing")
            views.append(ViewInfo(i, vid, int(v["camera"]), float(v["table_deg"]), cams[vid].with_name(vid)))
        if not views:
            raise FormatError(f"{p}: no [[views]]")
        return cls(root, meta, views)

    # ---- geometry
    @property
    def surfels(self) -> Surfels:
        if self._surfels is None:
            self._surfels = read_surfels_ply(self.root / "surfels.ply")
            if self._surfels.n_views != len(self.views):
                raise FormatError(
                    f"{self.root / 'surfels.ply'}: visibility has {self._surfels.n_views} views, model has {len(self.views)}"
                )
        return self._surfels

    @property
    def geometry(self) -> RigGeometry | None:
        if "rig" not in self.meta:
            return None
        return RigGeometry.from_dict(self.meta["rig"], where=f"{self.root / 'model.toml'}:rig")

    def view_index(self, view_id: str) -> int:
        for v in self.views:
            if v.id == view_id:
                return v.index
        raise InputError(f"view {view_id!r} not in model {self.root} (views: {[v.id for v in self.views][:8]}...)")

    def find_view(self, camera: int, table_deg: float) -> int:
        for v in self.views:
            if v.camera_index == camera and abs(((v.table_deg - table_deg) + 180) % 360 - 180) < 1e-6:
                return v.index
        raise InputError(f"no view (camera {camera}, table {table_deg} deg) in model {self.root}")

    def _meta_choice(self, table: str, key: str, *, default: str, choices: tuple[str, ...]) -> str:
        """``model.toml`` ``[table] key`` (``default`` when absent); raises
        :class:`FormatError` naming the file, the key and the choices when it is none of ``choices``."""
        value = self.meta.get(table, {}).get(key, default)
        if value not in choices:
            raise FormatError(
                f"{self.root / 'model.toml'}: {table}.{key} {value!r}, expected one of {', '.join(map(repr, choices))}"
            )
        return str(value)

    # ---- appearance
    @property
    def format(self) -> str:
        return str(self.meta["model"]["format"])

    @property
    def storage(self) -> str:
        """Pixel type of ``views/`` and ``reflectance/``: "half" or "float" (models
        written before ``[storage]`` existed are float32)."""
        return self._meta_choice("storage", "pixel_type", default="float", choices=STORAGE_TYPES)

    @property
    def storage_clamped(self) -> list[dict]:
        """The files whose values were clamped to the half range when written:
        ``[{"file", "values", "max_abs"}]`` (empty for float storage)."""
        return list(self.meta.get("storage", {}).get("clamped", []))

    @property
    def build_config(self) -> dict:
        """The build options the model was made with (``BuildConfig.to_dict()``), None
        values included; {} when not recorded. Reads the TOML table (and its
        ``build_config_none`` list) and the JSON string older models stored."""
        import json

        from .tomlio import join_nones

        prov = self.meta.get("provenance", {})
        raw = prov.get("build_config")
        if not raw:
            return {}
        if isinstance(raw, dict):
            return join_nones(raw, prov.get("build_config_none", ()))
        try:
            d = json.loads(raw)
        except (TypeError, ValueError) as e:
            raise FormatError(f"{self.root / 'model.toml'}: provenance.build_config is not JSON ({e})") from None
        if not isinstance(d, dict):
            raise FormatError(f"{self.root / 'model.toml'}: provenance.build_config is not a table")
        return d

    @property
    def views_premultiplied(self) -> bool:
        """Whether ``views/*.exr`` store premultiplied colour (format 2 on)."""
        return self.format != "opacityhull-model/1"

    def view_path(self, i: int) -> Path:
        return self.root / "views" / f"{self.views[i].id}.exr"

    def load_view_rgba(self, i: int) -> np.ndarray:
        """(H, W, 4) float32 RGBA of view ``i``, straight alpha. From a premultiplied
        (format 2) file through :func:`opacityhull.imageio.straight_from_premul` (colour 0
        where alpha < its cut-off, 2⁻¹²; built models' colour is 0 there already, below the
        build's matte floor ``alpha_eps``)."""
        from .imageio import read_exr, straight_from_premul

        a = read_exr(self.view_path(i), channels="RGBA")
        if self.views_premultiplied:
            return straight_from_premul(a)
        return a

    def load_views_premul(self, indices: Sequence[int] | None = None) -> list[np.ndarray]:
        """Premultiplied RGBA per view (list of (H, W, 4) float32; views may differ in size)."""
        from .imageio import read_exr

        out = []
        for i in range(len(self.views)) if indices is None else indices:
            if self.views_premultiplied:
                out.append(read_exr(self.view_path(i), channels="RGBA"))
                continue
            a = self.load_view_rgba(i)
            a[..., :3] *= a[..., 3:4]
            out.append(a)
        return out

    @property
    def has_reflectance(self) -> bool:
        return bool(self.meta.get("reflectance", {}).get("present", False))

    @property
    def light_samples(self) -> list[LightSample]:
        r = self.meta.get("reflectance", {})
        return [LightSample(L["key"], int(L["light_id"]), float(L["array_deg"])) for L in r.get("lights", [])]

    @property
    def reflectance_storage(self) -> str:
        """How ``reflectance/`` holds the one-light images: "layers" (one EXR layer per
        light sample; models written before the option) or "pca" (a rank-R PCA per view,
        :mod:`opacityhull.reflectance_pca`)."""
        return self._meta_choice("reflectance", "storage", default="layers", choices=REFLECTANCE_STORAGES)

    def load_reflectance(self, i: int) -> dict[str, np.ndarray]:
        """``{light key: (H, W, 3) premultiplied radiance}`` of view ``i`` (rebuilt from
        the PCA when the model stores one); raises :class:`FormatError` naming the view
        and light when a sample is missing or the file does not match."""
        from .imageio import read_exr_layers

        p = self.root / "reflectance" / f"{self.views[i].id}.exr"
        if not p.is_file():
            raise FormatError(f"{p}: one-light-at-a-time images of view {self.views[i].id} not found")
        if self.reflectance_storage == "pca":
            cam = self.views[i].camera
            return read_reflectance_pca(p, [L.key for L in self.light_samples], shape=(cam.height, cam.width))
        layers = read_exr_layers(p)
        for L in self.light_samples:
            if L.key not in layers:
                raise FormatError(
                    f"{p}: one-light image {L.key} (light {L.light_id} at array {L.array_deg} deg) missing"
                )
        return {k: v[..., :3] for k, v in layers.items()}

    def light_direction(self, i: int, sample: LightSample) -> np.ndarray:
        """Unit direction towards the light sample in the object frame, for view ``i``."""
        g = self.geometry
        if g is None:
            raise FormatError(f"{self.root / 'model.toml'}: no [rig] table, light directions unknown")
        return g.light_direction_object(sample.light_id, self.views[i].table_deg, sample.array_deg)

    def reflectance_metadata(self, i: int) -> dict[str, dict]:
        """The per-layer light attributes stored in ``reflectance/<view>.exr`` (format 2):
        ``{key: {"light_id", "array_deg", "intensity", "output_rgb", "direction",
        "position_m"}}`` (direction and position only when the model has a rig; a
        format 1 file gives ``{}`` entries)."""
        from .imageio import read_exr_header

        p = self.root / "reflectance" / f"{self.views[i].id}.exr"
        h = read_exr_header(p)
        names = {
            "lightId": "light_id",
            "arrayAngleDeg": "array_deg",
            "lightIntensity": "intensity",
            "lightOutputRGB": "output_rgb",
            "lightDirection": "direction",
            "lightPosition": "position_m",
        }
        out = {}
        for L in self.light_samples:
            d = {}
            for attr, name in names.items():
                v = h.get(f"{L.key}.{attr}")
                if v is not None:
                    d[name] = np.asarray(v, np.float64) if np.ndim(v) else v
            out[L.key] = d
        return out


def _light_header(view: ViewInfo, lights: Sequence[LightSample], geometry: RigGeometry | None) -> dict:
    """Header attributes of a view's reflectance EXR: each layer's light (why: compositing
    and relighting tools read a one-light image's light from its own file)."""
    from .imageio import REC709_CHROMATICITIES

    hdr = {
        "chromaticities": REC709_CHROMATICITIES,
        "view": view.id,
        "tableAngleDeg": float(view.table_deg),
        "lightFrame": "object frame (rig frame at table angle 0, metres); directions point from the "
        "object origin towards the light",
    }
    for L in lights:
        hdr[f"{L.key}.lightId"] = int(L.light_id)
        hdr[f"{L.key}.arrayAngleDeg"] = float(L.array_deg)
        spec = None
        if geometry is not None:
            try:
                spec = geometry.light(L.light_id)
            except ValueError:
                log.warning(
                    "light %d of sample %s is not in the rig geometry; its reflectance layer carries no direction",
                    L.light_id,
                    L.key,
                )
        if spec is None or geometry is None:
            continue
        hdr[f"{L.key}.lightIntensity"] = float(spec.intensity)
        hdr[f"{L.key}.lightOutputRGB"] = float(spec.intensity) * np.asarray(spec.colour, np.float64)
        hdr[f"{L.key}.lightDirection"] = geometry.light_direction_object(L.light_id, view.table_deg, L.array_deg)
        hdr[f"{L.key}.lightPosition"] = geometry.light_position_object(L.light_id, view.table_deg, L.array_deg)
    return hdr


# --------------------------------------------------------------------------- writer


def write_model(
    root,
    *,
    views: Sequence[ViewInfo],
    surfels: Surfels,
    view_rgba: Sequence[np.ndarray] | None = None,
    rig: dict | None = None,
    provenance: dict | None = None,
    reflectance: dict | None = None,
    extra_meta: dict | None = None,
    progress=None,
    storage: Storage = "float",
    reflectance_storage: ReflectanceStorage = "layers",
    pca_rank: int | None = None,
    pca_error: float = DEFAULT_PCA_ERROR,
    pca_block: int | None = DEFAULT_PCA_BLOCK,
) -> Path:
    """Write a complete model folder.

    Parameters
    ----------
    views : ViewInfo per view, in bit order.
    surfels : Surfels with ``n_views == len(views)``.
    view_rgba : per-view (H, W, 4) straight RGBA, optional (written premultiplied to
        ``views/``, with Rec.709 chromaticities).
    rig : rig geometry table (copied from the session).
    provenance : session path, options, timings.
    reflectance : ``{"lights": [LightSample...], "images": callable(view_index) -> {key: (H, W, 3)}}``.
    progress : callable(done, total) or None.
    storage : pixel type of ``views/`` and ``reflectance/``: "float" (32-bit, the
        default here) or "half" (16-bit: half the bytes; 11 significant bits, finite
        values beyond ±65504 clamped with a ``HalfOverflowWarning`` and listed in
        ``model.toml`` ``[storage] clamped``). Same values either way, no scale.
    reflectance_storage : "layers" (one EXR layer per light sample) or "pca" (per view a
        PCA per ``pca_block``-pixel block, None: one for the view,
        :mod:`opacityhull.reflectance_pca`: basis images over the non-zero box and K
        coefficients per block and rank; :meth:`OpacityHullModel.load_reflectance`
        rebuilds the layers). The rank is ``pca_rank`` (in [1, K]) in every block or,
        when None, the fewest components over the view's blocks whose relative Frobenius
        error over the view is at most ``pca_error``. The measured error, ranks and values ratio per view go to
        ``model.toml`` ``[reflectance]``.

    ``model.toml`` is written last, so a folder without it is an unfinished build.
    """
    from .imageio import REC709_CHROMATICITIES, atomic_path, write_exr, write_exr_layers
    from .tomlio import toml_dumps

    root = Path(root)
    if storage not in STORAGE_TYPES:
        raise InputError(f"write_model storage {storage!r}: expected one of {', '.join(map(repr, STORAGE_TYPES))}")
    if reflectance_storage not in REFLECTANCE_STORAGES:
        raise InputError(
            f"write_model reflectance_storage {reflectance_storage!r}: expected one of "
            f"{', '.join(map(repr, REFLECTANCE_STORAGES))}"
        )
    if reflectance_storage == "pca":
        check_pca_options(rank=pca_rank, error=pca_error, block=pca_block)
        n_lights = len(list(reflectance["lights"])) if reflectance is not None else 0
        if reflectance is not None and pca_rank is not None and int(pca_rank) > n_lights:
            raise InputError(f"write_model pca_rank {pca_rank} is more than the {n_lights} light samples")
    root.mkdir(parents=True, exist_ok=True)
    clamped: list[dict] = []
    if surfels.n_views != len(views):
        raise InputError(f"surfels have {surfels.n_views} views, {len(views)} views given")
    write_colmap_text(
        root / "cameras",
        [v.camera for v in views],
        [v.id for v in views],
        share_intrinsics=[v.camera_index for v in views],
    )
    write_surfels_ply(root / "surfels.ply", surfels)
    total = len(views) * (1 + (reflectance is not None))
    done = 0
    if view_rgba is not None:
        # not zip(): its reused result tuple would keep the previous view's image alive
        # while a lazy sequence makes the next one
        images = iter(view_rgba)
        for v in views:
            img = next(images, None)
            if img is None:
                break  # as zip(): a shorter sequence writes the views it has
            check_shape(f"view {v.id} RGBA", img, (v.camera.height, v.camera.width, 4))
            pre = np.array(img, dtype=np.float32)
            pre[..., :3] *= pre[..., 3:4]
            path = root / "views" / f"{v.id}.exr"
            header = {"chromaticities": REC709_CHROMATICITIES, "view": v.id}
            info = write_exr(path, pre, header=header, half=storage == "half")
            del img, pre  # a lazy sequence's next view is made before the loop rebinds these
            if info:
                clamped.append({"file": str(path), **info})
            done += 1
            if progress:
                progress(done, total)
    meta = {
        "model": {
            "format": MODEL_FORMAT,
            "units": "m",
            "software_version": __version__,
            "n_views": len(views),
            "n_surfels": len(surfels),
        },
        "provenance": _provenance_table(provenance),
        "views": [{"id": v.id, "camera": v.camera_index, "table_deg": v.table_deg} for v in views],
    }
    if rig is not None:
        meta["rig"] = rig
    if reflectance is not None:
        lights = list(reflectance["lights"])
        geometry = None
        if rig is not None:
            geometry = RigGeometry.from_dict(rig, where="write_model rig")
        else:
            log.warning("write_model: reflectance without a rig geometry; its layers carry no light direction")
        pca_views: list[dict] = []
        pca_values = [0.0, 0.0]  # values of the layers, values stored
        for v in views:
            imgs = reflectance["images"](v.index)
            path = root / "reflectance" / f"{v.id}.exr"
            layers = {L.key: imgs[L.key] for L in lights}
            shape = (v.camera.height, v.camera.width)
            header = _light_header(v, lights, geometry)
            if reflectance_storage == "pca":
                pv = write_reflectance_pca(
                    path,
                    layers,
                    [L.key for L in lights],
                    shape=shape,
                    header=header,
                    half=storage == "half",
                    rank=pca_rank,
                    error=pca_error,
                    block=pca_block,
                )
                pca_views.append(
                    {
                        "id": v.id,
                        "rank": pv.rank,
                        "rank_mean": round(pv.rank_mean, 4),
                        "rel_error": float(pv.rel_error),
                        "box": list(pv.box),
                    }
                )
                pca_values[0] += len(lights) * shape[0] * shape[1] * 3
                pca_values[1] += len(lights) * shape[0] * shape[1] * 3 / pv.values_ratio
                log.debug("reflectance %s: PCA rank %d, error %.3g", v.id, pv.rank, pv.rel_error)
                del pv
            else:
                info = write_exr_layers(path, layers, header=header, half=storage == "half", shape=shape)
                if info:
                    clamped.append({"file": str(path), **info})
            del imgs, layers  # the next view's images are made before the loop rebinds these
            done += 1
            if progress:
                progress(done, total)
        meta["reflectance"] = {
            "present": True,
            "storage": reflectance_storage,
            "lights": [{"key": L.key, "light_id": L.light_id, "array_deg": L.array_deg} for L in lights],
        }
        if reflectance_storage == "pca":
            meta["reflectance"].update(
                {
                    "pca_format": PCA_FORMAT,
                    "pca_rank": None if pca_rank is None else int(pca_rank),
                    "pca_error_target": None if pca_rank is not None else float(pca_error),
                    # block edge in pixels; 0: one PCA for the whole view
                    "pca_block": 0 if pca_block is None else int(pca_block),
                    "rank_max": max(d["rank"] for d in pca_views) if pca_views else 0,
                    "rel_error_max": max(d["rel_error"] for d in pca_views) if pca_views else 0.0,
                    # layers' values / stored values (same pixel type): the nominal ratio;
                    # report.json has the bytes on disk
                    "values_ratio": pca_values[0] / pca_values[1] if pca_values[1] else 1.0,
                    "pca_views": pca_views,
                }
            )
    else:
        meta["reflectance"] = {"present": False}
    meta["storage"] = {
        "pixel_type": storage,
        "values": "linear premultiplied RGBA (views), radiance at full DMX level (reflectance); no scale",
        "clamped_values": int(sum(c["values"] for c in clamped)),
        "clamped": clamped[:MAX_CLAMPED_LISTED],
    }
    if extra_meta:
        meta.update(extra_meta)
    with atomic_path(root / "model.toml") as tmp:
        tmp.write_text(toml_dumps(meta))
    return root


def _provenance_table(provenance: dict | None) -> dict:
    """``provenance`` as ``model.toml`` stores it: a ``build_config`` dict becomes a TOML
    table, the dotted keys of its None values listed in ``build_config_none`` (TOML has
    no null, and a None option is not its default: ``pca_block`` None is one PCA per view)."""
    from .tomlio import split_nones

    p = dict(provenance or {})
    bc = p.get("build_config")
    if isinstance(bc, dict):
        p["build_config"], nones = split_nones(bc)
        nones = sorted(set(p.get("build_config_none", [])) | set(nones))
        if nones:
            p["build_config_none"] = nones
    return p


def copy_model(
    model: OpacityHullModel,
    dst,
    *,
    storage: Storage,
    reflectance_storage: ReflectanceStorage | None = None,
    pca_rank: int | None = None,
    pca_error: float | None = None,
    pca_block: int | None = DEFAULT_PCA_BLOCK,
    reflectance_images: Callable[[int], dict[str, np.ndarray]] | None = None,
) -> OpacityHullModel:
    """``model`` written again to ``dst`` through :func:`write_model` with the pixel type
    ``storage`` (e.g. a float32 model converted to half) and ``reflectance_storage``
    (None: the model's own; ``pca_rank`` / ``pca_error`` / ``pca_block`` as in
    :func:`write_model`, rank and error None: the model's own target or the default): views, surfels, reflectance, rig and
    provenance; the pictures and the build report are not copied.

    ``reflectance_images``: view index -> ``{light key: (H, W, 3)}`` written in place of
    the model's own one-light images (e.g. perturbed copies of them; None: the model's);
    the model must have reflectance (else :class:`InputError`)."""
    r = model.meta.get("reflectance", {})
    if reflectance_storage is None:
        reflectance_storage = "pca" if model.has_reflectance and model.reflectance_storage == "pca" else "layers"
        if reflectance_storage == "pca" and pca_rank is None and pca_error is None:
            pca_rank = r.get("pca_rank")
            pca_error = r.get("pca_error_target")
            pca_block = int(r.get("pca_block", DEFAULT_PCA_BLOCK)) or None
    if reflectance_images is not None and not model.has_reflectance:
        raise InputError(f"copy_model: reflectance_images given, but model {model.root} has no reflectance")
    images = model.load_reflectance if reflectance_images is None else reflectance_images
    refl = {"lights": model.light_samples, "images": images} if model.has_reflectance else None
    write_model(
        dst,
        views=model.views,
        surfels=model.surfels,
        view_rgba=[model.load_view_rgba(i) for i in range(len(model.views))],
        rig=model.meta.get("rig"),
        provenance=model.meta.get("provenance"),
        reflectance=refl,
        storage=storage,
        reflectance_storage=reflectance_storage,
        pca_rank=pca_rank,
        pca_error=DEFAULT_PCA_ERROR if pca_error is None else float(pca_error),
        pca_block=pca_block,
    )
    return OpacityHullModel.open(dst)


# --------------------------------------------------------------------------- build products the evaluation reads

BUILD_DIR = "build"
"""``MODEL/build/``: the build's step products (cache) and what the evaluation must know
of how the views were made."""

FILLED_HOLES = "filled_holes.npz"
"""``MODEL/build/filled_holes.npz``: per view id, the mask holes the build filled as
shadows (:func:`opacityhull.reconstruct.build.fill_shadow_holes`; bit-packed like :data:`OPEN_HOLES`): ``eval loo``
restores the photograph's own mask there before comparing."""

OPEN_HOLES = "open_holes.npz"
"""``MODEL/build/open_holes.npz``: per view id, the mask holes a tolerant carve trusted
(:func:`opacityhull.reconstruct.build.open_hole_masks`, bit-packed rows with the image shape), so that the
geometry holdout of ``eval loo`` carves as the build did without the photographs."""
BRIGHT_EXTENSIONS = "bright_extensions.npz"
"""``MODEL/build/bright_extensions.npz``: per view id, the bright extensions of the mask a
tolerant carve doubted (:func:`opacityhull.reconstruct.build.bright_extension_masks`,
bit-packed like :data:`OPEN_HOLES`), which the geometry holdout doubts alike."""


def write_hole_masks(path: Path, holes: dict) -> None:
    """Write view id → (H, W) bool masks bit-packed (:data:`OPEN_HOLES`, :data:`FILLED_HOLES`)."""
    from .imageio import atomic_path

    arrays = {}
    for vid, m in holes.items():
        m = np.asarray(m, bool)
        arrays[f"{vid}.bits"] = np.packbits(m, axis=1)
        arrays[f"{vid}.shape"] = np.asarray(m.shape, np.int64)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def read_hole_masks(path: Path) -> dict:
    """View id → (H, W) bool of :data:`OPEN_HOLES` or :data:`FILLED_HOLES`; {} when the
    file is absent (a model built before it, or without the rule)."""
    if not path.is_file():
        return {}
    try:
        with np.load(path) as z:
            out = {}
            for key in z.files:
                if key.endswith(".bits"):
                    vid = key[: -len(".bits")]
                    h, w = (int(x) for x in z[f"{vid}.shape"])
                    out[vid] = np.unpackbits(z[key], axis=1, count=w)[:h].astype(bool)
            return out
    except (OSError, ValueError, KeyError) as e:
        raise FormatError(f"{path}: not a readable hole-mask file ({e}); rebuild the model to rewrite it") from e
