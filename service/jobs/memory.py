"""A job's predicted peak memory, from its options and its inputs' sizes (issue 28).

The fine stage's options bound its compute (`GSA_MAX_FINE_WORK`), not its memory: the
renders of every view are kept for the backward pass, so `fine_views: 64, fine_image_size:
1024, fine_iterations: 1` (3 % of the work budget) drove a worker to 5.7 GB. The service
therefore predicts a job's peak before it accepts it, and refuses (422, with the number) a job
predicted above the workers' budget (`GSA_WORKER_MEMORY_MB`).

The model is an upper bound fitted to peaks measured in a fresh child process that reads both
models, runs `align()` and writes the outputs, as a worker does (`scripts/measure_job_memory.py`;
docs/service.md, "Worker memory budget"):

    peak = MARGIN × ( BASE
                      + (PER_GAUSSIAN_FIXED + INPUT_COPIES × b) × min(n, SATURATION)
                      + INPUT_COPIES × b × max(0, n − SATURATION)
                      + fine: views × n × PER_VIEW_GAUSSIAN + views × size² × PER_PIXEL )

n: the source's plus the target's Gaussians (a multi-source job runs its sources one after
another: the largest counts); b: bytes one Gaussian takes in memory, from the file's bytes per
Gaussian (a PLY holds what memory does: 56–248 B), at least SH 0's and at most SH 3's.
`tests/service/test_job_memory.py` runs small jobs in child processes and checks the
prediction is above each measured peak.
"""

from __future__ import annotations

from typing import Any

MB = 1 << 20

BASE = 480 * MB  # interpreter, numpy, numba kernels, torch and the renderer (a cold process)
PER_GAUSSIAN_FIXED = 500  # search structures that stop growing once the subsamples are full
SATURATION = 400_000  # ... at about this many Gaussians (both models together)
INPUT_COPIES = 2.2  # both inputs, the moved source, the merged model while written
MIN_GAUSSIAN_BYTES, MAX_GAUSSIAN_BYTES = 56, 248  # SH 0 .. SH 3 (+ normals), in memory
PER_VIEW_GAUSSIAN = 130  # fine stage: projections of every Gaussian in every view
PER_PIXEL = 105  # fine stage: images, alphas and the compositing's saved state per pixel
PER_PIXEL_TRAINING = 130  # ... once more than one iteration has run (allocator growth)
MARGIN = 1.15

FINE_DEFAULTS = {"fine_views": 5, "fine_image_size": 128, "fine_iterations": 60}


def fine_may_run(options: dict[str, Any]) -> bool:
    """Whether the fine stage can run for these options: `coarse,fine`, or `auto` unless the
    nearest-neighbour refinement replaces it (refine on, or auto with canonical features)."""
    stages = tuple(options.get("stages") or ("auto",))
    if stages == ("coarse", "fine"):
        return True
    if stages != ("auto",):
        return False
    refine = options.get("refine", "auto")
    return not (refine == "on" or (refine == "auto" and options.get("features", "auto") == "canonical"))


def gaussian_bytes(n_gaussians: int | None, file_bytes: int | None) -> float:
    """Bytes one Gaussian of this model takes in memory (from its file's bytes per Gaussian)."""
    if not n_gaussians or not file_bytes:
        return MAX_GAUSSIAN_BYTES
    return min(max(file_bytes / n_gaussians, MIN_GAUSSIAN_BYTES), MAX_GAUSSIAN_BYTES)


def predict_job_memory(
    options: dict[str, Any],
    source_gaussians: list[int],
    target_gaussians: int,
    source_bytes: list[float] | None = None,
    target_bytes: float = MAX_GAUSSIAN_BYTES,
) -> int:
    """Predicted peak bytes of a job with these options and inputs (Gaussian counts, and the
    bytes a Gaussian of each input takes in memory; SH 3's when not given)."""
    source_bytes = source_bytes or [MAX_GAUSSIAN_BYTES] * len(source_gaussians)
    fine = fine_may_run(options)
    v = {k: int(options.get(k, d)) for k, d in FINE_DEFAULTS.items()}
    worst = 0.0
    for n_s, b_s in zip(source_gaussians or [0], source_bytes or [MAX_GAUSSIAN_BYTES], strict=False):
        n = n_s + target_gaussians
        b = (n_s * b_s + target_gaussians * target_bytes) / max(n, 1)
        peak = BASE + (PER_GAUSSIAN_FIXED + INPUT_COPIES * b) * min(n, SATURATION)
        peak += INPUT_COPIES * b * max(0, n - SATURATION)
        if fine:
            per_pixel = PER_PIXEL_TRAINING if v["fine_iterations"] > 1 else PER_PIXEL
            peak += v["fine_views"] * n * PER_VIEW_GAUSSIAN
            peak += v["fine_views"] * v["fine_image_size"] ** 2 * per_pixel
        worst = max(worst, peak)
    return int(MARGIN * worst)


def predict_for_assets(options: dict[str, Any], sources: list, target) -> int:
    """predict_job_memory for service assets (`n_gaussians`, `size`). An image set counts as
    no Gaussians here: its reconstruction's memory is not modelled."""

    def count(a) -> int:
        return int(a.n_gaussians or 0) if a.kind != "images" else 0

    return predict_job_memory(
        options,
        [count(a) for a in sources],
        count(target),
        [gaussian_bytes(a.n_gaussians, a.size) for a in sources],
        gaussian_bytes(target.n_gaussians, target.size),
    )
