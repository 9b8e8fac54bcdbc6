"""`align()`: features -> coarse (with frame hypotheses) -> fine, one call.

The CLI, the service worker, the benchmarks and the tests all call this.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from gsa.align.canonical import CanonicalFrame, canonical_features, frame_hypotheses, model_frame
from gsa.align.coarse import (
    AlignmentError,
    CoarseOptions,
    CoarseResult,
    coarse_align,
    find_candidates,
    icp_refine,
    query_workers,
)
from gsa.model import GaussianModel, ModelError
from gsa.sim3 import Sim3

Progress = Callable[[str, float], None]
FEATURE_MODES = ("auto", "file", "canonical")
STAGES = ("coarse", "fine")


@dataclass
class AlignOptions:
    stages: tuple[str, ...] = ("coarse",)
    features: str = "auto"  # auto: the files' own features when both have them, else canonical
    tau_f: float = 0.01
    coarse_iterations: int = 30
    max_candidates: int = 32
    weight_by_opacity: bool = False
    trim: float | None = 3.0
    # Nearest-neighbour ICP after the feature-guided stage; "auto": only with the
    # weight-free canonical features (see gsa.align.coarse.icp_refine).
    refine: str = "auto"
    # Ambiguous canonical frames: each hypothesis is tried on a source subsample.
    hypothesis_points: int = 2000
    hypothesis_iterations: int = 8
    refine_points: int = 20_000  # source Gaussians sampled for the refinement ICP
    refine_iterations: int = 100  # cheap: cached neighbour tables, see icp_refine
    # The feature stage and the quality metrics use at most this many source
    # Gaussians (the authors subsample to 30k-50k); the target is always used whole.
    max_points: int = 30_000
    inlier_threshold: float = 0.03  # GT-free inlier distance, as a fraction of the target's RMS radius
    seed: int = 0
    fine_iterations: int = 60
    fine_views: int = 5
    fine_lr: float = 0.01
    fine_image_size: int = 128
    fine_loss: str = "smooth_l1"
    fine_on: str = "features"  # or "colors" (paper Table 4 ablation)

    def __post_init__(self) -> None:
        self.stages = tuple(self.stages)
        unknown = [s for s in self.stages if s not in STAGES]
        if not self.stages or unknown or self.stages[0] != "coarse":
            raise ValueError(f"stages must be 'coarse' or 'coarse,fine', got {','.join(self.stages)}")
        if self.features not in FEATURE_MODES:
            raise ValueError(f"features must be one of {', '.join(FEATURE_MODES)}, got {self.features!r}")
        if not self.tau_f > 0:
            raise ValueError("tau_f must be positive")
        if self.refine not in ("auto", "on", "off"):
            raise ValueError(f"refine must be auto, on or off, got {self.refine!r}")
        if self.coarse_iterations < 1 or self.max_candidates < 1:
            raise ValueError("coarse_iterations and max_candidates must be at least 1")

    def coarse_options(self, iterations: int | None = None) -> CoarseOptions:
        return CoarseOptions(
            tau_f=self.tau_f,
            max_iterations=iterations or self.coarse_iterations,
            max_candidates=self.max_candidates,
            weight_by_opacity=self.weight_by_opacity,
            trim=self.trim,
        )


@dataclass
class AlignmentResult:
    transform: Sim3  # maps source coordinates into the target frame
    coarse: CoarseResult
    features: str  # which features guided the alignment
    metrics: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    hypotheses: list[dict] = field(default_factory=list)
    fine: object | None = None  # gsa.align.fine.FineResult when the fine stage ran
    source_frame: CanonicalFrame | None = None
    target_frame: CanonicalFrame | None = None

    def to_dict(self) -> dict:
        out = self.transform.to_dict()
        stages = {
            "coarse": {
                **self.coarse.transform.to_dict(),
                "iterations": self.coarse.iterations,
                "converged": self.coarse.converged,
                "matched": self.coarse.matched,
                "candidate_pairs": self.coarse.candidates,
                "history": self.coarse.history,
            }
        }
        if self.fine is not None:
            fine = self.fine
            stages["fine"] = {
                **fine.transform.to_dict(),
                "loss_history": [float(v) for v in fine.loss_history],
                "best_loss": float(fine.best_loss),
                "best_iteration": int(fine.best_iteration),
            }
        out.update(
            metrics=self.metrics,
            timings=self.timings,
            features=self.features,
            hypotheses=self.hypotheses,
            stages=stages,
        )
        return out


def _initial_transform(src: CanonicalFrame, dst: CanonicalFrame) -> Sim3:
    """Maps the source's canonical pose onto the target's."""
    return dst.to_canonical().inverse() @ src.to_canonical()


def _centroid_init(src: CanonicalFrame, dst: CanonicalFrame) -> Sim3:
    """The authors' start (centroids matched), plus the RMS-radius scale ratio."""
    s = dst.radius / src.radius
    return Sim3(s, np.eye(3), dst.center - s * src.center)


def _report(progress: Progress | None, stage: str, fraction: float) -> None:
    if progress is not None:
        progress(stage, float(min(max(fraction, 0.0), 1.0)))


def align(
    source: GaussianModel,
    target: GaussianModel,
    options: AlignOptions | None = None,
    progress: Progress | None = None,
) -> AlignmentResult:
    """Find the Sim(3) T with target ≈ T(source). `progress(stage, fraction)` is
    called as work advances; an exception raised in it aborts the alignment."""
    opts = options or AlignOptions()
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    try:
        source.validate("source")
        target.validate("target")
    except ModelError as exc:
        raise AlignmentError(str(exc)) from None
    for name, m in (("source", source), ("target", target)):
        if len(m) < 3:
            raise AlignmentError(f"{name} has {len(m)} Gaussians; at least 3 are needed")

    mode = opts.features
    if mode == "auto":
        both = source.feature_dim > 0 and source.feature_dim == target.feature_dim
        mode = "file" if both else "canonical"
    if mode == "file" and (source.feature_dim == 0 or source.feature_dim != target.feature_dim):
        raise AlignmentError(
            f"features='file' needs both models to carry features of one dimension "
            f"(source {source.feature_dim}, target {target.feature_dim})"
        )

    _report(progress, "features", 0.0)
    t = time.perf_counter()
    src_frame = model_frame(source)
    dst_frame = model_frame(target)
    src_pts = source.means.astype(np.float64)
    dst_pts = target.means.astype(np.float64)
    src_tree = cKDTree(src_pts)
    dst_tree = cKDTree(dst_pts)
    weights = source.opacities if opts.weight_by_opacity else None
    threshold = opts.inlier_threshold * dst_frame.radius
    rng = np.random.default_rng(opts.seed)

    def source_features(frame: CanonicalFrame, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        if mode == "file":
            return source.features[rows]
        return canonical_features(src_pts[rows], frame)

    def rows_of(weights_or_none, rows):
        return None if weights_or_none is None else weights_or_none[rows]

    # Each hypothesis: a source frame (re-labelled axes) and the initial transform it implies.
    hypotheses: list[_Hypothesis] = []
    if mode == "file":
        dst_feat = target.features
        hypotheses.append(_Hypothesis("centroid", src_frame, _centroid_init(src_frame, dst_frame)))
    else:
        dst_feat = canonical_features(dst_pts, dst_frame)
    for g in frame_hypotheses(src_frame, dst_frame):
        frame = src_frame.rotated(g)
        hypotheses.append(_Hypothesis(_label(g), frame, _initial_transform(frame, dst_frame)))
    dst_feat_tree = cKDTree(np.asarray(dst_feat, np.float64))
    refine = opts.refine == "on" or (opts.refine == "auto" and mode == "canonical")
    timings["features"] = time.perf_counter() - t
    _report(progress, "features", 1.0)

    t = time.perf_counter()
    scored: list[dict] = []
    best = hypotheses[0]
    if len(hypotheses) > 1:
        sub = _subsample(rng, len(source), opts.hypothesis_points)
        rev_sub = _subsample(rng, len(target), opts.hypothesis_points)
        short = opts.coarse_options(opts.hypothesis_iterations)
        best_score = -1.0
        for h, hyp in enumerate(hypotheses):
            entry = {"hypothesis": hyp.label, "score": 0.0}
            try:
                cand = find_candidates(
                    source_features(hyp.frame, sub), dst_feat, opts.tau_f, opts.max_candidates, dst_feat_tree
                )
                res = coarse_align(src_pts[sub], dst_pts, cand, hyp.init, short, rows_of(weights, sub))
                if refine:
                    res = icp_refine(src_pts[sub], dst_pts, dst_tree, res.transform, short, rows_of(weights, sub))
                fwd_d, _ = dst_tree.query(res.transform.apply(src_pts[sub]), k=1, workers=query_workers(len(sub)))
                fwd = float(np.mean(fwd_d <= threshold))
                rev = _reverse_inliers(res.transform, dst_pts[rev_sub], src_tree, threshold)
                entry.update(score=0.5 * (fwd + rev), inliers_forward=fwd, inliers_reverse=rev)
                hyp.init = res.transform
            except AlignmentError as exc:
                entry["error"] = str(exc)
            scored.append(entry)
            if entry["score"] > best_score:
                best, best_score = hyp, entry["score"]
                for e in scored:
                    e.pop("chosen", None)
                entry["chosen"] = True
            _report(progress, "hypotheses", (h + 1) / len(hypotheses))
    timings["hypotheses"] = time.perf_counter() - t

    t = time.perf_counter()
    stage_rows = _subsample(rng, len(source), opts.max_points)
    src_feat = source_features(best.frame, stage_rows)
    cand = find_candidates(src_feat, dst_feat, opts.tau_f, opts.max_candidates, dst_feat_tree)
    feature_stage = opts.coarse_options()
    if refine:
        # With canonical features the feature stage is the global initialiser: its
        # fixed point carries the two frames' estimation error, so converging it
        # tightly is wasted work; the refinement below removes what is left.
        feature_stage.rotation_tolerance = max(feature_stage.rotation_tolerance, 1e-3)
        feature_stage.scale_tolerance = max(feature_stage.scale_tolerance, 1e-4)
    coarse = coarse_align(
        src_pts[stage_rows], dst_pts, cand, best.init, feature_stage, rows_of(weights, stage_rows), progress
    )
    if refine:
        # A dense target with a sampled source is as accurate as all-to-all
        # nearest neighbours and several times cheaper.
        rows = _subsample(rng, len(source), opts.refine_points)
        refined = icp_refine(
            src_pts[rows], dst_pts, dst_tree, coarse.transform, opts.coarse_options(opts.refine_iterations),
            rows_of(weights, rows), progress,
        )
        coarse.transform = refined.transform
        coarse.history += refined.history
        coarse.iterations += refined.iterations
        coarse.converged = refined.converged
        coarse.seconds += refined.seconds
    timings["coarse"] = time.perf_counter() - t
    label = best.label

    transform = coarse.transform
    fine_result = None
    if "fine" in opts.stages:
        t = time.perf_counter()
        from gsa.align.fine import FineOptions, fine_align

        src_model, dst_model = source, target
        if mode == "canonical":
            src_model = source.with_features(src_feat)
            dst_model = target.with_features(dst_feat)
        fine_result = fine_align(
            src_model,
            dst_model,
            transform,
            FineOptions(
                iterations=opts.fine_iterations,
                lr=opts.fine_lr,
                views=opts.fine_views,
                image_size=opts.fine_image_size,
                loss=opts.fine_loss,
                on=opts.fine_on,
                seed=opts.seed,
            ),
            progress=progress,
        )
        transform = fine_result.transform
        timings["fine"] = time.perf_counter() - t

    t = time.perf_counter()
    metrics = quality_metrics(
        transform, src_pts[stage_rows], dst_pts, src_feat, dst_feat, threshold, src_tree, dst_tree,
        _subsample(rng, len(target), opts.max_points),
    )
    metrics["inlier_threshold"] = threshold
    metrics["hypothesis"] = label
    timings["metrics"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    _report(progress, "done", 1.0)
    return AlignmentResult(
        transform=transform,
        coarse=coarse,
        features=mode,
        metrics=metrics,
        timings=timings,
        hypotheses=scored,
        fine=fine_result,
        source_frame=best.frame,
        target_frame=dst_frame,
    )


@dataclass
class _Hypothesis:
    label: str
    frame: CanonicalFrame
    init: Sim3


def _subsample(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    return np.arange(n) if k >= n else np.sort(rng.choice(n, k, replace=False))


def _label(g: np.ndarray) -> str:
    axes = "xyz"
    return "".join(("-" if g[i, j] < 0 else "+") + axes[j] for i in range(3) for j in range(3) if g[i, j] != 0)


def _reverse_inliers(transform: Sim3, target_points: np.ndarray, source_tree: cKDTree, threshold: float) -> float:
    d, _ = source_tree.query(
        transform.inverse().apply(target_points), k=1, workers=query_workers(len(target_points))
    )
    return float(np.mean(d * transform.scale <= threshold))


def quality_metrics(
    transform: Sim3,
    src_pts: np.ndarray,
    dst_pts: np.ndarray,
    src_feat: np.ndarray,
    dst_feat: np.ndarray,
    threshold: float,
    src_tree: cKDTree,
    dst_tree: cKDTree,
    reverse_rows: np.ndarray | slice = slice(None),
) -> dict:
    """Ground-truth-free numbers a caller can judge a result by: the fractions of
    source (forward) and target (reverse) Gaussians with a partner within the
    inlier threshold, the RMS distance of forward inliers, and how well the
    features of spatial nearest neighbours agree."""
    fwd_d, fwd_i = dst_tree.query(transform.apply(src_pts), k=1, workers=query_workers(len(src_pts)))
    reverse = _reverse_inliers(transform, dst_pts[reverse_rows], src_tree, threshold)
    inlier = fwd_d <= threshold
    forward = float(inlier.mean())
    feat_d = np.linalg.norm(np.asarray(src_feat, np.float64) - np.asarray(dst_feat, np.float64)[fwd_i], axis=1)
    return {
        "inlier_fraction": 0.5 * (forward + reverse),
        "inlier_fraction_forward": forward,
        "inlier_fraction_reverse": reverse,
        "rms_residual": float(np.sqrt(np.mean(fwd_d[inlier] ** 2))) if inlier.any() else float("inf"),
        "feature_distance_median": float(np.median(feat_d)),
        "feature_agreement": float(np.mean(feat_d <= 0.05)),
    }
