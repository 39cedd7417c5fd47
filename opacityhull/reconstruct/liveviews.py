"""The streaming build's witness: how many views have full-resolution arrays alive at
once in this process (:data:`LIVE_VIEWS`). Its own module so that the per-view task
modules (:mod:`.perview`, :mod:`.matte_step`) and :mod:`.build` all report to it
without importing each other."""

from __future__ import annotations

import threading
import weakref
from collections import Counter

import numpy as np

__all__ = ["LiveViews", "LIVE_VIEWS"]


class LiveViews:
    """How many views have a full-resolution array (alpha, RGBA, photograph) alive at
    once in this process: the build's per-view loaders register what they hand out
    (:meth:`track`), and a finaliser counts each array out when it is freed. ``peak`` is
    the streaming structure's witness: it stays at the number of views in flight, not
    the number of views (tests/reconstruct/test_build_streaming.py). Thread-safe;
    counts only this process (process and Dask workers keep their own)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._live: Counter = Counter()
        #: most distinct views alive at once since :meth:`reset`
        self.peak = 0
        #: arrays registered since :meth:`reset`
        self.tracked = 0

    def reset(self) -> None:
        with self._lock:
            self.peak = len(self._live)
            self.tracked = 0

    @property
    def live(self) -> int:
        return len(self._live)

    def track(self, view: str, arr: np.ndarray) -> np.ndarray:
        """Register ``arr`` as a full-resolution array of ``view``; returns it."""
        with self._lock:
            self._live[view] += 1
            self.tracked += 1
            self.peak = max(self.peak, len(self._live))
        weakref.finalize(arr, self._gone, view)
        return arr

    def _gone(self, view: str) -> None:
        with self._lock:
            self._live[view] -= 1
            if self._live[view] <= 0:
                del self._live[view]


#: the process-wide counter the build's loaders report to
LIVE_VIEWS = LiveViews()
