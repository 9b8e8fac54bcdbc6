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
from urllib.parse import unquote, urlparse, urlunparse

log = logging.getLogger("gsa.webhooks")


def sign(secret: str, timestamp: str, body: bytes) -> str:
    mac = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def verify(secret: str, timestamp: str, body: bytes, signature: str) -> bool:
    return hmac.compare_digest(sign(secret, timestamp, body), signature)


# IPv6 forms whose low 32 bits are an IPv4 address a stack may reach: NAT64, IPv4-compatible
# (::a.b.c.d, deprecated but still routed by some stacks) and SIIT (::ffff:0:a.b.c.d).
_EMBED_LOW32 = tuple(ipaddress.ip_network(n) for n in ("64:ff9b::/96", "::/96", "::ffff:0:0:0/96"))
# IANA special-purpose blocks that are not globally reachable, spelled out because older
# Pythons' is_global misses some of them (192.0.0.0/24 beyond /29, for one).
_NOT_GLOBAL = tuple(
    ipaddress.ip_network(n)
    for n in (
        "0.0.0.0/8",
        "10.0.0.0/8",
        "100.64.0.0/10",
        "127.0.0.0/8",
        "169.254.0.0/16",
        "172.16.0.0/12",
        "192.0.0.0/24",
        "192.0.2.0/24",
        "192.168.0.0/16",
        "198.18.0.0/15",
        "198.51.100.0/24",
        "203.0.113.0/24",
        "240.0.0.0/4",
        "::/127",
        "100::/64",
        "2001::/23",
        "2001:db8::/32",
        "fc00::/7",
        "fe80::/10",
    )
)


def non_global(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """True for every address a webhook must not reach: anything not globally routable
    (private, loopback, link-local, shared 100.64.0.0/10 such as the metadata address
    100.100.100.200, benchmarking, documentation, reserved, unspecified), multicast, and
    IPv6 forms that embed such an IPv4 address (mapped, 6to4, Teredo, NAT64)."""
    if not ip.is_global or ip.is_multicast or any(ip in n for n in _NOT_GLOBAL if n.version == ip.version):
        return True
    if ip.version == 6:
        embedded = [ip.ipv4_mapped, ip.sixtofour, *(ip.teredo or ())]
        if any(ip in n for n in _EMBED_LOW32):
            embedded.append(ipaddress.IPv4Address(int(ip) & 0xFFFFFFFF))
        return any(e is not None and non_global(e) for e in embedded)
    return False


_LOCALHOST = ("127.0.0.1", "::1")


def _loopback_only(host: str, allow_private: bool) -> list[str]:
    """The addresses of a loopback-only deployment's webhook host, never from DNS: a
    loopback literal, or `localhost` (pinned to 127.0.0.1 and ::1); anything else is refused."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        if host.lower().rstrip(".") != "localhost":
            raise ValueError(
                f"webhook host {host!r} is not a loopback address (this deployment is loopback-only)"
            ) from None
        return list(_LOCALHOST)
    # Loopback is what this mode is for: a literal is taken whatever GSA_WEBHOOK_ALLOW_PRIVATE says,
    # as `localhost` is (it used to refuse 127.0.0.1 and accept localhost without ALLOW_PRIVATE).
    if ip.is_loopback:
        return [str(ip)]
    if not allow_private and non_global(ip):
        raise ValueError(f"webhook host {host!r} resolves to a non-public address")
    raise ValueError(f"webhook host {host!r} is not a loopback address (this deployment is loopback-only)")


def check_url(url: str, allow_private: bool, *, resolve: bool | None = None, loopback_only: bool = False) -> list[str]:
    """Refuse non-http(s) URLs and, unless allow_private, a host with any address that
    is not global (SSRF). Returns the addresses it resolved, once: delivery connects to
    one of these (deliver_to), never resolving the name again (no DNS-rebinding window).
    resolve: look the name up even when allow_private (delivery does; a submission to a
    deployment that allows private hosts is not held up by DNS): default not allow_private.
    loopback_only (GSA_WEBHOOK_LOOPBACK_ONLY, test and fuzz deployments): only loopback
    literals and `localhost`, checked without DNS at submission and delivery alike."""
    u = urlparse(url)
    if u.scheme not in ("http", "https") or not u.hostname:
        raise ValueError("webhook url must be an absolute http(s) URL")
    try:
        port = u.port or (443 if u.scheme == "https" else 80)
        host = u.hostname.encode("idna").decode("ascii")
    except (ValueError, UnicodeError):
        raise ValueError("webhook url has an invalid host or port") from None
    if loopback_only:
        return _loopback_only(host, allow_private)
    if not (resolve if resolve is not None else not allow_private):
        return []  # nothing to check, and the name is looked up when it is used
    try:
        addrs = [ipaddress.ip_address(host)]  # a literal: nothing to resolve
    except ValueError:
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except (socket.gaierror, UnicodeError, OSError):
            raise ValueError(f"webhook host {u.hostname!r} does not resolve") from None
        addrs = list(dict.fromkeys(ipaddress.ip_address(ai[4][0].split("%", 1)[0]) for ai in infos))
    if not addrs:
        raise ValueError(f"webhook host {u.hostname!r} does not resolve")
    if not allow_private and any(non_global(ip) for ip in addrs):
        raise ValueError(f"webhook host {u.hostname!r} resolves to a non-public address")
    return [str(ip) for ip in addrs]


def pinned_request(url: str, addr: str) -> tuple[str, dict[str, str], dict[str, str]]:
    """(url, headers, httpx extensions) that send a request for `url` to the address
    `addr`: the URL names the address, the Host header keeps the URL's host and port,
    and for https the TLS server name (SNI and certificate check) stays the host name."""
    u = urlparse(url)
    literal = f"[{addr}]" if ":" in addr else addr
    netloc = literal + (f":{u.port}" if u.port else "")
    headers = {"Host": u.netloc.rpartition("@")[2]}
    if u.username is not None:  # userinfo would be lost with the host: send it as Basic auth
        import base64

        cred = f"{unquote(u.username)}:{unquote(u.password or '')}".encode()
        headers["Authorization"] = "Basic " + base64.b64encode(cred).decode()
    extensions = {"sni_hostname": u.hostname} if u.scheme == "https" else {}
    return urlunparse(u._replace(netloc=netloc)), headers, extensions


def deliver_to(url: str, addrs: list[str], body: bytes, headers: dict[str, str], timeout: float):
    """POST to the first of the checked addresses that accepts a connection. No proxy
    from the environment (it would connect elsewhere), no redirects."""
    import httpx  # lazy: only processes that send webhooks pay for loading it

    last: Exception | None = None
    with httpx.Client(timeout=timeout, trust_env=False, follow_redirects=False) as client:
        for addr in addrs:
            target, extra, extensions = pinned_request(url, addr)
            try:
                return client.post(target, content=body, headers={**headers, **extra}, extensions=extensions)
            except (httpx.ConnectError, httpx.ConnectTimeout) as exc:
                last = exc
    raise last if last is not None else ValueError("no address to deliver to")


def iso_time(t: float | None) -> str | None:
    """ISO-8601 UTC, as the REST API writes times (pydantic's form: ...T12:00:00.5Z)."""
    return None if t is None else datetime.fromtimestamp(t, UTC).isoformat().replace("+00:00", "Z")


def post_job_event(store, job_id: str, settings) -> None:
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
    url = job.webhook["url"]
    addrs = check_url(  # resolved once, here; checked again
        url,
        settings.webhook_allow_private,
        resolve=True,
        loopback_only=getattr(settings, "webhook_loopback_only", False),
    )
    r = deliver_to(url, addrs, body, headers, settings.webhook_timeout_s)
    r.raise_for_status()


def deliver_with_retries(store, job_id: str, settings) -> bool:
    """Embedded mode: a daemon thread with exponential backoff."""
    delay = 1.0
    for attempt in range(settings.webhook_max_attempts):
        try:
            post_job_event(store, job_id, settings)
            return True
        # the delivery thread's boundary: any failure (store, resolution, connection, HTTP status)
        # is logged and retried, then given up, never left to end the thread unseen
        except Exception as exc:  # noqa: BLE001
            log.warning("webhook for %s failed (attempt %d): %s", job_id, attempt + 1, exc)
            time.sleep(delay)
            delay = min(delay * 5, 600)
    return False
