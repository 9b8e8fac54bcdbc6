"""The verdict of an alignment, typed: how sure align() is of its answer, why not, and the poses
worth picking instead (AlignmentResult.verdict). Read from the result's metrics, which keep the
result.json layout (docs/usage.md), so a result read back from JSON gives the same verdict."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gsa.sim3 import Sim3


@dataclass(frozen=True)
class Alternative:
    """A pose offered beside the answer (metrics["alternatives"][k])."""

    transform: Sim3  # source -> target in align()'s frame: what init_transform takes back
    origin: str  # where it came from: "flip:axis0", "the given start", "frame relabelling", ...
    tied: bool  # it scores within the search's tie of the answer (what makes a result ambiguous)
    rotation_offset_deg: float | None  # how far it turns from the answer
    scale_ratio: float | None  # its scale over the answer's
    score: float | None  # the search's score, where it was scored

    @classmethod
    def from_dict(cls, d: Mapping) -> Alternative:
        def number(key: str) -> float | None:
            value = d.get(key)
            return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None

        return cls(
            transform=Sim3.from_matrix(np.asarray(d["transform"], np.float64)),
            origin=str(d.get("origin", "")),
            tied=bool(d.get("tied", False)),
            rotation_offset_deg=number("rotation_offset_deg"),
            scale_ratio=number("scale_ratio"),
            score=number("score"),
        )


@dataclass(frozen=True)
class Verdict:
    """confidence in [0, 1]; doubtful: a person should look (ambiguous, or confidence under the
    threshold, or guidance the models contradict); reason: why, in words (None when confident);
    alternatives: the poses worth picking, listed for a doubtful or guided answer (and for every
    answer with AlignOptions(alternatives="always"))."""

    confidence: float
    doubtful: bool
    ambiguous: bool
    reason: str | None
    alternatives: tuple[Alternative, ...]

    @classmethod
    def from_metrics(cls, metrics: Mapping) -> Verdict:
        confidence = float(metrics.get("confidence", float("nan")))
        doubtful = bool(metrics.get("doubtful", False))
        ambiguous = bool(metrics.get("ambiguous", False))
        alternatives = tuple(Alternative.from_dict(a) for a in metrics.get("alternatives") or [])
        return cls(confidence, doubtful, ambiguous, _reason(metrics, doubtful, ambiguous, confidence), alternatives)


def _reason(metrics: Mapping, doubtful: bool, ambiguous: bool, confidence: float) -> str | None:
    if not doubtful:
        return None
    guidance = metrics.get("guidance")
    if isinstance(guidance, Mapping) and isinstance(guidance.get("doubt"), str):
        return guidance["doubt"]
    if ambiguous:
        return "another pose fits the models as well as this one (see alternatives)"
    return f"low confidence ({confidence:.2f})"
