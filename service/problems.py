"""RFC 9457 problem details, shared by HTTP (as JSON) and gRPC (as status)."""

from __future__ import annotations

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


def not_found(what: str, ident: str) -> Problem:
    # Same answer for "missing" and "owned by someone else": never leak existence.
    return Problem(404, "not-found", f"{what} not found", f"no {what.lower()} with id {ident!r}")


def invalid_input(detail: str, **extra: Any) -> Problem:
    return Problem(422, "invalid-input", "Invalid input", detail, **extra)


def too_large(detail: str) -> Problem:
    return Problem(413, "payload-too-large", "Payload too large", detail)
