"""The verdict of an alignment, typed: how sure align() is of its answer, why not, and the poses
worth picking instead (AlignmentResult.verdict, a stored field). `split_record` splits align()'s
working record into numbers, the verdict and the rest; `merged_record` puts them back in the
record's key order, which is result.json's `metrics` object (docs/usage.md). `Verdict.from_metrics`
reads that object back, so a result read from JSON gives the same verdict."""

from __future__ import annotations

import numbers
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from gsa.sim3 import Sim3

# The record's keys that the verdict holds (confidence, a number, stays in `metrics` too).
VERDICT_KEYS = ("doubtful", "ambiguous", "alternatives")


def is_number(value) -> bool:
    """An int or float (NumPy's too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class Alternative:
    """A pose offered beside the answer (result.json's metrics["alternatives"][k]); `details` is
    that entry whole, every key it carries (geometry, semantic_score, file_transform, ...)."""

    transform: Sim3 | None  # source -> target in align()'s frame (init_transform takes it back); None: unreadable
    origin: str  # where it came from: "flip:axis0", "the given start", "frame relabelling", ...
    tied: bool  # it scores within the search's tie of the answer (what makes a result ambiguous)
    rotation_offset_deg: float | None  # how far it turns from the answer
    scale_ratio: float | None  # its scale over the answer's
    score: float | None  # the search's score, where it was scored
    details: Mapping = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_dict(cls, d: Mapping) -> Alternative:
        def number(key: str) -> float | None:
            value = d.get(key)
            return float(value) if is_number(value) else None

        try:
            transform = Sim3.from_matrix(np.asarray(d["transform"], np.float64))
        except (KeyError, TypeError, ValueError):  # an entry without a readable pose keeps its details
            transform = None
        return cls(
            transform=transform,
            origin=str(d.get("origin", "")),
            tied=bool(d.get("tied", False)),
            rotation_offset_deg=number("rotation_offset_deg"),
            scale_ratio=number("scale_ratio"),
            score=number("score"),
            details=dict(d),
        )

    def to_dict(self) -> dict:
        """The entry as result.json writes it: `details` as given, else the typed fields."""
        if self.details:
            return dict(self.details)
        out = {"origin": self.origin, "tied": self.tied}
        if self.transform is not None:
            out["transform"] = self.transform.matrix().tolist()
        for key in ("rotation_offset_deg", "scale_ratio", "score"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out


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
        """The verdict in a record of result.json's `metrics` layout (or align()'s working record)."""
        confidence = metrics.get("confidence")
        confidence = float(confidence) if is_number(confidence) else float("nan")
        doubtful = bool(metrics.get("doubtful", False))
        ambiguous = bool(metrics.get("ambiguous", False))
        alternatives = tuple(Alternative.from_dict(a) for a in metrics.get("alternatives") or [])
        return cls(confidence, doubtful, ambiguous, _reason(metrics, doubtful, ambiguous, confidence), alternatives)

    def entries(self) -> dict:
        """The verdict's keys of result.json's `metrics` (confidence is among the numbers)."""
        return {
            "doubtful": self.doubtful,
            "ambiguous": self.ambiguous,
            "alternatives": [a.to_dict() for a in self.alternatives],
        }


def split_record(record: Mapping) -> tuple[dict, Verdict, dict, tuple[str, ...]]:
    """align()'s working record as (metrics, verdict, diagnostics, key order): metrics the
    entries that are numbers (int or float, not bool; an entry that is None is not a number and
    goes to diagnostics), the verdict from the record, diagnostics every other entry but the
    verdict's (booleans, labels, reports such as frame_snap, guidance, scene), and the record's
    key order, which `merged_record` keeps."""
    metrics, diagnostics = {}, {}
    for key, value in record.items():
        if key in VERDICT_KEYS:
            continue
        (metrics if is_number(value) else diagnostics)[key] = value
    return metrics, Verdict.from_metrics(record), diagnostics, tuple(record)


def merged_record(metrics: Mapping, verdict: Verdict, diagnostics: Mapping, order: Iterable[str] | None = None) -> dict:
    """result.json's `metrics` object: the three parts merged in `order` (the working record's),
    then keys added since (numbers, the verdict's, diagnostics). A verdict key is written where
    the order has it; one the order lacks, where it is true or non-empty, or always for a result
    built from its parts (no order)."""
    entries = verdict.entries()
    pool = {**metrics, **diagnostics}
    out = {}
    for key in order or ():
        if key in entries:
            out[key] = entries[key]
        elif key in pool:
            out[key] = pool[key]
    for key, value in metrics.items():
        out.setdefault(key, value)
    for key, value in entries.items():
        if key not in out and (value or order is None):
            out[key] = value
    for key, value in diagnostics.items():
        out.setdefault(key, value)
    return out


def _reason(metrics: Mapping, doubtful: bool, ambiguous: bool, confidence: float) -> str | None:
    if not doubtful:
        return None
    guidance = metrics.get("guidance")
    if isinstance(guidance, Mapping) and isinstance(guidance.get("doubt"), str):
        return guidance["doubt"]
    if ambiguous:
        return "another pose fits the models as well as this one (see alternatives)"
    share = metrics.get("coincident_share")
    if metrics.get("overlap_unconfirmed") and is_number(share):
        return (
            f"the models overlap at this pose but only {share:.0%} of the overlap coincides: they may lie "
            "near each other without being aligned (see alternatives)"
        )
    return f"low confidence ({confidence:.2f})"
