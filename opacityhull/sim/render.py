"""Rendering the simulated rig with Mitsuba 3.

Frames. Everything is rendered in the **object frame** (= rig frame at table angle 0):
the object, the bottom display (it turns with the table) and the calibration board are
static there; the view camera (``RigGeometry.view_camera``), the lights and the fixed
back display move by ``object_from_rig(table_deg)``. So meshes are loaded once and a
capture only rewrites a few transforms.

Scene cache. A Mitsuba scene is loaded once per *structure* — effect configuration,
what stands on the table (object, board or nothing), film size, and which emitters
exist — and changed between captures with ``mi.traverse`` + ``params.update()``
(sensor ``to_world``/field of view/principal point, rectangle ``to_world``, point-light
``position``/``intensity``, display bitmap ``data``): ~0.03 s per re-render against
seconds per load (PITFALLS).

Light model. Light-array lights are at ``LightSpec.position_rig(array_deg)`` (then moved
into the object frame): point lights, or, when the rig gives ``radius_m``, spheres of that
radius (a bulb behind a diffuser) of uniform radiance ``I / (π r²)`` — the same intensity
in every direction, so the same irradiance at the origin, and a glass shows the lamp. A light of calibrated ``intensity = 1`` gives
irradiance 1 (on a surface facing it) at the rig origin, whatever its distance:
Mitsuba intensity ``I = intensity * |p|^2 * (level / 255) * colour`` (W/sr), ``p`` its
rig-frame position. DMX level ``L`` scales linearly (``L / 255``).

Displays. A display is a rectangle whose emitting side is its ``normal``; showing a
pattern makes it an area emitter of radiance ``max_radiance * pattern / 255`` (linear
drive), the pattern upscaled to the panel's ``resolution`` with nearest neighbour and
shown with nearest-neighbour texture lookup, pattern row 0 towards the panel's ``up``.
Blank, powered-off or all-black panels have *no emitter*; they stay in the scene as
black absorbers (they shadow). Panels are drawn 0.5 mm behind their nominal plane (a
panel's cover glass) so an object or board resting on the bottom panel does not
z-fight with it.

Superposition. Light transport is linear in the emitters, so a capture is rendered as
*passes* — one per light switched on (one point light in the scene, no emitter-selection
noise) and one for the emitting displays — summed (:meth:`SimRenderer.passes_for`).
Each pass gets the effect selection of the phase its emitter group belongs to: the
displays of a matting shot taken with the lights on are rendered with the matting
selection, its lights with the lightfield one. Groups that provably add nothing are not
rendered: a capture with nothing switched on is exactly black without calling Mitsuba;
with the table empty only the emitting panels are visible (path depth 1, no light
passes: :func:`~opacityhull.sim.effects.backdrop_only_effects`); point lights on an
object made only of delta BSDFs show nothing.

Crop. A camera ray that cannot meet what stands on the table sees only the display
panels: their emission where they emit, else black (the panels are black absorbers and
nothing else is in the scene). So a pass renders only the window of pixels whose rays
can meet the object — its bounding box projected, plus the box filter's support (the
pixel itself: radius 0.5, ``sample_border`` off; the pinhole sensor has no depth of
field) and :data:`CROP_MARGIN_PX` — and takes every other pixel from the exact
backdrop-only render of the same displays (path depth 1; reused from the radiance
cache when the backdrop shot was taken, as the matting schedule does first), or 0 for a
light pass. Inside the window it is the same estimator as a full render (the same
integrator, sampler and spp per pixel); a pixel's value depends only on its own
samples, so there is no seam. The window is rendered by a pinhole camera whose
principal point is shifted by the window's offset (a crop of a pinhole image *is* a
pinhole image), and its size is that of the object's bounding cylinder about the table
axis seen by that camera (:func:`turntable_box`), the same at every table angle: Dr.Jit
compiles one kernel per film size and offset, so a capture compiles one per camera and
configuration, and none per angle. :func:`footprint_window`, :func:`crop_window`.

Radiance cache. The rig is deterministic: the same camera, table and array angles,
lights, patterns and content give the same radiance. The Monte-Carlo estimate of a pass
is therefore kept (LRU, ``cache_mb``) and reused by later captures of the same physical
state — the matting shots with and without a pattern and the lightfield shot of one
view share their light passes; exposure brackets and re-shoots cost nothing. The sensor
model (:mod:`~opacityhull.sim.sensor`) still draws fresh noise per capture. A reused
pass keeps the noise of the seed it was first rendered with.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from collections.abc import Mapping, Sequence

import numpy as np

from ..camera import Camera, mitsuba_sensor_params, object_from_rig
from ..charuco import CharucoSpec
from ..errors import InputError
from ..interrupts import deferred_signals
from ..riggeometry import DisplaySpec, RigGeometry
from . import shapes as S
from .effects import EffectConfig, backdrop_only_effects, select_effects
from .mitsuba_sensor import NEAR_CLIP_M, sensor_dict
from .scenes import MaterialSpec, Part, SceneSpec, board_parts
from .variants import choose_variant, use_mitsuba

log = logging.getLogger(__name__)

__all__ = [
    "SimState",
    "SimRenderer",
    "RenderPass",
    "phase_for_state",
    "light_intensity",
    "display_radiance",
    "nearest_resize",
    "DISPLAY_SETBACK_M",
    "NEAR_CLIP_M",
    "footprint_window",
    "crop_window",
    "crop_camera",
    "turntable_box",
    "CROP_MARGIN_PX",
    "CROP_STEPS",
    "CROP_MAX_FRACTION",
]

#: Panels are rendered this far behind their nominal plane (see module docstring).
DISPLAY_SETBACK_M = 0.0005

_DIAG_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])

#: Extra pixels around the projected bounding box, beyond the box filter's support
#: (absorbs rounding; the pinhole sensor has no depth of field to add).
CROP_MARGIN_PX = 1.0

#: Crop sides are rounded up to multiples of 1/CROP_STEPS of the frame side (at least
#: 8 px). Dr.Jit compiles a kernel per film size (~0.4 s); the size is already fixed
#: per camera (SimRenderer.crop_for), the rounding only merges near-equal cameras.
CROP_STEPS = 50

#: A window covering more of the frame than this is rendered as the full frame: the
#: backdrop render the crop needs would cost more than the pixels it saves.
CROP_MAX_FRACTION = 0.6


def footprint_window(camera: Camera, lo, hi, *, margin_px: float = CROP_MARGIN_PX) -> tuple[int, int, int, int] | None:
    """Pixels whose camera rays can meet the axis-aligned box ``[lo, hi]``.

    Parameters
    ----------
    camera : Camera
        Pinhole camera (no distortion), posed in the frame of the box.
    lo, hi : (3,) arrays
        Box corners, metres.
    margin_px : float
        Pixels added on every side beyond the box filter's support.

    Returns
    -------
    (x0, y0, x1, y1) : half-open pixel window, clipped to the frame; empty (x0 == x1 or
    y0 == y1) when the box projects outside the frame. None when a box corner is not in
    front of the near plane: the box may then cover any pixel (render the whole frame).

    Notes
    -----
    The box is convex, so its projection lies in the hull of its projected corners
    ``[umin, umax] x [vmin, vmax]``. Pixel ``i`` (OpenCV centres) integrates samples in
    ``[i - 0.5, i + 0.5)`` with a box filter of radius 0.5, so it can see the box only if
    ``umin - 0.5 < i < umax + 0.5``.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv, z = camera.project(corners)
    if not (np.all(z > NEAR_CLIP_M) and np.all(np.isfinite(uv))):
        return None
    pad = 0.5 + float(margin_px)
    x0 = int(np.clip(math.floor(uv[:, 0].min() - pad), 0, camera.width))
    x1 = int(np.clip(math.ceil(uv[:, 0].max() + pad), 0, camera.width))
    y0 = int(np.clip(math.floor(uv[:, 1].min() - pad), 0, camera.height))
    y1 = int(np.clip(math.ceil(uv[:, 1].max() + pad), 0, camera.height))
    if x1 <= x0 or y1 <= y0:
        return (0, 0, 0, 0)
    return (x0, y0, x1, y1)


def crop_window(
    window: tuple[int, int, int, int],
    width: int,
    height: int,
    *,
    steps: int = CROP_STEPS,
    min_size: tuple[int, int] = (0, 0),
) -> tuple[int, int, int, int]:
    """The render window ``(x0, y0, w, h)`` for a footprint ``(x0, y0, x1, y1)``: each side
    at least ``min_size``, rounded up to a multiple of ``max(8, ceil(side / steps))`` px
    (at most the frame), kept centred on the footprint and inside the frame, so it
    contains the footprint. An empty footprint gives ``(0, 0, 0, 0)``."""
    x0, y0, x1, y1 = (int(v) for v in window)
    if x1 <= x0 or y1 <= y0:
        return (0, 0, 0, 0)

    def side(a: int, b: int, n: int, least: int) -> tuple[int, int]:
        q = max(8, -(-n // int(steps)))
        size = min(n, -(-max(b - a, int(least)) // q) * q)
        start = a - (size - (b - a)) // 2
        return min(max(start, 0), n - size), size

    cx, w = side(x0, x1, int(width), min_size[0])
    cy, h = side(y0, y1, int(height), min_size[1])
    return (cx, cy, w, h)


def turntable_box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """A box containing the box ``[lo, hi]`` (object frame) at every table angle: the
    bounding cylinder about the table axis (+Y through the origin), as a box."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    r = float(np.sqrt(max(lo[0] ** 2, hi[0] ** 2) + max(lo[2] ** 2, hi[2] ** 2)))
    return np.array([-r, lo[1], -r]), np.array([r, hi[1], r])


def crop_camera(camera: Camera, x0: int, y0: int, w: int, h: int) -> Camera:
    """The pinhole camera whose image is pixels ``[x0, x0 + w) x [y0, y0 + h)`` of
    ``camera``'s (principal point shifted by the offset; same pose and focal length)."""
    K = np.array(camera.K, dtype=np.float64)
    K[0, 2] -= x0
    K[1, 2] -= y0
    return Camera(
        K=K,
        width=int(w),
        height=int(h),
        world_from_cam=camera.world_from_cam,
        dist=camera.dist,
        name=f"{camera.name}[{x0}:{x0 + w},{y0}:{y0 + h}]",
    )


# --------------------------------------------------------------------------- state


@dataclass(frozen=True)
class SimState:
    """What the rig is doing at capture time (read from the emulators by ``SimRig``).

    Attributes
    ----------
    table_deg : turntable angle (GRBL table axis).
    array_deg : light-array rotation angle.
    light_levels : light id -> DMX level 0..255 (missing = off).
    displays : display name -> shown pattern, uint8 (rows, cols, 3), or None (blank/off).
    content : "object" (the scene's object), "board" (the ChArUco board) or "none".
    charuco : the board placed when ``content == "board"``.
    phase : the capture phase, if the capture declared it (``SimRig.note_phase``), else
        None. Only "matting" and "envmatte" change anything: a displays-on shot of a
        declared phase gets that phase's selection; an undeclared one the matting
        integrator at the samples that keep both phases' bounds
        (``select_effects(declared=False)``).
    """

    table_deg: float = 0.0
    array_deg: float = 0.0
    light_levels: Mapping[int, int] = field(default_factory=dict)
    displays: Mapping[str, np.ndarray | None] = field(default_factory=dict)
    content: str = "object"
    charuco: CharucoSpec | None = None
    phase: str | None = None

    def lights_on(self) -> dict[int, int]:
        return {int(k): int(v) for k, v in self.light_levels.items() if int(v) > 0}

    def displays_on(self) -> dict[str, np.ndarray]:
        """Displays that emit anything (a shown, not all-black pattern)."""
        return {k: v for k, v in self.displays.items() if v is not None and np.any(np.asarray(v) > 0)}


def phase_for_state(state: SimState) -> str:
    """The capture phase a rig state belongs to (the simulator cannot be told; it infers).

    Board on the table → calibration; displays emitting and no light → matting, or
    envmatte if the capture declared it (``state.phase``; undeclared, an envmatte capture
    looks the same to the rig, and the undeclared matting selection stays within the
    envmatte error bounds, see ``benchmarks/sim_effects.py``); lights on → reflectance for
    a single light, lightfield for several or lights plus displays; nothing on → matting
    (the image is black anyway and nothing is rendered).
    """
    if state.content == "board":
        return "calibration"
    lights = state.lights_on()
    if not lights:
        return "envmatte" if state.phase == "envmatte" else "matting"
    if len(lights) == 1 and not state.displays_on():
        return "reflectance"
    return "lightfield"


@dataclass(frozen=True)
class RenderPass:
    """One Mitsuba render of a capture: an emitter group and the effects it is rendered with.

    Attributes
    ----------
    group : "displays" | "light"
    effects : EffectConfig
    light : (light id, DMX level) for a light pass, else None.
    """

    group: str
    effects: EffectConfig
    light: tuple[int, int] | None = None

    def to_json(self) -> dict:
        e = self.effects
        return {
            "group": self.group,
            "light": None if self.light is None else list(self.light),
            "phase": e.phase,
            "integrator": e.integrator,
            "max_depth": e.max_depth,
            "spp": e.spp,
            "sampler": e.sampler,
            "resolution_scale": e.resolution_scale,
        }


def lamp_radius(geometry: RigGeometry) -> float | None:
    """The smallest lamp radius of the rig's light array (metres), or ``None`` when any
    lamp is an ideal point light (effect selection then keeps the point-light rules)."""
    radii = [L.radius_m for L in geometry.lights]
    if not radii or any(r is None for r in radii):
        return None
    return float(min(r for r in radii if r is not None))


def light_intensity(geometry: RigGeometry, light_id: int, level: int) -> np.ndarray:
    """Mitsuba radiant intensity (RGB, W/sr) of a light at DMX ``level``: irradiance
    ``intensity * level / 255 * colour`` at the rig origin."""
    L = geometry.light(light_id)
    d2 = float(np.dot(L.position_m, L.position_m))
    return L.intensity * d2 * (float(level) / 255.0) * np.asarray(L.colour, dtype=np.float64)


def nearest_resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of (rows, cols, C) to (height, width, C) by pixel centres."""
    img = np.asarray(img)
    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img
    ri = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    ci = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return img[ri][:, ci]


def display_radiance(display: DisplaySpec, pattern: np.ndarray) -> np.ndarray:
    """Emitted radiance (rows, cols, 3) float32 of ``pattern`` (uint8) on ``display``:
    nearest-neighbour upscaled to the panel resolution, linear drive."""
    p = np.asarray(pattern)
    if p.ndim == 2:
        p = np.repeat(p[:, :, None], 3, axis=2)
    if p.ndim != 3 or p.shape[2] != 3:
        raise InputError(f"pattern for display {display.name!r} has shape {p.shape}, expected (rows, cols, 3)")
    w, h = display.resolution
    p = nearest_resize(p, w, h)
    return (display.max_radiance / 255.0) * p.astype(np.float32)


# --------------------------------------------------------------------------- helpers


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    d = Path(base) / "opacityhull" / "sim-geometry"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _geometry_file(kind: str, payload: np.ndarray, writer) -> str:
    """Write geometry once to a content-addressed cache file (Mitsuba loads files)."""
    h = hashlib.sha1(np.ascontiguousarray(payload).tobytes()).hexdigest()[:20]
    path = _cache_dir() / f"{kind}-{h}.{'ply' if kind == 'mesh' else 'txt'}"
    if not path.is_file():
        writer(path)
    return str(path)


def _mesh_file(mesh: S.TriMesh) -> str:
    payload = np.concatenate(
        [mesh.vertices.ravel(), mesh.normals.ravel(), mesh.uv.ravel(), mesh.faces.ravel().astype(np.float64)]
    )
    return _geometry_file("mesh", payload, lambda p: S.write_ply_mesh(p, mesh))


def _curves_file(fib: S.Fibres) -> str:
    payload = np.concatenate([fib.points.ravel(), [fib.radius_m]])
    return _geometry_file("curves", payload, lambda p: S.write_curves_txt(p, fib))


def _tensor(mi, img: np.ndarray):
    return mi.TensorXf(np.ascontiguousarray(img, dtype=np.float32))


def _texture(mi, img_rows_top: np.ndarray, *, nearest: bool = False) -> dict:
    # Mitsuba's bitmap row 0 is v = 0; images store the top row first: flip rows.
    return {
        "type": "bitmap",
        "data": _tensor(mi, img_rows_top[::-1]),
        "raw": True,
        "filter_type": "nearest" if nearest else "bilinear",
        "wrap_mode": "clamp" if nearest else "repeat",
    }


def bsdf_dict(mi, mat: MaterialSpec) -> dict:
    """Mitsuba BSDF dict of a material."""
    p = mat.params
    tex = None
    if mat.texture is not None:
        tex = _texture(mi, mat.texture.image())
    t = mat.type
    if t == "diffuse":
        refl = tex if tex is not None else {"type": "rgb", "value": list(p.get("reflectance", (0.5, 0.5, 0.5)))}
        return {"type": "diffuse", "reflectance": refl}
    if t in ("plastic", "roughplastic"):
        d = tex if tex is not None else {"type": "rgb", "value": list(p.get("diffuse", (0.5, 0.5, 0.5)))}
        out = {"type": t, "diffuse_reflectance": d, "int_ior": float(p.get("ior", 1.49))}
        if t == "roughplastic":
            out["alpha"] = float(p.get("roughness", 0.1))
            out["distribution"] = "ggx"
        return out
    if t in ("conductor", "roughconductor"):
        out: dict[str, Any] = {"type": t}
        if "specular" in p:
            out["material"] = "none"
            out["specular_reflectance"] = {"type": "rgb", "value": list(p["specular"])}
        else:
            out["material"] = p.get("conductor", "Al")
        if t == "roughconductor":
            out["alpha"] = float(p.get("roughness", 0.1))
            out["distribution"] = "ggx"
        return out
    if t in ("dielectric", "roughdielectric", "thindielectric"):
        out = {"type": t, "int_ior": float(p.get("ior", 1.5)), "ext_ior": 1.0}
        if "tint" in p:
            out["specular_transmittance"] = {"type": "rgb", "value": list(p["tint"])}
        if t == "roughdielectric":
            out["alpha"] = float(p.get("roughness", 0.1))
            out["distribution"] = "ggx"
        return out
    raise InputError(f"material {mat.name!r}: type {t!r} has no Mitsuba mapping")


def _black() -> dict:
    # a fresh dict per shape: Mitsuba merges shapes that share a BSDF instance into one
    # mesh, which would hide their to_world parameters
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}


def part_dicts(mi, parts: Sequence[Part]) -> dict:
    """Mitsuba shape dicts (keyed ``obj_<i>``) of object parts, object frame."""
    out = {}
    for i, p in enumerate(parts):
        key = f"obj_{i}"
        if p.kind == "board":
            out[key] = board_dict(mi, p.need(p.charuco, "charuco"))
            continue
        mat = p.need(p.material, "material")
        if p.kind == "mesh":
            out[key] = {
                "type": "ply",
                "filename": _mesh_file(p.need(p.mesh, "mesh")),
                "face_normals": False,
                "bsdf": bsdf_dict(mi, mat),
            }
        elif p.kind == "sphere":
            out[key] = {
                "type": "sphere",
                "center": [float(v) for v in p.need(p.centre_m, "centre_m")],
                "radius": float(p.need(p.radius_m, "radius_m")),
                "bsdf": bsdf_dict(mi, mat),
            }
        elif p.kind == "disk":
            T = np.eye(4)
            # local +z -> +Y
            T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]) * float(p.need(p.radius_m, "radius_m"))
            T[:3, 3] = p.need(p.centre_m, "centre_m")
            out[key] = {"type": "disk", "to_world": mi.ScalarTransform4f(T), "bsdf": bsdf_dict(mi, mat)}
        elif p.kind == "curves":
            out[key] = {
                "type": "linearcurve",
                "filename": _curves_file(p.need(p.fibres, "fibres")),
                "bsdf": bsdf_dict(mi, mat),
            }
        else:
            raise InputError(f"part {p.name!r}: unknown kind {p.kind!r}")
    return out


def board_to_world(charuco: CharucoSpec) -> np.ndarray:
    """4×4 map from Mitsuba's rectangle ([-1, 1]², normal +z) to the board in the object
    frame: local x → board x, local y → −board y (so the normal −board z points up;
    board z is into the board), scaled to the board size."""
    w, h = charuco.size_m
    local_to_board = np.array([[w / 2, 0, 0, w / 2], [0, -h / 2, 0, h / 2], [0, 0, -1, 0], [0, 0, 0, 1.0]])
    return charuco.object_from_board() @ local_to_board


def board_image(charuco: CharucoSpec, px_per_square: int = 120) -> np.ndarray:
    """Linear reflectance (rows, cols, 3) of the printed board: white paper 0.8, ink 0.03."""
    g = charuco.image(px_per_square).astype(np.float32) / 255.0
    refl = 0.03 + (0.8 - 0.03) * g
    return np.repeat(refl[:, :, None], 3, axis=2)


def board_dict(mi, charuco: CharucoSpec) -> dict:
    # Local y runs against board y (see board_to_world), so v = 0 (bitmap row 0) is the
    # board's last image row: the image goes in flipped — done by _texture.
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f(board_to_world(charuco)),
        "bsdf": {"type": "diffuse", "reflectance": _texture(mi, board_image(charuco))},
    }


def display_to_world(display: DisplaySpec, table_deg: float) -> np.ndarray:
    """Rectangle ``to_world`` of a panel in the object frame at ``table_deg`` (local x →
    panel right, local y → panel up, local z → normal; set back by DISPLAY_SETBACK_M)."""
    F = display.frame().copy()
    F[:3, 3] = F[:3, 3] - DISPLAY_SETBACK_M * F[:3, 2]
    w, h = display.size_m
    T = F @ np.diag([w / 2, h / 2, 1.0, 1.0])
    if not display.rotates_with_table:
        T = object_from_rig(table_deg) @ T
    return T


def _integrator_dict(cfg: EffectConfig) -> dict:
    if cfg.integrator == "direct":
        return {"type": "direct"}
    if cfg.integrator == "path":
        return {"type": "path", "max_depth": int(cfg.max_depth), "rr_depth": max(int(cfg.max_depth), 5)}
    if cfg.integrator == "aov":
        return {"type": "aov", "aovs": "dd:depth,nn:sh_normal,si:shape_index", "inner": {"type": "direct"}}
    raise InputError(f"integrator {cfg.integrator!r} unknown")


def _camera_key(cam: Camera) -> tuple:
    return (cam.width, cam.height)


# --------------------------------------------------------------------------- renderer


@dataclass
class _Loaded:
    # mi.Scene / mi.SceneParameters (or a sensor and its parameters); Any because the
    # Mitsuba module's types depend on the variant chosen at run time
    scene: Any
    params: Any
    keys: dict
    lock: threading.Lock = field(default_factory=threading.Lock)
    last: dict = field(default_factory=dict)  # parameter name -> signature of the value last set

    def assign(self, name: str, signature, make_value) -> None:
        """Set parameter ``name`` only if ``signature`` differs from the last one set: a
        parameter write marks its shape dirty, and a moved shape rebuilds the scene's
        acceleration structure (the whole object) at the next ``params.update()``."""
        if self.last.get(name) == signature:
            return
        self.params[name] = make_value()
        self.last[name] = signature


#: The only parameters a capture changes. ``params.update()`` schedules every parameter
#: it holds (meshes, textures...); keeping just these makes an update cost what changed.
_PARAM_KEEP = [
    r"sensor\..*",
    r"display_\d+\.to_world",
    r"display_\d+\.emitter\.radiance\.data",
    r"light\.position",
    r"light\.intensity\.value",
    r"light\.to_world",
    r"light\.emitter\.radiance\.value",
]


def _lamp_to_world(position, radius_m: float) -> np.ndarray:
    """4x4 world_from_unit-sphere of a lamp of ``radius_m`` centred at ``position``."""
    T = np.diag([radius_m, radius_m, radius_m, 1.0])
    T[:3, 3] = np.asarray(position, np.float64)
    return T


def _traverse(mi, scene):
    params = mi.traverse(scene)
    params.keep(_PARAM_KEEP)
    return params


class SimRenderer:
    """Renders a scene on a rig for given cameras and rig states; caches Mitsuba scenes.

    Parameters
    ----------
    scene : SceneSpec
    geometry : RigGeometry
        Lights and displays (cameras are passed per call).
    variant : str, optional
        Mitsuba variant (default :func:`~opacityhull.sim.variants.choose_variant`).
    overrides : mapping, optional
        Effect overrides applied to every selection (``select_effects(overrides=...)``).

    Notes
    -----
    Thread-safe: renders of one cached scene are serialised (its parameters are
    rewritten per render).
    """

    def __init__(
        self,
        scene: SceneSpec,
        geometry: RigGeometry,
        *,
        variant: str | None = None,
        overrides: Mapping | None = None,
        cache_mb: float = 256.0,
    ):
        self.scene = scene
        self.geometry = geometry
        self.variant = variant
        self.overrides = dict(overrides or {})
        self._cache: dict[tuple, _Loaded] = {}
        self._cache_lock = threading.Lock()
        self.loads = 0  # number of Mitsuba scene loads (tests check caching)
        self.renders = 0
        self.cache_bytes = int(max(0.0, float(cache_mb)) * 2**20)
        self._radiance: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._radiance_bytes = 0
        self._radiance_lock = threading.Lock()
        self.cache_hits = 0
        self._bounds: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        # rendered pixels against frame pixels over all passes (crop savings; benchmarks)
        self.pixels_rendered = 0
        self.pixels_framed = 0

    # ---- public
    @property
    def mi(self):
        # pinned at first use: Mitsuba's variant is process-global, and another caller
        # switching it must not change the variant this renderer's scenes were loaded in
        if self.variant is None:
            self.variant = choose_variant()
        return use_mitsuba(self.variant)

    def effects_for(self, state: SimState, *, camera: Camera | None = None) -> EffectConfig:
        """The effect configuration of the phase a capture in ``state`` belongs to
        (:func:`phase_for_state`), listing every emitter group switched on that is not
        provably black. What is actually rendered, pass by pass: :meth:`passes_for`.
        ``camera``: the camera the capture is for (its size picks the matting samples:
        ``select_effects(pixels=...)``)."""
        phase = "calibration" if state.content == "board" else phase_for_state(state)
        cfg = self._select(phase, declared=state.phase == phase, camera=camera)
        if state.content == "none":
            return backdrop_only_effects(cfg)
        # whatever is switched on is in the picture, even where the phase would not use it
        extra = []
        if state.lights_on() and "light_array" not in cfg.emitters and "light_array" not in cfg.skipped:
            extra.append("light_array")
        if state.displays_on() and "displays" not in cfg.emitters and "displays" not in cfg.skipped:
            extra.append("displays")
        if extra:
            cfg = replace(
                cfg,
                emitters=cfg.emitters + tuple(extra),
                reasons=cfg.reasons
                + (f"also switched on at capture time: {', '.join(extra)} (rendered with that group's own selection)",),
            )
        return cfg

    def passes_for(
        self, state: SimState, effects: EffectConfig | None = None, *, camera: Camera | None = None
    ) -> list[RenderPass]:
        """The Mitsuba renders a capture in ``state`` is the sum of.

        Without ``effects``, each emitter group switched on gets the selection of its own
        phase: the displays that of ``matting``, the lights that of ``reflectance`` (one
        light) or ``lightfield``; with the board on the table both get ``calibration``.
        With ``effects`` every group uses it (groups not in ``effects.emitters`` are not
        rendered). Either way, with nothing on the table only the displays are rendered,
        at depth 1 (:func:`~opacityhull.sim.effects.backdrop_only_effects`: exact).
        ``camera`` (the one rendered): its size picks a declared matting shot's samples.

        Raises
        ------
        ConfigError
            A light id that is not in the rig.
        """
        lights = state.lights_on()
        for lid in lights:
            self.geometry.light(lid)  # raises ConfigError for an unknown id
        disp = {n for n in state.displays_on() if self._has_display(n)}
        if effects is not None:
            cfg_d = cfg_l = effects
        elif state.content == "board":
            cfg_d = cfg_l = self._select("calibration")
        else:
            # a declared envmatte shot gets its own selection; every other displays pass
            # the matting one (at both phases' samples unless matting was declared)
            cfg_d = (
                self._select("envmatte", camera=camera)
                if state.phase == "envmatte"
                else self._select("matting", declared=state.phase == "matting", camera=camera)
            )
            cfg_l = self._select("reflectance" if len(lights) == 1 else "lightfield")
        if state.content == "none":
            cfg_d, cfg_l = backdrop_only_effects(cfg_d), None
        passes = []
        if disp and "displays" in cfg_d.emitters:
            passes.append(RenderPass("displays", cfg_d))
        if cfg_l is not None and "light_array" in cfg_l.emitters:
            passes.extend(RenderPass("light", cfg_l, (lid, level)) for lid, level in sorted(lights.items()))
        return passes

    def render(
        self,
        rig_camera: Camera,
        state: SimState,
        *,
        effects: EffectConfig | None = None,
        seed: int = 0,
        use_cache: bool = True,
    ) -> np.ndarray:
        """Radiance image (H, W, 3) float32 of ``rig_camera`` (pose in the rig frame) in
        ``state``: the sum of :meth:`passes_for` ``(state, effects)``.

        Parameters
        ----------
        rig_camera : Camera
            ``world_from_cam`` = rig_from_cam. No distortion (Mitsuba has none).
        state : SimState
        effects : EffectConfig, optional
            Force one configuration on every pass (default: each pass its own selection).
        seed : int
            Sampler seed; different seeds give independent noise (for passes not taken
            from the radiance cache).
        use_cache : bool
            Reuse (and keep) passes of physical states rendered before (module docstring).
            Off for timing and noise measurements.
        """
        if effects is not None and effects.integrator == "aov":
            raise InputError("render(): the aov integrator is for ground truth (groundtruth.render_ground_truth)")
        passes = self.passes_for(state, effects, camera=rig_camera)
        out = np.zeros((rig_camera.height, rig_camera.width, 3), np.float32)
        if not passes:
            return out
        parts = self._content_parts(state)
        for k, p in enumerate(passes):
            key = self._pass_key(rig_camera, state, p) if use_cache and self.cache_bytes > 0 else None
            img = self._cache_get(key)
            if img is None:
                img = self._render_pass(rig_camera, state, p, parts, seed * 1009 + k, use_cache=use_cache)
                self._cache_put(key, img)
            out += img
        return out

    def _select(self, phase: str, *, declared: bool = True, camera: Camera | None = None) -> EffectConfig:
        pixels = None if camera is None else camera.width * camera.height
        return select_effects(
            self.scene,
            phase,
            overrides=self.overrides or None,
            declared=declared,
            pixels=pixels,
            lamp_radius_m=lamp_radius(self.geometry),
        )

    def _render_pass(
        self, rig_camera: Camera, state: SimState, p: RenderPass, parts, seed: int, *, use_cache: bool = True
    ) -> np.ndarray:
        cfg = p.effects
        cam = self._render_camera(rig_camera, cfg)
        view = RigGeometry.view_camera(cam, state.table_deg)
        win = self.crop_for(cam, state, cfg, parts)
        self.pixels_framed += cam.width * cam.height
        x0, y0, w, h = win if win is not None else (0, 0, cam.width, cam.height)
        if win is not None:
            self.pixels_rendered += w * h
            if p.group == "displays":
                bp = RenderPass("displays", backdrop_only_effects(cfg))
                bstate = replace(state, content="none", charuco=None)
                key = self._pass_key(rig_camera, bstate, bp) if use_cache and self.cache_bytes > 0 else None
                base = self._cache_get(key)
                if base is None:
                    base = self._render_pass(rig_camera, bstate, bp, (), seed + 7919, use_cache=use_cache)
                    self._cache_put(key, base)
                out = np.array(base, dtype=np.float32)  # cached passes are read-only
            else:
                out = np.zeros((cam.height, cam.width, 3), np.float32)  # black panels: exactly 0
            if w == 0 or h == 0:
                return out  # nothing on the table is in view
            view = crop_camera(view, x0, y0, w, h)
        else:
            self.pixels_rendered += cam.width * cam.height
        if p.group == "displays":
            on = {n: img for n, img in state.displays_on().items() if self._has_display(n)}
            loaded = self._get(cfg, parts, state, cam, mode=("displays", tuple(sorted(on))))
            img = self._run(loaded, view, state, cfg, seed, displays=on)
        else:
            if p.light is None:  # point light and lamp sphere: one Mitsuba scene per radius
                raise InputError("a light pass without a light (RenderPass.light is None)")
            loaded = self._get(cfg, parts, state, cam, mode=("light", self.geometry.light(p.light[0]).radius_m))
            img = self._run(loaded, view, state, cfg, seed, light=p.light)
        if win is not None:
            out[y0 : y0 + h, x0 : x0 + w] = img
            img = out
        if cam.size != rig_camera.size:
            img = _downsample(img, rig_camera.width, rig_camera.height)
        return img

    def crop_for(
        self, rig_camera: Camera, state: SimState, cfg: EffectConfig, parts
    ) -> tuple[int, int, int, int] | None:
        """The window ``(x0, y0, w, h)`` a pass renders of ``rig_camera`` (rig frame) in
        ``state``, or None for the whole frame: no crop asked for (``cfg.crop``),
        supersampling (``resolution_scale`` != 1: the box-filtered downsampling would mix
        the border), nothing on the table, a bounding box reaching behind the camera, or
        a window over :data:`CROP_MAX_FRACTION` of the frame. ``w == 0`` means nothing on
        the table is in view.

        The window holds the footprint of the bounding box at this table angle; its
        *size* is that of the footprint of :func:`turntable_box` seen by the rig camera —
        the same at every table angle, so one camera compiles one kernel per
        configuration, not one per angle."""
        if not cfg.crop or abs(float(cfg.resolution_scale) - 1.0) > 1e-9 or not parts or state.content == "none":
            return None
        if state.content == "board":
            # calibration shots are few, and the board's corners must come out as the full
            # frame renders them (measured: a cropped render moved one camera's calibrated
            # rotation from within 0.4 deg to 0.48 deg); the crop saves nothing worth that
            return None
        bkey = (state.content, repr(state.charuco) if state.content == "board" else None)
        bounds = self._bounds.get(bkey)
        if bounds is None:
            from .scenes import parts_bounds

            bounds = self._bounds[bkey] = parts_bounds(parts)
        view = RigGeometry.view_camera(rig_camera, state.table_deg)
        fp = footprint_window(view, *bounds)
        if fp is None:
            return None
        fp_all = footprint_window(rig_camera, *turntable_box(*bounds))
        least = (0, 0) if fp_all is None else (fp_all[2] - fp_all[0], fp_all[3] - fp_all[1])
        win = crop_window(fp, view.width, view.height, min_size=least)
        if win[2] * win[3] > CROP_MAX_FRACTION * view.width * view.height:
            return None
        return win

    def _pass_key(self, cam: Camera, state: SimState, p: RenderPass) -> tuple:
        e = p.effects
        cam_key = (
            cam.width,
            cam.height,
            np.asarray(cam.K, np.float64).tobytes(),
            np.asarray(cam.world_from_cam, np.float64).tobytes(),
        )
        content = (state.content, repr(state.charuco) if state.content == "board" else None)
        if p.group == "displays":
            what = tuple((n, _digest(img)) for n, img in sorted(state.displays_on().items()) if self._has_display(n))
            array = None
        else:
            what, array = p.light, float(state.array_deg)
        return (p.group, e.key(), e.spp, e.resolution_scale, cam_key, float(state.table_deg), array, content, what)

    def _cache_get(self, key) -> np.ndarray | None:
        if key is None:
            return None
        with self._radiance_lock:
            img = self._radiance.get(key)
            if img is not None:
                self._radiance.move_to_end(key)
                self.cache_hits += 1
            return img

    def _cache_put(self, key, img: np.ndarray) -> None:
        if key is None or img.nbytes > self.cache_bytes:
            return
        img.setflags(write=False)  # shared between captures: never modified in place
        with self._radiance_lock:
            if key in self._radiance:
                return
            self._radiance[key] = img
            self._radiance_bytes += img.nbytes
            while self._radiance_bytes > self.cache_bytes and self._radiance:
                _, old = self._radiance.popitem(last=False)
                self._radiance_bytes -= old.nbytes

    def clear_radiance_cache(self) -> None:
        """Forget every cached pass (e.g. after changing the scene's geometry in place)."""
        with self._radiance_lock:
            self._radiance.clear()
            self._radiance_bytes = 0

    def render_rgba(
        self,
        camera_object: Camera,
        parts: Sequence[Part],
        *,
        extra: Mapping | None = None,
        integrator: dict,
        spp: int,
        sampler: str = "stratified",
        seed: int = 0,
        key: tuple = (),
        shape_names_out: dict[int, str] | None = None,
        updates: Mapping | None = None,
    ) -> np.ndarray:
        """Low-level: render ``parts`` (plus ``extra`` Mitsuba dict entries) from a camera
        posed in the object frame with the given integrator; returns the raw film
        channels (H, W, C). A ``shape_names_out`` dict is filled with the map from aov
        ``shape_index`` values to shape ids (``obj_<i>`` for part i). ``extra`` is used
        when the scene is first loaded (``key`` identifies it); ``updates`` (Mitsuba
        parameter name → value, e.g. a ``to_world``) are applied before every render.
        Used by ground truth and environment-map renders. A ``stratified`` sampler
        takes a square sample count: ``spp`` is rounded up to the next square (as
        Mitsuba would, but without its warning per render)."""
        mi = self.mi
        if sampler == "stratified":
            spp = math.isqrt(max(int(spp), 1) - 1) + 1
            spp *= spp
        full_key = (
            "raw",
            key,
            _camera_key(camera_object),
            sampler,
            spp,
            tuple(p.name for p in parts),
            repr(integrator),
        )
        with self._cache_lock:
            loaded = self._cache.get(full_key)
            if loaded is None:
                d = {
                    "type": "scene",
                    "integrator": integrator,
                    "sensor": sensor_dict(mi, camera_object, sampler=sampler, spp=spp),
                }
                d.update(part_dicts(mi, parts))
                d.update(extra or {})
                sc = mi.load_dict(d, optimize=False)  # keep shapes separate: their params are rewritten
                self.loads += 1
                loaded = _Loaded(sc, _traverse(mi, sc), {})
                self._cache[full_key] = loaded
        with loaded.lock:
            self._set_sensor(loaded, "sensor", camera_object)
            for k, v in (updates or {}).items():
                loaded.assign(k, _signature(v), lambda v=v: v)
            loaded.params.update()
            img = _render_array(mi, loaded.scene, loaded.params, seed=seed, spp=spp)
            self.renders += 1
            if shape_names_out is not None:
                shape_names_out.update(shape_index_names(mi, loaded.scene))
            return img

    def cache_info(self) -> dict:
        """Mitsuba scenes loaded and renders run; radiance-cache entries, bytes and hits."""
        return {
            "scenes": len(self._cache),
            "loads": self.loads,
            "renders": self.renders,
            "radiance_entries": len(self._radiance),
            "radiance_bytes": self._radiance_bytes,
            "radiance_hits": self.cache_hits,
        }

    # ---- internals
    def _has_display(self, name: str) -> bool:
        return any(d.name == name for d in self.geometry.displays)

    def _content_parts(self, state: SimState) -> tuple[Part, ...]:
        if state.content == "object":
            return self.scene.parts
        if state.content == "board":
            if state.charuco is None:
                return tuple(p for p in self.scene.parts if p.kind == "board") or board_parts(CharucoSpec())
            return board_parts(state.charuco)
        if state.content == "none":
            return ()
        raise InputError(f"state.content {state.content!r}: expected 'object', 'board' or 'none'")

    @staticmethod
    def _render_camera(rig_camera: Camera, cfg: EffectConfig) -> Camera:
        s = float(cfg.resolution_scale)
        return rig_camera if abs(s - 1.0) < 1e-9 else rig_camera.scaled(s)

    def _get(self, cfg: EffectConfig, parts, state: SimState, cam: Camera, mode: tuple) -> _Loaded:
        content_key = (
            state.content,
            None if state.charuco is None or state.content != "board" else repr(state.charuco),
        )
        key = ("capture", cfg.key(), cfg.spp, content_key, _camera_key(cam), mode)
        with self._cache_lock:
            loaded = self._cache.get(key)
            if loaded is None:
                loaded = self._build(cfg, parts, cam, mode)
                self._cache[key] = loaded
            return loaded

    def _build(self, cfg: EffectConfig, parts, cam: Camera, mode: tuple) -> _Loaded:
        mi = self.mi
        d: dict = {
            "type": "scene",
            "integrator": _integrator_dict(cfg),
            "sensor": sensor_dict(mi, cam, sampler=cfg.sampler, spp=cfg.spp),
        }
        d.update(part_dicts(mi, parts))
        emitting = set(mode[1]) if mode[0] == "displays" else set()
        keys: dict = {"displays": {}}
        if "displays" in cfg.shapes or emitting:
            for i, disp in enumerate(self.geometry.displays):
                k = f"display_{i}"
                entry = {
                    "type": "rectangle",
                    "to_world": mi.ScalarTransform4f(display_to_world(disp, 0.0)),
                    "bsdf": _black(),
                }
                if disp.name in emitting:
                    w, h = disp.resolution
                    entry["emitter"] = {
                        "type": "area",
                        "radiance": _texture(mi, np.zeros((h, w, 3), np.float32), nearest=True),
                    }
                d[k] = entry
                keys["displays"][disp.name] = k
        if mode[0] == "light":
            radius = mode[1] if len(mode) > 1 else None
            if radius is None:
                d["light"] = {
                    "type": "point",
                    "position": [0.0, 1.0, 0.0],
                    "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
                }
            else:
                d["light"] = {
                    "type": "sphere",
                    "to_world": mi.ScalarTransform4f(_lamp_to_world((0.0, 1.0, 0.0), radius)),
                    "bsdf": _black(),
                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
                }
                # seen directly it would break the crop's "exactly 0 outside the window"
                # (and is out of every camera's field); through glass it stays visible
                d["integrator"] = dict(d["integrator"], hide_emitters=True)
        sc = mi.load_dict(d, optimize=False)  # keep shapes separate: their params are rewritten
        self.loads += 1
        return _Loaded(sc, _traverse(mi, sc), keys)

    def _set_sensor(self, loaded: _Loaded, name: str, cam: Camera) -> None:
        mi = self.mi
        p = mitsuba_sensor_params(cam)
        pre = f"{name}." if name else ""
        T = np.asarray(p["to_world"], dtype=np.float64)
        # the stubs lack the constructor from a (4, 4) array that Mitsuba has
        loaded.assign(f"{pre}to_world", T.tobytes(), lambda: mi.AffineTransform4f(T))  # pyright: ignore[reportCallIssue, reportArgumentType]
        fov_x = math.degrees(2.0 * math.atan(cam.width / (2.0 * cam.fx)))
        loaded.assign(f"{pre}x_fov", fov_x, lambda: fov_x)
        for k in ("principal_point_offset_x", "principal_point_offset_y"):
            loaded.assign(f"{pre}{k}", float(p[k]), lambda k=k: p[k])

    def _crop_sensor(self, loaded: _Loaded, view: Camera, cfg: EffectConfig) -> _Loaded:
        """A sensor of ``view``'s film size for renders of ``loaded``'s scene (one per size;
        the caller holds ``loaded.lock``). Its pose and principal point are parameters,
        so moving the window costs no kernel compilation."""
        mi = self.mi
        sensors = loaded.keys.setdefault("crop_sensors", {})
        key = (view.width, view.height, cfg.sampler, cfg.spp)
        s = sensors.get(key)
        if s is None:
            sensor = mi.load_dict(sensor_dict(mi, view, sampler=cfg.sampler, spp=cfg.spp))
            params = mi.traverse(sensor)
            params.keep([r"to_world", r"x_fov", r"principal_point_offset_.*"])
            s = sensors[key] = _Loaded(sensor, params, {})
        return s

    def _run(
        self,
        loaded: _Loaded,
        view: Camera,
        state: SimState,
        cfg: EffectConfig,
        seed: int,
        *,
        displays: Mapping[str, np.ndarray] | None = None,
        light: tuple[int, int] | None = None,
    ) -> np.ndarray:
        mi = self.mi
        with loaded.lock:
            params = loaded.params
            film = loaded.scene.sensors()[0].film().crop_size()
            if (int(film[0]), int(film[1])) == view.size:
                self._set_sensor(loaded, "sensor", view)
                sensor = 0
            else:  # a crop window: its own sensor, the scene's stays as it is
                cs = self._crop_sensor(loaded, view, cfg)
                self._set_sensor(cs, "", view)
                cs.params.update()
                sensor = cs.scene
            for disp in self.geometry.displays:
                k = loaded.keys["displays"].get(disp.name)
                if k is None:
                    continue
                T = display_to_world(disp, state.table_deg)
                loaded.assign(f"{k}.to_world", T.tobytes(), lambda T=T: mi.AffineTransform4f(T))
                if displays is not None and disp.name in displays:
                    pat = displays[disp.name]
                    loaded.assign(
                        f"{k}.emitter.radiance.data",
                        _digest(pat),
                        lambda disp=disp, pat=pat: _tensor(mi, display_radiance(disp, pat)[::-1]),
                    )
            if light is not None:
                lid, level = light
                pos_rig = self.geometry.light(lid).position_rig(state.array_deg)
                pos = tuple(float(v) for v in object_from_rig(state.table_deg)[:3, :3] @ pos_rig)
                rgb = tuple(float(v) for v in light_intensity(self.geometry, lid, level))
                radius = self.geometry.light(lid).radius_m
                if radius is None:
                    loaded.assign("light.position", pos, lambda: mi.Point3f(*pos))
                    loaded.assign("light.intensity.value", rgb, lambda: mi.Color3f(*rgb))
                else:
                    T = _lamp_to_world(pos, radius)
                    # radiance of a sphere whose intensity (W/sr) in every direction is the
                    # point light's: I = L·πr², so irradiance at the origin is unchanged
                    rad = tuple(v / (math.pi * radius * radius) for v in rgb)
                    loaded.assign("light.to_world", T.tobytes(), lambda T=T: mi.AffineTransform4f(T))  # pyright: ignore[reportCallIssue, reportArgumentType]
                    loaded.assign("light.emitter.radiance.value", rad, lambda: mi.Color3f(*rad))
            params.update()
            img = _render_array(mi, loaded.scene, params, sensor=sensor, seed=seed, spp=cfg.spp)
            self.renders += 1
            return img[:, :, :3]


def _render_array(mi, scene, params, *, sensor=0, seed: int, spp: int) -> np.ndarray:
    """``mi.render`` evaluated into a float32 (H, W, C) array, with Ctrl-C, SIGTERM and
    SIGHUP held back until it is done (:func:`~opacityhull.interrupts.deferred_signals`):
    raised inside the render, an interrupt comes out of Dr.Jit as a ``RuntimeError``;
    Mitsuba's own SIGINT handler, run on this thread while it traces, can deadlock it in
    ``malloc``; and a capture must see the interrupt between two exposures. The kernel
    runs in ``np.array`` (``mi.render`` only traces it), so both are covered."""
    with deferred_signals("mi.render"):
        log.debug("mi.render: %d spp, seed %d", int(spp), int(seed))
        # the stubs type seed as mi.UInt32; Mitsuba converts a Python int
        img = mi.render(
            scene,
            params,
            sensor=sensor,
            seed=int(seed) & 0x7FFFFFFF,  # pyright: ignore[reportArgumentType]
            spp=int(spp),
        )
        return np.array(img, dtype=np.float32)


def shape_index_names(mi, scene) -> dict[int, str]:
    """Value of the aov ``shape_index`` channel → shape id (the Mitsuba dict key).

    In the JIT variants the channel holds the shape's registry id, which counts shapes
    across every scene loaded in the process; in scalar variants it is 1 + the position
    in ``scene.shapes()``. 0 is the background in both.
    """
    shapes = list(scene.shapes())
    ptr_type = getattr(mi, "ShapePtr", None)
    if ptr_type is not None and not mi.variant().startswith("scalar"):
        import drjit as dr

        ids = np.array(dr.reinterpret_array(mi.UInt32, ptr_type(shapes))).astype(np.int64).ravel().tolist()
    else:
        ids = list(range(1, len(shapes) + 1))
    return {int(i): s.id() for i, s in zip(ids, shapes, strict=True)}


def _signature(v):
    """A comparable signature of a parameter value (Mitsuba transforms via NumPy)."""
    try:
        return np.asarray(v.matrix if hasattr(v, "matrix") else v, dtype=np.float64).tobytes()
    except (TypeError, ValueError):
        return ("id", id(v))


def _digest(img: np.ndarray) -> str:
    a = np.ascontiguousarray(img)
    return hashlib.sha1(a.tobytes() + repr((a.shape, a.dtype.str)).encode()).hexdigest()


def _downsample(img: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA).astype(np.float32)
