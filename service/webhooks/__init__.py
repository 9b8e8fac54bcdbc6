"""Per-job completion webhooks: signing, URL checks and sending (delivery) and the
RQ task that delivers one in distributed mode.

RQ resolves the task by the name it was enqueued under, "service.webhooks.deliver_job",
so the task keeps this address; it imports the backend only when called, which is
what lets the backend import service.webhooks.delivery without a cycle.
"""

from __future__ import annotations


def deliver_job(job_id: str) -> None:
    """RQ task (queue <name>-webhooks, with RQ Retry): raising means 'retry later'."""
    from service.backend import process_backend
    from service.webhooks.delivery import post_job_event

    b = process_backend()
    post_job_event(b.store, job_id, b.settings)
