"""The worker's entry points, kept at this address on purpose.

RQ messages name their task as "service.worker.run_job" (see
service.backend.RQQueue.enqueue), and `gsa worker` starts run_rq_worker from
here, so these names must stay importable from service.worker. The code lives in:

- service.execution: one attempt of a job (claim, load, align, store artifacts)
- service.leases: leases, heartbeat, progress, the reaper
- service.runners: embedded workers, the RQ worker and its task
"""

from __future__ import annotations

from service.runners import run_job, run_rq_worker  # noqa: F401  (RQ resolves run_job by this name)
