"""Exports read back by the libraries their users use: json + nerfstudio's layout rules,
pycolmap, plyfile, cv2.FileStorage; values checked against the analytic scene."""

from __future__ import annotations

import json
import subprocess
import sys
from itertools import pairwise

import cv2
import numpy as np
import pytest

from opacityhull.errors import InputError
from opacityhull.export.formats import export_model
from opacityhull.sh import SH_C0, eval_sh, sh_basis
from opacityhull.imageio import srgb_encode
from opacityhull.render.synthetic import fibonacci_sphere


def _expected_srgb(m, points):
    """sRGB colour of the diffuse analytic sphere (view-independent) at ``points``."""
    return srgb_encode(np.clip(m.scene.radiance(points, points + m.surfels.normals), 0, 1))


# --------------------------------------------------------------------------- nerfstudio


@pytest.mark.parametrize("alpha", ["rgba", "mask"])
def test_nerfstudio_layout_and_conventions(diffuse_model, tmp_path, alpha):
    root, m = diffuse_model
    out = tmp_path / "ns"
    s = export_model(root, "nerfstudio", out, alpha=alpha)
    meta = json.loads((out / "transforms.json").read_text())
    # nerfstudio's data parser: camera_model at the top (or per frame), frames with file_path
    # relative to the JSON, transform_matrix 4x4 camera-to-world, OpenGL axes; w/h integers
    assert meta["camera_model"] == "OPENCV"
    assert meta["ply_file_path"] == "sparse_pc.ply" and (out / "sparse_pc.ply").is_file()
    assert len(meta["frames"]) == len(m.views) == s["images"]
    for fr, v in zip(meta["frames"], m.views, strict=True):
        cam = v.camera
        img = cv2.imread(str(out / fr["file_path"]), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint8
        assert img.shape == (cam.height, cam.width, 4 if alpha == "rgba" else 3)
        assert isinstance(fr["w"], int) and fr["w"] == cam.width and fr["h"] == cam.height
        T = np.array(fr["transform_matrix"])
        assert T.shape == (4, 4)
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(T[:3, 3], cam.centre_world, atol=1e-12)
        # OpenGL: the camera looks down its -Z axis, +Y is image up
        np.testing.assert_allclose(-T[:3, 2], cam.forward_world, atol=1e-12)
        # project surfels the way nerfstudio does (pixel centres at +0.5) and compare
        P = m.surfels.positions[::97].astype(np.float64)
        pc = (np.linalg.inv(T) @ np.c_[P, np.ones(len(P))].T).T[:, :3]
        x = fr["fl_x"] * pc[:, 0] / -pc[:, 2] + fr["cx"]
        y = fr["fl_y"] * -pc[:, 1] / -pc[:, 2] + fr["cy"]
        uv, _ = cam.project(P)
        np.testing.assert_allclose(np.c_[x, y], uv + 0.5, atol=1e-9)
        if alpha == "rgba":
            np.testing.assert_allclose(img[..., 3] / 255.0, m.view_rgba[v.index][..., 3], atol=0.5 / 255 + 1e-6)
        else:
            mask = cv2.imread(str(out / fr["mask_path"]), cv2.IMREAD_UNCHANGED)
            assert mask.ndim == 2 and mask.dtype == np.uint8
            np.testing.assert_array_equal(mask > 127, m.view_rgba[v.index][..., 3] >= 0.5)


# --------------------------------------------------------------------------- colmap


def test_colmap_text_and_binary_read_by_pycolmap(diffuse_model, tmp_path):
    import pycolmap

    root, m = diffuse_model
    out = tmp_path / "colmap"
    s = export_model(root, "colmap", out, max_points=400)
    sparse = out / "sparse" / "0"
    for suffix, reader in (("txt", "read_text"), ("bin", "read_binary")):
        assert (sparse / f"points3D.{suffix}").is_file()
        rec = pycolmap.Reconstruction()
        getattr(rec, reader)(str(sparse))
        assert rec.num_reg_images() == len(m.views)
        assert rec.num_cameras() == 3  # one per physical camera
        assert rec.num_points3D() == s["points3D"] > 300
        for img in rec.images.values():
            assert (out / "images" / img.name).is_file()
        n_checked = 0
        for pid, pt in rec.points3D.items():
            assert pt.track.length() >= 2
            for el in pt.track.elements:
                img = rec.image(el.image_id)
                cam = rec.camera(img.camera_id)
                xy = cam.img_from_cam(img.cam_from_world() * pt.xyz)
                np.testing.assert_allclose(img.points2D[el.point2D_idx].xy, xy, atol=1e-4)
                assert img.points2D[el.point2D_idx].point3D_id == pid
                n_checked += 1
        assert n_checked == s["observations"]


def test_colmap_point_colours_match_scene(diffuse_model, tmp_path):
    import pycolmap

    root, m = diffuse_model
    export_model(root, "colmap", tmp_path / "c", max_points=300)
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse" / "0"))
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    col = np.array([p.color for p in rec.points3D.values()]) / 255.0
    n = (xyz - np.asarray(m.scene.centre)) / m.scene.radius
    exp = srgb_encode(np.clip(m.scene.radiance(xyz, xyz + n), 0, 1))
    assert np.median(np.abs(col - exp)) < 0.02


# --------------------------------------------------------------------------- ply


def test_points_ply_colour_alpha_normals(diffuse_model, tmp_path):
    from plyfile import PlyData

    root, m = diffuse_model
    export_model(root, "ply", tmp_path / "p", sh_degree=1)
    v = PlyData.read(str(tmp_path / "p" / "points.ply"))["vertex"].data
    assert {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"} <= set(v.dtype.names)
    assert v["red"].dtype == np.uint8 and v["alpha"].dtype == np.uint8
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    np.testing.assert_allclose(xyz, m.surfels.positions)
    exp = _expected_srgb(m, xyz.astype(np.float64))
    got = np.stack([v["red"], v["green"], v["blue"]], 1) / 255.0
    # surfels some view sees within 60° of the normal (the rest only appear on silhouettes)
    vis = m.surfels.visible_bool()
    cos = np.stack(
        [
            ((v_.camera.centre_world - xyz) * m.surfels.normals).sum(1)
            / np.linalg.norm(v_.camera.centre_world - xyz, axis=1)
            for v_ in m.views
        ],
        1,
    )
    well = np.max(np.where(vis, cos, -1), axis=1) > 0.5
    assert well.mean() > 0.8
    assert np.percentile(np.abs(got - exp)[well], 95) < 0.03
    assert np.percentile(v["alpha"][well], 2) >= 240 and np.median(v["alpha"][well]) >= 253  # opaque sphere


def test_splats_ply_3dgs_layout(glossy_model, tmp_path):
    from plyfile import PlyData
    from scipy.spatial.transform import Rotation

    root, m = glossy_model
    s = export_model(root, "ply", tmp_path / "p", sh_degree=3)
    v = PlyData.read(str(tmp_path / "p" / "splats.ply"))["vertex"].data
    names = v.dtype.names
    # the property list 3DGS's load_ply reads, degree 3: 45 rest coefficients
    expect = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert list(names) == expect
    assert all(v[n].dtype == np.float32 for n in names)
    q = np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)  # w, x, y, z
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-5)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(R[:, :, 2], m.surfels.normals, atol=1e-4)  # local z → normal
    sc = np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], 1))
    np.testing.assert_allclose(sc[:, 0], 0.5 * m.surfels.radii, rtol=1e-5)
    assert np.all(sc[:, 2] < 0.05 * sc[:, 0])
    op = 1 / (1 + np.exp(-v["opacity"].astype(np.float64)))
    seen = m.surfels.visibility.any(axis=1)
    assert np.median(op[seen]) > 0.98 and np.all(op[~seen] < 1e-3)  # unseen surfels are made transparent
    # the fit error is reported per degree and does not grow with the degree
    rms = [s["sh_rms"][str(d)] for d in range(4)]
    assert all(b <= a + 1e-9 for a, b in pairwise(rms)) and rms[3] < 0.03
    # reassemble 3DGS's (N, 16, 3) and evaluate it from the captured views (colour = Σ c Y + 0.5)
    dc = np.stack([v[f"f_dc_{c}"] for c in range(3)], 1)[:, None, :]
    rest = np.stack([v[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15).transpose(0, 2, 1)
    coeffs = np.concatenate([dc, rest], 1).astype(np.float64)
    errs = []
    for vi in (0, 7, 13):
        cam = m.views[vi].camera
        seen = m.surfels.visible_in(vi)
        P = m.surfels.positions[seen].astype(np.float64)
        d = P - cam.centre_world
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pred = eval_sh(coeffs[seen], d)
        exp = srgb_encode(np.clip(m.scene.radiance(P, np.broadcast_to(cam.centre_world, P.shape)), 0, 1))
        errs.append(np.sqrt(np.mean((pred - exp) ** 2)))
    assert max(errs) < 0.05


def test_sh_basis_orthonormal():
    """Independent check of the constants: ∫ Y_i Y_j dΩ = δ_ij (Fibonacci quadrature)."""
    d = fibonacci_sphere(20000)
    Y = sh_basis(d, 3)
    G = Y.T @ Y * (4 * np.pi / len(d))
    np.testing.assert_allclose(G, np.eye(16), atol=2e-3)
    assert SH_C0 == pytest.approx(0.5 / np.sqrt(np.pi))


# --------------------------------------------------------------------------- opencv


def test_opencv_yaml_read_by_filestorage(diffuse_model, tmp_path):
    from opacityhull.riggeometry import RigGeometry

    root, m = diffuse_model
    export_model(root, "opencv", tmp_path / "cv")
    nominal = RigGeometry.from_dict(m.rig).nominal_cameras()
    for cam in nominal:
        fs = cv2.FileStorage(str(tmp_path / "cv" / f"{cam.name}.yaml"), cv2.FILE_STORAGE_READ)
        assert fs.isOpened()
        np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), cam.K)
        np.testing.assert_allclose(fs.getNode("world_from_cam").mat(), cam.world_from_cam, atol=1e-12)
        assert int(fs.getNode("image_width").real()) == cam.width
        assert fs.getNode("distortion_coefficients").mat().size == 5
        fs.release()
    for v in m.views[:5]:
        fs = cv2.FileStorage(str(tmp_path / "cv" / "views" / f"{v.id}.yaml"), cv2.FILE_STORAGE_READ)
        np.testing.assert_allclose(fs.getNode("world_from_cam").mat(), v.camera.world_from_cam, atol=1e-12)
        assert fs.getNode("table_deg").real() == pytest.approx(v.table_deg)
        fs.release()


# --------------------------------------------------------------------------- bad input


def test_bad_input(diffuse_model, tmp_path):
    root, _ = diffuse_model
    with pytest.raises(InputError, match="--format 'obj'"):
        export_model(root, "obj", tmp_path / "x")
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "precious.txt").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        export_model(root, "ply", keep)
    assert (keep / "precious.txt").read_text() == "x"
    with pytest.raises(InputError, match="--sh-degree"):
        export_model(root, "ply", tmp_path / "y", sh_degree=4)
    assert not (tmp_path / "y").exists() and not list(tmp_path.glob(".y.tmp*"))


def test_cli_exit_codes(diffuse_model, tmp_path):
    root, _ = diffuse_model
    exe = [sys.executable, "-m", "opacityhull.cli", "export"]
    r = subprocess.run(
        exe + [str(tmp_path / "nomodel"), "--format", "ply", "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
    )
    # a path that is not there is bad input (#35); a folder without model.toml is not a model
    assert r.returncode == 2 and "no such model folder" in r.stderr and "Traceback" not in r.stderr
    (tmp_path / "empty").mkdir()
    r = subprocess.run(
        exe + [str(tmp_path / "empty"), "--format", "ply", "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 4 and "model.toml" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(
        exe + [str(root), "--format", "obj", "--out", str(tmp_path / "o")], capture_output=True, text=True
    )
    assert r.returncode == 2 and "--format" in r.stderr
    r = subprocess.run(
        exe + [str(root), "--format", "opencv", "--out", str(tmp_path / "o"), "--json"], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["format"] == "opencv" and summary["cameras"] == 3
