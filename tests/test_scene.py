"""The scene path (gsa.align.scene, scene-scale registration): the scene test on rooms and objects, the path
itself on a small pair of harder room captures, the exposure estimate, and `--scene`."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from benchmarks.pairs import SCENE_HARD
from benchmarks.scene import scene_judge
from gsa.align import robust
from gsa.align import scene as S
from gsa.align.pipeline import AlignOptions, align
from gsa.geometry import axis_rotation
from gsa.io.ply import write_ply
from gsa.metrics import rre_deg, scale_error_pct
from gsa.sim3 import Sim3
from gsa.synth import make_object, make_scene, make_symmetric_object, random_sim3, scene_captures


@pytest.fixture(scope="module")
def room_pair():
    """Two harder captures (SCENE_HARD) of a generated room, ~150k Gaussians each."""
    scene = make_scene(seed=1801, n_gaussians=260_000)
    cap = scene_captures(scene, np.random.default_rng([0, 18, 1]), sizes=(150_000, 150_000), **SCENE_HARD)
    return cap


def _is_scene(model) -> bool:
    return S.scene_structure(S.scene_anchors(model, S.test_anchor_count(len(model), 2000))).is_scene


@pytest.mark.parametrize("seed", [1800, 1802])
def test_whole_rooms_pass_the_scene_test(seed):
    """Small rooms pass by their shell and the things inside it (not by size)."""
    room = make_scene(seed=seed, n_gaussians=150_000).transformed(random_sim3(np.random.default_rng(seed)))
    anchors = S.scene_anchors(room, 2000)
    st = S.scene_structure(anchors, gaussians=len(room))
    assert st.is_scene, st.to_dict()
    defaults = S.SceneOptions()
    assert st.shell_planes >= 4 and st.parts >= defaults.content_parts  # floor, ceiling and walls; furniture
    assert len(room) < defaults.scene_gaussians
    # The thresholds are the options': asking for more parts than the room holds fails it.
    stricter = S.SceneOptions(content_parts=st.parts + 1)
    assert not S.scene_structure(anchors, gaussians=len(room), options=stricter).is_room


def test_large_room_captures_pass_by_shell_and_size():
    scene = make_scene(seed=1803, n_gaussians=800_000)
    cap = scene_captures(scene, np.random.default_rng(5), sizes=(450_000, 450_000), **SCENE_HARD)
    choice = S.choose(cap.source, cap.target, "auto", True, 2000)
    assert choice.run, choice.to_dict()
    for side in ("source", "target"):
        assert choice.to_dict()["test"][side]["shell_planes"] >= S.SceneOptions().shell_planes


@pytest.mark.parametrize(
    "model",
    [
        lambda: make_object("bus", seed=3, n_gaussians=30_000),  # a box: a shell with nothing inside
        lambda: make_object("car", seed=1, n_gaussians=30_000),
        lambda: make_object("chair", seed=2, n_gaussians=3000),
        lambda: make_object("bus", seed=4, n_gaussians=3000, floaters=0.2),
        lambda: make_symmetric_object(704, 30_000),  # a square bottle: four large planes
        lambda: make_symmetric_object(705, 30_000),  # a square prism
    ],
)
def test_objects_fail_the_scene_test(model):
    m = model()
    for pose in (Sim3.identity(), random_sim3(np.random.default_rng(len(m)))):
        assert not _is_scene(m.transformed(pose))


def test_auto_takes_the_scene_path_for_rooms_only(room_pair):
    cap = room_pair
    choice = S.choose(cap.source, cap.target, "auto", True, 2000)
    assert set(choice.to_dict()["test"]) == {"source", "target"}
    car = make_object("car", seed=1, n_gaussians=20_000)
    off = S.choose(car, car.transformed(random_sim3(np.random.default_rng(1))), "auto", True, 2000)
    assert not off.run and "failed the scene test" in off.reason
    assert not S.choose(cap.source, cap.target, "auto", False, 2000).run  # learned features: object path
    assert S.choose(car, car, "on", False, 2000).run and not S.choose(cap.source, cap.target, "off", True, 2000).run


def test_scene_path_recovers_a_harder_room_pair(room_pair):
    cap = room_pair
    assert cap.gains[0] != cap.gains[1] and cap.wave is not None  # the harder captures
    result = align(cap.source, cap.target, AlignOptions(scene="on"))
    judged = scene_judge(result.transform, cap.truth, cap.source, cap.target)
    assert rre_deg(result.transform.rotation, cap.truth.rotation) < 0.5
    assert judged["translation_error_pct_extent"] < 0.5
    assert scale_error_pct(result.transform.scale, cap.truth.scale) < 0.5
    scene = result.diagnostics["scene"]
    assert scene["ran"] and scene["reason"] == "scene=on"
    assert scene["anchors"][0] > 2000 and max(scene["refine_cloud"]) <= S.SceneOptions().refine_cloud
    assert result.metrics["colour_weight"] > 0.5  # the exposures were brought together
    assert result.stages == ("coarse",) and result.fine is None
    assert {"inlier_fraction", "rms_residual", "confidence"} <= set(result.metrics)


def test_exposure_gains_are_found_pose_free(room_pair):
    cap = room_pair
    src = S.scene_anchors(cap.source, 4000)
    dst = S.scene_anchors(cap.target, 4000)
    gains = robust.exposure_gain(*robust.match_exposure(src, dst))
    truth = np.array(cap.gains[1]) / np.array(cap.gains[0])  # source colours into the target's exposure
    assert np.allclose(np.log2(gains), np.log2(truth), atol=0.2), (gains, truth)
    assert robust.exposure_gain(*robust.match_exposure(dst, dst)) == (1.0, 1.0, 1.0)


def test_scene_option_is_checked():
    with pytest.raises(ValueError, match="scene"):
        AlignOptions(scene="maybe")


def test_scene_options_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        S.SceneOptions().shell_planes = 2  # type: ignore[misc]


def test_object_path_reports_why_it_ran():
    car = make_object("car", seed=1, n_gaussians=5000)
    result = align(car, car.transformed(random_sim3(np.random.default_rng(2))), AlignOptions(scene="off"))
    assert result.diagnostics["scene"] == {"ran": False, "reason": "scene=off"}


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "gsa.cli", *map(str, args)], capture_output=True, text=True, timeout=300
    )


def test_cli_scene_flag(room_pair, tmp_path):
    cap = room_pair
    src, tgt = write_ply(cap.source, tmp_path / "a.ply"), write_ply(cap.target, tmp_path / "b.ply")
    ran = {}
    for flag in ("on", "off"):
        out = tmp_path / f"{flag}.json"
        r = _cli("align", src, tgt, "--scene", flag, "--out", out, "--quiet")
        assert r.returncode == 0, r.stderr
        data = json.loads(out.read_text())
        ran[flag] = data["metrics"]["scene"]["ran"]
        assert data["metrics"]["scene"]["reason"] == f"scene={flag}"
        if flag == "on":
            assert "scene path   scene=on" in r.stdout
            est = Sim3.from_matrix(np.array(data["transform"]))
            assert rre_deg(est.rotation, cap.truth.rotation) < 0.5
    assert ran == {"on": True, "off": False}
    bad = _cli("align", src, tgt, "--scene", "maybe", "--out", tmp_path / "x.json")
    assert bad.returncode != 0 and "--scene" in bad.stderr


def test_a_doubtful_scene_answer_is_weighed_against_the_object_paths(room_pair):
    """Objects pass the scene test too (a mug, a car with its seats): a doubtful scene answer
    meets the object path's, the better fit wins by more than a tie, and the other is offered."""
    from dataclasses import replace

    from gsa.align.pipeline import _second_opinion

    cap = room_pair
    rooms = align(cap.source, cap.target, AlignOptions(scene="on"))
    assert rre_deg(rooms.transform.rotation, cap.truth.rotation) < 2.0
    centre = cap.source.means.mean(0).astype(np.float64)
    turn = axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(90.0))
    wrong = rooms.transform.compose(Sim3(1.0, turn, centre - turn @ centre))
    objects = replace(rooms, transform=wrong, metrics={"alternatives": [], "doubtful": True})
    kept = _second_opinion(cap.source, cap.target, AlignOptions(), rooms, objects)
    assert kept.transform is rooms.transform and kept.verdict.doubtful
    assert kept.diagnostics["scene"]["second_opinion"]["chosen"] == "scene path"
    offered = [a.details for a in kept.verdict.alternatives if a.origin == "object path"]
    assert len(offered) == 1 and np.allclose(offered[0]["transform"], wrong.matrix())
    # the other way round: the object path's better fit replaces a wrong scene answer
    swapped = _second_opinion(cap.source, cap.target, AlignOptions(), objects, replace(rooms, metrics={}, verdict=None))
    assert swapped.diagnostics["scene"]["second_opinion"]["chosen"] == "object path"
    assert rre_deg(swapped.transform.rotation, cap.truth.rotation) < 2.0
    assert any(a.origin == "scene path" for a in swapped.verdict.alternatives)
