"""Camera model and its conversions: each round-trips, and each agrees with an
independent implementation (OpenCV's projectPoints, pycolmap's reader)."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.camera import (
    COINCIDENT_ANGLE_DEG,
    COINCIDENT_CENTRE_REL,
    Camera,
    camera_from_mitsuba_params,
    coincident_views,
    look_at_world_from_cam,
    mitsuba_sensor_params,
    nerfstudio_transform_matrix,
    object_from_rig,
    read_colmap_text,
    read_opencv_yaml,
    rig_from_object,
    rot_y,
    write_colmap_text,
    write_opencv_yaml,
)
from opacityhull.errors import FormatError, InputError, ShapeError


def make_cam(dist=(0, 0, 0, 0, 0), eye=(0.3, 0.4, 1.0), fx=300.0, fy=300.0, name="c"):
    K = np.array([[fx, 0, 79.3], [0, fy, 61.7], [0, 0, 1]])
    return Camera(
        K=K, width=160, height=120, dist=dist, world_from_cam=look_at_world_from_cam(eye, (0, 0.05, 0)), name=name
    )


def test_project_matches_opencv_with_distortion():
    cam = make_cam(dist=(-0.21, 0.08, 0.001, -0.0015, 0.01))
    rng = np.random.default_rng(0)
    P = rng.uniform(-0.1, 0.1, (200, 3))
    uv, z = cam.project(P)
    T = cam.cam_from_world
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    ref, _ = cv2.projectPoints(P, rvec, T[:3, 3], cam.K, cam.dist)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    assert np.all(z > 0)


def test_unproject_inverts_project_with_distortion():
    cam = make_cam(dist=(-0.2, 0.05, 0.001, 0.002, 0.0))
    P = np.random.default_rng(1).uniform(-0.08, 0.08, (100, 3))
    uv, z = cam.project(P)
    np.testing.assert_allclose(cam.unproject(uv, z), P, atol=1e-9)


def test_points_behind_camera_are_nan():
    cam = make_cam()
    behind = cam.centre_world - 0.5 * cam.forward_world
    uv, z = cam.project(behind[None])
    assert z[0] < 0 and np.all(np.isnan(uv))


def test_pixel_rays_hit_projected_points():
    cam = make_cam(dist=(-0.1, 0.0, 0.0, 0.0, 0.0))
    o, d = cam.pixel_rays()
    assert d.shape == (120, 160, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    # a point 0.8 m along the ray through pixel (37, 91) projects back to that pixel
    p = o + 0.8 * d[91, 37]
    uv, _ = cam.project(p[None])
    np.testing.assert_allclose(uv[0], [37, 91], atol=1e-6)


def test_supersampled_rays_are_stratified_and_pixel_major():
    cam = make_cam(dist=(-0.1, 0.0, 0.0, 0.0, 0.0))
    o, d = cam.supersampled_rays(2)
    assert d.shape == (120 * 160 * 4, 3)
    # samples 4k..4k+3 belong to pixel k (row-major); sample (i, j) is at (u + offs[j], v + offs[i])
    k = 91 * 160 + 37
    uv, _ = cam.project(o + 0.8 * d[4 * k : 4 * k + 4])
    np.testing.assert_allclose(uv, [[36.75, 90.75], [37.25, 90.75], [36.75, 91.25], [37.25, 91.25]], atol=1e-6)
    np.testing.assert_allclose(cam.supersampled_rays(1)[1], cam.pixel_rays()[1].reshape(-1, 3), atol=1e-12)


def test_camera_validation_messages():
    with pytest.raises(ShapeError, match=r"K has shape \(2, 2\)"):
        Camera(K=np.eye(2), width=10, height=10)
    with pytest.raises(InputError, match="skew"):
        Camera(K=np.array([[100, 1.0, 5], [0, 100, 5], [0, 0, 1]]), width=10, height=10)
    bad = np.eye(4)
    bad[0, 0] = 2
    with pytest.raises(InputError, match="not a rigid transform"):
        Camera(K=np.eye(3) * [100, 100, 1], width=10, height=10, world_from_cam=bad)


def test_look_at_handles_view_along_up_axis():
    T = look_at_world_from_cam((0, 2, 0), (0, 0, 0))  # straight down the table axis
    assert np.all(np.isfinite(T))
    np.testing.assert_allclose(T[:3, 2], [0, -1, 0], atol=1e-12)
    with pytest.raises(InputError, match="coincides"):
        look_at_world_from_cam((1, 1, 1), (1, 1, 1))


def test_table_rotation_convention():
    # +90 deg turns +Z towards +X (right-handed about +Y)
    np.testing.assert_allclose(rot_y(math.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rig_from_object(37.0) @ object_from_rig(37.0), np.eye(4), atol=1e-12)


def test_scaled_camera_projects_consistently():
    cam = make_cam()
    half = cam.scaled(0.5)
    P = np.random.default_rng(2).uniform(-0.05, 0.05, (20, 3))
    uv, _ = cam.project(P)
    uv2, _ = half.project(P)
    # continuous coordinates (pixel centre + 0.5) scale exactly
    np.testing.assert_allclose((uv2 + 0.5), (uv + 0.5) * 0.5, atol=1e-9)


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.2, 0.05, 0.001, 0.002, 0.0), (-0.2, 0.05, 0.001, 0.002, 0.01)])
def test_colmap_roundtrip_and_pycolmap_agrees(tmp_path, dist):
    import pycolmap

    cams = [
        make_cam(dist=dist, eye=(0.5 * math.sin(a), 0.3, 0.5 * math.cos(a)), name=f"v{i}")
        for i, a in enumerate([0, 1, 2])
    ]
    write_colmap_text(tmp_path, cams, share_intrinsics=[0, 0, 0], points3d=np.zeros((1, 3)))
    back = dict(read_colmap_text(tmp_path))
    for c in cams:
        b = back[c.name]
        np.testing.assert_allclose(b.K, c.K, atol=1e-9)
        np.testing.assert_allclose(b.dist, c.dist, atol=1e-12)
        np.testing.assert_allclose(b.world_from_cam, c.world_from_cam, atol=1e-9)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert len(rec.cameras) == 1 and len(rec.images) == 3
    for img in rec.images.values():
        c = next(x for x in cams if x.name == img.name)
        cfw = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        np.testing.assert_allclose(cfw.matrix(), c.cam_from_world[:3], atol=1e-9)
        # pycolmap projects with COLMAP's +0.5 pixel convention
        pcam = rec.cameras[img.camera_id]
        P = np.array([[0.01, 0.02, 0.03]])
        uv, _ = c.project(P)
        cam_pt = c.world_to_cam(P)[0]
        img_pt = pcam.img_from_cam(cam_pt[None] / cam_pt[2]) if False else pcam.img_from_cam(cam_pt[None])
        np.testing.assert_allclose(np.asarray(img_pt).reshape(-1)[:2], uv[0] + 0.5, atol=1e-6)


def test_colmap_reader_errors_name_file_and_line(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 FISHEYE 10 10 1 2 3\n")
    (tmp_path / "images.txt").write_text("")
    with pytest.raises(FormatError, match=r"cameras.txt:1: camera model FISHEYE"):
        read_colmap_text(tmp_path)
    with pytest.raises(FormatError, match="not found"):
        read_colmap_text(tmp_path / "nope")


def test_opencv_yaml_roundtrip(tmp_path):
    cam = make_cam(dist=(-0.1, 0.01, 0.0, 0.001, 0.0), name="cam3")
    write_opencv_yaml(tmp_path / "cam3.yaml", cam, extra={"reproj_rms_px": 0.25})
    back = read_opencv_yaml(tmp_path / "cam3.yaml")
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.dist, cam.dist)
    np.testing.assert_allclose(back.world_from_cam, cam.world_from_cam)
    assert back.name == "cam3" and back.size == cam.size
    fs = cv2.FileStorage(str(tmp_path / "cam3.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("reproj_rms_px").real() == pytest.approx(0.25)
    fs.release()


def test_mitsuba_params_roundtrip_and_refuse_distortion():
    cam = make_cam()
    back = camera_from_mitsuba_params(mitsuba_sensor_params(cam))
    np.testing.assert_allclose(back.K, cam.K, atol=1e-9)
    np.testing.assert_allclose(back.world_from_cam, cam.world_from_cam, atol=1e-12)
    with pytest.raises(InputError, match="distortion"):
        mitsuba_sensor_params(make_cam(dist=(0.1, 0, 0, 0, 0)))
    with pytest.raises(InputError, match="square pixels"):
        mitsuba_sensor_params(make_cam(fy=310.0))


def test_nerfstudio_matrix_is_opengl_convention():
    cam = make_cam()
    M = np.array(nerfstudio_transform_matrix(cam))
    # OpenGL camera looks down its -z; that must be the OpenCV +z (forward)
    np.testing.assert_allclose(-M[:3, 2], cam.forward_world, atol=1e-12)
    np.testing.assert_allclose(M[:3, 1], -cam.world_from_cam[:3, 1], atol=1e-12)
    np.testing.assert_allclose(M[:3, 3], cam.centre_world)


@settings(max_examples=40, deadline=None)
@given(
    st.floats(-0.3, 0.3),
    st.floats(-0.1, 0.1),
    st.floats(-0.005, 0.005),
    st.floats(-0.005, 0.005),
    st.floats(-0.9, 0.9),
    st.floats(-0.9, 0.9),
)
def test_undistort_inverts_distort(k1, k2, p1, p2, x, y):
    cam = make_cam(dist=(k1, k2, p1, p2, 0.0))
    xy = np.array([[x * 0.5, y * 0.5]])
    back = cam.undistort_normalized(cam.distort_normalized(xy), iterations=50)
    np.testing.assert_allclose(back, xy, atol=1e-6)


def test_look_at_image_up_is_world_up_and_right_handed():
    T = look_at_world_from_cam((0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    cam = Camera(K=np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]), width=101, height=101, world_from_cam=T)
    (u_up, v_up), (u_right, v_right) = cam.project(np.array([[0, 0.1, 0], [0.1, 0, 0]]))[0]
    assert v_up < 50 and abs(u_up - 50) < 1e-9  # world +Y appears above the centre
    assert u_right > 50  # seen from +Z, world +X is on the right
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def _ring(n, *, radius=0.6, height=0.2):
    cams = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = (radius * math.sin(a), height, radius * math.cos(a))
        cams.append(
            Camera(
                K=np.diag([500.0, 500.0, 1.0]) + np.array([[0, 0, 320], [0, 0, 240], [0, 0, 0]]),
                width=640,
                height=480,
                world_from_cam=look_at_world_from_cam(eye, (0, 0.05, 0)),
                name=f"c{k}",
            )
        )
    return cams


def _rotated(cam, angle_deg, axis=(0.0, 1.0, 0.0)):
    R, _ = cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * math.radians(angle_deg))
    T = cam.world_from_cam.copy()
    T[:3, :3] = T[:3, :3] @ R
    return cam.with_pose(T)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(2, 24), dup=st.lists(st.integers(0, 23), min_size=0, max_size=4, unique=True))
def test_coincident_views_finds_exactly_the_repeated_viewpoints(n, dup):
    """A ring of distinct viewpoints has no twins; appending copies of some of them (the
    temple ring photographs its first viewpoint twice) groups each with its original."""
    ring = _ring(n)
    assert coincident_views(ring) == []
    dup = [d for d in dup if d < n]
    cams = ring + [ring[d] for d in dup]
    assert coincident_views(cams) == sorted((d, n + k) for k, d in enumerate(dup))


def test_coincident_views_tolerances_and_chains():
    ring = _ring(12)
    spread = float(
        np.median([np.linalg.norm(c.centre_world - np.mean([q.centre_world for q in ring], 0)) for c in ring])
    )
    T = ring[3].world_from_cam.copy()
    T[:3, 3] += [0.4 * COINCIDENT_CENTRE_REL * spread, 0, 0]
    near = ring[3].with_pose(T)
    T2 = ring[3].world_from_cam.copy()
    T2[:3, 3] += [2.0 * COINCIDENT_CENTRE_REL * spread, 0, 0]
    far = ring[3].with_pose(T2)
    assert coincident_views(ring + [near]) == [(3, 12)]
    assert coincident_views(ring + [far]) == []
    # the same centre, turned: within the angle tolerance a twin, beyond it another view
    assert coincident_views(ring + [_rotated(ring[5], 0.5 * COINCIDENT_ANGLE_DEG)]) == [(5, 12)]
    assert coincident_views(ring + [_rotated(ring[5], 3.0 * COINCIDENT_ANGLE_DEG, (1, 0, 0))]) == []
    # a chain of near-duplicates is one group
    T3 = near.world_from_cam.copy()
    T3[:3, 3] += [0.4 * COINCIDENT_CENTRE_REL * spread, 0, 0]
    assert coincident_views(ring + [near, near.with_pose(T3)]) == [(3, 12, 13)]
    # every view at one centre (a pure rotation set): only equal orientations group
    hub = [_rotated(ring[0], a) for a in (0.0, 10.0, 20.0, 0.1)]
    assert coincident_views(hub) == [(0, 3)]
    assert coincident_views(ring[:1]) == [] and coincident_views([]) == []
    with pytest.raises(InputError, match="centre_tol_rel"):
        coincident_views(ring, centre_tol_rel=0.0)
    with pytest.raises(InputError, match="angle_tol_deg"):
        coincident_views(ring, angle_tol_deg=float("nan"))


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.2, 0.05, 0.001, 0.002, 0.01)])
def test_colmap_text_and_binary_go_through_pycolmap(tmp_path, dist):
    """pycolmap reads and writes COLMAP models (#33): ``write_colmap_text`` writes what
    ``pycolmap.Reconstruction.write_text`` writes, and text (COLMAP 3 or 4 layout, with
    or without points3D.txt) and binary read back to the same cameras."""
    from opacityhull.camera import colmap_reconstruction, read_colmap_model

    cams = [
        make_cam(dist=dist, eye=(0.5 * math.sin(a), 0.3 + 0.1 * a, 0.5 * math.cos(a)), name=f"v{i}.png")
        for i, a in enumerate([0.0, 1.3, 2.1, 4.0])
    ]
    kw = dict(share_intrinsics=[0, 0, 1, 1], points3d=np.array([[0.0, 0.01, 0.02], [0.1, 0.2, 0.3]]))
    rec = colmap_reconstruction(cams, **kw)
    write_colmap_text(tmp_path / "ours", cams, **kw)
    for d in ("lib", "bin"):
        (tmp_path / d).mkdir()
    rec.write_text(str(tmp_path / "lib"))  # COLMAP 4: also rigs.txt and frames.txt
    for n in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (tmp_path / "ours" / n).read_text() == (tmp_path / "lib" / n).read_text(), n
    (tmp_path / "ours" / "points3D.txt").unlink()  # a camera-only model (a session's cameras/)
    rec.write_binary(str(tmp_path / "bin"))
    for d in ("ours", "lib", "bin"):
        back = dict(read_colmap_model(tmp_path / d))
        assert list(back) == [c.name for c in cams]
        for c in cams:
            np.testing.assert_allclose(back[c.name].K, c.K, atol=1e-9)
            np.testing.assert_allclose(back[c.name].dist, c.dist, atol=1e-12)
            np.testing.assert_allclose(back[c.name].world_from_cam, c.world_from_cam, atol=1e-9)
