"""Generated rooms and their two captures (gsa.synth.scenes, scene-scale registration), and the `scene`
bench protocol on a tiny pair."""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest
from scipy.spatial import cKDTree

from benchmarks import pairs as pairs_mod
from benchmarks import peers as peers_mod
from benchmarks import protocols as P
from benchmarks.scene import scene_judge
from gsa.geometry import euler_xyz
from gsa.sim3 import Sim3
from gsa.synth import make_scene, scene_captures

ARRAYS = ("means", "quats", "log_scales", "opacity_logits", "sh")


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=5, n_gaussians=60_000)


def _spacing(model) -> float:
    d, _ = cKDTree(model.means).query(model.means[::37], k=2)
    return float(np.median(d[:, 1]))


def test_deterministic_by_seed(scene):
    again = make_scene(seed=5, n_gaussians=60_000)
    for name in ARRAYS:
        assert np.array_equal(getattr(scene, name), getattr(again, name)), name
    resampled = make_scene(seed=5, n_gaussians=60_000, sample_seed=99)
    other = make_scene(seed=6, n_gaussians=60_000)
    assert resampled.metadata["room"] == scene.metadata["room"]  # the same room ...
    assert not np.array_equal(resampled.means, scene.means)  # ... sampled elsewhere
    assert other.metadata["room"] != scene.metadata["room"]


def test_a_sample_seed_samples_the_same_surfaces(scene):
    resampled = make_scene(seed=5, n_gaussians=60_000, sample_seed=99)
    d, _ = cKDTree(scene.means).query(resampled.means[::11])
    assert np.median(d) < 2 * _spacing(scene)


@pytest.mark.parametrize("n", [1000, 12_345, 60_001])
def test_requested_size(n):
    model = make_scene(seed=1, n_gaussians=n, ceiling=n % 2 == 0)
    assert len(model) == n
    model.validate()


def test_room_contents(scene):
    meta = scene.metadata
    w, d, h = meta["room"]
    lo, hi = scene.means.min(0), scene.means.max(0)
    assert lo[2] >= -1e-3 and hi[2] <= h + 1e-5  # floor to ceiling (objects: within a sample spacing)
    assert np.isclose(meta["extent"], np.linalg.norm([w, d, h]))
    assert len(meta["objects"]) == 6 and meta["clutter"] == 12
    assert {o["kind"] for o in meta["openings"]} == {"window", "door"}
    on_floor = np.abs(scene.means[:, 2]) < 1e-4
    assert 0.05 < on_floor.mean() < 0.6
    # furniture and clutter stand inside the room, above the floor
    inside = (scene.means[:, 2] > 0.02) & (scene.means[:, 2] < h - 0.02)
    inner = inside & (scene.means[:, 0] > 0.05) & (scene.means[:, 0] < w - 0.05)
    inner &= (scene.means[:, 1] > 0.05) & (scene.means[:, 1] < d - 0.05)
    assert inner.mean() > 0.1


def test_a_million_gaussians_build_in_float32_without_whole_float64_copies():
    tracemalloc.start()
    try:
        model = make_scene(seed=2, n_gaussians=1_000_000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(model) == 1_000_000
    for name in ARRAYS:
        assert getattr(model, name).dtype == np.float32, name
    final = sum(getattr(model, name).nbytes for name in ARRAYS)
    # A float64 copy of every array alone would be 2x the model on top of it.
    assert peak < 4 * final, (peak / 1e6, final / 1e6)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_overlap_in_range_and_measured(scene, seed):
    cap = scene_captures(scene, np.random.default_rng(seed))
    assert 0.5 <= cap.overlap <= 0.8
    proj = scene.means.astype(np.float64) @ cap.direction
    in_src, in_dst = proj >= cap.cuts[0] - 1e-6, proj <= cap.cuts[1] + 1e-6
    both, union = np.count_nonzero(in_src & in_dst), np.count_nonzero(in_src | in_dst)
    assert cap.overlap == pytest.approx(both / union, abs=1e-3)
    assert cap.overlap_of_source == pytest.approx(both / np.count_nonzero(in_src), abs=1e-3)
    assert cap.overlap_of_target == pytest.approx(both / np.count_nonzero(in_dst), abs=1e-3)
    assert in_src[cap.source_index].all()
    second = cap.target_sampling.means.astype(np.float64) @ cap.direction
    assert (second[cap.target_index] <= cap.cuts[1] + 1e-6).all()
    assert abs(cap.direction[2]) < 1e-12 and np.isclose(np.linalg.norm(cap.direction), 1.0)


def test_captures_differ_in_density_and_size(scene):
    cap = scene_captures(scene, np.random.default_rng(4), sizes=(20_000, 30_000))
    assert len(cap.source_index) == 20_000 and len(cap.target_index) == 30_000
    assert len(cap.source) == 20_000 + cap.floaters[0]


def test_truth_maps_captures_back_onto_the_scene(scene):
    cap = scene_captures(scene, np.random.default_rng(7), independent=False)
    n_src, n_dst = len(cap.source_index), len(cap.target_index)
    extent = scene.metadata["extent"]
    back = cap.pose_target.inverse().apply(cap.target.means[:n_dst])
    assert np.abs(back - scene.means[cap.target_index]).max() < 1e-4 * extent
    # The relative truth carries each shared Gaussian from the source to the target.
    shared, i_src, i_dst = np.intersect1d(cap.source_index, cap.target_index, return_indices=True)
    assert len(shared) > 100
    moved = cap.truth.apply(cap.source.means[:n_src][i_src])
    assert np.abs(moved - cap.target.means[:n_dst][i_dst]).max() < 1e-4 * cap.extent_target
    for pose in (cap.pose_source, cap.pose_target):
        assert 0.2 <= pose.scale <= 5.0
    assert cap.extent_target == pytest.approx(extent * cap.pose_target.scale)
    assert cap.target.metadata["scene_extent"] == pytest.approx(cap.extent_target)


def test_independent_target_lies_on_the_scene(scene):
    cap = scene_captures(scene, np.random.default_rng(8))
    n_dst = len(cap.target_index)
    assert not np.isin(cap.target.means[:n_dst], cap.source.means).all(axis=1).any()
    tree = cKDTree(scene.means)
    d_true, _ = tree.query(cap.pose_target.inverse().apply(cap.target.means[:n_dst:7]))
    d_wrong, _ = tree.query(cap.pose_source.inverse().apply(cap.target.means[:n_dst:7]))
    assert np.median(d_true) < 2 * _spacing(scene)
    assert np.median(d_wrong) > 20 * _spacing(scene)


def test_floaters_are_appended_faint_and_inside(scene):
    cap = scene_captures(scene, np.random.default_rng(9))
    for model, index, n_float, pose in (
        (cap.source, cap.source_index, cap.floaters[0], cap.pose_source),
        (cap.target, cap.target_index, cap.floaters[1], cap.pose_target),
    ):
        assert n_float == len(model) - len(index) == model.metadata["floaters"]
        assert 0.01 <= n_float / len(index) <= 0.05 + 1e-3
        tail = model.opacities[len(index) :]
        assert tail.max() <= 0.3 + 1e-6 and np.median(model.opacities[: len(index)]) > 0.6
        surface = pose.inverse().apply(model.means[: len(index)])
        floating = pose.inverse().apply(model.means[len(index) :])
        assert (floating >= surface.min(0) - 1e-3).all() and (floating <= surface.max(0) + 1e-3).all()


def test_bad_overlap_range_is_an_error(scene):
    with pytest.raises(ValueError, match="overlap"):
        scene_captures(scene, np.random.default_rng(0), overlap=(0.5, 1.0))


def test_scene_judge():
    rng = np.random.default_rng(0)
    source = make_scene(seed=1, n_gaussians=2000)
    truth = Sim3(2.0, euler_xyz(np.radians([30.0, -40.0, 100.0])), np.array([1.0, 2.0, 3.0]))
    target = source.transformed(truth)
    target.metadata["scene_extent"] = 2.0 * source.metadata["extent"]
    exact = scene_judge(truth, truth, source, target)
    assert exact["scene_success"] and exact["translation_error_pct_extent"] < 1e-9
    shift = 0.03 * target.metadata["scene_extent"] * rng.normal(size=3)
    shift *= 0.03 * target.metadata["scene_extent"] / np.linalg.norm(shift)
    off = scene_judge(Sim3(truth.scale, truth.rotation, truth.translation + shift), truth, source, target)
    assert off["translation_error_pct_extent"] == pytest.approx(3.0) and not off["scene_success"]
    turned = Sim3(truth.scale, truth.rotation @ euler_xyz(np.radians([0.0, 0.0, 3.0])), truth.translation)
    assert not scene_judge(turned, truth, source, target)["scene_success"]


def test_scene_protocol_runs(monkeypatch, tmp_path, capsys):
    # The baseline captures: 6000 Gaussians are too few for SCENE_HARD (tests/test_scene.py has those).
    monkeypatch.setattr(P, "scene_pairs", lambda quick, seed: pairs_mod.scene_pairs(quick, seed, 1, 6000, hard=False))
    P.run_protocols(["scene"], quick=True, out=str(tmp_path), peers=["icp"])
    text = capsys.readouterr().out
    assert "success (RRE<2°, t<2% extent)" in text and "max peak RSS (MB)" in text
    rows = {r["method"]: r for r in json.loads((tmp_path / "scene.json").read_text())["rows"]}
    assert set(rows) == {P.GSA_COARSE, peers_mod.PlainICP.label}
    for row in rows.values():
        rec = row["records"][0]
        assert rec["peak_rss_mb"] > 0 and rec["peak_growth_mb"] >= 0
        assert 0.5 <= rec["overlap"] <= 0.8
        assert rec["source_gaussians"] > 6000 and rec["target_gaussians"] > 6000  # with floaters
        assert row["scene_success_rate"] == float(rec["scene_success"])
    gsa = rows[P.GSA_COARSE]
    assert gsa["scene_success_rate"] == 1.0 and gsa["median_translation_error_pct_extent"] < 2.0


def test_harder_captures(scene):
    """SCENE_HARD's options: each changes the captures the way it says (the harder scene data)."""
    plain = scene_captures(scene, np.random.default_rng(3), sizes=(15_000, 15_000))
    hard = scene_captures(
        scene,
        np.random.default_rng(3),
        sizes=(15_000, 15_000),
        exposure=0.5,
        white_balance=0.1,
        falloff=2.0,
        wavy=0.05,
        holes=3,
        no_ceiling=1.0,
    )
    h = scene.metadata["room"][2]
    for cap in (plain, hard):
        assert len(cap.source_index) == len(cap.target_index) == 15_000
    # no ceiling: not one Gaussian of either capture on it; the plain captures have some
    assert hard.no_ceiling == (True, True)
    assert (scene.means[plain.source_index, 2] > h - 1e-3).any()
    assert not (scene.means[hard.source_index, 2] > h - 1e-3).any()
    assert not (hard.target_sampling.means[hard.target_index, 2] > h - 1e-3).any()
    assert min(hard.holed) > 0 and plain.holed == (0, 0)
    # exposure: the colours are the plain DC under the recorded linear gains
    assert plain.gains == ((1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    g = np.array(hard.gains[0])
    assert not np.allclose(g, 1.0) and np.all((g > 2**-0.5 * 0.89) & (g < 2**0.5 * 1.11))
    rows = slice(0, len(hard.source_index))
    c_plain = np.clip(0.5 + 0.28209479177387814 * scene.sh[hard.source_index, 0, :], 0, 1)
    lin = np.where(c_plain <= 0.04045, c_plain / 12.92, ((c_plain + 0.055) / 1.055) ** 2.4)
    c_hard = hard.source.base_colors[rows]
    lin_hard = np.where(c_hard <= 0.04045, c_hard / 12.92, ((c_hard + 0.055) / 1.055) ** 2.4)
    unclipped = np.all(lin * g < 0.98, axis=1)
    assert np.allclose(lin_hard[unclipped], (lin * g)[unclipped], atol=2e-3)
    # wavy cut: the source's lowest projection varies along the cut by about the wave
    amp, wavelength, phase = hard.wave
    assert amp == pytest.approx(0.05 * scene.metadata["extent"]) and 0.5 <= wavelength / scene.metadata["extent"] <= 1
    pts = scene.means.astype(np.float64)
    cut = pts @ hard.direction + amp * np.sin(
        2 * np.pi * (pts @ np.array([-hard.direction[1], hard.direction[0], 0])) / wavelength + phase
    )
    assert (cut[hard.source_index] >= hard.cuts[0] - 1e-4).all()
    assert (pts[hard.source_index] @ hard.direction).min() < hard.cuts[0] - 0.5 * amp  # a plane would not hold them
    # falloff: near the scanner the capture is denser than its half of the room
    scanner = np.array(hard.scanners[0])
    d = np.linalg.norm(pts[hard.source_index] - scanner, axis=1)
    d_half = np.linalg.norm(pts[cut >= hard.cuts[0]] - scanner, axis=1)
    assert np.median(d) < 0.85 * np.median(d_half)
