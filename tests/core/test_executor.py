"""The executor interface (opacityhull.executor): serial, threads, processes and a real
2-worker Dask LocalCluster on 127.0.0.1 give bit-identical per-view mattes; an address
nobody answers on is a named InputError; a worker killed mid-map is retried, and one
that always dies is a clean WorkerLost, never a partial result."""

from __future__ import annotations

import os
import sys
import socket
import time

import numpy as np
import pytest

from opacityhull.errors import FormatError, InputError
from opacityhull.executor import WorkerLost, always_die, die_once, open_executor, parse_scheduler, worker_info

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    """2 worker processes, 1 thread each, on 127.0.0.1; the scheduler (in this process)
    gives up on a task after 1 worker death (default 3) so the always-dies test is quick."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        lc = LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None, silence_logs=40
        )
        try:
            yield lc.scheduler_address
        finally:
            lc.close()


@pytest.fixture(scope="module")
def pool():
    """One spawn process pool for the module: starting one (imports numpy, numba and the
    cached kernels in each worker) is the slow part, not the tasks."""
    with open_executor("processes", workers=2, retries=1) as ex:
        yield ex


@pytest.fixture
def executor(request, cluster, pool):
    """The executor named by the test's ``scheduler`` parameter."""
    name = request.node.callspec.params["scheduler"]
    if name == "processes":
        yield pool
    else:
        with open_executor(cluster if name == "cluster" else name, workers=2) as ex:
            yield ex


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from opacityhull.acquire.synthetic import SyntheticSessionConfig, write_synthetic_session

    root = tmp_path_factory.mktemp("exec") / "session"
    write_synthetic_session(
        root, SyntheticSessionConfig(n_cameras=2, n_table=3, width_px=48, height_px=36, noise=0.002, groundtruth=True)
    )
    return root


@pytest.fixture(scope="module")
def serial_alphas(session):
    from opacityhull.reconstruct.perview import matte_view, view_tasks

    tasks = view_tasks(session)
    with open_executor("serial") as ex:
        return tasks, ex.map(matte_view, tasks)


def test_parse_scheduler_names_the_bad_value():
    assert parse_scheduler("serial").kind == "serial"
    assert parse_scheduler("tcp://10.1.2.3:8786").address == "tcp://10.1.2.3:8786"
    for bad in ("dask", "tcp://host", "tcp://:8786", "tcp://h:99999", "Threads"):
        with pytest.raises(InputError, match="--scheduler"):
            parse_scheduler(bad)


def test_serial_matte_is_the_true_alpha(session, serial_alphas):
    """The reference itself is right: the synthetic session's true coverage alpha."""
    from opacityhull.imageio import read_exr

    tasks, alphas = serial_alphas
    assert len(alphas) == 6
    for t, a in zip(tasks, alphas, strict=True):
        true = read_exr(session / "groundtruth" / "alpha" / f"{t.view}.exr")[..., 0]
        assert a.shape == true.shape == (36, 48)
        assert np.abs(a - true).mean() < 0.01
        assert true.sum() > 20  # the sphere is in view


@pytest.mark.parametrize("scheduler", ["threads", "processes", "cluster"])
def test_schedulers_equal_serial_bit_for_bit(scheduler, executor, serial_alphas):
    from opacityhull.reconstruct.perview import matte_view

    tasks, ref = serial_alphas
    seen = []
    assert executor.n_workers == 2
    got = executor.map(matte_view, tasks, progress=lambda d, n: seen.append((d, n)))
    assert len(got) == len(ref)
    for a, b in zip(got, ref, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert seen[-1] == (len(tasks), len(tasks)) and len(seen) == len(tasks)
    # several views per task: the same results, in the same order
    seen.clear()
    got = executor.map(matte_view, tasks, chunksize=4, progress=lambda d, n: seen.append((d, n)))
    assert len(got) == len(ref) and all(np.array_equal(a, b) for a, b in zip(got, ref, strict=True))
    assert seen == [(4, 6), (6, 6)]  # items done, counted per finished chunk


@pytest.mark.parametrize("scheduler", ["processes", "cluster"])
def test_workers_run_one_numba_thread_and_are_other_processes(scheduler, executor):
    info = executor.map(worker_info, range(4))
    assert all(i["numba_threads"] == 1 for i in info)
    assert os.getpid() not in {i["pid"] for i in info}
    if scheduler == "cluster" and sys.platform.startswith("linux"):
        # the nanny's MALLOC_TRIM_THRESHOLD_ (adaptive mmap threshold off) is undone in
        # every worker by the executor's worker plugin (executor.tune_malloc)
        assert all(i["malloc_tuned"] for i in info), info


def test_tune_malloc_takes_on_glibc():
    from opacityhull.executor import tune_malloc

    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's mallopt")
    assert tune_malloc() is True and worker_info()["malloc_tuned"] is True


@pytest.mark.parametrize("scheduler", ["serial", "threads", "processes", "cluster"])
def test_task_errors_keep_their_type_and_message(scheduler, executor, session):
    """A view without matting images is corrupt data (FormatError naming the view), on
    every scheduler: the worker's exception is re-raised, not wrapped or swallowed."""
    from opacityhull.reconstruct.perview import ViewTask, matte_view

    tasks = [
        ViewTask(session_dir=str(session), camera=0, table_deg=0.0),
        ViewTask(session_dir=str(session), camera=1, table_deg=7.0),
    ]
    with pytest.raises(FormatError, match=r"c1_t007\.000"):
        executor.map(matte_view, tasks)


def test_unreachable_scheduler_is_a_named_input_error_within_the_timeout():
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    addr = f"tcp://127.0.0.1:{port}"
    t0 = time.monotonic()
    with pytest.raises(InputError, match=rf"--scheduler {addr}.*within 2 s"):
        open_executor(addr, timeout_s=2.0)
    # a hang guard, not a speed measurement: without the timeout the client waits forever
    assert time.monotonic() - t0 < 30.0


def test_lambdas_and_main_functions_are_refused_for_process_schedulers():
    with open_executor("processes", workers=1) as ex:
        with pytest.raises(InputError, match="module level"):
            ex.map(lambda x: x, [1])
        with pytest.raises(InputError, match="module level"):
            ex.map(lambda x: x, [1, 2, 3], chunksize=2)
        with pytest.raises(InputError, match="chunksize 0"):
            ex.map(worker_info, [1], chunksize=0)
    with open_executor("threads", workers=1) as ex:  # threads share the interpreter: fine
        assert ex.map(lambda x: 2 * x, [1, 2]) == [2, 4]


@pytest.mark.parametrize("scheduler", ["processes", "cluster"])
def test_worker_killed_mid_map_is_retried(scheduler, executor, tmp_path):
    """The first task SIGKILLs its own worker; the map still returns every result, in order."""
    marker = tmp_path / "died"
    items = [(str(marker), i) for i in range(6)]
    got = executor.map(die_once, items)
    assert marker.exists()  # a worker really died
    assert got == list(range(6))


def test_worker_that_always_dies_is_a_clean_error_processes():
    with (
        open_executor("processes", workers=1, retries=0) as ex,
        pytest.raises(WorkerLost, match=r"--scheduler processes: a worker process died.*always_die"),
    ):
        ex.map(always_die, [0, 1, 2])


def test_worker_that_always_dies_is_a_clean_error_cluster(cluster):
    with (
        open_executor(cluster) as ex,
        pytest.raises(WorkerLost, match=rf"--scheduler {cluster}: workers died.*always_die"),
    ):
        ex.map(always_die, [0])
