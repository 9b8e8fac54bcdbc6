#!/usr/bin/env python
"""Predicted against measured peak memory of default coarse jobs on large models, with and
without the semantic stage (docs/service.md, "Worker memory budget").

For each size N: a source of N Gaussians (SH 0, as the captures of the memory probe) against
a 50k-Gaussian target, two ways, each in a fresh child process that reads both models, runs
`align()` and writes every default output, as a worker does (benchmarks/service/measure_job_memory.py):

- default: two samplings of one car (a confident answer: the semantic stage does not run);
- semantic: a bus against a car (other objects: a doubtful answer, so the semantic
  tie-break renders both models, runs the backbone and lifts its features onto them);
- off: the default pair with `semantic: off`.

The admission cannot know whether an answer will be doubtful, so it counts the semantic stage
whenever it may run: a `default` job is predicted as a `semantic` one.

The row shows the prediction of `service.jobs.memory.predict_job_memory`, the child's peak RSS
(VmHWM), prediction / peak (the admission is an upper bound: at least 1) and whether the
semantic stage ran. `--save` keeps the measurements; `--load` prints them against the model as
it is now, without running anything.

    .venv/bin/python -m benchmarks.service.bench_job_memory [--sizes 50000 300000 3000000] [--save m.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))
from benchmarks.service.measure_job_memory import measure  # noqa: E402

TARGET_GAUSSIANS = 50_000


def write_pair(d: Path, n: int, other_object: bool) -> tuple[Path, Path]:
    import numpy as np

    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    gt = Sim3(1.4, np.eye(3), np.array([0.4, -0.2, 0.7]))
    if other_object:
        src = make_object("bus", seed=1, n_gaussians=n)
        tgt = make_object("car", seed=3, n_gaussians=TARGET_GAUSSIANS)
    else:
        src = make_object("car", seed=3, n_gaussians=n)
        tgt = make_object("car", seed=3, n_gaussians=TARGET_GAUSSIANS, sample_seed=11)
    write_ply(src, d / "source.ply")
    write_ply(tgt.transformed(gt), d / "target.ply")
    return d / "source.ply", d / "target.ply"


def options(kind: str) -> dict:
    """A default coarse job; `off`: with `semantic: off` (the admission then leaves it out)."""
    return {"stages": ["coarse"], **({"semantic": "off"} if kind == "off" else {})}


def row(m: dict) -> str:
    """One table row: the measurement against the current model's prediction."""
    from service.jobs.memory import MB, predict_job_memory

    pred = predict_job_memory(options(m["kind"]), [m["gaussians"]], TARGET_GAUSSIANS, [m["b_s"]], m["b_t"])
    peak = m["peak_bytes"]
    return (
        f"{m['gaussians']:>9,} {TARGET_GAUSSIANS:>7,} {m['kind']:>9} {str(m['semantic_ran']):>12} {pred / MB:>12,.0f} "
        f"{peak / MB:>8,.0f} {pred / peak:>10.2f} {m['seconds']:>6.1f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[50_000, 300_000, 3_000_000])
    ap.add_argument(
        "--kinds", nargs="+", default=["default", "semantic", "off"], choices=["default", "semantic", "off"]
    )
    ap.add_argument("--save", type=Path, help="append each measurement to this JSON-lines file")
    ap.add_argument("--load", type=Path, help="no runs: the table of saved measurements against the current model")
    a = ap.parse_args()
    from service.jobs.memory import gaussian_bytes

    print(
        f"{'source':>9} {'target':>7} {'run':>9} {'semantic ran':>12} {'predicted MB':>12} {'peak MB':>8} {'pred/peak':>10} {'s':>6}"
    )
    if a.load:
        for line in a.load.read_text().splitlines():
            print(row(json.loads(line)))
        return
    for n in a.sizes:
        for kind in a.kinds:
            with tempfile.TemporaryDirectory(prefix="gsa-bench-mem-") as d:
                src, tgt = write_pair(Path(d), n, other_object=kind == "semantic")
                got = measure(src, tgt, options(kind), timeout=3600)
                sizes = {
                    "b_s": gaussian_bytes(n, src.stat().st_size),
                    "b_t": gaussian_bytes(TARGET_GAUSSIANS, tgt.stat().st_size),
                }
            m = {"gaussians": n, "kind": kind, **got, **sizes}
            print(row(m), flush=True)
            if a.save:
                with a.save.open("a") as fh:
                    fh.write(json.dumps(m) + "\n")


if __name__ == "__main__":
    main()
