"""Request dependencies: the backend and the caller's identity.

Dependencies and the small read handlers are `async` on purpose: their work
is sub-millisecond (a Redis/SQLite point read), and a threadpool hop per
request costs more than that under many concurrent pollers."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.backend import Backend
from service.jobs import core

# The request scope's key for the caller's owner, once its key is known (service.api.middleware.RequestMetrics).
OWNER_SCOPE = "gsa.owner"

bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`")


def get_backend(request: Request) -> Backend:
    return request.app.state.backend


async def require_owner(
    request: Request,
    creds: HTTPAuthorizationCredentials | None = Depends(bearer),
) -> str:
    """401 without a valid key, 429 past the tenant's request rate (service.jobs.core.authenticate).
    The owner is left in the request's scope (OWNER_SCOPE) before the rate is checked, so the
    request metrics count even a rate-limited request for its tenant (service.metrics)."""
    b = get_backend(request)
    key = creds.credentials if creds else None
    owner = core.owner_for_key(b, key)
    if owner is not None:
        request.scope[OWNER_SCOPE] = owner
    return core.authenticate(b, key)


# Handler parameter types: the caller's owner id (401 without a valid key) and the app's backend.
Owner = Annotated[str, Depends(require_owner)]
AppBackend = Annotated[Backend, Depends(get_backend)]
