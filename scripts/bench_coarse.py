"""Coarse-alignment wall time for 100k and 200k Gaussians per model (two independent
samplings of a generated car, random Sim(3)); 5 runs each after a warm-up.

    python scripts/bench_coarse.py
"""
import time, numpy as np, os
from gsa.synth import make_object, random_sim3
from gsa.align.pipeline import align
from gsa.metrics import accuracy
rng = np.random.default_rng(3)
for N in (100_000, 200_000):
    src = make_object("car", seed=1, n_gaussians=N, sample_seed=5, floaters=0.02)
    gt = random_sim3(rng)
    tgt = make_object("car", seed=1, n_gaussians=N).transformed(gt)
    align(src.subset(np.arange(2000)), tgt.subset(np.arange(2000)))
    walls=[]; cpus=[]; coarse=[]
    for rep in range(5):
        t=time.perf_counter(); c=time.process_time(); r=align(src,tgt); walls.append(time.perf_counter()-t); cpus.append(time.process_time()-c)
        coarse.append(sum(r.timings[k] for k in ("features","hypotheses","coarse")))
    print(N, f"align wall min {min(walls):.2f} median {np.median(walls):.2f}; coarse stages wall min {min(coarse):.2f} median {np.median(coarse):.2f}; cpu min {min(cpus):.2f}; load {os.getloadavg()[0]:.1f}; rre {accuracy(r.transform, gt, src.means, tgt.means)['rre_deg']:.4f}", flush=True)
