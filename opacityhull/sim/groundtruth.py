"""Ground truth from the simulator: coverage alpha, depth, normals, shape ids, renders
under environment maps, and the ``groundtruth/`` folder of a simulated session.

Coverage alpha comes from an **object-only** render (no displays, no emitters) with the
``aov`` integrator and stratified pixel samples: the fraction of each pixel's area the
object covers. (The rgba film of a scene with backdrops has alpha 1 wherever a display
is hit — PITFALLS.)

Environment maps follow the project convention: equirectangular, +Y up, the centre
column looks along +Z; column ``u`` (in [0, 1) from the left edge) and row ``v`` (from
the top) look along ``(sin φ sin θ, cos θ, −cos φ sin θ)`` with ``φ = 2π u`` and
``θ = π v``, so u = 0.25 looks along +X and u = 0.75 along −X (the OpenEXR latitude-
longitude layout; :func:`equirect_direction`). That is
Mitsuba's own ``envmap`` mapping (verified by ``tests/sim/test_groundtruth.py`` with a
map bright only in one direction), so :func:`envmap_for_mitsuba` is where a conversion
would go and currently only validates.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ..camera import Camera, write_colmap_text, write_opencv_yaml
from ..envmap import direction_to_uv, uv_to_direction
from ..errors import InputError, ShapeError
from ..imageio import atomic_path, write_exr
from ..riggeometry import RigGeometry, view_id
from .effects import select_effects
from .render import NEAR_CLIP_M, SimRenderer, _black, display_to_world, light_intensity
from .scenes import DATA_DIR, Part, SceneSpec
from .shapes import write_ply_mesh

__all__ = [
    "render_ground_truth",
    "render_under_envmap",
    "envmap_for_mitsuba",
    "equirect_direction",
    "direction_to_equirect",
    "write_ground_truth",
    "default_geometry",
]


def default_geometry() -> RigGeometry:
    """Geometry of the default simulated rig (``opacityhull/sim/data/rig.toml``)."""
    d = tomllib.loads((DATA_DIR / "rig.toml").read_text())
    return RigGeometry.from_dict(d["geometry"], where=f"{DATA_DIR / 'rig.toml'}: geometry")


# --------------------------------------------------------------------------- envmaps


def equirect_direction(u, v) -> np.ndarray:
    """Unit direction (…, 3) of equirectangular coordinates ``u`` (columns, [0, 1) from
    the left edge) and ``v`` (rows, [0, 1] from the top): +Y up, u = 0.5 → +Z,
    u = 0.25 → +X, u = 0.75 → −X (:func:`opacityhull.envmap.uv_to_direction`)."""
    return uv_to_direction(u, v)


def direction_to_equirect(d) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`equirect_direction` (:func:`opacityhull.envmap.direction_to_uv`)."""
    return direction_to_uv(d, invalid="raise")


def envmap_for_mitsuba(envmap_rgb: np.ndarray) -> np.ndarray:
    """The equirectangular map (rows, cols, 3) float32 in the project convention, as
    Mitsuba's ``envmap`` expects it. The conventions coincide (pinned by a test), so
    this validates and copies: non-negative finite RGB."""
    env = np.asarray(envmap_rgb, dtype=np.float32)
    if env.ndim != 3 or env.shape[2] not in (3, 4) or env.shape[0] < 2 or env.shape[1] < 2:
        raise ShapeError(f"environment map has shape {env.shape}, expected (rows, cols, 3) equirectangular")
    env = env[:, :, :3]
    if not np.all(np.isfinite(env)) or np.any(env < 0):
        raise InputError("environment map has negative, NaN or Inf values")
    return np.ascontiguousarray(env)


# --------------------------------------------------------------------------- renders


_SHARED: dict[int, tuple[SceneSpec, SimRenderer]] = {}


def _renderer(scene: SceneSpec, geometry: RigGeometry | None, renderer: SimRenderer | None) -> SimRenderer:
    """The caller's renderer if it renders ``scene``, else one shared per scene (so that
    repeated calls — many views, many environment maps — reuse loaded Mitsuba scenes)."""
    if renderer is not None and renderer.scene is scene:
        return renderer
    hit = _SHARED.get(id(scene))
    if hit is not None and hit[0] is scene:
        return hit[1]
    if len(_SHARED) >= 4:
        _SHARED.pop(next(iter(_SHARED)))
    r = SimRenderer(scene, geometry or default_geometry())
    _SHARED[id(scene)] = (scene, r)  # holding the scene keeps its id from being reused
    return r


def render_ground_truth(
    scene: SceneSpec,
    camera: Camera,
    *,
    spp: int | None = None,
    parts: Sequence[Part] | None = None,
    renderer: SimRenderer | None = None,
    seed: int = 0,
) -> dict:
    """Coverage alpha, depth, normals and shape ids of the object alone.

    Parameters
    ----------
    scene : SceneSpec
    camera : Camera
        Posed in the **object frame** (a view camera, ``RigGeometry.view_camera``).
    spp : int, optional
        Stratified samples per pixel (rounded to a square); default from
        ``select_effects(scene, "groundtruth")`` (64, or 256 with fibres).
    parts : sequence of Part, optional
        What to render (default: the scene's object).
    renderer : SimRenderer, optional
        Reuse its scene cache.

    Returns
    -------
    dict with
        ``alpha`` (H, W) float32 — covered fraction of each pixel, in [0, 1];
        ``depth`` (H, W) float32 — z along the optical axis (metres) of the object
        surface, averaged over the covered part of the pixel; NaN where alpha = 0;
        ``normals`` (H, W, 3) float32 — unit shading normals in the object frame, 0 where
        alpha = 0;
        ``shape_id`` (H, W) int32 — 1 + index of the part seen at a sample inside the
        pixel (one sample per pixel), 0 = background.
    """
    if camera.has_distortion:
        raise InputError(f"camera {camera.name!r} has distortion; ground truth is rendered undistorted")
    cfg = select_effects(scene, "groundtruth")
    spp = int(spp or cfg.spp)
    if spp < 1:
        raise InputError(f"spp must be >= 1, got {spp}")
    parts = tuple(scene.parts if parts is None else parts)
    H, W = camera.height, camera.width
    if not parts:
        return {
            "alpha": np.zeros((H, W), np.float32),
            "depth": np.full((H, W), np.nan, np.float32),
            "normals": np.zeros((H, W, 3), np.float32),
            "shape_id": np.zeros((H, W), np.int32),
        }
    r = _renderer(scene, None, renderer)
    integ = {"type": "aov", "aovs": "dd:depth,nn:sh_normal,si:shape_index", "inner": {"type": "direct"}}
    img = r.render_rgba(camera, parts, integrator=integ, spp=spp, sampler="stratified", seed=seed, key=("gt",))
    # channels: inner R G B A, dd, nn.xyz, si
    alpha = np.clip(img[:, :, 3], 0.0, 1.0)
    t_sum = img[:, :, 4]
    n_sum = img[:, :, 5:8]
    covered = alpha > 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(covered, t_sum / np.maximum(alpha, 1e-12), np.nan)
    _, dirs = camera.pixel_rays()
    cos = dirs @ camera.forward_world
    # Mitsuba starts camera rays on the near clip plane: add the near-plane z back
    depth = (t * cos + NEAR_CLIP_M).astype(np.float32)
    nrm = np.linalg.norm(n_sum, axis=2, keepdims=True)
    normals = np.where(covered[..., None] & (nrm > 1e-12), n_sum / np.maximum(nrm, 1e-12), 0.0).astype(np.float32)
    # shape ids: one sample per pixel so the index is not averaged with its neighbours
    shape_names: dict[int, str] = {}
    one = r.render_rgba(
        camera,
        parts,
        integrator=integ,
        spp=1,
        sampler="independent",
        seed=seed + 1,
        key=("gt1",),
        shape_names_out=shape_names,
    )
    sid_raw = np.rint(one[:, :, 8]).astype(np.int32)
    shape_id = np.zeros_like(sid_raw)
    for i, name in shape_names.items():
        if name.startswith("obj_"):
            shape_id[sid_raw == i] = int(name[4:]) + 1
    return {"alpha": alpha.astype(np.float32), "depth": depth, "normals": normals, "shape_id": shape_id}


def _as_geometry(rig) -> RigGeometry:
    if rig is None:
        return default_geometry()
    if isinstance(rig, RigGeometry):
        return rig
    g = getattr(rig, "geometry", None)
    if isinstance(g, RigGeometry):
        return g
    if isinstance(rig, (str, Path)):
        p = Path(rig)
        try:
            d = tomllib.loads(p.read_text())
        except (OSError, tomllib.TOMLDecodeError) as e:
            raise InputError(f"rig {p}: cannot read rig TOML ({e})") from None
        return RigGeometry.from_dict(d.get("geometry", d), where=f"{p}: geometry")
    raise InputError(f"rig: expected a RigGeometry, a rig TOML path or a rig with .geometry, got {type(rig).__name__}")


def render_under_envmap(
    scene: SceneSpec,
    camera: Camera,
    envmap_rgb: np.ndarray,
    *,
    spp: int = 64,
    rig=None,
    table_deg: float = 0.0,
    seed: int = 0,
    renderer: SimRenderer | None = None,
) -> np.ndarray:
    """The object as it sits on the rig, lit by an environment map: straight RGBA.

    Parameters
    ----------
    scene : SceneSpec
    camera : Camera
        Posed in the **object frame** (a view camera); the environment map is in the
        object frame too (the relighting stage relights in that frame).
    envmap_rgb : (rows, cols, 3) float
        Equirectangular radiance, project convention (see module docstring).
    spp : int
        Samples per pixel.
    rig : RigGeometry, rig TOML path, or a rig with ``.geometry``; default the default
        simulated rig. Its displays are present, switched off: black panels that hide
        the part of the environment behind/below them. The light array is absent.
    table_deg : float
        Table angle, placing the displays that do not turn with the table.

    Returns
    -------
    (H, W, 4) float32: RGB radiance of the object (straight, i.e. divided by coverage),
    alpha = object coverage (object-only render). RGB is 0 where alpha = 0.

    Integrator and depth follow ``select_effects(scene, "lightfield")``.
    """
    from .variants import use_mitsuba

    env = envmap_for_mitsuba(envmap_rgb)
    geometry = _as_geometry(rig)
    r = _renderer(scene, geometry, renderer)
    mi = use_mitsuba(r.variant)
    cfg = select_effects(scene, "lightfield")
    if cfg.integrator == "direct":
        integ = {"type": "direct", "hide_emitters": True}
    else:
        integ = {"type": "path", "max_depth": int(cfg.max_depth), "hide_emitters": True}
    # the map is in the object frame (identity); only the rig-fixed displays move with the table
    extra = {"envmap": {"type": "envmap", "bitmap": mi.Bitmap(env)}}
    updates = {}
    for i, d in enumerate(geometry.displays):
        T = display_to_world(d, table_deg)
        extra[f"display_{i}"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(T), "bsdf": _black()}
        updates[f"display_{i}.to_world"] = mi.AffineTransform4f(T)
    import hashlib

    # a new map is a new scene (its sampling distribution is built at load); table angle
    # and camera only update parameters
    h = hashlib.sha1(env.tobytes()).hexdigest()[:16]
    dsig = hashlib.sha1(
        np.concatenate([display_to_world(d, 0.0).ravel() for d in geometry.displays] or [np.zeros(1)]).tobytes()
    ).hexdigest()[:16]
    key = ("envmap", h, env.shape, dsig, repr(integ))
    img = r.render_rgba(
        camera,
        scene.parts,
        extra=extra,
        integrator=integ,
        spp=spp,
        sampler="stratified",
        seed=seed,
        key=key,
        updates=updates,
    )
    rgb = img[:, :, :3]
    gt = render_ground_truth(scene, camera, spp=spp, renderer=r, seed=seed)
    alpha = gt["alpha"]
    with np.errstate(invalid="ignore", divide="ignore"):
        straight = np.where(alpha[..., None] > 1e-6, rgb / np.maximum(alpha[..., None], 1e-6), 0.0)
    return np.concatenate([straight, alpha[..., None]], axis=2).astype(np.float32)


# --------------------------------------------------------------------------- session ground truth


def write_ground_truth(
    root,
    *,
    scene: SceneSpec,
    geometry: RigGeometry,
    views: Sequence[tuple[int, float]],
    renderer: SimRenderer | None = None,
    rig_cameras: Sequence[Camera] | None = None,
    progress=None,
    spp: int | None = None,
) -> Path:
    """Write ``root/groundtruth/`` for the given views (camera index, table angle).

    Layout::

        cameras/                   COLMAP text: true view cameras in the object frame,
                                   image names = view ids c{c}_t{deg:07.3f}, one COLMAP
                                   camera per physical camera
        calibration/<name>.yaml    true rig cameras (OpenCV YAML, world_from_cam = rig_from_cam)
        alpha/<view id>.exr        coverage alpha of the object alone (1 channel)
        depth/<view id>.exr        z-depth in metres (1 channel, NaN off the object)
        normals/<view id>.exr      object-frame unit normals (RGB = xyz, 0 off the object)
        object.ply                 the object as triangles in the object frame
        lights.json                lights at array angle 0 (rig frame) and the light model
        scene.toml                 the scene spec

    Every file is written atomically. Returns the ``groundtruth`` folder.
    """
    gt = Path(root) / "groundtruth"
    gt.mkdir(parents=True, exist_ok=True)
    cams = list(rig_cameras) if rig_cameras is not None else geometry.nominal_cameras()
    uniq = []
    for c, a in views:
        key = (int(c), float(a) % 360.0)
        if not 0 <= key[0] < len(cams):
            raise InputError(f"ground truth: view camera index {c} not in 0..{len(cams) - 1}")
        if key not in uniq:
            uniq.append(key)
    r = _renderer(scene, geometry, renderer)
    # true cameras
    vcams = [RigGeometry.view_camera(cams[c], a, name=view_id(c, a)) for c, a in uniq]
    if vcams:
        write_colmap_text(gt / "cameras", vcams, [v.name for v in vcams], share_intrinsics=[c for c, _ in uniq])
    for cam in cams:
        write_opencv_yaml(gt / "calibration" / f"{cam.name}.yaml", cam)
    # object geometry, lights, scene
    write_ply_mesh(gt / "object.ply", scene.triangle_mesh())
    lights = {
        "frame": "rig frame at light-array angle 0; rotate about +Y by the array angle",
        "model": "point lights, or spheres of radius radius_m and uniform radiance I/(pi r^2) (the same "
        "intensity I in every direction); a light of intensity 1 gives irradiance 1 at the rig origin; "
        "DMX level L scales it by L/255",
        "lights": [
            {
                "id": L.id,
                "position_m": [float(v) for v in L.position_m],
                "intensity": float(L.intensity),
                "colour": [float(v) for v in L.colour],
                "radius_m": L.radius_m,
                "mitsuba_intensity_at_full_level": [float(v) for v in light_intensity(geometry, L.id, 255)],
            }
            for L in geometry.lights
        ],
    }
    with atomic_path(gt / "lights.json") as tmp:
        tmp.write_text(json.dumps(lights, indent=2) + "\n")
    from ..tomlio import toml_dumps

    with atomic_path(gt / "scene.toml") as tmp:
        tmp.write_text(toml_dumps(scene.to_toml_dict()))
    # per-view images
    for i, (_, vc) in enumerate(zip(uniq, vcams, strict=True)):
        res = render_ground_truth(scene, vc, spp=spp, renderer=r, seed=i)
        vid = vc.name
        write_exr(gt / "alpha" / f"{vid}.exr", res["alpha"])
        write_exr(gt / "depth" / f"{vid}.exr", res["depth"], header={"depth": "z along the optical axis, metres"})
        write_exr(gt / "normals" / f"{vid}.exr", res["normals"], header={"frame": "object"})
        if progress is not None:
            progress(i + 1, len(uniq))
    return gt
