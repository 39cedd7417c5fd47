"""Camera exports checked against the readers of the target tools (pycolmap, OpenCV
FileStorage) and an independent implementation of the OpenGL camera convention."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pycolmap
import pytest
from helpers import ring_cameras

from opacityhull.camera import Camera, read_opencv_yaml, rig_from_object
from opacityhull.charuco import CharucoSpec
from opacityhull.errors import InputError
from opacityhull.reconstruct.calibration import CharucoObservation, calibrate_observations, view_cameras
from opacityhull.reconstruct.exports import (
    export_colmap,
    export_nerfstudio,
    export_opencv_yaml,
    intrinsics_groups,
    plot_reprojection_errors,
)
from opacityhull.riggeometry import RigGeometry, view_id

W, H = 320, 240


@pytest.fixture(scope="module")
def calibrated():
    """A small exact calibration: three cameras, eight table angles, one distorted camera."""
    g = {
        "target_m": [0.0, 0.02, 0.0],
        "cameras": ring_cameras(W, H, [(35.0, 0.0), (50.0, 120.0), (65.0, -120.0)], distance_m=0.5, focal_px=300.0),
    }
    nominal = RigGeometry.from_dict(g).nominal_cameras()
    true = [
        Camera(
            K=c.K,
            dist=[-0.05, 0.0, 0.0, 0.0, 0.0] if i == 1 else np.zeros(5),
            width=W,
            height=H,
            world_from_cam=c.world_from_cam,
            name=c.name,
        )
        for i, c in enumerate(nominal)
    ]
    spec = CharucoSpec()
    obj = spec.board().getChessboardCorners().astype(np.float64)
    rng = np.random.default_rng(4)
    obs = []
    for c, cam in enumerate(true):
        for a in np.arange(0.0, 360.0, 45.0):
            T = rig_from_object(a) @ spec.object_from_board()
            uv, _ = cam.project(obj @ T[:3, :3].T + T[:3, 3])
            obs.append(CharucoObservation(c, a, np.arange(len(obj)), uv + rng.normal(0, 0.1, uv.shape), obj))
    # one collinear view, so the dropped-view marker appears in the plot
    o = obs[2]
    row = o.object_points[:, 1] == o.object_points[0, 1]
    obs[2] = CharucoObservation(0, o.table_deg, o.ids[row], o.image_points[row], o.object_points[row])
    return calibrate_observations(obs, image_sizes=[(W, H)] * 3, charuco=spec, nominal=nominal)


def _views(res, angles=(0.0, 90.0, 200.0)):
    views = [(c, a) for c in range(len(res.rig_cameras)) for a in angles]
    return views, view_cameras(res, views)


def test_opencv_yaml_round_trip_with_extras(calibrated, tmp_path):
    paths = export_opencv_yaml(calibrated, tmp_path / "calibration")
    assert [p.name for p in paths] == ["cam0.yaml", "cam1.yaml", "cam2.yaml"]
    for c, p in enumerate(paths):
        cam = read_opencv_yaml(p)
        ref = calibrated.rig_cameras[c]
        np.testing.assert_allclose(cam.K, ref.K, rtol=1e-12)
        np.testing.assert_allclose(cam.dist, ref.dist, atol=1e-15)
        np.testing.assert_allclose(cam.world_from_cam, ref.world_from_cam, atol=1e-12)
        assert (cam.width, cam.height, cam.name) == (W, H, ref.name)
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        assert fs.getNode("reproj_rms_px").real() == pytest.approx(calibrated.reproj_rms_px[c], rel=1e-12)
        assert int(fs.getNode("used_views").real()) == sum(v.startswith(f"c{c}_t") for v in calibrated.used_views)
        np.testing.assert_allclose(fs.getNode("object_from_board").mat(), calibrated.object_from_board, atol=1e-12)
        fs.release()
    assert not list((tmp_path / "calibration").glob(".tmp*"))  # atomic writes leave no debris


def test_colmap_export_reads_back_in_pycolmap(calibrated, tmp_path):
    views, cams = _views(calibrated)
    names = [f"{view_id(c, a)}.png" for c, a in views]
    out = export_colmap(cams, names, tmp_path / "sparse", share_intrinsics=True)
    rec = pycolmap.Reconstruction(str(out))
    assert rec.num_images() == len(cams)
    assert rec.num_cameras() == 3  # one COLMAP camera per physical camera
    by_name = {im.name: im for im in rec.images.values()}
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.05, 0.05, (20, 3)) + [0.0, 0.05, 0.0]
    for name, cam in zip(names, cams, strict=True):
        im = by_name[name]
        M = im.cam_from_world().matrix()
        np.testing.assert_allclose(M, cam.cam_from_world[:3, :], atol=1e-12)
        pc = rec.cameras[im.camera_id]
        assert (pc.width, pc.height) == (W, H)
        np.testing.assert_allclose(pc.calibration_matrix(), cam.K + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]], atol=1e-12)
        # pycolmap's own projection (its distortion code) = ours + 0.5 px (pixel-centre convention).
        Xc = X @ M[:, :3].T + M[:, 3]
        uv_colmap = np.asarray(pc.img_from_cam(Xc))
        uv, _ = cam.project(X)
        np.testing.assert_allclose(uv_colmap, uv + 0.5, atol=1e-6)
    assert calibrated.rig_cameras[1].has_distortion
    assert rec.cameras[by_name[names[3]].camera_id].model.name in ("OPENCV", "FULL_OPENCV")


def test_colmap_export_groupings(calibrated, tmp_path):
    views, cams = _views(calibrated, angles=(0.0, 45.0))
    names = [view_id(c, a) for c, a in views]
    assert intrinsics_groups(cams) == [0, 0, 1, 1, 2, 2]
    rec = pycolmap.Reconstruction(str(export_colmap(cams, names, tmp_path / "a", share_intrinsics=False)))
    assert rec.num_cameras() == 6
    rec = pycolmap.Reconstruction(str(export_colmap(cams, names, tmp_path / "b", share_intrinsics=[5, 5, 7, 7, 9, 9])))
    assert rec.num_cameras() == 3
    with pytest.raises(InputError, match="intrinsics differ"):
        export_colmap(cams, names, tmp_path / "c", share_intrinsics=[0, 0, 0, 1, 1, 1])
    with pytest.raises(InputError, match="duplicate image names"):
        export_colmap(cams, ["x"] * 6, tmp_path / "d")
    with pytest.raises(InputError, match="5 names for 6 cameras"):
        export_colmap(cams, names[:5], tmp_path / "e")


def _opengl_project(frame: dict, X: np.ndarray) -> np.ndarray:
    """Independent nerfstudio/OpenGL projection: camera looks down -z, y up; pixel
    coordinates with the top-left pixel's centre at (0.5, 0.5); OpenCV radial-tangential
    distortion applied in the image-down convention."""
    c2w = np.asarray(frame["transform_matrix"])
    w2c = np.linalg.inv(c2w)
    P = X @ w2c[:3, :3].T + w2c[:3, 3]
    x = P[:, 0] / -P[:, 2]
    y = -P[:, 1] / -P[:, 2]  # image rows grow downwards
    k1, k2, k3, p1, p2 = (frame[k] for k in ("k1", "k2", "k3", "p1", "p2"))
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([frame["fl_x"] * xd + frame["cx"], frame["fl_y"] * yd + frame["cy"]], axis=1)


def test_nerfstudio_export_matches_the_opengl_convention(calibrated, tmp_path):
    views, cams = _views(calibrated)
    img_dir = tmp_path / "data" / "images"
    images = [img_dir / f"{view_id(c, a)}.png" for c, a in views]
    masks = [f"masks/{view_id(c, a)}.png" for c, a in views]
    out = export_nerfstudio(cams, images, tmp_path / "data", mask_paths=masks)
    assert out == tmp_path / "data" / "transforms.json"
    meta = json.loads(out.read_text())
    assert meta["camera_model"] == "OPENCV" and "fl_x" not in meta  # per-frame intrinsics only
    X = np.random.default_rng(1).uniform(-0.05, 0.05, (30, 3)) + [0.0, 0.05, 0.0]
    for fr, cam, (c, a) in zip(meta["frames"], cams, views, strict=True):
        assert fr["file_path"] == f"images/{view_id(c, a)}.png"
        assert fr["mask_path"] == f"masks/{view_id(c, a)}.png"
        assert (fr["w"], fr["h"]) == (W, H)
        uv, _ = cam.project(X)
        np.testing.assert_allclose(_opengl_project(fr, X), uv + 0.5, atol=1e-9)
        # The OpenGL camera looks down its -z: the camera centre and forward axis in the world.
        M = np.asarray(fr["transform_matrix"])
        np.testing.assert_allclose(M[:3, 3], cam.centre_world, atol=1e-12)
        np.testing.assert_allclose(-M[:3, 2], cam.forward_world, atol=1e-12)
        assert np.linalg.det(M[:3, :3]) == pytest.approx(1.0)


def test_nerfstudio_export_without_masks_and_bad_inputs(calibrated, tmp_path):
    views, cams = _views(calibrated, angles=(0.0,))
    out = export_nerfstudio(cams, ["a.png", "b.png", "c.png"], tmp_path / "t.json")
    meta = json.loads(out.read_text())
    assert all("mask_path" not in f for f in meta["frames"])
    assert [f["file_path"] for f in meta["frames"]] == ["a.png", "b.png", "c.png"]
    with pytest.raises(InputError, match="one mask for every image"):
        export_nerfstudio(cams, ["a.png", "b.png", "c.png"], tmp_path / "u.json", mask_paths=["m.png", None, "n.png"])
    with pytest.raises(InputError, match="2 image paths for 3 cameras"):
        export_nerfstudio(cams, ["a.png", "b.png"], tmp_path / "v.json")


def test_reprojection_plot(calibrated, tmp_path):
    assert calibrated.dropped_views  # the collinear view
    p = plot_reprojection_errors(calibrated, tmp_path / "reproj.png")
    from opacityhull.imageio import read_png

    img = read_png(p)
    assert img.shape[0] > 300 and img.shape[1] > 800
    assert float(np.std(img)) > 0.01  # not a blank canvas


def test_views_of_a_rig_round_trip_through_colmap_text_reader(calibrated, tmp_path):
    """The core reader gives back the cameras the export wrote (incl. distortion)."""
    from opacityhull.camera import read_colmap_text

    views, cams = _views(calibrated)
    names = [view_id(c, a) for c, a in views]
    export_colmap(cams, names, tmp_path / "m", share_intrinsics=True)
    back = dict(read_colmap_text(tmp_path / "m"))
    for n, cam in zip(names, cams, strict=True):
        np.testing.assert_allclose(back[n].world_from_cam, cam.world_from_cam, atol=1e-12)
        np.testing.assert_allclose(back[n].K, cam.K, atol=1e-12)
        np.testing.assert_allclose(back[n].dist, cam.dist, atol=1e-15)
    assert math.isfinite(calibrated.rms_px)
