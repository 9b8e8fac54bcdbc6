"""The robustness-benchmark generators (gsa.synth.variants), the new primitives,
and the bench's symmetric-pose and confidence-calibration bookkeeping.

Fast: models of a few thousand Gaussians, no alignment runs.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from benchmarks import protocols as P
from gsa.geometry import axis_rotation, euler_xyz, rotation_distance_deg
from gsa.sim3 import Sim3, solve_sim3
from gsa.synth import (
    SYMMETRIC_FAMILIES,
    add_floaters,
    cut_by_plane,
    deform,
    make_object,
    make_symmetric_object,
    symmetric_spec,
    symmetry_rotations,
)
from gsa.synth.shapes import RegularPrism, Torus

LUMA = np.array([0.2126, 0.7152, 0.0722])


@pytest.fixture(scope="module")
def car():
    return make_object("car", seed=3, n_gaussians=3000, sh_degree=2)


# ---------------------------------------------------------------- primitives


def test_regular_frustum_samples_its_surface():
    k, r0, r1, length = 6, 1.0, 0.6, 2.0
    prim = RegularPrism((0, 0, 0), (0, 0, 1), r0, length, k, (1, 0, 0), top_radius=r1)
    pts, normals = prim.sample(20_000, np.random.default_rng(0))
    assert np.allclose(np.linalg.norm(normals, axis=1), 1)
    z = pts[:, 2]
    bottom, top = np.isclose(z, -1.0), np.isclose(z, 1.0)
    side = ~(bottom | top)
    areas = prim._part_areas()
    assert abs(bottom.mean() - areas[1] / areas.sum()) < 0.01 and abs(top.mean() - areas[2] / areas.sum()) < 0.01
    # side points: on the face whose normal they carry, at the apothem of their height
    t = (z[side] + 1) / 2
    apothem = (r0 + (r1 - r0) * t) * np.cos(np.pi / k)
    horiz = normals[side, :2] / np.linalg.norm(normals[side, :2], axis=1, keepdims=True)
    assert np.allclose(np.einsum("ij,ij->i", pts[side, :2], horiz), apothem, atol=1e-9)
    # caps: inside the polygon
    face_dirs = np.array([[np.cos(a), np.sin(a)] for a in (prim.face_angle(j) for j in range(k))])
    f = np.array([[0, 1.0], [-1.0, 0]])  # _frame((0,0,1)) maps frame angles to world angles + 90°
    support = (pts[bottom, :2] @ (face_dirs @ f).T).max(1)
    assert (support <= r0 * np.cos(np.pi / k) + 1e-9).all()


def test_torus_samples_its_surface():
    tor = Torus((0, 0, 1.0), (0, 0, 1), 2.0, 0.5, (0, 0, 0))
    pts, _ = tor.sample(5000, np.random.default_rng(1))
    rho = np.hypot(pts[:, 0], pts[:, 1])
    assert np.allclose((rho - 2.0) ** 2 + (pts[:, 2] - 1.0) ** 2, 0.25)
    # uniform by area: more on the outer half (area element ∝ R + r cos v)
    outer = (rho > 2.0).mean()
    assert abs(outer - (0.5 + 0.5 / (np.pi * 2.0) * 1.0)) < 0.03  # ∫(R+r cos v) over |v|<π/2 / (2πR)


# ---------------------------------------------------------------- cut_by_plane


def test_cut_by_plane_keeps_a_half_space(car):
    for seed in range(4):
        out = cut_by_plane(car, np.random.default_rng(seed), keep=(0.6, 0.8))
        meta = out.metadata
        assert 0.6 <= meta["cut_keep"] <= 0.8
        assert abs(len(out) / len(car) - meta["cut_keep"]) < 2 / len(car)
        n = np.asarray(meta["cut_normal"])
        assert abs(np.linalg.norm(n) - 1) < 1e-12
        proj = car.means.astype(np.float64) @ n
        kept = proj <= meta["cut_offset"]
        # exactly the Gaussians on the kept side, in order, with their attributes
        assert kept.sum() == len(out)
        assert np.array_equal(out.means, car.means[kept]) and np.array_equal(out.sh, car.sh[kept])
        assert meta["category"] == "car"
    a = cut_by_plane(car, np.random.default_rng(7))
    b = cut_by_plane(car, np.random.default_rng(7))
    c = cut_by_plane(car, np.random.default_rng(8))
    assert np.array_equal(a.means, b.means) and a.metadata["cut_normal"] != c.metadata["cut_normal"]
    with pytest.raises(ValueError):
        cut_by_plane(car, np.random.default_rng(0), keep=(0.8, 0.6))


# ---------------------------------------------------------------- add_floaters


def test_add_floaters(car):
    out = add_floaters(car, np.random.default_rng(0), fraction=0.2, opacity=(0.1, 0.3), box_scale=1.5)
    n = len(car)
    assert len(out) == n + round(0.2 * n) == out.metadata["floaters"] + n
    assert np.array_equal(out.means[:n], car.means) and np.array_equal(out.sh[:n], car.sh)
    fl = out.subset(np.arange(n, len(out)))
    assert out.sh_degree == car.sh_degree == 2 and not fl.sh[:, 1:].any()
    assert fl.opacities.min() >= 0.1 - 1e-6 and fl.opacities.max() <= 0.3 + 1e-6
    lo, hi = car.means.min(0).astype(np.float64), car.means.max(0).astype(np.float64)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.5
    assert (np.abs(fl.means - centre) <= half + 1e-4).all()
    assert (np.abs(fl.means - centre) > (hi - lo) / 2).any(axis=1).mean() > 0.3  # the box really is bigger
    colors = fl.base_colors
    assert (colors @ LUMA).min() > 0.49  # bright
    assert ((colors.max(1) - colors.min(1)) / colors.max(1)).mean() > 0.4  # and saturated
    assert np.allclose(np.linalg.norm(fl.quats, axis=1), 1, atol=1e-5)
    median = np.median(car.scales.max(1))
    assert 0.25 * median <= fl.scales.max(1).min() and fl.scales.max(1).max() <= 2.0 * median + 1e-6
    assert out.metadata["category"] == "car"
    again = add_floaters(car, np.random.default_rng(0))
    assert np.array_equal(again.means, out.means)


# ---------------------------------------------------------------- symmetric objects


def test_symmetric_specs_cover_families_and_orders():
    specs = [symmetric_spec(s) for s in range(30)]
    assert {f for f, _ in specs} == set(SYMMETRIC_FAMILIES)
    assert all(4 <= k <= 8 for _, k in specs) and len({k for _, k in specs}) >= 3


@pytest.mark.parametrize("seed", [0, 1, 2])  # one of each family
def test_symmetric_object_geometry_and_colour(seed):
    a = make_symmetric_object(seed, 3000, sample_seed=1)
    b = make_symmetric_object(seed, 3000, sample_seed=2)
    k = a.metadata["symmetry_order"]
    assert a.metadata["family"] == SYMMETRIC_FAMILIES[seed] and 4 <= k <= 8
    assert len(a) == len(b) == 3000 and not np.array_equal(a.means, b.means)
    xa, xb = a.means.astype(np.float64), b.means.astype(np.float64)
    diag = np.linalg.norm(np.ptp(xa, 0))
    tree = cKDTree(xb)
    d_id, i_id = tree.query(xa)
    rot = symmetry_rotations(a)[1]
    assert np.allclose(rot, axis_rotation((0, 0, 1), 2 * np.pi / k))
    d_rot, i_rot = tree.query(xa @ rot.T)
    # the rotated sampling lies on the other sampling's surface as closely as the unrotated one
    assert d_rot.max() < 0.04 * diag and np.median(d_rot) < 0.015 * diag
    assert np.mean(d_rot) < 1.2 * np.mean(d_id)
    # colours: the same where nothing is marked, different on the marked sector
    theta = np.arctan2(xa[:, 1], xa[:, 0])
    sector = np.round(np.angle(np.exp(1j * (theta - a.metadata["mark_angle"]))) / (2 * np.pi / k)).astype(int) % k
    marked = sector == 0
    assert 0.8 / k < marked.mean() < 1.3 / k  # 1/k of the surface
    ca, cb = a.base_colors, b.base_colors
    diff_rot = np.linalg.norm(ca - cb[i_rot], axis=1)
    assert np.mean(diff_rot[marked] > 0.3) > 0.9  # the marked sector moved to an unmarked one
    plain = (sector != 0) & (sector != k - 1)  # neither marked before nor after the rotation
    assert np.mean(diff_rot[plain] < 0.2) > 0.95
    diff_id = np.linalg.norm(ca - cb[i_id], axis=1)  # identity pose: colours agree everywhere
    assert np.mean(diff_id < 0.2) > 0.95
    # centred by the shape: the axis passes through the origin (xy mean ≈ 0 by symmetry)
    assert np.abs(xa[:, :2].mean(0)).max() < 0.02 * diag
    # deterministic
    assert np.array_equal(make_symmetric_object(seed, 3000, sample_seed=1).means, a.means)


def test_symmetric_object_sh_degree():
    m = make_symmetric_object(4, 500, sh_degree=3)
    assert m.sh_degree == 3 and len(m) == 500


def test_symmetric_judge_counts_symmetric_poses():
    source = make_symmetric_object(1, 300)
    k = source.metadata["symmetry_order"]
    truth = Sim3(2.0, euler_xyz(np.radians([30.0, -70.0, 120.0])), np.array([1.0, 2.0, 3.0]))
    rot = axis_rotation((0, 0, 1), 2 * np.pi * 2 / k)
    est = Sim3(2.0, truth.rotation @ rot, truth.translation)  # truth composed with a symmetry
    got = P.symmetric_judge(est, truth, source, source)
    assert got["rre_any_symmetric_deg"] < 1e-6 and got["symmetric_pose"] == 2
    assert P.symmetric_judge(truth, truth, source, source)["symmetric_pose"] == 0


# ---------------------------------------------------------------- deform


def test_deform(car):
    out = deform(car, np.random.default_rng(0), stretch=0.25, taper=0.2, bend=0.15)
    info = out.metadata["deform"]
    f = np.asarray(info["stretch_factors"])
    assert len(out) == len(car)
    assert abs(np.prod(f) - 1) < 1e-12 and (f >= 1 / 1.25 - 1e-12).all() and (f <= 1.25 + 1e-12).all()
    axes = np.asarray(info["stretch_axes"])
    assert np.allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    moved = np.linalg.norm(out.means - car.means, axis=1)
    size = np.linalg.norm(np.ptp(car.means, 0))
    assert np.median(moved) > 0.01 * size and moved.max() < 0.5 * size
    assert np.allclose(out.means.mean(0), car.means.mean(0), atol=1e-4 * size)
    # the identity is the best similarity onto the deformed copy: nothing left to undo
    best = solve_sim3(car.means.astype(np.float64), out.means.astype(np.float64))
    assert rotation_distance_deg(best.rotation, np.eye(3)) < 1e-3 and abs(best.scale - 1) < 1e-5
    assert info["undone_rotation_deg"] > 0.01
    for name in ("quats", "log_scales", "opacity_logits", "sh"):
        assert np.array_equal(getattr(out, name), getattr(car, name))
    assert np.array_equal(deform(car, np.random.default_rng(0)).means, out.means)
    # no deformation at all: only the float32 round trip
    same = deform(car, np.random.default_rng(0), stretch=0, taper=0, bend=0)
    assert np.allclose(same.means, car.means, atol=1e-5)


# ---------------------------------------------------------------- calibration


def _rec(rre, doubtful, confidence=0.5, error=False):
    r = {
        "pair": "p",
        "seconds": 1.0,
        "rre_deg": rre,
        "scale_error_pct": 0.0,
        "ate_normalized": 0.0,
        "doubtful": doubtful,
        "confidence": confidence,
    }
    if error:
        r["error"] = "boom"
        r["rre_deg"] = float("nan")
    return r


def test_calibration_numbers():
    records = [
        _rec(1.0, False),
        _rec(2.0, False),
        _rec(90.0, False),  # unflagged: 2 of 3 succeed
        _rec(120.0, True),
        _rec(170.0, True),
        _rec(0.5, True),  # flagged: 2 failures, 1 success
        _rec(0.0, True, error=True),  # an error is a flagged failure
    ]
    row = P.summarise("symmetric", P.GSA_COARSE, records)
    P.add_time_ratio([row])
    assert row["flag_results"] == 7 and row["flagged"] == 4
    assert row["flagged_rate"] == pytest.approx(4 / 7)
    assert row["unflagged"] == 3 and row["unflagged_success_rate"] == pytest.approx(2 / 3)
    assert row["failures"] == 4 and row["failures_flagged_rate"] == pytest.approx(3 / 4)
    assert row["success_rate"] == pytest.approx(3 / 7)
    text = P.format_table("symmetric", [row])
    assert "Confidence calibration" in text and "4/7 flagged doubtful (57%)" in text
    assert "unflagged: 3, 67% succeed" in text and "failures: 4, 75% flagged" in text
    # peers' records carry no flag: no calibration fields, no line
    peer = P.summarise(
        "symmetric", "plain ICP", [{k: v for k, v in r.items() if k not in ("doubtful", "confidence")} for r in records]
    )
    assert "flagged_rate" not in peer
    P.add_time_ratio([peer])
    assert "Confidence calibration" not in P.format_table("symmetric", [peer])
    # one summary over protocols, for the GSA coarse row only
    other = P.summarise("partial", P.GSA_COARSE, [_rec(1.0, False), _rec(30.0, False)])
    line = P.calibration_summary({"symmetric": [row, peer], "partial": [other], "io": [{"protocol": "io"}]})
    assert "over symmetric, partial: 9 results" in line
    assert "unflagged: 5, 60% succeed" in line and "failures: 5, 60% flagged" in line
    # no confidence reported (today's align()): said so
    none = P.summarise("x", P.GSA_COARSE, [_rec(1.0, False, confidence=None)])
    P.add_time_ratio([none])
    assert none["flagged_rate"] == 0 and none["unflagged_success_rate"] == 1.0
    assert np.isnan(none["failures_flagged_rate"]) and "reported no confidence" in P.format_table("x", [none])


def test_symmetric_success_column():
    recs = [
        dict(_rec(150.0, False), rre_any_symmetric_deg=1.0),
        dict(_rec(1.0, False), rre_any_symmetric_deg=1.0),
        dict(_rec(40.0, False), rre_any_symmetric_deg=40.0),
    ]
    row = P.summarise("symmetric", P.GSA_COARSE, recs)
    P.add_time_ratio([row])
    assert row["success_rate"] == pytest.approx(1 / 3) and row["success_rate_any_symmetric"] == pytest.approx(2 / 3)
    text = P.format_table("symmetric", [row])
    assert "success, any symmetric pose (RRE<5°)" in text and "| 67% |" in text


def _FakeResult(metrics):
    from gsa.align.coarse import CoarseResult
    from gsa.align.result import AlignmentResult

    ident = Sim3.identity()
    return AlignmentResult(ident, CoarseResult(ident, iterations=0, converged=True), "none", metrics=metrics)


@pytest.mark.parametrize(
    "metrics, expected",
    [
        ({"confidence": 0.2, "ambiguous": True, "doubtful": True}, (0.2, True)),
        ({}, (None, False)),  # align() without confidence reporting
    ],
)
def test_gsa_runner_carries_confidence(monkeypatch, metrics, expected):
    monkeypatch.setattr(P, "align", lambda source, target, options: _FakeResult(metrics))
    est, _, fields = P.gsa_runner(False)(None, None)[P.GSA_COARSE]
    assert isinstance(est, Sim3) and (fields["confidence"], fields["doubtful"]) == expected


def test_protocol_records_carry_flags(monkeypatch, tmp_path, capsys):
    """evaluate() puts the runner's extra fields into the records, the judge's too,
    and run_protocols ends with the calibration line."""

    def pairs(quick, seed):
        def make(i):
            def f():
                src = make_symmetric_object(i, 400, sample_seed=1)
                truth = P.random_sim3(np.random.default_rng(i))
                return src, make_symmetric_object(i, 400, sample_seed=2).transformed(truth), truth

            return f

        return [(f"{symmetric_spec(i)[0]}-k{symmetric_spec(i)[1]}-{i}", make(i)) for i in range(2)]

    def runner(source, target):
        k = source.metadata["symmetry_order"]
        return {
            P.GSA_COARSE: (
                Sim3(1.0, axis_rotation((0, 0, 1), 2 * np.pi / k), np.zeros(3)),
                0.1,
                {"confidence": 0.9, "doubtful": False},
            )
        }

    monkeypatch.setattr(P, "symmetric_pairs", pairs)
    monkeypatch.setattr(P, "default_runners", lambda seed, peers, quick: [runner])
    monkeypatch.setattr(P, "random_sim3", lambda rng: Sim3.identity())
    P.run_protocols(["symmetric"], quick=True, out=str(tmp_path))
    text = capsys.readouterr().out
    row = next(r for r in __import__("json").loads((tmp_path / "symmetric.json").read_text())["rows"])
    rec = row["records"][0]
    assert rec["doubtful"] is False and rec["confidence"] == 0.9 and "family" in rec and "symmetry_order" in rec
    assert rec["rre_any_symmetric_deg"] < 1e-6 and rec["rre_deg"] > 40  # a symmetric pose, not the true one
    assert row["success_rate"] == 0 and row["success_rate_any_symmetric"] == 1
    assert row["unflagged_success_rate"] == 0 and row["failures_flagged_rate"] == 0
    assert "Confidence calibration, GSA coarse, over symmetric: 2 results" in text
