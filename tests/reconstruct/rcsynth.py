"""Analytic test scenes for the reconstruction tests: sessions on disk whose every pixel
is known, written with the real :class:`opacityhull.session.SessionWriter`.

The object is a sphere (``kind="sphere"``) or a sphere core with a semi-transparent
halo (``kind="fuzzy"``: true alpha 0.35 where a ray meets only the halo, so mattes are
fractional there). Images are ray-cast in NumPy with ``ss × ss`` samples per pixel:
each sample sees the object or, behind it, the display texel the ray hits (the bottom
panel turns with the table, the back panel is fixed), so composites and coverage alpha
come from the same rays. This is independent of the code under test (it does not call
``matting.backdrop_from_displays``).

The photo-refinement tests' scene is in memory instead: a textured sphere inside a
larger sphere standing for the hull, both about the origin, seen by cameras on a sphere
(:func:`sphere_cameras`, :func:`sphere_photo`, :func:`sphere_hull_surfels`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from opacityhull.camera import Camera, look_at_world_from_cam, object_from_rig, write_colmap_text, write_opencv_yaml
from opacityhull.imageio import read_png, write_exr, write_png
from opacityhull.riggeometry import RigGeometry, view_id
from opacityhull.session import SessionWriter

# the rig, the ray caster and the shot keys are shared with the paper-scale session
# writer (one copy of the scene)
from opacityhull.acquire.synthetic import CENTRE_M, CORE_R_M
from opacityhull.acquire.synthetic import panel_hits as _panel_hits
from opacityhull.acquire.synthetic import panel_texels as _panel_texels
from opacityhull.acquire.synthetic import pixel_rays as _rays
from opacityhull.acquire.synthetic import record_shot_key
from opacityhull.acquire.synthetic import synthetic_rig as rig_dict
from opacityhull.acquire.synthetic import sphere_albedo as _albedo
from opacityhull.acquire.synthetic import sphere_hit_t as _sphere_t

CORE_R = CORE_R_M  # the paper-scale writer's sphere: 0.04 m at (0, 0.06, 0)
HALO_R = 0.055
CENTRE = CENTRE_M
HALO_ALPHA = 0.35


def _display_radiance(o, d, table_deg, geo: RigGeometry, patterns: dict | None):
    """Radiance of the displays along rays (object frame); 0 where no display is hit."""
    out = np.zeros((d.shape[0], 3))
    best = np.full(d.shape[0], np.inf)
    if patterns is None:
        return out
    Robj = object_from_rig(table_deg)[:3, :3]
    for disp in geo.displays:
        pat = patterns.get(disp.name)
        if pat is None:
            continue
        t, x, y, inside = _panel_hits(o, d, disp, Robj)
        hit = inside & (t < best)
        rows, cols = pat.shape[:2]
        row, col = _panel_texels(x[hit], y[hit], disp.size_m, rows, cols)
        out[hit] = disp.max_radiance * pat[row, col]
        best[hit] = t[hit]
    return out


def render_view(
    cam: Camera,
    table_deg: float,
    geo: RigGeometry,
    *,
    kind="sphere",
    patterns=None,
    light_dir=None,
    ss=3,
    rays=None,
    hide_object=False,
):
    """(colour (H, W, 3), alpha (H, W)) of the object in front of the displays showing
    ``patterns`` ({display: (rows, cols, 3)} or None = dark), lit by a directional
    ``light_dir`` (object frame) plus ambient (None: a fixed key light)."""
    H, W = cam.height, cam.width
    o, d = rays if rays is not None else _rays(cam, ss)
    tc = _sphere_t(o, d, CENTRE, CORE_R)
    if hide_object:
        tc = np.full_like(tc, np.inf)
    core = np.isfinite(tc)
    X = o + np.where(core, tc, 0.0)[:, None] * d
    n = (X - CENTRE) / CORE_R
    L = np.array([0.5, 0.8, 0.4]) if light_dir is None else np.asarray(light_dir, float)
    L = L / np.linalg.norm(L)
    shade = (0.15 if light_dir is None else 0.0) + 0.85 * np.clip(n @ L, 0, None)
    Fcore = _albedo(n) * shade[:, None]
    back = _display_radiance(o, d, table_deg, geo, patterns)
    col = np.where(core[:, None], Fcore, back)
    a = core.astype(np.float64)
    if kind == "fuzzy" and not hide_object:
        halo = (~core) & np.isfinite(_sphere_t(o, d, CENTRE, HALO_R))
        Fh = np.array([0.6, 0.5, 0.35]) * (0.3 if light_dir is None else 0.8 * max(L[1], 0.0))
        col = np.where(halo[:, None], HALO_ALPHA * Fh + (1 - HALO_ALPHA) * back, col)
        a = np.where(halo, HALO_ALPHA, a)
    col = col.reshape(H, W, ss * ss, 3).mean(2)
    a = a.reshape(H, W, ss * ss).mean(2)
    return col.astype(np.float32), a.astype(np.float32)


def uv_sphere(c, r, seg=48, rings=24):
    th = np.linspace(0, np.pi, rings + 1)
    ph = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    V = [c + r * np.array([0, 1, 0])]
    for t in th[1:-1]:
        for p in ph:
            V.append(c + r * np.array([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)]))
    V.append(c - r * np.array([0, 1, 0]))
    V = np.array(V)
    F = []
    for j in range(seg):
        F.append([0, 1 + j, 1 + (j + 1) % seg])
    for i in range(rings - 2):
        for j in range(seg):
            a = 1 + i * seg + j
            b = 1 + i * seg + (j + 1) % seg
            F += [[a, a + seg, b], [b, a + seg, b + seg]]
    last = len(V) - 1
    base = 1 + (rings - 2) * seg
    for j in range(seg):
        F.append([base + j, last, base + (j + 1) % seg])
    F = np.array(F)
    # orient outwards
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    nrm = np.cross(B - A, C - A)
    flip = (nrm * (A + B + C - 3 * c)).sum(1) < 0
    F[flip] = F[flip][:, ::-1]
    return V, F


def write_ply(path, V, F):
    from plyfile import PlyData, PlyElement

    v = np.empty(len(V), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = V.T
    f = np.empty(len(F), dtype=[("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = F
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")]).write(str(path))


def make_session(
    root,
    *,
    kind="sphere",
    n_cams=3,
    n_angles=6,
    width=64,
    height=48,
    n_patterns=2,
    object_absent=True,
    off_shots=True,
    reflectance=True,
    cameras="yaml",
    noise=0.002,
    seed=0,
    ss=3,
    exposure_s=1.0,
    white_level=4.0,
    rms_px=0.3,
    hide_object_in=(),
    calibration_phase=False,
    elevations=(15.0, 55.0),
    board_hidden_from=(),
    reflectance_level=255,
):
    """Write a session folder; returns a dict with geometry, views, true alphas, cameras.

    ``cameras``: "yaml" (calibration/<cam>.yaml), "none" (no camera source at all).
    ``n_patterns`` random patterns, each followed by its complement (2 n_patterns shots).
    ``hide_object_in``: view ids whose images show no object (an empty silhouette).
    ``calibration_phase``: add ChArUco captures (the board lying on the table, rendered by
    the calibration module's independent ray caster) at the session's table angles.
    ``board_hidden_from``: camera indices whose calibration images show no board (a
    camera that cannot be calibrated).
    ``reflectance_level``: DMX level of the one-light shots (recorded in ``extra``); the
    images are dimmed by ``level / 255`` as a real light would be.
    """
    root = Path(root)
    rng = np.random.default_rng(seed)
    rig = rig_dict(n_cams, width, height, elevations=elevations)
    geo = RigGeometry.from_dict(rig)
    rig_cams = geo.nominal_cameras()
    angles = [360.0 * i / n_angles for i in range(n_angles)]
    views = [(c, a) for c in range(n_cams) for a in angles]
    meta = {
        "session": {
            "rig_source": f"synthetic:{kind}",
            "plan_name": "synthetic",
            "white_level": white_level,
            "seed": seed,
        },
        "rig": rig,
    }
    if calibration_phase:
        from opacityhull.charuco import CharucoSpec

        spec = CharucoSpec()
        meta["charuco"] = spec.to_dict()
    w = SessionWriter(root, fsync=False).create(meta)
    # patterns: random cells and their complements, saved as uploaded (8-bit PNG)
    pats = {}
    for k in range(n_patterns):
        base = {}
        for d in geo.displays:
            cols, rows = d.resolution
            base[d.name] = rng.uniform(0.05, 0.95, (rows, cols, 3)).astype(np.float32)
        for pid, imgs in ((2 * k + 1, base), (2 * k + 2, {n: 1.0 - x for n, x in base.items()})):
            for name, img in imgs.items():
                write_png(root / "patterns" / name / f"p{pid:03d}.png", img, linear=True)
            pats[pid] = {
                d.name: read_png(root / "patterns" / d.name / f"p{pid:03d}.png", linear=True) for d in geo.displays
            }
    gain = 1.0

    def add(img, phase, c, a, **kw):
        key = record_shot_key(phase, c, a, kw)
        img = img + rng.normal(0.0, noise, img.shape).astype(np.float32)
        val = np.minimum(img * gain * exposure_s, white_level).astype(np.float32)
        w.add_image(
            val,
            id=f"{key}/e0",
            shot=key,
            phase=phase,
            camera=c,
            table_deg=a,
            rel_path=f"images/{key}_e0.exr",
            exposure_s=exposure_s,
            **kw,
        )

    if calibration_phase:
        from opacityhull.reconstruct.calibration import render_charuco_view

        for c in range(n_cams):
            for a in angles:
                cam = RigGeometry.view_camera(rig_cams[c], a)
                if c in board_hidden_from:
                    img = np.full((height, width), 0.4, np.float32)
                else:
                    img = render_charuco_view(
                        cam, world_from_board=spec.object_from_board(), charuco=spec, px_per_square=48
                    )
                img = np.asarray(img, np.float32)
                if img.ndim == 2:
                    img = np.repeat(img[..., None], 3, axis=2)
                add(0.8 * img, "calibration", c, a)
    true_alpha = {}
    vcams = []
    for c, a in views:
        cam = RigGeometry.view_camera(rig_cams[c], a, name=view_id(c, a))
        vcams.append(cam)
        rays = _rays(cam, ss)
        kw = {"kind": kind, "ss": ss, "rays": rays, "hide_object": view_id(c, a) in hide_object_in}
        for pid, p in pats.items():
            col, al = render_view(cam, a, geo, patterns=p, **kw)
            add(col, "matting", c, a, pattern=pid)
            if object_absent:
                bg = _display_radiance(*rays, a, geo, p).reshape(height, width, ss * ss, 3).mean(2)
                add(bg.astype(np.float32), "matting", c, a, pattern=pid, object_present=False)
        col, al = render_view(cam, a, geo, patterns=None, **kw)
        if off_shots:
            add(col, "matting", c, a, pattern=None)
        add(col, "lightfield", c, a)
        true_alpha[view_id(c, a)] = al
        if reflectance:
            for lid in (0, 1):
                Ld = geo.light_direction_object(lid, a, 0.0)
                colL, _ = render_view(cam, a, geo, patterns=None, light_dir=Ld, **kw)
                add(
                    colL * np.float32(reflectance_level / 255.0),
                    "reflectance",
                    c,
                    a,
                    light=lid,
                    lights_deg=0.0,
                    extra={"level": int(reflectance_level)},
                )
    w.close()
    if cameras == "yaml":
        for cam in rig_cams:
            write_opencv_yaml(root / "calibration" / f"{cam.name}.yaml", cam, extra={"reproj_rms_px": rms_px})
    gt = root / "groundtruth"
    write_colmap_text(gt / "cameras", vcams, [v.name for v in vcams], share_intrinsics=[c for c, _ in views])
    for cam in rig_cams:
        write_opencv_yaml(gt / "calibration" / f"{cam.name}.yaml", cam)
    for vid, al in true_alpha.items():
        write_exr(gt / "alpha" / f"{vid}.exr", al)
    V, F = uv_sphere(CENTRE, CORE_R)
    write_ply(gt / "object.ply", V, F)
    return {
        "geometry": geo,
        "views": views,
        "alpha": true_alpha,
        "view_cameras": vcams,
        "rig_cameras": rig_cams,
        "patterns": pats,
    }


def built_sphere(tmp_path_factory, tag: str, config, *, reflectance: bool, seed: int):
    """A 4-angle sphere session under ``tag`` and its model built with ``config``:
    ``(session_dir, model_dir, build report)``, for module-scoped fixtures."""
    from opacityhull.reconstruct.build import build_model

    root = tmp_path_factory.mktemp(tag) / "session"
    make_session(root, kind="sphere", n_angles=4, reflectance=reflectance, seed=seed)
    out = tmp_path_factory.mktemp(f"{tag}_model") / "model"
    return root, out, build_model(root, out, config=config)


def cli_session(tmp_path_factory, tag: str) -> Path:
    """A small sphere session under ``tag`` (2 cameras x 3 table angles, 40x30 px, with
    one-light shots), for module-scoped fixtures of the build-CLI tests; its folder."""
    root = tmp_path_factory.mktemp(tag) / "session"
    make_session(root, kind="sphere", n_cams=2, n_angles=3, width=40, height=30, reflectance=True, seed=3, ss=2)
    return root


# --------------------------------------------------------------------------- the photo tests' spheres


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors on a golden-angle spiral (near-uniform on the sphere)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = math.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], axis=1)


def sphere_cameras(n: int, *, distance_m: float, sizes=((64, 64),), focal_px: float | None = None) -> list[Camera]:
    """``n`` pinhole cameras ``v0``, ``v1``, ... at ``distance_m`` from the origin along
    :func:`fibonacci_directions`, looking at it; image sizes (w, h) cycling through
    ``sizes`` (so stacks of them are padded), focal length ``focal_px`` (None: 1.1 w),
    principal point at the image centre."""
    out = []
    for k, d in enumerate(fibonacci_directions(n)):
        w, h = sizes[k % len(sizes)]
        f = 1.1 * w if focal_px is None else focal_px
        K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (1.0, 0.0, 0.0)
        wfc = look_at_world_from_cam(distance_m * d, (0, 0, 0), up)
        out.append(Camera(K=K, width=w, height=h, world_from_cam=wfc, name=f"v{k}"))
    return out


def sphere_photo(cam: Camera, *, r_true: float, r_hull: float, textured: bool = True, seed: int = 1):
    """Exact ray cast of ``cam``: the grey albedo of the true sphere (radius ``r_true``
    m; Lambertian, view-independent), black elsewhere, and as alpha the disc of the hull
    sphere (``r_hull``: the silhouettes the hull was carved from). The albedo is a smooth
    random texture (features a few pixels wide, from ``seed``), or 0.4 without
    ``textured``. Returns (H, W, 3) and (H, W) float32."""
    o, d = cam.pixel_rays()
    d = d.reshape(-1, 3)

    def hit(r):
        b = d @ o
        disc = b * b - (o @ o - r * r)
        return disc >= 0, -b - np.sqrt(np.maximum(disc, 0))

    m_true, t = hit(r_true)
    m_hull, _ = hit(r_hull)
    n = (o + t[:, None] * d) / r_true
    if textured:
        rng = np.random.default_rng(seed)
        g = np.full(n.shape[0], 0.45)
        for _ in range(12):
            g += 0.06 * np.sin(n @ (rng.normal(size=3) * 9.0) + rng.uniform(0, 2 * math.pi))
    else:
        g = np.full(n.shape[0], 0.4)
    g = np.where(m_true, g, 0.0)
    img = np.repeat(g.reshape(cam.height, cam.width, 1), 3, axis=2).astype(np.float32)
    return img, m_hull.reshape(cam.height, cam.width).astype(np.float32)


def sphere_hull_surfels(n: int, *, radius: float, cameras):
    """``n`` surfels on the sphere of ``radius`` m about the origin (at
    :func:`fibonacci_directions`, outward normals, radii covering the sphere), each
    visible from the cameras it faces (the sphere is convex): ``(positions, normals,
    radii, (n, V) visibility)``."""
    nrm = fibonacci_directions(n)
    pos = radius * nrm
    C = np.array([c.centre_world for c in cameras])
    vis = np.einsum("nk,vk->nv", nrm, C) - (pos * nrm).sum(1)[:, None] > 0
    return pos, nrm, np.full(n, radius * math.sqrt(4 / n)), vis
