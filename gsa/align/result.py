"""What `align()` returns (gsa.align.types re-exports it beside AlignOptions). Its own module:
the scene path builds results, and gsa.align.types imports the criteria, which the scene path's
options belong to."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gsa.align.coarse import CoarseResult
from gsa.align.verdict import Verdict
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
        metrics: GT-free quality numbers and the verdict (confidence, doubtful, ...).
        timings: seconds per step ("features", "hypotheses", "coarse", "fine", "metrics", "total", ...).
        hypotheses: the scored initialisations.
        fine: the fine stage's result when it ran.
        lifting: gsa.features LiftReports (as dicts) when features were lifted.
        source_frame: the source's canonical frame as chosen (axes re-labelled).
        target_frame: the target's canonical frame.
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

    @property
    def verdict(self) -> Verdict:
        """How sure align() is, why not, and the poses worth picking instead (typed; read from
        `metrics`, whose layout result.json keeps)."""
        return Verdict.from_metrics(self.metrics)

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
            metrics=self.metrics,
            timings=self.timings,
            features=self.features,
            stages_run=list(self.stages),
            hypotheses=self.hypotheses,
            stages=stages,
        )
        if self.lifting:
            out["lifting"] = self.lifting
        return out
