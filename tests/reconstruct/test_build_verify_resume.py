"""``build --resume`` verifies what it reuses (#35): every product a step reuses must
still have the digest recorded when it was written. A corrupted model file reruns the
step that wrote it, and ``render`` then works; a cache pickle overwritten with text or
with a valid pickle of another type reruns its step, with a note, never a traceback."""

from __future__ import annotations

import hashlib
import json
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

import rcsynth
from opacityhull.reconstruct.build import STEPS, BuildConfig, build_model, file_digest
from opacityhull.reconstruct.buildstore import FULL_DIGEST_MAX_BYTES
from opacityhull.reconstruct.steps.base import BuildContext, Step, check_steps

CLI = Path(sys.executable).with_name("opacityhull")
CFG = BuildConfig(hull_res=40, pictures=False)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("verify")
    session = tmp / "session"
    rcsynth.make_session(session, kind="sphere", n_angles=4, reflectance=False, seed=13)
    ref = tmp / "ref"
    build_model(session, ref, config=CFG)
    return session, ref


def _model_digests(root: Path) -> dict:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.parts[len(root.parts)] not in ("build",) and p.name not in ("model.toml", "report.json")
    }


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _flip(path: Path, offset: int, n: int = 64) -> None:
    b = bytearray(path.read_bytes())
    off = min(offset, len(b) - n)
    b[off : off + n] = bytes(x ^ 0xFF for x in b[off : off + n])
    path.write_bytes(bytes(b))


@pytest.mark.parametrize("target", ["surfels.ply", "views"])
def test_a_corrupted_model_file_reruns_the_write_step_and_render_works(built, tmp_path, target):
    session, ref = built
    out = _copy(ref, tmp_path / "m")
    f = out / "surfels.ply" if target == "surfels.ply" else sorted((out / "views").glob("*.exr"))[1]
    _flip(f, f.stat().st_size // 2)
    rep = build_model(session, out, config=CFG, resume=True)
    assert rep.steps["write"] == "ran" and rep.steps["geometry"] == "reused" and rep.steps["cameras"] == "reused"
    assert any(str(f.relative_to(out)) in n and "changed since it was written" in n for n in rep.notes), rep.notes
    assert _model_digests(out) == _model_digests(ref)  # rewritten byte for byte
    r = subprocess.run(
        [str(CLI), "render", str(out), "--view", "0,0", "--out", str(tmp_path / "v.png"), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    # an unchanged model resumes with every step reused and no note
    rep = build_model(session, out, config=CFG, resume=True)
    assert set(rep.steps.values()) == {"reused"} and not any("runs again" in n for n in rep.notes)


@pytest.mark.parametrize("name", ["cameras.pkl", "geometry.pkl"])
@pytest.mark.parametrize("how", ["text", "wrong type"])
def test_an_overwritten_cache_pickle_reruns_its_step(built, tmp_path, name, how):
    session, ref = built
    out = _copy(ref, tmp_path / "m")
    p = out / "build" / name
    if how == "text":
        p.write_text("this is not a pickle\n" * 3)
    else:
        p.write_bytes(pickle.dumps({"a": "dict", "not": "the product"}))
    rep = build_model(session, out, config=CFG, resume=True)
    step = name.removesuffix(".pkl")
    assert rep.steps[step] == "ran"
    assert any(name in n for n in rep.notes), rep.notes
    assert _model_digests(out) == _model_digests(ref)


def test_a_wrong_type_pickle_with_a_matching_digest_reruns_its_step(built, tmp_path):
    """Even when the manifest's digest is rewritten to match (a cache edited on purpose),
    the product's type is checked before it is used."""
    session, ref = built
    out = _copy(ref, tmp_path / "m")
    p = out / "build" / "cameras.pkl"
    p.write_bytes(pickle.dumps(("views", "not cameras")))
    man = out / "build" / "manifest.json"
    d = json.loads(man.read_text())
    d["steps"]["cameras"]["digests"]["build/cameras.pkl"] = file_digest(p)
    man.write_text(json.dumps(d))
    rep = build_model(session, out, config=CFG, resume=True)
    assert rep.steps["cameras"] == "ran" and any("not the cameras step's product" in n for n in rep.notes)


def test_file_digest_hashes_whole_files_and_edges_of_large_ones(tmp_path, monkeypatch):
    import opacityhull.reconstruct.buildstore as bs

    f = tmp_path / "x.bin"
    data = bytes(range(256)) * 4096 * 3  # 3 MiB: the middle MiB is outside both edges
    f.write_bytes(data)
    assert file_digest(f) == "sha256:" + hashlib.sha256(data).hexdigest()
    assert FULL_DIGEST_MAX_BYTES >= 64 << 20
    monkeypatch.setattr(bs, "FULL_DIGEST_MAX_BYTES", 1000)
    d = bs.file_digest(f)
    assert d.startswith(f"edges:{len(data)}:")
    _flip(f, len(data) // 2)  # the middle of a large file is not read: the mtime and edges are
    f.write_bytes(f.read_bytes())
    assert bs.file_digest(f).split(":")[3] == d.split(":")[3]


def test_the_step_list_is_checked():
    check_steps(STEPS)
    names = [s.name for s in STEPS]
    assert names[:2] == ["verify", "cameras"] and names.index("geometry") < names.index("write")

    def noop(ctx: BuildContext) -> None:
        pass

    from opacityhull.errors import InputError

    with pytest.raises(InputError, match="reads 'geometry', which no earlier step makes"):
        check_steps((Step(name="early", run=noop, inputs=("geometry",)), *STEPS))
    with pytest.raises(InputError, match="listed twice"):
        check_steps((*STEPS, STEPS[1]))
