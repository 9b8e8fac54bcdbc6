"""Feature-guided ICP with a closed-form Sim(3) step (paper Sec. 3.3, Alg. 3).

For every source Gaussian the candidates are the target Gaussians whose feature
lies within τ_f; the spatially closest candidate is its match; the hybrid
closed form (Kabsch–Umeyama R, t + Horn's symmetric s) is solved; repeat.

Unlike the authors' dense N×M matrices, candidates come from a KD-tree over
the 3-D features, found once (features do not move) and kept as a fixed
(N, K) table; each iteration is then a gather and an argmin over K, so memory
is O(N·K) and 200k-vs-200k models fit in well under 2 GB.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from gsa.align.nearest import nearest_candidate, query_workers
from gsa.errors import GSAError
from gsa.geometry import rotation_angle
from gsa.sim3 import DegenerateCorrespondencesError, Sim3, solve_sim3

Progress = Callable[[str, float], None]


class AlignmentError(GSAError, ValueError):
    """The inputs cannot be aligned (no feature-compatible correspondences, ...)."""


@dataclass
class CoarseOptions:
    tau_f: float = 0.01  # feature-distance threshold (paper default)
    max_iterations: int = 30  # stops earlier once the matches stop changing
    max_candidates: int = 32  # K: the most feature-similar candidates kept per source
    trim: float | None = 3.0  # drop matches beyond trim × median residual (None: keep all)
    # Convergence: the update is below these (radians; relative scale), or the matches repeat.
    rotation_tolerance: float = 2e-5
    scale_tolerance: float = 2e-6
    workers: int = -1  # KD-tree query threads for large queries (-1: all cores)


@dataclass
class CandidateTable:
    """Feature-compatible target indices per source row, padded with -1."""

    source_index: np.ndarray  # (S,) source Gaussians with at least one candidate
    target_index: np.ndarray  # (S, K) int64, -1 = no candidate
    truncated: int  # sources that had more than K candidates within τ_f

    @property
    def pair_count(self) -> int:
        return int((self.target_index >= 0).sum())


@dataclass(frozen=True)
class CoarseResult:
    transform: Sim3
    iterations: int
    converged: bool
    history: list[dict] = field(default_factory=list)
    matched: int = 0
    candidates: int = 0
    seconds: float = 0.0


def find_candidates(
    source_features: np.ndarray,
    target_features: np.ndarray,
    tau_f: float,
    max_candidates: int,
    target_tree: cKDTree | None = None,
    workers: int = -1,
) -> CandidateTable:
    """Up to K target candidates per source with ‖f_s − f_t‖ ≤ τ_f, most similar first."""
    if source_features.shape[1] != target_features.shape[1]:
        raise AlignmentError(
            f"feature dimensions differ: source {source_features.shape[1]}, target {target_features.shape[1]}"
        )
    tree = target_tree if target_tree is not None else cKDTree(np.asarray(target_features, np.float64))
    k = int(min(max_candidates + 1, len(target_features)))
    dist, idx = tree.query(
        np.asarray(source_features, np.float64),
        k=k,
        distance_upper_bound=tau_f,
        workers=query_workers(len(source_features), workers),
    )
    dist = dist.reshape(len(source_features), k)
    idx = idx.reshape(len(source_features), k)
    found = np.isfinite(dist)
    truncated = int(found[:, -1].sum()) if k > max_candidates else 0
    if k > max_candidates:
        found, idx = found[:, :max_candidates], idx[:, :max_candidates]
    has_any = found.any(axis=1)
    table = np.where(found, idx, -1)[has_any]
    return CandidateTable(np.flatnonzero(has_any), table.astype(np.int64), truncated)


def _icp(
    p: np.ndarray,
    q: np.ndarray,
    match: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    init: Sim3,
    opts: CoarseOptions,
    weights: np.ndarray | None,
    progress: Progress | None,
    stage: str,
) -> CoarseResult:
    """Alternate matching and the closed-form step until the matches repeat or
    the update is negligible. `match(x)` gives (residual, target index) per row.

    Each step solves for the whole transform from the original source points,
    not an increment, so no error accumulates across iterations.
    """
    t0 = time.perf_counter()
    transform = init
    history: list[dict] = []
    previous = None
    converged = False
    iteration = 0
    matched_count = 0
    for iteration in range(1, opts.max_iterations + 1):
        residual, matched = match(transform.apply(p))
        keep = np.ones(len(p), bool)
        if opts.trim is not None:
            median = np.median(residual)
            if median > 0:
                keep = residual <= opts.trim * median
        matched_count = int(keep.sum())
        try:
            new = solve_sim3(p[keep], q[matched[keep]], None if weights is None else weights[keep])
        except DegenerateCorrespondencesError as exc:
            raise AlignmentError(f"{stage} iteration {iteration}: {exc}") from None
        delta = new @ transform.inverse()
        angle = rotation_angle(delta.rotation)
        history.append(
            {
                "stage": stage,
                "iteration": iteration,
                "matched": matched_count,
                "rms_residual": float(np.sqrt(np.mean(residual[keep] ** 2))),
                "delta_rotation_deg": float(np.degrees(angle)),
                "scale": new.scale,
            }
        )
        transform = new
        if progress is not None:
            progress("coarse", iteration / opts.max_iterations)
        same_matches = previous is not None and np.array_equal(previous, matched)
        small = angle < opts.rotation_tolerance and abs(np.log(delta.scale)) < opts.scale_tolerance
        previous = matched
        if same_matches or small:
            converged = True
            break
    return CoarseResult(
        transform=transform,
        iterations=iteration,
        converged=converged,
        history=history,
        matched=matched_count,
        seconds=time.perf_counter() - t0,
    )


def coarse_align(
    source_points: np.ndarray,
    target_points: np.ndarray,
    candidates: CandidateTable,
    init: Sim3,
    options: CoarseOptions | None = None,
    weights: np.ndarray | None = None,
    progress: Progress | None = None,
) -> CoarseResult:
    """Alg. 3 from `init`: each source's match is its spatially closest
    feature-compatible candidate. Points are (N, 3) / (M, 3)."""
    opts = options or CoarseOptions()
    if len(candidates.source_index) < 3:
        raise AlignmentError(
            f"only {len(candidates.source_index)} source Gaussians have a target Gaussian within "
            f"feature distance τ_f={opts.tau_f}; the models' features do not agree (raise τ_f?)"
        )
    p = np.asarray(source_points, np.float64)[candidates.source_index]
    w = None if weights is None else np.asarray(weights, np.float64)[candidates.source_index]
    table = candidates.target_index
    q_all = np.ascontiguousarray(target_points, np.float64)

    def match(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return nearest_candidate(np.ascontiguousarray(x), q_all, table)

    result = _icp(p, q_all, match, init, opts, w, progress, "features")
    return replace(result, candidates=candidates.pair_count)


def icp_refine(
    source_points: np.ndarray,
    target_points: np.ndarray,
    target_tree: cKDTree,
    init: Sim3,
    options: CoarseOptions | None = None,
    weights: np.ndarray | None = None,
    progress: Progress | None = None,
    neighbours: int = 8,
) -> CoarseResult:
    """Plain trimmed nearest-neighbour ICP with the same closed-form step.

    Used after the feature-guided stage when the features are the weight-free
    canonical ones: those come from each model's own frame estimate, so two
    independent samplings disagree on them by the frames' estimation error
    (continuous when two principal extents are close). Feature-gated matches
    would freeze that error in; once the feature stage has removed the gross
    misalignment, free nearest neighbours converge to the geometric optimum.
    """
    opts = options or CoarseOptions()
    p = np.asarray(source_points, np.float64)
    q = np.ascontiguousarray(target_points, np.float64)
    # KD-tree queries dominate plain ICP. Near convergence the nearest neighbour
    # is almost always among the previous k nearest, so query k at a time and
    # iterate on that cached table (a cheap compiled scan), re-querying only
    # until a fresh table no longer changes the answer.
    result: CoarseResult | None = None
    transform = init
    history: list[dict] = []
    budget = opts.max_iterations
    while budget > 0:
        _, table = target_tree.query(
            transform.apply(p), k=min(neighbours, len(q)), workers=query_workers(len(p), opts.workers)
        )
        table = np.ascontiguousarray(table.reshape(len(p), -1), np.int64)

        def match(x: np.ndarray, table: np.ndarray = table) -> tuple[np.ndarray, np.ndarray]:
            return nearest_candidate(np.ascontiguousarray(x), q, table)

        inner = replace(opts, max_iterations=budget)
        result = _icp(p, q, match, transform, inner, weights, progress, "refine")
        history += result.history
        budget -= result.iterations
        transform = result.transform
        if result.iterations <= 2:
            break
    assert result is not None
    return replace(result, history=history, iterations=len(history))
