"""``render --scheduler``: an orbit rendered through local threads or a real 2-worker Dask
LocalCluster on 127.0.0.1 equals the serial orbit bit for bit (every frame is rendered
whole by one worker with the same deterministic kernels; only which process renders it
changes): the float EXR frames, the splat counts under a budget, and the GIF."""

from __future__ import annotations

import os

import numpy as np
import pytest

from opacityhull.executor import open_executor
from opacityhull.imageio import read_exr
from opacityhull.render import runner
from opacityhull.render.config import RenderConfig
from opacityhull.render.runner import FrameTask, render_frames, run_render
from opacityhull.render.synthetic import write_sphere_model

distributed = pytest.importorskip("distributed")

FRAMES = 5


@pytest.fixture(scope="module")
def cluster(dask_cluster):
    return dask_cluster


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    """1500 surfels, 24 views of 32x24 px: an orbit frame renders in milliseconds."""
    root, _ = write_sphere_model(
        tmp_path_factory.mktemp("rsched") / "sphere", n_surfels=1500, width=32, height=24, table_step_deg=45.0
    )
    return root


def _orbit(model, out, executor=None, **kw):
    return run_render(model, out, orbit=FRAMES, background="grey", executor=executor, **kw)


@pytest.fixture(scope="module")
def serial_orbit(tiny_model, tmp_path_factory):
    out = tmp_path_factory.mktemp("rsched_serial") / "orbit.exr"
    return _orbit(tiny_model, out, budget=600)


def assert_same_orbit(a: dict, b: dict):
    assert a["frames"] == b["frames"] == FRAMES
    assert [os.path.basename(p) for p in a["paths"]] == [os.path.basename(p) for p in b["paths"]]
    for pa, pb in zip(a["paths"], b["paths"], strict=True):
        fa, fb = read_exr(pa), read_exr(pb)
        assert fa.shape == (24, 32, 3) and float(fa.max()) > 0.05  # a composited, non-empty frame
        np.testing.assert_array_equal(fa, fb)
    assert a["splats_per_frame"] == b["splats_per_frame"]
    assert max(a["splats_per_frame"]) <= 600 < a["surfels"]  # the budget cut really ran in the workers
    assert a["lod_tau"] == b["lod_tau"]
    with open(a["gif"], "rb") as ga, open(b["gif"], "rb") as gb:
        assert ga.read() == gb.read()


@pytest.mark.parametrize("scheduler", ["threads", "cluster"])
def test_an_orbit_through_a_scheduler_equals_the_serial_orbit_bit_for_bit(
    scheduler, cluster, tiny_model, serial_orbit, tmp_path
):
    with open_executor(cluster if scheduler == "cluster" else scheduler, workers=2) as ex:
        done = []
        s = _orbit(
            tiny_model, tmp_path / "orbit.exr", executor=ex, budget=600, progress=lambda d, n: done.append((d, n))
        )
        assert s["scheduler"] == ex.scheduler
        # 5 frames on 2 slots: chunks of 2, 2, 1 frames, progress counted in frames
        assert done[-1] == (FRAMES, FRAMES) and len(done) == 3
    assert_same_orbit(serial_orbit, s)


def test_a_worker_opens_the_model_once_and_again_when_it_is_rebuilt(tiny_model, tmp_path):
    from opacityhull.render.cameras import orbit_cameras
    from opacityhull.model import OpacityHullModel

    runner._STATE.clear()
    m = OpacityHullModel.open(tiny_model)
    cams = orbit_cameras([v.camera for v in m.views], 2, width=16, height=12)

    def task(tag):
        return FrameTask(
            model_path=str(tiny_model),
            cameras=cams,
            config=RenderConfig(),
            exclude=[],
            budget=None,
            paths=[str(tmp_path / f"{tag}_{i}.png") for i in range(2)],
        )

    a = render_frames(task("a"))
    b = render_frames(task("b"))
    assert a["ms_load"] > 0 and b["ms_load"] == 0.0  # the second task reused the open model
    assert a["gif"] == [] and len(a["ms"]) == 2 and (tmp_path / "b_1.png").exists()
    st = next(iter(runner._STATE.values()))
    toml = tiny_model / "model.toml"
    os.utime(toml, ns=(toml.stat().st_atime_ns, toml.stat().st_mtime_ns + 10**9))  # "rebuilt"
    c = render_frames(task("c"))
    assert c["ms_load"] > 0 and next(iter(runner._STATE.values())) is not st and len(runner._STATE) == 1
    runner._STATE.clear()


def test_render_cli_with_threads_writes_the_same_orbit_as_serial(tiny_model, tmp_path):
    import json

    from typer.testing import CliRunner

    from opacityhull.cli import app, normalize_argv

    def cli(out, scheduler):
        argv = [
            "render",
            str(tiny_model),
            "--out",
            str(out),
            "--orbit",
            "3",
            "--background",
            "grey",
            "--json",
            "--scheduler",
            scheduler,
        ]
        res = CliRunner().invoke(app, normalize_argv(argv), env={"COLUMNS": "4000"})
        assert res.exit_code == 0, res.output
        return json.loads(res.stdout)

    a = cli(tmp_path / "s" / "o.exr", "serial")
    b = cli(tmp_path / "t" / "o.exr", "threads")
    assert a["scheduler"] == "serial" and b["scheduler"] == "threads"
    for pa, pb in zip(a["paths"], b["paths"], strict=True):
        np.testing.assert_array_equal(read_exr(pa), read_exr(pb))
    assert (tmp_path / "t" / "o.gif").exists()
