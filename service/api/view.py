"""Results pages in the browser: a job's page (three synchronised 3D views, numbers,
renders), its files, the viewer's static code and the operator's list of jobs.

Browsers cannot send `Authorization: Bearer`, and an API key must never sit in a URL.
So an API call (`POST /v1/jobs/{id}/view-link`, `POST /v1/view-link`) returns a
short-lived signed link (service.api.view_links); opening it moves the token into an
HttpOnly cookie scoped to that page's path and redirects to the clean URL. A bearer
key still works on every route here (curl, scripts).
"""

from __future__ import annotations

import time
from functools import lru_cache
from urllib.parse import urlsplit

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, StreamingResponse
from pydantic import BaseModel

from gsa.viewer.page import (
    PAGE_HEADERS,
    STATIC_FILES,
    ResultView,
    ViewerNotBuilt,
    esc,
    fmt,
    is_many_result,
    layout,
    render_many_page,
    render_page,
)
from gsa.viewer.preview import PREVIEW_NAMES
from service.api.deps import AppBackend, Owner, get_backend
from service.api.openapi import problem_responses
from service.api.schemas import JobOut, RefineIn
from service.api.view_links import LinkError, sign, verify
from service.backend import Backend
from service.jobs import core
from service.jobs.many import is_many, many_preview_name
from service.models import Job, JobState
from service.problems import Problem, invalid_input, not_found

router = APIRouter()
COOKIE = "gsa_view"
STATIC = "/v1/view/static/"
JOBS_PAGE = "/v1/view/jobs"


class ViewLink(BaseModel):
    url: str
    expires_at: int


def _link(b: Backend, scope: str, owner: str, path: str) -> ViewLink:
    token, expires_at = sign(b.settings.view_secret, scope, owner, b.settings.view_link_ttl_s)
    return ViewLink(url=f"{path}?token={token}", expires_at=expires_at)


@router.post(
    "/v1/jobs/{job_id}/view-link",
    operation_id="createJobViewLink",
    status_code=201,
    response_model=ViewLink,
    tags=["view"],
    summary="A short-lived browser link to the job's results page",
    description="The link (relative URL) opens `GET /v1/jobs/{id}/view` without an API key; it expires after "
    "GSA_VIEW_LINK_TTL_S seconds (default 900).",
    responses=problem_responses(401, 404),
)
def create_job_view_link(job_id: str, owner: Owner, b: AppBackend) -> ViewLink:
    core.get_job(b, owner, job_id)  # another owner's job: 404, as everywhere
    return _link(b, f"job:{job_id}", owner, f"/v1/jobs/{job_id}/view")


@router.post(
    "/v1/view-link",
    operation_id="createJobsViewLink",
    status_code=201,
    response_model=ViewLink,
    tags=["view"],
    summary="A short-lived browser link to the list of the caller's jobs",
    responses=problem_responses(401),
)
def create_jobs_view_link(owner: Owner, b: AppBackend) -> ViewLink:
    return _link(b, "jobs", owner, JOBS_PAGE)


def browser_owner(request: Request, b: Backend, scope: str, token: str | None) -> str:
    """The caller of a browser route: a bearer key, else the signed token (query or cookie)."""
    auth = request.headers.get("authorization", "")
    if auth[:7].lower() == "bearer ":
        owner = core.owner_for_key(b, auth[7:].strip())
        if owner is None:
            raise Problem(401, "unauthorized", "Unauthorized", "the API key is not valid")
        return owner
    if b.settings.auth_disabled:
        return "anonymous"
    presented = token or request.cookies.get(COOKIE)
    if not presented:
        raise Problem(
            401,
            "unauthorized",
            "Unauthorized",
            "open this page through a link from POST /v1/jobs/{id}/view-link (or POST /v1/view-link)",
        )
    try:
        return verify(b.settings.view_secret, scope, presented).owner
    except LinkError as exc:
        if exc.expired:
            raise Problem(401, "link-expired", "Link expired", str(exc)) from None
        raise Problem(403, "link-invalid", "Link not valid for this page", str(exc)) from None


def _to_cookie(request: Request, token: str, path: str) -> RedirectResponse:
    """Token from the query into an HttpOnly cookie for `path`; back to the clean URL
    (the token leaves the address bar, history and Referer)."""
    resp = RedirectResponse(path, status_code=303)
    expires_at = int(token.rsplit(".", 2)[-2])
    resp.set_cookie(
        COOKIE,
        token,
        max_age=max(expires_at - int(time.time()), 1),
        path=path,
        httponly=True,
        samesite="lax",
        secure=request.url.scheme == "https",
    )
    resp.headers["Referrer-Policy"] = "no-referrer"
    resp.headers["Cache-Control"] = "no-store"
    return resp


def job_views(job: Job) -> tuple[list[ResultView], list[tuple[str, str]]]:
    """The job's results and the URLs of their previews and renders."""
    names = {a.name for a in job.artifacts}
    results = (job.result or {}).get("results") or []
    files = f"/v1/jobs/{job.id}/view/files/"
    prefix = (lambda i: f"s{i}/") if len(results) > 1 else (lambda i: "")
    views = []
    for i, result in enumerate(results):
        ref = job.sources[i] if i < len(job.sources) else None
        label = (ref.filename or ref.asset_id) if ref else f"source {i + 1}"
        p = prefix(i)
        preview = {k: files + p + n for k, n in PREVIEW_NAMES.items() if p + n in names}
        renders = [
            (n[len(p) :], files + n) for n in sorted(names) if n.startswith(f"{p}renders/") and n.endswith(".png")
        ]
        views.append(ResultView(label=label, result=result, preview=preview, renders=renders))
    extra = [(n, files + n) for n in sorted(names) if n.startswith("synchronized/") and n.endswith(".png")]
    return views, extra


@router.get("/v1/jobs/{job_id}/view", include_in_schema=False)
def job_page(job_id: str, request: Request, token: str | None = None):
    b = get_backend(request)
    owner = browser_owner(request, b, f"job:{job_id}", token)
    job = core.get_job(b, owner, job_id)
    if token:
        return _to_cookie(request, token, f"/v1/jobs/{job_id}/view")
    notes = list((job.result or {}).get("notes") or [])
    if job.state != JobState.succeeded:
        notes.insert(0, f"The job is {job.state.value} (stage {job.stage or '—'}, {job.progress:.0%}); reload later.")
        if job.error:
            notes.insert(1, f"{job.error.get('title', 'error')}: {job.error.get('detail', '')}")
    if job.state == JobState.succeeded and is_many(job) and is_many_result(job.result):
        return HTMLResponse(_many_page(job, notes), headers=PAGE_HEADERS)
    views, extra = job_views(job) if job.state == JobState.succeeded else ([], [])
    # Guided alignment: the job it refines and its follow-ups, each through its own signed link.
    links = [(f"refines job {job.parent_job}", _page_link(b, owner, job.parent_job))] if job.parent_job else []
    links += [(f"follow-up job {c}", _page_link(b, owner, c)) for c in job.children]
    page = render_page(
        f"Job {job.id}",
        views,
        STATIC,
        subtitle=f"target: {job.target.filename or job.target.asset_id} · {job.state.value}",
        notes=notes,
        extra_renders=extra,
        links=links,
        guide={"mode": "service", "refine": f"/v1/jobs/{job_id}/view/refine"},
        poll=None if job.terminal else f"/v1/jobs/{job_id}/view/state",
    )
    return HTMLResponse(page, headers=PAGE_HEADERS)


def _many_page(job: Job, notes: list[str]) -> str:
    """A many job's page: its models in the reference frame (their previews, preview/model{k}.splat),
    a toggle each, and the graph of its edges (gsa.viewer.page.render_many_page)."""
    names = {a.name for a in job.artifacts}
    files = f"/v1/jobs/{job.id}/view/files/"
    n = len(job.result["models"])
    previews = [files + many_preview_name(k) if many_preview_name(k) in names else None for k in range(n)]
    return render_many_page(
        f"Job {job.id}",
        job.result,
        previews,
        STATIC,
        subtitle=f"{n} models into one frame · {job.state.value}",
        notes=notes,
    )


def _page_link(b: Backend, owner: str, job_id: str) -> str:
    return _link(b, f"job:{job_id}", owner, f"/v1/jobs/{job_id}/view").url


@router.get("/v1/jobs/{job_id}/view/state", include_in_schema=False)
def job_state(job_id: str, request: Request) -> JSONResponse:
    """The job's state for its page, which polls it while the job runs (the page's cookie is
    scoped to /v1/jobs/{id}/view, so the API's GET /v1/jobs/{id} is not open to it)."""
    b = get_backend(request)
    job = core.get_job(b, browser_owner(request, b, f"job:{job_id}", None), job_id)
    body = {"id": job.id, "state": job.state.value, "stage": job.stage, "progress": job.progress}
    return JSONResponse({**body, "terminal": job.terminal}, headers={"Cache-Control": "no-store"})


def _same_origin(request: Request) -> None:
    """A page's POST carries its cookie; the browser's Origin must be this server's, so another
    site (SameSite=Lax stops cross-site ones, not another port or subdomain of the same site)
    cannot start jobs with it. Bearer-key callers are not browsers and skip this."""
    if request.headers.get("authorization", "")[:7].lower() == "bearer ":
        return
    origin = request.headers.get("origin")
    if not origin or urlsplit(origin).netloc != request.headers.get("host"):
        raise Problem(403, "cross-origin", "Cross-origin request", "this page's actions come from its own origin only")


@router.post("/v1/jobs/{job_id}/view/refine", include_in_schema=False)
async def job_page_refine(job_id: str, body: RefineIn, request: Request) -> JSONResponse:
    """The page's guide: POST /v1/jobs/{id}:refine for the page's cookie (same body and checks),
    or, with up_axes and no start, the automatic search again about those axes. Answers the
    follow-up job and a signed link to its page, which the page opens."""
    b = get_backend(request)
    owner = browser_owner(request, b, f"job:{job_id}", None)
    _same_origin(request)
    hints = body.model_dump(exclude_unset=True)
    if hints.get("up_axes") is not None and not any(hints.get(k) is not None for k in core.REFINE_STARTS):
        job = await run_in_threadpool(_search_again, b, owner, job_id, hints)
    else:
        job, _ = await run_in_threadpool(core.refine_job, b, owner, job_id, hints, None)
    request.app.state.metrics.job_created("http", owner)
    return JSONResponse(
        {"job": JobOut.from_job(job).model_dump(mode="json"), "view_url": _page_link(b, owner, job.id)},
        status_code=202,
        headers={"Location": f"/v1/jobs/{job.id}", "Cache-Control": "no-store"},
    )


def _search_again(b: Backend, owner: str, parent_id: str, hints: dict) -> Job:
    """A follow-up job on the parent's inputs and options with new up_axes (and front_axes and
    fixed_scale when given) and no start: the search runs again, turning only about the up axes. The REST refine
    takes exactly one start (alternative, init_transform, point_pairs); a person who only knows
    which way is up needs the search, not a local refinement of a pose they doubt. Linked to the
    parent as core.refine_job links its jobs."""
    parent = core.get_job(b, owner, parent_id)
    if not parent.terminal:
        raise Problem(409, "job-not-finished", "Job not finished", f"job {parent_id} is {parent.state.value}")
    if len(parent.sources) != 1:
        raise invalid_input(f"job {parent.id} aligns {len(parent.sources)} sources; refine takes a job with one source")
    options = {k: v for k, v in parent.options.items() if k not in ("init_transform", "point_pairs")}
    options = core.refined_hints(options, {k: hints[k] for k in core.REFINE_HINTS if k in hints})
    options = {k: v for k, v in options.items() if v is not None}
    core.check_request(b, 1, options, parent.webhook)  # 422 naming a bad up_axes or front_axes
    refs = (*parent.sources, parent.target)
    assets = [b.store.get_asset(ref.asset_id) for ref in refs]
    if any(a is None or a.owner != owner or a.key != ref.key for a, ref in zip(assets, refs)):
        raise Problem(409, "input-deleted", "Input deleted", f"job {parent_id}'s inputs were deleted: submit a new job")
    job_id, _ = core.claim(b, owner, None, "")
    job = core.create_job(b, owner, job_id, assets[:-1], assets[-1], options, parent.webhook, None, parent.id)
    with b.store.blob_lock(f"job-children:{parent_id}"):  # the lock core.refine_job takes
        now = b.store.get(parent_id)
        if now is not None:
            b.store.update(parent_id, children=[*now.children, job.id])
    return job


@router.get("/v1/jobs/{job_id}/view/files/{name:path}", include_in_schema=False)
def job_file(job_id: str, name: str, request: Request):
    b = get_backend(request)
    owner = browser_owner(request, b, f"job:{job_id}", None)
    _, art = core.get_artifact(b, owner, job_id, name)
    headers = {
        "Content-Length": str(art.size),
        "Cache-Control": "private, max-age=300",
        "X-Content-Type-Options": "nosniff",
        "Content-Security-Policy": "sandbox",
    }
    if art.size == 0:
        return Response(b"", media_type=art.content_type, headers=headers)
    return StreamingResponse(b.storage.open(art.key, 0, art.size - 1), media_type=art.content_type, headers=headers)


@lru_cache(maxsize=4)
def _static(name: str) -> bytes:
    from gsa.viewer.page import static_file

    return static_file(name)


@router.get("/v1/view/static/{name}", include_in_schema=False)
def static(name: str):
    if name not in STATIC_FILES:
        raise not_found("File", name)
    try:
        data = _static(name)
    except ViewerNotBuilt as exc:
        raise Problem(503, "viewer-not-built", "Viewer not built", str(exc)) from None
    return Response(data, media_type=STATIC_FILES[name], headers={"Cache-Control": "public, max-age=3600"})


def _age(seconds: float) -> str:
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            return f"{seconds / size:.0f} {unit}"
    return f"{seconds:.0f} s"


def _confidence(job: Job) -> tuple[float | None, bool]:
    result = job.result or {}
    if is_many_result(result):  # a many job: its models' confidences
        metrics = [m for m in result["models"] if isinstance(m, dict)]
    else:
        metrics = [r.get("metrics") or {} for r in result.get("results") or [] if isinstance(r, dict)]
    conf = [m["confidence"] for m in metrics if isinstance(m.get("confidence"), int | float)]
    return (min(conf) if conf else None), any(m.get("doubtful") for m in metrics)


@router.get(JOBS_PAGE, include_in_schema=False)
def jobs_page(request: Request, token: str | None = None, state: JobState | None = None):
    b = get_backend(request)
    owner = browser_owner(request, b, "jobs", token)
    if token:
        return _to_cookie(request, token, JOBS_PAGE)
    now = time.time()
    rows = []
    for job in b.store.list(owner, state, 200, None):
        conf, doubtful = _confidence(job)
        link = _link(b, f"job:{job.id}", owner, f"/v1/jobs/{job.id}/view").url
        sources = ", ".join(s.filename or s.asset_id for s in job.sources)
        rows.append(
            f'<tr class="state-{esc(job.state.value)}"><td><a href="{esc(link)}">{esc(job.id)}</a></td>'
            f"<td>{esc(job.state.value)}</td><td>{esc(job.stage or '')} {job.progress:.0%}</td>"
            f"<td>{esc(_age(now - job.created_at))}</td><td>{fmt(conf, 3)}</td>"
            f"<td>{'doubtful' if doubtful else ''}</td><td>{esc(sources)} → {esc(job.target.filename or '')}</td></tr>"
        )
    head = "".join(f"<th>{h}</th>" for h in ("job", "state", "stage", "age", "confidence", "flag", "models"))
    body = (
        f"<header><h1>Jobs of {esc(owner)}</h1><p class=sub>newest first, at most 200; the links open each "
        f"job's page and expire like this one</p></header><table class=jobs><tr>{head}</tr>{''.join(rows)}</table>"
    )
    return HTMLResponse(layout(f"GSA jobs: {owner}", body, STATIC), headers=PAGE_HEADERS)
