"""Signed browser links for the results pages (no API key ever goes into a URL).

A token is `v1.<owner, base64url>.<expiry, unix seconds>.<HMAC-SHA256, base64url>`
signed over (scope, owner, expiry) with the server's GSA_VIEW_SECRET. The scope is
what the URL opens ("job:<id>" for one job's page, "jobs" for the operator's list)
and is not in the token: a link for one job does not open another. Without a
configured secret each process makes a random one at start (links then work only
against the process that signed them: set GSA_VIEW_SECRET for several API processes).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
import time
from dataclasses import dataclass

_process_secret = secrets.token_bytes(32)


class LinkError(Exception):
    """A token that does not open this page: `expired` says whether it was only too old."""

    def __init__(self, message: str, *, expired: bool = False):
        super().__init__(message)
        self.expired = expired


@dataclass(frozen=True)
class Grant:
    owner: str
    expires_at: int


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def _key(secret: str | None) -> bytes:
    return secret.encode() if secret else _process_secret


def _mac(secret: str | None, scope: str, owner: str, expires_at: int) -> bytes:
    msg = f"gsa-view-v1\n{scope}\n{owner}\n{expires_at}".encode()
    return hmac.new(_key(secret), msg, hashlib.sha256).digest()


def sign(secret: str | None, scope: str, owner: str, ttl_s: float, now: float | None = None) -> tuple[str, int]:
    """A token for `scope` and `owner`, valid `ttl_s` seconds; returns (token, expiry)."""
    expires_at = int((time.time() if now is None else now) + ttl_s)
    mac = _mac(secret, scope, owner, expires_at)
    return f"v1.{_b64(owner.encode())}.{expires_at}.{_b64(mac)}", expires_at


def verify(secret: str | None, scope: str, token: str, now: float | None = None) -> Grant:
    """The grant in a token for `scope`; LinkError if it is malformed, forged, for
    another scope or expired (checked after the signature: a forged expiry is forged)."""
    parts = token.split(".") if isinstance(token, str) and len(token) < 4096 else []
    if len(parts) != 4 or parts[0] != "v1" or not parts[2].isdigit():
        raise LinkError("the link is malformed")
    try:
        owner, mac = _unb64(parts[1]).decode(), _unb64(parts[3])
    except (ValueError, UnicodeDecodeError):
        raise LinkError("the link is malformed") from None
    expires_at = int(parts[2])
    if not hmac.compare_digest(mac, _mac(secret, scope, owner, expires_at)):
        raise LinkError("the link's signature does not match (altered, or for another page)")
    if expires_at < (time.time() if now is None else now):
        raise LinkError("the link has expired: ask the API for a new one", expired=True)
    return Grant(owner=owner, expires_at=expires_at)
