"""gRPC front end (proto/gsa/v1/alignment.proto) over the same store and queue
as HTTP, plus the standard grpc.health.v1 service and server reflection."""

from __future__ import annotations

import json
import logging
import tempfile
import time
from concurrent import futures

import grpc
import numpy as np
from google.protobuf import empty_pb2
from google.protobuf.timestamp_pb2 import Timestamp
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from service.backend import Backend
from service.jobs import core, many, retention
from service.jobs.options import parse_options
from service.models import Job, JobState
from service.problems import Problem, invalid_input, too_large
from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg

log = logging.getLogger("gsa.grpc")
SERVICE_NAME = "gsa.v1.AlignmentService"

_STATE = {
    JobState.queued: pb.JOB_STATE_QUEUED,
    JobState.running: pb.JOB_STATE_RUNNING,
    JobState.succeeded: pb.JOB_STATE_SUCCEEDED,
    JobState.failed: pb.JOB_STATE_FAILED,
    JobState.cancelled: pb.JOB_STATE_CANCELLED,
}
_CODE = {
    400: grpc.StatusCode.INVALID_ARGUMENT,
    401: grpc.StatusCode.UNAUTHENTICATED,
    403: grpc.StatusCode.PERMISSION_DENIED,
    404: grpc.StatusCode.NOT_FOUND,
    409: grpc.StatusCode.FAILED_PRECONDITION,
    413: grpc.StatusCode.RESOURCE_EXHAUSTED,
    429: grpc.StatusCode.RESOURCE_EXHAUSTED,  # a tenant's rate or job limit (service.jobs.quotas)
    415: grpc.StatusCode.INVALID_ARGUMENT,
    416: grpc.StatusCode.OUT_OF_RANGE,
    422: grpc.StatusCode.INVALID_ARGUMENT,
    503: grpc.StatusCode.UNAVAILABLE,
    507: grpc.StatusCode.RESOURCE_EXHAUSTED,  # storage full, or a tenant's storage quota
}


def _ts(t: float | None) -> Timestamp | None:
    if t is None:
        return None
    ts = Timestamp()
    ts.FromNanoseconds(int(t * 1e9))
    return ts


def _transform(d: dict) -> pb.Transform:
    metrics = d.get("metrics") or {}
    return pb.Transform(
        matrix=[float(x) for row in d["transform"] for x in row],
        scale=float(d["scale"]),
        rotation=[float(x) for row in d["rotation"] for x in row],
        quaternion=[float(x) for x in d["quaternion"]],
        translation=[float(x) for x in d["translation"]],
        confidence=float(metrics.get("confidence", 0.0)),
        ambiguous=bool(metrics.get("ambiguous", False)),
        doubtful=bool(metrics.get("doubtful", False)),
        quaternion_xyzw=[float(x) for x in d.get("quaternion_xyzw") or []],
        inverse_matrix=[float(x) for row in d.get("inverse_transform") or [] for x in row],
        gltf_node_matrix=[float(x) for x in d.get("gltf_node_matrix") or []],
        source_frame=_frame((d.get("frames") or {}).get("source")),
        target_frame=_frame((d.get("frames") or {}).get("target")),
    )


def _many_model(m: dict) -> dict:
    """A many job's model entry in a pair result's shape: its file_transform (the transform
    contract's file coordinates) with its own confidence."""
    from gsa.sim3 import Sim3  # numpy only

    t = Sim3.from_matrix(np.asarray(m["file_transform"], np.float64))
    return {**t.to_dict(), "metrics": {"confidence": m["confidence"], "doubtful": m["doubtful"]}}


def _frame(f: dict | None) -> pb.Frame | None:
    if not f:
        return None
    return pb.Frame(**{k: str(f.get(k) or "") for k in ("format", "convention", "handedness", "up_axis", "units")})


def job_to_pb(job: Job) -> pb.Job:
    msg = pb.Job(
        id=job.id,
        state=_STATE[job.state],
        stage=job.stage or "",
        progress=job.progress,
        created_at=_ts(job.created_at),
        updated_at=_ts(job.updated_at),
        started_at=_ts(job.started_at),
        finished_at=_ts(job.finished_at),
        attempts=job.attempts,
        max_attempts=job.max_attempts,
        cancel_requested=job.cancel_requested,
        source_asset_ids=[s.asset_id for s in job.sources],
        target_asset_id=job.target.asset_id,
        options_json=json.dumps(job.options),
        artifacts=[pb.Artifact(name=a.name, size=a.size, content_type=a.content_type) for a in job.artifacts],
        parent_job=job.parent_job or "",
        children=job.children,
    )
    if job.state == JobState.queued and job.next_attempt_at is not None:
        msg.next_attempt_at.CopyFrom(_ts(job.next_attempt_at))
    if job.error:
        msg.error.CopyFrom(
            pb.Problem(
                type=job.error.get("type", ""),
                title=job.error.get("title", ""),
                status=int(job.error.get("status", 0)),
                detail=job.error.get("detail") or "",
            )
        )
    if job.result:
        msg.result_json = json.dumps(job.result)
        results = job.result.get("results") or []
        try:
            if "models" in job.result:  # a many job: one per model, into the reference's file coordinates
                results = [_many_model(m) for m in job.result["models"]]
            msg.transforms.extend(_transform(r) for r in results)
            if results:
                msg.transform.CopyFrom(msg.transforms[0])
        except (
            KeyError,
            TypeError,
        ):  # a result shape this build does not know: result_json still has it
            pass
    return msg


def _point(p: pb.Point) -> list[float]:
    return [p.x, p.y, p.z]


def guidance_options(g: pb.Guidance) -> dict:
    """A Guidance message as the JSON options it stands for (init_transform, point_pairs,
    up_axes, front_axes, fixed_scale): only the ones set. Their values are checked with the other options."""
    out: dict = {}
    if g.init_transform:
        m = list(g.init_transform)
        out["init_transform"] = [m[i : i + 4] for i in range(0, 16, 4)] if len(m) == 16 else m
    if g.HasField("point_pairs"):
        pp = g.point_pairs
        out["point_pairs"] = {"source": [_point(x) for x in pp.source], "target": [_point(x) for x in pp.target]}
    if g.HasField("up_axes"):
        out["up_axes"] = [_point(g.up_axes.source), _point(g.up_axes.target)]
    if g.HasField("front_axes"):
        out["front_axes"] = [_point(g.front_axes.source), _point(g.front_axes.target)]
    if g.HasField("fixed_scale"):
        out["fixed_scale"] = g.fixed_scale
    return out


def _header_options(header: pb.SubmitHeader) -> dict:
    """options_json with the Guidance message's hints merged in (each given in one place only)."""
    try:
        options = json.loads(header.options_json or "{}")
    except ValueError:
        raise invalid_input("options_json is not JSON") from None
    if not isinstance(options, dict):
        raise invalid_input("options_json must be a JSON object")
    if header.HasField("guidance"):
        hints = guidance_options(header.guidance)
        twice = sorted(set(hints) & {k for k, v in options.items() if v is not None})
        if twice:
            raise invalid_input(f"{', '.join(twice)} given both in guidance and in options_json", option=twice[0])
        options.update(hints)
    return parse_options(options, "invalid options")


def _job_request(header: pb.SubmitHeader, files: dict[tuple[int, int], core.Upload]) -> core.JobRequest:
    """A SubmitAlignment as the service core's JobRequest: uploaded sources, else the header's
    asset ids; the uploaded target, else target_asset_id."""
    options = _header_options(header)
    webhook = None
    if header.HasField("webhook") and header.webhook.url:
        webhook = {"url": header.webhook.url}
        if header.webhook.secret:
            webhook["secret"] = header.webhook.secret
    src_up = sorted(k for k in files if k[0] == pb.ROLE_SOURCE)
    tgt_up = [k for k in files if k[0] == pb.ROLE_TARGET]
    if len(tgt_up) > 1 or (not tgt_up and not header.target_asset_id):
        raise invalid_input("exactly one target is required (chunks or target_asset_id)")
    sources = [files[k] for k in src_up] if src_up else list(header.source_asset_ids)
    target = files[tgt_up[0]] if tgt_up else header.target_asset_id
    identity = {
        "files": {f"{r}:{i}": f for (r, i), f in sorted(files.items())},
        "sources": list(header.source_asset_ids) if not src_up else [],
        "target": header.target_asset_id if not tgt_up else "",
        "options": options,
        "webhook": webhook,
        "api": "grpc",
    }
    return core.JobRequest(sources, target, options, webhook, identity, separators=(", ", ": "))


# Status details and trailing metadata share the client's metadata limit (grpc's defaults: 8 KiB soft,
# 16 KiB hard): past it the client sees RESOURCE_EXHAUSTED, not the status sent. Whatever a
# problem repeats from the request (names, values, lists) is clipped to stay well within it.
_TEXT_MAX = 512
_PROBLEM_MAX = 4096


def _clip(text: str) -> str:
    return text if len(text) <= _TEXT_MAX else text[: _TEXT_MAX - 1] + "…"


def _bounded_problem(p: Problem) -> str:
    """The problem as gsa-problem's JSON, within _PROBLEM_MAX bytes: long strings clipped, and
    if still too long, only its RFC 9457 members."""
    d = {k: _clip(v) if isinstance(v, str) else v for k, v in p.to_dict().items()}
    text = json.dumps(d)
    if len(text.encode()) > _PROBLEM_MAX:
        text = json.dumps({k: d[k] for k in ("type", "title", "status", "detail") if k in d})
    return text


class AlignmentServicer(pbg.AlignmentServiceServicer):
    def __init__(self, backend: Backend, metrics=None):
        self.b = backend
        self.metrics = metrics

    # -------------------------------------------------------------- helpers
    def _owner(self, context) -> str:
        md = dict(context.invocation_metadata())
        auth = md.get("authorization", "")
        key = auth[7:] if auth.lower().startswith("bearer ") else None
        return self._guard(lambda: core.authenticate(self.b, key, "a valid API key is required"), context)

    @staticmethod
    def _abort(context, p: Problem):
        md = [("gsa-problem", _bounded_problem(p))]
        if "Retry-After" in p.headers:  # as HTTP's header: 429 (rate, jobs), 503
            md.append(("retry-after", p.headers["Retry-After"]))
        context.set_trailing_metadata(tuple(md))
        context.abort(_CODE.get(p.status, grpc.StatusCode.INTERNAL), _clip(p.detail or p.title))

    def _guard(self, fn, context):
        try:
            return fn()
        except Problem as p:
            self._abort(context, p)

    # ------------------------------------------------------------------ rpcs
    def SubmitAlignment(self, request_iterator, context):
        owner = self._owner(context)
        return self._guard(lambda: self._submit(owner, request_iterator), context)

    def _submit(self, owner, request_iterator):
        files: dict[tuple[int, int], core.Upload] = {}  # (role, index) -> its chunks, spooled
        try:
            header = self._receive(request_iterator, files)
            job, created = core.submit_job(self.b, owner, _job_request(header, files), header.idempotency_key or None)
            if created and self.metrics is not None:
                self.metrics.job_created("grpc", owner)
            return job_to_pb(job)
        finally:
            for f in files.values():
                f.file.close()

    def _receive(self, request_iterator, files: dict[tuple[int, int], core.Upload]) -> pb.SubmitHeader:
        """Read a SubmitAlignment stream: its one SubmitHeader (returned), then FileChunks,
        spooled into `files` by (role, index) within the upload limits."""
        s = self.b.settings
        header = None
        sizes: dict[tuple[int, int], int] = {}
        for req in request_iterator:
            kind = req.WhichOneof("payload")
            if kind == "header":
                if header is not None:
                    raise invalid_input("more than one SubmitHeader")
                header = req.header
                continue
            if kind != "chunk":
                raise invalid_input("empty SubmitRequest")
            if header is None:
                raise invalid_input("the first message must be a SubmitHeader")
            c = req.chunk
            if c.role not in (pb.ROLE_SOURCE, pb.ROLE_TARGET):
                raise invalid_input("FileChunk.role must be ROLE_SOURCE or ROLE_TARGET")
            k = (c.role, c.index)
            if k not in files:
                if len(files) > s.max_sources + 1:
                    raise too_large("too many files")
                files[k] = core.Upload(tempfile.SpooledTemporaryFile(max_size=1 << 20), c.filename or None)
                sizes[k] = 0
            sizes[k] += len(c.data)
            if sizes[k] > s.max_upload_bytes:
                raise too_large(f"file {files[k].filename!r} exceeds the limit of {s.max_upload_bytes} bytes")
            files[k].file.write(c.data)
        if header is None:
            raise invalid_input("no SubmitHeader received")
        return header

    def RefineJob(self, request, context):
        owner = self._owner(context)

        def refine():
            hints = guidance_options(request.guidance) if request.HasField("guidance") else {}
            if request.HasField("alternative"):
                hints["alternative"] = request.alternative
            job, created = core.refine_job(self.b, owner, request.job_id, hints, request.idempotency_key or None)
            if created and self.metrics is not None:
                self.metrics.job_created("grpc", owner)
            return job_to_pb(job)

        return self._guard(refine, context)

    def SubmitManyAlignment(self, request, context):
        owner = self._owner(context)

        def submit():
            try:
                options = json.loads(request.options_json or "{}")
            except ValueError:
                raise invalid_input("options_json is not JSON") from None
            webhook = None
            if request.HasField("webhook") and request.webhook.url:
                webhook = {"url": request.webhook.url}
                if request.webhook.secret:
                    webhook["secret"] = request.webhook.secret
            req = many.ManyRequest(
                assets=list(request.asset_ids),
                reference=request.reference_asset_id or None,
                edges=request.edges or "auto",
                merged=request.merged,
                merge=request.merge or "concat",
                options=parse_options(options, "invalid options"),
                webhook=webhook,
            )
            job, created = many.submit_many(self.b, owner, req, request.idempotency_key or None, "grpc")
            if created and self.metrics is not None:
                self.metrics.job_created("grpc", owner)
            return job_to_pb(job)

        return self._guard(submit, context)

    def GetJob(self, request, context):
        owner = self._owner(context)
        return self._guard(lambda: job_to_pb(core.get_job(self.b, owner, request.job_id)), context)

    def CancelJob(self, request, context):
        owner = self._owner(context)
        return self._guard(lambda: job_to_pb(core.cancel_job(self.b, owner, request.job_id)), context)

    def DeleteJob(self, request, context):
        owner = self._owner(context)

        def delete():
            retention.delete_job(self.b, owner, request.job_id)
            return empty_pb2.Empty()

        return self._guard(delete, context)

    def WatchJob(self, request, context):
        owner = self._owner(context)
        job = self._guard(lambda: core.get_job(self.b, owner, request.job_id), context)
        last = None
        while context.is_active():
            job = self.b.store.get(request.job_id)
            if job is None:
                return
            if job.version != last:
                last = job.version
                yield job_to_pb(job)
            if job.terminal:
                return
            time.sleep(0.1)

    def GetArtifact(self, request, context):
        owner = self._owner(context)
        _, art = self._guard(
            lambda: core.get_artifact(self.b, owner, request.job_id, request.name),
            context,
        )
        if request.offset < 0 or request.length < 0:  # not read as 0 / "to the end"
            self._abort(
                context,
                invalid_input(
                    f"offset ({request.offset}) and length ({request.length}) must not be negative",
                    option="offset" if request.offset < 0 else "length",
                    minimum=0,
                ),
            )
        start = int(request.offset)
        if start >= art.size and art.size > 0:
            self._abort(
                context,
                Problem(
                    416,
                    "range-not-satisfiable",
                    "Range Not Satisfiable",
                    f"offset {start} is past the end ({art.size} bytes)",
                ),
            )
        end = art.size - 1 if request.length == 0 else min(art.size - 1, start + int(request.length) - 1)
        pos = start
        for chunk in self.b.storage.open(art.key, start, end):
            yield pb.ArtifactChunk(
                data=chunk,
                offset=pos,
                total_size=art.size,
                content_type=art.content_type,
            )
            pos += len(chunk)


def serve_grpc(
    backend: Backend, port: int, host: str | None = None, metrics=None, max_workers: int = 16
) -> grpc.Server:
    """Serve gRPC on host:port; host defaults to settings.grpc_host (loopback unless configured)."""
    s = backend.settings
    host = host or s.grpc_host
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"  # an IPv6 literal
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=max_workers),
        options=[
            ("grpc.max_receive_message_length", 8 * 1024 * 1024),
            ("grpc.max_send_message_length", 8 * 1024 * 1024),
        ],
    )
    pbg.add_AlignmentServiceServicer_to_server(AlignmentServicer(backend, metrics), server)
    hs = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(hs, server)
    hs.set("", health_pb2.HealthCheckResponse.SERVING)
    hs.set(SERVICE_NAME, health_pb2.HealthCheckResponse.SERVING)
    names = (
        pb.DESCRIPTOR.services_by_name["AlignmentService"].full_name,
        health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
        reflection.SERVICE_NAME,
    )
    reflection.enable_server_reflection(names, server)
    bound = server.add_insecure_port(f"{host}:{port}")
    if bound == 0:
        raise RuntimeError(f"cannot bind gRPC port {port}")
    server.start()
    log.info(
        "gRPC listening on %s:%d (max upload %d bytes per file)",
        host,
        bound,
        s.max_upload_bytes,
    )
    return server
