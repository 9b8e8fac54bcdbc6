"""Processes that run jobs: in-process workers (embedded mode) and the RQ
worker with its task entry point (distributed mode)."""

from __future__ import annotations

import gc
import logging
import os
import sys
import threading
import time
import uuid

from service.backend import Backend, process_backend
from service.execution import execute
from service.leases import reap, start_reaper

log = logging.getLogger("gsa.worker")


def start_embedded_workers(backend: Backend, stop: threading.Event) -> list[threading.Thread]:
    """In-process workers for embedded mode: poll the SQLite queue, run jobs."""
    reap(backend, force=True)  # jobs "running" in a previous process were lost with it

    def loop():
        while not stop.is_set():
            ran = False
            for job_id in backend.store.queued_ids():
                if stop.is_set():
                    break
                try:
                    if execute(job_id, backend) is not None:
                        ran = True
                except Exception:
                    log.exception("embedded worker error on %s", job_id)
            if not ran:
                backend.queue.wake.wait(1.0)
                backend.queue.wake.clear()

    threads = []
    for i in range(max(backend.settings.embedded_workers, 1)):
        t = threading.Thread(target=loop, name=f"gsa-worker-{i}", daemon=True)
        t.start()
        threads.append(t)
    return threads


def run_job(job_id: str) -> str | None:
    """RQ task entry point (runs in the forked work horse)."""
    state = execute(job_id, process_backend())
    return state.value if state else None


def _warm_up() -> None:
    """Load the library and run one tiny alignment in the worker parent, so each
    forked work horse inherits imported modules and loaded numba kernels
    (a cold process pays ~1 s on its first alignment).

    numba's default GNU-OpenMP threading layer aborts a child that forks after
    the parent ran parallel code, so the worker uses the fork-safe `workqueue`
    layer (fine here: one job thread per process)."""
    if "numba" not in sys.modules:
        os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
    t = time.perf_counter()
    try:
        import numba

        if numba.config.THREADING_LAYER not in ("workqueue", "tbb"):
            log.warning(
                "numba threading layer %s is not fork-safe: skipping warm-up",
                numba.config.THREADING_LAYER,
            )
            return
        from gsa.align.outputs import write_outputs  # noqa: F401
        from gsa.align.pipeline import AlignOptions, align
        from gsa.synth import make_object

        m = make_object("car", seed=0, n_gaussians=500)
        align(m, m, AlignOptions(coarse_iterations=2))
        # Import only (torch and the render kernels): running torch ops here
        # would start its OpenMP pool, which does not survive fork().
        import gsa.render.views  # noqa: F401
    except Exception:  # a broken library shows up in the jobs' errors; keep serving
        log.exception("worker warm-up failed")
        return
    # Pre-fork hygiene: move everything loaded so far out of the GC's reach so the
    # horses' collections do not copy-on-write the whole inherited heap.
    gc.collect()
    gc.freeze()
    log.info("worker warm-up took %.2f s", time.perf_counter() - t)


def run_rq_worker(burst: bool = False, name: str | None = None) -> None:
    """A worker process: RQ worker on the job + webhook queues, plus a reaper."""
    from rq import Worker  # lazy: embedded mode runs without RQ

    backend = process_backend()
    if backend.redis is None:
        raise SystemExit("gsa worker needs GSA_REDIS_URL (embedded mode runs workers inside `gsa serve`)")
    _warm_up()
    stop = threading.Event()
    start_reaper(backend, stop)
    queues = [backend.queue.hooks, backend.queue.q]  # webhooks first: they are tiny
    w = Worker(queues, connection=backend.redis, name=name or f"gsa-{uuid.uuid4().hex[:8]}")
    try:
        w.work(burst=burst, with_scheduler=True)
    finally:
        stop.set()
