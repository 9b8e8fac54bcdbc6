"""Per-job completion webhooks: HMAC-SHA256-signed POSTs, retried off the worker path.

This module only signs, checks and sends; it knows nothing of the backend, so
the backend (embedded mode delivers from a thread) can import it. The RQ task
that delivers in distributed mode is service.webhooks.deliver_job.

Signature: header `X-GSA-Signature: sha256=<hex>` over `<timestamp>.<body>`
with `X-GSA-Timestamp: <unix seconds>`; receivers recompute it with the
shared secret and reject stale timestamps (replay protection).
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import logging
import socket
import time
from datetime import UTC, datetime
from urllib.parse import urlparse

log = logging.getLogger("gsa.webhooks")


def sign(secret: str, timestamp: str, body: bytes) -> str:
    mac = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def verify(secret: str, timestamp: str, body: bytes, signature: str) -> bool:
    return hmac.compare_digest(sign(secret, timestamp, body), signature)


def check_url(url: str, allow_private: bool) -> None:
    """Refuse non-http(s) and, unless allowed, private/loopback targets (SSRF)."""
    u = urlparse(url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise ValueError("webhook url must be an absolute http(s) URL")
    if allow_private:
        return
    try:
        addrs = {ai[4][0] for ai in socket.getaddrinfo(u.hostname, u.port or 443)}
    except socket.gaierror:
        raise ValueError(f"webhook host {u.hostname!r} does not resolve") from None
    for a in addrs:
        ip = ipaddress.ip_address(a)
        if ip.is_private or ip.is_loopback or ip.is_link_local or ip.is_reserved or ip.is_multicast:
            raise ValueError(f"webhook host {u.hostname!r} resolves to a non-public address")


def iso_time(t: float | None) -> str | None:
    """ISO-8601 UTC, as the REST API writes times (pydantic's form: ...T12:00:00.5Z)."""
    return None if t is None else datetime.fromtimestamp(t, UTC).isoformat().replace("+00:00", "Z")


def post_job_event(store, job_id: str, settings) -> None:
    import httpx  # lazy: only processes that send webhooks pay for loading it

    job = store.get(job_id)
    if job is None or not job.webhook:
        return
    body = json.dumps(
        {
            "job_id": job.id,
            "state": job.state.value,
            "finished_at": iso_time(job.finished_at),
            "attempts": job.attempts,
        },
        separators=(",", ":"),
    ).encode()
    ts = str(int(time.time()))
    headers = {
        "Content-Type": "application/json",
        "X-GSA-Timestamp": ts,
        "X-GSA-Job": job.id,
    }
    secret = job.webhook.get("secret") or settings.webhook_secret
    if secret:
        headers["X-GSA-Signature"] = sign(secret, ts, body)
    check_url(job.webhook["url"], settings.webhook_allow_private)
    r = httpx.post(
        job.webhook["url"],
        content=body,
        headers=headers,
        timeout=settings.webhook_timeout_s,
    )
    r.raise_for_status()


def deliver_with_retries(store, job_id: str, settings) -> bool:
    """Embedded mode: a daemon thread with exponential backoff."""
    delay = 1.0
    for attempt in range(settings.webhook_max_attempts):
        try:
            post_job_event(store, job_id, settings)
            return True
        except Exception as exc:
            log.warning("webhook for %s failed (attempt %d): %s", job_id, attempt + 1, exc)
            time.sleep(delay)
            delay = min(delay * 5, 600)
    return False
