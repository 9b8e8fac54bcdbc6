"""Per-job completion webhooks: the RQ task that delivers one (distributed mode).

RQ resolves the task by the name it was enqueued under,
"service.webhooks.deliver_job", so the task keeps this address. Signing, URL
checks and sending live in service.webhook_delivery (re-exported here), which
the backend imports for embedded-mode delivery: keeping the two apart is what
lets this module import the backend without a cycle.
"""

from __future__ import annotations

from service.backend import process_backend
from service.webhook_delivery import (  # noqa: F401  (public names, re-exported)
    check_url,
    deliver_with_retries,
    post_job_event,
    postpone,
    settle,
    sign,
    verify,
)


def deliver_job(job_id: str) -> None:
    """RQ task (queue <name>-webhooks, with RQ Retry): raising means 'retry later'.
    A failure keeps the webhook owed (postponed past RQ's next retry); the last
    one gives up and clears it (service.webhook_delivery's outbox)."""
    from rq import get_current_job  # lazy: see service.backend.RQQueue

    b = process_backend()
    try:
        post_job_event(b.store, job_id, b.settings)
    except Exception:
        rq_job = get_current_job()
        left = getattr(rq_job, "retries_left", None) if rq_job is not None else None
        if left:
            try:
                retry_in = float(rq_job.get_retry_interval())
            except Exception:
                retry_in = 600.0
            postpone(b.store, job_id, retry_in, b.settings)
        else:
            settle(b.store, job_id)
        raise
