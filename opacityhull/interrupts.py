"""Holding Ctrl-C (SIGINT), SIGTERM and SIGHUP back while native code runs.

A ``KeyboardInterrupt`` must not be raised inside a native call that calls back into
Python: Dr.Jit runs ``mi.render``'s Python parts (``dr.custom``) from C++ and turns an
exception raised there into a ``RuntimeError``, and Mitsuba's own SIGINT handler
(installed for the duration of ``Integrator.render``) cancels the render and re-raises
the signal. :func:`deferred_signals` records the signal instead and delivers it once,
to the handler that was in place, when the block ends: a Ctrl-C then stops a capture
between two exposures, like one arriving anywhere else.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["DEFERRED_SIGNALS", "deferred_signals", "signals_off_this_thread"]

log = logging.getLogger(__name__)

#: the signals :func:`deferred_signals` holds back (those the platform has)
DEFERRED_SIGNALS: tuple[signal.Signals, ...] = tuple(
    s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP")) if s is not None
)


def signals_off_this_thread() -> None:
    """Block SIGINT, SIGTERM and SIGHUP in the calling thread (not the main one); call it
    first thing in a helper thread's target (the capture's writer, the emulators).

    Python runs its signal handlers in the main thread whichever thread the kernel hands
    a signal to, so this changes nothing for Python code. It keeps C-level handlers off
    threads that allocate: while :func:`deferred_signals` blocks them in the main
    thread, the kernel delivers to some other thread, and Mitsuba's SIGINT handler
    (which logs) must then land on an idle or computing Dr.Jit worker, not on a thread
    inside ``malloc`` (the EXR writer)."""
    if threading.current_thread() is threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, DEFERRED_SIGNALS)


@contextmanager
def deferred_signals(what: str = "critical section", *, deliver: bool = True) -> Iterator[list[int]]:
    """Record SIGINT, SIGTERM and SIGHUP during the block instead of acting on them (and
    block them in this thread, so that no C-level handler interrupts it either).

    Yields the list of signal numbers that arrived meanwhile (in arrival order). On
    leaving the block the previous handlers are restored, then, with ``deliver``, the
    first recorded signal is raised again in this process — exactly once — so its own
    handler runs at that safe point (``KeyboardInterrupt`` for Ctrl-C,
    :class:`~opacityhull.errors.Terminated` under
    :class:`~opacityhull.cliutil.terminate_as_interrupt`). If the block raised, the
    signal is delivered just the same and its exception replaces that one (chained as
    its context): the interrupt says why the work stopped. ``deliver=False`` leaves
    acting on the list to the caller (``rig.safe()``'s clean-up).

    Only the main thread can set signal handlers: elsewhere (a Dask or pool worker) the
    block runs unprotected and the list stays empty. A signal that is ignored
    (``SIG_IGN``, e.g. under ``nohup``) or whose handler was set from C (not
    restorable from Python) is left alone.
    """
    pending: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield pending
        return
    old: dict[int, object] = {}

    def record(signum, frame) -> None:
        pending.append(signum)

    try:
        for s in DEFERRED_SIGNALS:
            h = signal.getsignal(s)
            if h is signal.SIG_IGN or h is None:
                continue
            old[s] = signal.signal(s, record)
    except ValueError:  # not the main interpreter: cannot set handlers here either
        for s, h in old.items():
            signal.signal(s, h)  # pyright: ignore[reportArgumentType]
        yield pending
        return
    # Blocked in this thread too: a handler set from C during the block (Mitsuba's, for
    # the length of Integrator.render) logs, which allocates — not async-signal-safe: run
    # on top of this thread's own malloc it deadlocked on the arena lock (gdb, 1 in 3,000
    # SIGINTs: benchmarks/out/interrupt_stress_before.md). The kernel hands the signal to
    # another thread meanwhile (whose C handler trips Python's flag) or keeps it pending
    # until the mask is restored; either way `record` gets it.
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, list(old)) if old and hasattr(signal, "pthread_sigmask") else None
    try:
        yield pending
    finally:
        if mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a pending signal reaches `record` here
        for s, h in old.items():
            signal.signal(s, h)  # pyright: ignore[reportArgumentType]
        if pending and deliver:
            signum = pending[0]
            log.debug("%s: %s arrived during it, delivered now", what, signal.Signals(signum).name)
            # raise_signal runs the restored handler before returning (its exception
            # propagates from here, replacing one the block may have raised)
            signal.raise_signal(signum)
