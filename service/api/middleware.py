"""Problem-details error handlers, request-size limit and request metrics."""

from __future__ import annotations

import json
import logging
import time
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.deps import OWNER_SCOPE
from service.problems import Problem, too_large

log = logging.getLogger("gsa.api")
PROBLEM_JSON = "application/problem+json"


def problem_response(p: Problem, request: Request | None = None) -> JSONResponse:
    return JSONResponse(
        p.to_dict(request.url.path if request else None),
        status_code=p.status,
        media_type=PROBLEM_JSON,
        headers=p.headers or None,
    )


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem):
        return problem_response(exc, request)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg"), "type": e.get("type")} for e in exc.errors()]
        p = Problem(
            422,
            "validation-error",
            "Request validation failed",
            "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors),
            errors=errors,
        )
        return problem_response(p, request)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        kinds = {
            404: "not-found",
            405: "method-not-allowed",
            401: "unauthorized",
            403: "forbidden",
        }
        p = Problem(
            exc.status_code,
            kinds.get(exc.status_code, f"http-{exc.status_code}"),
            _title(exc.status_code),
            exc.detail if isinstance(exc.detail, str) else None,
        )
        p.headers = dict(exc.headers or {})
        return problem_response(p, request)

    @app.exception_handler(Exception)
    async def _unhandled(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(Problem(500, "internal-error", "Internal server error"), request)


def _title(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


DEFAULT_MAX_BODY_BYTES = 1 << 20


class BodyLimit:
    """Pure ASGI middleware: caps the request body (Content-Length or chunked)
    and answers 413 as soon as the cap is passed, without reading the rest.

    Multipart bodies (uploads) get `max_bytes_for(path)`; every other content type
    (JSON, form-urlencoded, none) at most `max_body_bytes` (default: the app's
    settings.max_body_bytes), whatever the path allows for uploads."""

    def __init__(self, app, max_bytes_for, max_body_bytes: int | None = None):
        self.app = app
        self.max_bytes_for = max_bytes_for  # path -> byte cap for multipart bodies
        self.max_body_bytes = max_body_bytes

    def _body_cap(self, scope) -> int:
        if self.max_body_bytes is not None:
            return self.max_body_bytes
        # Starlette puts the application in the scope before the middleware stack runs.
        backend = getattr(getattr(scope.get("app"), "state", None), "backend", None)
        return getattr(getattr(backend, "settings", None), "max_body_bytes", DEFAULT_MAX_BODY_BYTES)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT", "PATCH"):
            return await self.app(scope, receive, send)
        cap = self.max_bytes_for(scope["path"])
        headers = dict(scope.get("headers") or [])
        ctype = headers.get(b"content-type", b"").split(b";", 1)[0].strip().lower()
        if ctype != b"multipart/form-data":
            cap = min(cap, self._body_cap(scope))
        cl = headers.get(b"content-length")
        if cl is not None and cl.isdigit() and int(cl) > cap:
            return await _send_problem(scope, send, too_large(f"request body exceeds the limit of {cap} bytes"))
        seen = 0
        started = False

        async def limited_receive():
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > cap:
                    raise too_large(f"request body exceeds the limit of {cap} bytes")
            return msg

        async def tracking_send(msg):
            nonlocal started
            if msg["type"] == "http.response.start":
                started = True
            await send(msg)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except Problem as p:
            if started:
                raise
            await _send_problem(scope, send, p)


async def _send_problem(scope, send, p: Problem) -> None:
    body = json.dumps(p.to_dict(scope.get("path"))).encode()
    await send(
        {
            "type": "http.response.start",
            "status": p.status,
            "headers": [
                (b"content-type", PROBLEM_JSON.encode()),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class RequestMetrics:
    """Pure ASGI (BaseHTTPMiddleware costs a task and a queue per request):
    counts requests by route template and records latency."""

    def __init__(self, app, metrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = [500]

        async def send_wrapper(msg):
            if msg["type"] == "http.response.start":
                status[0] = msg["status"]
            await send(msg)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", "unmatched")
            self.metrics.requests.labels(scope["method"], path, str(status[0])).inc()
            self.metrics.latency.labels(scope["method"], path).observe(time.perf_counter() - t0)
            owner = scope.get(OWNER_SCOPE)  # set by service.api.deps.require_owner once the key is known
            if owner is not None:
                self.metrics.request_done(owner, status[0])
