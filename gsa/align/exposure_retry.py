"""A doubtful answer aligned again in the exposure its own close pairs give.

robust.match_exposure finds an exposure change from the two palettes alone (no pose). On
captures whose surfaces are greys and browns everywhere (a room) no gain passes its tests, and
elsewhere the palettes of two partial halves can pass a gain a fifth of a stop to most of a stop
off the true one (a bouquet, a rock, a statue); either way the colour term then counts the
truth's pairs as disagreeing, and the truth loses to a pose tens of degrees off. Even a wrong
answer pairs surfaces of one kind, so its close pairs' colour ratio (robust.pose_gain) lies
nearer the exposure's (docs/benchmarks.md, "The gain at a pose"). Where the answer is doubtful
and its pairs' gain differs from the one it was scored under (the palettes', or none) by more
than PaletteOptions.retry_gain_stops in some channel, within the bounds match_exposure keeps (so
two instances of other paints are left alone), the pair is aligned again with the source in
that exposure; the second answer is kept where it scores higher, both poses scored on the
second pass's anchors, and the other is offered as an alternative.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gsa.align import frame_snap, robust
from gsa.align.types import AlignmentResult, AlignOptions
from gsa.model import GaussianModel
from gsa.sim3 import Sim3

RETRY = "aligned again in the answer's exposure"
FIRST = "before the exposure retry"


def gain_to_try(src: robust.Anchors, dst: robust.Anchors, result: AlignmentResult, opts: AlignOptions):
    """The linear-RGB gain (source onto target) to align again under, from the models' anchors
    as recorded, or None where the rule does not apply: a confident answer, too few close
    pairs, or a gain the retry does not take (gain_to_retry)."""
    if result.verdict is None or not result.verdict.doubtful:
        return None
    palette = opts.criteria.pose.palette
    found = np.asarray(robust.exposure_gain(*robust.match_exposure(src, dst, palette)))
    at_answer = robust.pose_gain(src, dst, result.transform.apply(src.points), opts.criteria.pose.colour_pair_distance)
    return None if at_answer is None else gain_to_retry(found, at_answer, palette)


def gain_to_retry(found: np.ndarray, at_answer: np.ndarray, palette: robust.PaletteOptions) -> np.ndarray | None:
    """`at_answer` (the gain the answer's close pairs give), where it differs from `found` (the
    gain the answer was scored under: the palettes', 1 where they found none) by more than
    palette.retry_gain_stops in some channel and stays within match_exposure's bounds (gain and
    white balance); else None."""
    stops = np.abs(np.log2(at_answer / found))
    if stops.max() <= palette.retry_gain_stops:
        return None
    if np.abs(np.log2(at_answer)).max() > np.log2(palette.max_exposure_gain):
        return None
    if at_answer.max() / at_answer.min() > palette.max_white_balance:
        return None
    return at_answer


def retried(
    source: GaussianModel,
    target: GaussianModel,
    opts: AlignOptions,
    first: AlignmentResult,
    align_again: Callable[[GaussianModel], AlignmentResult],
) -> AlignmentResult:
    """`first`, or the answer of `align_again(source in the answer's exposure)` where
    gain_to_try gives a gain and that answer scores higher; the kept one records the retry in
    metrics["exposure_retry"] and offers the other as an alternative."""
    if first.verdict is None or not first.verdict.doubtful:
        return first  # before any anchors are built: most answers end here
    target_anchors = robust.anchors(target, opts.anchor_count)
    gain = gain_to_try(robust.anchors(source, opts.anchor_count), target_anchors, first, opts)
    if gain is None:
        return first
    shifted = source.with_exposure(gain)
    second = align_again(shifted)
    k = opts.criteria.pose
    src, dst = robust.match_exposure(robust.anchors(shifted, opts.anchor_count), target_anchors, k.palette)
    noise = 0.5 * (robust.colour_noise(src, k) + robust.colour_noise(dst, k))
    weight = robust.colour_trust(src, dst, noise, k)
    scores = {
        name: robust.score_pose(src, dst, r.transform, name, weight, k).score
        for name, r in (("first", first), ("second", second))
    }
    kept, other, other_name = (second, first, FIRST) if scores["second"] > scores["first"] else (first, second, RETRY)
    report = {
        "gain": [round(float(g), 4) for g in gain],
        "first_score": round(scores["first"], 4),
        "second_score": round(scores["second"], 4),
        "kept": "second" if kept is second else "first",
        "rotation_between_deg": round(robust.rotation_offset_deg(first.transform, second.transform), 3),
    }
    record = kept.record()
    alternatives = list(record.get("alternatives") or [])
    offered = [kept.transform] + [Sim3.from_matrix(np.asarray(a["transform"], np.float64)) for a in alternatives]
    if all(robust.rotation_offset_deg(other.transform, p) > frame_snap.FRAME_SNAP_SAME_DEG for p in offered):
        alt = frame_snap.replaced_pose(other.transform, other.record(), other_name)
        alternatives.append(alt | {"rotation_offset_deg": robust.rotation_offset_deg(other.transform, kept.transform)})
    kept.set_record(record | {"alternatives": alternatives, "exposure_retry": report})
    kept.timings = first.timings | {f"exposure_retry_{step}": v for step, v in second.timings.items()}
    kept.lifting = first.lifting
    return kept
