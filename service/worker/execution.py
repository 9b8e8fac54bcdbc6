"""Running one attempt of a job: claim it, load inputs, call the library, store artifacts.

The attempt's lease, heartbeat and progress reports are service.worker.leases'; a
failure becomes an RFC 9457 problem (service.problems) chosen by exception type.
"""

from __future__ import annotations

import gc
import logging
import random
import sys
import threading
import time
import uuid
from contextlib import nullcontext

from gsa.recon.calibration import Calibration
from service.backend import Backend, notify_webhook
from service.jobs.inputs import load_input
from service.jobs.many import is_many
from service.jobs.options import DEFAULT_OUTPUTS, align_options
from service.models import Job, JobState
from service.problems import Problem, infrastructure_problem, invalid_input, store_errors
from service.worker.artifacts import collect_outputs, store_artifacts, synchronized_renders
from service.worker.interrupt import Interrupter
from service.worker.leases import (
    JobCancelled,
    JobProgress,
    JobTimeout,
    LeaseLost,
    attempt_artifacts,
    finish_attempt,
    heartbeat,
    job_workspace,
    worker_name,
)
from service.worker.many import run_many

log = logging.getLogger("gsa.worker")


def execute(job_id: str, backend: Backend, interrupt: bool = False) -> JobState | None:
    """Run one attempt of a job. Returns the state it left the job in (None: not ours)."""
    store, s = backend.store, backend.settings
    job = store.get(job_id)
    if job is None or job.state != JobState.queued:
        return None
    if job.next_attempt_at is not None and job.next_attempt_at > time.time():
        # Its retry back-off has not passed: embedded workers simply look again later; an RQ
        # message delivered early (a reaper re-send) is scheduled again for the right time.
        if backend.redis is not None:
            ref = backend.queue.enqueue(job_id, delay_s=job.next_attempt_at - time.time())
            store.update(job_id, states={JobState.queued}, queue_ref=ref, enqueued_at=time.time())
        return None
    if job.attempts >= job.max_attempts:
        store.update(
            job_id,
            states={JobState.queued},
            state=JobState.failed,
            finished_at=time.time(),
            error=Problem(
                500,
                "attempts-exhausted",
                "Job failed",
                f"gave up after {job.attempts} attempts",
            ).to_dict(),
        )
        notify_webhook(backend, job_id)
        return JobState.failed
    token = uuid.uuid4().hex
    now = time.time()
    if not store.update(
        job_id,
        states={JobState.queued},
        state=JobState.running,
        attempts=job.attempts + 1,
        run_token=token,
        lease_until=now + s.lease_s,
        worker=worker_name(),
        started_at=now,
        stage="loading",
        progress=0.0,
        error=None,
        next_attempt_at=None,
    ):
        return None  # another worker claimed it, or it was cancelled meanwhile
    lost, stop = threading.Event(), threading.Event()
    # Only a work horse, which exits after its job, is stopped where the library reports nothing:
    # an exception raised in it may surface through a native call and leave that call's state
    # half-updated (numba's dispatcher answers SystemError), which a long-lived process keeps.
    interrupter = Interrupter() if interrupt else None
    deadline = time.monotonic() + s.job_timeout_s
    hb = threading.Thread(
        target=heartbeat, args=(backend, job_id, token, lost, stop, interrupter, deadline), daemon=True
    )
    hb.start()
    prog = JobProgress(backend, job, token, lost, max(len(job.sources), 1))
    prog.interrupter = interrupter
    art_prefix = attempt_artifacts(job_id, token)
    final: JobState | None = None
    try:
        try:
            final = _run(backend, job, token, prog, art_prefix)
        except Exception as exc:
            stop_asked = interrupter.requested if interrupter is not None else None
            if stop_asked is None or isinstance(exc, (JobCancelled, LeaseLost, JobTimeout)):
                raise
            raise stop_asked() from exc  # the stop, wrapped by the native call it went through
    except JobCancelled:
        final = JobState.cancelled if finish_attempt(backend, job_id, token, JobState.cancelled) else None
    except (LeaseLost, JobTimeout) as exc:
        if isinstance(exc, JobTimeout):
            err = Problem(
                504,
                "job-timeout",
                "Job timed out",
                f"the job ran longer than {s.job_timeout_s:.0f} s",
            ).to_dict()
            final = JobState.failed if finish_attempt(backend, job_id, token, JobState.failed, error=err) else None
    except Exception as exc:  # last resort: whatever the attempt raised becomes the job's outcome
        infra = infrastructure_problem(exc, s.unavailable_retry_after_s)
        if infra is not None:
            final = _retry_later(backend, job, token, exc, infra)
        else:
            err = problem_for(exc)
            if err.status >= 500:
                log.exception("job %s failed", job_id)
            final = (
                JobState.failed
                if finish_attempt(backend, job_id, token, JobState.failed, error=err.to_dict())
                else None
            )
    finally:
        stop.set()
        _clean_up(backend, job_id, prog, final, art_prefix)
        _release_memory()
    if final is not None and final != JobState.queued:
        notify_webhook(backend, job_id)
    return final


def _clean_up(backend: Backend, job_id: str, prog: JobProgress, final: JobState | None, art_prefix: str) -> None:
    """After an attempt: its last stage's time, and no partial artifacts from a failed attempt."""
    try:  # clean-up must not mask the attempt's outcome (e.g. Redis or the disk gone meanwhile)
        prog.finish()
        if final != JobState.succeeded:
            backend.storage.delete_prefix(art_prefix)
    except Exception as exc:
        if infrastructure_problem(exc) is not None:  # a full disk, a store away: one line, not a traceback
            log.warning("job %s: clean-up after the attempt failed: %s: %s", job_id, type(exc).__name__, exc)
        else:
            log.exception("job %s: clean-up after the attempt failed", job_id)


def _retry_later(backend: Backend, job: Job, token: str, exc: Exception, problem: Problem) -> JobState | None:
    """The attempt failed on the service's own infrastructure (storage full or
    failing, job store unreachable), not on the job: put the job back in the
    queue for another attempt after a back-off (retry_delay; the record's
    next_attempt_at says when), or fail it with that problem (503/507, not
    alignment-failed) once its attempts are spent. If the store cannot be
    written either, the lease expires and the reaper requeues the job."""
    attempts = job.attempts + 1  # this attempt's number (`job` was read before the claim)
    try:
        if attempts >= job.max_attempts:
            log.warning(
                "job %s attempt %d hit an infrastructure error (%s: %s)", job.id, attempts, type(exc).__name__, exc
            )
            ok = finish_attempt(backend, job.id, token, JobState.failed, error=problem.to_dict())
            return JobState.failed if ok else None
        delay = retry_delay(backend.settings, attempts)
        log.warning(
            "job %s attempt %d hit an infrastructure error (%s: %s); next attempt in %.1f s",
            job.id,
            attempts,
            type(exc).__name__,
            exc,
            delay,
        )
        if not backend.store.update(
            job.id,
            states={JobState.running},
            token=token,
            state=JobState.queued,
            stage="requeued",
            run_token=None,
            lease_until=None,
            worker=None,
            next_attempt_at=time.time() + delay,
        ):
            return None
    except Exception as err:  # last resort: the attempt's own error is what the job reports
        if infrastructure_problem(err) is None:
            log.exception("job %s: could not record the retry; the reaper will requeue it", job.id)
        else:  # the store as full or away as the attempt found it: one line
            log.warning(
                "job %s: could not record the retry (%s: %s); the reaper will requeue it",
                job.id,
                type(err).__name__,
                err,
            )
        return None
    try:
        ref = backend.queue.enqueue(job.id, delay_s=delay)
        backend.store.update(job.id, queue_ref=ref, enqueued_at=time.time())
    except store_errors() as err:  # the job is back in the queue: the reaper re-sends a message it lacks
        log.warning("job %s: requeued; recording its queue message failed: %s: %s", job.id, type(err).__name__, err)
    return JobState.queued


def retry_delay(settings, attempt: int) -> float:
    """Seconds before the attempt after attempt number `attempt` (1-based): exponential
    (base·2^(attempt-1), capped at retry_backoff_max_s) with "equal jitter", a uniform draw
    between half and all of it: never sooner than half (what was full may need the time)
    and spread so that jobs failed by one outage do not all come back together."""
    d = min(settings.retry_backoff_max_s, settings.retry_backoff_base_s * 2 ** max(attempt - 1, 0))
    return d / 2 + random.uniform(0, d / 2) if d > 0 else 0.0


def library_input_errors() -> tuple[type[Exception], ...]:
    """The library's errors about its input (unreadable PLY, inconsistent model,
    a model the aligner cannot use): the client's to fix, so 422, not 500."""
    # lazy: the aligner's modules are heavy; by the time a job fails they are loaded
    from gsa.align.coarse import AlignmentError
    from gsa.io.ply import PlyError
    from gsa.model import ModelError

    return (PlyError, ModelError, AlignmentError)


def problem_for(exc: Exception) -> Problem:
    """The problem a job attempt that raised `exc` reports, chosen by exception type."""
    if isinstance(exc, Problem):
        return exc
    if isinstance(exc, library_input_errors()):
        return invalid_input(str(exc))
    return Problem(500, "alignment-failed", "Alignment failed", f"{type(exc).__name__}: {exc}")


def _run(backend: Backend, job: Job, token: str, prog: JobProgress, art_prefix: str) -> JobState | None:
    if is_many(job):  # N models into one frame (N-way registration)
        return run_many(backend, job, token, prog, art_prefix)
    # lazy: the aligner (numba kernels, ~1 s of imports) loads in the processes that run jobs
    from gsa.align.contract import hints_from_files
    from gsa.align.outputs import result_dict, write_outputs
    from gsa.align.pipeline import align

    opts_in = dict(job.options)
    outputs = set(opts_in.pop("outputs", None) or DEFAULT_OUTPUTS)
    recon_iterations = opts_in.pop("recon_iterations", None)
    reconstructions: dict = {}
    if opts_in.pop("renders", True) is False:
        outputs.discard("renders")
    notes = []
    opts = align_options(backend.settings, opts_in, only_known=True)

    with job_workspace(job.id, token) as work:
        prog("loading", 0.0)
        target = load_input(backend, job.target, work, "target", prog, reconstructions, recon_iterations)
        prog("loading", 0.5)  # a scene model takes seconds to read: report between the inputs
        # photo sets of the target's camera (EXIF) are reconstructed with its intrinsics: one lens, one scale
        shared = Calibration.of_model(target)
        results, files, transforms = [], [], []
        multi = len(job.sources) > 1
        for i, ref in enumerate(job.sources):
            prog.part = i
            source = load_input(
                backend,
                ref,
                work,
                f"source{i}",
                prog,
                reconstructions,
                recon_iterations,
                calibration=shared,
            )
            prog.check(force=True)
            # Guidance comes in the files' own coordinates (as results state transforms).
            formats = (source.metadata.get("format", "ply"), target.metadata.get("format", "ply"))
            with _interruptible(prog):
                res = align(source, target, hints_from_files(opts, *formats), progress=prog)
            prog("writing", 0.99)
            out_dir = work / f"out{i}"
            extra = {
                "job_id": job.id,
                "source_asset_id": ref.asset_id,
                "target_asset_id": job.target.asset_id,
            }
            if job.parent_job:
                extra["parent_job"] = job.parent_job
            with _interruptible(prog):
                paths = write_outputs(res, source, target, out_dir, outputs=outputs, extra=extra)
            d = result_dict(res, source, target)  # + the transform contract (docs/formats.md)
            d["source_asset_id"] = ref.asset_id
            results.append(d)
            files += collect_outputs(paths, f"s{i}/" if multi else "")
            transforms.append(res.transform)
            del source, res
        if multi and "renders" in outputs:
            prog.part = len(job.sources) - 1
            prog("renders", 0.0)
            files += synchronized_renders(backend, job, target, transforms, work, notes)
        # Models reconstructed from image sets are results in their own right.
        files += [(f"reconstructed/{n}.ply", p) for n, (_, p) in sorted(reconstructions.items())]
        prog.check(force=True)
        artifacts = store_artifacts(backend, files, art_prefix, progress=prog)
    result = dict(results[0]) if len(results) == 1 else {}
    result["results"] = results
    if reconstructions:
        result["reconstructions"] = {n: summ for n, (summ, _) in reconstructions.items()}
    if notes:
        result["notes"] = notes
    if job.parent_job:
        result["parent_job"] = job.parent_job
    ok = finish_attempt(
        backend,
        job.id,
        token,
        JobState.succeeded,
        result=result,
        artifacts=artifacts,
        progress=1.0,
        stage="done",
    )
    return JobState.succeeded if ok else None


def _interruptible(prog: JobProgress):
    """Where the heartbeat may stop the job's thread (service.worker.interrupt)."""
    return prog.interrupter.interruptible() if prog.interrupter is not None else nullcontext()


def _release_memory() -> None:
    gc.collect()
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        torch.cuda.empty_cache()
