"""Time and peak memory of reading and writing large INRIA PLY files (scene-size models).

Each (size, SH degree) runs in its own child process, which generates a model of random
Gaussians, writes it as PLY, drops it, and reads the file back. Peak memory is the kernel's
high-water mark (VmHWM), reset just before each operation (/proc/self/clear_refs "5"), so
it is exact, not sampled; "growth" is that peak minus the resident memory just before the
operation. The model itself is `model MB` (its arrays' bytes): reading never needs more than
that one copy plus a bounded chunk, writing nothing beyond the model plus a chunk.

    .venv/bin/python -m benchmarks.ply_memory --sizes 1M,2M,5M --sh 0,3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _status_mb(field: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak() -> None:
    # "5" resets VmHWM to the current RSS (Linux >= 4.0), so each operation's peak is its own.
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")


def _measured(fn):
    before = _status_mb("VmRSS")
    _reset_peak()
    t0 = time.perf_counter()
    out = fn()
    seconds = time.perf_counter() - t0
    return out, seconds, _status_mb("VmHWM") - before


def random_model(n: int, degree: int, seed: int = 0):
    """n Gaussians with random (finite) attributes; generation is not what is measured."""
    from gsa.model import GaussianModel, sh_coeff_count

    rng = np.random.default_rng(seed)
    k = sh_coeff_count(degree)
    sh = np.empty((n, k, 3), np.float32)
    for lo in range(0, n, 1 << 20):  # in slices: float64 temporaries of a 5M SH-3 draw would be 2 GB
        hi = min(n, lo + (1 << 20))
        sh[lo:hi] = rng.standard_normal((hi - lo, k, 3), dtype=np.float32)
    return GaussianModel(
        means=rng.standard_normal((n, 3), dtype=np.float32),
        quats=rng.standard_normal((n, 4), dtype=np.float32) + np.float32(2.0),
        log_scales=rng.standard_normal((n, 3), dtype=np.float32) - np.float32(4.0),
        opacity_logits=rng.standard_normal(n, dtype=np.float32),
        sh=sh,
    )


def model_mb(model) -> float:
    arrays = [model.means, model.quats, model.log_scales, model.opacity_logits, model.sh]
    return sum(a.nbytes for a in arrays) / 2**20


def child(n: int, degree: int, workdir: str) -> dict:
    from gsa.io.ply import read_ply, write_ply

    model = random_model(n, degree)
    size_mb = model_mb(model)
    path = Path(workdir) / f"m{n}_{degree}.ply"
    _, write_s, write_growth = _measured(lambda m=model: write_ply(m, path))
    del model  # the read is measured alone
    baseline = _status_mb("VmRSS")
    loaded, read_s, read_growth = _measured(lambda: read_ply(path))
    assert len(loaded) == n and loaded.sh_degree == degree
    file_mb = path.stat().st_size / 2**20
    path.unlink()
    return {
        "gaussians": n,
        "sh_degree": degree,
        "file_mb": file_mb,
        "model_mb": size_mb,
        "write_seconds": write_s,
        "write_peak_growth_mb": write_growth,
        "read_seconds": read_s,
        "read_peak_growth_mb": read_growth,
        "read_rss_before_mb": baseline,
    }


def parse_size(text: str) -> int:
    text = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(text[-1:], 1)
    return int(float(text.rstrip("km")) * mult)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1M,2M,5M")
    parser.add_argument("--sh", default="0,3", help="SH degrees, comma separated")
    parser.add_argument("--child", nargs=3, metavar=("N", "DEGREE", "DIR"), help=argparse.SUPPRESS)
    parser.add_argument("--json", action="store_true", help="also print the rows as JSON")
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(int(args.child[0]), int(args.child[1]), args.child[2])))
        return 0
    rows = []
    with tempfile.TemporaryDirectory(prefix="gsa-plymem-") as d:
        for n in (parse_size(s) for s in args.sizes.split(",")):
            for degree in (int(x) for x in args.sh.split(",")):
                proc = subprocess.run(
                    [sys.executable, "-m", "benchmarks.ply_memory", "--child", str(n), str(degree), d],
                    capture_output=True,
                    text=True,
                    env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
                )
                if proc.returncode:
                    sys.stderr.write(proc.stderr)
                    return proc.returncode
                rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
                r = rows[-1]
                print(
                    f"{n:>9,} SH{degree}: file {r['file_mb']:7.0f} MB, model {r['model_mb']:7.0f} MB | "
                    f"write {r['write_seconds']:6.2f} s, +{r['write_peak_growth_mb']:6.0f} MB | "
                    f"read {r['read_seconds']:6.2f} s, +{r['read_peak_growth_mb']:6.0f} MB "
                    f"({r['read_peak_growth_mb'] / r['model_mb']:.2f}x the model)",
                    flush=True,
                )
    print(f"load average: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    if args.json:
        print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
