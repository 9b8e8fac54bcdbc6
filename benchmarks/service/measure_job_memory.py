"""Peak memory of one alignment job, as a worker runs it, in a fresh child process.

The child reads the two models, runs `align()` with the job's options and writes the job's
outputs (what `service.worker.execution` does for a single-source job), then reports its own peak
RSS (`ru_maxrss`, which includes the interpreter, numpy, numba and torch: the worker's cost of
one job from a cold process). The parent prints one JSON line per run with the prediction of
`service.jobs.memory.predict_job_memory` beside it.

    .venv/bin/python -m benchmarks.service.measure_job_memory --gaussians 3000 \
        --options '{"stages": ["coarse", "fine"], "fine_views": 8, "fine_image_size": 256, "fine_iterations": 1}'
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository


def child(src: str, tgt: str, options: dict, out: str) -> dict:
    from gsa.align.outputs import write_outputs
    from gsa.align.pipeline import AlignOptions, align
    from gsa.io import read_model
    from service.jobs.options import DEFAULT_OUTPUTS

    opts = dict(options)
    outputs = set(opts.pop("outputs", None) or DEFAULT_OUTPUTS)
    if opts.pop("renders", True) is False:
        outputs.discard("renders")
    if isinstance(opts.get("stages"), list):
        opts["stages"] = tuple(opts["stages"])
    t0 = time.perf_counter()
    source, target = read_model(src), read_model(tgt)
    res = align(source, target, AlignOptions(**opts))
    write_outputs(res, source, target, Path(out), outputs=outputs)
    return {
        "peak_bytes": _peak_rss_bytes(),
        "seconds": round(time.perf_counter() - t0, 2),
        "fine_ran": res.fine is not None,
        "semantic_ran": bool((res.diagnostics.get("semantic") or {}).get("used")),
        "semantic_seconds": round(res.timings.get("semantic", 0.0), 2),
    }


def _peak_rss_bytes() -> int:
    """This process's own RSS high-water mark. VmHWM, not ru_maxrss: Linux carries ru_maxrss
    across exec, so a child started from a large parent (a test runner holding 800 MB) would
    report the parent's size."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measure(src: Path, tgt: Path, options: dict, timeout: float = 900) -> dict:
    """Run one job in a fresh child process; its measured peak (bytes) and seconds."""
    with tempfile.TemporaryDirectory(prefix="gsa-mem-") as out:
        arg = json.dumps({"src": str(src), "tgt": str(tgt), "options": options, "out": out})
        p = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--child", arg],
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=ROOT,
            env={**__import__("os").environ, "PYTHONPATH": str(ROOT)},
        )
        if p.returncode != 0:
            raise RuntimeError(p.stderr[-3000:])
        return json.loads(p.stdout.strip().splitlines()[-1])


def make_pair(d: Path, n: int, sh_degree: int = 3) -> tuple[Path, Path]:
    import numpy as np

    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    src = make_object("car", seed=3, n_gaussians=n, sh_degree=sh_degree)
    gt = Sim3(1.4, np.eye(3), np.array([0.4, -0.2, 0.7]))
    write_ply(src, d / "source.ply")
    write_ply(src.transformed(gt), d / "target.ply")
    return d / "source.ply", d / "target.ply"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--child")
    ap.add_argument("--gaussians", type=int, nargs="+", default=[3000])
    ap.add_argument("--options", action="append", default=[], help="job options JSON (repeatable)")
    a = ap.parse_args()
    if a.child:
        c = json.loads(a.child)
        print(json.dumps(child(c["src"], c["tgt"], c["options"], c["out"])))
        return
    from service.jobs.memory import predict_job_memory

    for n in a.gaussians:
        with tempfile.TemporaryDirectory() as d:
            src, tgt = make_pair(Path(d), n)
            for o in a.options or ["{}"]:
                options = json.loads(o)
                got = measure(src, tgt, options)
                pred = predict_job_memory(options, [n], n)
                print(json.dumps({"gaussians": n, "options": options, **got, "predicted_bytes": pred}), flush=True)


if __name__ == "__main__":
    main()
