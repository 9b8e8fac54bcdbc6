"""The typed verdict (gsa.align.verdict) read from metrics as result.json keeps them."""

import copy
import json

import numpy as np
import pytest

from gsa.align import Alternative, Verdict
from gsa.align.result import AlignmentResult
from gsa.align.verdict import VERDICT_KEYS, is_number, merged_record, split_record
from gsa.sim3 import Sim3


def test_verdict_reads_a_guided_doubt_and_its_alternatives_from_result_json():
    turned = Sim3(2.0, np.diag([1.0, -1.0, -1.0]), np.array([0.5, 0.0, 0.0]))
    metrics = json.loads(
        json.dumps(
            {
                "confidence": 0.2,
                "doubtful": True,
                "ambiguous": False,
                "guidance": {"doubt": "the models fit better at another pose"},
                "alternatives": [
                    {"origin": "the given start", "transform": turned.matrix().tolist(), "rotation_offset_deg": 180.0},
                    {"origin": "flip:axis0", "transform": np.eye(4).tolist(), "tied": True, "score": 0.9},
                ],
            }
        )
    )
    v = Verdict.from_metrics(metrics)
    assert v.doubtful and not v.ambiguous and v.confidence == 0.2
    assert v.reason == "the models fit better at another pose"
    first, second = v.alternatives
    assert isinstance(first, Alternative) and first.origin == "the given start" and not first.tied
    assert np.allclose(first.transform.matrix(), turned.matrix()) and abs(first.transform.scale - 2.0) < 1e-12
    assert first.rotation_offset_deg == 180.0 and first.score is None
    assert second.tied and second.score == 0.9


def test_a_low_confidence_verdict_says_so_and_a_confident_one_gives_no_reason():
    assert Verdict.from_metrics({"confidence": 0.31, "doubtful": True}).reason == "low confidence (0.31)"
    confident = Verdict.from_metrics({"confidence": 0.93, "doubtful": False, "alternatives": []})
    assert confident.reason is None and confident.alternatives == () and not confident.doubtful


def _grey(model):
    out = model.subset(np.arange(len(model)))
    out.sh[:, 0, :] = 0.3
    return out


def _same_verdict(a: Verdict, b: Verdict) -> bool:
    def alt(x: Alternative) -> tuple:
        return (x.origin, x.tied, x.rotation_offset_deg, x.scale_ratio, x.score, json.dumps(x.details))

    return (a.confidence, a.doubtful, a.ambiguous, a.reason) == (b.confidence, b.doubtful, b.ambiguous, b.reason) and [
        alt(x) for x in a.alternatives
    ] == [alt(x) for x in b.alternatives]


@pytest.mark.parametrize("kind", ["doubtful", "confident"])
def test_a_result_keeps_only_numbers_in_metrics_and_writes_result_json_as_before(kind, monkeypatch):
    """align()'s working record is split into metrics (numbers), the typed verdict and the
    diagnostics; result.json's metrics object is that record as it was, key order included, and
    reading it back gives the same verdict."""
    from gsa.align import result as result_module
    from gsa.align.pipeline import align
    from gsa.synth import make_object, random_sim3
    from gsa.synth.variants import make_symmetric_object

    records = []
    split = result_module.split_record
    monkeypatch.setattr(
        result_module, "split_record", lambda record: (records.append(copy.deepcopy(record)), split(record))[1]
    )
    if kind == "doubtful":  # a grey symmetric object: geometry cannot pick among its poses
        truth = random_sim3(np.random.default_rng([1, 9]))
        source = _grey(make_symmetric_object(seed=1, n_gaussians=3000, sample_seed=11))
        target = _grey(make_symmetric_object(seed=1, n_gaussians=3000, sample_seed=12)).transformed(truth)
    else:
        source = make_object("car", seed=3, n_gaussians=3000)
        target = source.transformed(random_sim3(np.random.default_rng(5)))
    result = align(source, target)
    assert result.verdict.doubtful is (kind == "doubtful")
    assert kind == "confident" or result.verdict.alternatives
    assert result.metrics and all(is_number(v) for v in result.metrics.values()), result.metrics
    assert not set(result.metrics) & set(result.diagnostics) and not set(VERDICT_KEYS) & set(result.diagnostics)
    assert all(not is_number(v) for v in result.diagnostics.values())
    written = result.to_dict()["metrics"]
    assert json.dumps(written) == json.dumps(records[-1])  # same keys, values and order as align()'s record
    read_back = Verdict.from_metrics(json.loads(json.dumps(written)))
    assert _same_verdict(read_back, result.verdict)
    again = AlignmentResult(result.transform, result.coarse, result.features, metrics=json.loads(json.dumps(written)))
    assert json.dumps(again.to_dict()["metrics"]) == json.dumps(written)
    assert _same_verdict(again.verdict, result.verdict) and again.metrics == result.metrics


def test_the_record_keeps_its_order_when_entries_change_or_are_added():
    record = {"confidence": 0.4, "doubtful": True, "margin": None, "scene": {"ran": False}, "ambiguous": False}
    metrics, verdict, diagnostics, order = split_record(record)
    assert metrics == {"confidence": 0.4} and diagnostics == {"margin": None, "scene": {"ran": False}}
    assert verdict.doubtful and verdict.alternatives == () and order == tuple(record)
    assert list(merged_record(metrics, verdict, diagnostics, order)) == list(record)  # no "alternatives" added
    r = AlignmentResult(Sim3.identity(), None, "none", metrics=record)
    r.diagnostics["photo_match"] = {"accepted": False}
    r.set_record(r.record() | {"alternatives": [{"origin": "x", "transform": np.eye(4).tolist(), "extra": 1}]})
    assert list(r.record()) == [*record, "photo_match", "alternatives"]
    assert r.verdict.alternatives[0].details["extra"] == 1 and r.verdict.alternatives[0].origin == "x"
    built = AlignmentResult(Sim3.identity(), None, "none", metrics={"confidence": 0.9}, verdict=verdict)
    assert built.record() == {"confidence": 0.9, "doubtful": True, "ambiguous": False, "alternatives": []}
