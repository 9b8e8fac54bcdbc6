#!/usr/bin/env python
"""The longest stretches of an alignment without a progress report (docs/service.md, "Cancel and
leases": an embedded-mode job stops at its next report, so a long stretch without one is a late
cancel).

A bus of N Gaussians against a 3,000-Gaussian car (as benchmarks/service/measure_cancel.py writes
its pair: other objects, a doubtful answer, so the semantic stage, the frame snap and the
relabelling choice run too) is aligned in-process with default options and a progress callback
that notes the time, the stage and the library line that reported. A sampler thread notes the
aligning thread's innermost `gsa` frames every --sample-s seconds, so each long gap also says
what ran in it. Prints the longest gaps (start to first report and last report to the end
included), each with its stage, the lines before and after and the code sampled most in it.

    .venv/bin/python -m benchmarks.report_gaps --gaussians 300000
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import threading
import time
import traceback

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HELPERS = {"_report", "<lambda>", "report", "__call__", "tick"}  # pass a report on: name their caller


def pair(n: int):
    from gsa.synth import make_object

    return make_object("bus", seed=1, n_gaussians=n), make_object("car", seed=3, n_gaussians=3000)


def _where(frames) -> str:
    """The innermost library frame of a stack (file:function:line), else the innermost."""
    inside = [f for f in frames if f"{os.sep}gsa{os.sep}" in f.filename and f.name not in HELPERS]
    f = (inside or list(frames))[-1]
    return f"{os.path.relpath(f.filename, ROOT)}:{f.name}:{f.lineno}"


def _sampled(frame) -> str:
    """The two innermost library frames of a live frame."""
    stack = traceback.extract_stack(frame)
    inside = [f for f in stack if f"{os.sep}gsa{os.sep}" in f.filename]
    return " < ".join(f"{os.path.basename(f.filename)}:{f.name}:{f.lineno}" for f in reversed(inside[-2:])) or "-"


def measure(source, target, sample_s: float = 0.1, options=None):
    """align() with a recording callback; returns (reports, samples, t0, t1, result).
    reports: (time, stage, fraction, where), samples: (time, where)."""
    from gsa.align.pipeline import AlignOptions, align

    reports: list[tuple[float, str, float, str]] = []
    samples: list[tuple[float, str]] = []
    me = threading.get_ident()
    stop = threading.Event()

    def progress(stage: str, fraction: float) -> None:
        reports.append((time.monotonic(), stage, fraction, _where(traceback.extract_stack()[:-1])))

    def sampler() -> None:
        while not stop.wait(sample_s):
            frame = sys._current_frames().get(me)
            if frame is not None:
                samples.append((time.monotonic(), _sampled(frame)))

    thread = threading.Thread(target=sampler, daemon=True)
    thread.start()
    t0 = time.monotonic()
    try:
        result = align(source, target, options or AlignOptions(), progress=progress)
    finally:
        t1 = time.monotonic()
        stop.set()
        thread.join()
    return reports, samples, t0, t1, result


def gaps(reports, samples, t0: float, t1: float) -> list[dict]:
    """Every stretch between consecutive reports (and start/end), longest first."""
    marks = [(t0, "(start)", 0.0, "align() called")] + list(reports) + [(t1, "(end)", 1.0, "align() returned")]
    out = []
    for a, b in zip(marks, marks[1:]):
        inside = collections.Counter(w for t, w in samples if a[0] <= t < b[0])
        out.append(
            {
                "gap_s": round(b[0] - a[0], 3),
                "stage": a[1] if a[1] != "(start)" else b[1],
                "fraction": round(a[2], 3),
                "after": a[3],
                "before": b[3],
                "ran": [f"{w} ×{k}" for w, k in inside.most_common(3)],
            }
        )
    return sorted(out, key=lambda g: -g["gap_s"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gaussians", type=int, default=300_000)
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--sample-s", type=float, default=0.1)
    ap.add_argument("--json", help="also write every gap to this JSON file")
    a = ap.parse_args()
    from gsa.align import semantic

    semantic.available_backbone()  # as the service's worker does in its warm-up
    source, target = pair(a.gaussians)
    reports, samples, t0, t1, result = measure(source, target, a.sample_s)
    rows = gaps(reports, samples, t0, t1)
    stages = collections.Counter(s for _, s, _, _ in reports)
    print(
        f"N={a.gaussians:,}: align {t1 - t0:.1f} s, {len(reports)} reports, load {os.getloadavg()[0]:.1f}, "
        f"semantic used: {bool((result.metrics.get('semantic') or {}).get('used'))}, "
        f"doubtful: {result.metrics.get('doubtful')}"
    )
    print("reports per stage: " + ", ".join(f"{s} {k}" for s, k in stages.items()))
    print(f"longest gaps (of {len(rows)}):")
    for g in rows[: a.top]:
        print(f"  {g['gap_s']:7.2f} s  {g['stage']:<11} @{g['fraction']:.2f}  {g['after']}  ->  {g['before']}")
        for r in g["ran"]:
            print(f"             ran: {r}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"gaussians": a.gaussians, "align_s": t1 - t0, "gaps": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
