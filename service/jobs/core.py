"""Operations shared by the HTTP and gRPC front ends: authenticating a caller,
ingesting uploads as assets, submitting jobs (with idempotency), cancelling,
reading artifacts."""

from __future__ import annotations

import hashlib
import hmac
import json
import tempfile
import time
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from service.backend import Backend, notify_webhook
from service.jobs import quotas
from service.jobs.inputs import (
    check_image,
    model_content_type,
    model_format,
    sniff,
    validate_model,
    validate_ply,
    validate_zip,
)
from service.jobs.options import validate_options
from service.models import TERMINAL, Asset, InputRef, Job, JobState, new_id
from service.problems import Problem, invalid_input, not_found, too_large
from service.storage import CHUNK, new_key
from service.webhooks.delivery import check_url


class _Hashing:
    """Wraps a stream: sha256 + the first bytes (for type sniffing) as it flows."""

    def __init__(self, data: BinaryIO | Iterable[bytes]):
        self.data = data
        self.sha = hashlib.sha256()
        self.head = b""

    def __iter__(self):
        it = iter(lambda: self.data.read(CHUNK), b"") if hasattr(self.data, "read") else iter(self.data)
        for chunk in it:
            if len(self.head) < 65536:
                self.head += chunk[: 65536 - len(self.head)]
            self.sha.update(chunk)
            yield chunk


def _local(b: Backend, key: str, tmpdir: Path) -> Path:
    if hasattr(b.storage, "local_path"):
        return b.storage.local_path(key)
    return b.storage.download(key, tmpdir / "blob")


def blob_key(owner: str, sha256: str) -> str:
    """Where an owner's upload with these bytes is stored: content-addressed, so
    identical uploads share one blob. Per owner: dedup never crosses tenants (an
    owner cannot learn what another uploaded)."""
    return f"cas/{hashlib.sha256(owner.encode()).hexdigest()[:32]}/{sha256}"


def owner_for_key(b: Backend, presented: str | None) -> str | None:
    """The owner of an API key, or None. Compares against every key with
    hmac.compare_digest so timing reveals neither the key nor which one matched."""
    if b.settings.auth_disabled:
        return "anonymous"
    if not presented:
        return None
    found = None
    p = presented.encode()
    for key, owner in b.settings.api_keys.items():
        if hmac.compare_digest(key.encode(), p):
            found = owner
    return found


def authenticate(b: Backend, presented: str | None, detail: str | None = None) -> str:
    """The caller's owner for the API key it presented (None: no key). 401 for a missing or
    unknown key (`detail` replaces the text that tells which), 429 past the owner's request
    rate (one bucket for HTTP and gRPC)."""
    owner = owner_for_key(b, presented)
    if owner is None:
        if detail is None:
            detail = (
                "a valid API key is required: Authorization: Bearer <key>"
                if presented is None
                else "the API key is not valid"
            )
        p = Problem(401, "unauthorized", "Unauthorized", detail)
        p.headers["WWW-Authenticate"] = 'Bearer realm="gsa"'
        raise p
    quotas.check_rate(b, owner)
    return owner


def sha256_file(fh: BinaryIO, max_bytes: int | None = None) -> str:
    """sha256 of a seekable file's bytes from its start; the file is left at its start.
    413 once it holds more than max_bytes."""
    fh.seek(0)
    sha, size = hashlib.sha256(), 0
    while chunk := fh.read(CHUNK):
        size += len(chunk)
        if max_bytes is not None and size > max_bytes:
            raise too_large(f"upload exceeds the limit of {max_bytes} bytes")
        sha.update(chunk)
    fh.seek(0)
    return sha.hexdigest()


def _digest(data: BinaryIO, max_bytes: int) -> str | None:
    """sha256 of a seekable upload; None for a stream that cannot be re-read."""
    if not (hasattr(data, "seek") and hasattr(data, "read")):
        return None
    return sha256_file(data, max_bytes)


def _length(data: BinaryIO) -> int:
    """Bytes in a seekable upload (left at its start)."""
    data.seek(0, 2)
    n = data.tell()
    data.seek(0)
    return n


def _reuse(b: Backend, owner: str, sha256: str, filename: str | None, expect: str | None) -> Asset | None:
    """A new asset id for bytes this owner already stored: no second copy, one more
    reference to the blob. None if no live asset holds these bytes."""
    key = blob_key(owner, sha256)
    for other_id in b.store.blob_ref_ids(key):
        other = b.store.get_asset(other_id)
        if other is None or other.owner != owner or other.key != key:
            continue
        if expect == "ply" and other.kind != "ply":
            raise invalid_input(f"{filename or 'upload'}: not a PLY file (it does not start with 'ply')")
        asset = other.model_copy(update={"id": new_id("ast"), "filename": filename, "created_at": time.time()})
        with b.store.blob_lock(key):
            b.store.add_blob_ref(key, asset.id)
            if not b.storage.exists(key):  # its last other user was deleted meanwhile: store it afresh
                b.store.remove_blob_ref(key, asset.id)
                return None
        quotas.record(b, owner, key, other.size)  # counted once (a blob stored before the ledger: now)
        b.store.put_asset(asset)
        return asset
    return None


def release_blob(b: Backend, asset: Asset) -> None:
    """Drop asset's reference to its blob; the bytes go with the last reference."""
    with b.store.blob_lock(asset.key):
        if b.store.remove_blob_ref(asset.key, asset.id) == 0:
            b.storage.delete(asset.key)
            quotas.forget(b, asset.owner, asset.key)


def ingest(b: Backend, owner: str, data, filename: str | None, *, expect: str | None = None) -> Asset:
    """Stream one upload to storage, validate it, record it. Nothing remains on failure.
    Bytes this owner already uploaded are stored once (service.jobs.core.blob_key)."""
    s = b.settings
    sha = _digest(data, s.max_upload_bytes)
    if sha is not None:
        reused = _reuse(b, owner, sha, filename, expect)
        if reused is not None:
            return reused
    # The tenant's storage quota, before anything is written (a stream of unknown length: once full).
    quotas.check_storage(b, owner, _length(data) if sha is not None else 0)
    key = blob_key(owner, sha) if sha else new_key("uploads", filename or "upload")
    asset_id = new_id("ast")
    if sha is not None:
        # Claim the blob before writing it: a delete of its last other user now leaves the bytes.
        with b.store.blob_lock(key):
            b.store.add_blob_ref(key, asset_id)
    h = _Hashing(data)
    name = filename or "upload"
    try:
        size = b.storage.put(key, h, max_bytes=s.max_upload_bytes)
        kind = sniff(h.head)
        if size == 0:
            raise invalid_input(f"{name}: the upload is empty")
        fmt = model_format(h.head, size)  # any 3DGS format (docs/formats.md); a SOG zip is told below
        if expect == "ply" and kind not in ("ply", "zip") and fmt is None:
            raise invalid_input(f"{name}: not a PLY file nor another 3DGS format (it does not start with 'ply')")
        fields = dict(
            id=asset_id,
            owner=owner,
            key=key,
            size=size,
            filename=filename,
            sha256=h.sha.hexdigest(),
            created_at=time.time(),
        )
        with tempfile.TemporaryDirectory() as tmp:
            path = _local(b, key, Path(tmp))
            if kind == "zip":
                fmt = model_format(h.head, size, path)
                if expect == "ply" and fmt is None:
                    raise invalid_input(f"{name}: a zip archive that is not a SOG model (no meta.json)")
            if fmt == "ply":
                n = validate_ply(path, s.max_gaussians, name)
                asset = Asset(**fields, kind="ply", content_type="application/x-ply", n_gaussians=n)
            elif fmt is not None:  # kind "ply" stands for any 3DGS model file
                n = validate_model(path, s.max_gaussians, name)
                asset = Asset(**fields, kind="ply", content_type=model_content_type(fmt), n_gaussians=n)
            elif kind == "zip":
                n = validate_zip(path, s, name)
                asset = Asset(**fields, kind="images", content_type="application/zip", n_images=n)
            else:
                raise invalid_input(f"{name}: not a 3DGS .ply or a .zip of images (unrecognised file type)")
        # Counted before the record exists: if either write fails (a full disk), the blob and
        # its count go together below, and no asset names a deleted blob.
        quotas.record(b, owner, key, size)
        b.store.put_asset(asset)
        return asset
    except BaseException:
        # Another upload of the same bytes may have finished meanwhile: its reference keeps the blob.
        try:
            with b.store.blob_lock(key):
                if b.store.remove_blob_ref(key, asset_id) == 0:
                    b.storage.delete(key)
                    quotas.forget(b, owner, key)
        # cleanup while an error is answered (re-raised below): whatever the store fails with
        # (unreachable, full disk), only a blob no other asset can share goes
        except Exception:  # noqa: BLE001
            if not key.startswith("cas/"):
                b.storage.delete(key)
        raise


def ingest_images(b: Backend, owner: str, files: list[tuple[str | None, BinaryIO]], label: str) -> Asset:
    """Several image uploads -> one image-set asset (stored as a zip)."""
    s = b.settings
    if len(files) > s.max_images:
        raise too_large(f"{label}: {len(files)} images exceeds the limit of {s.max_images}")
    with tempfile.TemporaryFile() as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
            for i, (fname, fh) in enumerate(files):
                head = fh.read(65536)
                check_image(head, f"{label}[{i}] {fname or ''}".strip(), s)
                ext = ".png" if sniff(head) == "png" else ".jpg"
                total = len(head)
                with zf.open(f"{i:05d}{ext}", "w", force_zip64=True) as out:
                    out.write(head)
                    while chunk := fh.read(CHUNK):
                        total += len(chunk)
                        if total > s.max_upload_bytes:
                            raise too_large(f"{label}[{i}]: exceeds the limit of {s.max_upload_bytes} bytes")
                        out.write(chunk)
        tmp.seek(0)
        return ingest(b, owner, tmp, f"{label}.zip")


def get_asset(b: Backend, owner: str, asset_id: str) -> Asset:
    a = b.store.get_asset(asset_id)
    if a is None or a.owner != owner:
        raise not_found("Asset", asset_id)
    return a


def claim(b: Backend, owner: str, idempotency_key: str | None, fingerprint: str) -> tuple[str, Job | None]:
    """Reserve a job id. With an Idempotency-Key already used: the earlier job
    (same body) or 422 (different body). Returns (job_id, existing_job)."""
    job_id = new_id("job")
    if not idempotency_key:
        return job_id, None
    if len(idempotency_key) > 255:
        raise invalid_input("Idempotency-Key is longer than 255 characters")
    prev = b.store.claim_idempotency(owner, idempotency_key, fingerprint, job_id)
    if prev is None:
        return job_id, None
    prev_id, prev_hash = prev
    if prev_hash != fingerprint:
        raise Problem(
            422,
            "idempotency-key-reused",
            "Idempotency-Key reused",
            "this Idempotency-Key was already used with a different request body",
        )
    job = b.store.get(prev_id)
    if job is None:  # the first request is still uploading
        raise Problem(
            409,
            "idempotency-in-progress",
            "Request in progress",
            "a request with this Idempotency-Key is still being processed; retry shortly",
        )
    return prev_id, job


def release(b: Backend, owner: str, idempotency_key: str | None) -> None:
    """Forget a claimed key whose request failed, so the client can retry it."""
    if idempotency_key:
        try:
            b.store.release_idempotency(owner, idempotency_key)
        # cleanup on a failed request: never hides the request's own error;
        # an unreleased claim lapses (IDEM_PENDING_S)
        except Exception:  # noqa: BLE001
            pass


def discard_asset(b: Backend, asset: Asset) -> None:
    b.store.delete_asset(asset.id)
    release_blob(b, asset)


def check_request(
    b: Backend, n_sources: int, options: dict[str, Any], webhook: dict | None, owner: str | None = None
) -> None:
    s = b.settings
    if owner is not None:  # before any upload is stored; create_job checks again, atomically
        quotas.check_active_jobs(b, owner)
        quotas.check_storage(b, owner)
    if n_sources < 1:
        raise invalid_input("at least one source model is required")
    if n_sources > s.max_sources:
        raise too_large(f"{n_sources} sources exceeds the limit of {s.max_sources}")
    validate_options(options, s)
    if webhook:
        try:
            check_url(webhook["url"], s.webhook_allow_private, loopback_only=s.webhook_loopback_only)
        except ValueError as exc:
            raise invalid_input(str(exc)) from None


def check_memory(b: Backend, sources: list[Asset], target: Asset, options: dict[str, Any]) -> None:
    """Refuse (422) a job whose predicted peak memory is above the workers' budget."""
    budget_mb = b.settings.worker_memory_mb
    if not budget_mb:
        return
    from service.jobs.memory import MB, effective_options, predict_for_assets

    predicted = predict_for_assets(effective_options(options, b.settings), sources, target)
    if predicted > budget_mb * MB:
        mb = -(-predicted // MB)
        raise invalid_input(
            f"this job is predicted to need {mb} MB of worker memory, above the workers' budget of "
            f"{budget_mb} MB (GSA_WORKER_MEMORY_MB): fewer fine_views, a smaller fine_image_size "
            f"or smaller inputs",
            option="memory",
            value=mb,
            maximum=budget_mb,
        )


def create_job(
    b: Backend,
    owner: str,
    job_id: str,
    sources: list[Asset],
    target: Asset,
    options: dict[str, Any],
    webhook: dict | None,
    idempotency_key: str | None,
    parent_job: str | None = None,
) -> Job:
    check_memory(b, sources, target, options)
    now = time.time()

    def ref(a):
        return InputRef(asset_id=a.id, key=a.key, kind=a.kind, filename=a.filename)

    job = Job(
        id=job_id,
        owner=owner,
        created_at=now,
        updated_at=now,
        max_attempts=b.settings.max_attempts,
        sources=[ref(a) for a in sources],
        target=ref(target),
        options=options,
        webhook=webhook,
        idempotency_key=idempotency_key,
        parent_job=parent_job,
    )
    quotas.check_storage(b, owner)
    if b.settings.tenant_max_active_jobs > 0:
        # Count and create under one per-owner lock (Redis: across API processes), so
        # concurrent submissions cannot pass the limit together.
        with b.store.blob_lock(f"tenant-jobs:{owner}"):
            quotas.check_active_jobs(b, owner)
            b.store.create(job)
    else:
        b.store.create(job)
    # Enqueue after the record exists (a worker may start at once); remember the
    # queue's handle so a lost message can be detected and re-sent.
    try:
        ref = b.queue.enqueue(job.id)
        b.store.update(job.id, queue_ref=ref, enqueued_at=time.time())
    except BaseException:
        # A full disk or a lost store between the two writes: answer the error with no
        # half-created job behind it (a worker that got the message finds no record).
        try:
            b.store.delete(job.id)
        except Exception:  # noqa: BLE001 -- cleanup, last resort: never hides the error being answered
            pass
        raise
    return job


@dataclass
class Upload:
    """One uploaded file as a front end received it: seekable (spooled), not yet stored."""

    file: BinaryIO
    filename: str | None = None


@dataclass
class ImageSet:
    """Image uploads that make one input together (stored as one zip, `label`.zip)."""

    images: list[Upload]
    label: str


# An input of a job request: an asset id the caller uploaded before, a model file, or images.
Input = str | Upload | ImageSet


@dataclass
class JobRequest:
    """A job submission as a front end parsed it (HTTP JSON or multipart, gRPC)."""

    sources: list[Input]
    target: Input
    options: dict[str, Any]  # parsed (service.jobs.options.parse_options), checked by submit_job
    webhook: dict | None
    # What makes a retry with the same Idempotency-Key the same request; an Upload in it counts
    # by its bytes' sha256. With the JSON separators its fingerprint is made with: each front
    # end keeps its own, since a changed fingerprint turns the replay of a key claimed earlier
    # (kept IDEM_TTL_S) into a 422.
    identity: dict[str, Any]
    separators: tuple[str, str] = (",", ":")


def fingerprint(identity: Any, separators: tuple[str, str] = (",", ":")) -> str:
    """sha256 of a request's identity as key-sorted JSON (an Upload: its bytes' sha256)."""

    def value(o):
        return sha256_file(o.file) if isinstance(o, Upload) else str(o)

    text = json.dumps(identity, sort_keys=True, separators=separators, default=value)
    return hashlib.sha256(text.encode()).hexdigest()


def submit_job(b: Backend, owner: str, req: JobRequest, idempotency_key: str | None) -> tuple[Job, bool]:
    """Create a job (the one path of HTTP and gRPC): check the request, claim the
    Idempotency-Key, store the uploads as assets, create and enqueue the job. On any
    failure nothing stays behind: not the assets stored here, not the claim. Returns
    (job, created): created is False for a replayed Idempotency-Key."""
    check_request(b, len(req.sources), req.options, req.webhook, owner)
    inputs = [*req.sources, req.target]
    given = {i: get_asset(b, owner, i) for i in inputs if isinstance(i, str)}
    if all(isinstance(i, str) for i in inputs):  # no uploads: the memory check comes before the claim
        check_memory(b, [given[i] for i in req.sources], given[req.target], req.options)
    job_id, existing = claim(b, owner, idempotency_key, fingerprint(req.identity, req.separators))
    if existing is not None:
        return existing, False
    made: list[Asset] = []

    def stored(i: Input) -> Asset:
        if isinstance(i, str):
            return given[i]
        if isinstance(i, Upload):
            asset = ingest(b, owner, i.file, i.filename)
        else:
            asset = ingest_images(b, owner, [(u.filename, u.file) for u in i.images], i.label)
        made.append(asset)
        return asset

    try:
        sources = [stored(i) for i in req.sources]
        target = stored(req.target)
        job = create_job(b, owner, job_id, sources, target, req.options, req.webhook, idempotency_key)
    except BaseException:
        # Leave nothing behind: uploaded blobs, asset records, the idempotency claim.
        for a in made:
            discard_asset(b, a)
        release(b, owner, idempotency_key)  # a retry with the key must not find it claimed
        raise
    return job, True


def get_job(b: Backend, owner: str, job_id: str) -> Job:
    job = b.store.get(job_id)
    if job is None or job.owner != owner:
        raise not_found("Job", job_id)
    return job


def cancel_job(b: Backend, owner: str, job_id: str) -> Job:
    job = get_job(b, owner, job_id)
    if job.state in TERMINAL:
        if job.state == JobState.cancelled:
            return job
        raise Problem(
            409,
            "job-finished",
            "Job already finished",
            f"job {job_id} is {job.state.value}",
        )
    now = time.time()
    # A queued job is cancelled at once; a running one is flagged and its worker
    # stops at its next progress callback (then marks it cancelled).
    if b.store.update(
        job_id,
        states={JobState.queued},
        state=JobState.cancelled,
        cancel_requested=True,
        finished_at=now,
        stage="cancelled",
    ):
        notify_webhook(b, job_id)
    else:
        b.store.update(job_id, states={JobState.running}, cancel_requested=True)
    return get_job(b, owner, job_id)


def get_artifact(b: Backend, owner: str, job_id: str, name: str):
    job = get_job(b, owner, job_id)
    if job.state != JobState.succeeded:
        raise Problem(
            409,
            "job-not-finished",
            "Artifacts not available",
            f"job {job_id} is {job.state.value}; artifacts exist once it has succeeded",
        )
    for a in job.artifacts:
        if a.name == name:
            return job, a
    raise not_found("Artifact", name)


# POST /v1/jobs/{id}:refine and gRPC RefineJob: where the follow-up job starts (exactly one) and
# the hints it may change (the parent's are kept unless given; null drops one).
REFINE_STARTS = ("alternative", "init_transform", "point_pairs")
REFINE_HINTS = ("up_axes", "front_axes", "fixed_scale")
REFINE_FIELDS = (*REFINE_STARTS, *REFINE_HINTS)


def refine_options(parent: Job, hints: dict[str, Any]) -> dict[str, Any]:
    """The follow-up job's options: the parent's, its start replaced by the one chosen in
    `hints` (an alternative of its result, init_transform or point_pairs), up_axes, front_axes
    and fixed_scale the parent's unless `hints` gives them (refined_hints). 422 naming the field
    for a bad one."""
    unknown = sorted(set(hints) - set(REFINE_FIELDS))
    if unknown:
        raise invalid_input(f"unknown refine field(s): {', '.join(unknown)}", allowed=list(REFINE_FIELDS))
    starts = [k for k in REFINE_STARTS if hints.get(k) is not None]
    if len(starts) != 1:
        raise invalid_input(
            "give exactly one of alternative, init_transform, point_pairs"
            + (f" (got {', '.join(starts)})" if starts else ""),
            option=starts[-1] if starts else "alternative",
            allowed=list(REFINE_STARTS),
        )
    if len(parent.sources) != 1:
        raise invalid_input(f"job {parent.id} aligns {len(parent.sources)} sources; refine takes a job with one source")
    kept = {k: v for k, v in parent.options.items() if k not in ("init_transform", "point_pairs")}
    options = refined_hints(kept, hints)
    if starts[0] == "alternative":
        options["init_transform"] = alternative_transform(parent, hints["alternative"])
    else:
        options[starts[0]] = hints[starts[0]]
    return options


def refined_hints(options: dict[str, Any], hints: dict[str, Any]) -> dict[str, Any]:
    """`options` with the REFINE_HINTS that `hints` gives replacing its own (null drops one). The
    parent's fronts are stated about its up axes: new (or dropped) up axes drop them too, unless
    `hints` gives fronts as well."""
    options = dict(options)
    if "up_axes" in hints and "front_axes" not in hints and hints["up_axes"] != options.get("up_axes"):
        options.pop("front_axes", None)
    for k in REFINE_HINTS:
        if k in hints:
            options.pop(k, None)
            if hints[k] is not None:
                options[k] = hints[k]
    return options


def alternative_transform(parent: Job, index: Any) -> list[list[float]]:
    """The parent result's metrics.alternatives[index] pose, in the input files' own coordinates
    (as init_transform is given; the result lists alternatives in the internal frame)."""
    if parent.state != JobState.succeeded or not parent.result:
        raise Problem(
            409,
            "no-result",
            "Job has no result",
            f"job {parent.id} is {parent.state.value}: only a succeeded job's alternatives can be refined",
        )
    alternatives = (parent.result.get("metrics") or {}).get("alternatives") or []
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(alternatives):
        raise invalid_input(
            f"'alternative' must be an index into the parent result's metrics.alternatives, which has "
            f"{len(alternatives)} entr{'y' if len(alternatives) == 1 else 'ies'}",
            option="alternative",
            minimum=0,
            maximum=len(alternatives) - 1,
        )
    from gsa.io import frames  # numpy only
    from gsa.sim3 import Sim3

    formats = parent.result.get("frames") or {}
    src_fmt = (formats.get("source") or {}).get("format") or "ply"
    dst_fmt = (formats.get("target") or {}).get("format") or "ply"
    try:
        internal = Sim3.from_matrix(np.asarray(alternatives[index]["transform"], np.float64))
    except (KeyError, TypeError, ValueError):  # a result stored by another library version
        raise invalid_input(f"alternative {index} has no 4×4 transform", option="alternative") from None
    return frames.file_transform(internal, src_fmt, dst_fmt).matrix().tolist()


def refine_job(
    b: Backend, owner: str, parent_id: str, hints: dict[str, Any], idempotency_key: str | None
) -> tuple[Job, bool]:
    """A follow-up job on the parent's own inputs with a guidance hint (docs/service.md, "Guided
    alignment"), linked both ways: child.parent_job, parent.children. 404 for another owner's
    job, 409 while the parent is queued or running, 422 for a bad hint. Returns (job, created):
    created is False for a replayed Idempotency-Key."""
    parent = get_job(b, owner, parent_id)
    if not parent.terminal:
        raise Problem(
            409,
            "job-not-finished",
            "Job not finished",
            f"job {parent_id} is {parent.state.value}; refine it once it has finished",
        )
    options = refine_options(parent, hints)
    check_request(b, len(parent.sources), options, parent.webhook, owner)
    assets = []
    for ref in [*parent.sources, parent.target]:
        a = b.store.get_asset(ref.asset_id)
        if a is None or a.owner != owner or a.key != ref.key:
            raise Problem(
                409,
                "input-deleted",
                "Input deleted",
                f"job {parent_id}'s input asset {ref.asset_id} was deleted: submit a new job",
            )
        assets.append(a)
    sources, target = assets[:-1], assets[-1]
    check_memory(b, sources, target, options)
    identity = {"refine": parent_id, "options": options}
    job_id, existing = claim(b, owner, idempotency_key, fingerprint(identity, separators=(", ", ": ")))
    if existing is not None:
        return existing, False
    try:
        job = create_job(b, owner, job_id, sources, target, options, parent.webhook, idempotency_key, parent.id)
    except BaseException:
        release(b, owner, idempotency_key)
        raise
    # The parent lists its children. A store-wide lock keyed by the parent (the one the
    # stores already have, blob_lock) keeps two concurrent refines from losing one.
    with b.store.blob_lock(f"job-children:{parent_id}"):
        now = b.store.get(parent_id)
        if now is not None:
            b.store.update(parent_id, children=[*now.children, job.id])
    return job, True
