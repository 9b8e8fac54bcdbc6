#!/usr/bin/env python
"""Chaos run with real processes: submit small jobs while workers are SIGKILLed at
random moments, Redis is restarted, the API is SIGKILLed and restarted and the
storage is filled to its quota; print jobs submitted / completed / lost /
duplicated and the recovery time after each fault.

    python -m benchmarks.service.chaos_service [--jobs 100] [--workers 3] [--rounds 2] [--gap 4] [--seed 0]

Starts its own redis-server (free loopback port, fsync'ed append-only file),
`gsa serve` and `gsa worker` processes in a temp dir (tests/service/chaos_run.py;
the pytest version is tests/service/test_chaos_service.py). Recovery time: from
the end of a fault (the process restarted, the storage freed) to the next job
seen finishing. Exit status 1 when a job was lost or finished twice.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))

from tests.service.chaos_run import DEFAULT_FAULTS, ChaosRun  # noqa: E402


def make_pair(d: Path, n: int) -> dict:
    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    src = make_object("car", seed=3, n_gaussians=n)
    write_ply(src, d / "source.ply")
    write_ply(src.transformed(Sim3(1.3, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], [0.2, 0.1, -0.3])), d / "target.ply")
    return {"source": d / "source.ply", "target": d / "target.ply"}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--jobs", type=int, default=100)
    ap.add_argument("--workers", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=2, help="times the fault sequence is repeated")
    ap.add_argument("--gap", type=float, default=4.0, help="mean seconds between faults")
    ap.add_argument("--gaussians", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--webhook-wait", type=float, default=180, help="seconds to wait for late webhooks at the end")
    ap.add_argument("--keep", action="store_true", help="keep the temp folder (logs)")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="gsa-chaos-"))
    run = ChaosRun(tmp / "dep", make_pair(tmp, a.gaussians), a.jobs, a.workers, a.seed, a.gap, a.webhook_wait)
    try:
        rep = run.run(DEFAULT_FAULTS * a.rounds, deadline_s=120 + 20 * a.rounds * len(DEFAULT_FAULTS))
    finally:
        run.close()
        if a.keep:
            print(f"logs kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    done = sum(rep.final.values())
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    print(
        f"jobs submitted {rep.submitted} (client retries {rep.submit_retries}), on the server {rep.jobs_on_server}, "
        f"final {done} {rep.final}, lost {len(rep.lost)}, duplicated {len(rep.duplicated)}, "
        f"without a webhook {len(rep.missing_webhooks)}, "
        f"with artifacts of other than one attempt {len(rep.artifact_sets_not_one)}; most attempts {rep.attempts_max}; errors {rep.errors}; "
        f"{rep.wall_s} s; load {load}"
    )
    for f in rep.faults:
        print(f"  {f['fault']:<14} recovery {f['recovery_s']} s  {f['note']}")
    print(json.dumps({"lost": rep.lost, "duplicated": rep.duplicated, "missing_webhooks": rep.missing_webhooks}))
    ok = rep.submitted == a.jobs == rep.jobs_on_server and not rep.lost and not rep.duplicated
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
