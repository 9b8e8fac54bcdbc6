"""One attempt of a many job (service.jobs.many has the job type and its submission): load the N
models, run the edges (spread over the workers: service.worker.edges), the global step of
gsa.align.many, and store many.json, merged.ply and the previews."""

from __future__ import annotations

import json
import time

from service.backend import Backend, RQQueue
from service.jobs.many import many_preview_name
from service.jobs.options import align_options
from service.models import Job, JobState
from service.problems import invalid_input
from service.worker.edges import (
    LocalEdgePool,
    RedisEdgePool,
    edge_from_payload,
    enqueue_edge_tasks,
    live_workers,
    work_through,
)
from service.worker.leases import JobProgress, finish_attempt, job_workspace


class _EdgeReports:
    """The edges' reports as the job's stage and progress: while this attempt runs edge k of E
    the stage reads "edge k/E: <align stage>"; while it waits on the other workers' edges,
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
    from gsa.align.many_frames import frame_evidence

    t0 = time.perf_counter()
    reports = _EdgeReports(prog)
    sent = 0
    if isinstance(backend.queue, RQQueue) and all(ref.kind == "ply" for ref in job.sources):
        pool = RedisEdgePool(backend.redis, job.id, token)
        pool.create(pairs, ttl_s=backend.settings.job_timeout_s + backend.settings.lease_s)
        if live_workers(backend) > 1:  # one worker runs them all itself: no task to wait behind it
            sent = enqueue_edge_tasks(backend, job, token, len(pairs) - 1)
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
        result = solve_graph(
            len(models),
            graph,
            reference,
            [c for c, _ in frames],
            [s for _, s in frames],
            names,
            frames=frame_evidence(models, pairs),
        )
    except ManyError as exc:  # input the global step cannot work with: the client's
        raise invalid_input(str(exc)) from None
    result.timings.update(
        pairwise=t_pairwise,
        per_edge=sum(e.seconds for e in graph) / max(len(graph), 1),
        edges=len(graph),
        edge_tasks=sent,
        total=time.perf_counter() - t0,
    )
    return result, [p["worker"] for p in payloads]


def run_many(backend: Backend, job: Job, token: str, prog: JobProgress, art_prefix: str) -> JobState | None:
    """One attempt of a many job: load the N models, align_many (reports per edge; a cancel
    stops it at the next report), write many.json (and merged.ply), store them."""
    from gsa.align.many import ManyError, check_models, merged_model, select_edges  # lazy: the aligner's modules
    from gsa.align.outputs import write_json
    from gsa.io.ply import write_ply
    from service.jobs.inputs import load_input
    from service.worker.artifacts import store_artifacts

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
        try:
            check_models(models, names)  # as align_many does, before any edge runs
        except ManyError as exc:  # the client's input
            raise invalid_input(str(exc)) from None
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
