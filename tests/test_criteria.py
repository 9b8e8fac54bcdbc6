"""The criteria in force reach every stage: a criterion changed through
AlignOptions.criteria is the one the search, the refinement, the verdict, the frame snap, the
relabelling choice, the open ends, the guidance and the scene path decide by. Each stage is
stopped at the call that reads it (a recording stand-in raises Seen), so no stage runs whole."""

from dataclasses import replace

import numpy as np
import pytest

from gsa import manhattan
from gsa.align import frame_snap, open_ends, pipeline, robust, scene
from gsa.align.criteria import Criteria
from gsa.align.guided import GuidanceCriteria
from gsa.align.open_ends import OpenEndCriteria
from gsa.align.pipeline import AlignOptions, _Hypothesis, _Pair
from gsa.align.scene import SceneOptions
from gsa.align.scene import path as scene_path
from gsa.geometry import axis_rotation
from gsa.sim3 import Sim3
from tests.test_open_ends import _vessel

CRITERIA = Criteria(
    pose=replace(robust.PoseCriteria(), truncation=0.123, score_tie=0.0456),
    search=replace(robust.SearchOptions(), refine_points=321),
    refine=replace(robust.RefineCriteria(), whole_overlap=0.5, coincident_share=0.6),
    verdict=replace(robust.VerdictCriteria(), confidence_threshold=0.99),
    guidance=replace(GuidanceCriteria(), local_turn_deg=7.0),
    scene=replace(SceneOptions(), scene_gaussians=1234, scene_anchors=2345),
    open_ends=replace(OpenEndCriteria(), slab=0.05),
)


class Seen(Exception):
    """Raised by a recording stand-in: the stage reached the call, with what it passed."""


def _stop(seen: list, pick):
    def record(*args, **kwargs):
        seen.append(pick(*args, **kwargs))
        raise Seen

    return record


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    folder = tmp_path_factory.mktemp("vessels")
    source = _vessel(0.5, 1.0, 0.2, 5, folder)
    target = _vessel(0.35, 1.2, 0.15, 6, folder).transformed(Sim3(1.3, np.eye(3), np.array([0.2, 0.0, 0.1])))
    return source, target


@pytest.fixture
def pair(models):
    return _Pair.build(*models, AlignOptions(criteria=CRITERIA, semantic="off", learned="off"))


def test_the_default_criteria_are_the_stages_own_defaults():
    k = AlignOptions().criteria
    assert k == Criteria() and k.pose == robust.PoseCriteria() and k.scene == SceneOptions()
    assert k.refinement(rigid=True) == robust.RIGID_REFINE and k.refinement(rigid=False) == robust.RefineCriteria()
    options = k.search_options(AlignOptions().search_rotations, 0)
    assert options == robust.SearchOptions()
    with pytest.raises(ValueError, match="search_rotations"):
        Criteria(search=replace(robust.SearchOptions(), rotations=100))
    with pytest.raises(ValueError, match="Criteria.pose"):
        Criteria(search=replace(robust.SearchOptions(), criteria=CRITERIA.pose))
    with pytest.raises(ValueError, match="criteria"):
        AlignOptions(criteria={"pose": {}})  # a job's JSON never reaches the criteria


def test_the_search_and_the_refinement_take_the_criteria_in_force(pair, monkeypatch):
    seen: list = []
    monkeypatch.setattr(robust, "global_search", _stop(seen, lambda src, dst, starts, options, **kw: options))
    with pytest.raises(Seen):
        pair.anchor_search.search(None)
    assert seen[-1].criteria is CRITERIA.pose and seen[-1].refine_points == 321
    assert seen[-1].rotations == pair.opts.search_rotations
    monkeypatch.setattr(robust, "refine", _stop(seen, lambda *a, criteria=None, **kw: criteria))
    with pytest.raises(Seen):
        pair.refinement.refine_global(Sim3.identity(), None)
    assert seen[-1] is CRITERIA.refine
    rigid = replace(pair, opts=replace(pair.opts, rigid=True))
    with pytest.raises(Seen):
        rigid.refinement.refine_global(Sim3.identity(), None)
    assert seen[-1] == replace(CRITERIA.refine, deformable=False)


def test_the_verdict_and_the_guidance_take_the_criteria_in_force(pair, monkeypatch):
    seen: list = []
    real = robust.verdict

    def verdict(final, search, coincide=None, criteria=None, offer_always=False):
        seen.append(criteria)
        return real(final, search, coincide, criteria, offer_always)

    monkeypatch.setattr(robust, "verdict", verdict)
    assert pair.judge.verdict(Sim3.identity(), None)["doubtful"]  # confidence_threshold 0.99
    assert seen == [CRITERIA.verdict]
    turns = pipeline.guided.local_turns(CRITERIA.guidance)
    angles = [np.degrees(np.arccos(np.clip((np.trace(t) - 1) / 2, -1, 1))) for t in turns]
    assert np.allclose(angles, 7.0)
    monkeypatch.setattr(pipeline.guided, "local_turns", _stop(seen, lambda criteria=None: criteria))
    with pytest.raises(Seen):
        pair.anchor_search.local_start(Sim3.identity(), None, lambda pose: True)
    assert seen[-1] is CRITERIA.guidance


def test_the_frame_snap_the_choice_and_the_open_ends_take_the_criteria_in_force(pair, monkeypatch):
    src, dst = pair.anchors()
    best = _Hypothesis("test", pair.src_frame, Sim3.identity())
    rotation = manhattan.relabellings(*pair.normal_frames)[0]
    answer = manhattan.turned_onto(Sim3.identity(), rotation, src.center) @ Sim3(
        1.0, axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(8.0)), np.zeros(3)
    )
    seen: list = []
    monkeypatch.setattr(manhattan, "fit_shift", _stop(seen, lambda pose, p, q, reach: reach))
    said: list = []

    def upside_down(points, axis, criteria=None):  # the ends say the answer maps open onto closed
        said.append(axis)
        return axis if len(said) == 1 else -(answer.rotation @ said[0])

    monkeypatch.setattr(open_ends, "open_direction", upside_down)
    for stage in (frame_snap.snap_to_frames, frame_snap.choose_relabelling, open_ends.turn_open_ends):
        with pytest.raises(Seen):
            stage(pair, best, answer, {"alternatives": []})
    assert np.allclose(seen, CRITERIA.pose.truncation * dst.radius)
    monkeypatch.setattr(open_ends, "open_direction", _stop(seen, lambda points, axis, criteria=None: criteria))
    with pytest.raises(Seen):
        open_ends.turn_open_ends(pair, best, answer, {})
    assert seen[-1] is CRITERIA.open_ends
    # the pipeline's tests of other instances and whole models read the refinement's criteria
    metrics = {"overlap_estimate": 0.55, "coincident_share": 0.55, "alternatives": []}
    assert frame_snap.other_instances(metrics, CRITERIA.refine) and not frame_snap.other_instances(metrics)
    assert frame_snap.whole_models(metrics, CRITERIA.refine) and not frame_snap.whole_models(metrics)
    calls: list = []
    for name in ("snap_to_frames", "choose_relabelling"):
        monkeypatch.setattr(frame_snap, name, lambda p, b, t, m, name=name: calls.append(name) or (t, m))
    monkeypatch.setattr(open_ends, "turn_open_ends", lambda p, b, t, m: calls.append("open_ends") or (t, m))
    monkeypatch.setattr(frame_snap, "frames_supported", lambda p: True)
    pipeline._doubtful_search_answer(pair, best, None, answer, metrics, {}, None)
    assert calls == ["snap_to_frames", "choose_relabelling", "open_ends"]


def test_the_scene_test_and_path_take_the_criteria_in_force(models, monkeypatch):
    source, target = models
    opts = AlignOptions(criteria=CRITERIA, semantic="off", learned="off")
    seen: list = []
    monkeypatch.setattr(scene, "choose", _stop(seen, lambda *a, options=None, **kw: options))
    with pytest.raises(Seen):
        pipeline.align(source, target, opts)
    assert seen[-1] is CRITERIA.scene
    monkeypatch.setattr(scene_path, "scene_anchors", _stop(seen, lambda model, count, seed, o: (count, o)))
    with pytest.raises(Seen):
        scene.align_scene(source, target, opts, scene.SceneChoice(True, "test"))
    assert seen[-1] == (2345, CRITERIA.scene)
    choice = scene.SceneChoice(True, "test", *[scene.Structure(3, 0.5, 3, 0.1, [], gaussians=2000) for _ in range(2)])
    result = pipeline.AlignmentResult(Sim3.identity(), None, "none", metrics={"doubtful": True})
    assert pipeline._object_path_too(AlignOptions(), choice, result)
    assert not pipeline._object_path_too(opts, choice, result)  # scene_gaussians 1234: these are sites
