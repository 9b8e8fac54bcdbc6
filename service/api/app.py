"""The FastAPI application factory.

Lifespan starts the backend's background threads: the reaper (both modes),
the in-process workers (embedded mode) and, if configured, the gRPC server
sharing this process's job store and queue.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.middleware.cors import CORSMiddleware

from service.api import artifacts, assets, jobs, many, ops, view
from service.api.middleware import BodyLimit, RequestMetrics, install_error_handlers, problem_response
from service.api.openapi import custom_openapi
from service.api.request_ids import RequestIds
from service.backend import Backend, make_backend
from service.jobs.retention import start_retention
from service.metrics import Metrics
from service.problems import Problem, infrastructure_problem
from service.settings import Settings, get_settings
from service.worker.leases import start_reaper
from service.worker.runners import start_embedded_workers

log = logging.getLogger("gsa.api")


def create_app(
    settings: Settings | None = None,
    backend: Backend | None = None,
    *,
    run_workers: bool = True,
) -> FastAPI:
    settings = settings or get_settings()
    if not settings.api_keys and not settings.auth_disabled:
        log.warning("no API keys configured (GSA_API_KEYS) and auth not disabled: every request will get 401")

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        b = app.state.backend
        stop = threading.Event()
        start_reaper(b, stop)
        start_retention(b, stop)
        if b.settings.embedded and run_workers:
            start_embedded_workers(b, stop)
        grpc_server = None
        if b.settings.grpc_port:
            from service.rpc.server import serve_grpc  # lazy: grpcio loads only when gRPC is on

            grpc_server = serve_grpc(b, b.settings.grpc_port, metrics=app.state.metrics)
        try:
            yield
        finally:
            stop.set()
            if grpc_server is not None:
                grpc_server.stop(grace=2)

    app = FastAPI(
        title="GSA alignment service",
        version="1.0.0",
        summary="Align 3D Gaussian Splatting models with a similarity transform Sim(3).",
        description="Jobs are asynchronous: POST /v1/jobs answers 202 with a Location to poll. "
        "Errors are RFC 9457 application/problem+json. Authenticate with `Authorization: Bearer <api key>`.",
        lifespan=lifespan,
        docs_url="/docs" if settings.public_docs else None,
        redoc_url=None,
        openapi_url="/openapi.json" if settings.public_docs else None,
        generate_unique_id_function=operation_id,
    )
    app.state.backend = backend or make_backend(settings)
    app.state.metrics = Metrics(app.state.backend)
    install_error_handlers(app)
    install_infrastructure_handlers(app, settings.unavailable_retry_after_s)
    s = app.state.backend.settings
    per_file = s.max_upload_bytes

    def cap(path: str) -> int:
        if path == "/v1/assets":
            return per_file * 2 + (1 << 20) if s.max_images <= 2 else per_file * s.max_images + (1 << 20)
        if path == "/v1/jobs":
            return per_file * (s.max_sources + 1 + 2 * s.max_images) + (1 << 20)
        return 1 << 20

    app.add_middleware(BodyLimit, max_bytes_for=cap)
    app.add_middleware(RequestMetrics, metrics=app.state.metrics)
    if s.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=s.cors_origins,
            allow_methods=["GET", "HEAD", "POST", "DELETE", "OPTIONS"],
            allow_headers=[
                "Authorization",
                "Content-Type",
                "Idempotency-Key",
                "If-None-Match",
                "If-Range",
                "Range",
                "X-Request-Id",
            ],
            expose_headers=["X-Request-Id", "ETag", "Location", "Retry-After", "Content-Range"],
        )
    app.add_middleware(RequestIds)  # outermost: every response, even a refused one, carries its id
    # This order is the order of the paths in the OpenAPI document.
    for resource in (ops, assets, jobs, artifacts, view, many):
        app.include_router(resource.router)

    app.openapi = lambda: custom_openapi(app)
    return app


def operation_id(route) -> str:
    """A route without an explicit operation_id gets its handler's name in camelCase
    (get_job -> getJob), not FastAPI's path-and-method id, so ids stay stable."""
    head, *rest = route.name.split("_")
    return head + "".join(w[:1].upper() + w[1:] for w in rest)


def install_infrastructure_handlers(app: FastAPI, retry_after: int) -> None:
    """Job store unreachable (Redis down, SQLite locked) -> 503 + Retry-After;
    storage full -> 507; other storage I/O errors -> 503; all problem+json.

    These are specific handlers, so Starlette's ExceptionMiddleware answers them
    like any other problem and the keep-alive connection stays usable (the
    catch-all Exception handler re-raises to the server after answering)."""
    classes: list[type[BaseException]] = [sqlite3.OperationalError, OSError]
    try:
        import redis.exceptions as rexc

        classes += [rexc.ConnectionError, rexc.TimeoutError]
    except ImportError:  # embedded mode without the Redis client
        pass

    async def _infrastructure(request: Request, exc: Exception):
        p = infrastructure_problem(exc, retry_after)
        if p is None:
            log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
            p = Problem(500, "internal-error", "Internal server error")
        else:
            log.warning("%s %s: %s (%s: %s)", request.method, request.url.path, p.status, type(exc).__name__, exc)
        return problem_response(p, request)

    for cls in classes:
        app.add_exception_handler(cls, _infrastructure)
