"""Matched starts (gsa.align.robust.matching): descriptors that follow a shape through any
similarity, and poses from paired descriptors that reach a partial capture's truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gsa.align import robust
from gsa.align.robust.matching import MatchOptions, descriptors, matched_poses
from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3
from gsa.synth.variants import cut_by_plane


def test_descriptors_follow_the_shape_through_a_similarity():
    points = make_object("chair", seed=2, n_gaussians=3000).means.astype(np.float64)[:1500]
    truth = Sim3(7.5, random_sim3(np.random.default_rng(4)).rotation, np.array([3.0, -2.0, 1.0]))
    before, spacing = descriptors(points)
    after, moved_spacing = descriptors(truth.apply(points))
    assert np.allclose(before, after, atol=1e-9)  # angles and relative distances only
    assert np.isclose(moved_spacing, 7.5 * spacing)
    assert np.allclose(before.sum(axis=1), 4.0)  # four histograms, each a distribution
    # the histograms tell the places of a shape apart (not all one histogram)
    assert np.median(np.linalg.norm(before - before.mean(axis=0), axis=1)) > 0.1


def _partial_chair_anchors():
    """Anchors of two disjoint halves of a chair, each cut by its own plane, the target moved
    and shrunk 5x, and that move."""
    rng = np.random.default_rng([5, 1])
    model = make_object("chair", seed=4, n_gaussians=16_000)
    halves = rng.random(len(model)) < 0.5
    source = cut_by_plane(model.subset(halves), rng, keep=(0.6, 0.7))
    truth = Sim3(0.2, random_sim3(rng).rotation, np.array([1.0, 2.0, 3.0]))
    target = cut_by_plane(model.subset(~halves), rng, keep=(0.6, 0.7)).transformed(truth)
    return robust.anchors(source, 2000), robust.anchors(target, 2000), truth


def test_matched_poses_reach_the_truth_of_two_partial_captures_of_one_object():
    """Two disjoint halves of a chair, each cut by its own plane, the target moved and shrunk
    5x: the starts come from paired anchors, not from the (misleading) centres. Generated
    objects are built of boxes and cylinders, alike everywhere in shape alone; their colours
    tell the places apart (the search passes its colour trust)."""
    src, dst, truth = _partial_chair_anchors()
    poses = matched_poses(src, dst, np.random.default_rng(0), count=4, min_deg=10.0, colour=1.0)
    assert 1 <= len(poses) <= 4
    assert all(rre_deg(a.rotation, b.rotation) > 10.0 for i, a in enumerate(poses) for b in poses[:i])
    errors = [rre_deg(p.rotation, truth.rotation) for p in poses]
    near = int(np.argmin(errors))
    assert errors[near] < 10.0, errors  # close enough for the anchors' ICP to finish
    assert abs(poses[near].scale / truth.scale - 1.0) < 0.15


def test_a_model_matched_with_itself_gives_the_identity_first():
    anchors = robust.anchors(make_object("boat", seed=1, n_gaussians=4000), 800)
    poses = matched_poses(anchors, anchors, np.random.default_rng(0), 2, 10.0, MatchOptions(triples=500))
    assert poses and rre_deg(poses[0].rotation, np.eye(3)) < 1.0 and abs(poses[0].scale - 1.0) < 0.02


def test_the_widened_search_refines_the_matched_starts():
    src, dst, truth = _partial_chair_anchors()
    widened = robust.global_search(src, dst, widen_if=lambda first: True)
    matched = [c for c in widened.candidates if c.origin == "matched"]
    assert matched, [c.origin for c in widened.candidates]
    assert min(rre_deg(c.transform.rotation, truth.rotation) for c in matched) < 2.0  # refined to the truth
    without = robust.global_search(src, dst, options=robust.SearchOptions(match_top=0), widen_if=lambda first: True)
    assert not any(c.origin == "matched" for c in without.candidates)
    first = robust.global_search(src, dst)  # not widened: no matched starts
    assert not any(c.origin == "matched" for c in first.candidates)


def test_a_triples_pose_is_fitted_again_to_every_pair_that_agrees_with_it():
    """LO-RANSAC's local step: a pose 8 degrees off (as a triple of pairs a spacing apart
    gives) is fitted again to the pairs it agrees with and lands on the truth, the outliers
    (a third of the pairs) left out."""
    from gsa.align.robust.matching import DescriptorPairs, _refit

    rng = np.random.default_rng(3)
    truth = Sim3(2.5, random_sim3(rng).rotation, np.array([1.0, -4.0, 2.0]))
    p = rng.uniform(-1.0, 1.0, size=(600, 3))
    q = truth.apply(p) + rng.normal(scale=0.005, size=p.shape)
    q[:200] = rng.uniform(-4.0, 4.0, size=(200, 3))  # pairs of unlike places
    off = Sim3(truth.scale, truth.rotation @ axis_rotation([0.0, 0.0, 1.0], np.radians(8.0)), truth.translation)
    pairs = DescriptorPairs(p, q, tolerance=0.5)
    refitted = _refit(off, p, q, pairs.tolerance, rounds=5)
    assert rre_deg(off.rotation, truth.rotation) > 7.9
    assert rre_deg(refitted.rotation, truth.rotation) < 0.5
    assert abs(refitted.scale / truth.scale - 1.0) < 0.01
    assert pairs.agreement(refitted) == pytest.approx(400 / 600, abs=0.02)
    assert _refit(off, p, q, pairs.tolerance, rounds=0) is off


def test_the_capped_icp_holds_two_halves_that_overlap_on_little():
    """Two parts of one chair that share a fifth of its length, started at the truth: the plain
    cut-off (4 median distances) takes in the pairs of the parts one side lacks and slides the
    pose off; capped at 2 of the score's truncation distances it stays near."""
    from gsa.align.robust.poses import bidirectional_icp

    model = make_object("chair", seed=4, n_gaussians=16_000)
    x = model.means[:, 0]
    lo, hi = np.quantile(x, [0.4, 0.6])
    src, dst = robust.anchors(model.subset(x < hi), 2000), robust.anchors(model.subset(x > lo), 2000)
    rows = (np.arange(len(src)), np.arange(len(dst)))
    start = Sim3(1.0, np.eye(3), np.zeros(3))
    plain = bidirectional_icp(src, dst, start, *rows, 70)
    capped = bidirectional_icp(src, dst, start, *rows, 70, reach=2.0)
    assert rre_deg(plain.rotation, np.eye(3)) > 45.0
    assert rre_deg(capped.rotation, np.eye(3)) < 15.0


def _chain_returning(monkeypatch, pose: Sim3):
    """The doubtful chain (semantic tie-break, the frames' turns) replaced by one that answers
    `pose`, as its rules for other instances do when they turn an answer."""
    from gsa.align import pipeline

    def chain(pair, best, search, transform, metrics, timings, progress):
        return pose, metrics | {"chain": "ran"}

    monkeypatch.setattr(pipeline, "_doubtful_chain", chain)


def _doubtful(pair, answer: Sim3, colour: float):
    from gsa.align.pipeline import _doubtful_search_answer, _Hypothesis

    search = robust.SearchResult(candidates=[], colour_weight=colour, margin=0.0, rivals=[])
    metrics = {"doubtful": True, "alternatives": []}
    best = _Hypothesis("test", pair.src_frame, answer)
    return _doubtful_search_answer(pair, best, search, answer, metrics, {}, None)


def test_an_answer_the_local_shapes_hold_is_turned_only_onto_a_pose_they_hold(monkeypatch):
    """Two halves of one chair at their truth: the local shapes hold it, so the chain's half
    turn (a rule for other instances) is refused and offered first, while a pose the shapes
    hold as well (a degree off) is taken."""
    from gsa.align.pipeline import _Pair
    from gsa.align.types import AlignOptions

    rng = np.random.default_rng([5, 1])
    model = make_object("chair", seed=4, n_gaussians=16_000)
    halves = rng.random(len(model)) < 0.5
    truth = Sim3(0.2, random_sim3(rng).rotation, np.array([1.0, 2.0, 3.0]))
    source, target = model.subset(halves), model.subset(~halves).transformed(truth)
    pair = _Pair.build(source, target, AlignOptions(semantic="off"))
    half_turn = truth @ Sim3(1.0, axis_rotation([0.0, 1.0, 0.0], np.pi), np.zeros(3))
    _chain_returning(monkeypatch, half_turn)
    kept, report = _doubtful(pair, truth, colour=1.0)
    shapes = report["local_shapes"]
    assert kept is truth and shapes["holds"] and shapes["kept"] == "the answer", shapes
    assert shapes["agreement"] >= shapes["needed"] > shapes["chain_agreement"]
    assert np.allclose(report["alternatives"][0]["transform"], half_turn.matrix())
    assert report["doubtful"] and "chain" not in report  # the chain's report goes with its pose
    near = truth @ Sim3(1.0, axis_rotation([0.0, 1.0, 0.0], np.radians(1.0)), np.zeros(3))
    _chain_returning(monkeypatch, near)
    taken, report = _doubtful(pair, truth, colour=1.0)
    assert taken is near and report["local_shapes"]["kept"] == "the chain's pose" and report["chain"] == "ran"


def test_the_chain_turns_an_answer_the_local_shapes_do_not_hold(monkeypatch):
    """Two shapes whose parts do not correspond (a chair and an airplane: generated instances
    of one kind are near copies of one shape, and pair 5-18 % like places): the local shapes
    do not hold the answer, so the chain's rules decide as before."""
    from gsa.align.pipeline import _Pair
    from gsa.align.types import AlignOptions

    source = make_object("chair", seed=4, n_gaussians=8000)
    target = make_object("airplane", seed=4, n_gaussians=8000)
    pair = _Pair.build(source, target, AlignOptions(semantic="off"))
    identity = Sim3(1.0, np.eye(3), np.zeros(3))
    turned = Sim3(1.0, axis_rotation([0.0, 1.0, 0.0], np.pi), np.zeros(3))
    _chain_returning(monkeypatch, turned)
    answer, report = _doubtful(pair, identity, colour=0.0)
    assert answer is turned and report["chain"] == "ran"
    assert not report["local_shapes"]["holds"], report["local_shapes"]


def test_align_reports_the_local_shapes_share_of_the_answer_and_each_alternative():
    """With alternatives always offered (as N-way edges ask), the answer and each alternative
    carry the share of the local shapes' pairs they hold: the right answer over the share
    needed, a half turn of it under."""
    from gsa.align import AlignOptions, align
    from gsa.align.many import edge_from_result, held_poses

    rng = np.random.default_rng([5, 2])
    model = make_object("chair", seed=4, n_gaussians=8000)
    halves = rng.random(len(model)) < 0.5
    truth = random_sim3(rng)
    result = align(model.subset(halves), model.subset(~halves).transformed(truth), AlignOptions(alternatives="always"))
    assert rre_deg(result.transform.rotation, truth.rotation) < 2.0
    metrics = result.metrics
    assert metrics["local_agreement"] >= metrics["local_agreement_needed"] > 0
    alternatives = [a.details for a in result.verdict.alternatives]
    assert alternatives and all("local_agreement" in a for a in alternatives)
    far = [
        a["local_agreement"]
        for a in alternatives
        if rre_deg(Sim3.from_matrix(np.asarray(a["transform"])).rotation, truth.rotation) > 150
    ]
    assert far and max(far) < metrics["local_agreement"]
    edge = edge_from_result(0, 1, result, 0.0)
    assert held_poses(edge)[0] and len(edge.agreements) == 1 + len(edge.alternatives)


def test_a_pose_that_slid_off_the_scores_peak_is_held_within_reach():
    """Two halves of one chair, each cut by its own plane: a pose 15 degrees off scores under
    half of what the capped ICP from it reaches (the truth), so it is held there; the truth
    itself, and a pose that keeps over half of the peak's score, are left as they are."""
    from gsa.synth.variants import cut_by_plane

    rng = np.random.default_rng([7, 0])
    model = make_object("chair", seed=4, n_gaussians=16_000)
    halves = rng.random(len(model)) < 0.5
    a = cut_by_plane(model.subset(halves), rng, keep=(0.6, 0.7))
    b = cut_by_plane(model.subset(~halves), rng, keep=(0.6, 0.7))
    src, dst = robust.anchors(a, 2000), robust.anchors(b, 2000)
    opts = robust.SearchOptions()

    def turned(deg: float) -> Sim3:
        return Sim3(1.0, axis_rotation([0.0, 1.0, 0.0], np.radians(deg)), np.zeros(3))

    held = robust.held_within_reach(src, dst, turned(15.0), 0.0, opts)
    assert held is not None and rre_deg(held[0].transform.rotation, np.eye(3)) < 1.0
    assert held[1].score < opts.matching.slid_share * held[0].score  # the pose it was held from, as scored
    assert robust.held_within_reach(src, dst, turned(0.0), 0.0, opts) is None
    assert robust.held_within_reach(src, dst, turned(6.0), 0.0, opts) is None
    # where nothing overlaps the scores are no share of anything: nothing is held
    apart = Sim3(1.0, np.eye(3), np.array([50.0, 0.0, 0.0]) * dst.radius)
    assert robust.held_within_reach(src, dst, apart, 0.0, opts) is None


def _cut_chair_halves():
    from gsa.synth.variants import cut_by_plane

    rng = np.random.default_rng([7, 0])
    model = make_object("chair", seed=4, n_gaussians=16_000)
    halves = rng.random(len(model)) < 0.5
    a = cut_by_plane(model.subset(halves), rng, keep=(0.6, 0.7))
    b = cut_by_plane(model.subset(~halves), rng, keep=(0.6, 0.7))
    return a, b


def test_a_held_pose_better_in_geometry_and_colour_is_taken_where_colours_agree_little():
    """Two small halves dealt from one capture agree in colour only in part (an iPhone room
    drawn to 12k: 0.53 at the truth), so the coloured score at the held pose keeps less than
    half of its geometric one and the colours-agree test refused it; a held pose that fits
    both better than the slid one, geometry and colours each, is taken all the same."""
    a, b = _cut_chair_halves()
    src, dst = robust.anchors(a, 2000), robust.anchors(b, 2000)
    noise = np.random.default_rng(5).normal(0.0, 6.0, dst.lab.shape)  # CIELAB units
    dst = replace(dst, lab=dst.lab + noise)
    opts = robust.SearchOptions()
    slid = Sim3(1.0, axis_rotation([0.0, 1.0, 0.0], np.radians(15.0)), np.zeros(3))
    found = robust.held_within_reach(src, dst, slid, 1.0, opts)
    assert found is not None and rre_deg(found[0].transform.rotation, np.eye(3)) < 1.0
    held, before = found
    assert held.score < opts.matching.slid_share * held.geometry  # the colours agree little
    assert held.geometry > before.geometry and held.colour > before.colour


def test_a_pose_beyond_the_capped_icps_reach_is_held_from_turned_starts():
    """40 degrees off two cut halves of a chair the capped ICP alone ends 28 degrees off; from
    starts turned 6 and 12 degrees about 26 axes through the answer the best reaches the truth.
    It is the second cap (one truncation, the pairs the score counts) that climbs the score's
    peak: at two truncations alone the best ends 1.6 degrees off it."""
    a, b = _cut_chair_halves()
    src, dst = robust.anchors(a, 2000), robust.anchors(b, 2000)
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    pose = Sim3(1.0, axis_rotation(axis, np.radians(40.0)), np.zeros(3))
    opts = robust.SearchOptions()
    assert opts.matching.icp_reach == (2.0, 1.0)
    alone = robust.held_within_reach(src, dst, pose, 0.0, opts)
    assert alone is None or rre_deg(alone[0].transform.rotation, np.eye(3)) > 10.0
    turned = robust.held_within_reach(src, dst, pose, 0.0, opts, (6.0, 12.0))
    assert turned is not None and rre_deg(turned[0].transform.rotation, np.eye(3)) < 0.5
    wide_only = replace(opts, matching=replace(opts.matching, icp_reach=(2.0,)))
    wide = robust.held_within_reach(src, dst, pose, 0.0, wide_only, (6.0, 12.0))
    assert wide is not None and rre_deg(wide[0].transform.rotation, np.eye(3)) > 1.0
    assert wide[0].score < turned[0].score


def test_a_doubtful_answer_beside_the_peak_is_held_before_the_chain(monkeypatch):
    """The doubtful answer 40 degrees off two cut halves of a chair: held from turned starts
    before the chain runs, the answer offered first, metrics.held_within_reach saying so."""
    from gsa.align.pipeline import _Pair
    from gsa.align.types import AlignOptions

    a, b = _cut_chair_halves()
    pair = _Pair.build(a, b, AlignOptions(semantic="off"))
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    answer = Sim3(1.0, axis_rotation(axis, np.radians(40.0)), np.zeros(3))
    seen = []

    def chain(pair, best, search, transform, metrics, timings, progress):
        seen.append(transform)
        return transform, metrics

    from gsa.align import pipeline

    monkeypatch.setattr(pipeline, "_doubtful_chain", chain)
    pose, report = _doubtful(pair, answer, colour=0.0)
    assert rre_deg(pose.rotation, np.eye(3)) < 3.0
    assert report["held_within_reach"]["turned"] and report["held_within_reach"]["score"] > 0
    assert np.allclose(report["alternatives"][0]["transform"], answer.matrix())
    assert not seen or seen[0] is pose  # the chain, where it ran, saw the held pose


def test_the_hypotheses_the_search_scores_best_join_the_matched_starts():
    """With the search's score, more triples are drawn and the hypotheses most pairs agree
    with are ranked by it: those it ranks best join the starts found by agreement alone, which
    come first and unchanged (between two partial halves agreement is a weak proxy, the score
    peaks at the truth). Here the score is closeness to the truth itself: the joining poses come
    nearest first, each min_deg from every other start."""
    src, dst, truth = _partial_chair_anchors()
    plain = matched_poses(src, dst, np.random.default_rng(0), count=4, min_deg=10.0, colour=1.0)
    calls: list[int] = []

    def nearness(poses: list[Sim3]) -> np.ndarray:
        calls.append(len(poses))
        return -np.array([rre_deg(p.rotation, truth.rotation) for p in poses])

    options = MatchOptions(scored_triples=50_000, scored_top=300, scored_count=2)
    scored = matched_poses(src, dst, np.random.default_rng(0), 4, 10.0, options, 1.0, nearness)

    def same(a: list[Sim3], b: list[Sim3]) -> bool:
        return len(a) == len(b) and all(np.array_equal(x.matrix(), y.matrix()) for x, y in zip(a, b, strict=True))

    assert same(scored[: len(plain)], plain)  # the agreement's starts, as before
    joined = scored[len(plain) :]
    assert calls == [300] and len(joined) == 2
    errors = [rre_deg(p.rotation, truth.rotation) for p in joined]
    assert errors[0] <= errors[1]
    # min_deg apart from each other and from the found ones
    assert all(
        rre_deg(a.rotation, b.rotation) > 10.0 for a in joined for b in plain + [p for p in joined if p is not a]
    )
    # no score, or none to join: the plain starts
    none = MatchOptions(scored_count=0)
    assert same(matched_poses(src, dst, np.random.default_rng(0), 4, 10.0, none, 1.0, nearness), plain)


def test_the_scored_hypotheses_need_no_consensus():
    """The consensus gate keeps agreement's starts to poses many pairs agree with; the scored
    hypotheses are picked by the score, not by agreement, so they join even where no pose
    reaches the gate (the iPhone room's pairs 21 and 25), however far the palettes are shared
    (the caller passes a score only where colours are trusted; halves of a small capture share
    less than all of their palettes: weights 0.74-0.96). Without the score nothing passes such a gate."""
    src, dst, truth = _partial_chair_anchors()
    unreachable = MatchOptions(min_consensus=1.01, scored_triples=50_000, scored_top=300, scored_count=2)
    assert matched_poses(src, dst, np.random.default_rng(0), 4, 10.0, unreachable, 1.0) == []

    def nearness(poses: list[Sim3]) -> np.ndarray:
        return -np.array([rre_deg(p.rotation, truth.rotation) for p in poses])

    for colour in (1.0, 0.6):
        joined = matched_poses(src, dst, np.random.default_rng(0), 4, 10.0, unreachable, colour, nearness)
        assert len(joined) == 2
        assert rre_deg(joined[0].rotation, truth.rotation) < 10.0
        assert rre_deg(joined[0].rotation, joined[1].rotation) > 10.0


def test_the_pairs_assume_the_scale_their_anchor_spacings_give():
    """A descriptor describes a number of anchors, so the pairs are alike at the scale the two
    models' anchor spacings give (here within a fifth of the truth's 0.2). A pose far off that
    scale pairs neighbourhoods of unlike size: with a score that favours the smallest scale (as
    colours compared under a shifted exposure favoured a source shrunk onto a plain floor), the
    hypotheses it ranks best lie beyond scale_spread of it and are dropped; the starts within it
    are the ones found without the bound, in order."""
    from gsa.align.robust.matching import descriptor_pairs

    src, dst, truth = _partial_chair_anchors()
    pairs = descriptor_pairs(src, dst, MatchOptions(), 1.0)
    assert abs(pairs.scale / truth.scale - 1.0) < 0.2
    assert pairs.scale_fits(Sim3(1.9 * pairs.scale, np.eye(3), np.zeros(3)), 2.0)
    assert not pairs.scale_fits(Sim3(0.45 * pairs.scale, np.eye(3), np.zeros(3)), 2.0)

    def smallest(poses: list[Sim3]) -> np.ndarray:
        return -np.array([p.scale for p in poses])

    opts = MatchOptions(scored_triples=50_000, scored_top=1000, scored_count=2)
    unbounded = matched_poses(
        src, dst, np.random.default_rng(0), 4, 10.0, replace(opts, scale_spread=np.inf), 1.0, smallest
    )
    assert min(p.scale for p in unbounded) < 0.5 * pairs.scale
    bounded = matched_poses(src, dst, np.random.default_rng(0), 4, 10.0, opts, 1.0, smallest)
    kept = [p for p in unbounded if pairs.scale_fits(p, opts.scale_spread)]
    assert bounded and len(bounded) == len(kept) < len(unbounded)
    assert all(a.scale == b.scale and np.array_equal(a.rotation, b.rotation) for a, b in zip(bounded, kept))
