"""A callback that a CPU render calls between its steps, on the thread that renders.

One view of a 3M-Gaussian model is a single renderer call of ~0.7 s on two idle cores (a lifting
pass, forward and backward, ~1.6 s; twice that on a busy box), too long between two progress
reports for a cancelled service job, which stops at a report. The CPU backend calls `step()`
between its kernels (covariances, projection, footprints, depth order, binning, packing,
compositing, and the compositing's backward and reduction, each a fraction of that call), and a
caller that must be able to stop within a render (gsa.align.semantic, gsa.features.lift's
back-projection) installs its callback for the calls it makes with `between_steps(call)`; the
callback may raise, which unwinds the render (the kernel lock is released on the way out).
Nothing else changes: the same kernels run on the same data, so the images are the same.

align() installs one too (gsa.align.pair._Repeater: its last progress report, repeated once it is
0.1 s old), and its long loops call `step()` between their passes; one native call too long to
split (a LAPACK SVD) runs through `waiting()`, which calls `step()` while it waits.

Thread-local, like the backbone's block hooks (gsa.align.semantic): the service's embedded workers
are threads, and one job's callback must not run in another job's render.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from typing import TypeVar

_LOCAL = threading.local()
T = TypeVar("T")
U = TypeVar("U")


def step() -> None:
    """Call this thread's callback (between_steps), if one is installed."""
    call = getattr(_LOCAL, "call", None)
    if call is not None:
        call()


@contextlib.contextmanager
def between_steps(call: Callable[[], None] | None) -> Iterator[None]:
    """`call()` between the steps of every CPU render this thread makes inside the block (None:
    the callback already installed, if any, stays); the one installed before is back afterwards."""
    previous = getattr(_LOCAL, "call", None)
    _LOCAL.call = call if call is not None else previous
    try:
        yield
    finally:
        _LOCAL.call = previous


def waiting(call: Callable[[], T], poll_s: float = 0.05) -> T:
    """`call()`'s value, the call made on a helper thread while this thread calls `step()` every
    poll_s, for one long native call that releases the GIL (the same call on the same data: the
    same value). Where `step()` raises, the helper runs its call to the end unwaited for. Without
    a callback installed, `call()` runs on this thread."""
    if getattr(_LOCAL, "call", None) is None:
        return call()
    box: dict = {}

    def run() -> None:
        try:
            box["value"] = call()
        except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread
            box["error"] = exc

    helper = threading.Thread(target=run, name="gsa-steps-waiting", daemon=True)
    helper.start()
    while helper.is_alive():
        step()
        helper.join(poll_s)
    if "error" in box:
        raise box["error"]
    return box["value"]


def parallel(calls: Sequence[Callable[[], T]], poll_s: float = 0.05) -> list[T]:
    """Each call's value, in order, the calls run on up to one thread per core while this
    thread calls `step()` every poll_s (as `waiting`). For independent calls into numpy and
    scipy's trees, which release the GIL: the same calls on the same data, so the same values,
    in less time where cores are free. The first error raised is raised here; where `step()`
    raises, the calls not yet started are dropped and the running ones finish unwaited for."""
    workers = min(len(calls), _cores())
    if workers <= 1:
        return [call() for call in calls]
    pool = ThreadPoolExecutor(workers, thread_name_prefix="gsa-steps-parallel")
    try:
        futures = [pool.submit(call) for call in calls]
        while wait(futures, poll_s).not_done:
            step()
        return [f.result() for f in futures]
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def parallel_map(fn: Callable[[U], T], items: Iterable[U]) -> list[T]:
    """`parallel` of fn over each item, in order."""
    return parallel([functools.partial(fn, item) for item in items])


def _cores() -> int:
    """The cores this process may run on (its affinity where the platform says, as a container's
    cpuset does), else the machine's."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1
