"""The scene path (gsa.align.scene, `align_scene`): anchors, the room search (global
search and translation sweep) or the site search (gsa.align.scene.sites), the
refinement on thinned full-resolution clouds, and the verdict.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from gsa.align import robust
from gsa.align.choices import Progress
from gsa.align.coarse import CoarseResult
from gsa.align.scene.choice import SceneChoice, check_models
from gsa.align.scene.common import scene_anchors, translation_sweep
from gsa.align.scene.sites import _site_polish, _sites, site_search
from gsa.model import GaussianModel
from gsa.sim3 import Sim3


def align_scene(
    source: GaussianModel,
    target: GaussianModel,
    opts,
    choice: SceneChoice,
    progress: Progress | None = None,
):
    """The scene path (module docstring): anchors, global search without frame
    relabellings, trimmed refinement on thinned full-resolution clouds, verdict; by the
    criteria in force (opts.criteria)."""
    from gsa.align.result import AlignmentResult

    k = opts.criteria
    o = k.scene
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    check_models(source, target)
    _report(progress, "features", 0.0)
    t = time.perf_counter()
    count = max(opts.anchor_count, o.scene_anchors)
    src, dst = robust.match_exposure(
        scene_anchors(source, count, opts.seed, o), scene_anchors(target, count, opts.seed, o), k.pose.palette
    )
    timings["anchors"] = time.perf_counter() - t
    _report(progress, "features", 1.0)

    _report(progress, "hypotheses", 0.0)
    t = time.perf_counter()
    sites = _sites(src, dst, o)
    if sites is None:
        search = robust.global_search(
            src,
            dst,
            None,
            k.search_options(opts.search_rotations, opts.seed),
            widen_if=lambda first: robust.verdict(first.best, first, criteria=k.verdict)["doubtful"],
        )
        search = translation_sweep(src, dst, search, opts.seed, o)
    else:
        search = site_search(src, dst, *sites, opts.seed, o, k.search_options(0, opts.seed), k.verdict)
    timings["hypotheses"] = time.perf_counter() - t
    _report(progress, "hypotheses", 1.0)
    scored = [c.to_dict(search.best.transform) | {"chosen": c is search.best} for c in search.candidates]

    t = time.perf_counter()
    rng = np.random.default_rng(opts.seed)
    p_idx, q_idx = (_thinned(a.kept, o.refine_cloud, rng) for a in (src, dst))
    p_cloud, q_cloud = source.means[p_idx].astype(np.float64), target.means[q_idx].astype(np.float64)
    p_tree, q_tree = cKDTree(p_cloud), cKDTree(q_cloud)
    half = opts.refine_points // 2
    p = p_cloud[robust.subsample(rng, len(p_cloud), half)]
    q_rows = robust.subsample(rng, len(q_cloud), half)
    q = q_cloud[q_rows]
    normals, flatness = target.surface_normals(q_idx)
    start = search.best if sites is None else _site_polish(src, dst, search, rng)
    transform, history = robust.refine(
        p,
        q,
        p_tree,
        q_tree,
        start.transform,
        opts.refine_iterations,
        target_normals=(normals, flatness, normals[q_rows], flatness[q_rows]),
        criteria=k.refinement(rigid=True),  # two captures of one place are never deformed copies
    )
    refine_kept = True
    if sites is not None:
        # On a site whose Gaussians are far denser in one part (an SfM garden's table) the
        # full-resolution refinement can slide to a pose that the anchors - the whole
        # site, in colour - score clearly lower: the start is kept then.
        refined = robust.score_pose(src, dst, transform, "refined", search.colour_weight, search.criteria)
        if refined.score < start.score - search.criteria.score_tie:
            transform, refine_kept = start.transform, False
    coarse = CoarseResult(
        transform=transform,
        iterations=len(history),
        converged=len(history) < opts.refine_iterations,
        history=history,
        matched=history[-1]["matched"] if history else 0,
        seconds=time.perf_counter() - t,
    )
    timings["coarse"] = time.perf_counter() - t
    _report(progress, "coarse", 1.0)

    t = time.perf_counter()
    metrics = _inliers(transform, p, q, p_tree, q_tree, opts.inlier_threshold * dst.radius)
    final = robust.score_pose(src, dst, transform, "final", search.colour_weight, search.criteria)
    coincide = robust.coincidence(p, q, p_tree, q_tree, transform, criteria=k.refine)
    metrics.update(robust.verdict(final, search, coincide, k.verdict, offer_always=opts.alternatives == "always"))
    metrics["hypothesis"] = search.best.origin
    metrics["scene"] = choice.to_dict() | {
        "kind": "room" if sites is None else "site",
        "refinement_kept": refine_kept,
        "anchors": [len(src), len(dst)],
        "refine_cloud": [len(p_cloud), len(q_cloud)],
        "exposure_gains": list(
            robust.exposure_gain(src, dst)
        ),  # linear RGB gains: the source's colours in the target's exposure
    }
    timings["metrics"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    _report(progress, "done", 1.0)
    return AlignmentResult(
        transform=transform,
        coarse=coarse,
        features="none",
        stages=("coarse",),
        metrics=metrics,
        timings=timings,
        hypotheses=scored,
    )


def _report(progress: Progress | None, stage: str, fraction: float) -> None:
    if progress is not None:
        progress(stage, fraction)


def _thinned(kept: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    """Rows of at most `limit` of the floater-free Gaussians, uniformly at random: a
    fixed-size cloud whatever the capture's size, with the full-resolution positions."""
    idx = np.flatnonzero(kept)
    if len(idx) > limit:
        idx = np.sort(rng.choice(idx, limit, replace=False))
    return idx


def _inliers(transform: Sim3, p, q, p_tree: cKDTree, q_tree: cKDTree, threshold: float) -> dict:
    """GT-free inlier fractions both ways (on the refinement's samples) and the forward
    inliers' RMS residual, in target units."""
    d_f, _ = q_tree.query(transform.apply(p), workers=-1)
    d_r, _ = p_tree.query(transform.inverse().apply(q), workers=-1)
    d_r = d_r * transform.scale
    fwd, rev = d_f <= threshold, d_r <= threshold
    return {
        "inlier_fraction": float(0.5 * (fwd.mean() + rev.mean())),
        "inlier_fraction_forward": float(fwd.mean()),
        "inlier_fraction_reverse": float(rev.mean()),
        "rms_residual": float(np.sqrt(np.mean(d_f[fwd] ** 2))) if fwd.any() else float("inf"),
        "inlier_threshold": threshold,
    }
