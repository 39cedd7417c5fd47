"""`import colmap`: a synthetic calibrated image set becomes a session."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from opacityhull.acquire.importers import closest_point_to_axes, import_colmap
from opacityhull.acquire.verify import verify_session
from opacityhull.camera import Camera, look_at_world_from_cam, write_colmap_text
from opacityhull.errors import InputError
from opacityhull.imageio import srgb_decode
from opacityhull.session import Session

TARGET = np.array([0.1, 0.2, -0.05])


def _synthetic_set(tmp_path, n=5, *, rgba_every=2, masks=False, size=(40, 30)):
    w, h = size
    rng = np.random.default_rng(0)
    cams, names = [], []
    img_dir = tmp_path / "images"
    img_dir.mkdir()
    mask_dir = tmp_path / "masks"
    if masks:
        mask_dir.mkdir()
    pixels = {}
    for i in range(n):
        az = 2 * np.pi * i / n
        eye = TARGET + np.array([1.5 * np.sin(az), 0.3 + 0.1 * i, 1.5 * np.cos(az)])
        K = np.array([[50.0 + i, 0, (w - 1) / 2 + 0.5 * i], [0, 50.0 + i, (h - 1) / 2], [0, 0, 1]])
        cam = Camera(
            K=K,
            width=w,
            height=h,
            world_from_cam=look_at_world_from_cam(eye, TARGET),
            dist=[0.01 * i, 0, 0, 0, 0] if i == 1 else np.zeros(5),
        )
        name = f"sub/img_{i:02d}.png" if i == 3 else f"img_{i:02d}.png"
        cams.append(cam)
        names.append(name)
        q = rng.integers(0, 256, size=(h, w, 4 if i % rgba_every == 0 else 3), dtype=np.uint8)
        (img_dir / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(img_dir / name), q[:, :, [2, 1, 0, 3]] if q.shape[2] == 4 else q[:, :, ::-1])
        pixels[i] = q
        if masks:
            m = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
            (mask_dir / name).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(mask_dir / (name + ".png")), m)
            pixels[("mask", i)] = m
    write_colmap_text(tmp_path / "model", cams, names=names)
    return cams, names, pixels, img_dir, (mask_dir if masks else None)


def test_import_colmap_session(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    cams, names, pixels, img_dir, _ = _synthetic_set(tmp_path, rgba_every=1)
    out = tmp_path / "session"
    rep = import_colmap(tmp_path / "model", img_dir, out)
    assert rep["images"] == 5 and rep["masks"] == 5  # every image carries alpha
    np.testing.assert_allclose(rep["target_m"], TARGET, atol=1e-9)
    v = verify_session(out)
    assert v["ok"] and v["per_phase"] == {"lightfield": 5, "mask": 5} and v["complete"] is None
    s = Session.open(out)
    # per-view cameras = the input poses, named by view id
    vc = s.view_cameras()
    assert sorted(vc) == [f"c{i}_t000.000" for i in range(5)]
    for i, cam in enumerate(cams):
        got = vc[f"c{i}_t000.000"]
        np.testing.assert_allclose(got.world_from_cam, cam.world_from_cam, atol=1e-9)
        np.testing.assert_allclose(got.K, cam.K, atol=1e-9)
        np.testing.assert_allclose(got.dist, cam.dist, atol=1e-12)
    # pycolmap reads the same model independently
    rec = pycolmap.Reconstruction(str(out / "cameras"))
    assert rec.num_images() == 5
    for img in rec.images.values():
        i = int(img.name.split("_")[0][1:])
        T = np.eye(4)
        T[:3, :] = img.cam_from_world().matrix()
        np.testing.assert_allclose(T, cams[i].cam_from_world, atol=1e-9)
    # geometry: nominal cameras sit where the real ones are, looking at the target
    g = s.geometry
    np.testing.assert_allclose(g.target_m, TARGET, atol=1e-9)
    for i, nc in enumerate(g.nominal_cameras()):
        np.testing.assert_allclose(nc.centre_world, cams[i].centre_world, atol=1e-9)
        np.testing.assert_allclose(nc.K, cams[i].K, atol=1e-9)
    assert g.lights == () and g.displays == ()
    # pixels: sRGB decoded to linear; alpha from the RGBA images
    for i in range(5):
        img = s.load_image(s.select(phase="lightfield", camera=i)[0])
        np.testing.assert_allclose(img, srgb_decode(pixels[i][..., :3] / 255.0), atol=1e-6)
    m = s.load_image(s.select(phase="mask", camera=2)[0])
    assert m.shape == (30, 40, 1)
    np.testing.assert_allclose(m[..., 0], pixels[2][..., 3] / 255.0, atol=1e-6)


def test_import_refuses_views_without_a_matte(tmp_path):
    """#33: images 1 and 3 have no alpha and there is no --masks: `build` could not use
    the session (exit 4 on the first view), so the import refuses it, saying how to fix it."""
    _, _, _, img_dir, _ = _synthetic_set(tmp_path, rgba_every=2)
    with pytest.raises(InputError, match=r"img_01.png: COLMAP image 'img_01.png' has no matte.*--masks DIR"):
        import_colmap(tmp_path / "model", img_dir, tmp_path / "session")
    assert not (tmp_path / "session").exists()


def test_import_with_mask_folder_and_errors(tmp_path):
    cams, names, pixels, img_dir, mask_dir = _synthetic_set(tmp_path, n=3, rgba_every=99, masks=True)
    out = tmp_path / "s"
    rep = import_colmap(tmp_path / "model", img_dir, out, masks_dir=mask_dir)
    assert rep["masks"] == 3
    s = Session.open(out)
    m = s.load_image(s.select(phase="mask", camera=1)[0])[..., 0]
    np.testing.assert_allclose(m, pixels[("mask", 1)] / 255.0, atol=1e-6)
    with pytest.raises(InputError, match="not empty"):
        import_colmap(tmp_path / "model", img_dir, out)
    (img_dir / names[2]).unlink()
    with pytest.raises(InputError, match="img_02"):
        import_colmap(tmp_path / "model", img_dir, tmp_path / "s2")
    assert not (tmp_path / "s2").exists()  # nothing written when an image is missing


def test_closest_point_to_axes_degenerate_cases():
    rng = np.random.default_rng(1)
    # general position: every axis passes through p
    p = np.array([0.3, -0.2, 1.0])
    C = rng.normal(size=(6, 3)) * 3
    np.testing.assert_allclose(closest_point_to_axes(C, p - C), p, atol=1e-9)
    # parallel axes (all cameras looking the same way): finite, on the centroid's line
    C = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], float)
    D = np.tile([0, 0, 1.0], (3, 1))
    q = closest_point_to_axes(C, D)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(q[:2], C.mean(0)[:2], atol=1e-9)
    # one camera, coincident viewpoints
    q = closest_point_to_axes(C[:1], D[:1])
    np.testing.assert_allclose(q, C[0], atol=1e-9)
    q = closest_point_to_axes(np.zeros((3, 3)), [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(q, 0, atol=1e-12)
    with pytest.raises(InputError):
        closest_point_to_axes(C, np.zeros((3, 3)))
