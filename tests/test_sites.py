"""Outdoor sites (scenes that are not rooms): the generators (gsa.synth.sites), the site test and the scene
path's site search (gsa.align.scene), and the `site` bench pairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from benchmarks.scene import scene_judge
from benchmarks.site import SITE_HARD, point_files, site_pairs
from gsa.align import scene as S
from gsa.align.pipeline import AlignOptions, align
from gsa.align.scene import sites as scene_sites
from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg, scale_error_pct
from gsa.synth import make_object, scene_captures
from gsa.synth.sites import PointSite, make_site, resample_site, robust_extent

GARDEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-dev" / "garden_sfm_points.npz"


def test_make_site_is_deterministic_and_exact():
    a, b = make_site(seed=5, n_gaussians=20_000), make_site(seed=5, n_gaussians=20_000)
    assert len(a) == 20_000 and a.means.dtype == np.float32
    assert np.array_equal(a.means, b.means) and np.array_equal(a.sh, b.sh)
    assert a.metadata["kind"] == "site" and a.metadata["extent"] > 30
    other = make_site(seed=5, n_gaussians=20_000, sample_seed=9)
    assert not np.array_equal(a.means, other.means)
    # One site, two samplings: the same layout, so every Gaussian of one lies on the other.
    assert other.metadata["objects"] == a.metadata["objects"]
    # Wider than tall: a ground with things on it (sky floaters aside).
    ptp = np.ptp(np.percentile(a.means, [1, 99], axis=0), axis=0)
    assert ptp[2] < 0.5 * min(ptp[0], ptp[1])


def test_site_args_resample_the_same_site():
    """scene_captures resamples a site from its metadata: giving the drawn counts back must
    not shift the layout (a shift moves every tree and the captures no longer agree)."""
    site = make_site(seed=7, n_gaussians=30_000)
    again = make_site(seed=7, n_gaussians=30_000, sample_seed=3, **site.metadata["site_args"])
    assert again.metadata["objects"] == site.metadata["objects"]
    cap = scene_captures(site, np.random.default_rng(0), sizes=(12_000, 12_000), resample=resample_site)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(cap.target.means).query(cap.truth.apply(cap.source.means.astype(np.float64)))
    assert np.median(d) < 0.005 * cap.extent_target


def test_point_site_from_points():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (3000, 2))
    pts = np.column_stack([xy, 0.1 * np.sin(xy[:, 0])])
    ps = PointSite(pts, rng.uniform(0, 1, (3000, 3)))
    a, b = ps.sample(10_000, 1), ps.sample(10_000, 1)
    assert len(a) == 10_000 and np.array_equal(a.means, b.means)
    assert not np.array_equal(a.means, ps.sample(10_000, 2).means)
    # Gaussians stay on the points' surface (within their spacing) and keep the extent robust.
    assert np.abs(a.means[:, 2] - 0.1 * np.sin(a.means[:, 0])).max() < 0.1
    assert abs(a.metadata["extent"] - robust_extent(pts)) < 1e-9
    with pytest.raises(ValueError):
        PointSite(pts[:10], np.zeros((10, 3)))


@pytest.fixture(scope="module")
def site_pair():
    site = make_site(seed=2601, n_gaussians=170_000)
    return scene_captures(
        site, np.random.default_rng([0, 26, 1]), sizes=(90_000, 100_000), resample=resample_site, **SITE_HARD
    )


def test_sites_pass_the_site_test_and_objects_do_not(site_pair):
    cap = site_pair
    choice = S.choose(cap.source, cap.target, "auto", True, 2000)
    assert choice.run, choice.to_dict()
    # A shed's walls and the ground can make a room test's shell too; either way the
    # path searches the pair as sites, as both grounds lie open to the sky.
    anchors = [S.scene_anchors(m, S.SceneOptions().scene_anchors) for m in (cap.source, cap.target)]
    sites = scene_sites._sites(*anchors)
    assert sites is not None and all(s.open_ground for s in sites)
    for model in (make_object("airplane", seed=0, n_gaussians=20_000), make_object("car", seed=1, n_gaussians=20_000)):
        st = S.scene_structure(S.scene_anchors(model, S.test_anchor_count(len(model), 2000)), gaussians=len(model))
        assert not st.is_scene, st.to_dict()


def test_scene_path_aligns_a_site_pair(site_pair):
    cap = site_pair
    assert cap.gains[0] != cap.gains[1] and cap.wave is not None  # the harder captures
    result = align(cap.source, cap.target, AlignOptions())
    scene = result.diagnostics["scene"]
    assert scene["ran"] and scene["kind"] == "site"
    judged = scene_judge(result.transform, cap.truth, cap.source, cap.target)
    assert rre_deg(result.transform.rotation, cap.truth.rotation) < 0.5
    assert judged["translation_error_pct_extent"] < 0.5
    assert scale_error_pct(result.transform.scale, cap.truth.scale) < 0.5
    assert not result.verdict.doubtful


def test_site_search_only_turns_about_the_ground():
    up = np.array([0.0, 0.6, 0.8])
    for options in (S.SceneOptions(), S.SceneOptions(site_yaw_deg=10.0)):
        rots = scene_sites._site_rotations(np.array([0.0, 0.0, 1.0]), up, options)
        assert len(rots) == 2 * round(360 / options.site_yaw_deg)
        mapped = rots @ np.array([0.0, 0.0, 1.0])
        assert np.allclose(np.abs(mapped @ up), 1.0, atol=1e-9)  # the up onto ±up, turned about it
        assert np.allclose(np.einsum("nij,nkj->nik", rots, rots), np.eye(3), atol=1e-9)
        assert abs(rre_deg(rots[1], rots[0]) - options.site_yaw_deg) < 1e-6  # steps of site_yaw_deg


def test_site_bench_pairs(tmp_path):
    pairs = site_pairs(True, 0, data=tmp_path)  # an empty folder: generated pairs only
    assert [label for label, _ in pairs] == ["site-0", "site-1", "site-2"]
    with pytest.raises(ValueError):
        point_files(tmp_path / "missing")


@pytest.mark.skipif(not GARDEN.exists(), reason="the garden SfM points live in ../shared/data/real-dev")
def test_garden_point_site():
    files = point_files(GARDEN.parent)
    assert GARDEN in files
    labels = [label for label, _ in site_pairs(True, 0, data=GARDEN.parent)]
    assert labels[-1] == "garden_sfm_points-0" and len(labels) == 3
    ps = PointSite.from_file(GARDEN)
    model = ps.sample(50_000, 0)
    assert len(model) == 50_000 and model.metadata["points"] == 138_766
    assert model.metadata["extent"] < 0.5 * float(np.linalg.norm(np.ptp(ps.points, axis=0)))


def test_ground_up_is_the_plane_of_the_ground_not_its_mean_normal():
    """_ground_up: a hilly ground tilted 12 degrees, with a raised border along one side (a
    band of anchors above the plane, which tilts a plain least-squares plane by 1.7
    degrees), gives the tilted plane's normal within 0.6 degrees, signed as the hint."""
    rng = np.random.default_rng(3)
    tilt = axis_rotation(np.array([1.0, 0.0, 0.0]), np.radians(12.0))
    xy = rng.uniform(-10, 10, (3000, 2))
    z = 0.3 * np.sin(xy[:, 0] / 2.0) * np.cos(xy[:, 1] / 3.0)  # hills and hollows about the plane
    kerb = np.column_stack([rng.uniform(-10, 10, 500), rng.uniform(8, 10, 500), rng.uniform(0.5, 1.5, 500)])
    ground = np.vstack([np.column_stack([xy, z]), kerb]) @ tilt.T
    w = np.full(len(ground), 1.0 / len(ground))
    truth = tilt @ np.array([0.0, 0.0, 1.0])
    for hint in (np.array([0.0, 0.3, 1.0]), np.array([0.0, -0.3, -1.0])):
        up = scene_sites._ground_up(ground, w, hint / np.linalg.norm(hint), S.SceneOptions())
        assert up @ hint > 0
        assert np.degrees(np.arccos(min(1.0, abs(float(up @ truth))))) < 0.6


def test_placed_starts_rank_by_colour_where_geometry_cannot():
    """On a flat, evenly sampled field any turn and shift lays the source on the target:
    geometry cannot rank placements. With colour (a field of coloured patches), the
    best placement is the true one."""
    from gsa.align import robust
    from gsa.model import GaussianModel
    from gsa.sim3 import Sim3

    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, (40_000, 2))
    patches = np.floor(xy / 4.0).astype(int)
    palette = rng.uniform(0.1, 0.9, (10, 10, 3))
    colours = palette[patches[:, 0] + 5, patches[:, 1] + 5]
    field = np.column_stack([xy, 0.02 * rng.standard_normal(len(xy))]).astype(np.float32)
    keep = xy[:, 0] < 4.0  # the source misses a side: its centre is not the target's
    truth = Sim3(1.3, axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(70.0)), np.array([2.0, -1.0, 0.5]))
    source = GaussianModel.from_colors(field[keep], colours[keep])
    target = GaussianModel.from_colors(truth.apply(field.astype(np.float64)).astype(np.float32), colours)
    src, dst = robust.anchors(source, 2000), robust.anchors(target, 2000)
    up = np.array([0.0, 0.0, 1.0])
    rotations = scene_sites._site_rotations(up, up, S.SceneOptions())

    def best_placement(w_colour):
        (r, scale, centre), *_ = robust.placed_starts(
            src, dst, np.random.default_rng(1), rotations=rotations, points=64, step=0.25, truncation=0.2,
            scales=(0.8, 1.0, 1.25), count=3, min_deg=15.0, capture=lambda r, s, t, steps: (s, t),
            capture_steps=(), w_colour=w_colour, colour_sigma=robust.PoseCriteria().colour_sigma,
            centres=robust.box_lattice(dst.points, scene_sites._site_frame(up), 0.25 * dst.radius),
        )  # fmt: skip
        return rre_deg(r, truth.rotation), np.linalg.norm(centre - truth.apply(src.center)) / dst.radius

    turn, shift = best_placement(1.0)
    assert turn < 5.0 and shift < 0.3
    # Geometry alone: a wrong turn ties with (or beats) the true one here.
    assert best_placement(0.0)[0] > 5.0
    # Colours that disagree everywhere, tried only where the models overlap, score every
    # placement below zero: each rotation's best is still a placement (a scale among the
    # trials), never an unset row.
    repainted = robust.anchors(GaussianModel.from_colors(field[keep], 1.0 - colours[keep]), 2000)
    placements = robust.placed_starts(
        repainted, dst, np.random.default_rng(1), rotations=rotations[:8], points=64, step=0.5, truncation=0.2,
        scales=(1.0,), count=8, min_deg=1.0, capture=lambda r, s, t, steps: (s, t), capture_steps=(),
        w_colour=1.0, colour_sigma=1.0, centres=truth.apply(repainted.center)[None],
    )  # fmt: skip
    assert len(placements) == 8
    assert all(np.isclose(scale, dst.radius / repainted.radius) for _, scale, _ in placements)


def test_climb_moves_a_near_pose_onto_the_site(site_pair):
    """_climb: from the truth turned 4 degrees about the up axis, shifted and scaled, the
    climb ends closer to the truth than it started, and scores higher."""
    from gsa.align import robust
    from gsa.sim3 import Sim3

    cap = site_pair
    o = S.SceneOptions()
    src, dst = robust.match_exposure(
        S.scene_anchors(cap.source, o.scene_anchors), S.scene_anchors(cap.target, o.scene_anchors)
    )
    up = cap.truth.rotation @ np.array([0.0, 0.0, 1.0])
    turn = axis_rotation(up, np.radians(4.0))
    c = cap.truth.apply(src.center)
    start_pose = Sim3(
        cap.truth.scale * 1.05,
        turn @ cap.truth.rotation,
        turn @ (cap.truth.translation - c) + c + 0.05 * dst.radius * up,
    )
    k = robust.PoseCriteria()
    start = robust.score_pose(src, dst, start_pose, "start", 1.0, k)
    climbed = robust.score_pose(src, dst, scene_sites._climb(src, dst, start, 1.0, k, o).transform, "climbed", 1.0, k)
    assert climbed.score > start.score
    assert rre_deg(climbed.transform.rotation, cap.truth.rotation) < 1.0
    assert scale_error_pct(climbed.transform.scale, cap.truth.scale) < 1.0


def test_terrain_captures_are_two_partial_samplings_moved_by_the_truth():
    from gsa.synth.terrain import make_terrain, terrain_captures

    first, size = make_terrain(3, 1, 20_000)
    again, _ = make_terrain(3, 1, 20_000)
    other, _ = make_terrain(3, 2, 20_000)
    assert len(first) == 20_000 and 30 <= size <= 80
    assert np.array_equal(first.means, again.means) and not np.array_equal(first.means, other.means)
    assert np.ptp(first.means[:, 1]) < 0.5 * np.ptp(first.means[:, 0])  # Y is up: the scene is flat along it
    cap = terrain_captures(3, 20_000, np.random.default_rng(0))
    assert 0.6 * 20_000 - 1 <= len(cap.source) <= 0.8 * 20_000 + 1
    assert 0.6 * 20_000 - 1 <= len(cap.target) <= 0.8 * 20_000 + 1
    assert 0.2 <= cap.truth.scale <= 5.0
    # the target is the second sampling's far part under the truth: taken back, it lies on the scene
    back = cap.truth.inverse().apply(cap.target.means.astype(np.float64))
    d, _ = cKDTree(first.means).query(back)
    assert np.median(d) < 0.5 * size / np.sqrt(20_000)


def test_site_search_finds_a_terrain_whose_ups_disagree():
    """Two partial captures of a rolling terrain: each capture's up is its own part's ground
    plane, here 8.5 degrees apart, so no up-aligned rotation is near the truth (the search
    without the matched starts answered 174 degrees off); the matched starts trust no up."""
    from gsa.align import robust
    from gsa.synth.terrain import terrain_captures

    cap = terrain_captures(6, 80_000, np.random.default_rng(6))
    opts = AlignOptions()
    k, o = opts.criteria, opts.criteria.scene
    src, dst = robust.match_exposure(
        S.scene_anchors(cap.source, o.scene_anchors, 0, o), S.scene_anchors(cap.target, o.scene_anchors, 0, o)
    )
    sites = scene_sites._sites(src, dst, o)
    assert sites is not None
    ups_apart = np.degrees(np.arccos(abs((cap.truth.rotation @ sites[0].up) @ sites[1].up)))
    assert ups_apart > 5.0
    search = scene_sites.site_search(src, dst, *sites, 0, o, k.search_options(0, 0), k.verdict)
    assert rre_deg(search.best.transform.rotation, cap.truth.rotation) < 2.0
    assert scale_error_pct(search.best.transform.scale, cap.truth.scale) < 2.0


def test_rolling_hills_pass_the_site_test():
    """Terrain whose slopes pass 30 degrees over a third of its ground (gsa.synth.terrain's
    terrain 2711): both captures are sites, with most of their weight on the ground; with
    ground_deg 30 both failed (ground share 0.21) and the pair went to the object path."""
    from gsa.synth.terrain import terrain_captures

    cap = terrain_captures(2711, 300_000, np.random.default_rng([0, 27, 11]))
    choice = S.choose(cap.source, cap.target, "auto", True, 2000)
    assert choice.run and choice.source.is_site and choice.target.is_site
    assert choice.source.site.ground_share > 0.35 and choice.target.site.ground_share > 0.35
    strict = S.SceneOptions(ground_deg=30.0)
    assert not S.choose(cap.source, cap.target, "auto", True, 2000, options=strict).run
