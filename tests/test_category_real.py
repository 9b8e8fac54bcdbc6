"""The real-mesh cross-instance protocol: mesh sampling, the symmetry-aware judge, the table."""

from pathlib import Path

import numpy as np
import pytest

from benchmarks.category_real import (
    category_real_judge,
    category_real_pairs,
    format_category_real,
    instance_symmetries,
    per_class,
)
from gsa.geometry import axis_rotation
from gsa.sim3 import Sim3
from gsa.synth.meshes import find_meshes, load_mesh, mesh_to_gaussians


def _box_mesh(half: tuple[float, float, float]):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) * half
    faces = []
    for axis in range(3):
        for side in (-1, 1):
            quad = [i for i, c in enumerate(corners) if np.sign(c[axis]) == side]
            faces += [quad[:3], quad[1:]]
    return corners.astype(np.float32), np.array(faces, np.int32)


def _write_meshes(folder, shapes: dict[str, list[tuple]]):
    for category, halves in shapes.items():
        for i, half in enumerate(halves):
            v, f = _box_mesh(half)
            colours = (
                np.full((len(f), 3), np.nan, np.float16)
                if i % 2
                else np.random.default_rng(i).uniform(0, 1, (len(f), 3))
            )
            np.savez(folder / f"{category}_{i}.npz", V=v, F=f, C=colours.astype(np.float16))


def test_meshes_sample_on_the_surface_with_colours(tmp_path):
    _write_meshes(tmp_path, {"crate": [(1.0, 0.5, 0.25), (2.0, 1.0, 0.5)]})
    groups = find_meshes(tmp_path)
    assert list(groups) == ["crate"] and len(groups["crate"]) == 2
    mesh = load_mesh(groups["crate"][1])  # uncoloured: NaN colours become one grey
    model = mesh_to_gaussians(mesh, 3000, np.random.default_rng(0), floaters=0.1)
    assert len(model) == 3000
    surface = model.means[model.opacities > 0.5]
    # normalised: bounding-box diagonal 1, every surface point on a face of the box
    half = np.array([2.0, 1.0, 0.5]) / np.linalg.norm([4.0, 2.0, 1.0])
    on_face = np.isclose(np.abs(surface), half, atol=1e-5).any(axis=1)
    assert on_face.mean() > 0.99
    assert np.allclose(model.base_colors[model.opacities > 0.5], 0.62, atol=0.1)


def test_bad_meshes_are_refused(tmp_path):
    np.savez(tmp_path / "x_0.npz", V=np.zeros((3, 3), np.float32), F=np.array([[0, 1, 5]], np.int32))
    with pytest.raises(ValueError, match="outside V"):
        load_mesh(tmp_path / "x_0.npz")


def test_symmetries_are_measured_not_assumed():
    rng = np.random.default_rng(0)
    # a cylinder about y: turn-symmetric about y, half turns about x and z
    t, y = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-1, 1, 4000)
    cylinder = np.stack([0.3 * np.cos(t), y, 0.3 * np.sin(t)], 1)
    turns = instance_symmetries(cylinder)
    assert len(turns) > 300
    # an L-shaped set has no symmetry at all
    bar = np.stack([rng.uniform(0, 1, 2000), rng.uniform(0, 0.1, 2000), rng.uniform(0, 0.1, 2000)], 1)
    leg = np.stack([rng.uniform(0, 0.1, 1000), rng.uniform(0, 0.6, 1000), rng.uniform(0, 0.1, 1000)], 1)
    assert instance_symmetries(np.concatenate([bar, leg])) == []


def test_judge_accepts_a_symmetric_pose_and_keeps_the_strict_error(tmp_path):
    _write_meshes(tmp_path, {"crate": [(1.0, 0.5, 0.25), (1.2, 0.5, 0.3)]})
    ((label, make),) = category_real_pairs(tmp_path, quick=True, seed=0)
    source, target, truth = make()
    assert label == "crate-0-1"
    half_turn = Sim3(
        rotation=truth.rotation @ axis_rotation([0, 1, 0], np.pi), translation=truth.translation, scale=truth.scale
    )
    judged = category_real_judge(half_turn, truth, source, target)
    assert judged["rre_deg"] < 1.0 and judged["rre_strict_deg"] > 179.0
    wrong = Sim3(
        rotation=truth.rotation @ axis_rotation([1, 1, 0], 0.7), translation=truth.translation, scale=truth.scale
    )
    assert category_real_judge(wrong, truth, source, target)["rre_deg"] > 20.0


def test_table_reports_each_class():
    records = [
        {"category": "a", "rre_deg": 1.0, "doubtful": False},
        {"category": "a", "rre_deg": 90.0, "doubtful": True, "closest_alternative_rre_deg": 2.0},
        {"category": "b", "rre_deg": 3.0, "doubtful": False},
    ]
    per = per_class(records)
    assert per["a"]["success_rate"] == 0.5 and per["b"]["median_rre_deg"] == 3.0
    row = {
        "method": "GSA",
        "per_class": per,
        "success_rate": 2 / 3,
        "median_rre_deg": 3.0,
        "mean_rre_deg": 31.3,
        "seconds_per_pair": 1.0,
        "records": records,
        "flag_results": 3,
        "flagged": 1,
        "unflagged_success_rate": 1.0,
        "failures_flagged_rate": 1.0,
    }
    table = format_category_real([row])
    assert "50% (45.5°)" in table and "**67%**" in table and "1/1" in table


CATEGORY_DEV = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "category-dev"


def test_a_flipped_cross_instance_result_offers_the_truth_among_its_alternatives():
    """Two real bottles: the search's best pose is upside down (the other instance piles more
    surface together that way), flagged; the half turns of the chosen pose are offered, and
    one of them is the truth, so a person can pick it (before they were offered: the three
    next candidates, all 170° off)."""
    if not (CATEGORY_DEV / "bottle_1.npz").exists():
        pytest.skip(f"the shared real-mesh folder {CATEGORY_DEV} is absent (CI has it at ../shared/data)")
    from gsa.align import align

    make = dict(category_real_pairs(CATEGORY_DEV, quick=False, seed=0))["bottle-0-1"]
    source, target, truth = make()
    result = align(source, target)
    v = result.verdict

    def judged(transform: Sim3) -> float:
        return category_real_judge(transform, truth, source, target)["rre_deg"]

    offered = [a.transform for a in v.alternatives]
    errors = [judged(result.transform)] + [judged(t) for t in offered]
    assert min(errors) < 5.0, errors
    assert errors[0] < 5.0 or v.doubtful  # a wrong choice is flagged
    assert any(a.origin.startswith("flip:") for a in v.alternatives)
    # the verdict's list stays short: at most 8 poses beside the answers a later step replaced
    # ("before the frame snap", ...) and the relabellings the frame choice adds (24 at most)
    replaced = [a for a in v.alternatives if a.origin.startswith("before ")]
    relabellings = [a for a in v.alternatives if a.origin == "frame relabelling"]
    assert len(v.alternatives) - len(replaced) - len(relabellings) <= 8 and len(relabellings) <= 24


def test_a_large_symmetric_surface_is_judged_symmetric_against_its_dense_sampling():
    """A wide vase sampled densely, judged on a sparse sample: against the sample alone a
    perfect turn symmetry moves it by the sample's own spacing (> 1 % of the diagonal here);
    against the dense surface it does not."""
    rng = np.random.default_rng(3)
    n = 30000
    t, y = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1, 1, n)
    radius = 0.8 + 0.3 * np.sin(2.0 * y)  # wide, and not the same upside down
    surface = np.stack([radius * np.cos(t), y, radius * np.sin(t)], 1)
    sample = surface[rng.choice(n, 1500, replace=False)]
    assert len(instance_symmetries(sample)) < 300
    turns = instance_symmetries(sample, surface)
    assert len(turns) >= 359
    y_axis = np.array([0.0, 1.0, 0.0])
    assert all(np.allclose(g @ y_axis, y_axis) for g in turns[:359])
