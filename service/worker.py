"""Running a job: claim it, load inputs, call the library, store artifacts.

Delivery is at-least-once. A worker claims a queued job by compare-and-set
(state queued -> running, attempts + 1, a fresh run_token, a lease) and keeps
renewing the lease from a heartbeat thread. If the worker dies (SIGKILL, OOM,
machine lost) the lease expires and any reaper (every API process and every
worker runs one) puts the job back in the queue, or fails it once
max_attempts is spent, so no job stays "running" forever. Every write a worker
makes is conditional on its run_token, so a worker that was presumed dead but
comes back cannot overwrite the job's newer attempt.
"""

from __future__ import annotations

import gc
import logging
import mimetypes
import os
import re
import socket
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

from service.backend import Backend, notify_webhook, process_backend
from service.jobs import Artifact, InputRef, Job, JobState
from service.inputs import safe_extract
from service.options import DEFAULT_OUTPUTS, align_option_names, server_options
from service.problems import Problem, invalid_input

log = logging.getLogger("gsa.worker")



class JobCancelled(Exception):
    pass


class LeaseLost(Exception):
    pass


class JobTimeout(Exception):
    pass


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def content_type(name: str) -> str:
    if name.endswith(".ply"):
        return "application/x-ply"
    if name.endswith(".json"):
        return "application/json"
    return mimetypes.guess_type(name)[0] or "application/octet-stream"


# Where each library stage sits in a job's overall 0..1 progress (the library
# reports a fraction per stage); unknown stages hold the current value, so the
# published progress never goes backwards.
STAGE_SPAN = {
    "loading": (0.0, 0.05), "features": (0.05, 0.2), "hypotheses": (0.2, 0.4), "coarse": (0.4, 0.7),
    "refine": (0.7, 0.8), "fine": (0.8, 0.97), "writing": (0.97, 0.99), "renders": (0.97, 0.99), "done": (0.97, 0.99),
}  # fmt: skip


# Image-set inputs: gsa.recon's stages ("recon:sfm:features" -> "sfm") come first.
RECON_SPAN = {
    "images": (0.0, 0.02),
    "sfm": (0.02, 0.1),
    "masks": (0.1, 0.12),
    "train": (0.12, 0.4),
}


class _Progress:
    """The progress callback handed to align(): writes stage/progress (throttled),
    records stage durations, and raises to abort on cancel/lease loss/timeout."""

    def __init__(
        self,
        backend: Backend,
        job: Job,
        token: str,
        lost: threading.Event,
        n_parts: int,
    ):
        self.b, self.job_id, self.token, self.lost = backend, job.id, token, lost
        self.n = n_parts
        self.part = 0
        self.started = time.monotonic()
        self.stage: str | None = None
        self.stage_t0 = time.monotonic()
        self.last_write = 0.0
        self.last_check = 0.0
        self.overall = 0.0

    def check(self, force: bool = False) -> None:
        if self.lost.is_set():
            raise LeaseLost()
        if time.monotonic() - self.started > self.b.settings.job_timeout_s:
            raise JobTimeout()
        now = time.monotonic()
        if force or now - self.last_check > 0.2:
            self.last_check = now
            job = self.b.store.get(self.job_id)
            if job is None or job.run_token != self.token:
                raise LeaseLost()
            if job.cancel_requested or job.state == JobState.cancelled:
                raise JobCancelled()

    def set_stage(self, stage: str) -> None:
        if stage != self.stage:
            now = time.monotonic()
            if self.stage is not None:
                self.b.store.record_stage(self.stage, now - self.stage_t0)
            self.stage, self.stage_t0 = stage, now

    def __call__(self, stage: str, fraction: float) -> None:
        changed = stage != self.stage
        self.set_stage(stage)
        self.check(force=changed)
        now = time.monotonic()
        if changed or now - self.last_write > 0.2:
            self.last_write = now
            f = max(0.0, min(1.0, float(fraction)))
            key = stage.split(":")[1] if stage.startswith("recon:") else stage
            span = RECON_SPAN if stage.startswith("recon:") else STAGE_SPAN
            lo, hi = span.get(key, (None, None))
            within = (
                (lo + f * (hi - lo))
                if lo is not None
                else (self.overall * self.n - self.part)
            )
            # 1.0 is kept for "succeeded"; a running job's progress stays below it.
            self.overall = min(max(self.overall, (self.part + within) / self.n), 0.999)
            self.b.store.update(
                self.job_id,
                states={JobState.running},
                token=self.token,
                stage=stage,
                progress=self.overall,
            )

    def finish(self) -> None:
        self.set_stage("__end__")


def _heartbeat(
    backend: Backend,
    job_id: str,
    token: str,
    lost: threading.Event,
    stop: threading.Event,
) -> None:
    lease = backend.settings.lease_s
    while not stop.wait(lease / 3):
        try:
            ok = backend.store.update(
                job_id,
                states={JobState.running},
                token=token,
                lease_until=time.time() + lease,
            )
        except Exception:  # transient store error: the lease has slack for two misses
            log.exception("lease renewal failed for %s", job_id)
            continue
        if not ok:
            lost.set()
            return


def _load(
    backend: Backend,
    ref: InputRef,
    workdir: Path,
    name: str,
    progress: _Progress,
    reconstructions: dict | None = None,
    recon_iterations: int | None = None,
):
    """A job input as a GaussianModel: a PLY as is, an image set through gsa.recon
    (its summary and model file are recorded in `reconstructions`)."""
    reconstructions = {} if reconstructions is None else reconstructions
    from gsa.io.ply import read_ply

    s = backend.settings
    if ref.kind == "ply":
        path = backend.storage.download(ref.key, workdir / f"{name}.ply")
        return read_ply(path, max_gaussians=s.max_gaussians)
    if ref.kind == "images":
        # lazy: SfM and 3DGS training load OpenCV, pycolmap and torch
        from gsa.recon import ImageSetError, MaskError, SfMError, reconstruct

        archive = backend.storage.download(ref.key, workdir / f"{name}.zip")
        images = safe_extract(archive, workdir / f"{name}-images", s)
        preset = "gpu" if s.worker_device.startswith("cuda") else "cpu"
        try:
            res = reconstruct(
                images,
                workdir / f"{name}-recon",
                preset=preset,
                progress=lambda st, f: progress(f"recon:{st}", f),
                iterations=recon_iterations,
            )
        except (ImageSetError, SfMError, MaskError) as exc:
            raise Problem(
                422,
                "reconstruction-failed",
                "Reconstruction failed",
                f"{name} images: {exc}",
            ) from None
        summary = {
            k: v for k, v in res.summary().items() if k not in ("model", "cameras")
        }
        reconstructions[name] = (summary, Path(res.model_path))
        return res.model
    raise invalid_input(f"unknown input kind {ref.kind!r}")


def _collect(paths: dict, prefix: str) -> list[tuple[str, Path]]:
    """write_outputs' {artifact name: path} -> (public name, file); names may hold
    one folder level ("renders/before.png"), served as artifacts/renders/before.png."""
    clean = lambda n: "/".join(
        re.sub(r"[^A-Za-z0-9._-]", "_", seg).lstrip("._-") or "x"
        for seg in n.split("/")
    )
    out = []
    for name, p in sorted(paths.items()):
        p, name = Path(p), clean(name)
        if p.is_dir():
            out += [
                (f"{prefix}{name}/{f.name}", f)
                for f in sorted(p.iterdir())
                if f.is_file()
            ]
        else:
            out.append((prefix + name, p))
    return out


def execute(job_id: str, backend: Backend) -> JobState | None:
    """Run one attempt of a job. Returns the state it left the job in (None: not ours)."""
    store, s = backend.store, backend.settings
    job = store.get(job_id)
    if job is None or job.state != JobState.queued:
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
    ):
        return None  # another worker claimed it, or it was cancelled meanwhile
    lost, stop = threading.Event(), threading.Event()
    hb = threading.Thread(
        target=_heartbeat, args=(backend, job_id, token, lost, stop), daemon=True
    )
    hb.start()
    prog = _Progress(backend, job, token, lost, max(len(job.sources), 1))
    art_prefix = f"jobs/{job_id}/{token}"
    final: JobState | None = None
    try:
        final = _run(backend, job, token, prog, art_prefix)
    except JobCancelled:
        final = (
            JobState.cancelled
            if _finish(backend, job_id, token, JobState.cancelled)
            else None
        )
    except (LeaseLost, JobTimeout) as exc:
        if isinstance(exc, JobTimeout):
            err = Problem(
                504,
                "job-timeout",
                "Job timed out",
                f"the job ran longer than {s.job_timeout_s:.0f} s",
            ).to_dict()
            final = (
                JobState.failed
                if _finish(backend, job_id, token, JobState.failed, error=err)
                else None
            )
    except Exception as exc:
        err = problem_for(exc)
        if err.status >= 500:
            log.exception("job %s failed", job_id)
        final = (
            JobState.failed
            if _finish(backend, job_id, token, JobState.failed, error=err.to_dict())
            else None
        )
    finally:
        stop.set()
        prog.finish()
        if final != JobState.succeeded:
            backend.storage.delete_prefix(
                art_prefix
            )  # no partial artifacts from a failed attempt
        _release_memory()
    if final is not None:
        notify_webhook(backend, job_id)
    return final


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


def _run(
    backend: Backend, job: Job, token: str, prog: _Progress, art_prefix: str
) -> JobState | None:
    from gsa.align.outputs import write_outputs
    from gsa.align.pipeline import AlignOptions, align

    opts_in = dict(job.options)
    outputs = set(opts_in.pop("outputs", None) or DEFAULT_OUTPUTS)
    recon_iterations = opts_in.pop("recon_iterations", None)
    reconstructions: dict = {}
    if opts_in.pop("renders", True) is False:
        outputs.discard("renders")
    notes = []
    known = align_option_names()
    unknown = sorted(set(opts_in) - known)
    if unknown:
        raise Problem(
            422,
            "invalid-input",
            "Invalid options",
            f"unknown alignment options: {', '.join(unknown)}",
        )
    if "stages" in opts_in and isinstance(opts_in["stages"], list):
        opts_in["stages"] = tuple(opts_in["stages"])
    opts_in.update(server_options(backend.settings, known))
    try:
        opts = AlignOptions(**opts_in)
    except (TypeError, ValueError) as exc:
        raise Problem(422, "invalid-input", "Invalid options", str(exc)) from None

    with tempfile.TemporaryDirectory(prefix="gsa-job-") as tmp:
        work = Path(tmp)
        prog("loading", 0.0)
        target = _load(
            backend, job.target, work, "target", prog, reconstructions, recon_iterations
        )
        results, files, transforms = [], [], []
        multi = len(job.sources) > 1
        for i, ref in enumerate(job.sources):
            prog.part = i
            source = _load(
                backend,
                ref,
                work,
                f"source{i}",
                prog,
                reconstructions,
                recon_iterations,
            )
            prog.check(force=True)
            res = align(source, target, opts, progress=prog)
            prog("writing", 0.99)
            out_dir = work / f"out{i}"
            extra = {
                "job_id": job.id,
                "source_asset_id": ref.asset_id,
                "target_asset_id": job.target.asset_id,
            }
            paths = write_outputs(
                res, source, target, out_dir, outputs=outputs, extra=extra
            )
            d = res.to_dict()
            d["source_asset_id"] = ref.asset_id
            results.append(d)
            files += _collect(paths, f"s{i}/" if multi else "")
            transforms.append(res.transform)
            del source, res
        if multi and "renders" in outputs:
            # Paper App. B: every model in the reference frame, seen from the same cameras.
            prog.part = len(job.sources) - 1
            prog("renders", 0.0)
            files += _synchronized(backend, job, target, transforms, work, notes)
        # Models reconstructed from image sets are results in their own right.
        files += [
            (f"reconstructed/{n}.ply", p)
            for n, (_, p) in sorted(reconstructions.items())
        ]
        prog.check(force=True)
        artifacts = []
        for name, path in files:
            key = f"{art_prefix}/{name}"
            with open(path, "rb") as fh:
                size = backend.storage.put(key, fh)
            artifacts.append(
                Artifact(name=name, key=key, size=size, content_type=content_type(name))
            )
    result = dict(results[0]) if len(results) == 1 else {}
    result["results"] = results
    if reconstructions:
        result["reconstructions"] = {
            n: summ for n, (summ, _) in reconstructions.items()
        }
    if notes:
        result["notes"] = notes
    ok = _finish(
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


def _synchronized(
    backend: Backend, job: Job, target, transforms, work: Path, notes: list
) -> list:
    from gsa.io.ply import read_ply
    from gsa.render.views import write_synchronized_renders
    from gsa.sim3 import Sim3

    if any(ref.kind != "ply" for ref in job.sources):
        notes.append(
            "synchronized renders skipped: they need every source as a 3DGS model file"
        )
        return []
    models = [target] + [
        read_ply(work / f"source{i}.ply", max_gaussians=backend.settings.max_gaussians)
        for i in range(len(job.sources))
    ]
    feats = all(m.features is not None for m in models)
    paths = write_synchronized_renders(
        models, work / "sync", transforms=[Sim3.identity(), *transforms], features=feats
    )
    return [(f"synchronized/{Path(p).name}", Path(p)) for _, p in sorted(paths.items())]


def _finish(
    backend: Backend, job_id: str, token: str, state: JobState, **fields
) -> bool:
    return backend.store.update(
        job_id,
        states={JobState.running},
        token=token,
        state=state,
        finished_at=time.time(),
        lease_until=None,
        **fields,
    )


def _release_memory() -> None:
    gc.collect()
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        torch.cuda.empty_cache()


# ------------------------------------------------------------------ reaper
def reap(backend: Backend, *, force: bool = False) -> list[str]:
    """Requeue (or fail, when attempts are spent) running jobs whose lease expired.

    force=True treats every running job as lost: embedded mode at startup, where
    the only possible worker was the previous process.
    """
    now = time.time()
    touched = []
    for job in backend.store.running():
        if not force and job.lease_until is not None and job.lease_until > now:
            continue
        common = dict(
            states={JobState.running},
            token=job.run_token,
            lease_until=None,
            worker=None,
        )
        if job.cancel_requested:
            ok = backend.store.update(
                job.id, state=JobState.cancelled, finished_at=now, **common
            )
        elif job.attempts >= job.max_attempts:
            err = Problem(
                500,
                "worker-lost",
                "Job failed",
                f"the worker running this job was lost {job.attempts} times; giving up",
            ).to_dict()
            ok = backend.store.update(
                job.id, state=JobState.failed, finished_at=now, error=err, **common
            )
        else:
            ok = backend.store.update(
                job.id,
                state=JobState.queued,
                stage="requeued",
                run_token=None,
                **common,
            )
            if ok:
                backend.queue.enqueue(job.id)
        if ok:
            log.warning(
                "reaped job %s (attempt %d, worker %s)",
                job.id,
                job.attempts,
                job.worker,
            )
            touched.append(job.id)
            if job.cancel_requested or job.attempts >= job.max_attempts:
                notify_webhook(backend, job.id)
    return touched


def _requeue(backend: Backend, job_id: str) -> None:
    ref = backend.queue.enqueue(job_id)
    backend.store.update(job_id, queue_ref=ref, enqueued_at=time.time())


def resend_lost(backend: Backend) -> list[str]:
    """Queued jobs whose queue message is gone (e.g. the worker died between
    dequeuing and claiming) are enqueued again. Duplicates are harmless: the
    claim is a compare-and-set, so only one delivery ever runs the job."""
    now = time.time()
    grace = 2 * backend.settings.lease_s
    out = []
    for job_id in backend.store.queued_ids():
        job = backend.store.get(job_id)
        if job is None or job.state != JobState.queued or not job.queue_ref:
            continue
        if job.enqueued_at is not None and now - job.enqueued_at < grace:
            continue
        if backend.queue.lost(job.queue_ref):
            log.warning("re-sending lost queue message for job %s", job_id)
            _requeue(backend, job_id)
            out.append(job_id)
    return out


def start_reaper(backend: Backend, stop: threading.Event) -> threading.Thread:
    def loop():
        while not stop.wait(backend.settings.reaper_interval_s):
            try:
                reap(backend)
                resend_lost(backend)
            except Exception:
                log.exception("reaper pass failed")

    t = threading.Thread(target=loop, name="gsa-reaper", daemon=True)
    t.start()
    return t


# ---------------------------------------------------------- embedded worker
def start_embedded_workers(
    backend: Backend, stop: threading.Event
) -> list[threading.Thread]:
    """In-process workers for embedded mode: poll the SQLite queue, run jobs."""
    reap(backend, force=True)  # jobs "running" in a previous process were lost with it

    def loop():
        while not stop.is_set():
            ran = False
            for job_id in backend.store.queued_ids():
                if stop.is_set():
                    break
                try:
                    if execute(job_id, backend) is not None:
                        ran = True
                except Exception:
                    log.exception("embedded worker error on %s", job_id)
            if not ran:
                backend.queue.wake.wait(1.0)
                backend.queue.wake.clear()

    threads = []
    for i in range(max(backend.settings.embedded_workers, 1)):
        t = threading.Thread(target=loop, name=f"gsa-worker-{i}", daemon=True)
        t.start()
        threads.append(t)
    return threads


# -------------------------------------------------------------- RQ worker
def run_job(job_id: str) -> str | None:
    """RQ task entry point (runs in the forked work horse)."""
    state = execute(job_id, process_backend())
    return state.value if state else None


def _warm_up() -> None:
    """Load the library and run one tiny alignment in the worker parent, so each
    forked work horse inherits imported modules and loaded numba kernels
    (a cold process pays ~1 s on its first alignment).

    numba's default GNU-OpenMP threading layer aborts a child that forks after
    the parent ran parallel code, so the worker uses the fork-safe `workqueue`
    layer (fine here: one job thread per process)."""
    if "numba" not in sys.modules:
        os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
    t = time.perf_counter()
    try:
        import numba

        if numba.config.THREADING_LAYER not in ("workqueue", "tbb"):
            log.warning(
                "numba threading layer %s is not fork-safe: skipping warm-up",
                numba.config.THREADING_LAYER,
            )
            return
        from gsa.align.outputs import write_outputs  # noqa: F401
        from gsa.align.pipeline import AlignOptions, align
        from gsa.synth import make_object

        m = make_object("car", seed=0, n_gaussians=500)
        align(m, m, AlignOptions(coarse_iterations=2))
        # Import only (torch and the render kernels): running torch ops here
        # would start its OpenMP pool, which does not survive fork().
        import gsa.render.views  # noqa: F401
    except Exception:  # a broken library shows up in the jobs' errors; keep serving
        log.exception("worker warm-up failed")
        return
    # Pre-fork hygiene: move everything loaded so far out of the GC's reach so the
    # horses' collections do not copy-on-write the whole inherited heap.
    gc.collect()
    gc.freeze()
    log.info("worker warm-up took %.2f s", time.perf_counter() - t)


def run_rq_worker(burst: bool = False, name: str | None = None) -> None:
    """A worker process: RQ worker on the job + webhook queues, plus a reaper."""
    from rq import Worker

    backend = process_backend()
    if backend.redis is None:
        raise SystemExit(
            "gsa worker needs GSA_REDIS_URL (embedded mode runs workers inside `gsa serve`)"
        )
    _warm_up()
    stop = threading.Event()
    start_reaper(backend, stop)
    queues = [backend.queue.hooks, backend.queue.q]  # webhooks first: they are tiny
    w = Worker(
        queues, connection=backend.redis, name=name or f"gsa-{uuid.uuid4().hex[:8]}"
    )
    try:
        w.work(burst=burst, with_scheduler=True)
    finally:
        stop.set()
