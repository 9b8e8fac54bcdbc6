"""Coarse-alignment wall time, in process, for 50k, 100k and 200k Gaussians per model
(two independent samplings of a generated car with 2 % floaters, random Sim(3));
5 runs each after a warm-up, and Open3D FPFH + RANSAC + ICP on the same pair in the
same run when the `peers` extra is installed (the ratio is what compares across machines).

    python -m benchmarks.coarse_speed [SIZES...]
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from benchmarks.peers import available_peers
from gsa.align.pipeline import align
from gsa.metrics import accuracy
from gsa.synth import make_object, random_sim3


def main(sizes: list[int]) -> None:
    rng = np.random.default_rng(3)
    open3d = available_peers(["open3d"])
    for n in sizes:
        src = make_object("car", seed=1, n_gaussians=n, sample_seed=5, floaters=0.02)
        truth = random_sim3(rng)
        tgt = make_object("car", seed=1, n_gaussians=n).transformed(truth)
        align(src.subset(np.arange(3000)), tgt.subset(np.arange(3000)))  # compile / load kernels
        walls = []
        for _ in range(5):
            t = time.perf_counter()
            result = align(src, tgt)
            walls.append(time.perf_counter() - t)
        rre = accuracy(result.transform, truth, src.means, tgt.means)["rre_deg"]
        line = (
            f"{n:,} vs {n:,}: align() wall min {min(walls):.2f} s, median {np.median(walls):.2f} s, "
            f"RRE {rre:.4f}°, confidence {result.metrics['confidence']:.2f}"
        )
        if open3d:
            peer_walls = []
            for _ in range(3):
                t = time.perf_counter()
                est = open3d[0].register(src, tgt, seed=0)
                peer_walls.append(time.perf_counter() - t)
            peer_rre = accuracy(est, truth, src.means, tgt.means)["rre_deg"]
            line += (
                f"; Open3D median {np.median(peer_walls):.2f} s (RRE {peer_rre:.2f}°), "
                f"ratio GSA/Open3D {np.median(walls) / np.median(peer_walls):.2f}"
            )
        print(line + f"; load {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [50_000, 100_000, 200_000])
