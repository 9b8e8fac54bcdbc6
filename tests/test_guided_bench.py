"""`gsa bench guided` (benchmarks.guided): the hints it simulates are what they claim to be, and
its table judges each row by its required share."""

import numpy as np

from benchmarks.guided import (
    BARS,
    PICKED,
    ROWS,
    START_OFF_DEG,
    WRONG_UP_DEG,
    _passed,
    format_guided,
    with_guidance,
)
from gsa.align.guided import pairs_transform
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3


def _pairs(cross_instance: bool):
    def make():
        truth = random_sim3(np.random.default_rng(3))
        source = make_object("car", seed=1, n_gaussians=3000, sample_seed=1)
        target = make_object("car", seed=2 if cross_instance else 1, n_gaussians=3000, sample_seed=2)
        return source, target.transformed(truth), truth

    return [("car-0", make)]


def _angle(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_hints_are_made_from_the_truth_as_the_protocol_says():
    up = np.array([0.0, 0.0, 1.0])
    for cross_instance in (False, True):
        ((label, make),) = with_guidance(_pairs(cross_instance), "kind", up, cross_instance, seed=0)
        source, target, truth = make()
        hints = target.metadata["guidance"]
        assert label == "kind:car-0"
        start = Sim3.from_matrix(np.asarray(hints["init"]["init_transform"]))
        assert abs(rre_deg(start.rotation, truth.rotation) - START_OFF_DEG) < 1e-6
        src_up, dst_up = hints["up"]["up_axes"]
        assert _angle(truth.rotation @ np.asarray(src_up), dst_up) < 1e-6
        assert abs(_angle(hints["wrong_up"]["up_axes"][1], dst_up) - WRONG_UP_DEG) < 1e-6
        a, b = (np.asarray(p) for p in hints["pairs"]["point_pairs"])
        assert a.shape == b.shape == (PICKED, 3)
        # Clicks on corresponding parts: their fit is near the truth, a few degrees off at most
        # (2 % noise; between two instances, proportions differ too).
        fit, _ = pairs_transform(a, b)
        assert rre_deg(fit.rotation, truth.rotation) < (25.0 if cross_instance else 12.0)
        assert "symmetry_rotations" in target.metadata


def test_each_row_passes_by_its_own_rule_and_the_table_says_which():
    assert not _passed("default", {"rre_deg": 170.0, "closest_alternative_rre_deg": 9.0})
    assert _passed("default", {"rre_deg": 170.0, "closest_alternative_rre_deg": 2.0})
    assert not _passed("init", {"rre_deg": 4.0}) and _passed("up", {"rre_deg": 4.0})
    assert _passed("wrong_up", {"rre_deg": 90.0, "doubtful": True})
    assert not _passed("wrong_up", {"rre_deg": 90.0, "doubtful": False})
    assert not _passed("pairs", {"error": "ValueError", "rre_deg": float("nan")})
    rows = [
        {
            "method": ROWS[hint],
            "hint": hint,
            "passed_by_group": {"partial": 1.0, "category-real": 0.5},
            "passed_rate": 0.75,
            "median_rre_deg": 1.0,
            "records": [{"group": "partial"}, {"group": "category-real"}],
        }
        for hint in ROWS
    ]
    table = format_guided(rows)
    for hint in ROWS:
        assert ROWS[hint] in table
    assert f"{BARS['up'] * 100:.0f} %" in table and "50 %" in table
