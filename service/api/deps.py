"""Request dependencies: the backend and the caller's identity.

Dependencies and the small read handlers are `async` on purpose: their work
is sub-millisecond (a Redis/SQLite point read), and a threadpool hop per
request costs more than that under many concurrent pollers."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service import quotas
from service.backend import Backend
from service.problems import Problem

bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`")


def get_backend(request: Request) -> Backend:
    return request.app.state.backend


def owner_for_key(backend: Backend, presented: str | None) -> str | None:
    """The owner of an API key, or None. Compares against every key with
    hmac.compare_digest so timing reveals neither the key nor which one matched."""
    if backend.settings.auth_disabled:
        return "anonymous"
    if not presented:
        return None
    found = None
    p = presented.encode()
    for key, owner in backend.settings.api_keys.items():
        if hmac.compare_digest(key.encode(), p):
            found = owner
    return found


async def require_owner(
    request: Request,
    creds: HTTPAuthorizationCredentials | None = Depends(bearer),
) -> str:
    backend = get_backend(request)
    owner = owner_for_key(backend, creds.credentials if creds else None)
    if owner is None:
        p = Problem(
            401,
            "unauthorized",
            "Unauthorized",
            "a valid API key is required: Authorization: Bearer <key>" if creds is None else "the API key is not valid",
        )
        p.headers["WWW-Authenticate"] = 'Bearer realm="gsa"'
        raise p
    quotas.check_rate(backend, owner)  # 429 with Retry-After past the tenant's request rate
    return owner


# Handler parameter types: the caller's owner id (401 without a valid key) and the app's backend.
Owner = Annotated[str, Depends(require_owner)]
B = Annotated[Backend, Depends(get_backend)]
