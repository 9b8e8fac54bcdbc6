"""A many job's edges (pairwise alignments) spread over the queue's workers.

The attempt that runs a many job (the parent) puts its E edges in a pool and works through it
itself; in distributed mode, when more than one worker is live, it also enqueues one RQ job per
other edge (`run_edge_task`), which claims one edge, loads its two models and runs it. So one
worker still finishes the job alone (no task is sent), every added worker takes edges off it,
and other jobs in the queue interleave with the edges instead of waiting for the whole job. A
claim carries a deadline its holder renews; the parent takes over an edge whose claim lapsed (a
task killed mid-edge) and runs it itself, and a task whose edge raises gives it back. A task
does nothing when the job is cancelled or its attempt is no longer current (the pool is per
attempt: a requeued job starts a new one). Embedded mode has no queue: a local pool, parent only.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from service.backend import Backend, RQQueue
from service.models import Job, JobState
from service.worker.horse import restore_torch_threads
from service.worker.leases import JobCancelled, LeaseLost, job_workspace, worker_name

log = logging.getLogger("gsa.worker")

# A claim lapses this long after its holder last renewed it (renewed every quarter of it).
CLAIM_S = 60.0
EDGE_TASK = "service.worker.edges.run_edge_task"


def edge_payload(edge, worker: str) -> dict[str, Any]:
    """What a pool keeps of one pairwise alignment (a gsa.align.many.Edge before the global step)."""
    return {
        "transform": edge.transform.matrix().tolist(),
        "confidence": edge.confidence,
        "doubtful": edge.doubtful,
        "ambiguous": edge.ambiguous,
        "alternatives": [a.matrix().tolist() for a in edge.alternatives],
        "scores": list(edge.scores),
        "agreements": list(edge.agreements),
        "agreement_needed": edge.agreement_needed,
        "seconds": edge.seconds,
        "worker": worker,
    }


def edge_from_payload(i: int, j: int, data: dict[str, Any]):
    import numpy as np

    from gsa.align.many import Edge
    from gsa.sim3 import Sim3

    def sim3(m):
        return Sim3.from_matrix(np.asarray(m, np.float64))

    return Edge(
        source=i,
        target=j,
        transform=sim3(data["transform"]),
        confidence=float(data["confidence"]),
        doubtful=bool(data["doubtful"]),
        ambiguous=bool(data["ambiguous"]),
        alternatives=[sim3(a) for a in data["alternatives"]],
        scores=[None if v is None else float(v) for v in data.get("scores") or []],
        agreements=[None if v is None else float(v) for v in data.get("agreements") or []],
        agreement_needed=None if data.get("agreement_needed") is None else float(data["agreement_needed"]),
        seconds=float(data["seconds"]),
    )


class LocalEdgePool:
    """The pool in one process (embedded mode): the parent claims every edge itself."""

    def __init__(self, pairs: Sequence[tuple[int, int]]):
        self.pairs = [tuple(p) for p in pairs]
        self._pending = list(range(len(self.pairs)))
        self._results: dict[int, dict] = {}

    def claim(self, worker: str) -> int | None:
        return self._pending.pop(0) if self._pending else None

    def renew(self, k: int, worker: str) -> None:
        pass

    def finish(self, k: int, payload: dict) -> None:
        self._results[k] = payload

    def results(self) -> dict[int, dict]:
        return dict(self._results)

    def lapsed(self, now: float | None = None) -> list[int]:
        return []

    def recreate_if_lost(self) -> bool:
        return False

    def take_over(self, k: int, worker: str) -> None:
        pass

    def release(self, k: int) -> None:
        self._pending.insert(0, k)

    def delete(self) -> None:
        pass


class RedisEdgePool:
    """The pool in Redis, one per attempt (job id + run token), shared by the parent and its helpers."""

    def __init__(self, redis, job_id: str, token: str):
        self.r = redis
        base = f"gsa:many-edges:{job_id}:{token}"
        self.k_pairs, self.k_pending = base + ":pairs", base + ":pending"
        self.k_claims, self.k_results = base + ":claims", base + ":results"
        self._pairs: list[tuple[int, int]] | None = None

    def create(self, pairs: Sequence[tuple[int, int]], ttl_s: float) -> None:
        keys = (self.k_pairs, self.k_pending, self.k_claims, self.k_results)
        with self.r.pipeline() as p:
            p.delete(*keys)
            p.set(self.k_pairs, json.dumps([list(map(int, q)) for q in pairs]))
            p.rpush(self.k_pending, *range(len(pairs)))
            for key in keys:
                p.expire(key, int(ttl_s))
            p.execute()
        self._pairs = [tuple(q) for q in pairs]
        self._ttl_s = ttl_s

    def recreate_if_lost(self) -> bool:
        """Put the pool back (every edge without a result pending again) when its keys are gone:
        a Redis restart without persistence, or an eviction. True if it had to."""
        if self._pairs is None or self.r.exists(self.k_pairs):
            return False
        done = self.results()
        self.create(self._pairs, self._ttl_s)
        with self.r.pipeline() as p:
            for k, payload in done.items():
                p.hset(self.k_results, str(k), json.dumps(payload))
                p.lrem(self.k_pending, 0, k)
            p.execute()
        return True

    @property
    def pairs(self) -> list[tuple[int, int]] | None:
        """The edges as (source, target) model indices; None when the pool is gone."""
        if self._pairs is None:
            raw = self.r.get(self.k_pairs)
            self._pairs = None if raw is None else [tuple(q) for q in json.loads(raw)]
        return self._pairs

    def _claim_record(self, worker: str) -> str:
        return json.dumps({"worker": worker, "until": time.time() + CLAIM_S})

    def claim(self, worker: str) -> int | None:
        raw = self.r.lpop(self.k_pending)
        if raw is None:
            return None
        k = int(raw)
        self.r.hset(self.k_claims, str(k), self._claim_record(worker))
        return k

    def renew(self, k: int, worker: str) -> None:
        self.r.hset(self.k_claims, str(k), self._claim_record(worker))

    def finish(self, k: int, payload: dict) -> None:
        with self.r.pipeline() as p:
            p.hset(self.k_results, str(k), json.dumps(payload))
            p.hdel(self.k_claims, str(k))
            p.execute()

    def results(self) -> dict[int, dict]:
        return {int(k): json.loads(v) for k, v in self.r.hgetall(self.k_results).items()}

    def lapsed(self, now: float | None = None) -> list[int]:
        """Claimed edges without a result whose claim was not renewed in time (holder gone)."""
        now = time.time() if now is None else now
        done = set(self.r.hkeys(self.k_results))
        out = []
        for k, v in self.r.hgetall(self.k_claims).items():
            if k not in done and json.loads(v)["until"] < now:
                out.append(int(k))
        return sorted(out)

    def take_over(self, k: int, worker: str) -> None:
        self.renew(k, worker)

    def release(self, k: int) -> None:
        """Give edge k back (its holder failed): the next claim gets it without waiting out the claim."""
        with self.r.pipeline() as p:
            p.hdel(self.k_claims, str(k))
            p.lpush(self.k_pending, k)
            p.execute()

    def delete(self) -> None:
        self.r.delete(self.k_pairs, self.k_pending, self.k_claims, self.k_results)


class _Renewer:
    """Renews one claim every quarter of CLAIM_S while an edge runs (a thread: align() may go
    long between progress reports)."""

    def __init__(self, pool, k: int, worker: str):
        self.pool, self.k, self.worker = pool, k, worker
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, name=f"gsa-edge-claim-{k}", daemon=True)

    def _loop(self) -> None:
        while not self.stop.wait(CLAIM_S / 4):
            try:
                self.pool.renew(self.k, self.worker)
            except Exception:  # noqa: BLE001  (Redis down: the claim may lapse; the parent then reruns the edge)
                log.warning("could not renew the claim on edge %s", self.k)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)


def run_one_edge(pool, k: int, worker: str, models: dict, options, progress=None) -> dict:
    """Align edge k's two models (as given by index in `models`), record its result in the pool."""
    from gsa.align.many import edge_from_result
    from gsa.align.pipeline import align

    i, j = pool.pairs[k]
    t0 = time.perf_counter()
    with _Renewer(pool, k, worker):
        result = align(models[i], models[j], options, progress=progress)
    payload = edge_payload(edge_from_result(i, j, result, time.perf_counter() - t0), worker)
    pool.finish(k, payload)
    return payload


def live_workers(backend: Backend) -> int:
    """The RQ workers registered on the job queue now (0 in embedded mode)."""
    if not isinstance(backend.queue, RQQueue):
        return 0
    import rq

    return rq.Worker.count(queue=backend.queue.q)


def worker_label() -> str:
    """Who runs an edge: the RQ worker's name in distributed mode (the work horse's job knows
    it), else host:pid."""
    try:
        from rq import get_current_job
    except ImportError:  # embedded mode runs without RQ installed
        job = None
    else:
        job = get_current_job()
    return (job.worker_name if job is not None else None) or worker_name()


def enqueue_edge_tasks(backend: Backend, job: Job, token: str, n: int) -> int:
    """n edge tasks (one RQ job each) for this attempt's pool; returns how many were sent."""
    if n <= 0 or not isinstance(backend.queue, RQQueue):
        return 0
    for _ in range(n):
        backend.queue.q.enqueue(EDGE_TASK, job.id, token, **backend.queue.task_options())
    return n


def work_through(
    pool,
    models: Sequence,
    options,
    check: Callable[[], None],
    on_edge: Callable[[int, int, str, float], None] | None = None,
    on_progress: Callable[[int, int, bool], None] | None = None,
    poll_s: float = 0.2,
) -> list[dict]:
    """The parent's loop: claim and run edges until every edge has a result, taking over lapsed
    claims; check() raises to stop (cancel, lease lost, timeout). Returns the payloads by edge."""
    me = worker_label()
    total = len(pool.pairs)
    mapping = dict(enumerate(models))
    while True:
        check()
        k = pool.claim(me)
        if k is None:
            results = pool.results()
            if on_progress:
                on_progress(len(results), total, True)
            if len(results) == total:
                return [results[e] for e in range(total)]
            if pool.recreate_if_lost():
                log.warning(
                    "the edge pool of %d edges was lost (Redis restarted?): unfinished ones pending again", total
                )
                continue
            lapsed = pool.lapsed()
            if not lapsed:
                time.sleep(poll_s)
                continue
            k = lapsed[0]
            log.warning("edge %d of %d: its helper's claim lapsed; running it here", k, total)
            pool.take_over(k, me)
        report = None
        if on_edge is not None:

            def report(stage: str, fraction: float, k: int = k) -> None:
                on_edge(k, total, stage, fraction)

        run_one_edge(pool, k, me, mapping, options, report)
        if on_progress:
            on_progress(len(pool.results()), total, False)


def run_edge_task(job_id: str, token: str) -> int | None:
    """RQ task, one per edge but the parent's first: claim one edge of the attempt's pool and run
    it; nothing when the pool is empty or gone, the job cancelled or its attempt no longer current.
    Returns the edge run here, if any."""
    from service.backend import process_backend
    from service.jobs.inputs import load_input
    from service.jobs.options import align_options

    restore_torch_threads()
    backend = process_backend()
    job = backend.store.get(job_id)
    if job is None or job.state != JobState.running or job.run_token != token:
        return None
    pool = RedisEdgePool(backend.redis, job_id, token)
    if pool.pairs is None or (k := pool.claim(worker_label())) is None:
        return None
    last = [0.0]

    def check(*_):
        now = time.monotonic()
        if now - last[0] < 0.5:
            return
        last[0] = now
        current = backend.store.get(job_id)
        if current is None or current.run_token != token or current.state != JobState.running:
            raise LeaseLost()
        if current.cancel_requested:
            raise JobCancelled()

    try:
        with job_workspace(job_id, token) as work:
            i, j = pool.pairs[k]
            models = {idx: load_input(backend, job.sources[idx], work, f"model{idx}", check) for idx in (i, j)}
            run_one_edge(pool, k, worker_label(), models, align_options(backend.settings, job.options), check)
    except (JobCancelled, LeaseLost):
        log.info("edge %d of %s not run: the job was cancelled or its attempt ended", k, job_id)
        return None
    except BaseException:
        # The parent reruns it (and fails the job with the right problem if it fails again).
        pool.release(k)
        raise
    return k
