"""Whole-process wall time of `gsa align` on a 50k-vs-50k Gaussian pair: Python
start-up, imports, numba (cache loading or compilation), PLY reading, alignment
and writing result.json, as a user sees it.

    python -m benchmarks.cli_speed [--runs 5] [--gaussians 50000] [--keep DIR] [-- extra gsa align args]

The pair: two independent samplings of a generated car, the target moved by a
random Sim(3). Prints every run, then min/median; the first run is also shown on
its own (it may compile numba kernels when the cache is cold), plus the time of
`python -c "import gsa.cli"` and of a bare `python -c pass`, and the in-process
`timings` of the last result.json (median over runs).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _gsa_command() -> list[str]:
    script = Path(sys.executable).with_name("gsa")
    return [str(script)] if script.exists() else [sys.executable, "-m", "gsa.cli"]


def _timed(cmd: list[str], env: dict | None = None) -> tuple[float, subprocess.CompletedProcess]:
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    return time.perf_counter() - t, proc


def _summary(values: list[float]) -> str:
    return f"min {min(values):.3f} s, median {statistics.median(values):.3f} s"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--gaussians", type=int, default=50_000)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--keep", help="write the pair and results here instead of a temporary folder")
    parser.add_argument("extra", nargs="*", help="more `gsa align` arguments (after --)")
    args = parser.parse_args(argv)

    import numpy as np

    from gsa.io import write_ply
    from gsa.synth import make_object, random_sim3

    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="gsa_bench_cli_"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        n = args.gaussians
        truth = random_sim3(np.random.default_rng(args.seed))
        source = make_object("car", seed=1, n_gaussians=n, sample_seed=5, floaters=0.02)
        target = make_object("car", seed=1, n_gaussians=n).transformed(truth)
        src, dst = write_ply(source, folder / "source.ply"), write_ply(target, folder / "target.ply")
        out = folder / "result.json"
        cmd = [*_gsa_command(), "align", str(src), str(dst), "--out", str(out), "--quiet", *args.extra]
        print(f"pair: {len(source)} vs {len(target)} Gaussians in {folder}")
        print("command: " + " ".join(cmd), flush=True)

        walls: list[float] = []
        timings: dict[str, list[float]] = {}
        for i in range(args.runs):
            wall, proc = _timed(cmd)
            if proc.returncode != 0:
                print(proc.stdout + proc.stderr, file=sys.stderr)
                raise SystemExit(f"gsa align failed with exit code {proc.returncode}")
            walls.append(wall)
            result = json.loads(out.read_text())
            for key, value in (result.get("timings") or {}).items():
                if isinstance(value, (int, float)):
                    timings.setdefault(key, []).append(float(value))
            load = os.getloadavg()[0]
            print(
                f"run {i + 1}: {wall:.3f} s (in-process total {result.get('timings', {}).get('total', float('nan')):.3f} s, "
                f"load {load:.1f})",
                flush=True,
            )

        imports = [_timed([sys.executable, "-c", "import gsa.cli"])[0] for _ in range(args.runs)]
        bare = [_timed([sys.executable, "-c", "pass"])[0] for _ in range(args.runs)]
        print()
        print(f"gsa align (whole process, {args.runs} runs): {_summary(walls)}; first run {walls[0]:.3f} s")
        if len(walls) > 1:
            print(f"gsa align without the first run:       {_summary(walls[1:])}")
        print(f'python -c "import gsa.cli":             {_summary(imports)}')
        print(f'python -c "pass":                       {_summary(bare)}')
        if timings:
            print(
                "in-process timings (median over runs): "
                + ", ".join(f"{k} {statistics.median(v):.3f} s" for k, v in timings.items())
            )
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
