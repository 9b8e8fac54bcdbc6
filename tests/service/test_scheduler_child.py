"""The RQ scheduler child never outlives its `gsa worker` (no orphan scheduler).

`gsa worker` runs RQ with its scheduler (webhook retries are scheduled jobs), which RQ forks
as a child process holding the queues' `rq:scheduler-lock:*`. A SIGKILLed worker used to leave
that child orphaned (275-394 MB, alive 18+ minutes) and holding the lock, so no other worker's
scheduler could take over. Now the child asks the kernel for SIGTERM when its parent dies
(prctl PR_SET_PDEATHSIG, and a parent-watching thread where prctl is missing) and, on that
SIGTERM, releases its locks and exits.
"""

from __future__ import annotations

import os
import signal
import time
from datetime import datetime
from pathlib import Path

import pytest
import redis

from tests.service.conftest import service_env, start_worker, wait_until
from tests.service.harness import RedisServer


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


@pytest.mark.slow
def test_sigkilled_worker_takes_its_scheduler_child_and_lock_with_it(tmp_path, redis_url):
    db = redis_url + "/6"
    r = redis.Redis.from_url(db)
    r.flushdb()
    worker = start_worker(tmp_path, service_env(tmp_path, GSA_REDIS_URL=db))
    children: list[int] = []
    try:
        wait_until(lambda: r.keys("rq:scheduler-lock:*") and worker.descendants(), 120, 0.2, "scheduler child")
        children = worker.descendants()
        assert children, "the worker forked no scheduler"
        os.kill(worker.p.pid, signal.SIGKILL)  # the worker alone, as the OOM killer does
        worker.p.wait(10)
        wait_until(lambda: not any(_alive(p) for p in children), 15, 0.1, "the scheduler child to exit")
        wait_until(lambda: not r.keys("rq:scheduler-lock:*"), 15, 0.1, "the scheduler lock to be released")
    finally:
        for pid in children + worker.descendants():
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        worker.kill()


def _live_scheduler_locks(r: redis.Redis, since: float) -> list[str]:
    """The `rq:scheduler-lock:<queue>` keys whose owner (`rq:scheduler:<name>`, RQ's scheduler
    hash, refreshed every second by a running scheduler) has beaten since `since`: a lock
    restored from the append-only file, held by a scheduler that died in the outage, does not
    count."""
    live = []
    for key in r.keys("rq:scheduler-lock:*"):
        owner = r.get(key)
        beat = owner and r.hget(b"rq:scheduler:" + owner, "last_heartbeat")
        if beat and datetime.fromisoformat(beat.decode().replace("Z", "+00:00")).timestamp() >= since:
            live.append(key.decode())
    return live


@pytest.mark.slow
def test_scheduler_is_back_within_a_minute_of_a_redis_restart_with_idle_workers(tmp_path):
    """RQ's scheduler child exits on its first Redis error, and RQ restarted it only at a
    maintenance pass, which an idle worker reached only between BLPOPs of 405 s: after a short
    outage no scheduler ran (no retry back-off, no webhook retry sent) for minutes."""
    srv = RedisServer(tmp_path / "redis")  # same port and data folder across the restart
    srv.start()
    r = redis.Redis(port=srv.port)
    env = service_env(tmp_path, GSA_REDIS_URL=srv.url)
    workers = [start_worker(tmp_path, env, name=f"idle-{i}") for i in range(2)]
    try:
        queues = 2  # the jobs' queue and the webhooks' queue: one lock each
        wait_until(lambda: len(_live_scheduler_locks(r, 0)) == queues, 120, 0.2, "the schedulers' locks")
        time.sleep(3)  # both workers idle in their blocking dequeue
        srv.stop(kill=True)
        time.sleep(3)
        srv.start()
        back = time.time()
        try:
            wait_until(lambda: len(_live_scheduler_locks(r, back)) == queues, 60, 0.5, "a live scheduler")
        except TimeoutError:
            pytest.fail(
                f"no live scheduler lock 60 s after Redis restarted: {r.keys('rq:scheduler*')}\n"
                + "\n".join(w.tail() for w in workers)
            )
        print(f"scheduler lock back {time.time() - back:.1f} s after the restart")
        assert all(w.p.poll() is None for w in workers)
    finally:
        for w in workers:
            w.kill()
        srv.stop(kill=True)
