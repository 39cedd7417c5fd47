"""Reflectance stored as a per-view PCA (issue 14, "PCA per view ... with the error
reported"): the file as OpenEXR itself reads it, the reconstruction against NumPy's SVD,
exact ranks, the reported error against the measured one, relighting against the
layered model, bad options and corrupt files, and the build's flags and report."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from helpers import invoke_cli
from opacityhull.errors import ConfigError, FormatError, InputError
from opacityhull.model import OpacityHullModel, copy_model
from opacityhull.reflectance_pca import (
    allocate_ranks,
    compress_view,
    read_reflectance_pca,
    write_reflectance_pca,
)
from opacityhull.relight.relit import Relighter, compress_reflectance_reference


def _stack(m: OpacityHullModel, i: int) -> np.ndarray:
    d = m.load_reflectance(i)
    return np.stack([d[L.key] for L in m.light_samples])


def _rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """The analytic Lambertian sphere (8 views of 40x32, 60 light samples) as float
    layers, and copies as one rank-6 PCA per view (float), rank 4 per 8-px block (float)
    and per block at a 1 % error target (half, the defaults)."""
    from opacityhull.relight.synthetic import write_sphere_model

    tmp = tmp_path_factory.mktemp("pca")
    src = OpacityHullModel.open(write_sphere_model(tmp / "layers", width=40, height=32))

    def pca(name, **kw):
        return copy_model(src, tmp / name, reflectance_storage="pca", **kw)

    return {
        "layers": src,
        "view6": pca("view6", storage="float", pca_rank=6, pca_block=None),
        "block4": pca("block4", storage="float", pca_rank=4, pca_block=8),
        "err1": pca("err1", storage="half", pca_error=0.01),
    }


def _raw(path: Path, part: int = 0):
    """Header and channels of one part as the OpenEXR package returns them (no
    opacityhull reader)."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return dict(f.header(part)), {k: np.asarray(v.pixels) for k, v in f.channels(part).items()}


def _blocks(box, block):
    x0, y0, x1, y1 = box
    for iy, y in enumerate(range(y0, y1, block)):
        for ix, x in enumerate(range(x0, x1, block)):
            yield iy, ix, slice(y, min(y1, y + block)), slice(x, min(x1, x + block))


def test_the_file_read_by_openexr_itself_rebuilds_what_the_loader_returns(models):
    m, src = models["block4"], models["layers"]
    meta = tomllib.loads((m.root / "model.toml").read_text())
    r = meta["reflectance"]
    assert r["storage"] == "pca" and r["pca_rank"] == 4 and r["pca_block"] == 8
    keys = [L.key for L in m.light_samples]
    for i, v in enumerate(m.views):
        p = m.root / "reflectance" / f"{v.id}.exr"
        with OpenEXR.File(str(p)) as f:
            assert [q.name() for q in f.parts] == ["basis", "coefficients"]
        h, ch = _raw(p, 0)
        h1, co = _raw(p, 1)
        assert h["reflectanceStorage"] == "pca" and h["pcaRank"] == 4
        assert (h["pcaBlockWidth"], h["pcaBlockHeight"]) == (8, 8) and h["pcaKeys"] == ",".join(keys)
        assert set(ch) == {f"pc{j:03d}.{c}" for j in range(4) for c in "RGB"}
        assert set(co) == {"rank"} | {f"{k}.c{j:03d}" for k in keys for j in range(4)}
        assert all(c.dtype == np.float32 for c in ch.values())
        (x0, y0), (x1, y1) = h["dataWindow"]
        (dx0, dy0), (dx1, dy1) = h["displayWindow"]
        assert (dx0, dy0, dx1 + 1, dy1 + 1) == (0, 0, v.camera.width, v.camera.height)
        box = (int(x0), int(y0), int(x1) + 1, int(y1) + 1)
        pv = r["pca_views"][i]
        assert pv["id"] == v.id and pv["box"] == list(box) and pv["rank"] == 4
        # the crop is the box of the non-zero pixels: nothing lost outside, and it is tight
        s = _stack(src, i)
        nz = np.nonzero(np.any(s != 0, axis=(0, 3)))
        assert (nz[1].min(), nz[0].min(), nz[1].max() + 1, nz[0].max() + 1) == box
        assert (box[2] - box[0]) * (box[3] - box[1]) < v.camera.width * v.camera.height
        # one-light image k over block b = sum_j coefficients.<key>.c<j>[b] * basis.pc<j>
        B = np.stack([np.stack([ch[f"pc{j:03d}.{c}"] for c in "RGB"], -1) for j in range(4)])
        loaded = m.load_reflectance(i)
        for k in keys[::7]:
            img = np.zeros((v.camera.height, v.camera.width, 3))
            for iy, ix, ys, xs in _blocks(box, 8):
                c = np.array([co[f"{k}.c{j:03d}"][iy, ix] for j in range(4)], np.float64)
                img[ys, xs] = np.einsum(
                    "j,jyxc->yxc", c, B[:, ys.start - box[1] : ys.stop - box[1], xs.start - box[0] : xs.stop - box[0]]
                )
            np.testing.assert_allclose(loaded[k], img, rtol=1e-5, atol=1e-6 * s.max())
        # each block has the fixed rank, except all-zero ones (rank 0)
        ranks = co["rank"]
        for iy, ix, ys, xs in _blocks(box, 8):
            assert ranks[iy, ix] == (4 if s[:, ys, xs].any() else 0)
        # the light attributes of the layered file are still in the header
        assert m.reflectance_metadata(i).keys() == src.reflectance_metadata(i).keys()
        np.testing.assert_allclose(
            m.reflectance_metadata(i)[keys[0]]["direction"], src.reflectance_metadata(i)[keys[0]]["direction"]
        )
        # the error in the header and in model.toml is the one measured here
        assert h["pcaRelError"] == pytest.approx(_rel(_stack(m, i), s), rel=1e-3)
        assert pv["rel_error"] == pytest.approx(h["pcaRelError"], rel=1e-6)


def test_the_reconstruction_is_numpys_truncated_svd_per_view_and_per_block(models):
    src = models["layers"]
    for i in (0, 5):
        s = _stack(src, i)
        tol = 2e-5 * float(np.abs(s).max())
        # one PCA for the view
        np.testing.assert_allclose(_stack(models["view6"], i), compress_reflectance_reference(s, 6), atol=tol)
        sv = np.linalg.svd(s.reshape(len(s), -1).astype(np.float64), compute_uv=False)
        err = float(np.sqrt((sv[6:] ** 2).sum() / (sv**2).sum()))
        assert models["view6"].meta["reflectance"]["pca_views"][i]["rel_error"] == pytest.approx(err, rel=2e-3)
        # per block: each block is its own truncated SVD
        got = _stack(models["block4"], i)
        box = tuple(models["block4"].meta["reflectance"]["pca_views"][i]["box"])
        ref = np.zeros_like(s)
        for _, _, ys, xs in _blocks(box, 8):
            blk = s[:, ys, xs]
            ref[:, ys, xs] = compress_reflectance_reference(blk, 4) if blk.any() else 0
        np.testing.assert_allclose(got, ref, atol=tol)
    # blocks see fewer normals each: rank 4 per block beats rank 6 for the whole view
    r = {n: models[n].meta["reflectance"]["rel_error_max"] for n in ("view6", "block4")}
    assert r["block4"] < 0.6 * r["view6"]


def test_an_error_target_picks_the_smallest_rank_and_half_storage_keeps_it(models):
    m, src = models["err1"], models["layers"]
    r = m.meta["reflectance"]
    assert r["pca_error_target"] == 0.01 and "pca_rank" not in r and r["pca_block"] == 8
    assert m.storage == "half"
    for i, pv in enumerate(r["pca_views"]):
        s = _stack(src, i)
        _, co = _raw(m.root / "reflectance" / f"{m.views[i].id}.exr", 1)
        kept, dropped = [], []
        for iy, ix, ys, xs in _blocks(tuple(pv["box"]), 8):
            blk = s[:, ys, xs].reshape(len(s), -1).astype(np.float64)
            rank = int(co["rank"][iy, ix])
            sv2 = np.linalg.svd(blk, compute_uv=False) ** 2 if blk.any() else np.zeros(1)
            kept += list(sv2[:rank])
            dropped += list(sv2[rank:])
        total = sum(kept) + sum(dropped)
        # the view's truncation error meets the target, and with its smallest kept
        # component dropped as well it would not: the fewest components that do
        assert np.sqrt(sum(dropped) / total) <= 0.01 < np.sqrt((sum(dropped) + min(kept)) / total)
        # the largest sigma^2 across blocks are the ones kept
        assert min(kept) >= max(dropped) * (1 - 1e-9)
        assert pv["rank"] == int(co["rank"].max())
        measured = _rel(_stack(m, i), s)
        # half rounding of basis and coefficients adds ~2**-11 relative on top of the truncation
        assert measured == pytest.approx(pv["rel_error"], rel=1e-3)
        assert measured <= 0.01 + 2 * 2.0**-11
    assert r["rel_error_max"] == max(pv["rel_error"] for pv in r["pca_views"])


def test_a_rank_deficient_stack_is_exact_at_its_rank(tmp_path):
    rng = np.random.default_rng(1)
    H, W = 12, 10
    a, b = rng.random((H, W, 3), np.float32), rng.random((H, W, 3), np.float32)
    # 2 distinct lights, repeated and mixed with non-negative weights: rank 2
    imgs = [a, b, a, b, 0.5 * a + 0.25 * b, 2 * a, b]
    keys = [f"l{k}" for k in range(len(imgs))]
    p = tmp_path / "v.exr"
    for block in (None, 4):
        pv = write_reflectance_pca(p, dict(zip(keys, imgs, strict=True)), keys, shape=(H, W), error=1e-5, block=block)
        assert pv.rank == 2 and pv.rel_error < 1e-6 and set(pv.ranks.ravel()) == {2}
        back = read_reflectance_pca(p, keys, shape=(H, W))
        for k, img in zip(keys, imgs, strict=True):
            np.testing.assert_allclose(back[k], img, rtol=0, atol=2e-6)
    assert allocate_ranks([np.array([3.0, 1.0, 0.0, 0.0])], target=1e-9) == [2]
    # across blocks the largest sigma^2 are kept first: 4^2 + 3^2 of 4^2 + 3^2 + 1 + 0.5^2
    assert allocate_ranks([np.array([4.0, 1.0]), np.array([3.0, 0.5])], target=0.25) == [1, 1]
    assert allocate_ranks([np.array([4.0, 1.0]), np.array([3.0, 0.5])], target=0.15) == [2, 1]
    assert allocate_ranks([np.zeros(3)], target=0.01) == [0]
    # an all-zero view: rank 1, error 0, one pixel stored
    z = write_reflectance_pca(p, {k: np.zeros((H, W, 3)) for k in keys}, keys, shape=(H, W), rank=None)
    assert (z.rank, z.rel_error, z.box) == (1, 0.0, (0, 0, 1, 1))
    assert all(not v.any() for v in read_reflectance_pca(p, keys, shape=(H, W)).values())


@settings(max_examples=25, deadline=None)
@given(
    K=st.integers(1, 9),
    H=st.integers(1, 7),
    W=st.integers(1, 7),
    seed=st.integers(0, 2**31 - 1),
    frac=st.floats(0.0, 1.0),
    half=st.booleans(),
    block=st.sampled_from([None, 2, 3, 5]),
)
def test_the_reported_error_is_the_measured_error_of_what_is_stored(tmp_path_factory, K, H, W, seed, frac, half, block):
    rng = np.random.default_rng(seed)
    s = rng.random((K, H, W, 3)).astype(np.float32) * rng.uniform(0.01, 100)
    r = max(1, int(round(frac * K)))
    keys = [f"l{k}" for k in range(K)]
    p = tmp_path_factory.mktemp("h") / "v.exr"
    layers = {k: s[i] for i, k in enumerate(keys)}
    pv = write_reflectance_pca(p, layers, keys, shape=(H, W), rank=r, half=half, block=block)
    back = read_reflectance_pca(p, keys, shape=(H, W))
    measured = _rel(np.stack([back[k] for k in keys]), s)
    assert pv.rel_error == pytest.approx(measured, rel=1e-3, abs=1e-6)
    assert _raw(p)[0]["pcaRelError"] == pytest.approx(pv.rel_error, rel=1e-6)
    # without half rounding it is the truncated SVDs' error (every block's, or the view's)
    ref = np.zeros_like(s)
    for _, _, ys, xs in _blocks((0, 0, W, H), max(H, W) if block is None else block):
        ref[:, ys, xs] = compress_reflectance_reference(s[:, ys, xs], r)
    ref_err = _rel(ref, s)
    assert pv.truncation_error == pytest.approx(ref_err, rel=1e-3, abs=2e-6)
    if not half:
        assert measured == pytest.approx(ref_err, rel=1e-3, abs=2e-6)
    else:
        assert abs(measured - ref_err) <= 2 * 2.0**-11 + 1e-6


def test_relighting_a_pca_model_matches_the_layered_model_within_the_stored_error(models, probes_dir):
    from opacityhull.relight.envmap import load_envmap

    src = models["layers"]
    for name in ("view6", "block4", "err1"):
        m = models[name]
        stored = m.meta["reflectance"]["rel_error_max"]
        a, b = Relighter(src), Relighter(m)
        num = den = 0.0
        for probe in ("grace", "uffizi"):
            env = load_envmap(probes_dir / f"{probe}.hdr", yaw_deg=90)
            for i in range(len(src.views)):
                x, y = a.relight_view(i, envmap=env), b.relight_view(i, envmap=env)
                np.testing.assert_array_equal(x[..., 3], y[..., 3])  # the matte is untouched
                num += float(np.sum((x[..., :3].astype(np.float64) - y[..., :3]) ** 2))
                den += float(np.sum(x[..., :3].astype(np.float64) ** 2))
        relit = float(np.sqrt(num / den))
        # relighting sums the one-light images with smooth weights, which averages the
        # discarded components out: the relit error stays below the stack's error
        assert 0 < relit <= stored, (name, relit, stored)


@pytest.fixture(scope="module")
def probes_dir():
    from opacityhull.data import PROBES_DIR

    if not (PROBES_DIR / "grace.hdr").is_file():
        pytest.skip(f"light probes not found in {PROBES_DIR}")
    return PROBES_DIR


# --------------------------------------------------------------------------- bad input


def test_bad_ranks_targets_and_non_finite_data_are_refused(models, tmp_path):
    src = models["layers"]
    K = len(src.light_samples)
    s = np.ones((3, 4, 5, 3), np.float32)
    with pytest.raises(InputError, match=r"PCA rank 0: expected an integer >= 1"):
        compress_view(s, rank=0)
    with pytest.raises(InputError, match=r"PCA rank 4 is more than the 3 light samples"):
        compress_view(s, rank=4)
    with pytest.raises(InputError, match=r"PCA error target 1.5"):
        compress_view(s, error=1.5)
    with pytest.raises(InputError, match=r"PCA block 1: expected an edge of at least 2 pixels"):
        compress_view(s, block=1)
    with pytest.raises(InputError, match=rf"pca_rank {K + 1} is more than the {K} light samples"):
        copy_model(src, tmp_path / "m", storage="float", reflectance_storage="pca", pca_rank=K + 1)
    with pytest.raises(InputError, match=r"reflectance_storage 'zip'"):
        copy_model(src, tmp_path / "m", storage="float", reflectance_storage="zip")  # type: ignore[arg-type]
    bad = s.copy()
    bad[1, 2, 3, 0] = np.nan
    with pytest.raises(InputError, match=r"v\.exr: 1 NaN/Inf value\(s\) in the one-light images \(first in image 1\)"):
        write_reflectance_pca(tmp_path / "v.exr", {f"l{k}": bad[k] for k in range(3)}, ["l0", "l1", "l2"], shape=(4, 5))
    assert not (tmp_path / "v.exr").exists()
    from opacityhull.reconstruct.build import BuildConfig

    with pytest.raises(ConfigError, match="reflectance_storage must be one of 'layers', 'pca'"):
        BuildConfig(reflectance_storage="zip")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="pca_rank must be None or an integer >= 1"):
        BuildConfig(pca_rank=0)
    with pytest.raises(ConfigError, match=r"pca_error must be a relative error in \(0, 1\)"):
        BuildConfig(pca_error=0.0)
    with pytest.raises(ConfigError, match=r"pca_block must be None \(one PCA per view\) or an integer >= 2"):
        BuildConfig(pca_block=1)


def _corrupt_copy(models, tmp_path) -> OpacityHullModel:
    import shutil

    shutil.copytree(models["block4"].root, tmp_path / "m")
    return OpacityHullModel.open(tmp_path / "m")


def test_a_truncated_pca_file_is_a_format_error_naming_it(models, tmp_path):
    m = _corrupt_copy(models, tmp_path)
    p = m.root / "reflectance" / f"{m.views[2].id}.exr"
    p.write_bytes(p.read_bytes()[:300])
    with pytest.raises(FormatError, match=rf"{p.name}: not a readable EXR file") as e:
        m.load_reflectance(2)
    assert e.value.exit_code == 4


def _rewrite(p: Path, edit) -> None:
    """Rewrite the two parts of ``p`` after ``edit(h0, basis, h1, coeffs)`` changed them."""
    h0, b = _raw(p, 0)
    h1, c = _raw(p, 1)
    edit(h0, b, h1, c)
    parts = [
        OpenEXR.Part({k: v for k, v in h.items() if k not in ("channels", "name")}, ch, name=n)
        for h, ch, n in ((h0, b, "basis"), (h1, c, "coefficients"))
    ]
    with OpenEXR.File(parts) as f:
        f.write(str(p))


def test_mismatched_pca_files_name_the_file_and_the_key(models, tmp_path):
    m = _corrupt_copy(models, tmp_path)
    key = m.light_samples[7].key
    p = m.root / "reflectance" / f"{m.views[1].id}.exr"

    def nan(h0, b, h1, c):
        c[f"{key}.c002"] = c[f"{key}.c002"].copy()
        c[f"{key}.c002"][0, 0] = np.nan

    _rewrite(p, nan)
    with pytest.raises(
        FormatError, match=rf"{p.name}: PCA coefficients {key}\.c002 of one-light image {key} hold NaN/Inf"
    ):
        m.load_reflectance(1)

    def gone(h0, b, h1, c):
        del c[f"{key}.c003"]

    p5 = m.root / "reflectance" / f"{m.views[5].id}.exr"
    _rewrite(p5, gone)
    with pytest.raises(FormatError, match=rf"{p5.name}: PCA coefficients {key}\.c003 of one-light image {key} missing"):
        m.load_reflectance(5)

    p3 = m.root / "reflectance" / f"{m.views[3].id}.exr"

    def no_layer(h0, b, h1, c):
        del b["pc003.G"]

    _rewrite(p3, no_layer)
    with pytest.raises(FormatError, match=r"PCA rank 4 needs basis layers pc000..pc003 .*missing \['pc003.G'\]"):
        m.load_reflectance(3)

    p2 = m.root / "reflectance" / f"{m.views[2].id}.exr"

    def blocks(h0, b, h1, c):
        h0["pcaBlockWidth"] = 16

    _rewrite(p2, blocks)
    with pytest.raises(FormatError, match=rf"{p2.name}: coefficients part is \d+x\d+ blocks, the data window holds"):
        m.load_reflectance(2)
    # a layered file where model.toml says PCA
    p4 = m.root / "reflectance" / f"{m.views[4].id}.exr"
    p4.write_bytes((models["layers"].root / "reflectance" / p4.name).read_bytes())
    with pytest.raises(FormatError, match=r"header reflectanceStorage is None, expected 'pca'"):
        m.load_reflectance(4)
    # model.toml naming an unknown storage
    t = m.root / "model.toml"
    t.write_text(t.read_text().replace('storage = "pca"', 'storage = "zip"'))
    with pytest.raises(FormatError, match=r"model\.toml: reflectance\.storage 'zip'"):
        OpacityHullModel.open(m.root).load_reflectance(0)


def test_a_model_without_the_storage_key_reads_layers(models):
    src = models["layers"]
    meta = dict(src.meta)
    meta["reflectance"] = {k: v for k, v in src.meta["reflectance"].items() if k != "storage"}
    old = OpacityHullModel(src.root, meta, src.views)
    assert old.reflectance_storage == "layers"
    np.testing.assert_array_equal(_stack(old, 0), _stack(src, 0))


# --------------------------------------------------------------------------- build CLI


def test_build_reflectance_storage_flag_and_report(cli_session, tmp_path):
    out = tmp_path / "model"
    base = ["build", cli_session, "--out", out, "--hull-res", "24", "--no-pictures", "--json"]
    res = invoke_cli(base)
    assert res.exit_code == 0, res.output
    layers = json.loads(res.stdout)["metrics"]
    assert layers["reflectance_storage"] == "layers" and "reflectance_pca" not in layers
    m = OpacityHullModel.open(out)
    ref = [_stack(m, i) for i in range(len(m.views))]

    # only the write step reruns; the one-light images come back within the reported error
    res = invoke_cli([*base, "--resume", "--reflectance-storage", "pca", "--pca-rank", "2"])
    assert res.exit_code == 0, res.output
    summ = json.loads(res.stdout)
    assert summ["steps"]["write"] == "ran" and summ["steps"]["matting"] == "reused"
    pca = summ["metrics"]["reflectance_pca"]
    assert summ["metrics"]["reflectance_storage"] == "pca"
    m = OpacityHullModel.open(out)
    assert m.reflectance_storage == "pca"
    assert pca["rank"] == 2 and set(pca["rank_per_view"].values()) == {2}
    assert json.loads((out / "report.json").read_text())["metrics"]["reflectance_pca"] == pca
    for i, v in enumerate(m.views):
        err = _rel(_stack(m, i), ref[i])
        # the layered build's half pixels and the PCA's half basis round differently
        assert err == pytest.approx(pca["rel_error_per_view"][v.id], rel=0.02, abs=2.0**-10)
    # the report gives the PCA files' bytes (at 40x30 px the channel list of the
    # coefficients part outweighs the pixels: the byte gain needs real view sizes)
    on_disk = sum((out / "reflectance" / f"{v.id}.exr").stat().st_size for v in m.views) / len(m.views)
    assert summ["metrics"]["disk_bytes_per_view_reflectance"] == on_disk

    res = invoke_cli([*base, "--resume", "--reflectance-storage", "pca", "--pca-error", "0.02"])
    assert res.exit_code == 0, res.output
    pca = json.loads(res.stdout)["metrics"]["reflectance_pca"]
    assert pca["error_target"] == 0.02 and pca["rank"] is None
    assert pca["rel_error_max"] <= 0.02 + 2.0**-10


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--reflectance-storage", "zip"], "--reflectance-storage 'zip': expected layers or pca"),
        (["--pca-rank", "3"], "--pca-rank / --pca-error / --pca-block need --reflectance-storage pca"),
        (["--reflectance-storage", "pca", "--pca-block", "1"], "--pca-block 1: expected 0 (one PCA per view)"),
        (["--reflectance-storage", "pca", "--pca-rank", "0"], "--pca-rank 0: expected an integer >= 1"),
        (["--reflectance-storage", "pca", "--pca-error", "2"], "--pca-error 2.0: expected a relative error in (0, 1)"),
        (["--reflectance-storage", "pca", "--pca-rank", "2", "--pca-error", "0.1"], "give one"),
    ],
)
def test_bad_pca_flags_are_exit_2_naming_them(cli_session, tmp_path, flags, message):
    res = invoke_cli(["build", cli_session, "--out", tmp_path / "m", *flags])
    assert res.exit_code == 2, res.output
    assert message in " ".join(res.stderr.split())
    assert not (tmp_path / "m").exists()
