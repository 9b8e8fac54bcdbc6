"""The spin settle (gsa.align.spin): the turn about a nearly turn-symmetric object's axis taken
from the parts that break the symmetry; and the guidance's front deciding between poses the
geometry ties (robust.prefer_among_tied)."""

import numpy as np

from gsa.align import robust, spin
from gsa.align.guided import front_gap_deg
from gsa.geometry import axis_rotation, rotation_distance_deg
from gsa.model import GaussianModel
from gsa.sim3 import Sim3
from gsa.synth.objects import surface_gaussians
from gsa.synth.shapes import Box, Cylinder, Torus


def _model(parts, n: int, seed: int) -> GaussianModel:
    rng = np.random.default_rng(seed)
    areas = np.array([p.area() for p in parts])
    counts = rng.multinomial(n, areas / areas.sum())
    samples = [p.sample(int(k), rng) for p, k in zip(parts, counts)]
    means = np.concatenate([s[0] for s in samples])
    normals = np.concatenate([s[1] for s in samples])
    colours = np.full((len(means), 3), 0.6)
    spacing = np.sqrt(areas.sum() / n)
    means, colours, scales, quats, opacities = surface_gaussians(means, normals, colours, spacing, 0, rng)
    return GaussianModel.from_colors(means, colours, quats=quats, scales=scales, opacities=opacities)


def _mug(radius: float, height: float, seed: int, handle: bool = True) -> GaussianModel:
    """A cup about +Z with (or without) a handle on its +X side."""
    parts = [Cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), radius, height, (0.6, 0.6, 0.6))]
    if handle:
        parts.append(Torus((radius + 0.12, 0.0, 0.0), (0.0, 1.0, 0.0), 0.13, 0.03, (0.6, 0.6, 0.6)))
    return _model(parts, 12_000, seed)


def _turned_about_z(truth: Sim3, degrees: float, target: GaussianModel) -> Sim3:
    """The truth turned about the target's up (the mapped +Z) through the target's axis."""
    up = truth.rotation @ np.array([0.0, 0.0, 1.0])
    pivot = truth.apply(np.zeros((1, 3)))[0]
    turn = axis_rotation(up, np.radians(degrees))
    return Sim3(1.0, turn, pivot - turn @ pivot).compose(truth)


def test_two_mugs_turned_along_their_body_come_back_onto_the_handle():
    source = _mug(0.40, 0.9, seed=1)
    target_canonical = _mug(0.46, 0.8, seed=2)  # another instance: wider, lower
    truth = Sim3(1.7, axis_rotation(np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5]), 2.0), np.ones(3))
    target = target_canonical.transformed(truth)
    for off in (25.0, -70.0, 150.0):
        settled = spin.settle_spin(source, target, _turned_about_z(truth, off, target))
        assert settled is not None
        pose, report = settled
        assert rotation_distance_deg(pose.rotation, truth.rotation) < 2.0, (off, report)
        assert abs(abs(report["turn_deg"]) - abs(off)) < 3.0


def test_a_right_answer_stays_where_it_is():
    source, target = _mug(0.40, 0.9, seed=1), _mug(0.40, 0.9, seed=5)
    pose, report = spin.settle_spin(source, target, Sim3.identity())
    assert rotation_distance_deg(pose.rotation, np.eye(3)) < 1.0, report


def test_nothing_to_settle_on_a_plain_cup_or_a_box():
    cups = _mug(0.4, 0.9, seed=1, handle=False), _mug(0.4, 0.9, seed=2, handle=False)
    assert spin.settle_spin(*cups, Sim3.identity()) is None  # no part breaks the symmetry
    box = _model([Box((0.0, 0.0, 0.0), (1.0, 0.6, 0.3), (0.6, 0.6, 0.6))], 8_000, 3)
    assert spin.settle_spin(box, box, Sim3.identity()) is None  # no axis it nearly spins about


def test_a_tilted_answer_is_not_turned():
    source, target = _mug(0.40, 0.9, seed=1), _mug(0.42, 0.85, seed=2)
    tilted = Sim3(1.0, axis_rotation(np.array([1.0, 0.0, 0.0]), np.radians(40.0)), np.zeros(3))
    assert spin.settle_spin(source, target, tilted) is None  # its axes disagree: the tilt is not this step's


def _candidate(degrees: float, score: float) -> robust.Candidate:
    rotation = axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(degrees))
    return robust.Candidate(Sim3(1.0, rotation, np.zeros(3)), f"up:{degrees:g}", score, score)


def test_the_front_decides_between_poses_the_geometry_ties():
    candidates = [_candidate(0.0, 0.50), _candidate(40.0, 0.49), _candidate(180.0, 0.40)]
    found = robust.decide(candidates, 0.0)
    assert [c.origin for c in found.rivals] == ["up:40"]
    fronts = ((1.0, 0.0, 0.0), tuple(axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(38.0)) @ [1.0, 0, 0]))
    chosen = robust.prefer_among_tied(found, lambda c: front_gap_deg(c.transform.rotation, fronts))
    assert chosen.best.origin == "up:40"
    assert chosen.margin < 0  # the geometry preferred the other one, and the verdict says so
    assert "up:0" in [c.origin for c in chosen.rivals]
    assert [c.origin for c in chosen.offered][0] == "up:0"
    # a pose outside the tie is never taken, however well it agrees with the front
    behind = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0))
    assert robust.prefer_among_tied(found, lambda c: front_gap_deg(c.transform.rotation, behind)).best.origin in (
        "up:0",
        "up:40",
    )
