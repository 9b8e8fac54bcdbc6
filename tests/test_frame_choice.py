"""Choosing among the 24 relabellings of two instances' frames: the surface-mass grids tell
which end is which where the frames cannot, and a doubtful answer turned end for end is turned
back (the replaced pose kept as the first alternative)."""

import numpy as np

from gsa.geometry import axis_rotation, rotation_distance_deg
from gsa.manhattan import manhattan_frame, relabelling_agreement, relabellings
from gsa.sim3 import Sim3
from gsa.synth import random_sim3
from gsa.synth.meshes import load_mesh, mesh_to_gaussians
from tests.test_category_real import _box_mesh


def _bench(base_half, back_half, seed: int, folder):
    """A long base with a back rising at its +x end (a bench, a bathtub's tall end): a
    mirror plane but no turn of it onto itself, so one relabelling of its frame is right."""
    v1, f1 = _box_mesh(base_half)
    v2, f2 = _box_mesh(back_half)
    v2 = v2 + np.array([base_half[0] - back_half[0], base_half[1] + back_half[1], 0.0], np.float32)
    path = folder / f"bench{seed}_0.npz"
    np.savez(path, V=np.concatenate([v1, v2]), F=np.concatenate([f1, f2 + len(v1)]))
    return mesh_to_gaussians(load_mesh(path), 6000, np.random.default_rng(seed), floaters=0.02)


def _pair(tmp_path, truth: Sim3):
    # Two instances of other proportions: a longer, lower one and a shorter one with a taller back.
    source = _bench((1.0, 0.15, 0.35), (0.12, 0.45, 0.35), 1, tmp_path)
    target = _bench((0.8, 0.2, 0.3), (0.1, 0.6, 0.3), 2, tmp_path).transformed(truth)
    return source, target


def test_the_mass_grids_pick_the_true_relabelling_of_two_instances(tmp_path):
    truth = random_sim3(np.random.default_rng(3))
    source, target = _pair(tmp_path, truth)
    frames = manhattan_frame(source), manhattan_frame(target)
    agreement = relabelling_agreement(source, target, *frames)
    candidates = relabellings(*frames)
    errors = np.array([rotation_distance_deg(r, truth.rotation) for r in candidates])
    assert errors.min() < 2.0  # the frames hold the truth
    best = int(np.argmax(agreement))
    assert errors[best] == errors.min(), (errors[best], agreement.round(3))
    end_for_end = int(
        np.argmin([rotation_distance_deg(r, truth.rotation @ axis_rotation([0, 1, 0], np.pi)) for r in candidates])
    )
    assert agreement[best] > agreement[end_for_end] + 0.05, agreement.round(3)
    # the same model against itself agrees (nearly) perfectly at the identity
    assert relabelling_agreement(source, source, frames[0], frames[0])[0] > 0.999


def test_a_doubtful_answer_end_for_end_is_turned_back(tmp_path):
    from gsa.align import frame_snap
    from gsa.align.pipeline import _Hypothesis, _Pair
    from gsa.align.types import AlignOptions

    truth = random_sim3(np.random.default_rng(5))
    source, target = _pair(tmp_path, truth)
    pair = _Pair.build(source, target, AlignOptions(semantic="off"))
    flipped = truth @ Sim3(1.0, axis_rotation([0, 1, 0], np.pi), np.zeros(3))  # back onto the wrong end
    best = _Hypothesis("test", pair.src_frame, flipped)
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    assert frame_snap.whole_models(metrics)
    chosen, updated = frame_snap.choose_relabelling(pair, best, flipped, metrics)
    assert updated["frame_choice"]["switched"], updated["frame_choice"]
    assert rotation_distance_deg(chosen.rotation, truth.rotation) < 2.0
    assert updated["alternatives"][0]["origin"] == "before the relabelling choice"
    assert np.allclose(updated["alternatives"][0]["transform"], flipped.matrix())
    assert all(a["origin"] == "frame relabelling" for a in updated["alternatives"][1:])
    assert all(a["tied"] is False for a in updated["alternatives"])  # every alternative says whether it ties
    # every other relabelling is offered once (the replaced pose is one of them), best-scored first
    relabelled = updated["alternatives"][1:]
    assert len(relabelled) == 22, len(relabelled)
    scores = [a["shape_agreement"] for a in relabelled]
    assert scores == sorted(scores, reverse=True)
    others = [Sim3.from_matrix(np.asarray(a["transform"])).rotation for a in updated["alternatives"]]
    assert all(rotation_distance_deg(r, chosen.rotation) > 2.0 for r in others)
    # an answer far from every relabelling, between other instances neither of which spins
    # freely: the frames hold the truth all the same, and it is turned onto them
    tilted = truth @ Sim3(1.0, axis_rotation([1, 1, 0], np.radians(40)), np.zeros(3))
    turned, report = frame_snap.choose_relabelling(pair, best, tilted, metrics)
    assert report["frame_choice"]["frames_hold"] and report["frame_choice"]["switched"], report["frame_choice"]
    assert rotation_distance_deg(turned.rotation, truth.rotation) < 2.0
    assert np.allclose(report["alternatives"][0]["transform"], tilted.matrix())
    # where the surfaces coincide (two captures of one object) it is left as it is: the frames do not explain it
    coinciding = metrics | {"coincident_share": 0.9}
    kept, report = frame_snap.choose_relabelling(pair, best, tilted, coinciding)
    assert kept is tilted and report["frame_choice"]["used"] is False
    offered = [Sim3.from_matrix(np.asarray(a["transform"])) for a in report["alternatives"]]
    assert min(rotation_distance_deg(p.rotation, truth.rotation) for p in offered) < 2.0  # still offered
    # a part of a model inside another (overlap estimate below whole) is not asked
    assert not frame_snap.whole_models(metrics | {"overlap_estimate": 0.6})
    # two instances whose parts differ in length read under the whole-model 0.875 even at the
    # truth: with their surfaces apart they are asked; two captures of one object that coincide are not
    assert frame_snap.whole_models(metrics | {"overlap_estimate": 0.8})
    assert not frame_snap.whole_models(metrics | {"overlap_estimate": 0.8, "coincident_share": 0.9})
    assert frame_snap.whole_models(metrics | {"overlap_estimate": 0.9, "coincident_share": 0.9})


def _vase(radius: float, height: float, neck: float, seed: int, folder):
    """A cylinder with a narrower neck on top (a vase, a bottle): it turns freely about its axis
    (y), so its dominant-normal frame is any turn about it."""
    segments = 96
    t = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    rings = [(radius, 0.0), (radius, height), (neck, height), (neck, 1.3 * height)]
    vertices = np.array([[r * np.cos(a), y, r * np.sin(a)] for r, y in rings for a in t], np.float32)
    faces = []
    for ring in range(len(rings) - 1):
        for k in range(segments):
            a, b = ring * segments + k, ring * segments + (k + 1) % segments
            faces += [[a, b, a + segments], [b, b + segments, a + segments]]
    bottom = len(vertices)
    vertices = np.concatenate([vertices, np.array([[0.0, 0.0, 0.0]], np.float32)])
    faces += [[bottom, (k + 1) % segments, k] for k in range(segments)]
    path = folder / f"vase{seed}_0.npz"
    np.savez(path, V=vertices, F=np.array(faces, np.int32))
    return mesh_to_gaussians(load_mesh(path), 6000, np.random.default_rng(seed), floaters=0.02)


def test_an_answer_off_the_frames_of_a_model_that_spins_freely_is_kept(tmp_path):
    from gsa.align import frame_snap
    from gsa.align.pipeline import _Hypothesis, _Pair
    from gsa.align.types import AlignOptions

    truth = random_sim3(np.random.default_rng(7))
    source = _vase(0.5, 1.0, 0.2, 1, tmp_path)
    target = _vase(0.35, 1.2, 0.15, 2, tmp_path).transformed(truth)
    pair = _Pair.build(source, target, AlignOptions(semantic="off"))
    assert pair.spins_freely

    # right up to the vase's own turn about its axis, as far from every relabelling as such a turn goes
    def spun_by(deg: float) -> Sim3:
        return truth @ Sim3(1.0, axis_rotation([0, 1, 0], np.radians(deg)), np.zeros(3))

    def off_frames(pose: Sim3) -> float:
        return min(rotation_distance_deg(r, pose.rotation) for r in relabellings(*pair.normal_frames))

    spun = spun_by(max(range(90), key=lambda deg: off_frames(spun_by(deg))))
    assert off_frames(spun) > frame_snap.CHOICE_MAX_DEG
    best = _Hypothesis("test", pair.src_frame, spun)
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    kept, report = frame_snap.choose_relabelling(pair, best, spun, metrics)
    assert kept is spun and report["frame_choice"]["frames_hold"] is False, report["frame_choice"]


def _guided_pair(tmp_path, truth: Sim3, **hints):
    from gsa.align.pipeline import _Hypothesis, _Pair
    from gsa.align.types import AlignOptions

    source, target = _pair(tmp_path, truth)
    opts = AlignOptions(semantic="off", **hints)
    pair = _Pair.build(source, target, opts)
    from gsa.align import guided

    start_pose, report = guided.start_transform(opts)
    return pair, _Hypothesis("guided", pair.src_frame, start_pose), report


def test_a_guided_answer_that_drifted_off_the_users_frame_is_turned_onto_the_relabelling_it_started_on(tmp_path):
    from gsa.align import frame_snap

    truth = random_sim3(np.random.default_rng(7))
    start = truth @ Sim3(1.0, axis_rotation([1.0, 0.3, -0.5], np.radians(20)), np.zeros(3))
    pair, best, report = _guided_pair(tmp_path, truth, init_transform=start.matrix().tolist())
    # the refinement drifted 40 deg further, off the frames and beyond the plain snap's reach
    drifted = truth @ Sim3(1.0, axis_rotation([1.0, 0.3, -0.5], np.radians(60)), np.zeros(3))
    metrics = {"doubtful": True, "overlap_estimate": 0.8, "coincident_share": 0.3, "alternatives": []}
    assert frame_snap.surfaces_apart(metrics) and not frame_snap.other_instances(metrics)
    chosen, updated = frame_snap.guided_snap(pair, best, drifted, metrics, report, ())
    assert rotation_distance_deg(chosen.rotation, truth.rotation) < 2.0
    assert updated["frame_snap"]["used"] and updated["frame_snap"]["onto"]
    assert updated["alternatives"][0]["origin"] == "before the frame snap"
    assert np.allclose(updated["alternatives"][0]["transform"], drifted.matrix())
    # two captures of one object that coincide keep their fit
    kept, _ = frame_snap.guided_snap(pair, best, drifted, metrics | {"coincident_share": 0.9}, report, ())
    assert kept is drifted


def test_the_guidance_points_at_one_relabelling_or_none(tmp_path):
    from gsa.align import frame_snap

    truth = random_sim3(np.random.default_rng(8))
    start = truth @ Sim3(1.0, axis_rotation([0.2, 1.0, 0.4], np.radians(22)), np.zeros(3))
    pair, best, report = _guided_pair(tmp_path, truth, init_transform=start.matrix().tolist())
    rotation = frame_snap.guided_relabelling(pair, best.init, report, ())
    assert rotation_distance_deg(rotation, truth.rotation) < 2.0
    # a pose midway between relabellings (60 deg about a diagonal) is on no relabelling's leash
    frames = pair.normal_frames
    between = Sim3(1.0, relabellings(*frames)[0] @ axis_rotation(frames[0].axes.sum(0), np.radians(60)), np.zeros(3))
    pair2, best2, report2 = _guided_pair(tmp_path, truth, init_transform=between.matrix().tolist())
    assert frame_snap.guided_relabelling(pair2, best2.init, report2, ()) is None
    # picked pairs: the relabelling that misses the clicks least
    rng = np.random.default_rng(9)
    src = pair.source.means[rng.choice(len(pair.source), 4, replace=False)].astype(np.float64)
    clicks = {"point_pairs": (src.tolist(), truth.apply(src + rng.normal(0, 0.02, src.shape)).tolist())}
    pair3, best3, report3 = _guided_pair(tmp_path, truth, **clicks)
    rotation = frame_snap.guided_relabelling(pair3, best3.init, report3, ())
    assert rotation_distance_deg(rotation, truth.rotation) < 2.0


def test_a_doubtful_answer_about_given_up_axes_is_turned_onto_the_frames_and_kept_upright(tmp_path):
    from gsa.align import frame_snap

    truth = random_sim3(np.random.default_rng(11))
    up = np.array([0.0, 1.0, 0.0])  # the benches' back rises along +y in both
    hints = {"up_axes": (up.tolist(), (truth.rotation @ up).tolist())}
    from gsa.align.pipeline import _Hypothesis, _Pair
    from gsa.align.types import AlignOptions

    source, target = _pair(tmp_path, truth)
    pair = _Pair.build(source, target, AlignOptions(semantic="off", **hints))
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    for turn_deg in (35.0, 180.0):  # drifted about the up axis; end for end (the heavy ends piled together)
        answer = truth @ Sim3(1.0, axis_rotation(up, np.radians(turn_deg)), np.zeros(3))
        best = _Hypothesis("guided:up", pair.src_frame, answer)
        chosen, updated = frame_snap.up_snap(pair, best, answer, metrics)
        assert rotation_distance_deg(chosen.rotation, truth.rotation) < 2.0, (turn_deg, updated.get("frame_choice"))
        assert np.degrees(np.arccos(np.clip((chosen.rotation @ up) @ (truth.rotation @ up), -1, 1))) < 1e-6
        assert updated["alternatives"][0]["origin"] in ("before the frame snap", "before the relabelling choice")
    # two captures of one object keep their fit; so does an answer about up axes no relabelling
    # keeps (a target up half way between two of its frame's axes: a wrong hint)
    kept, _ = frame_snap.up_snap(pair, best, answer, metrics | {"coincident_share": 0.9})
    assert kept is answer
    wrong = truth.rotation @ axis_rotation([0.0, 0.0, 1.0], np.radians(45)) @ up
    pair_wrong = _Pair.build(source, target, AlignOptions(semantic="off", up_axes=(up.tolist(), wrong.tolist())))
    kept, _ = frame_snap.up_snap(pair_wrong, best, answer, metrics)
    assert kept is answer


def _box(half, seed: int, folder):
    v, f = _box_mesh(half)
    path = folder / f"box{seed}_0.npz"
    np.savez(path, V=v, F=f)
    return mesh_to_gaussians(load_mesh(path), 6000, np.random.default_rng(seed), floaters=0.0)


def _end_features(model) -> np.ndarray:
    """A part label as a network would give it: one direction on the +x end of a long box (a
    tub's taps end), another elsewhere; unit vectors, as the lifted features are."""
    x = np.asarray(model.means, np.float64)[:, 0]
    return np.where((x > 0.5 * x.max())[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_the_lifted_features_tell_the_ends_of_two_boxes_apart_where_the_mass_cannot(tmp_path):
    from gsa.manhattan import feature_agreement

    truth = random_sim3(np.random.default_rng(7))
    source = _box((1.0, 0.3, 0.5), 1, tmp_path)
    target = _box((0.8, 0.4, 0.45), 2, tmp_path)  # other proportions
    source_features, target_features = _end_features(source), _end_features(target)
    target = target.transformed(truth)  # the features stay with their Gaussians
    frames = manhattan_frame(source), manhattan_frame(target)
    candidates = relabellings(*frames)
    errors = np.array([rotation_distance_deg(r, truth.rotation) for r in candidates])
    end_for_end = int(
        np.argmin([rotation_distance_deg(r, truth.rotation @ axis_rotation([0, 1, 0], np.pi)) for r in candidates])
    )
    right = int(np.argmin(errors))
    assert errors[right] < 2.0
    mass = relabelling_agreement(source, target, *frames)
    assert abs(mass[right] - mass[end_for_end]) < 0.01, mass.round(4)  # a box: both ends alike
    parts = feature_agreement(
        source,
        target,
        *frames,
        (np.asarray(source.means), source_features),
        (np.asarray(target.means), target_features),
    )
    assert parts[right] > parts[end_for_end] + 0.1, parts.round(3)
    # the best-scored keep the +x end where it belongs: the truth, or its half turn about x
    about_x = truth.rotation @ axis_rotation([1, 0, 0], np.pi)
    best = candidates[int(np.argmax(parts))]
    assert min(rotation_distance_deg(best, truth.rotation), rotation_distance_deg(best, about_x)) < 2.0
    # a model against itself agrees perfectly at the identity
    assert (
        feature_agreement(source, source, frames[0], frames[0], *[(np.asarray(source.means), source_features)] * 2)[0]
        > 0.999
    )


def test_a_models_own_symmetries_among_the_relabellings_of_its_frame(tmp_path):
    from gsa.canonical import SIGNED_PERMUTATIONS
    from gsa.manhattan import equivalent_relabellings, self_relabellings

    identity = next(k for k, g in enumerate(SIGNED_PERMUTATIONS) if np.array_equal(g, np.eye(3)))
    bench = _bench((1.0, 0.15, 0.35), (0.12, 0.45, 0.35), 1, tmp_path)  # a mirror plane, no turn
    bench_self = self_relabellings(bench, manhattan_frame(bench))
    assert bench_self.sum() == 1 and bench_self[identity], bench_self
    box = _box((1.0, 0.3, 0.5), 1, tmp_path)  # three half turns
    box_self = self_relabellings(box, manhattan_frame(box))
    assert box_self.sum() == 4 and box_self[identity], box_self
    square = _box((0.5, 0.3, 0.5), 2, tmp_path)  # also quarter turns about its short axis
    assert self_relabellings(square, manhattan_frame(square)).sum() == 8
    # relabellings that differ by a symmetry of either model are one answer
    alone = np.zeros(24, bool)
    alone[identity] = True
    assert equivalent_relabellings(identity, alone, alone).sum() == 1
    alike = equivalent_relabellings(5, box_self, alone)
    assert alike.sum() == 4 and alike[5]
    assert equivalent_relabellings(5, alone, box_self).sum() == 4


def test_the_shapes_settle_the_choice_between_two_benches_and_the_tiebreak_is_skipped(tmp_path):
    from gsa.align import frame_snap
    from gsa.align.pipeline import _Hypothesis, _Pair, _shape_settled_answer
    from gsa.align.types import AlignOptions

    truth = random_sim3(np.random.default_rng(5))
    source, target = _pair(tmp_path, truth)
    pair = _Pair.build(source, target, AlignOptions())
    flipped = truth @ Sim3(1.0, axis_rotation([0, 1, 0], np.pi), np.zeros(3))
    best = _Hypothesis("test", pair.src_frame, flipped)
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    settled = _shape_settled_answer(pair, best, flipped, metrics)
    assert settled is not None
    chosen, report = settled
    assert rotation_distance_deg(chosen.rotation, truth.rotation) < 2.0
    assert report["semantic"]["used"] is False
    assert report["semantic"]["settled_by_shape"]["lead_sigma"] >= frame_snap.SHAPE_DECISIVE_SIGMA
    assert report["doubtful"] is True  # still a guess between other instances
    assert len(report["alternatives"]) >= 22  # every relabelling still offered
    # an answer far off every relabelling is turned onto the settled one all the same
    tilted = truth @ Sim3(1.0, axis_rotation([1, 1, 0], np.radians(40)), np.zeros(3))
    chosen, report = _shape_settled_answer(pair, best, tilted, metrics)
    assert rotation_distance_deg(chosen.rotation, truth.rotation) < 2.0
    assert report["frame_snap"]["onto"] == "the relabelling the shapes settle"
    assert np.allclose(report["alternatives"][0]["transform"], tilted.matrix())  # the search's answer offered
    # a part inside a whole, two captures whose surfaces coincide, or the tie-break turned off:
    # left to the usual path
    assert _shape_settled_answer(pair, best, flipped, metrics | {"coincident_share": 0.9}) is None
    assert _shape_settled_answer(pair, best, flipped, metrics | {"overlap_estimate": 0.6}) is None
    assert (
        _shape_settled_answer(_Pair.build(source, target, AlignOptions(semantic="off")), best, flipped, metrics) is None
    )


def test_the_shapes_do_not_settle_the_choice_between_two_boxes(tmp_path):
    """A box turns onto itself by half turns: which end is which is the question the mass
    grids cannot answer, so the semantic tie-break keeps it."""
    from gsa.align.pipeline import _Hypothesis, _Pair, _shape_settled_answer
    from gsa.align.types import AlignOptions

    truth = random_sim3(np.random.default_rng(7))
    source = _box((1.0, 0.3, 0.5), 1, tmp_path)
    target = _box((0.8, 0.4, 0.45), 2, tmp_path).transformed(truth)
    pair = _Pair.build(source, target, AlignOptions())
    best = _Hypothesis("test", pair.src_frame, truth)
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    assert _shape_settled_answer(pair, best, truth, metrics) is None


def _ellipsoid(radii, bump, seed: int, folder):
    """A curved body (a UV-sphere mesh scaled per axis) with a smaller one stuck on at `bump`:
    its dominant-normal frame holds little of the surface, as animals', people's and mugs' do."""
    lat, lon = np.meshgrid(np.linspace(0, np.pi, 25), np.linspace(0, 2 * np.pi, 49), indexing="ij")
    grid = np.stack([np.sin(lat) * np.cos(lon), np.cos(lat), np.sin(lat) * np.sin(lon)], -1).reshape(-1, 3)
    rows, cols = lat.shape
    quads = [
        (i * cols + j, i * cols + j + 1, (i + 1) * cols + j + 1, (i + 1) * cols + j)
        for i in range(rows - 1)
        for j in range(cols - 1)
    ]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))], np.int32)
    body = grid * np.asarray(radii)
    knob = grid * 0.3 * min(radii) + np.asarray(bump)
    path = folder / f"blob{seed}_0.npz"
    np.savez(path, V=np.concatenate([body, knob]).astype(np.float32), F=np.concatenate([faces, faces + len(grid)]))
    return mesh_to_gaussians(load_mesh(path), 6000, np.random.default_rng(seed), floaters=0.02)


def test_frames_that_hold_little_of_the_surfaces_turn_nothing(tmp_path):
    """Curved models' relabellings are arbitrary turns: a doubtful answer between them is left as
    the search and tie-break gave it (the frame snap reports why), where boxes' frames still act."""
    from gsa.align import frame_snap
    from gsa.align.pipeline import AlignOptions, _Pair, align

    truth = random_sim3(np.random.default_rng(8))
    source = _ellipsoid((1.0, 0.6, 0.45), (0.9, 0.3, 0.0), 1, tmp_path)
    target = _ellipsoid((0.9, 0.65, 0.5), (0.8, 0.35, 0.0), 2, tmp_path).transformed(truth)
    pair = _Pair.build(source, target, AlignOptions(semantic="off"))
    assert not frame_snap.frames_supported(pair), [f.support for f in pair.normal_frames]
    result = align(source, target, AlignOptions(semantic="off"))
    m = result.diagnostics
    assert result.verdict.doubtful, "the pair was meant to be doubtful (a near-symmetric body)"
    assert m["frames"]["used"] is False and "not a frame" in m["frames"]["reason"], m["frames"]
    assert "frame_snap" not in m and "frame_choice" not in m
    boxes = _Pair.build(*_pair(tmp_path, truth), AlignOptions(semantic="off"))
    assert frame_snap.frames_supported(boxes), [f.support for f in boxes.normal_frames]


def test_the_geometry_keeps_an_answer_it_fits_clearly_better_than_a_turn_onto_the_frames(tmp_path):
    """Two samplings of one bench, one bent: the frames' rules are made for other instances,
    and a turn end for end that the surfaces fit clearly worse is refused; a turn the geometry
    cannot tell from the answer is left to the frames."""
    from gsa.align.frame_snap import geometry_prefers
    from gsa.align.pipeline import AlignOptions, _Pair
    from gsa.synth.variants import deform

    truth = random_sim3(np.random.default_rng(7))
    source = _bench((1.0, 0.15, 0.35), (0.12, 0.45, 0.35), 1, tmp_path)
    other = _bench((1.0, 0.15, 0.35), (0.12, 0.45, 0.35), 2, tmp_path)
    target = deform(other, np.random.default_rng(3)).transformed(truth)
    pair = _Pair.build(source, target, AlignOptions())
    centre = pair.src_frame.center
    half = axis_rotation(np.array([0.0, 1.0, 0.0]), np.pi)
    end_for_end = truth.compose(Sim3(1.0, half, centre - half @ centre))
    refused = geometry_prefers(pair, truth, end_for_end, {"colour_weight": 0.0})
    assert refused["answer_wins"] and refused["answer"] > refused["turned"]
    assert not geometry_prefers(pair, truth, truth, {"colour_weight": 0.0})["answer_wins"]
