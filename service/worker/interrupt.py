"""Stopping a job's thread where the library computes without reporting.

A job stops on cancel, a lost lease or its timeout when its progress callback raises
(service.worker.leases.JobProgress). Some stretches of the library report nothing for seconds on
a large model (on 3M Gaussians the frame snap and the relabelling choice run 10-18 s each, the
hypotheses-to-coarse step ~28 s): the cancel waited for them. The heartbeat thread, which watches
the job's record anyway, now raises the stop in the job's thread itself
(PyThreadState_SetAsyncExc: the exception is raised at that thread's next Python instruction, so
it waits at most for one native call, a renderer kernel or a tree query).

Only where the job's thread said it may be interrupted (`interruptible`: the library's own
computation), and never inside a `shielded` section (the store and storage I/O the progress
callback does there): an exception half-way through a Redis exchange would leave its connection
unusable. A stop that arrives in a shielded section is raised when the section ends.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_set_async_exc = ctypes.pythonapi.PyThreadState_SetAsyncExc


class Interrupter:
    """Raise an exception in one job thread, at a safe point (module docstring)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._thread: int | None = None  # the job thread while it is interruptible
        self._shielded = 0
        self._armed = False  # the stop is pending in the job thread
        self._deferred = False  # the stop waits for the shielded section to end
        self.requested: type[BaseException] | None = None  # the first stop asked for

    @contextmanager
    def interruptible(self) -> Iterator[None]:
        """Around the library's computation in the job's own thread."""
        with self._lock:
            if self.requested is not None:
                raise self.requested()
            self._thread = threading.get_ident()
        try:
            yield
        finally:
            with self._lock:
                if self._armed:  # not raised yet: it must not be raised outside
                    _raise_in(self._thread, None)
                    self._armed = False
                self._thread = None

    @contextmanager
    def shielded(self) -> Iterator[None]:
        """Around I/O in the job's thread that must not be cut half-way; a stop asked for
        meanwhile is raised once the outermost shielded section ends."""
        with self._lock:
            self._shielded += 1
            if self._armed:
                _raise_in(self._thread, None)
                self._armed, self._deferred = False, True
        try:
            yield
        finally:
            with self._lock:
                self._shielded -= 1
                if not self._shielded and self._deferred and self._thread is not None:
                    _raise_in(self._thread, self.requested)
                    self._armed, self._deferred = True, False

    def interrupt(self, exc_type: type[BaseException]) -> None:
        """From another thread: stop the job's thread with exc_type. The first stop asked for
        is the one raised; asking again changes nothing."""
        with self._lock:
            if self.requested is not None:
                return
            self.requested = exc_type
            if self._thread is not None and not self._shielded:
                _raise_in(self._thread, exc_type)
                self._armed = True
            else:
                self._deferred = True


def _raise_in(thread: int, exc_type: type[BaseException] | None) -> None:
    # None clears a pending exception (NULL is passed).
    _set_async_exc(ctypes.c_ulong(thread), None if exc_type is None else ctypes.py_object(exc_type))
