"""RFC 9457 problem details, shared by HTTP (as JSON) and gRPC (as status)."""

from __future__ import annotations

import errno
import re
import sqlite3
import sys
from typing import Any

PROBLEM_BASE = "https://gsa.dev/problems/"


class Problem(Exception):
    """An error a client should see. `kind` becomes the problem `type` URI."""

    def __init__(
        self,
        status: int,
        kind: str,
        title: str,
        detail: str | None = None,
        **extra: Any,
    ):
        super().__init__(detail or title)
        self.status = status
        self.kind = kind
        self.title = title
        self.detail = detail
        self.extra = extra
        self.headers: dict[str, str] = {}

    def to_dict(self, instance: str | None = None) -> dict[str, Any]:
        d: dict[str, Any] = {
            "type": PROBLEM_BASE + self.kind,
            "title": self.title,
            "status": self.status,
        }
        if self.detail:
            d["detail"] = self.detail
        if instance:
            d["instance"] = instance
        d.update(self.extra)
        return d


# An id or name echoed back in a problem: the service's own are far shorter. A longer one is
# described, not repeated (a 9 KB id, echoed in gRPC's status message and trailing metadata both,
# passed the client's metadata limit: RESOURCE_EXHAUSTED instead of NOT_FOUND).
ECHO_MAX = 64
_ECHOABLE = re.compile(r"[A-Za-z0-9_.:/-]*")


def not_found(what: str, ident: str) -> Problem:
    # Same answer for "missing" and "owned by someone else": never leak existence.
    if len(ident) <= ECHO_MAX and _ECHOABLE.fullmatch(ident):
        said = f"id {ident!r}"
    else:
        said = f"the id given ({len(ident)} characters, not one of this service's)"
    return Problem(404, "not-found", f"{what} not found", f"no {what.lower()} with {said}")


def invalid_input(detail: str, **extra: Any) -> Problem:
    return Problem(422, "invalid-input", "Invalid input", detail, **extra)


def too_large(detail: str) -> Problem:
    return Problem(413, "payload-too-large", "Payload too large", detail)


def unavailable(detail: str, retry_after: int, kind: str = "service-unavailable") -> Problem:
    p = Problem(503, kind, "Service unavailable", detail)
    p.headers["Retry-After"] = str(max(int(retry_after), 1))
    return p


# errno values that mean "no room left": answered 507, not 503.
_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG}
# OSErrors that are about a particular file (a bug or lost data), not the infrastructure.
_NOT_INFRA = (FileNotFoundError, IsADirectoryError, NotADirectoryError, FileExistsError)


def store_errors() -> tuple[type[Exception], ...]:
    """What the job store or queue raises when it cannot answer: SQLite's errors, I/O
    errors and, when Redis is in use at all, Redis's (`except store_errors():`)."""
    rexc = sys.modules.get("redis.exceptions")
    return (sqlite3.Error, OSError, *((rexc.RedisError,) if rexc is not None else ()))


def infrastructure_problem(exc: BaseException, retry_after: int = 5) -> Problem | None:
    """The problem for a failure of the service's own infrastructure (job store
    unreachable, storage full or failing), or None if `exc` is not one.

    Redis connection/timeout errors and a locked/unavailable SQLite database are
    503 with Retry-After; a full disk (ENOSPC/EDQUOT, "database or disk is full")
    is 507; other storage I/O errors (EIO, EROFS, EACCES...) are 503."""
    rexc = sys.modules.get("redis.exceptions")  # only if Redis is in use at all
    if rexc is not None and isinstance(exc, (rexc.ConnectionError, rexc.TimeoutError)):
        return unavailable(
            f"the job store (Redis) is unreachable ({type(exc).__name__}); retry later",
            retry_after,
            "store-unavailable",
        )
    if isinstance(exc, sqlite3.OperationalError):
        msg = str(exc).lower()
        if "full" in msg:
            return _insufficient(f"the job database is full: {exc}")
        if any(k in msg for k in ("locked", "busy", "disk i/o", "unable to open", "readonly")):
            return unavailable(
                f"the job database is unavailable ({exc}); retry later", retry_after, "store-unavailable"
            )
        return None
    if isinstance(exc, OSError) and not isinstance(exc, _NOT_INFRA) and type(exc).__module__ == "builtins":
        if exc.errno in _FULL:
            return _insufficient("the service's storage is full; retry later or contact the operator")
        return unavailable(
            f"storage I/O error ({exc.strerror or type(exc).__name__}); retry later",
            retry_after,
            "storage-unavailable",
        )
    return None


def _insufficient(detail: str) -> Problem:
    return Problem(507, "insufficient-storage", "Insufficient storage", detail)
