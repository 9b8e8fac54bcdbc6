"""A small Python client for the GSA alignment service (HTTP, httpx).

    from gsa.client import GSAClient
    with GSAClient("http://localhost:8000", api_key="...") as c:
        job = c.submit("source.ply", "target.ply", options={"stages": ["coarse"]})
        job = c.wait(job["id"])
        c.fetch_all(job["id"], "out/")

Part of the library package so the CLI can use it without the server extras;
it never imports `service`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx

from gsa import errors

TERMINAL = ("succeeded", "failed", "cancelled")
# GSAClient.wait's pauses before retrying a poll that failed in transport: 25.5 s in all, time for
# an API process to be restarted.
WAIT_RETRY_DELAYS = (0.5, 1.0, 2.0, 4.0, 8.0, 10.0)


class ServiceError(errors.GSAError):
    """An error answer from the service; `.problem` holds the RFC 9457 body."""

    def __init__(self, status: int, problem: dict, request_id: str | None = None):
        self.status = status
        self.problem = problem
        self.request_id = request_id
        super().__init__(self.describe())

    def describe(self) -> str:
        """One line: the problem's title and status, its detail, and the request id that
        finds the answer in the server's log ("Invalid input (422): photos.zip: ... (request 3f2a...)")."""
        p = self.problem if isinstance(self.problem, dict) else {}
        title = str(p.get("title") or "").strip() or _reason(self.status)
        text = f"{title} ({self.status})"
        detail = " ".join(str(p.get("detail") or "").split())
        if detail:
            text += f": {detail}"
        if self.request_id:
            text += f" (request {self.request_id})"
        return text


# The name ServiceError had before the library's base took it (gsa.errors.GSAError): still
# imported by service/cli.py and tests/service/test_http.py.
GSAError = ServiceError


def _reason(status: int) -> str:
    from http import HTTPStatus

    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


class ServiceUnreachable(errors.GSAError, ConnectionError):
    """The service could not be reached at all (refused, unresolvable host,
    connect timeout, connection dropped): no answer to report, only why."""

    def __init__(self, url: str, reason: str):
        self.url, self.reason = url, reason
        super().__init__(f"cannot reach {url}: {reason}")


def _reason(exc: BaseException) -> str:
    """'connection refused', 'name or service not known', 'timed out', ...: the
    operating system's words for why a connection failed, without errno noise."""
    if isinstance(exc, httpx.TimeoutException):
        return "timed out"
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:  # the OSError under httpx/httpcore's wrappers
        seen.add(id(e))
        if isinstance(e, OSError) and (e.strerror or e.errno):
            return (e.strerror or os.strerror(e.errno)).lower()
        e = e.__cause__ or e.__context__
    text = str(exc)
    if text.startswith("[Errno") and "] " in text:
        text = text.split("] ", 1)[1]
    return (text or type(exc).__name__).lower()


class _Client(httpx.Client):
    """httpx.Client whose failures to connect (or connections dropped before any
    answer) raise ServiceUnreachable naming the server, not an httpx traceback."""

    def __init__(self, *args, server: str, **kwargs):
        super().__init__(*args, **kwargs)
        self.server = server

    def send(self, request: httpx.Request, **kwargs) -> httpx.Response:
        try:
            return super().send(request, **kwargs)
        except (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError) as exc:
            raise ServiceUnreachable(self.server, _reason(exc)) from exc


class JobFailed(ServiceError):
    def __init__(self, job: dict):
        self.job = job
        err = job.get("error") or {"title": f"job {job.get('state')}"}
        super().__init__(int(err.get("status", 0) or 0), err)


class GSAClient:
    def __init__(
        self,
        base_url: str | None = None,
        api_key: str | None = None,
        timeout: float = 60.0,
        transport: httpx.BaseTransport | None = None,
    ):
        base_url = base_url or os.environ.get("GSA_SERVER", "http://127.0.0.1:8000")
        api_key = api_key if api_key is not None else os.environ.get("GSA_API_KEY")
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.base_url = str(base_url).rstrip("/")
        self.http = _Client(
            base_url=base_url, headers=headers, timeout=timeout, transport=transport, server=self.base_url
        )
        self._etags: dict[str, tuple[str, dict]] = {}

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> GSAClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @staticmethod
    def _check(r: httpx.Response) -> httpx.Response:
        if r.status_code >= 400:
            try:
                body = r.json()
            except ValueError:
                body = None
            if not isinstance(body, dict):  # not problem+json: a proxy's page, plain text
                body = {"title": r.reason_phrase, "detail": r.text[:500]}
            raise ServiceError(r.status_code, body, r.headers.get("x-request-id"))
        return r

    # ---------------------------------------------------------------- assets
    def upload(self, path: str | os.PathLike) -> dict:
        p = Path(path)
        with open(p, "rb") as fh:
            return self._check(self.http.post("/v1/assets", files={"file": (p.name, fh)})).json()

    def list_assets(self, limit: int = 50, cursor: str | None = None) -> dict:
        """One page of your assets, newest first: {"items": [...], "next_cursor": ...}."""
        params = {k: v for k, v in {"limit": limit, "cursor": cursor}.items() if v is not None}
        return self._check(self.http.get("/v1/assets", params=params)).json()

    # ------------------------------------------------------------------ jobs
    def submit(
        self,
        source: str | os.PathLike | Sequence[str | os.PathLike],
        target: str | os.PathLike,
        options: dict[str, Any] | None = None,
        *,
        webhook_url: str | None = None,
        webhook_secret: str | None = None,
        idempotency_key: str | None = None,
    ) -> dict:
        """Upload model files (.ply or image .zip) and create a job; several sources = multi-model job."""
        import json

        sources = [source] if isinstance(source, (str, os.PathLike)) else list(source)
        data = {"options": json.dumps(options or {})}
        if webhook_url:
            data["webhook_url"] = webhook_url
            if webhook_secret:
                data["webhook_secret"] = webhook_secret
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        with ExitStack() as stack:
            files = [("source", (Path(s).name, stack.enter_context(open(s, "rb")))) for s in sources]
            files.append(("target", (Path(target).name, stack.enter_context(open(target, "rb")))))
            r = self.http.post("/v1/jobs", files=files, data=data, headers=headers)
        return self._check(r).json()

    def submit_many(
        self,
        asset_ids: Sequence[str],
        *,
        reference: str | None = None,
        edges: str = "auto",
        merged: bool = False,
        merge: str = "concat",
        options: dict | None = None,
        webhook: dict | None = None,
        idempotency_key: str | None = None,
    ) -> dict:
        """A many job (POST /v1/many-jobs): every model's Sim(3) into the reference's frame; wait
        for it as any job, its result is many.json's content (docs/service.md)."""
        body: dict = {"assets": list(asset_ids), "edges": edges, "merged": merged, "merge": merge}
        body["options"] = options or {}
        if reference is not None:
            body["reference"] = reference
        if webhook:
            body["webhook"] = webhook
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        return self._check(self.http.post("/v1/many-jobs", json=body, headers=headers)).json()

    def status(self, job_id: str) -> dict:
        """The job; polls reuse the ETag so an unchanged job costs a 304."""
        headers = {}
        cached = self._etags.get(job_id)
        if cached:
            headers["If-None-Match"] = cached[0]
        r = self.http.get(f"/v1/jobs/{job_id}", headers=headers)
        if r.status_code == 304 and cached:
            return cached[1]
        job = self._check(r).json()
        if "etag" in r.headers:
            self._etags[job_id] = (r.headers["etag"], job)
        return job

    def list(self, state: str | None = None, limit: int = 50, cursor: str | None = None) -> dict:
        params = {k: v for k, v in {"state": state, "limit": limit, "cursor": cursor}.items() if v is not None}
        return self._check(self.http.get("/v1/jobs", params=params)).json()

    def cancel(self, job_id: str) -> dict:
        return self._check(self.http.post(f"/v1/jobs/{job_id}:cancel")).json()

    def wait(
        self,
        job_id: str,
        timeout: float | None = None,
        poll: float = 0.5,
        on_progress: Callable[[dict], None] | None = None,
        raise_on_failure: bool = True,
        retries: int = len(WAIT_RETRY_DELAYS),
    ) -> dict:
        """Poll until the job is final. Once the service has answered, a poll that fails in
        transport (connection refused or dropped, a read timed out: an API restarting, a proxy
        closing a keep-alive connection) is retried `retries` times, after WAIT_RETRY_DELAYS;
        only then is it raised. A service never reached at all is raised at once."""
        deadline = None if timeout is None else time.monotonic() + timeout
        last = None
        answered, failures = False, 0
        while True:
            try:
                job = self.status(job_id)
            except (ServiceUnreachable, httpx.TransportError):
                if not answered or failures >= retries:  # a wrong URL or a server down fails at once
                    raise
                time.sleep(WAIT_RETRY_DELAYS[min(failures, len(WAIT_RETRY_DELAYS) - 1)])
                failures += 1
                continue
            answered, failures = True, 0
            if on_progress and (job["state"], job.get("stage"), job.get("progress")) != last:
                last = (job["state"], job.get("stage"), job.get("progress"))
                on_progress(job)
            if job["state"] in TERMINAL:
                if raise_on_failure and job["state"] != "succeeded":
                    raise JobFailed(job)
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['state']} after {timeout} s")
            time.sleep(poll)

    def fetch(self, job_id: str, name: str, dest: str | os.PathLike) -> Path:
        """Download one artifact, resuming a partial file with a Range request."""
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        part = dest.with_name(dest.name + ".part")
        have = part.stat().st_size if part.exists() else 0
        headers = {"Range": f"bytes={have}-"} if have else {}
        with self.http.stream("GET", f"/v1/jobs/{job_id}/artifacts/{name}", headers=headers) as r:
            if r.status_code == 416:
                have = 0
            elif r.status_code >= 400:
                r.read()
                self._check(r)
            mode = "ab" if r.status_code == 206 else "wb"
            if r.status_code != 416:
                with open(part, mode) as fh:
                    fh.writelines(r.iter_bytes(1 << 20))
        if not part.exists():
            return self.fetch(job_id, name, dest)
        os.replace(part, dest)
        return dest

    def fetch_all(
        self,
        job_id: str,
        out_dir: str | os.PathLike,
        names: Sequence[str] | None = None,
    ) -> list[Path]:
        job = self.status(job_id)
        arts = [a["name"] for a in job.get("artifacts", [])]
        return [self.fetch(job_id, n, Path(out_dir) / n) for n in (names or arts)]
