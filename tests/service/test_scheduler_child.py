"""The RQ scheduler child never outlives its `gsa worker` (issue 28).

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
from pathlib import Path

import pytest
import redis

from tests.service.conftest import service_env, start_worker, wait_until


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
