"""A doubtful answer decided by the learned canonical head (gsa.align.orient): each model's pose
in its category's canonical frame gives a pose between them with no search, source -> canonical
-> target. The search's own poses are geometric local optima; the learned pose picks among them
(the nearest within `pick_deg`) and, where none is near, is itself refined by the anchors' ICP.

Where the learned pose agrees with the geometric answer, the answer is kept as it was and the
hand-made chain after it (the frame snap and relabelling choice, gsa.align.frame_snap) is not
run: that chain was fitted to the boxy development categories and moved same-object pairs (a
model against a bent copy of itself) off right answers. Where both models' fits are unsure the
route steps aside and the older chain runs.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

from gsa.align.robust.poses import rotation_offset_deg
from gsa.model import GaussianModel
from gsa.sim3 import Sim3


@dataclass(frozen=True)
class LearnedCriteria:
    pick_deg: float = 25.0  # a search pose this near the learned one is taken in its place
    agree_deg: float = 15.0  # the geometric answer this near the learned pose: kept
    confident_deg: float = 8.0  # ... this near, with both fits confident: the verdict says confident
    refined_leash_deg: float = 30.0  # the ICP from the learned pose may move it this far


class OrientCache:
    """Each model's OrientResult, the last `kept` models, keyed by geometry (what its views show)."""

    def __init__(self, kept: int = 8):
        self.kept = kept
        self._entries: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def orient(self, model: GaussianModel, seed: int):
        from gsa.align.orient import OrientCriteria, orient
        from gsa.align.semantic import geometry_digest

        key = (geometry_digest(model), seed)
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
        result = orient(model, OrientCriteria(), seed=seed)
        with self._lock:
            self._entries[key] = result
            while len(self._entries) > self.kept:
                self._entries.popitem(last=False)
        return result

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


ORIENTS = OrientCache()


def _models_oriented(pair):
    return ORIENTS.orient(pair.source, pair.opts.seed), ORIENTS.orient(pair.target, pair.opts.seed)


def learned_answer(pair, search, transform: Sim3, metrics: dict, criteria: LearnedCriteria = LearnedCriteria()):
    """(transform, metrics) decided by the learned poses, or None (with the reason in
    metrics["learned"]) where they cannot decide."""
    from gsa.align.semantic import available_backbone
    from gsa.errors import GSAError
    from gsa.features.nocs import load_head
    from gsa.sim3 import DegenerateCorrespondencesError

    try:
        if load_head() is None or available_backbone() is None:
            return None, {"used": False, "reason": "no canonical head or backbone installed"}
        src, dst = _models_oriented(pair)
    except (DegenerateCorrespondencesError, GSAError, ValueError) as exc:  # unreadable weights, too few patches
        return None, {"used": False, "reason": str(exc)}
    from gsa.align.orient import relative_pose

    report = {
        "source_confidence": round(src.inlier_share, 4),
        "target_confidence": round(dst.inlier_share, 4),
    }
    if not (src.confident and dst.confident):
        return None, report | {"used": False, "reason": "a model's canonical pose is unsure"}
    learned = pair.constrain(relative_pose(src, dst))
    offset = rotation_offset_deg(transform, learned)
    report["answer_offset_deg"] = round(offset, 2)
    if offset <= criteria.agree_deg:
        out = metrics | {"learned": report | {"used": True, "outcome": "agrees with the geometric answer"}}
        if offset <= criteria.confident_deg:
            out["doubtful"] = False
        return transform, out
    near = [c for c in search.candidates if rotation_offset_deg(c.transform, learned) <= criteria.pick_deg]
    if near:
        start = max(near, key=lambda c: c.score).transform
        how = "a search pose near the learned one"
    else:
        start = learned
        how = "the learned pose"
    refined = pair.constrain(pair.refinement.refine_global(start, None).transform)
    if rotation_offset_deg(refined, learned) > criteria.refined_leash_deg:
        refined = start
    previous = {"origin": "geometric answer (before the learned pose)", "transform": transform.matrix().tolist()}
    updated = metrics | pair.judge.verdict(refined, search)
    updated["alternatives"] = [previous] + list(updated.get("alternatives") or [])
    updated["doubtful"] = True  # the learned pose overruled the geometry: a person should look
    return refined, updated | {"learned": report | {"used": True, "outcome": f"turned onto {how}"}}
