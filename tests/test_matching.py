"""Matched starts (gsa.align.robust.matching): descriptors that follow a shape through any
similarity, and poses from paired descriptors that reach a partial capture's truth."""

from __future__ import annotations

import numpy as np

from gsa.align import robust
from gsa.align.robust.matching import MatchOptions, descriptors, matched_poses
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
