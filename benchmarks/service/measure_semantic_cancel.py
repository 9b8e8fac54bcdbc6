#!/usr/bin/env python
"""How soon a cancel stops an alignment in the semantic stage, from one traced run.

A doubtful pair (a bus of N Gaussians against a 50k-Gaussian car, as benchmarks/service/bench_job_memory.py's
`semantic` kind) is aligned in-process with a default coarse job's options; the progress callback
records when it is called, and a cancel flag is read where the service's callback reads the job
(service.worker.leases.JobProgress: at a report, at most every 0.2 s). For every cancel moment t
over the semantic stage (a grid of --moments moments, and just after every report), the latency is
the time from t to the first read at or after t: the job then raises and unwinds (~0.1 s in the
service's measured cancels). Prints the stage's length, its report count, the longest gaps between
reports (with the stage fraction before each) and the latency's maximum and quantiles.

--cancel-at S: a real cancel instead, S seconds into the semantic stage (the callback raises at the
first read after it); prints the time from the flag to align() returning the exception.

    .venv/bin/python -m benchmarks.service.measure_semantic_cancel --gaussians 3000000
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

READ_EVERY_S = 0.2  # JobProgress reads the job at most this often


class Cancelled(Exception):
    pass


def pair(n: int):
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    gt = Sim3(1.4, np.eye(3), np.array([0.4, -0.2, 0.7]))
    source = make_object("bus", seed=1, n_gaussians=n)
    target = make_object("car", seed=3, n_gaussians=50_000).transformed(gt)
    return source, target


def latencies(reads: np.ndarray, start: float, end: float, moments: int) -> np.ndarray:
    """Latency of a cancel at each moment: the grid over [start, end) and just after each read."""
    grid = np.linspace(start, end, moments, endpoint=False)
    at = np.concatenate([grid, reads[(reads >= start) & (reads < end)] + 1e-6])
    nxt = np.searchsorted(reads, at)
    ok = nxt < len(reads)
    return reads[nxt[ok]] - at[ok]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=300_000)
    ap.add_argument("--moments", type=int, default=1000)
    ap.add_argument("--cancel-at", type=float, help="seconds into the semantic stage: a real cancel")
    ap.add_argument("--json", action="store_true", help="one JSON line")
    a = ap.parse_args()
    from gsa.align import semantic
    from gsa.align.pipeline import AlignOptions, align

    semantic.available_backbone()  # as the service's worker does in its warm-up
    source, target = pair(a.gaussians)
    calls: list[tuple[float, str, float]] = []
    reads: list[float] = []
    stage_start = [None]
    flagged = [None]

    def progress(stage: str, fraction: float) -> None:
        now = time.perf_counter()
        calls.append((now, stage, fraction))
        if stage == "semantic" and stage_start[0] is None:
            stage_start[0] = now
        changed = len(calls) < 2 or calls[-2][1] != stage
        if changed or now - (reads[-1] if reads else -1e9) > READ_EVERY_S:
            reads.append(now)
            if a.cancel_at is not None and stage_start[0] is not None and now - stage_start[0] >= a.cancel_at:
                if flagged[0] is None:  # the flag is set at cancel_at; this read is the first to see it
                    flagged[0] = stage_start[0] + a.cancel_at
                raise Cancelled()

    t0 = time.perf_counter()
    try:
        result = align(source, target, AlignOptions(stages=("coarse",)), progress=progress)
    except Cancelled:
        took = time.perf_counter() - flagged[0]
        print(f"N={a.gaussians:,} cancel {a.cancel_at} s into the semantic stage: stopped {took:.2f} s after the flag")
        return
    returned = time.perf_counter()
    total = returned - t0
    used = bool((result.diagnostics.get("semantic") or {}).get("used"))
    sem = [(t, f) for t, s, f in calls if s == "semantic"]
    if not sem:
        print("the semantic stage did not run")
        return
    start = sem[0][0]
    # the stage shows until the next stage's first report (or align() returns): its tail counts
    end = next((t for t, s, _ in calls if t > start and s != "semantic"), returned)
    times = np.array([t for t, _ in sem] + [end])
    gaps = np.diff(times)
    worst = np.argsort(-gaps)[:5]
    lat = latencies(np.array(reads + [end]), start, end, a.moments)
    out = {
        "gaussians": a.gaussians,
        "semantic_used": used,
        "align_s": round(total, 1),
        "stage_s": round(end - start, 1),
        "reports": len(sem),
        "longest_gaps": [(round(float(gaps[i]), 2), round(float(sem[i][1]), 3)) for i in worst],
        "latency_max_s": round(float(lat.max()), 2),
        "latency_p99_s": round(float(np.quantile(lat, 0.99)), 2),
        "latency_median_s": round(float(np.median(lat)), 2),
        "load": os.getloadavg(),
    }
    print(json.dumps(out) if a.json else "\n".join(f"{k}: {v}" for k, v in out.items()))


if __name__ == "__main__":
    main()
