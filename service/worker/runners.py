"""Processes that run jobs: in-process workers (embedded mode) and the RQ
worker with its task entry point (distributed mode)."""

from __future__ import annotations

import gc
import logging
import os
import signal
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

from service.backend import Backend, process_backend
from service.models import JobState
from service.problems import infrastructure_problem, store_errors
from service.settings import Settings
from service.worker.execution import execute
from service.worker.horse import remember_torch_threads, restore_torch_threads
from service.worker.leases import reap, start_reaper, sweep_workspaces

log = logging.getLogger("gsa.worker")


def start_embedded_workers(backend: Backend, stop: threading.Event) -> list[threading.Thread]:
    """In-process workers for embedded mode: poll the SQLite queue, run jobs."""
    reap(backend, force=True)  # jobs "running" in a previous process were lost with it
    sweep_workspaces(backend)  # and their temp folders with them

    s = backend.settings
    warm = _warming_up(s)

    def loop():
        if not _waited(warm, stop):
            return
        pause = 0.0
        while not stop.is_set():
            ran, trouble = False, None
            try:
                for job_id in backend.store.queued_ids():
                    if stop.is_set():
                        break
                    try:
                        state = execute(job_id, backend)
                    except Exception as exc:  # last resort: one job's unforeseen error never stops the worker thread
                        if infrastructure_problem(exc) is None:
                            log.exception("embedded worker error on %s", job_id)
                            continue
                        trouble = f"{type(exc).__name__}: {exc}"  # the store cannot take the claim
                        break
                    if state == JobState.queued:  # the attempt hit the infrastructure: put back for later
                        trouble = "the last attempt hit an infrastructure error"
                        break
                    if state is not None:
                        ran, pause = True, 0.0
            except store_errors() as exc:  # the queue itself could not be read
                trouble = f"{type(exc).__name__}: {exc}"
            if trouble is not None:
                # Every job needs the disk and the store: on a full disk (or a store that fails)
                # the next job would fail the same way at once, so no job is started for a
                # while (doubling, as a job's own retry back-off), one line each time.
                pause = min(max(2 * pause, s.retry_backoff_base_s, 1.0), max(s.retry_backoff_max_s, 1.0))
                log.warning("embedded worker: %s; starting no job for %.0f s", trouble, pause)
                stop.wait(pause)
                continue
            if not ran:
                backend.queue.wake.wait(1.0)
                backend.queue.wake.clear()

    threads = []
    for i in range(max(backend.settings.embedded_workers, 1)):
        t = threading.Thread(target=loop, name=f"gsa-worker-{i}", daemon=True)
        t.start()
        threads.append(t)
    return threads


def _warming_up(settings: Settings) -> threading.Event:
    """The embedded workers' warm-up (_warm_up) in a thread of its own: the API answers
    meanwhile (a job submitted then waits queued), and the workers take jobs once the returned
    event is set (the warm-up done, or failed)."""
    warm = threading.Event()

    def run():
        try:
            _warm_up(settings, fork=False)
        finally:
            warm.set()

    threading.Thread(target=run, name="gsa-worker-warm-up", daemon=True).start()
    return warm


def _waited(event: threading.Event, stop: threading.Event) -> bool:
    """Wait for `event`; False if `stop` came first."""
    while not event.wait(0.5):
        if stop.is_set():
            return False
    return True


def _terminated(signum, frame):
    raise SystemExit(128 + signum)


def run_job(job_id: str) -> str | None:
    """RQ task entry point (runs in the forked work horse).

    RQ's work horse dies at once on SIGTERM (SIG_DFL): here it becomes SystemExit,
    so the attempt unwinds (its temp folder and partial artifacts are removed) and
    the reaper requeues the job when its lease expires."""
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if main else None
    restore_torch_threads()
    try:
        state = execute(job_id, process_backend(), interrupt=True)  # the horse exits after the job
    finally:
        if main:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
    return state.value if state else None


def _warm_up(settings: Settings | None = None, *, fork: bool = True) -> None:
    """Load the library and run one tiny alignment and render before taking jobs: a cold
    process pays ~1 s on its first alignment, ~2 s importing torch, and a fresh install (an
    empty numba cache, as in a new container) ~20-80 s compiling the renderer on its first job.

    `fork=True`, the RQ worker parent: each forked work horse inherits the imported modules and
    loaded numba kernels. numba's default GNU-OpenMP threading layer aborts a child that forks
    after the parent ran parallel code, so the worker uses the fork-safe `workqueue` layer
    (fine here: one job thread per process); torch runs on one thread here (see
    service.worker.horse), and the heap is frozen for the horses' copy-on-write.

    `fork=False`, the embedded workers (`gsa serve` without Redis): jobs run in threads of this
    process, nothing forks, so none of that applies; torch keeps its thread count."""
    if fork:
        from gsa.kernels import use_workqueue_layer

        use_workqueue_layer()
    t = time.perf_counter()
    try:
        import numba

        if fork and numba.config.THREADING_LAYER not in ("workqueue", "tbb"):
            log.warning(
                "numba threading layer %s is not fork-safe: skipping warm-up",
                numba.config.THREADING_LAYER,
            )
            return
        import torch

        from gsa.align.outputs import write_outputs
        from gsa.align.pipeline import AlignOptions, align
        from gsa.synth import make_object

        if fork:
            remember_torch_threads(torch.get_num_threads())
            torch.set_num_threads(1)
        m = make_object("car", seed=0, n_gaussians=500)
        res = align(m, m, AlignOptions(coarse_iterations=2))
        with tempfile.TemporaryDirectory(prefix="gsa-warm-up-") as d:
            write_outputs(res, m, m, Path(d), outputs={"result", "renders"})
        if settings is not None and settings.semantic != "off":
            # The semantic tie-break's backbone (~2 s to read, 90 MB) once per worker: read in
            # a horse, it went with the horse, and every doubtful job read it again.
            from gsa.align.semantic import available_backbone

            if available_backbone(str(settings.features_backbone) if settings.features_backbone else None) is not None:
                log.info("worker warm-up: semantic backbone loaded")
    except Exception:  # a broken library shows up in the jobs' errors; keep serving
        log.exception("worker warm-up failed")
        return
    if fork:
        # Pre-fork hygiene: move everything loaded so far out of the GC's reach so the
        # horses' collections do not copy-on-write the whole inherited heap.
        gc.collect()
        gc.freeze()
    log.info("worker warm-up took %.2f s", time.perf_counter() - t)


PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int, sig: int = signal.SIGTERM) -> None:
    """In a child process: get `sig` when `parent` dies. Linux: prctl(PR_SET_PDEATHSIG);
    elsewhere (or if prctl fails) a daemon thread that watches the parent pid. Either way the
    parent may have died before this ran: then the signal is sent now."""
    armed = False
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if not armed:

        def watch():
            while os.getppid() == parent:
                time.sleep(1.0)
            os.kill(os.getpid(), sig)

        threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    if os.getppid() != parent:
        os.kill(os.getpid(), sig)


def _scheduler_dies_with_its_worker() -> None:
    """RQ forks its scheduler (which holds `rq:scheduler-lock:<queue>`) as a child of the
    worker; a SIGKILLed worker left it orphaned, holding the lock. Wrap the child's entry
    point so it gets SIGTERM when the worker dies: RQ's scheduler handles SIGTERM by
    releasing its locks and stopping."""
    import rq.scheduler as rq_scheduler

    if getattr(rq_scheduler.run, "_gsa_wrapped", False):
        return
    original, parent = rq_scheduler.run, os.getpid()

    def run(scheduler):
        _die_with_parent(parent)
        return original(scheduler)

    run._gsa_wrapped = True
    rq_scheduler.run = run


# An idle worker checks its RQ scheduler at least this often (seconds): see _worker_class.
SCHEDULER_CHECK_S = 10


def _worker_class():
    """RQ's Worker, made to re-establish its scheduler soon after a Redis outage.

    RQ's scheduler child exits on its first Redis error, and RQ starts it again only at a
    maintenance pass, which an idle worker reaches only between blocking dequeues of
    worker_ttl - 15 = 405 s: after an outage with idle workers no scheduler ran (no retry
    back-off or webhook retry was delivered) for minutes. Here the blocking dequeue is bounded,
    and each turn of the work loop after it (every SCHEDULER_CHECK_S at most, and as soon as
    Redis answers again) asks for the scheduler lock when this worker runs no scheduler: the
    lock is taken if it is free or still this worker's own (its dead child's lock, restored
    from Redis's append-only file), and a scheduler child is forked for it."""
    from rq import Worker  # lazy: embedded mode runs without RQ

    class GsaWorker(Worker):
        keep_scheduler = True  # off in burst mode, where RQ runs no scheduler process

        @property
        def dequeue_timeout(self) -> int:
            return min(super().dequeue_timeout, SCHEDULER_CHECK_S)

        @property
        def should_run_maintenance_tasks(self) -> bool:
            return super().should_run_maintenance_tasks or self._scheduler_check_due()

        def run_maintenance_tasks(self) -> None:
            if super().should_run_maintenance_tasks:  # RQ's own pass (also restarts a dead scheduler)
                super().run_maintenance_tasks()
            else:
                self.scheduler.acquire_locks(auto_start=True)  # starts a child if it gets a lock
                # Only a check Redis answered counts: one that failed is retried on the next turn.
                self._scheduler_checked = time.monotonic()

        def _scheduler_check_due(self) -> bool:
            s = self.scheduler
            if not self.keep_scheduler or s is None or getattr(self, "_stop_requested", False):
                return False
            if s._process is not None and s._process.is_alive():
                return False
            return time.monotonic() - getattr(self, "_scheduler_checked", 0.0) >= SCHEDULER_CHECK_S

    return GsaWorker


def run_rq_worker(burst: bool = False, name: str | None = None, settings: Settings | None = None) -> None:
    """A worker process: RQ worker on the job + webhook queues, plus a reaper.

    RQ's work loop gives up ("... quitting") on most Redis errors (a restart, a
    failover, a network blip). A supervisor loop around it waits for Redis with
    capped exponential backoff (worker_reconnect_min_s .. worker_reconnect_max_s),
    logging each retry, and starts a fresh RQ worker once Redis answers, so
    queued and requeued jobs run again. It ends only on a stop request
    (SIGTERM/SIGINT), or when the queue is drained in burst mode."""
    from redis.exceptions import ConnectionError as RedisConnectionError
    from redis.exceptions import TimeoutError as RedisTimeoutError

    backend = process_backend(settings)
    if backend.redis is None:
        raise SystemExit("gsa worker needs GSA_REDIS_URL (embedded mode runs workers inside `gsa serve`)")
    s = backend.settings
    _warm_up(s)
    try:
        sweep_workspaces(backend)  # what a SIGKILLed horse on this machine left behind
    except store_errors() as exc:  # Redis not up yet: the reaper sweeps later
        log.warning("start-up sweep of job temp folders skipped: %s", exc)
    stop = threading.Event()
    start_reaper(backend, stop)
    _scheduler_dies_with_its_worker()
    worker_class = _worker_class()
    queues = [backend.queue.hooks, backend.queue.q]  # webhooks first: they are tiny
    base = name or f"gsa-{uuid.uuid4().hex[:8]}"
    delay, retry = s.worker_reconnect_min_s, 0
    try:
        while True:
            # A worker lost with Redis may leave its registration behind (a Redis
            # that persisted it): each reconnection registers under a fresh name.
            w = None
            started = time.monotonic()
            error: Exception | None = None
            try:
                # RQ retries a task whose worker died mid-run (a webhook delivery, whose
                # Retry would else be lost with it) only at a maintenance pass: every
                # 10 min by default, so this worker runs one every 30 s.
                w = worker_class(
                    queues,
                    connection=backend.redis,
                    name=base if retry == 0 else f"{base}.{retry}",
                    maintenance_interval=30,
                )
                w.max_connection_wait_time = s.worker_reconnect_max_s  # RQ's own retry while dequeuing
                w.keep_scheduler = not burst
                w.work(burst=burst, with_scheduler=True)
            except (RedisConnectionError, RedisTimeoutError) as exc:  # registering, or in teardown
                error = exc
            # A SIGTERM/SIGINT (warm shutdown) ends the worker for good.
            stopped = w is not None and (
                getattr(w, "_shutdown_requested_date", None) is not None or getattr(w, "_stop_requested", False)
            )
            if stopped or (burst and error is None and _redis_up(backend)):
                return
            if time.monotonic() - started > 60:  # it ran a good while: start the backoff afresh
                delay = s.worker_reconnect_min_s
            why = f"{type(error).__name__}: {error}" if error else "the RQ work loop ended"
            delay, retry = _wait_for_redis(backend, why, retry, delay, s.worker_reconnect_max_s)
    finally:
        stop.set()


def _redis_up(backend: Backend) -> bool:
    try:
        return bool(backend.redis.ping())
    except store_errors():
        return False


def _wait_for_redis(backend: Backend, why: str, retry: int, delay: float, cap: float) -> tuple[float, int]:
    """Sleep with capped exponential backoff until Redis answers a PING; returns
    the next delay and the retry count. SIGTERM/SIGINT while waiting end the process (RQ's handlers
    belong to the worker that just ended)."""

    def _exit(signum, frame):
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, _exit)
    signal.signal(signal.SIGINT, _exit)
    while True:
        retry += 1
        log.warning("worker lost Redis (%s); reconnect attempt %d in %.1f s", why, retry, delay)
        time.sleep(delay)
        delay = min(delay * 2, cap)
        try:
            if backend.redis.ping():
                log.warning("Redis is back; restarting the worker (reconnect attempt %d)", retry)
                return delay, retry
        except store_errors() as exc:
            why = f"{type(exc).__name__}: {exc}"
