"""N-way registration jobs: N assets into one reference frame with the library's
gsa.align.many.align_many, as one job over both front ends (POST /v1/many-jobs, gRPC
SubmitManyAlignment).

A many job is an ordinary job record: `sources` are its N assets in the order given, `target`
its reference asset (so deletion, retention, quotas, cancel and artifacts work as for any job),
and `options` holds the per-edge align() options plus `many` ({reference, edges, merged, merge}),
which marks it. Its result is many.json's content; its artifacts many.json, when asked merged.ply, and
each model's preview for the results page (preview/model{k}.splat)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from service.backend import Backend
from service.jobs import core, quotas
from service.jobs.options import GUIDANCE_OPTIONS, SERVICE_OPTIONS, validate_options
from service.models import Asset, Job
from service.problems import invalid_input
from service.webhooks.delivery import check_url

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
    from service.jobs.memory import MARGIN, MB, effective_options, gaussian_bytes, predict_job_memory

    sized = sorted(((a.n_gaussians or 0, gaussian_bytes(a.n_gaussians, a.size)) for a in assets), reverse=True)
    (n1, b1), (n2, b2) = sized[0], sized[1]
    held = sum(n * bb for n, bb in sized[2:]) + (sum(n * bb for n, bb in sized) if merged else 0)
    predicted = predict_job_memory(effective_options(options, b.settings), [n1], n2, [b1], b2) + int(MARGIN * held)
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


def many_preview_name(k: int) -> str:
    """The artifact of model k's preview for the results page: a .splat in its own frame."""
    return f"preview/model{k}.splat"
