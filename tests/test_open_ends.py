"""Which way up two spinning models are: a container's open end (a ring) against its filled
foot (a disk), read on the sampled Gaussians; an upside-down doubtful answer between two such
instances is turned end for end, a right one is left alone."""

import numpy as np

from gsa.align import open_ends
from gsa.geometry import axis_rotation, rotation_distance_deg
from gsa.sim3 import Sim3
from gsa.synth import random_sim3
from gsa.synth.meshes import load_mesh, mesh_to_gaussians

SEGMENTS = 96


def _vessel(radius: float, height: float, neck: float, seed: int, folder, foot: bool = True, lid: bool = False):
    """A cylinder with a narrower neck on top, turning freely about y; `foot` closes its bottom
    with a disk, `lid` its neck."""
    t = np.linspace(0.0, 2.0 * np.pi, SEGMENTS, endpoint=False)
    rings = [(radius, 0.0), (radius, height), (neck, height), (neck, 1.3 * height)]
    vertices = [[r * np.cos(a), y, r * np.sin(a)] for r, y in rings for a in t]
    faces = []
    for ring in range(len(rings) - 1):
        for k in range(SEGMENTS):
            a, b = ring * SEGMENTS + k, ring * SEGMENTS + (k + 1) % SEGMENTS
            faces += [[a, b, a + SEGMENTS], [b, b + SEGMENTS, a + SEGMENTS]]
    if foot:
        vertices.append([0.0, 0.0, 0.0])
        faces += [[len(vertices) - 1, (k + 1) % SEGMENTS, k] for k in range(SEGMENTS)]
    if lid:
        vertices.append([0.0, 1.3 * height, 0.0])
        top = (len(rings) - 1) * SEGMENTS
        faces += [[len(vertices) - 1, top + k, top + (k + 1) % SEGMENTS] for k in range(SEGMENTS)]
    path = folder / f"vessel{seed}_0.npz"
    np.savez(path, V=np.array(vertices, np.float32), F=np.array(faces, np.int32))
    return mesh_to_gaussians(load_mesh(path), 6000, np.random.default_rng(seed), floaters=0.02)


def _surface(model) -> np.ndarray:
    return model.means[model.opacities > 0.5].astype(np.float64)


def test_the_open_end_of_a_vessel_is_read_whichever_way_its_axis_points(tmp_path):
    vase = _surface(_vessel(0.5, 1.0, 0.2, 1, tmp_path))
    up = np.array([0.0, 1.0, 0.0])
    for axis in (up, -up):
        assert np.allclose(open_ends.open_direction(vase, axis), up)
    turned = random_sim3(np.random.default_rng(2))
    assert np.allclose(open_ends.open_direction(turned.apply(vase), turned.rotation @ up), turned.rotation @ up)
    # closed at both ends (a capped bottle) or open at both (a tube): the ends do not say
    capped = _surface(_vessel(0.5, 1.0, 0.2, 3, tmp_path, lid=True))
    tube = _surface(_vessel(0.5, 1.0, 0.2, 4, tmp_path, foot=False))
    assert open_ends.open_direction(capped, up) is None
    assert open_ends.open_direction(tube, up) is None


def _pair(tmp_path, truth: Sim3, **target_shape):
    from gsa.align.pipeline import _Pair
    from gsa.align.types import AlignOptions

    source = _vessel(0.5, 1.0, 0.2, 5, tmp_path)
    target = _vessel(0.35, 1.2, 0.15, 6, tmp_path, **target_shape).transformed(truth)
    return _Pair.build(source, target, AlignOptions(semantic="off"))


def _flipped_about(centre: np.ndarray) -> Sim3:
    flip = axis_rotation([1, 0, 0], np.pi)
    return Sim3(1.0, flip, centre - flip @ centre)


def _axis_error_deg(pose: Sim3, truth: Sim3) -> float:
    up = np.array([0.0, 1.0, 0.0])
    return float(np.degrees(np.arccos(np.clip((pose.rotation @ up) @ (truth.rotation @ up), -1.0, 1.0))))


def test_an_upside_down_answer_between_two_vessels_is_turned_end_for_end(tmp_path):
    from gsa.align.pipeline import _Hypothesis

    truth = random_sim3(np.random.default_rng(7))
    pair = _pair(tmp_path, truth)
    upside_down = truth @ _flipped_about(_surface(pair.source).mean(0))  # as a search leaves it: centroid on centroid
    assert _axis_error_deg(upside_down, truth) > 179.0
    best = _Hypothesis("test", pair.src_frame, upside_down)
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    turned, updated = open_ends.turn_open_ends(pair, best, upside_down, metrics)
    assert updated["open_ends"]["turned"], updated["open_ends"]
    assert _axis_error_deg(turned, truth) < 3.0
    assert updated["doubtful"] is True
    assert updated["alternatives"][0]["origin"] == "before the open-end turn"
    assert np.allclose(updated["alternatives"][0]["transform"], upside_down.matrix())
    # the turned pose lands on the target, not beside it: centroid on centroid, to a tenth of its size
    target_points = pair.dst_pts[pair.target.opacities > 0.5]
    size = np.linalg.norm(np.ptp(target_points, axis=0))
    gap = np.linalg.norm(turned.apply(_surface(pair.source).mean(0)) - target_points.mean(0))
    assert gap < 0.1 * size, (gap, size)
    # the right way up it is left as it is
    kept, report = open_ends.turn_open_ends(pair, best, truth, metrics)
    assert kept is truth and report["open_ends"]["turned"] is False and report["open_ends"]["agreement"] > 0.99


def test_ends_that_do_not_say_leave_the_answer(tmp_path):
    from gsa.align.pipeline import _Hypothesis

    truth = random_sim3(np.random.default_rng(8))
    pair = _pair(tmp_path, truth, lid=True)  # the target capped: its ends do not say which is open
    upside_down = truth @ _flipped_about(_surface(pair.source).mean(0))
    best = _Hypothesis("test", pair.src_frame, upside_down)
    metrics = {"doubtful": True, "overlap_estimate": 0.95, "coincident_share": 0.2, "alternatives": []}
    kept, report = open_ends.turn_open_ends(pair, best, upside_down, metrics)
    assert kept is upside_down and report["open_ends"]["target_open"] is None
    assert rotation_distance_deg(kept.rotation, truth.rotation) > 179.0
