"""N-way registration jobs (issue 30): N assets into one reference frame with the library's
gsa.align.many.align_many, as one job over both front ends (POST /v1/many-jobs, gRPC
SubmitManyAlignment).

A many job is an ordinary job record: `sources` are its N assets in the order given, `target`
its reference asset (so deletion, retention, quotas, cancel and artifacts work as for any job),
and `options` holds the per-edge align() options plus `many` ({reference, edges, merged, merge}),
which marks it. Its result is many.json's content; its artifacts many.json, when asked merged.ply, and
each model's preview for the results page (preview/model{k}.splat)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

from service.backend import Backend, RQQueue
from service.jobs import core, quotas
from service.jobs.models import Asset, Job, JobState
from service.jobs.options import GUIDANCE_OPTIONS, SERVICE_OPTIONS, align_options, validate_options
from service.problems import invalid_input
from service.webhooks.delivery import check_url
from service.worker.edges import (
    LocalEdgePool,
    RedisEdgePool,
    edge_from_payload,
    enqueue_helpers,
    live_workers,
    work_through,
)
from service.worker.leases import JobProgress, finish_attempt, job_workspace

EDGE_MODES = ("auto", "all", "sparse")
MERGE_MODES = ("concat", "dedup")
# Per-pair options that have no meaning across a graph of N models (guidance names one pair's
# files) or that name a pair job's outputs: refused, naming the option.
REFUSED_OPTIONS = (*sorted(SERVICE_OPTIONS), *GUIDANCE_OPTIONS)


@dataclass
class ManyRequest:
    """A many-job submission as a front end parsed it."""

    assets: list[str]
    reference: str | None
    edges: str
    merged: bool
    merge: str
    options: dict[str, Any]  # align() options for every edge (service.jobs.options.parse_options)
    webhook: dict | None

    def identity(self, api: str) -> dict[str, Any]:
        return {
            "many": self.assets,
            "reference": self.reference,
            "edges": self.edges,
            "merged": self.merged,
            "merge": self.merge,
            "options": self.options,
            "webhook": self.webhook,
            "api": api,
        }


def is_many(job: Job) -> bool:
    return isinstance(job.options.get("many"), dict)


def _check_shape(b: Backend, req: ManyRequest) -> None:
    n, cap = len(req.assets), b.settings.max_many_models
    if n < 2:
        raise invalid_input(f"a many job needs at least 2 assets, got {n}", option="assets", minimum=2, value=n)
    if n > cap:
        raise invalid_input(
            f"{n} assets exceeds the limit of {cap} models per many job (GSA_MAX_MANY_MODELS)",
            option="assets",
            maximum=cap,
            value=n,
        )
    if len(set(req.assets)) != n:
        raise invalid_input("each asset may appear once in 'assets'", option="assets")
    if req.reference is not None and req.reference not in req.assets:
        raise invalid_input("'reference' must be one of 'assets'", option="reference")
    if req.edges not in EDGE_MODES:
        raise invalid_input(f"'edges' must be one of {', '.join(EDGE_MODES)}", option="edges", allowed=list(EDGE_MODES))
    if req.edges == "all" and n * (n - 1) // 2 > b.settings.max_many_edges:
        raise invalid_input(
            f"'edges: all' over {n} models is {n * (n - 1) // 2} pairwise alignments, past the limit of "
            f"{b.settings.max_many_edges} per many job (GSA_MAX_MANY_EDGES): use 'auto' or 'sparse', "
            "which align each model with its most similar few",
            option="edges",
            maximum=b.settings.max_many_edges,
            value=n * (n - 1) // 2,
        )
    if req.merge not in MERGE_MODES:
        raise invalid_input(
            f"'merge' must be one of {', '.join(MERGE_MODES)}", option="merge", allowed=list(MERGE_MODES)
        )
    refused = [k for k in REFUSED_OPTIONS if req.options.get(k) is not None]
    if refused:
        raise invalid_input(
            f"option(s) a many job does not take: {', '.join(refused)} (artifacts: set 'merged'; "
            "guidance names one pair's files)",
            option=refused[0],
        )


def check_many_memory(b: Backend, assets: list[Asset], options: dict[str, Any], merged: bool) -> None:
    """422 (option memory) when the job's predicted peak is above the workers' budget: the
    largest pair's job (service.jobs.memory) plus every other model held in memory, plus the
    merged model when asked."""
    budget_mb = b.settings.worker_memory_mb
    if not budget_mb:
        return
    from service.jobs.memory import MARGIN, MB, gaussian_bytes, predict_job_memory

    sized = sorted(((a.n_gaussians or 0, gaussian_bytes(a.n_gaussians, a.size)) for a in assets), reverse=True)
    (n1, b1), (n2, b2) = sized[0], sized[1]
    held = sum(n * bb for n, bb in sized[2:]) + (sum(n * bb for n, bb in sized) if merged else 0)
    predicted = predict_job_memory(options, [n1], n2, [b1], b2) + int(MARGIN * held)
    if predicted > budget_mb * MB:
        mb = -(-predicted // MB)
        raise invalid_input(
            f"this many job is predicted to need {mb} MB of worker memory, above the workers' budget of "
            f"{budget_mb} MB (GSA_WORKER_MEMORY_MB): fewer or smaller models, or no merged model",
            option="memory",
            value=mb,
            maximum=budget_mb,
        )


def submit_many(b: Backend, owner: str, req: ManyRequest, idempotency_key: str | None, api: str) -> tuple[Job, bool]:
    """Check and create a many job (the one path of HTTP and gRPC). 422 for a bad request
    (fewer than 2 or more than GSA_MAX_MANY_MODELS assets, an image set, options a many job
    does not take), 404 for an asset that is not the caller's, 429/507 as any job. Returns
    (job, created): created is False for a replayed Idempotency-Key."""
    quotas.check_active_jobs(b, owner)
    quotas.check_storage(b, owner)
    _check_shape(b, req)
    options = validate_options(dict(req.options), b.settings)
    if req.webhook:
        s = b.settings
        try:
            check_url(req.webhook["url"], s.webhook_allow_private, loopback_only=s.webhook_loopback_only)
        except ValueError as exc:
            raise invalid_input(str(exc)) from None
    assets = [core.get_asset(b, owner, a) for a in req.assets]
    for a in assets:
        if a.kind != "ply":
            raise invalid_input(f"asset {a.id} is an image set: a many job takes 3DGS models", option="assets")
    check_many_memory(b, assets, options, req.merged)
    reference = req.reference or req.assets[0]
    options["many"] = {"reference": reference, "edges": req.edges, "merged": req.merged, "merge": req.merge}
    job_id, existing = core.claim(b, owner, idempotency_key, core.fingerprint(req.identity(api)))
    if existing is not None:
        return existing, False
    ref_asset = assets[req.assets.index(reference)]
    try:
        job = core.create_job(b, owner, job_id, assets, ref_asset, options, req.webhook, idempotency_key)
    except BaseException:
        core.release(b, owner, idempotency_key)
        raise
    return job, True


# ---------------------------------------------------------------- the worker's side


class _EdgeReports:
    """The edges' reports as the job's stage and progress: while this attempt runs edge k of E
    the stage reads "edge k/E: <align stage>"; while it waits on the helpers' edges,
    "d/E edges done: waiting". Progress is (edges done + the running stage's span) / E."""

    def __init__(self, prog: JobProgress):
        self.prog = prog
        self.edge: int | None = None
        self.done = 0

    def __call__(self, k: int, total: int, stage: str, fraction: float) -> None:
        p = self.prog
        if k != self.edge:
            self.edge = k
            p.n, p.part, p.label = total, min(self.done, total - 1), f"edge {k + 1}/{total}"
            p.last_write = 0.0  # show the new edge at once
        p(stage, fraction)

    def edges_done(self, done: int, total: int, waiting: bool) -> None:
        p = self.prog
        if waiting and (done > self.done or self.edge is not None):
            self.edge = None
            p.n, p.part, p.label = total, min(done, total - 1), f"{done}/{total} edges done"
            p.overall = max(p.overall, min(done / total, 0.999))
            p.last_write = 0.0
            p("waiting", 0.0)
        self.done = done
        p.check(force=waiting)


def _model_entries(data: dict, job: Job, models, result) -> None:
    """Each model's asset, file name, format and its transform in file coordinates (the
    internal-frame one is many.json's own)."""
    from gsa.io import frames  # numpy only

    ref_fmt = models[result.reference].metadata.get("format", "ply")
    for entry, ref, model, t in zip(data["models"], job.sources, models, result.transforms):
        fmt = model.metadata.get("format", "ply")
        entry["asset_id"] = ref.asset_id
        entry["filename"] = ref.filename
        entry["format"] = fmt
        entry["file_transform"] = frames.file_transform(t, fmt, ref_fmt).matrix().tolist()


def many_preview_name(k: int) -> str:
    """The artifact of model k's preview for the results page: a .splat in its own frame."""
    return f"preview/model{k}.splat"


def _previews(models, work) -> list[tuple[str, object]]:
    """Each model's .splat preview in its own (internal) frame, which the results page places by
    its transform; together at most the one-model preview cap (gsa.viewer.preview)."""
    from gsa.viewer.preview import DEFAULT_MAX_GAUSSIANS, downsample, write_splat

    cap = max(DEFAULT_MAX_GAUSSIANS // len(models), 20_000)
    return [
        (many_preview_name(k), write_splat(downsample(m, cap), work / many_preview_name(k)))
        for k, m in enumerate(models)
    ]


def _run_edges(backend: Backend, job: Job, token: str, prog: JobProgress, models, names, reference, pairs, opts):
    """Every edge's pairwise alignment (spread over the workers: service.worker.edges), then the
    global step; the edges' results say which worker ran each."""
    from gsa.align.many import ManyError, model_frame, solve_graph

    t0 = time.perf_counter()
    reports = _EdgeReports(prog)
    helpers = 0
    if isinstance(backend.queue, RQQueue) and all(ref.kind == "ply" for ref in job.sources):
        pool = RedisEdgePool(backend.redis, job.id, token)
        pool.create(pairs, ttl_s=backend.settings.job_timeout_s + backend.settings.lease_s)
        helpers = enqueue_helpers(backend, job, token, min(len(pairs) - 1, live_workers(backend) - 1))
    else:
        pool = LocalEdgePool(pairs)
    try:
        payloads = work_through(pool, models, opts, check=prog.check, on_edge=reports, on_progress=reports.edges_done)
    finally:
        pool.delete()
    graph = [edge_from_payload(i, j, p) for (i, j), p in zip(pairs, payloads)]
    frames = [model_frame(m) for m in models]
    t_pairwise = time.perf_counter() - t0
    try:
        result = solve_graph(len(models), graph, reference, [c for c, _ in frames], [s for _, s in frames], names)
    except ManyError as exc:  # input the global step cannot work with: the client's
        raise invalid_input(str(exc)) from None
    result.timings.update(
        pairwise=t_pairwise,
        per_edge=sum(e.seconds for e in graph) / max(len(graph), 1),
        edges=len(graph),
        helpers=helpers,
        total=time.perf_counter() - t0,
    )
    return result, [p["worker"] for p in payloads]


def run_many(backend: Backend, job: Job, token: str, prog: JobProgress, art_prefix: str) -> JobState | None:
    """One attempt of a many job: load the N models, align_many (reports per edge; a cancel
    stops it at the next report), write many.json (and merged.ply), store them."""
    from gsa.align.many import merged_model, select_edges  # lazy: the aligner's modules
    from gsa.align.outputs import write_json
    from gsa.io.ply import write_ply
    from service.jobs.inputs import load_input
    from service.storage.artifacts import store_artifacts

    many = job.options["many"]
    opts = align_options(backend.settings, job.options)
    names = [ref.asset_id for ref in job.sources]
    reference = names.index(many["reference"])
    with job_workspace(job.id, token) as work:
        prog.n, prog.part = 1, 0
        models = []
        for i, ref in enumerate(job.sources):
            prog("loading", i / len(job.sources))
            models.append(load_input(backend, ref, work, f"model{i}", prog))
        for name, m in zip(names, models):
            if len(m) < 3:  # as align_many refuses it, before any edge runs
                raise invalid_input(f"{name}: {len(m)} Gaussians; at least 3 are needed")
        pairs = select_edges(models, many["edges"])
        result, workers = _run_edges(backend, job, token, prog, models, names, reference, pairs, opts)
        prog.label = None
        prog("writing", 0.0)
        data = result.to_dict()
        for entry, worker in zip(data["edges"], workers):
            entry["worker"] = worker  # which worker ran the edge (they spread over the queue's workers)
        _model_entries(data, job, models, result)
        files = []
        if many.get("merged"):
            merged, removed = merged_model(models, result, many.get("merge", "concat"))
            write_ply(merged, work / "merged.ply")
            data["merge"] = {"mode": many.get("merge", "concat"), "removed": removed, "gaussians": len(merged)}
            del merged
        data["job_id"] = job.id
        write_json(data, work / "many.json")
        data = json.loads((work / "many.json").read_text())  # the result is many.json's content, as stored
        files.insert(0, ("many.json", work / "many.json"))
        if many.get("merged"):
            files.append(("merged.ply", work / "merged.ply"))
        files += _previews(models, work)
        prog.check(force=True)
        artifacts = store_artifacts(backend, files, art_prefix, progress=prog)
    ok = finish_attempt(
        backend, job.id, token, JobState.succeeded, result=data, artifacts=artifacts, progress=1.0, stage="done"
    )
    return JobState.succeeded if ok else None
