"""``build_model`` as a chain of named steps on disk (``MODEL/build/manifest.json``):
``resume`` reuses every step whose inputs and parameters are unchanged, redoes only
what is stale (down to single views of the matting step), a build interrupted after a
step resumes without redoing it, and what was reused is in the report. Checked through
the manifest, the report and a count of matting solves, never through time."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import rcsynth
from opacityhull.errors import FormatError
from opacityhull.model import OpacityHullModel
from opacityhull.reconstruct.steps import write as build_mod  # the write step calls write_model
from opacityhull.reconstruct.build import BuildConfig, build_model

CFG = BuildConfig(hull_res=32, pictures=False)
V = 12  # 3 cameras x 4 table angles


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    return rcsynth.built_sphere(tmp_path_factory, "steps", CFG, reflectance=False, seed=11)


@pytest.fixture(scope="module")
def session(built):
    return built[0]


@pytest.fixture(scope="module")
def reference(built):
    """One uninterrupted build, the model every resumed build must equal."""
    return built[1], built[2]


@pytest.fixture
def solves(monkeypatch):
    """Counts triangulation-matting solves (one per view matted)."""
    n = {"calls": 0}
    from opacityhull.reconstruct import matte_step

    real = matte_step.solve_matte

    def counting(*a, **k):
        n["calls"] += 1
        return real(*a, **k)

    monkeypatch.setattr(matte_step, "solve_matte", counting)
    return n


class Stop(Exception):
    pass


def stop_at(name):
    def on_step(step):
        if step == name:
            raise Stop(step)

    return on_step


def assert_same_model(a, b):
    ma, mb = OpacityHullModel.open(a), OpacityHullModel.open(b)
    assert [v.id for v in ma.views] == [v.id for v in mb.views]
    np.testing.assert_array_equal(ma.surfels.positions, mb.surfels.positions)
    np.testing.assert_array_equal(ma.surfels.visible_bool(), mb.surfels.visible_bool())
    for i in range(len(ma.views)):
        np.testing.assert_array_equal(ma.load_view_rgba(i), mb.load_view_rgba(i))


def manifest(out):
    return json.loads((out / "build" / "manifest.json").read_text())


def test_fresh_build_records_every_step_and_reports_it_ran(reference):
    out, rep = reference
    steps = manifest(out)["steps"]
    assert {"cameras", "matting", "geometry", "write"} <= set(steps)
    assert set(rep.steps.values()) == {"ran"}
    # the manifest names the inputs: one key per view of the matting step
    assert len(steps["matting"]["inputs"]["views"]) == V
    assert steps["geometry"]["params"]["hull_res"] == 32
    assert (out / "model.toml").is_file()


def test_interrupted_after_matting_resumes_without_matting_again(session, reference, tmp_path, solves):
    out = tmp_path / "model"
    with pytest.raises(Stop):
        build_model(session, out, config=CFG, on_step=stop_at("silhouettes"))
    assert solves["calls"] == V
    assert not (out / "model.toml").exists()  # an interrupted build never looks finished
    assert set(manifest(out)["steps"]) == {"cameras", "matting"}
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG, resume=True)
    assert solves["calls"] == 0
    assert rep.steps["cameras"] == "reused" and rep.steps["matting"] == "reused"
    assert rep.steps["geometry"] == "ran" and rep.steps["write"] == "ran"
    assert rep.summary()["steps"] == rep.steps
    assert_same_model(out, reference[0])


def test_interrupted_while_writing_leaves_no_model_toml_and_resumes_the_write(session, reference, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    assert (out / "model.toml").is_file()

    # a later build changes a geometry option and is stopped inside write_model: the old
    # model.toml must not survive next to half-rewritten views
    def boom(*a, **k):
        raise Stop("write")

    real = build_mod.write_model
    build_mod.write_model = boom
    try:
        with pytest.raises(Stop):
            build_model(
                session, out, config=BuildConfig(hull_res=32, pictures=False, alpha_threshold=0.45), resume=True
            )
    finally:
        build_mod.write_model = real
    assert not (out / "model.toml").exists()
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG, resume=True)
    assert solves["calls"] == 0
    # the rewritten model is the first build's again (same key), so its fit (the default
    # --optimize fast), untouched by the interrupted build, is reused
    assert rep.steps == {
        "cameras": "reused",
        "matting": "reused",
        "geometry": "ran",
        "write": "ran",
        "optimize": "reused",
    }
    assert_same_model(out, reference[0])


def test_resume_of_a_finished_build_reuses_everything(session, reference, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG, resume=True)
    assert solves["calls"] == 0
    assert set(rep.steps.values()) == {"reused"}
    assert rep.surfels == reference[1].surfels
    assert_same_model(out, reference[0])


def test_a_changed_parameter_redoes_only_the_steps_it_feeds(session, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    solves["calls"] = 0
    rep = build_model(session, out, config=BuildConfig(hull_res=28, pictures=False), resume=True)
    assert solves["calls"] == 0
    assert rep.steps["matting"] == "reused" and rep.steps["geometry"] == "ran"
    assert manifest(out)["steps"]["geometry"]["params"]["hull_res"] == 28
    from opacityhull.reconstruct.matting import MattingOptions

    rep = build_model(
        session,
        out,
        config=BuildConfig(hull_res=28, pictures=False, matting=MattingOptions(max_alpha_std=0.04)),
        resume=True,
    )
    assert solves["calls"] == V
    assert rep.steps["cameras"] == "reused" and rep.steps["matting"] == "ran" and rep.steps["geometry"] == "ran"


def test_without_resume_everything_runs_again(session, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG)
    assert solves["calls"] == V
    assert set(rep.steps.values()) == {"ran"}


def test_only_the_views_whose_images_changed_or_were_unfinished_are_matted_again(session, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    # one view killed between its alpha and its sidecar; one view's image touched
    mattes = sorted((out / "build" / "mattes").glob("*.json"))
    assert len(mattes) == V
    mattes[0].unlink()
    from opacityhull.session import Session

    s = Session.open(session)
    touched = s.select(phase="matting", kind=None, camera=2)[0]
    st = os.stat(session / touched.path)
    os.utime(session / touched.path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG, resume=True)
    assert solves["calls"] == 2
    assert rep.steps["matting"] == f"reused {V - 2} of {V} views"
    # the touched image's bytes are the same, so the mattes (and all below) are the same
    assert rep.steps["geometry"] == "reused"


def test_a_corrupt_step_manifest_is_named(session, tmp_path):
    out = tmp_path / "model"
    (out / "build").mkdir(parents=True)
    (out / "build" / "manifest.json").write_text("{not json")
    with pytest.raises(FormatError, match=r"manifest\.json: unreadable build manifest.*without --resume"):
        build_model(session, out, config=CFG, resume=True)
    (out / "build" / "manifest.json").write_text('{"format": "other/9", "steps": {}}')
    with pytest.raises(FormatError, match=r"not an opacityhull\.build/1 manifest"):
        build_model(session, out, config=CFG, resume=True)


def test_an_unreadable_step_product_is_rebuilt_not_trusted(session, reference, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    (out / "build" / "geometry.pkl").write_bytes(b"\x80\x05garbage")
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG, resume=True)
    assert rep.steps["geometry"] == "ran" and rep.steps["matting"] == "reused"
    assert_same_model(out, reference[0])


def test_a_build_can_take_an_open_session(session, reference, tmp_path):
    from opacityhull.session import Session

    out = tmp_path / "model"
    build_model(Session.open(session), out, config=CFG)
    assert_same_model(out, reference[0])


def test_a_matte_whose_bytes_no_longer_match_its_sidecar_is_matted_again(session, reference, tmp_path, solves):
    out = tmp_path / "model"
    build_model(session, out, config=CFG)
    first = sorted((out / "build" / "mattes").glob("*.npy"))[0]
    a = np.load(first)
    np.save(first, np.zeros_like(a))  # torn by a power loss, or edited by hand
    solves["calls"] = 0
    rep = build_model(session, out, config=CFG, resume=True)
    assert solves["calls"] == 1
    assert rep.steps["matting"] == f"reused {V - 1} of {V} views"
    np.testing.assert_array_equal(np.load(first), a)
    assert rep.steps["geometry"] == "reused"  # the matte came out as before
    assert_same_model(out, reference[0])
