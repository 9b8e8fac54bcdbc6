"""Per-job completion webhooks: the RQ task that delivers one (distributed mode).

RQ resolves the task by the name it was enqueued under,
"service.webhooks.deliver_job", so the task keeps this address. Signing, URL
checks and sending live in service.webhook_delivery, which the backend imports
for embedded-mode delivery: keeping the two apart is what lets this module
import the backend without a cycle.
"""

from __future__ import annotations

from service.backend import process_backend
from service.webhook_delivery import post_job_event


def deliver_job(job_id: str) -> None:
    """RQ task (queue <name>-webhooks, with RQ Retry): raising means 'retry later'."""
    b = process_backend()
    post_job_event(b.store, job_id, b.settings)
