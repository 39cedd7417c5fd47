"""One small executor interface for per-view and per-tile work: serial, local threads,
local processes, or a Dask distributed cluster.

``open_executor(scheduler)`` takes the value of ``--scheduler``:

- ``serial`` (the default): in the calling thread, no set-up; the reference the others
  must equal bit for bit.
- ``threads``: a local :class:`concurrent.futures.ThreadPoolExecutor`. Useful only when
  the work releases the GIL (the ``nogil`` numba kernels, EXR codecs).
- ``processes``: a local :class:`concurrent.futures.ProcessPoolExecutor` started with
  ``spawn`` (a ``fork`` after numba's threading layer or OpenBLAS started can deadlock).
- ``tcp://HOST:PORT``: a :class:`dask.distributed.Client` of a running scheduler (see
  ``docs/distributed.md``). Workers read the session and write the model through a path
  they all see, so tasks send paths, not pixels, wherever they can.

Every executor's :meth:`Executor.map` returns the results in the order of the items, or
raises; it never returns part of them. An exception raised by the task is re-raised as
is (an :class:`~opacityhull.errors.InputError` from view 17 stays one). A worker that
dies (killed, out of memory, segfault) is retried: the process pool is restarted and
the unfinished items resubmitted, up to ``retries`` times; Dask reschedules the task on
another worker by itself (up to the scheduler's ``distributed.scheduler.allowed-failures``,
default 3). Past that the map raises :class:`WorkerLost` naming the scheduler and item.

Numba and workers (pitfalls met while building this):

- The task function must be importable by module path in the worker (module level in
  ``opacityhull``): ``spawn`` workers cannot unpickle a ``__main__`` function at all, and
  Dask's cloudpickle ships one *by value*, so a numba dispatcher it closes over is a new
  object in every task and recompiles every time (seconds per task). :meth:`Executor.map`
  refuses ``__main__`` functions and lambdas for the process-based schedulers.
- ``@njit(cache=True)`` kernels load from the on-disk cache in each worker on the first
  call (once per worker process, not per task: workers are long-lived); the cache lives
  beside the package, so every machine needs the same installed version (a different
  source file invalidates it, and a read-only install compiles in memory per worker).
- ``parallel=True`` kernels start ``NUMBA_NUM_THREADS`` threads (= cores) in *every*
  worker: two workers on two cores then run four threads and lose to serial. Workers
  here set numba to ``numba_threads`` threads (default 1) at start; for an external
  cluster this is done by a worker plugin, which also reaches workers that join later.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Iterable, Sequence

from .errors import DeviceError, InputError

log = logging.getLogger(__name__)

__all__ = ["Executor", "WorkerLost", "open_executor", "parse_scheduler", "SCHEDULERS"]

#: The local scheduler names; anything else must be a ``tcp://HOST:PORT`` address.
SCHEDULERS = ("serial", "threads", "processes")

Progress = Callable[[int, int], None]


class WorkerLost(DeviceError):
    """A worker process died while running a task (killed, out of memory, crashed) more
    often than the retries allow. Exit code 3, like a device that stopped answering:
    the inputs are fine, re-running may succeed."""


@dataclass(frozen=True, kw_only=True)
class SchedulerSpec:
    """A parsed ``--scheduler`` value: ``kind`` in serial|threads|processes|tcp and, for
    tcp, the ``address`` (``tcp://HOST:PORT``)."""

    kind: str
    address: str | None = None


def parse_scheduler(scheduler: str) -> SchedulerSpec:
    """Check a ``--scheduler`` value; ``InputError`` naming it when it is none of
    ``serial``, ``threads``, ``processes``, ``tcp://HOST:PORT``."""
    s = str(scheduler).strip()
    if s in SCHEDULERS:
        return SchedulerSpec(kind=s)
    if s.startswith("tcp://"):
        rest = s[len("tcp://") :]
        host, sep, port = rest.rpartition(":")
        if sep and host and port.isdigit() and 0 < int(port) < 65536:
            return SchedulerSpec(kind="tcp", address=s)
    raise InputError(
        f"--scheduler {scheduler!r}: expected serial, threads, processes or tcp://HOST:PORT "
        "(a dask scheduler's address)"
    )


def _check_shippable(fn: Callable, scheduler: str) -> None:
    mod = getattr(fn, "__module__", None)
    name = getattr(fn, "__qualname__", repr(fn))
    if mod == "__main__" or "<lambda>" in name or "<locals>" in name:
        raise InputError(
            f"--scheduler {scheduler}: task {mod}.{name} is not importable by module path in a "
            "worker (a __main__, lambda or nested function); define it at module level in a module "
            "the workers can import (numba kernels would otherwise recompile in every task)"
        )


def numba_max_threads() -> int:
    """The size of numba's thread pool in this process (``NUMBA_NUM_THREADS``, fixed when
    numba is imported): the most :func:`numba.set_num_threads` accepts."""
    from numba.core import config as numba_config

    # set at import from the environment, so not a declared attribute of the module
    return int(getattr(numba_config, "NUMBA_NUM_THREADS"))  # noqa: B009  set at runtime: pyright cannot see it


def set_numba_threads(n: int | None) -> None:
    """Limit numba's thread pool in this process (a worker) to ``n`` threads (None: leave)."""
    if n is None:
        return
    os.environ["NUMBA_NUM_THREADS"] = str(int(n))
    try:
        import numba

        numba.set_num_threads(max(1, min(int(n), numba_max_threads())))
    except (
        ImportError,
        ValueError,
        RuntimeError,
    ) as e:  # numba missing or its pool already fixed: only slower, never wrong
        log.debug("could not set numba threads to %s: %s", n, e)


#: glibc ``mallopt`` parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: whether :func:`tune_malloc` took effect in this process (reported by :func:`worker_info`)
_malloc_tuned = False


def tune_malloc() -> bool:
    """Undo what a Dask nanny's ``MALLOC_TRIM_THRESHOLD_=65536`` (its default
    ``distributed.nanny.pre-spawn-environ``) does to this process: setting any malloc
    threshold switches glibc's adaptive mmap threshold off, so every array over 128 kB
    is a fresh ``mmap`` whose pages fault in on first touch, and freed memory goes back to
    the OS at once. Per-view work allocates many image-sized arrays: measured on 640x480
    matting, 128 ms of CPU per view in a worker against 78 ms in a plain process. Here:
    arrays up to 32 MB from the heap again (glibc's largest mmap threshold), and trimming
    only past 256 MB free. True if glibc took both; False elsewhere (nothing changes)."""
    import ctypes
    import ctypes.util

    global _malloc_tuned
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = bool(libc.mallopt(_M_MMAP_THRESHOLD, 32 * 2**20)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 256 * 2**20))
        _malloc_tuned = _malloc_tuned or ok
        return ok
    except (OSError, AttributeError) as e:  # not glibc: its allocator has no such switch
        log.debug("mallopt not available: %s", e)
        return False


class Executor:
    """Ordered ``map`` over items, and ``close``. Use as a context manager.

    Attributes
    ----------
    scheduler : the ``--scheduler`` value it was opened with.
    n_workers : parallel slots (1 for serial).
    """

    scheduler: str = "serial"
    n_workers: int = 1

    def map(
        self, fn: Callable[[Any], Any], items: Iterable[Any], *, progress: Progress | None = None, chunksize: int = 1
    ) -> list:
        """``[fn(x) for x in items]``, in item order; ``progress(done, total)`` as tasks finish.

        ``chunksize`` items go to a worker as one task: use it when one item costs about
        as much as the scheduler's per-task overhead (a few ms on Dask)."""
        items = list(items)
        cs = int(chunksize)
        if cs < 1:
            raise InputError(f"chunksize {chunksize}: expected an integer >= 1")
        if cs == 1 or len(items) <= 1:
            return self._map(fn, items, progress=progress)
        if self.scheduler not in ("serial", "threads"):
            _check_shippable(fn, self.scheduler)
        chunks = [(fn, items[i : i + cs]) for i in range(0, len(items), cs)]
        n = len(items)
        prog = None if progress is None else (lambda done, total: progress(min(done * cs, n), n))
        return [y for part in self._map(apply_chunk, chunks, progress=prog) for y in part]

    def _map(self, fn, items: list, *, progress: Progress | None = None) -> list:
        raise NotImplementedError

    def close(self) -> None:
        """Release the workers (a no-op for serial); idempotent."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.scheduler} x{self.n_workers}>"


class SerialExecutor(Executor):
    def _map(self, fn, items, *, progress=None):
        out = []
        for i, x in enumerate(items):
            out.append(fn(x))
            if progress:
                progress(i + 1, len(items))
        return out


class _PoolExecutor(Executor):
    """Threads or spawn processes via concurrent.futures; a broken process pool (a worker
    died) is restarted and its unfinished items resubmitted up to ``retries`` times."""

    def __init__(self, kind: str, *, workers: int | None, retries: int, numba_threads: int | None):
        self.scheduler = kind
        # 0 is not "the default": `or` took --workers 0 for the core count
        self.n_workers = int(os.cpu_count() or 1) if workers is None else int(workers)
        if self.n_workers < 1:
            raise InputError(f"--workers {workers}: expected at least 1")
        self.retries = int(retries)
        self.numba_threads = numba_threads
        self._pool = None

    def _new_pool(self):
        if self.scheduler == "threads":
            return cf.ThreadPoolExecutor(max_workers=self.n_workers, thread_name_prefix="opacityhull")
        import multiprocessing as mp

        return cf.ProcessPoolExecutor(
            max_workers=self.n_workers,
            mp_context=mp.get_context("spawn"),
            initializer=set_numba_threads,
            initargs=(self.numba_threads,),
        )

    def _map(self, fn, items, *, progress=None):
        if self.scheduler == "processes":
            _check_shippable(fn, self.scheduler)
        n = len(items)
        results: dict[int, Any] = {}
        attempts = 0
        while len(results) < n:
            if self._pool is None:
                self._pool = self._new_pool()
            todo = [i for i in range(n) if i not in results]
            futs = {}
            broken_at = None
            try:
                for i in todo:
                    futs[self._pool.submit(fn, items[i])] = i
            except BrokenProcessPool:  # a worker died while the rest were being queued
                broken_at = i
            try:
                for f in cf.as_completed(futs):
                    i = futs[f]
                    try:
                        results[i] = f.result()
                    except BrokenProcessPool:
                        broken_at = i if broken_at is None else broken_at
                        continue
                    if progress:
                        progress(len(results), n)
            except BaseException:
                for f in futs:
                    f.cancel()
                raise
            if broken_at is None:
                continue
            # every worker of a broken pool is gone; start a fresh one for what is left
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            attempts += 1
            left = n - len(results)
            if attempts > self.retries:
                raise WorkerLost(
                    f"--scheduler {self.scheduler}: a worker process died while running "
                    f"{fn.__module__}.{fn.__qualname__} (first unfinished item {broken_at}: "
                    f"{items[broken_at]!r}); {left} of {n} item(s) unfinished after "
                    f"{self.retries} restart(s) (out of memory? check dmesg)"
                )
            log.warning(
                "scheduler %s: a worker died (item %d); restarting the pool for %d item(s), retry %d/%d",
                self.scheduler,
                broken_at,
                left,
                attempts,
                self.retries,
            )
        return [results[i] for i in range(n)]

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(Executor):
    """A ``dask.distributed.Client`` of the scheduler at ``address``."""

    def __init__(self, address: str, *, timeout_s: float, numba_threads: int | None):
        try:
            from distributed import Client
        except ImportError as e:  # pragma: no cover - dask is a dependency
            raise InputError(
                f"--scheduler {address}: dask.distributed is not installed ({e}); pip install 'dask[distributed]'"
            ) from e
        self.scheduler = address
        self.client: Any = None
        try:
            self.client = Client(address, timeout=f"{float(timeout_s)}s", set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise InputError(
                f"--scheduler {address}: no dask scheduler answered within {timeout_s:g} s ({e}); "
                "start one with `dask scheduler` (see docs/distributed.md) or use --scheduler "
                "serial|threads|processes"
            ) from None
        self.n_workers = max(
            1, sum(w.get("nthreads", 1) for w in self.client.scheduler_info(n_workers=-1).get("workers", {}).values())
        )
        try:
            if NumbaThreads is not None:
                self.client.register_plugin(NumbaThreads(numba_threads), name="opacityhull-numba-threads")
        except Exception as e:  # noqa: BLE001  a remote worker may fail in any way (old Dask, no plugin support): slower, never wrong
            log.warning("--scheduler %s: could not set up the workers (numba threads, malloc): %s", address, e)

    def _map(self, fn, items, *, progress=None):
        from distributed import as_completed
        from distributed.client import FutureCancelledError
        from distributed.scheduler import KilledWorker

        _check_shippable(fn, self.scheduler)
        n = len(items)
        # pure=False: identical items (a view matted twice on purpose) are still two tasks
        futs = self.client.map(fn, items, pure=False)
        done = 0
        try:
            for f in as_completed(futs, loop=self.client.loop):
                if f.status == "error":
                    f.result()  # re-raises the task's own exception (or KilledWorker)
                done += 1
                if progress:
                    progress(done, n)
            return self.client.gather(futs)
        except KilledWorker as e:
            raise WorkerLost(
                f"--scheduler {self.scheduler}: workers died while running {fn.__module__}."
                f"{fn.__qualname__} (dask gave up after distributed.scheduler.allowed-failures "
                f"retries): {e}"
            ) from None
        except (FutureCancelledError, OSError) as e:
            raise WorkerLost(
                f"--scheduler {self.scheduler}: lost the scheduler or the tasks while running "
                f"{fn.__module__}.{fn.__qualname__}: {e}"
            ) from None
        finally:
            pending = [f for f in futs if not f.done()]
            if pending:
                self.client.cancel(pending)

    def close(self):
        c = getattr(self, "client", None)
        if c is not None:
            try:
                c.close(timeout=10)
            finally:
                self.client = None


def _make_numba_plugin_class():
    try:
        from distributed.diagnostics.plugin import WorkerPlugin
    except ImportError:  # pragma: no cover
        return None

    class NumbaThreads(WorkerPlugin):
        """Sets numba's thread count (None: leave it) and undoes the nanny's malloc
        setting (:func:`tune_malloc`) in each worker, also workers that join later."""

        name = "opacityhull-numba-threads"

        def __init__(self, n: int | None):
            self.n = None if n is None else int(n)

        def setup(self, worker):
            set_numba_threads(self.n)
            tune_malloc()

    NumbaThreads.__module__ = __name__
    return NumbaThreads


def open_executor(
    scheduler: str = "serial",
    *,
    workers: int | None = None,
    timeout_s: float = 10.0,
    retries: int = 2,
    numba_threads: int | None = 1,
) -> Executor:
    """The executor of a ``--scheduler`` value.

    Parameters
    ----------
    scheduler : ``serial`` | ``threads`` | ``processes`` | ``tcp://HOST:PORT``.
    workers : local pool size (threads/processes); default the number of cores.
    timeout_s : how long to wait for a ``tcp://`` scheduler to answer; past it an
        ``InputError`` names the address.
    retries : local process pool restarts after a worker died (Dask: the scheduler's
        ``allowed-failures`` governs).
    numba_threads : numba threads per worker process (processes, tcp), None = numba's
        default (one per core, which oversubscribes when workers share a machine).

    Returns
    -------
    Executor (close it, or use ``with``).
    """
    spec = parse_scheduler(scheduler)
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: expected at least 1 (leave it out for one per core)")
    if spec.kind == "serial":
        return SerialExecutor()
    if spec.kind in ("threads", "processes"):
        return _PoolExecutor(spec.kind, workers=workers, retries=retries, numba_threads=numba_threads)
    if not (timeout_s > 0):
        raise InputError(f"--scheduler-timeout {timeout_s}: expected a positive number of seconds")
    return DaskExecutor(str(spec.address), timeout_s=timeout_s, numba_threads=numba_threads)


# ---- module-level tasks (importable in workers) used by the tests and benchmarks


def apply_chunk(args: tuple) -> list:
    """``(fn, items)`` -> ``[fn(x) for x in items]``: one task for a chunk of items."""
    fn, items = args
    return [fn(x) for x in items]


def worker_info(_item: Any = None) -> dict:
    """Where a task ran: pid, numba's thread count there, and whether its malloc was
    tuned (:func:`tune_malloc`; Dask workers)."""
    try:
        import numba

        nthreads = int(numba.get_num_threads())
    except ImportError:  # pragma: no cover
        nthreads = -1
    return {"pid": os.getpid(), "numba_threads": nthreads, "malloc_tuned": _malloc_tuned}


def die_once(item: Sequence) -> Any:
    """``item = (marker_path, value)``: the first task to find no file at ``marker_path``
    creates it and kills its own worker process (SIGKILL, as the OOM killer would);
    every other call returns ``value``. For testing the retry of a worker lost mid-map."""
    marker, value = item
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return value
    os.close(fd)
    import signal

    os.kill(os.getpid(), signal.SIGKILL)
    return value  # pragma: no cover


def always_die(item: Any) -> Any:
    """Kills its own worker process every time (a task no retry can save)."""
    import signal

    os.kill(os.getpid(), signal.SIGKILL)
    return item  # pragma: no cover


NumbaThreads = _make_numba_plugin_class()
