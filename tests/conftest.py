"""Suite-wide settings.

Small BLAS calls on OpenBLAS's spinning threads ran ~35x slower on the 2-core CI
machine when other work competed for the cores; one BLAS thread per process is faster
for every test here (the heavy kernels use numba or Dr.Jit threads, not BLAS). The
variables must be set before NumPy loads OpenBLAS, hence at conftest import time (the
Makefile sets them too).
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import pytest  # noqa: E402


@pytest.fixture(scope="session", autouse=True)
def _simcache_root(tmp_path_factory):
    """Root of tests/simcache.py for this run: ``<basetemp>/simcache`` (shared by the
    pytest-xdist workers, whose basetemps are siblings)."""
    import simcache

    base = tmp_path_factory.getbasetemp()
    if base.name.startswith("popen-gw"):
        base = base.parent
    return simcache.configure(base / "simcache")


@pytest.fixture(scope="session")
def sim_cache(_simcache_root):
    """The :mod:`simcache` module (``captured``, ``built``, ``report``), configured."""
    import simcache

    return simcache


@pytest.fixture(scope="session")
def dask_cluster():
    """Address of one 2-worker ``distributed.LocalCluster`` (1 thread each, on 127.0.0.1),
    shared by the tests that run build, LOO and render steps through ``--scheduler``;
    starting one is the slow part. (tests/core/test_executor.py keeps its own: it kills
    workers and needs ``allowed-failures = 1``.)"""
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    # dashboard_address=None (no dashboard) is accepted at runtime; distributed annotates it as str
    lc = LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,  # pyright: ignore[reportArgumentType]
        silence_logs=40,
    )
    try:
        yield lc.scheduler_address
    finally:
        lc.close()


def _prebuilds(items) -> list:
    """The distinct modules among ``items`` that define ``prebuild()`` (tests/background.py)."""
    mods = []
    for item in items:
        mod = getattr(item, "module", None)
        if mod is not None and callable(getattr(mod, "prebuild", None)) and mod not in mods:
            mods.append(mod)
    return mods


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """Modules with a ``prebuild()`` run last: their background jobs, started with the
    session, are done by then (tests/background.py)."""
    late = set(_prebuilds(items))
    if late:
        items[:] = [i for i in items if getattr(i, "module", None) not in late] + [
            i for i in items if getattr(i, "module", None) in late
        ]


@pytest.fixture(scope="session", autouse=True)
def _background_jobs(request, tmp_path_factory, _simcache_root):
    """Start the selected modules' ``prebuild()`` jobs when the session begins and stop
    what still runs when it ends. pytest-xdist workers do not prebuild (each would start
    every job): their fixtures start the jobs they need on demand."""
    import background
    import simcache

    background.configure(tmp_path_factory.getbasetemp() / "background")
    if "PYTEST_XDIST_WORKER" not in os.environ:
        for mod in _prebuilds(request.session.items):
            mod.prebuild()
        simcache.start_prefetch()
    try:
        yield
    finally:
        background.stop_all()
