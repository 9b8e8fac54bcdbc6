#!/usr/bin/env python
"""Fuzz the HTTP API of a real deployment with thousands of generated requests
and print the numbers: requests, unexpected 5xx, hangs, peak server RSS, and
whether what was stored before is byte-identical after.

    python -m benchmarks.service.fuzz_service [--requests 3000] [--outages 3] [--bound 10] [--worker]
        [--seed N] [--save out/fuzz-found]

Starts its own redis-server (free loopback port, append-only file), `gsa serve`
and, for the baseline (and with --worker for the whole run), a `gsa worker`, in a
temp dir. The generators and checks are tests/service/fuzz_requests.py (the
pytest version is tests/service/test_fuzz_service.py). Every --outages-th part of
the run happens with Redis stopped: there, and only there, 503 is expected.
Exit status 1 when anything broke the contract.

This is the random search (new cases on every run unless --seed is given); the test
suite only replays fixed ones. Every request that broke the contract is written to
--save as a .http file (tests/service/fuzz_requests.dump_http): what this finds joins
the stored corpus, tests/service/corpus/, which tests/service/test_fuzz_corpus.py
replays on every test run (check its "# expect:" line; ids of this run's baseline
jobs and assets will not exist there).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from hypothesis import HealthCheck, Phase, given, seed, settings

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))

from tests.service.fuzz_requests import requests  # noqa: E402
from tests.service.fuzz_run import FuzzSession, dumps  # noqa: E402


def make_pair(d: Path) -> tuple[Path, Path]:
    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    src = make_object("car", seed=3, n_gaussians=3000)
    write_ply(src, d / "source.ply")
    write_ply(src.transformed(Sim3(1.3, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], [0.2, 0.1, -0.3])), d / "target.ply")
    return d / "source.ply", d / "target.ply"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--requests", type=int, default=3000)
    ap.add_argument("--outages", type=int, default=3, help="Redis outages spread over the run (0: none)")
    ap.add_argument("--outage-requests", type=int, default=60, help="requests sent during each outage")
    ap.add_argument("--bound", type=float, default=10.0, help="seconds one request may take")
    ap.add_argument("--worker", action="store_true", help="keep a worker running the fuzzed jobs")
    ap.add_argument("--keep", action="store_true", help="keep the temp folder (logs)")
    ap.add_argument("--seed", type=int, default=None, help="replay one run's draws (default: new ones every run)")
    ap.add_argument(
        "--save", type=Path, default=ROOT / "out" / "fuzz-found", help="where requests that broke the contract go"
    )
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="gsa-fuzz-"))
    t0 = time.monotonic()
    src, tgt = make_pair(tmp)
    s = FuzzSession(tmp / "dep", src.read_bytes(), worker=a.worker, bound_s=a.bound, save_dir=a.save)
    batches = iter(range(1 << 30))
    try:
        targets = s.store_baseline(src, tgt)
        strategy = requests(s.corpus, targets, s.names)

        def batch(n: int) -> None:
            @settings(
                max_examples=n,
                deadline=None,
                database=None,
                phases=[Phase.generate],
                suppress_health_check=list(HealthCheck),
            )
            @given(req=strategy)
            def one(req):
                s.run(req)

            if a.seed is not None:  # each batch its own draws, the same ones for the same --seed
                one = seed(a.seed * 1000 + next(batches))(one)
            one()

        normal = a.requests - a.outages * a.outage_requests
        parts = a.outages + 1
        outage_log = []
        for i in range(parts):
            batch(max(normal // parts, 1))
            if i < a.outages:
                s.redis_down()
                t = time.monotonic()
                batch(a.outage_requests)
                s.redis_up()
                outage_log.append(round(time.monotonic() - t, 1))
        changed = s.changed()
        summary = s.summary()
        if a.worker:
            summary["fuzzed_jobs"] = outcomes = s.fuzzed_job_outcomes()
            summary["fuzzed_jobs_failed_500"] = sum(n for k, n in outcomes.items() if "(500 " in k)
        summary["outages_s"] = outage_log
        summary["stored_before_unchanged"] = not changed
        summary["wall_s"] = round(time.monotonic() - t0, 1)
        try:
            summary["load_avg"] = [round(x, 2) for x in os.getloadavg()]
        except OSError:
            pass
        print(dumps(summary))
        for f in s.stats.failures:
            print("FAIL", f)
        if s.stats.failures:
            print(f"requests that broke the contract: {a.save} (copy them to tests/service/corpus/)")
        for c in changed:
            print("CHANGED", c)
        broken = s.stats.unexpected_5xx + s.stats.hangs + s.stats.no_answer + s.stats.other + len(changed)
        broken += summary.get("fuzzed_jobs_failed_500", 0)
        return 1 if broken else 0
    finally:
        s.close()
        if a.keep:
            print(f"logs kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
