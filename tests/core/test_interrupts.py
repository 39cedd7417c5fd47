"""opacityhull.interrupts.deferred_signals, in process: a signal sent with os.kill inside
the block reaches the previous handler only after the block, exactly once; the previous
handlers are back afterwards; off the main thread the block is left unprotected; and
signals_off_this_thread blocks the signals in a helper thread only."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from opacityhull.cliutil import terminate_as_interrupt
from opacityhull.errors import Terminated
from opacityhull.interrupts import deferred_signals, signals_off_this_thread


@pytest.fixture
def handlers():
    """Restore SIGINT, SIGTERM and SIGHUP's handlers after the test."""
    sigs = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    old = {s: signal.getsignal(s) for s in sigs}
    yield
    for s, h in old.items():
        signal.signal(s, h)


def _counter():
    calls: list[int] = []

    def handler(signum, frame):
        calls.append(signum)

    return handler, calls


def test_signal_in_block_is_delivered_after_it_once(handlers):
    prev, calls = _counter()
    signal.signal(signal.SIGINT, prev)
    with deferred_signals("test") as pending:
        assert signal.getsignal(signal.SIGINT) is not prev
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        seen_inside = list(calls)
    assert seen_inside == []
    # blocked in this thread, the two may merge into one pending signal: one or two recorded
    assert pending[:1] == [signal.SIGINT] and set(pending) == {signal.SIGINT}
    assert calls == [signal.SIGINT]  # the stop is delivered once
    assert signal.getsignal(signal.SIGINT) is prev
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])  # unblocked again


def test_ctrl_c_raises_after_the_block_ran_to_its_end(handlers):
    signal.signal(signal.SIGINT, signal.default_int_handler)
    reached = []
    with pytest.raises(KeyboardInterrupt), deferred_signals("test"):
        os.kill(os.getpid(), signal.SIGINT)
        reached.append("end of block")
    assert reached == ["end of block"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_arrives_as_terminated_after_the_block(handlers):
    with terminate_as_interrupt():
        with pytest.raises(Terminated) as e, deferred_signals("test"):
            os.kill(os.getpid(), signal.SIGTERM)
        assert e.value.signum == signal.SIGTERM


def test_signal_wins_over_the_blocks_own_error(handlers):
    signal.signal(signal.SIGINT, signal.default_int_handler)
    with pytest.raises(KeyboardInterrupt) as e, deferred_signals("test"):
        os.kill(os.getpid(), signal.SIGINT)
        raise ValueError("render failed")
    assert isinstance(e.value.__context__, ValueError)


def test_nothing_delivered_without_a_signal_and_handlers_restored(handlers):
    prev, calls = _counter()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, prev)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    with deferred_signals("test") as pending:
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN  # ignored on purpose (nohup): left alone
        os.kill(os.getpid(), signal.SIGHUP)
    assert pending == [] and calls == []
    assert signal.getsignal(signal.SIGINT) is prev and signal.getsignal(signal.SIGTERM) is prev


def test_no_deliver_leaves_the_signal_to_the_caller(handlers):
    prev, calls = _counter()
    signal.signal(signal.SIGTERM, prev)
    with deferred_signals("test", deliver=False) as pending:
        os.kill(os.getpid(), signal.SIGTERM)
    assert pending == [signal.SIGTERM] and calls == []


def test_no_op_off_the_main_thread(handlers):
    prev, calls = _counter()
    signal.signal(signal.SIGINT, prev)
    seen: dict = {}

    def work():
        with deferred_signals("worker") as pending:
            seen["handler"] = signal.getsignal(signal.SIGINT)
            seen["pending"] = pending

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen == {"handler": prev, "pending": []}
    assert signal.getsignal(signal.SIGINT) is prev and calls == []


def test_signals_off_a_helper_thread_only():
    seen: dict = {}

    def work():
        signals_off_this_thread()
        seen["mask"] = signal.pthread_sigmask(signal.SIG_BLOCK, [])

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert {signal.SIGINT, signal.SIGTERM, signal.SIGHUP} <= seen["mask"]
    signals_off_this_thread()  # the main thread: a no-op
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
