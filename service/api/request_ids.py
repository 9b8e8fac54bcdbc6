"""Request ids: every response carries `X-Request-Id` (the client's, when it sent a
sane one, else a new one), and one access log line per request names it, so a
client's report can be found in the server's logs."""

from __future__ import annotations

import contextvars
import json
import logging
import re
import time
import uuid

from service.problems import Problem

HEADER = "x-request-id"
# Ids a client may choose: short, printable, no separators that could forge log fields.
_SANE = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")

request_id: contextvars.ContextVar[str | None] = contextvars.ContextVar("gsa_request_id", default=None)
access_log = logging.getLogger("gsa.api.access")
log = logging.getLogger("gsa.api")


class RequestIdFilter(logging.Filter):
    """Adds `request_id` to every record logged while a request is handled (or "-")."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = request_id.get() or "-"
        return True


class RequestIds:
    """Pure ASGI, outermost: the id is set before any other layer (body limit, error
    handlers) runs, so their problems carry it too."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        sent = dict(scope.get("headers") or []).get(HEADER.encode(), b"").decode("latin-1")
        rid = sent if _SANE.match(sent) else uuid.uuid4().hex
        token = request_id.set(rid)
        t0 = time.perf_counter()
        status = [500]
        started = [False]

        async def send_with_id(msg):
            if msg["type"] == "http.response.start":
                started[0] = True
                status[0] = msg["status"]
                msg = {**msg, "headers": [*msg.get("headers", []), (HEADER.encode(), rid.encode())]}
            await send(msg)

        try:
            await self.app(scope, receive, send_with_id)
        except Exception:
            # An error no handler answered. Starlette's catch-all answers outside every
            # middleware (so without this id): answer here, as problem+json with the id.
            if started[0]:
                raise
            log.exception("unhandled error on %s %s", scope["method"], scope["path"])
            await _internal_error(scope, send_with_id)
        finally:
            access_log.info(
                "%s %s %d %.1f ms",
                scope["method"],
                scope["path"],
                status[0],
                1000 * (time.perf_counter() - t0),
                extra={"request_id": rid},
            )
            request_id.reset(token)


async def _internal_error(scope, send) -> None:
    body = json.dumps(Problem(500, "internal-error", "Internal server error").to_dict(scope.get("path"))).encode()
    headers = [(b"content-type", b"application/problem+json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": 500, "headers": headers})
    await send({"type": "http.response.body", "body": body})
