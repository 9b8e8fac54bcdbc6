"""align() reports within its long stretches, not only between stages: a service job in embedded
mode stops at its next report, so the search's ICPs, the semantic stage's tail (the sweep's ICPs,
the picked pose's quality), the frame snap and the relabelling choice (24 relabellings, each
refitted) must each report. Every step of those loops calls gsa.render.steps.step(), which
repeats align()'s last report once it is REPEAT_S old; with REPEAT_S = 0 each step reports, and
the reports are counted by the code they came from. The reports change nothing: the pose is the
same with and without a callback."""

from __future__ import annotations

import collections
import sys

import numpy as np
import pytest

import gsa.align.pair as pair_module
from gsa.align import robust, semantic
from gsa.align.criteria import Criteria
from gsa.align.pipeline import AlignOptions, align
from gsa.synth import make_object
from tests.tiny_vit import tiny_vit

REGIONS = (
    "global_search",
    "refine_global",
    "_swept_poses",
    "snap_to_frames",
    "choose_relabelling",
    "fit_shift",
    "relabelling_agreement",
    "feature_agreement",
    "quality_metrics",
)


@pytest.fixture(scope="module")
def traced():
    """(regions counted per (stage, code), result with reports, result without) of a doubtful
    cross-instance pair (a bus against a car) with a small backbone, every step reporting."""
    mp = pytest.MonkeyPatch()
    vit = tiny_vit()
    mp.setattr(semantic, "available_backbone", lambda path=None: vit)
    mp.setattr(semantic, "MODEL_VIEWS", semantic.ModelViewCache())
    mp.setattr(pair_module, "REPEAT_S", 0.0)
    source = make_object("bus", seed=1, n_gaussians=2000)
    target = make_object("car", seed=3, n_gaussians=3000)
    counts: collections.Counter = collections.Counter()
    stages: list[str] = []

    def progress(stage: str, fraction: float) -> None:
        stages.append(stage)
        frame, names = sys._getframe(1), set()
        while frame is not None:
            names.add(frame.f_code.co_name)
            frame = frame.f_back
        for region in REGIONS:
            if region in names:
                counts[(stage, region)] += 1

    # The all-pairs fit (opt-in) leaves this pair's surfaces apart (share 0.36; 0.50 with the
    # default trimmed fit), so the answer also takes the frame snap's stretch.
    options = AlignOptions(criteria=Criteria(refine=robust.RefineCriteria(deformable=True)))
    try:
        with_reports = align(source, target, options, progress=progress)
        without = align(source, target, options)
    finally:
        mp.undo()
    return counts, stages, with_reports, without


def test_the_pair_runs_the_long_stretches(traced):
    _, stages, result, _ = traced
    assert result.verdict.doubtful and result.diagnostics["semantic"]["used"]
    assert "frame_snap" in result.diagnostics and "frame_choice" in result.diagnostics
    assert stages[-1] == "done"


def test_the_search_and_its_refinement_report_within(traced):
    counts = traced[0]
    assert counts[("hypotheses", "global_search")] >= 10  # every ICP iteration of every start
    assert counts[("hypotheses", "refine_global")] >= 3  # the full-resolution ICP's iterations


def test_the_semantic_tail_reports_within(traced):
    counts = traced[0]
    assert counts[("semantic", "_swept_poses")] >= 10  # the sweep and its ICPs
    assert counts[("semantic", "snap_to_frames")] >= 1
    # each of the 24 relabellings is refitted (manhattan.fit_shift) with a report per pass
    assert counts[("semantic", "choose_relabelling")] >= 24
    assert counts[("semantic", "fit_shift")] >= 24
    assert counts[("semantic", "feature_agreement")] == 24
    assert counts[("learned", "relabelling_agreement")] == 24


def test_reports_change_nothing(traced):
    _, _, with_reports, without = traced
    np.testing.assert_array_equal(with_reports.transform.matrix(), without.transform.matrix())
    assert with_reports.diagnostics["frame_choice"] == without.diagnostics["frame_choice"]
