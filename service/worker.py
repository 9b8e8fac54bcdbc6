"""The worker's public entry points, kept at this address on purpose.

RQ messages name their task as "service.worker.run_job" (see
service.backend.RQQueue.enqueue), and `gsa worker` starts run_rq_worker from
here, so these names must stay importable from service.worker. The code lives in:

- service.execution: one attempt of a job (claim, load, align, store artifacts)
- service.leases: leases, heartbeat, progress, the reaper
- service.runners: embedded workers, the RQ worker and its task
"""

from __future__ import annotations

from service.execution import execute  # noqa: F401
from service.leases import reap, resend_lost, start_reaper  # noqa: F401
from service.runners import run_job, run_rq_worker, start_embedded_workers  # noqa: F401
