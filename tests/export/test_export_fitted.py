"""``export --format ply`` of a model built with ``--optimize`` (#29 item 4): ``splats.ply``
is the fitted splats in the 3DGS layout a splat viewer opens, every value the fit's own
(read back with plyfile against ``MODEL/optimized/splats.ply``); ``--splats hull`` and
unfitted models keep the hull export; ``--splats fitted`` without a fit exits 2."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from plyfile import PlyData
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

import fitted
from opacityhull.cli import app
from opacityhull.export.formats import FLAT_AXIS_FRACTION
from opacityhull.optimize.splatply import read_splat_ply


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "4000"})


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return fitted.sphere(tmp_path_factory)


def test_fitted_splats_ply_holds_the_fit_values_in_the_3dgs_layout(model, tmp_path):
    r = run("export", model, "--format", "ply", "--out", tmp_path / "p", "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    fit = read_splat_ply(model / "optimized" / "splats.ply")  # the fit's own output
    N, B = fit["sh"].shape[:2]
    assert s["splats"] == "fitted" and s["points"] == N and s["sh_degree"] == s["sh_degree_fitted"] == 1 and B == 4
    ply = PlyData.read(str(tmp_path / "p" / "splats.ply"))
    v = ply["vertex"].data
    names = list(v.dtype.names or ())
    want = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    want += [f"f_rest_{i}" for i in range(3 * (B - 1))]
    want += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == want and all(v.dtype[n] == np.dtype("<f4") for n in names)
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    np.testing.assert_array_equal(xyz, fit["means"])
    for c in range(3):
        np.testing.assert_array_equal(v[f"f_dc_{c}"], fit["sh"][:, 0, c])
        for j in range(1, B):  # 3DGS's features_rest: channel-major
            np.testing.assert_array_equal(v[f"f_rest_{c * (B - 1) + j - 1}"], fit["sh"][:, j, c])
    np.testing.assert_array_equal(v["opacity"], fit["opacity_logits"])
    np.testing.assert_array_equal(np.stack([v["scale_0"], v["scale_1"]], 1), fit["log_scales"])
    np.testing.assert_array_equal(np.stack([v[f"rot_{i}"] for i in range(4)], 1), fit["quats"])
    np.testing.assert_allclose(
        v["scale_2"], fit["log_scales"].min(axis=1) + np.log(FLAT_AXIS_FRACTION), rtol=0, atol=1e-6
    )
    # as a 3DGS viewer reads it: R(q) diag(exp(scale))² Rᵀ, the normal the rotation's z axis
    R = Rotation.from_quat(np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64), scalar_first=True)
    M = R.as_matrix()
    nrm = np.stack([v["nx"], v["ny"], v["nz"]], 1)
    np.testing.assert_allclose(M[:, :, 2], nrm, atol=1e-5)
    sig = np.exp(np.stack([v["scale_0"], v["scale_1"], v["scale_2"]], 1).astype(np.float64))
    cov = np.einsum("nij,nj,nkj->nik", M, sig**2, M)
    assert np.all(np.einsum("ni,nij,nj->n", nrm, cov, nrm) <= (FLAT_AXIS_FRACTION * sig[:, :2].min(1)) ** 2 * 1.001)
    # the fit moved every kind of parameter away from the hull's start (the file is the fit, not the hull)
    assert np.ptp(fit["log_scales"][:, 0] - fit["log_scales"][:, 1]) > 1e-3 and np.ptp(fit["opacity_logits"]) > 1e-3
    # points.ply: the centres, their DC colour (8-bit sRGB) and opacity
    pts = PlyData.read(str(tmp_path / "p" / "points.ply"))["vertex"].data
    np.testing.assert_array_equal(np.stack([pts["x"], pts["y"], pts["z"]], 1), fit["means"])
    dc = np.clip(0.5 + 0.28209479177387814 * fit["sh"][:, 0, 0], 0, 1)
    assert np.abs(pts["red"].astype(float) - dc * 255).max() <= 0.5 + 1e-3  # the DC colour is display (sRGB) already
    op = 1 / (1 + np.exp(-fit["opacity_logits"].astype(np.float64)))
    assert np.abs(pts["alpha"].astype(float) - op * 255).max() <= 0.5 + 1e-6


def test_sh_degree_drops_the_higher_bands_and_hull_keeps_the_old_export(model, tmp_path):
    from opacityhull.model import OpacityHullModel

    r = run("export", model, "--format", "ply", "--out", tmp_path / "h", "--splats", "hull", "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["splats"] == "hull" and "sh_rms" in s and s["points"] == len(OpacityHullModel.open(model).surfels)
    v = PlyData.read(str(tmp_path / "h" / "splats.ply"))["vertex"].data
    assert len([n for n in v.dtype.names or () if n.startswith("f_rest_")]) == 3 * 15  # the hull's degree-3 SH fit


def test_bad_splats_input_exits_2_and_writes_nothing(model, tmp_path):
    plain = tmp_path / "plain"
    shutil.copytree(model, plain)
    shutil.rmtree(plain / "optimized")
    for m, val, words in (
        (plain, "fitted", ("--splats fitted", "are missing", "--optimize")),
        (model, "nerf", ("--splats 'nerf'", "auto, fitted, hull")),
    ):
        out = tmp_path / f"out_{val}"
        r = run("export", m, "--format", "ply", "--out", out, "--splats", val)
        err = " ".join(r.stderr.split())
        assert r.exit_code == 2 and all(w in err for w in words), err
        assert not out.exists() and "Traceback" not in err
    r = run("export", plain, "--format", "ply", "--out", tmp_path / "auto", "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["splats"] == "hull"  # auto without a fit: the hull
