"""The learned canonical head's route: the closed-form canonical fit, the head's file, `gsa orient`,
and the learned decision in a doubtful alignment."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gsa.align import learned
from gsa.align.orient import FRONT, UP, OrientCriteria, OrientResult, fit_canonical, relative_pose
from gsa.align.pipeline import AlignOptions, align
from gsa.cli import main
from gsa.features import nocs
from gsa.features.nocs import CanonicalHead, CanonicalPatches, load_head, save_head
from gsa.features.vit import WeightsError
from gsa.io import read_model, write_model
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3


def _patches(rotation: np.ndarray, n: int, outliers: float, rng) -> tuple[CanonicalPatches, Sim3]:
    """Patches whose canonical coordinates are truth(points) plus noise, a share of them wrong;
    truth scales the points' extent to the canonical frame's unit diagonal."""
    points = rng.normal(0, 2.0, (n, 3)) + rng.normal(0, 5, 3)
    diagonal = np.linalg.norm(np.percentile(points, 99, axis=0) - np.percentile(points, 1, axis=0))
    truth = Sim3(1.0 / diagonal, rotation, np.zeros(3))
    truth = Sim3(truth.scale, rotation, -truth.apply(points.mean(0)))
    coords = truth.apply(points) + rng.normal(0, 0.01, (n, 3))
    bad = rng.uniform(size=n) < outliers
    coords[bad] = rng.uniform(-0.5, 0.5, (bad.sum(), 3))
    return CanonicalPatches(points, coords, np.full(n, 0.05), np.zeros(n, int)), truth


def test_fit_recovers_the_canonical_pose_through_outliers():
    rng = np.random.default_rng(3)
    patches, truth = _patches(random_sim3(rng).rotation, 600, 0.4, rng)
    result = fit_canonical(patches)
    assert rre_deg(result.transform.rotation, truth.rotation) < 1.0
    assert abs(result.transform.scale / truth.scale - 1) < 0.02
    assert np.allclose(result.up, truth.rotation.T @ UP, atol=0.02)
    assert np.allclose(result.front, truth.rotation.T @ FRONT, atol=0.02)
    assert result.confident and 0.5 < result.inlier_share < 0.7


def test_fit_of_noise_is_not_confident():
    rng = np.random.default_rng(4)
    p = CanonicalPatches(rng.normal(size=(400, 3)), rng.uniform(-0.5, 0.5, (400, 3)), np.ones(400), np.zeros(400, int))
    assert not fit_canonical(p, OrientCriteria()).confident


def test_relative_pose_goes_through_the_canonical_frame():
    rng = np.random.default_rng(5)
    (pa, a), (pb, b) = (_patches(random_sim3(rng).rotation, 300, 0.0, rng) for _ in range(2))
    fa, fb = fit_canonical(pa), fit_canonical(pb)
    rel = relative_pose(fa, fb)  # x_b = rel(x_a) where both land on one canonical point
    x = rng.normal(size=(5, 3))
    assert np.allclose(b.apply(rel.apply(x)), a.apply(x), atol=0.01)


def test_head_file_round_trip_and_bad_files(tmp_path):
    head = CanonicalHead(embed_dim=32, hidden=16, heads=2, depth=1)
    path = save_head(head, tmp_path / "h.pt", {"command": "test"})
    loaded = load_head(path)
    x = torch.randn(2, 4, 4, 32)
    assert torch.allclose(loaded(x), head.half().float()(x), atol=1e-4)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="cannot read"):
        load_head(tmp_path / "bad.pt")
    with pytest.raises(WeightsError, match="does not exist"):
        load_head(tmp_path / "missing.pt")


@pytest.mark.semantic
def test_orient_command_writes_up_front_and_the_turned_model(tmp_path, capsys):
    """The command's plumbing with a head of random weights (no trained head is shipped; see
    gsa.features.nocs): unit, orthogonal up and front in the file's coordinates, the transform
    that takes them to +Y and +Z, and the turned copy written."""
    torch.manual_seed(0)
    head = save_head(CanonicalHead(), tmp_path / "h.pt", {"command": "python -m training.train_head (test)"})
    model = make_object("chair", seed=1, n_gaussians=8_000, sample_seed=2)
    write_model(model, tmp_path / "m.ply")
    args = ["orient", str(tmp_path / "m.ply"), "--head", str(head), "--views", "6"]
    code = main([*args, "--out", str(tmp_path / "o.json"), "--aligned-out", str(tmp_path / "up.ply")])
    assert code == 0
    out = json.loads((tmp_path / "o.json").read_text())
    up, front = np.asarray(out["up"]), np.asarray(out["front"])
    assert np.isclose(np.linalg.norm(up), 1.0) and np.isclose(np.linalg.norm(front), 1.0)
    assert abs(up @ front) < 1e-6
    rot = np.asarray(out["transform"]["rotation"])
    assert np.allclose(rot @ up, UP, atol=1e-6) and np.allclose(rot @ front, FRONT, atol=1e-6)
    assert 0.0 <= out["confidence"] <= 1.0 and out["head"].startswith("python -m training.train_head")
    turned = read_model(tmp_path / "up.ply")
    assert len(turned) == len(model)
    # turned about its centre with its own scale: the spread of the points is unchanged
    assert np.isclose(np.linalg.norm(turned.means.std(0)), np.linalg.norm(model.means.std(0)), rtol=1e-4)
    assert json.loads(capsys.readouterr().out)["confidence"] == out["confidence"]


def test_orient_without_a_head_says_how_to_get_one(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("GSA_CANONICAL_HEAD", raising=False)
    monkeypatch.setattr(nocs, "SHIPPED_HEAD", tmp_path / "none.pt")
    write_model(make_object("car", seed=0, n_gaussians=2000), tmp_path / "m.ply")
    assert main(["orient", str(tmp_path / "m.ply")]) != 0
    assert "training.train_head" in capsys.readouterr().err


def test_orient_command_refuses_a_bad_head(tmp_path, capsys):
    write_model(make_object("car", seed=0, n_gaussians=2000), tmp_path / "m.ply")
    (tmp_path / "h.pt").write_text("nope")
    assert main(["orient", str(tmp_path / "m.ply"), "--head", str(tmp_path / "h.pt")]) != 0
    assert "cannot read" in capsys.readouterr().err


def _doubtful_pair():
    from tests.test_semantic import _doubtful_pair as pair

    return pair(3000)


def test_the_learned_route_steps_aside_without_a_head(monkeypatch, tmp_path):
    monkeypatch.delenv("GSA_CANONICAL_HEAD", raising=False)
    monkeypatch.setattr(nocs, "SHIPPED_HEAD", tmp_path / "none.pt")
    source, target = _doubtful_pair()
    result = align(source, target, AlignOptions(semantic="off"))
    assert result.verdict.doubtful
    assert result.diagnostics["learned"] == {"used": False, "reason": "no canonical head or backbone installed"}
    off = align(source, target, AlignOptions(semantic="off", learned="off")).diagnostics
    assert "learned" not in off


@pytest.mark.semantic
def test_the_learned_pose_picks_among_the_search_poses(monkeypatch, tmp_path):
    """An oracle stands in for the head (the route's decision, not the head's quality, is under
    test): each model's canonical pose is its true one, so the learned pose between them is the
    truth, and the doubtful pair ends on the search pose nearest it."""
    monkeypatch.setenv("GSA_CANONICAL_HEAD", str(save_head(CanonicalHead(), tmp_path / "h.pt", {})))
    source, target = _doubtful_pair()
    truth = random_sim3(np.random.default_rng([1, 9]))  # tests.test_semantic._doubtful_pair's

    def oracle(model, seed):
        pose = Sim3.identity() if model is source else truth.inverse()
        return OrientResult(pose, pose.rotation.T @ UP, pose.rotation.T @ FRONT, 0.9, 0.01, 100, True)

    monkeypatch.setattr(learned, "_models_oriented", lambda pair: (oracle(pair.source, 0), oracle(pair.target, 0)))
    result = align(source, target, AlignOptions(semantic="off"))
    report = result.diagnostics["learned"]
    assert report["used"], report
    assert rre_deg(result.transform.rotation, truth.rotation) < 3.0
