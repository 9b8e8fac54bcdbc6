"""Benchmark suite: tables/JSON shape of the protocols, and each peer wrapper
recovering a known Sim(3) on an easy pair.

Kept fast: the protocols run on a couple of tiny pairs (monkeypatched pair
lists), not the --quick sizes.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import peers as peers_mod
from benchmarks import protocols as P
from gsa.geometry import euler_xyz
from gsa.metrics import accuracy
from gsa.sim3 import Sim3
from gsa.synth import make_object

TABLE_COLUMNS = [
    "method",
    "mean RRE (°)",
    "mean scale err (%)",
    "success (RRE<5°)",
    "s / pair",
    "time ratio vs GSA coarse",
]


def _easy_pair(n=1500, seed=0):
    """A duplicate under a small rotation, scale 2.5 and a shift."""
    model = make_object("car", seed=seed, n_gaussians=n)
    truth = Sim3(2.5, euler_xyz(np.radians([10.0, -6.0, 8.0])), np.array([0.4, -0.2, 1.0]))
    return model, model.transformed(truth), truth


def _assert_recovers(peer, rre_deg=1.0, scale_pct=1.0):
    source, target, truth = _easy_pair()
    est = peer.register(source, target, seed=0)
    acc = accuracy(est, truth, source.means, target.means)
    assert acc["rre_deg"] < rre_deg, acc
    assert acc["scale_error_pct"] < scale_pct, acc


def test_umeyama_exact():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(50, 3))
    truth = Sim3(0.3, euler_xyz(np.radians([170.0, 20.0, -90.0])), np.array([1.0, 2.0, 3.0]))
    est = peers_mod.umeyama(x, truth.apply(x))
    assert abs(est.scale - 0.3) < 1e-9
    assert np.allclose(est.rotation, truth.rotation, atol=1e-9)
    assert np.allclose(est.translation, truth.translation, atol=1e-9)


def test_plain_icp_recovers_easy_pair():
    _assert_recovers(peers_mod.PlainICP())


def test_plain_icp_fails_on_half_turn():
    """Without features the centroid start cannot undo a 180° turn: the row in
    the tables is a real measurement, not a copy of GSA's."""
    model = make_object("car", seed=0, n_gaussians=1500)
    truth = Sim3(1.0, euler_xyz(np.radians([0.0, 0.0, 180.0])), np.zeros(3))
    est = peers_mod.PlainICP().register(model, model.transformed(truth))
    assert accuracy(est, truth, model.means, model.means)["rre_deg"] > 30.0


def test_open3d_recovers_easy_pair():
    """open3d is an optional extra (gsa[peers]) not installed in CI: importorskip."""
    pytest.importorskip("open3d")
    peer = peers_mod.Open3DFPFH()
    if peer.unavailable():
        pytest.skip(peer.unavailable())
    _assert_recovers(peer)


def test_splatreg_recovers_easy_pair():
    """splatreg is an optional extra (gsa[peers]) not installed in CI: importorskip.
    With its global initialiser on the benchmark's 300-Gaussian subsample it takes
    ≈ 16 s here (1.6°, 1.1 %); from its identity default it did not recover (12°, 75 %)."""
    pytest.importorskip("splatreg")
    _assert_recovers(peers_mod.SplatReg(), rre_deg=5.0, scale_pct=5.0)


def test_splatreg_matrix_convention():
    """splatreg is an optional extra (gsa[peers]) not installed in CI: importorskip.
    Fast check of what the wrapper relies on: our models convert to its
    Gaussians, and its 4x4 [[sR, t], [0, 1]] maps source into target."""
    pytest.importorskip("splatreg")
    import torch
    from splatreg import Gaussians, apply_transform

    source, target, truth = _easy_pair(n=200)
    g = peers_mod._to_splatreg(source, Gaussians)
    moved = apply_transform(g, torch.as_tensor(truth.matrix(), dtype=torch.float32), truth.scale)
    assert np.allclose(moved.means.numpy(), target.means, atol=1e-3 * np.abs(target.means).max())
    assert abs(Sim3.from_matrix(truth.matrix()).scale - truth.scale) < 1e-9


def test_unknown_peer_is_an_error():
    with pytest.raises(ValueError, match="unknown peer"):
        peers_mod.available_peers(["nope"])


def test_missing_peer_is_skipped_with_a_note(monkeypatch):
    monkeypatch.setattr(peers_mod.importlib.util, "find_spec", lambda name: None)
    notes = []
    got = peers_mod.available_peers(["icp", "open3d", "splatreg"], note=notes.append)
    assert [p.name for p in got] == ["icp"]
    assert len(notes) == 2 and all("skipped" in n for n in notes)


@pytest.fixture
def tiny_pairs(monkeypatch):
    """Two tiny pairs per protocol, so the whole loop runs in seconds."""

    def pairs(kind):
        def make(i):
            def f():
                model = make_object(["car", "bus"][i], seed=i, n_gaussians=800)
                rng = np.random.default_rng(i)
                truth = P.random_sim3(rng)
                return model, model.transformed(truth), truth

            return f

        return [(f"{['car', 'bus'][i]}-{i}" + ("-1" if kind == "category" else ""), make(i)) for i in range(2)]

    monkeypatch.setattr(P, "dup_pairs", lambda quick, seed: pairs("dup"))
    monkeypatch.setattr(P, "same_pairs", lambda quick, seed: pairs("same"))
    monkeypatch.setattr(P, "category_pairs", lambda quick, seed, instances=None: pairs("category"))
    for kind in ("partial", "noisy", "symmetric", "deform"):
        monkeypatch.setattr(P, f"{kind}_pairs", lambda quick, seed, kind=kind: pairs(kind))
    # The fine stage renders: far too slow for a unit test; its rows are covered by the quick run.
    monkeypatch.setattr(P, "FINE_ROWS", False)


@pytest.mark.parametrize("name", ["dup", "same", "category", "partial", "noisy", "symmetric", "deform"])
def test_protocol_table_and_json(tiny_pairs, tmp_path, capsys, name):
    P.run_protocols([name], quick=True, out=str(tmp_path), peers=["icp"])
    text = capsys.readouterr().out
    for col in TABLE_COLUMNS:
        # Cross-instance pairs have no single true scale (paper Sec. 4.3): RRE only.
        if not (name == "category" and "scale" in col):
            assert col in text
    data = json.loads((tmp_path / f"{name}.json").read_text())
    rows = {r["method"]: r for r in data["rows"]}
    assert set(rows) == {P.GSA_COARSE, peers_mod.PlainICP.label}
    gsa = rows[P.GSA_COARSE]
    assert gsa["pairs"] == 2 and gsa["time_ratio_vs_gsa_coarse"] == 1.0
    assert gsa["mean_rre_deg"] < 1.0 and gsa["success_rate"] == 1.0  # duplicates: GSA must succeed
    for r in rows.values():
        for key in ("mean_rre_deg", "mean_scale_error_pct", "success_rate", "seconds_per_pair"):
            assert key in r
    if name == "category":
        assert set(gsa["per_category_mean_rre_deg"]) == {"car", "bus"}
        assert "car RRE (°)" in text
    # GSA rows carry align()'s flag; the calibration is under the table and over all protocols run
    assert {"confidence", "doubtful"} <= set(gsa["records"][0]) and "flagged_rate" in gsa
    assert "flagged_rate" not in rows[peers_mod.PlainICP.label]
    assert "Confidence calibration (success = RRE < 5°):" in text
    assert f"Confidence calibration, {P.GSA_COARSE}, over {name}: 2 results" in text
    if name == "symmetric":  # tiny pairs are not symmetric objects: only the identity pose counts
        assert "success, any symmetric pose (RRE<5°)" in text
        assert gsa["success_rate_any_symmetric"] == gsa["success_rate"]


@pytest.mark.slow
def test_ablation_rows(tiny_pairs, tmp_path, capsys):
    P.run_protocols(["ablation"], quick=True, out=str(tmp_path))
    rows = {r["method"]: r for r in json.loads((tmp_path / "ablation.json").read_text())["rows"]}
    assert {label for label, _ in P.ABLATION_COARSE} <= set(rows)
    assert "features off (plain ICP, centroid/RMS start)" in rows
    assert rows["coarse (default: feature stage + NN refinement)"]["mean_rre_deg"] < 1.0


def test_failed_peer_counts_as_failure():
    rows = P.summarise(
        "x",
        "m",
        [
            {"pair": "a", "seconds": 1.0, "rre_deg": 1.0, "scale_error_pct": 0.0, "ate_normalized": 0.0},
            {"pair": "b", "seconds": 1.0, "error": "boom", "rre_deg": float("nan")},
        ],
    )
    assert rows["failed"] == 1 and rows["success_rate"] == 0.5


def test_unknown_protocol():
    with pytest.raises(ValueError, match="unknown protocol"):
        P.run_protocols(["nope"])


def test_deform_symmetric_pairs_bend_the_target_of_one_symmetric_object():
    """Two captures of one symmetric object, the target bent: same family and k as the
    symmetric protocol's pair, the target carrying the bend it was given."""
    label, make = P.deform_symmetric_pairs(True, 0)[0]
    plain_label, plain_make = P.symmetric_pairs(True, 0)[0]
    source, target, truth = make()
    plain_source, plain_target, plain_truth = plain_make()
    assert label == plain_label and np.allclose(truth.matrix(), plain_truth.matrix())
    assert "deform" in target.metadata and "deform" not in plain_target.metadata
    assert np.allclose(source.means, plain_source.means)
    assert not np.allclose(target.means, plain_target.means)
