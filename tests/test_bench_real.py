"""`gsa bench real`: split pairs from a folder of captures (disjoint halves, own plane cuts,
random Sim(3), optional exposure shift), and the protocol end to end on a small capture."""

import numpy as np
import pytest

from benchmarks import protocols
from benchmarks.real_captures import find_captures, real_split_pairs, split_pair
from gsa.io.formats import write_model
from gsa.synth import make_object


@pytest.fixture
def captures(tmp_path):
    folder = tmp_path / "captures"
    folder.mkdir()
    write_model(make_object("car", 0, 4000), folder / "car.ply", "ply")
    write_model(make_object("chair", 1, 4000), folder / "chair.spz", "spz")
    (folder / "notes.txt").write_text("not a capture")
    return folder


def test_captures_are_found_by_format(captures):
    assert [p.name for p in find_captures(captures)] == ["car.ply", "chair.spz"]
    with pytest.raises(ValueError, match="no 3DGS files"):
        real_split_pairs(captures / "..", quick=True, seed=0)


def test_halves_are_disjoint_and_cut():
    model = make_object("car", 0, 6000)
    model.means[:, 0] += np.arange(len(model)) * 1e-9  # every Gaussian told apart by its position
    source, target = split_pair(model, np.random.default_rng(3))
    key = lambda m: {tuple(x) for x in m.means.tolist()}  # noqa: E731
    assert not key(source) & key(target)
    for half in (source, target):
        # a half holds ~50 % of the capture, of which the plane kept 60-90 %
        assert 0.6 * 0.45 * len(model) < len(half) < 0.9 * 0.55 * len(model)
        assert 0.6 <= half.metadata["cut_keep"] <= 0.9


def test_pairs_move_the_target_and_shift_the_source_exposure(captures):
    plain = real_split_pairs(captures, quick=True, seed=0)
    shifted = real_split_pairs(captures, quick=True, seed=0, exposure=True)
    assert [label for label, _ in plain] == ["car.ply-0", "car.ply-1", "chair.spz-0", "chair.spz-1"]
    source, target, truth = plain[0][1]()
    source_x, target_x, truth_x = shifted[0][1]()
    assert np.allclose(truth.matrix(), truth_x.matrix())
    assert "exposure_gain" in source_x.metadata and "exposure_gain" not in source.metadata
    assert not np.allclose(source.base_colors, source_x.base_colors)
    # the target is a moved half: mapped back by the truth, it lies where the capture is
    back = truth.inverse().apply(target.means)
    assert np.allclose(back.mean(0), source.means.mean(0), atol=0.5 * np.ptp(source.means, axis=0).max())


def test_protocol_runs_and_succeeds_on_generated_captures(captures, tmp_path, monkeypatch):
    monkeypatch.setattr(protocols, "FINE_ROWS", False)
    rows = protocols.protocol_real(True, 0, tmp_path / "out", peers=[], data=captures)
    assert [r["variant"] for r in rows] == ["as captured", "exposure shifted"]
    for row in rows:
        assert row["pairs"] == 4 and set(row["per_capture_mean_rre_deg"]) == {"car.ply", "chair.spz"}
        assert row["success_rate"] == 1.0, [(r["pair"], r["rre_deg"]) for r in row["records"]]
    assert (tmp_path / "out" / "real.json").exists()


def test_pairs_per_capture_and_variants_follow_the_environment(captures, monkeypatch):
    from benchmarks import real_captures as rc

    monkeypatch.delenv("GSA_REAL_PAIRS", raising=False)
    monkeypatch.delenv("GSA_REAL_VARIANTS", raising=False)
    assert rc.pair_range(False) == range(rc.PAIRS_PER_CAPTURE[0])
    assert rc.pair_range(True) == range(rc.PAIRS_PER_CAPTURE[1])
    assert rc.variants() == [False, True]
    monkeypatch.setenv("GSA_REAL_PAIRS", "5")
    assert len(real_split_pairs(captures, quick=True, seed=0)) == 10
    monkeypatch.setenv("GSA_REAL_PAIRS", "3:5")
    later = real_split_pairs(captures, quick=True, seed=0)
    assert [label for label, _ in later] == ["car.ply-3", "car.ply-4", "chair.spz-3", "chair.spz-4"]
    monkeypatch.setenv("GSA_REAL_PAIRS", "5")
    same = dict(real_split_pairs(captures, quick=True, seed=0))["car.ply-3"]()[2]
    assert np.allclose(same.matrix(), dict(later)["car.ply-3"]()[2].matrix())  # pair k is the same in any range
    monkeypatch.setenv("GSA_REAL_CAPTURES", "chair*")
    assert [label for label, _ in real_split_pairs(captures, quick=True, seed=0)][:1] == ["chair.spz-0"]
    chair = dict(real_split_pairs(captures, quick=True, seed=0))["chair.spz-3"]()[2]
    monkeypatch.delenv("GSA_REAL_CAPTURES")
    assert np.allclose(
        chair.matrix(), dict(real_split_pairs(captures, quick=True, seed=0))["chair.spz-3"]()[2].matrix()
    )
    monkeypatch.setenv("GSA_REAL_VARIANTS", "exposure")
    assert rc.variants() == [True]
    monkeypatch.delenv("GSA_REAL_GAUSSIANS", raising=False)
    assert rc.gaussian_cap(False) is None and rc.gaussian_cap(True) == rc.QUICK_GAUSSIANS
    whole = dict(real_split_pairs(captures, quick=False, seed=0))["car.ply-3"]()
    monkeypatch.setenv("GSA_REAL_GAUSSIANS", "1000")
    small = dict(real_split_pairs(captures, quick=False, seed=0))["car.ply-3"]()
    assert len(small[0]) + len(small[1]) <= 1000 < len(whole[0]) + len(whole[1])
    quick_small = dict(real_split_pairs(captures, quick=True, seed=0))["car.ply-3"]()
    assert np.allclose(small[2].matrix(), quick_small[2].matrix())  # drawn down alike in either mode
    assert np.array_equal(small[0].means, quick_small[0].means)
    for bad in ("x", "50", "-3"):
        monkeypatch.setenv("GSA_REAL_GAUSSIANS", bad)
        with pytest.raises(ValueError, match="GSA_REAL_GAUSSIANS"):
            rc.gaussian_cap(False)
    monkeypatch.delenv("GSA_REAL_GAUSSIANS")
    for bad in ("0", "x", "5:5", "a:3"):
        monkeypatch.setenv("GSA_REAL_PAIRS", bad)
        with pytest.raises(ValueError, match="GSA_REAL_PAIRS"):
            rc.pair_range(False)
    monkeypatch.setenv("GSA_REAL_VARIANTS", "as-captured,sunset")
    with pytest.raises(ValueError, match="sunset"):
        rc.variants()


def test_per_capture_breakdown_lists_misses_with_their_flag():
    from benchmarks.real_captures import per_capture, per_capture_table

    def rec(cap, k, rre, doubtful=False, **more):
        return {
            "pair": f"{cap}-{k}",
            "category": cap,
            "rre_deg": rre,
            "doubtful": doubtful,
            "seconds": 2.0 + k,
            "source_gaussians": 1000 + k,
            "target_gaussians": 900 + k,
            **more,
        }

    records = [
        rec("a.spz", 0, 0.1),
        rec("a.spz", 1, 179.5, True),
        rec("b.sog", 0, 0.2),
        rec("b.sog", 1, float("nan"), error="ValueError: x"),
    ]
    caps = per_capture(records)
    assert caps["a.spz"]["successes"] == 1 and caps["a.spz"]["misses"] == [
        {"pair": "a.spz-1", "rre_deg": 179.5, "doubtful": True}
    ]
    assert caps["b.sog"]["misses"][0]["error"] == "ValueError: x" and caps["a.spz"]["median_seconds"] == 2.5
    table = per_capture_table([{"method": "GSA · as captured", "per_capture": caps}])
    assert "| a.spz | 950 | 2 | 1/2 (50 %) | 179.5 D | 2.5 |" in table and "failed" in table
