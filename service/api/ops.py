"""Operations endpoints: liveness, readiness, Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.api.deps import AppBackend, Owner
from service.api.openapi import problem_responses
from service.api.schemas import Health
from service.problems import Problem

router = APIRouter()


@router.get("/healthz", operation_id="healthz", response_model=Health, tags=["ops"], summary="Liveness")
async def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    operation_id="readyz",
    response_model=Health,
    tags=["ops"],
    summary="Readiness: job store and storage reachable",
    responses=problem_responses(503),
)
def readyz(b: AppBackend):
    checks = b.ready()
    if not all(checks.values()):
        bad = ", ".join(k for k, v in checks.items() if not v)
        p = Problem(503, "not-ready", "Service not ready", f"failing: {bad}", checks=checks)
        p.headers["Retry-After"] = str(b.settings.unavailable_retry_after_s)
        raise p
    return Health(status="ready", checks=checks)


@router.get(
    "/metrics",
    operation_id="getMetrics",
    tags=["ops"],
    summary="Prometheus metrics (operators: GSA_METRICS_OWNERS)",
    description="Service-wide numbers (every tenant's job counts): only keys whose owner is in "
    "GSA_METRICS_OWNERS may read them; any other key is 403.",
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}, **problem_responses(401, 403)},
    response_class=Response,
)
def metrics(request: Request, owner: Owner, b: AppBackend):
    s = b.settings
    if not s.auth_disabled and owner not in s.metrics_owners:
        raise Problem(
            403,
            "forbidden",
            "Forbidden",
            "/metrics shows every tenant's numbers: it is for operators (owners in GSA_METRICS_OWNERS)",
        )
    return Response(
        generate_latest(request.app.state.metrics.registry),
        media_type=CONTENT_TYPE_LATEST,
    )
