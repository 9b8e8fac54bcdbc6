"""Running jobs: one attempt (execution), leases and the reaper (leases), the
embedded and RQ workers (runners), format conversion in a child process (convert).

RQ messages name their task "service.worker.run_job" (service.backend.RQQueue.enqueue):
that name stays resolvable here for workers of any version, and imports the
runners only when called, so importing a submodule of this package stays light.
"""

from __future__ import annotations


def run_job(job_id: str) -> str | None:
    """RQ task entry point: see service.worker.runners.run_job."""
    from service.worker.runners import run_job as run

    return run(job_id)
