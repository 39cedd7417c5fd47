"""``--scheduler`` on ``build`` and ``eval loo``: a build through local threads or a real
2-worker Dask LocalCluster on 127.0.0.1 equals the serial build bit for bit (matting is
per view and deterministic; every later step runs in the calling process on the same
alphas), and so does the geometry-holdout LOO whose rebuilds run on the cluster. An
address nobody answers on is a named error (exit 2) for build, eval loo and render."""

from __future__ import annotations

import socket

import numpy as np
import pytest

import rcsynth
from opacityhull.executor import open_executor
from opacityhull.model import OpacityHullModel
from opacityhull.reconstruct.build import BuildConfig, build_model

distributed = pytest.importorskip("distributed")

CFG = BuildConfig(hull_res=32, pictures=False)


@pytest.fixture(scope="module")
def cluster(dask_cluster):
    return dask_cluster


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """``(session_dir, model_dir)`` of one build run serially (the reference)."""
    session, out, rep = rcsynth.built_sphere(tmp_path_factory, "sched", CFG, reflectance=True, seed=12)
    assert rep.scheduler == "serial"
    return session, out


@pytest.fixture(scope="module")
def session(built):
    return built[0]


@pytest.fixture(scope="module")
def serial_model(built):
    return built[1]


def assert_same_model(a, b):
    ma, mb = OpacityHullModel.open(a), OpacityHullModel.open(b)
    assert [v.id for v in ma.views] == [v.id for v in mb.views]
    np.testing.assert_array_equal(ma.surfels.positions, mb.surfels.positions)
    np.testing.assert_array_equal(ma.surfels.normals, mb.surfels.normals)
    np.testing.assert_array_equal(ma.surfels.visible_bool(), mb.surfels.visible_bool())
    for i in range(len(ma.views)):
        np.testing.assert_array_equal(ma.load_view_rgba(i), mb.load_view_rgba(i))
    assert ma.light_samples == mb.light_samples and len(ma.light_samples) > 0
    ra, rb = ma.load_reflectance(0), mb.load_reflectance(0)
    assert sorted(ra) == sorted(rb)
    for key in ra:
        np.testing.assert_array_equal(ra[key], rb[key])


@pytest.mark.parametrize("scheduler", ["threads", "cluster"])
def test_build_through_a_scheduler_equals_the_serial_build_bit_for_bit(
    scheduler, cluster, session, serial_model, tmp_path
):
    out = tmp_path / "model"
    with open_executor(cluster if scheduler == "cluster" else scheduler, workers=2) as ex:
        rep = build_model(session, out, config=CFG, executor=ex)
    assert rep.scheduler == ex.scheduler
    assert rep.steps["matting"] == "ran"
    assert_same_model(out, serial_model)
    # the workers wrote the per-view mattes into the model's build folder
    assert len(list((out / "build" / "mattes").glob("*.npy"))) == len(OpacityHullModel.open(out).views)


def test_geometry_holdout_through_the_cluster_equals_serial(cluster, serial_model, tmp_path):
    from opacityhull.evaluate.holdout import run_loo_holdouts

    a = run_loo_holdouts(serial_model, views="every:3", holdout="geometry", out=tmp_path / "serial")
    with open_executor(cluster) as ex:
        b = run_loo_holdouts(serial_model, views="every:3", holdout="geometry", out=tmp_path / "cluster", executor=ex)
    assert [r["view"] for r in a["per_view"]] == [r["view"] for r in b["per_view"]]
    assert len(a["per_view"]) == 4
    for ra, rb in zip(a["per_view"], b["per_view"], strict=True):
        assert ra["surfels"] == rb["surfels"]
        assert ra["psnr"] == rb["psnr"] and ra["ssim"] == rb["ssim"]


def _dead_address() -> str:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        return f"tcp://127.0.0.1:{s.getsockname()[1]}"


def _invoke(argv):
    from typer.testing import CliRunner

    from opacityhull.cli import app, normalize_argv

    return CliRunner().invoke(app, normalize_argv([str(a) for a in argv]), env={"COLUMNS": "4000"})


@pytest.mark.parametrize("command", ["build", "loo", "render"])
def test_an_address_that_does_not_answer_is_a_named_error(command, session, serial_model, tmp_path):
    addr = _dead_address()
    opts = ["--scheduler", addr, "--scheduler-timeout", "1.5"]
    argv = {
        "build": ["build", session, "--out", tmp_path / "m", *opts],
        "loo": ["eval", "loo", serial_model, "--holdout", "geometry", "--out", tmp_path / "loo", *opts],
        "render": ["render", serial_model, "--out", tmp_path / "r.png", *opts],
    }[command]
    res = _invoke(argv)
    text = " ".join(res.stderr.split())
    assert res.exit_code == 2, res.output
    assert f"--scheduler {addr}: no dask scheduler answered within 1.5 s" in text
    assert "Traceback" not in res.output
    assert not (tmp_path / "m" / "model.toml").exists() and not (tmp_path / "r.png").exists()


@pytest.mark.parametrize("command", ["build", "loo", "render"])
def test_a_malformed_scheduler_is_named(command, session, serial_model, tmp_path):
    argv = {
        "build": ["build", session, "--out", tmp_path / "m"],
        "loo": ["eval", "loo", serial_model, "--out", tmp_path / "loo"],
        "render": ["render", serial_model, "--out", tmp_path / "r.png"],
    }[command]
    res = _invoke([*argv, "--scheduler", "tcp://nohost"])
    assert res.exit_code == 2, res.output
    assert "--scheduler 'tcp://nohost': expected serial, threads, processes or tcp://HOST:PORT" in " ".join(
        res.stderr.split()
    )
    assert not (tmp_path / "m").exists()


def test_a_scheduler_with_nothing_to_distribute_is_refused_not_ignored(serial_model, tmp_path):
    res = _invoke(
        ["eval", "loo", serial_model, "--holdout", "blend", "--out", tmp_path / "loo", "--scheduler", "threads"]
    )
    assert res.exit_code == 2, res.output
    assert "--scheduler threads: with --holdout blend there is no per-view rebuild" in " ".join(res.stderr.split())
    assert not (tmp_path / "loo").exists()


def test_loo_progress_names_each_holdout_on_a_pipe(serial_model, tmp_path):
    """Off a terminal (here: the test runner's pipe) rich draws no live bar, so ``eval
    loo --holdout both`` prints one line per finished holdout and its total; before, the
    two holdouts shared one bar, whose elapsed time froze when the first was complete."""
    res = _invoke(["eval", "loo", serial_model, "--holdout", "both", "--views", "0,3", "--out", tmp_path / "loo"])
    assert res.exit_code == 0, res.output
    err = " ".join(res.stderr.split())
    blend, geometry = (
        err.find("leave-one-out: blend holdout done in "),
        err.find("leave-one-out: geometry holdout done in "),
    )
    assert 0 <= blend < geometry < err.find("leave-one-out: done in ")
