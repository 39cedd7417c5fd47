"""The Mitsuba-rendered synthetic set of ``benchmarks/synthetic_set.py`` (#29) at a tiny
size: its ``transforms.json`` is what ``import nerfstudio`` accepts, and the alpha it
wrote is the object's silhouette seen by the written camera — checked against an
independent rasterization (OpenCV ``fillConvexPoly`` of the projected triangles, 16×16
supersampled), not against Mitsuba."""

from __future__ import annotations

import importlib
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def synthetic_set():
    sys.path.insert(0, str(BENCH))
    try:
        mod = importlib.import_module("synthetic_set")
    finally:
        sys.path.remove(str(BENCH))
    return mod


@pytest.fixture(scope="module")
def tiny_set(synthetic_set, tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "set"
    info = synthetic_set.render_set(out, synthetic_set.SetConfig(views=6, size_px=48, spp=16), log=lambda *a, **k: None)
    return out, info


def _coverage(parts, T_gl: np.ndarray, angle_x: float, size: int, ss: int = 16) -> np.ndarray:
    """Fraction of each pixel covered by the projected triangles (OpenCV rasterizer)."""
    import cv2

    world_from_cam = T_gl @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV camera
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    f = 0.5 * size / math.tan(0.5 * angle_x)
    canvas = np.zeros((size * ss, size * ss), np.uint8)
    polys = []
    for p in parts:
        X = (p.vertices - t) @ R  # camera coordinates
        assert np.all(X[:, 2] > 0)
        u = f * X[:, 0] / X[:, 2] + 0.5 * size  # continuous image coordinates (pixel edges at integers)
        v = f * X[:, 1] / X[:, 2] + 0.5 * size
        uv = np.stack([u, v], 1) * ss * 16  # shift=4 fixed point
        polys += list(np.round(uv[p.faces]).astype(np.int32))
    for tri in polys:  # one call each: fillPoly's even-odd rule would cancel overlaps
        cv2.fillConvexPoly(canvas, tri, 255, lineType=cv2.LINE_8, shift=4)
    return canvas.reshape(size, ss, size, ss).mean(axis=(1, 3)) / 255.0


def test_the_set_imports_and_its_alpha_is_the_silhouette(synthetic_set, tiny_set, tmp_path):
    from opacityhull.acquire.importers import import_nerfstudio
    from opacityhull.imageio import read_png
    from opacityhull.session import Session

    out, info = tiny_set
    meta = json.loads((out / "transforms.json").read_text())
    assert len(meta["frames"]) == 6 and info["views"] == 6
    assert len(json.loads((out / "transforms_test.json").read_text())["frames"]) == 1  # every 10th: view 0
    rep = import_nerfstudio(out / "transforms.json", tmp_path / "session")
    assert rep["images"] == 6 and rep["masks"] == 6
    assert len(Session.open(tmp_path / "session").view_cameras() or {}) == 6
    parts = synthetic_set.bulldozer_parts(0)
    for fr in meta["frames"]:
        alpha = read_png(out / (fr["file_path"] + ".png"))[..., 3]
        cov = _coverage(parts, np.asarray(fr["transform_matrix"]), meta["camera_angle_x"], 48)
        # measured: mean |alpha - coverage| 0.004-0.009, IoU 0.95-0.98, the oracle's area
        # 1.5-3 % larger (fillConvexPoly includes the pixels an edge touches: it halves
        # from 8x8 to 16x16 subsamples); the alpha's own noise at 16 spp ~0.1 per edge pixel
        assert np.abs(alpha - cov).mean() < 0.015, np.abs(alpha - cov).mean()
        a, c = alpha > 0.5, cov > 0.5
        assert (a & c).sum() / (a | c).sum() > 0.9
        assert alpha.sum() == pytest.approx(cov.sum(), rel=0.05)
        # pixels the oracle covers fully / not at all: alpha 1 / 0 (up to the edge noise)
        assert np.mean(alpha[cov == 1.0] > 0.9) > 0.98 and np.all(alpha[cov == 0.0] < 0.1)


def test_the_set_is_deterministic(synthetic_set, tiny_set, tmp_path):
    """The same settings render the same cameras and the same pixels."""
    from opacityhull.imageio import read_png

    out, _ = tiny_set
    again = tmp_path / "again"
    synthetic_set.render_set(again, synthetic_set.SetConfig(views=6, size_px=48, spp=16), log=lambda *a, **k: None)
    assert (again / "transforms.json").read_text() == (out / "transforms.json").read_text()
    for fr in json.loads((out / "transforms.json").read_text())["frames"]:
        a = read_png(out / (fr["file_path"] + ".png"))
        b = read_png(again / (fr["file_path"] + ".png"))
        assert np.array_equal(a, b), fr["file_path"]
