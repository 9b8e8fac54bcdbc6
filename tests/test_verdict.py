"""The typed verdict (gsa.align.verdict) read from metrics as result.json keeps them."""

import json

import numpy as np

from gsa.align import Alternative, Verdict
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
