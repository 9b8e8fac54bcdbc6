"""What `align()` returns (gsa.align.types re-exports it beside AlignOptions). Its own module:
the scene path builds results, and gsa.align.types imports the criteria, which the scene path's
options belong to."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gsa.align.coarse import CoarseResult
from gsa.align.verdict import Verdict, is_number, merged_record, split_record
from gsa.canonical import CanonicalFrame
from gsa.sim3 import Sim3

if TYPE_CHECKING:
    from gsa.align.fine import FineResult


@dataclass
class AlignmentResult:
    """What `align()` found; `to_dict()` is the result.json layout.

    Attributes:
        transform: maps source coordinates into the target frame.
        coarse: the coarse stage's result (its transform is `transform` when no fine stage ran).
        features: which features guided the alignment.
        stages: the stages that ran (AlignOptions.stages resolved; ("photo",) when the
            photos' matched texture gave the pose, gsa.align.photo).
        metrics: GT-free quality numbers only (int or float: confidence, inlier_fraction,
            score, margin, ...); a measure that did not apply (None) is in `diagnostics`.
        timings: seconds per step ("features", "hypotheses", "coarse", "fine", "metrics", "total", ...).
        hypotheses: the scored initialisations.
        fine: the fine stage's result when it ran.
        lifting: gsa.features LiftReports (as dicts) when features were lifted.
        source_frame: the source's canonical frame as chosen (axes re-labelled).
        target_frame: the target's canonical frame.
        verdict: how sure align() is, why not, and the poses worth picking instead (typed).
        diagnostics: the rest of align()'s record: flags and labels (hypothesis, ranked_by),
            reports (scene, frame_snap, frame_choice, guidance, semantic, photo_match, ...) and
            measures that did not apply (None).
        record_order: the record's key order, which result.json's `metrics` keeps (None for a
            result built from its parts).

    Built with `metrics` as align()'s working record (result.json's `metrics` layout: numbers,
    verdict and reports in one dict), or with no verdict, the record is split into the three: its
    verdict and diagnostics replace any given (dataclasses.replace(result, metrics=record) too).
    """

    transform: Sim3  # maps source coordinates into the target frame
    coarse: CoarseResult
    features: str  # which features guided the alignment
    stages: tuple[str, ...] = ("coarse",)  # the stages that ran (AlignOptions.stages resolved)
    metrics: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    hypotheses: list[dict] = field(default_factory=list)
    fine: FineResult | None = None  # when the fine stage ran
    lifting: list[dict] = field(default_factory=list)  # gsa.features LiftReports when features were lifted
    source_frame: CanonicalFrame | None = None
    target_frame: CanonicalFrame | None = None
    verdict: Verdict | None = None
    diagnostics: dict = field(default_factory=dict)
    record_order: tuple[str, ...] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.verdict is None or not all(is_number(v) for v in self.metrics.values()):
            self.set_record(self.metrics)

    def record(self) -> dict:
        """result.json's `metrics` object: numbers, verdict and diagnostics merged, in the order
        align()'s record had them (a new dict)."""
        return merged_record(self.metrics, self.verdict, self.diagnostics, self.record_order)

    def set_record(self, record: Mapping) -> None:
        """Replace metrics, verdict and diagnostics by a record of result.json's `metrics` layout."""
        self.metrics, self.verdict, self.diagnostics, self.record_order = split_record(record)

    def to_dict(self) -> dict:
        out = self.transform.to_dict()
        stages = {
            "coarse": {
                **self.coarse.transform.to_dict(),
                "iterations": self.coarse.iterations,
                "converged": self.coarse.converged,
                "matched": self.coarse.matched,
                "candidate_pairs": self.coarse.candidates,
                "history": self.coarse.history,
            }
        }
        if self.fine is not None:
            fine = self.fine
            stages["fine"] = {
                **fine.transform.to_dict(),
                "loss_history": [float(v) for v in fine.loss_history],
                "best_loss": float(fine.best_loss),
                "best_iteration": int(fine.best_iteration),
            }
        out.update(
            metrics=self.record(),
            timings=self.timings,
            features=self.features,
            stages_run=list(self.stages),
            hypotheses=self.hypotheses,
            stages=stages,
        )
        if self.lifting:
            out["lifting"] = self.lifting
        return out
