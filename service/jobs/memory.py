"""A job's predicted peak memory, from its options and its inputs' sizes.

The fine stage's options bound its compute (`GSA_MAX_FINE_WORK`), not its memory: the
renders of every view are kept for the backward pass, so `fine_views: 64, fine_image_size:
1024, fine_iterations: 1` (3 % of the work budget) drove a worker to 5.7 GB. The service
therefore predicts a job's peak before it accepts it, and refuses (422, with the number) a job
predicted above the workers' budget (`GSA_WORKER_MEMORY_MB`).

The model is an upper bound fitted to peaks measured in a fresh child process that reads both
models, runs `align()` and writes the outputs, as a worker does (`benchmarks/service/measure_job_memory.py`;
docs/service.md, "Worker memory budget"):

    peak = MARGIN × ( BASE
                      + (PER_GAUSSIAN_FIXED + INPUT_COPIES × b) × min(n, SATURATION)
                      + INPUT_COPIES × b × max(0, n − SATURATION)
                      + fine: views × n × PER_VIEW_GAUSSIAN + views × size² × PER_PIXEL
                      + the largest of
                        fine: views × n × PER_VIEW_GAUSSIAN + views × size² × PER_PIXEL,
                        semantic: SEMANTIC_BASE + lift(max(n_s, n_t)) + LIFTED × min(n_s, n_t),
                        renders: RENDER_VIEW_GAUSSIAN × the views × Gaussians of one call )

The semantic tie-break (gsa.align.semantic: orbit views of both models, the DINOv2 backbone
over them, its features lifted back onto every Gaussian) runs on a doubtful answer of the
search, which cannot be known at submission: it is counted unless it cannot run (`semantic:
off`, the deployment's GSA_SEMANTIC=off, or the fine stage, which replaces it: one or the
other, never both, so the larger of the two counts). Its peak is the lifting of the larger
model: per Gaussian its float64 sums (LIFTED), and per renderer pass the channels of every
Gaussian in every view of the pass (LIFT_VALUE) and their projections (LIFT_VIEW_GAUSSIAN),
passes sized as semantic.py sizes them; while the other model's sums are held. Before its
renders were depth-only and a few views a call, and its lifting in bounded passes, the stage
took 11.7 GB at 3M Gaussians (docs/service.md). The `renders` output draws 3 views (and the
fine stage's) of each model, a few views a renderer call (gsa.render.views), after the alignment.

n: the source's plus the target's Gaussians (a multi-source job runs its sources one after
another: the largest counts); b: bytes one Gaussian takes in memory, from the file's bytes per
Gaussian (a PLY holds what memory does: 56–248 B), at least SH 0's and at most SH 3's.
`tests/service/test_job_memory.py` runs small jobs in child processes and checks the
prediction is above each measured peak.
"""

from __future__ import annotations

from typing import Any

from service.jobs.options import library_defaults

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

FINE_OPTIONS = ("fine_views", "fine_image_size", "fine_iterations")  # defaults: the library's

# The semantic stage (fitted to benchmarks/service/bench_job_memory.py's peaks at 50k, 300k and 3M).
SEMANTIC_BASE = 200 * MB  # the backbone (and its ONNX file while read), views, tokens, the upsampled maps
LIFTED = 33 * 8  # a Gaussian's float64 sums of the 32 lifted channels and its visibility
LIFT_VALUE = 16  # a channel of a Gaussian in a view of a pass: rendered, its gradient, the probe's
LIFT_VIEW_GAUSSIAN = 150  # a Gaussian's projection in a view of a pass, kept for the backward
# As gsa.align.semantic sizes the lifting's passes (LIFT_VIEW_GAUSSIANS_PER_CALL, LIFT_VALUES_PER_PASS).
LIFT_VIEWS_BUDGET, LIFT_VALUES_BUDGET, LIFT_CHANNELS = 300_000, 40_000_000, 33
# The `renders` output: a Gaussian in a view of a renderer call (projection, SH colour, ...), calls
# of at most RENDER_CALL_BUDGET views x Gaussians (gsa.render.views.VIEW_GAUSSIANS_PER_CALL).
RENDER_VIEW_GAUSSIAN = 200
RENDER_CALL_BUDGET, RENDER_NOVEL_VIEWS = 1_200_000, 3


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


GUIDANCE = ("init_transform", "point_pairs", "up_axes", "front_axes", "fixed_scale")


def semantic_may_run(options: dict[str, Any]) -> bool:
    """Whether the semantic tie-break can run: not turned off, no fine stage (a fine result is
    never tie-broken), not the scene path (`scene: on`), no guidance (a guided answer is snapped,
    not tie-broken)."""
    if options.get("semantic", "auto") == "off" or options.get("scene") == "on":
        return False
    if any(options.get(k) is not None for k in GUIDANCE):
        return False
    return tuple(options.get("stages") or ("auto",)) != ("coarse", "fine")


def semantic_memory(n_source: int, n_target: int) -> float:
    """The semantic stage's bytes above the rest of the job (see the module docstring)."""
    big, small = max(n_source, n_target), min(n_source, n_target)
    views = max(1, min(4, LIFT_VIEWS_BUDGET // max(big, 1)))
    channels = min(LIFT_CHANNELS, max(1, LIFT_VALUES_BUDGET // (views * max(big, 1))))
    lift = LIFTED * big + LIFT_VALUE * views * big * channels + LIFT_VIEW_GAUSSIAN * views * big
    return SEMANTIC_BASE + lift + LIFTED * small


def renders_memory(options: dict[str, Any], n_largest: int, fine: bool) -> float:
    """The `renders` output's bytes above the rest of the job (0 when not asked for)."""
    outputs = options.get("outputs") or ("renders",)  # no outputs named: all of them
    if "renders" not in outputs or options.get("renders", True) is False:
        return 0.0
    views = RENDER_NOVEL_VIEWS + (int(options.get("fine_views", library_defaults()["fine_views"])) if fine else 0)
    per_call = max(1, min(views, RENDER_CALL_BUDGET // max(n_largest, 1)))
    return RENDER_VIEW_GAUSSIAN * per_call * n_largest


def effective_options(options: dict[str, Any], settings) -> dict[str, Any]:
    """The job's options as the worker will run them, where that changes its memory: a
    deployment with GSA_SEMANTIC=off runs no semantic stage."""
    if getattr(settings, "semantic", "auto") == "off":
        return {**options, "semantic": "off"}
    return options


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
    semantic = semantic_may_run(options)
    d = library_defaults()
    v = {k: int(options.get(k, d[k])) for k in FINE_OPTIONS}
    worst = 0.0
    for n_s, b_s in zip(source_gaussians or [0], source_bytes or [MAX_GAUSSIAN_BYTES], strict=False):
        n = n_s + target_gaussians
        b = (n_s * b_s + target_gaussians * target_bytes) / max(n, 1)
        peak = BASE + (PER_GAUSSIAN_FIXED + INPUT_COPIES * b) * min(n, SATURATION)
        peak += INPUT_COPIES * b * max(0, n - SATURATION)
        stage = 0.0  # the fine stage or the semantic one: never both
        if fine:
            per_pixel = PER_PIXEL_TRAINING if v["fine_iterations"] > 1 else PER_PIXEL
            stage = v["fine_views"] * n * PER_VIEW_GAUSSIAN + v["fine_views"] * v["fine_image_size"] ** 2 * per_pixel
        if semantic:
            stage = max(stage, semantic_memory(n_s, target_gaussians))
        stage = max(stage, renders_memory(options, max(n_s, target_gaussians), fine))
        worst = max(worst, peak + stage)
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
