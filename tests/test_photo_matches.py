"""Two reconstructions registered by their photos' shared texture (gsa.align.photo).

Anchors here are made by hand: points on a model's surface, each with a random 128-byte
"texture" descriptor seen from two views (a little noise each). tests/test_recon.py registers
two real pycolmap reconstructions the same way.
"""

from __future__ import annotations

import numpy as np
import pytest

from gsa.align import photo
from gsa.align.pipeline import AlignOptions, align
from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg, scale_error_pct
from gsa.recon.anchors import PhotoAnchors
from gsa.sim3 import Sim3
from gsa.synth import make_object

TRUTH = Sim3(
    2.5, axis_rotation(np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2]), 2.4), np.array([1.0, -2.0, 0.5])
)


def _anchors(points, texture, rows, pose, rng, views=2, noise=0.0005):
    """Anchors of points[rows] moved by `pose`, each seen `views` times (descriptor noise ±4)."""
    pts = pose.apply(points[rows]) + noise * pose.scale * rng.normal(size=(len(rows), 3))
    desc = np.repeat(texture[rows], views, axis=0).astype(np.int64)
    desc = np.clip(desc + rng.integers(-4, 5, size=desc.shape), 0, 255).astype(np.uint8)
    return PhotoAnchors(pts, desc, np.repeat(np.arange(len(rows)), views))


def _joined(*parts: PhotoAnchors) -> PhotoAnchors:
    """One target's anchors made of several groups of points."""
    offsets = np.cumsum([0] + [len(p.points) for p in parts[:-1]])
    return PhotoAnchors(
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.descriptors for p in parts]),
        np.concatenate([p.point_index + o for p, o in zip(parts, offsets)]),
    )


@pytest.fixture(scope="module")
def surface():
    model = make_object("car", seed=1, n_gaussians=6000)
    rng = np.random.default_rng(0)
    rows = rng.choice(len(model), 500, replace=False)
    return model, model.means[rows].astype(np.float64), rng.integers(0, 256, size=(500, 128))


def test_the_shared_texture_gives_the_pose(surface):
    _, points, texture = surface
    rng = np.random.default_rng(1)
    src = _anchors(points, texture, np.arange(0, 350), Sim3.identity(), rng)
    dst = _anchors(points, texture, np.arange(150, 500), TRUTH, rng)
    found = photo.register(src, dst)
    assert found.accepted, found.reason
    assert found.inliers >= 190 and found.matches >= 190  # the 200 shared points
    assert rre_deg(found.transform.rotation, TRUTH.rotation) < 0.1
    assert scale_error_pct(found.transform.scale, TRUTH.scale) < 0.1
    assert found.confidence == pytest.approx(1.0)


def test_wrong_matches_are_outvoted(surface):
    """A third of the target's points carry a source point's texture at a wrong place."""
    _, points, texture = surface
    rng = np.random.default_rng(2)
    src = _anchors(points, texture, np.arange(0, 350), Sim3.identity(), rng)
    right = _anchors(points, texture, np.arange(150, 350), TRUTH, rng)
    wrong_rows = np.arange(0, 100)
    wrong = _anchors(points, texture, wrong_rows, TRUTH, rng)
    shuffled = PhotoAnchors(wrong.points[rng.permutation(len(wrong.points))], wrong.descriptors, wrong.point_index)
    dst = _joined(right, shuffled)
    found = photo.register(src, dst)
    assert found.accepted, found.reason
    assert found.matches >= 290 and 190 <= found.inliers <= 210
    assert rre_deg(found.transform.rotation, TRUTH.rotation) < 0.1


def test_unrelated_texture_is_refused(surface):
    _, points, texture = surface
    rng = np.random.default_rng(3)
    src = _anchors(points, texture, np.arange(0, 350), Sim3.identity(), rng)
    other = rng.integers(0, 256, size=texture.shape)
    found = photo.register(src, _anchors(points, other, np.arange(0, 350), TRUTH, rng))
    assert not found.accepted
    assert found.confidence == 0.0
    assert "matched" in found.reason


def test_matches_on_a_line_are_refused(surface):
    _, _, texture = surface
    rng = np.random.default_rng(4)
    line = np.outer(np.linspace(-1, 1, 500), [1.0, 0.2, 0.1])
    src = _anchors(line, texture, np.arange(0, 300), Sim3.identity(), rng, noise=1e-5)
    dst = _anchors(line, texture, np.arange(0, 300), TRUTH, rng, noise=1e-5)
    found = photo.register(src, dst)
    assert not found.accepted
    assert "line" in found.reason


def test_anchors_follow_their_model_and_read_back(surface, tmp_path):
    model, points, texture = surface
    rng = np.random.default_rng(5)
    anchors = _anchors(points, texture, np.arange(500), Sim3.identity(), rng)
    moved = model.transformed(TRUTH)
    assert "photo_anchors" not in moved.metadata
    model.metadata["photo_anchors"] = anchors
    try:
        moved = model.transformed(TRUTH)
        assert np.allclose(moved.metadata["photo_anchors"].points, TRUTH.apply(anchors.points))
        assert photo.photo_anchors(moved) is not None
        # anchors that no longer lie on their model are not used
        radius = np.median(np.linalg.norm(model.means - np.median(model.means, axis=0), axis=1))
        model.metadata["photo_anchors"] = anchors.transformed(Sim3(1.0, np.eye(3), np.array([0.0, radius, 0.0])))
        assert photo.photo_anchors(model) is None
    finally:
        model.metadata.pop("photo_anchors")
    back = PhotoAnchors.load(anchors.save(tmp_path / "anchors.npz"))
    assert np.array_equal(back.points, anchors.points)
    assert np.array_equal(back.descriptors, anchors.descriptors)
    assert np.array_equal(back.point_index, anchors.point_index)


def _pair(surface, target_texture=None):
    model, points, texture = surface
    rng = np.random.default_rng(6)
    source = make_object("car", seed=1, n_gaussians=6000, sample_seed=11)
    target = make_object("car", seed=1, n_gaussians=6000, sample_seed=12).transformed(TRUTH)
    source.metadata["photo_anchors"] = _anchors(points, texture, np.arange(0, 350), Sim3.identity(), rng)
    target.metadata["photo_anchors"] = _anchors(
        points, texture if target_texture is None else target_texture, np.arange(150, 500), TRUTH, rng
    )
    return source, target


def test_align_takes_the_photos_pose_and_reports_both_verdicts(surface):
    source, target = _pair(surface)
    r = align(source, target)
    assert r.stages == ("photo",)
    assert rre_deg(r.transform.rotation, TRUTH.rotation) < 0.1
    assert scale_error_pct(r.transform.scale, TRUTH.scale) < 0.1
    m, d = r.metrics, r.diagnostics
    assert d["photo_match"]["accepted"] and not r.verdict.doubtful and m["confidence"] > 0.9
    assert set(d["geometric_verdict"]) == {"confidence", "ambiguous", "doubtful"}
    assert r.to_dict()["stages_run"] == ["photo"]
    off = align(source, target, AlignOptions(photo_matches="off"))
    assert off.stages != ("photo",) and "photo_match" not in off.diagnostics


def test_a_refused_match_says_why_and_the_geometry_answers(surface):
    rng = np.random.default_rng(7)
    source, target = _pair(surface, target_texture=rng.integers(0, 256, size=(500, 128)))
    r = align(source, target)
    assert r.stages != ("photo",)
    assert r.diagnostics["photo_match"]["accepted"] is False
    assert r.diagnostics["photo_match"]["reason"]


def test_hints_take_precedence_over_the_photos(surface):
    source, target = _pair(surface)
    r = align(source, target, AlignOptions(init_transform=TRUTH.matrix().tolist()))
    assert r.stages != ("photo",) and "photo_match" not in r.diagnostics


def test_large_anchor_sets_are_capped_and_still_register(surface):
    """Past MAX_DESCRIPTORS a side each point keeps one view, then a random share of points."""
    _, points, texture = surface
    rng = np.random.default_rng(8)
    src = _anchors(points, texture, np.arange(0, 350), Sim3.identity(), rng, views=4)
    dst = _anchors(points, texture, np.arange(150, 500), TRUTH, rng, views=4)
    capped = photo._capped(src, 500, seed=0)
    assert len(capped) == 350 and len(np.unique(capped.point_index)) == 350  # one view per point
    assert len(photo._capped(src, 200, seed=0)) == 200
    pairs, _ = photo.matched_pairs(src, dst, limit=250)
    assert 70 <= len(pairs) <= 200  # about (250/350)² of the 200 shared points
    assert (pairs[:, 1] == pairs[:, 0] - 150).mean() > 0.95  # and they are the right ones


def test_two_poses_agreed_by_repeated_texture_are_left_to_the_geometry(surface):
    """200 shared points say TRUTH, 150 others say TRUTH turned half a turn: the photos do not decide."""
    _, points, texture = surface
    rng = np.random.default_rng(9)
    src = _anchors(points, texture, np.arange(0, 350), Sim3.identity(), rng)
    turned = TRUTH.compose(Sim3(1.0, axis_rotation(np.array([0.0, 1.0, 0.0]), np.pi), np.zeros(3)))
    one = _anchors(points, texture, np.arange(0, 200), TRUTH, rng)
    two = _anchors(points, texture, np.arange(200, 350), turned, rng)
    dst = _joined(one, two)
    found = photo.register(src, dst)
    assert not found.accepted
    assert "two poses" in found.reason and "180° apart" in found.reason
    # with the second pose's pairs fewer than half the first's, the first is taken
    few = _anchors(points, texture, np.arange(200, 260), turned, rng)
    dst = _joined(one, few)
    found = photo.register(src, dst)
    assert found.accepted and rre_deg(found.transform.rotation, TRUTH.rotation) < 0.1


def test_a_shared_background_does_not_register_two_different_objects(surface):
    """Two different objects photographed in one place: their SfM points share the background
    (a ring of textured points around them), not their surfaces. Only points on each model
    take part, so the photos are not used and the geometry answers."""
    _, points, texture = surface
    rng = np.random.default_rng(10)
    source = make_object("car", seed=1, n_gaussians=6000)
    target = make_object("airplane", seed=2, n_gaussians=6000).transformed(TRUTH)
    angle = rng.uniform(0, 2 * np.pi, 300)
    ring = np.stack([6 * np.cos(angle), rng.uniform(-1, 1, 300), 6 * np.sin(angle)], axis=1)
    ring_texture = rng.integers(0, 256, size=(300, 128))
    everywhere = np.arange(300)
    source.metadata["photo_anchors"] = _joined(
        _anchors(points, texture, np.arange(0, 300), Sim3.identity(), rng),
        _anchors(ring, ring_texture, everywhere, Sim3.identity(), rng),
    )
    target.metadata["photo_anchors"] = _joined(
        _anchors(
            target.means.astype(np.float64),
            rng.integers(0, 256, size=(6000, 128)),
            np.arange(300),
            Sim3.identity(),
            rng,
        ),
        _anchors(ring, ring_texture, everywhere, TRUTH, rng),
    )
    # all anchors together would register the background, confidently
    whole = photo.register(source.metadata["photo_anchors"], target.metadata["photo_anchors"])
    assert whole.accepted and rre_deg(whole.transform.rotation, TRUTH.rotation) < 0.1
    on_source = photo.photo_anchors(source)
    assert len(on_source.points) == 300  # the car's own points; the ring is left out
    r = align(source, target)
    assert r.stages != ("photo",)
    assert r.diagnostics["photo_match"]["accepted"] is False


def test_subset_keeps_the_chosen_points_and_their_views():
    anchors = PhotoAnchors(
        np.arange(12, dtype=float).reshape(4, 3),
        np.arange(6 * 128, dtype=np.int64).reshape(6, 128).astype(np.uint8),
        np.array([0, 1, 1, 2, 3, 3]),
    )
    kept = anchors.subset(np.array([False, True, False, True]))
    assert np.array_equal(kept.points, anchors.points[[1, 3]])
    assert np.array_equal(kept.point_index, [0, 0, 1, 1])
    assert np.array_equal(kept.descriptors, anchors.descriptors[[1, 2, 4, 5]])


def test_a_broken_anchors_file_is_a_warning_not_a_failure(tmp_path):
    from gsa.io.ply import ReaderWarning, write_ply
    from gsa.recon.folder import is_reconstruction, read_reconstruction

    write_ply(make_object("car", seed=1, n_gaussians=500), tmp_path / "model.ply")
    (tmp_path / "report.json").write_text("{}")
    (tmp_path / "anchors.npz").write_bytes(b"not an npz")
    assert is_reconstruction(tmp_path)
    with pytest.warns(ReaderWarning, match="aligning without its photos"):
        model = read_reconstruction(tmp_path)
    assert "photo_anchors" not in model.metadata and len(model) == 500
