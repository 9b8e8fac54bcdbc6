"""The webhook outbox: a final state records that a webhook is owed, in the same
store write; a delivery clears it; the reaper re-sends one still owed after
GSA_WEBHOOK_OUTBOX_GRACE_S. So a webhook is sent even when the process that
wrote the final state died before enqueueing (or finishing) the delivery, and a
delivered one is not sent again."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from tests.service.conftest import (
    ALICE,
    PY,
    Proc,
    service_env,
    start_api,
    start_worker,
    submit_pair,
    wait_job,
    wait_until,
)
from tests.service.harness import RedisServer

pytestmark = pytest.mark.slow  # starts servers and worker processes

QUICK = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0, "outputs": ["result"]}
GRACE = 3.0


class Receiver:
    """A webhook receiver on a free loopback port. hold_first: the first request
    is held unanswered until `release` (a delivery in flight when its process dies)."""

    def __init__(self, hold_first: bool = False):
        self.got: list[bytes] = []  # bodies of the deliveries it answered 204
        self.seen: list[bytes] = []  # every body received, held ones too
        self.release = threading.Event()
        if not hold_first:
            self.release.set()
        outer = self

        class H(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                outer.seen.append(body)
                if len(outer.seen) == 1:
                    outer.release.wait(60)
                    if hold_first:
                        return  # its sender is gone: no answer
                outer.got.append(body)
                self.send_response(204)
                self.end_headers()

            def log_message(self, *a):
                pass

        self.srv = ThreadingHTTPServer(("127.0.0.1", 0), H)
        self.url = f"http://127.0.0.1:{self.srv.server_port}/hook"
        threading.Thread(target=self.srv.serve_forever, daemon=True).start()

    def close(self):
        self.release.set()
        self.srv.shutdown()


def _owed(env: dict) -> list[str]:
    from service.backend import make_backend
    from service.settings import Settings

    b = make_backend(Settings(redis_url=env.get("GSA_REDIS_URL"), storage_root=env["GSA_STORAGE_ROOT"]))
    return b.store.webhooks_due(float("inf"))


def test_redis_a_webhook_never_enqueued_is_sent_by_the_reaper_and_a_delivered_one_once(tmp_path, pair):
    redis = RedisServer(tmp_path / "redis")
    redis.start()
    hook = Receiver()
    env = service_env(tmp_path, GSA_REDIS_URL=redis.url, GSA_WEBHOOK_OUTBOX_GRACE_S=GRACE, GSA_QUEUE_NAME="outbox")
    api, url, _ = start_api(tmp_path, env, name="api-outbox")
    worker = None
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            # No worker yet: a job the test runs as a worker would, up to its final
            # state, and then "dies" before enqueueing the webhook.
            lost = submit_pair(c, pair, QUICK, webhook_url=hook.url).json()["id"]
            code = (
                "import os, signal, sys, time, uuid\n"
                "from service.backend import make_backend\n"
                "from service.leases import finish_attempt\n"
                "from service.models import JobState\n"
                "b = make_backend(); jid = sys.argv[1]; tok = uuid.uuid4().hex\n"
                "assert b.store.update(jid, states={JobState.queued}, state=JobState.running, attempts=1,\n"
                "    run_token=tok, lease_until=time.time() + 60, started_at=time.time())\n"
                "assert finish_attempt(b, jid, tok, JobState.succeeded, progress=1.0)\n"
                "os.kill(os.getpid(), signal.SIGKILL)  # dies here: notify_webhook never runs\n"
            )
            dying = Proc([PY, "-c", code, lost], env, tmp_path / "dying.log")
            assert dying.p.wait(60) == -9, dying.tail()
            assert c.get(f"/v1/jobs/{lost}").json()["state"] == "succeeded"
            assert _owed(env) == [lost]  # owed, written with the final state

            worker = start_worker(tmp_path, env, name="worker-outbox")
            normal = submit_pair(c, pair, QUICK, webhook_url=hook.url).json()["id"]
            assert wait_job(c, normal)["state"] == "succeeded"

            bodies = wait_until(lambda: len(hook.got) >= 2 and hook.got, 30 + GRACE, 0.1, "both webhooks")
            events = [json.loads(b) for b in bodies]
            assert sorted(e["job_id"] for e in events) == sorted([lost, normal]), events
            assert all(e["state"] == "succeeded" for e in events), events
            # Nothing owed any more, and nothing sent twice over several grace periods.
            wait_until(lambda: _owed(env) == [], 10, 0.1, "the outbox to empty")
            time.sleep(2 * GRACE + 1)
            assert len(hook.seen) == 2, [json.loads(b) for b in hook.seen]
    finally:
        if worker is not None:
            worker.kill()
        api.stop()
        hook.close()
        redis.stop()


def test_embedded_a_delivery_lost_with_its_process_is_sent_again_after_a_restart(tmp_path, pair):
    hook = Receiver(hold_first=True)
    env = service_env(tmp_path, GSA_WEBHOOK_OUTBOX_GRACE_S=GRACE)
    api, url, _ = start_api(tmp_path, env, name="api-outbox-1")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            jid = submit_pair(c, pair, QUICK, webhook_url=hook.url).json()["id"]
            assert wait_job(c, jid)["state"] == "succeeded"
            wait_until(lambda: hook.seen, 30, 0.05, "the first delivery")  # in flight, held
        api.kill()  # SIGKILL: the delivery thread dies with the process
        hook.release.set()
        assert hook.got == []
        api, url, _ = start_api(tmp_path, env, name="api-outbox-2")
        wait_until(lambda: hook.got, 30 + GRACE, 0.1, "the re-sent webhook")
        assert hook.got[0] == hook.seen[0]  # the same event, byte for byte
        assert json.loads(hook.got[0])["job_id"] == jid
        time.sleep(2 * GRACE + 1)
        assert len(hook.got) == 1 and len(hook.seen) == 2
    finally:
        api.stop()
        hook.close()
