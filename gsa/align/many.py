"""Many models into one frame (N-way registration): pairwise alignments over a graph of edges, then a
global step over Sim(3) that makes them agree around the cycles they close.

An edge (i, j) holds T_ij with model_j ≈ T_ij(model_i), its confidence, doubtful flag and
alternatives (align()'s metrics). The global step finds X_k (model k into the reference
frame) with X_i ≈ X_j ∘ T_ij for every edge:

0. a consensus over each edge's poses (consensus_rotations): the pose each edge enters the
   least squares with is the one that agrees with the rotations its edges, summed, find most
   plausible (an alternative there is a correction); a pose's plausibility is the share of
   the models' local-shape pairs it holds where any of the edge's poses holds (two captures of
   one object), else its semantic score (pose_weights);
1. every model is first put in a normalised frame (centroid at 0, RMS radius 1), so that
   translation residuals are fractions of the model's size and scales are near 1;
2. initialisation: a maximum spanning tree over each edge's triangle support (how many
   triangles through it close within tolerance) and confidence, so one confident but wrong
   edge is not trusted just because align() was sure of it;
3. IRLS: chordal rotation averaging (linear least squares, then projection onto SO(3)),
   log-scale and translation least squares, each edge weighted by its confidence times a
   Cauchy weight of its residual against the current solution; an edge beyond PRUNE
   tolerances gets weight 0 (a line process in Open3D's sense);
4. a pruned edge whose alternative agrees with the solution is replaced by it ("corrected")
   and the IRLS runs again.

Residuals are in tolerance units: max(rotation / ROT_TOL_DEG, |log scale| / LOG_SCALE_TOL,
centroid displacement / (size · TRANS_TOL)).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from gsa.align.many_frames import (
    FrameEvidence,
    edge_targets,
    frame_evidence,
    incident_edges,
    on_cycles,
    on_frames,
    relabelled,
    synchronise,
)
from gsa.errors import GSAError
from gsa.geometry import rotation_angle
from gsa.model import GaussianModel
from gsa.sim3 import Sim3

# Tolerances of one "unit" of residual: what a right coarse alignment of partial captures stays
# within; a residual above PRUNE units is a wrong edge, between 1 and PRUNE a poor one.
ROT_TOL_DEG = 5.0
LOG_SCALE_TOL = 0.05
TRANS_TOL = 0.05
PRUNE = 3.0
# Corrected when an alternative's residual is this small: alternatives are search poses,
# refined less than the chosen one.
ACCEPT_ALTERNATIVE = 2.0
# All pairs up to this many models; beyond, each model to its SPARSE_K most similar.
ALL_PAIRS_MAX = 8
SPARSE_K = 3
# Floor of an edge's weight: a pruned edge still fixes a model no other edge reaches,
# so the least squares stay determined (that model's confidence says it is unsupported).
WEIGHT_FLOOR = 1e-6
IRLS_ITERATIONS = 15
# A model whose confidence is below this is flagged doubtful in to_dict (align()'s own flag
# sits at the same level: gsa.align.robust).
MODEL_DOUBTFUL = 0.5
# A model is contested (and flagged doubtful whatever its confidence) when the global step
# overruled one of its edges that align() was surer of, by more than this, than of every
# edge of it the solution agrees with: the cycles and the most confident measurement disagree,
# and either may be wrong (three agreeing half turns outvote one right edge).
CONTEST_MARGIN = 0.1
# A doubtful edge's pose this near the relabelling the frames' consensus gives it is taken as
# it is; farther, it is turned onto the relabelling (as frame_snap.FRAME_SNAP_SAME_DEG).
FRAME_EXACT_DEG = 2.0
EDGE_STATUSES = ("kept", "down-weighted", "pruned", "corrected")


class ManyError(GSAError, ValueError):
    """Input align_many cannot work with (fewer than two models, a bad reference, ...)."""


@dataclass
class Edge:
    """One pairwise alignment: model `target` ≈ transform(model `source`)."""

    source: int
    target: int
    transform: Sim3
    confidence: float = 1.0
    doubtful: bool = False
    ambiguous: bool = False
    alternatives: list[Sim3] = field(default_factory=list)
    # The semantic tie-break's score of the transform and of each alternative (None: not scored).
    scores: list[float | None] = field(default_factory=list)
    # The share of the local shapes' pairs the transform and each alternative hold (None: not
    # measured), and the share that counts as holding (align()'s local_agreement metrics).
    agreements: list[float | None] = field(default_factory=list)
    agreement_needed: float | None = None
    seconds: float = 0.0
    # Set by the global step:
    used: Sim3 | None = None  # the transform the solution used (an alternative when corrected)
    status: str = "kept"
    weight: float = 1.0
    residual: dict | None = None  # of `used` against the solution
    measured_residual: dict | None = None  # of `transform` (differs when corrected)
    triangle_support: float | None = None

    def to_dict(self, names: Sequence[str]) -> dict:
        return {
            "source": names[self.source],
            "target": names[self.target],
            "source_index": self.source,
            "target_index": self.target,
            "transform": self.transform.matrix().tolist(),
            "used_transform": (self.used or self.transform).matrix().tolist(),
            "confidence": self.confidence,
            "doubtful": self.doubtful,
            "ambiguous": self.ambiguous,
            "alternatives": len(self.alternatives),
            "status": self.status,
            "weight": self.weight,
            "residual": self.residual,
            "measured_residual": self.measured_residual,
            "triangle_support": self.triangle_support,
            "seconds": self.seconds,
        }


@dataclass
class ManyResult:
    names: list[str]
    reference: int
    transforms: list[Sim3]  # model k -> reference frame (gsa's internal frame, as model.transformed takes)
    confidences: list[float]
    edges: list[Edge]
    cycles: dict
    timings: dict = field(default_factory=dict)
    # Per model, the edges (indices into `edges`) that contest its transform (see CONTEST_MARGIN).
    contested: dict[int, list[int]] = field(default_factory=dict)

    def doubtful(self, k: int) -> bool:
        return self.confidences[k] < MODEL_DOUBTFUL or bool(self.contested.get(k))

    def to_dict(self) -> dict:
        return {
            "reference": self.names[self.reference],
            "models": [
                {
                    "name": name,
                    "index": k,
                    **self.transforms[k].to_dict(),
                    "confidence": self.confidences[k],
                    "doubtful": self.doubtful(k),
                    "contested_by": [
                        f"{self.names[self.edges[e].source]} -> {self.names[self.edges[e].target]}"
                        for e in self.contested.get(k, [])
                    ],
                }
                for k, name in enumerate(self.names)
            ],
            "edges": [e.to_dict(self.names) for e in self.edges],
            "pruned": [f"{self.names[e.source]} -> {self.names[e.target]}" for e in self.edges if e.status == "pruned"],
            "corrected": [
                f"{self.names[e.source]} -> {self.names[e.target]}" for e in self.edges if e.status == "corrected"
            ],
            "cycles": self.cycles,
            "timings": self.timings,
            "frame": "gsa internal (RDF); transforms map each model as read by gsa into the reference's frame",
        }


# ---------------------------------------------------------------- residuals


def _normaliser(centre: np.ndarray, size: float) -> Sim3:
    """x -> (x - centre) / size."""
    return Sim3(1.0 / size, np.eye(3), -np.asarray(centre, np.float64) / size)


def residual_of(error: Sim3) -> dict:
    """An error transform (identity when consistent) in a normalised frame, in its parts and
    in tolerance units. Its translation is the displacement of the model's centroid (0 there)
    in units of the model's size."""
    rot = float(np.degrees(rotation_angle(error.rotation)))
    log_s = float(abs(np.log(error.scale)))
    trans = float(np.linalg.norm(error.translation))
    units = max(rot / ROT_TOL_DEG, log_s / LOG_SCALE_TOL, trans / TRANS_TOL)
    return {"rotation_deg": rot, "log_scale": log_s, "translation": trans, "units": units}


def _edge_error(x: list[Sim3], i: int, j: int, t_ij: Sim3) -> Sim3:
    """T_ij⁻¹ ∘ X_j⁻¹ ∘ X_i: identity when the edge agrees with the solution."""
    return t_ij.inverse() @ x[j].inverse() @ x[i]


# ---------------------------------------------------------------- the consensus over poses

# Cross-instance, a wrong edge is mostly a half turn of the right one, and half turns agree with
# one another around cycles: a flipped member shows its flip on all its edges, so the cycles
# alone cannot tell the right frame from a wrong one (docs/benchmarks.md, n-way). What can is
# how plausible each edge found each of its poses: the semantic tie-break scores the pose it
# chose and the alternatives it offered. The consensus picks one rotation per model so that
# the plausibility of the poses the edges agree with, summed over all edges, is highest.
CONSENSUS_DEG = 15.0  # an edge agrees with two models' rotations through a pose this near
CONSENSUS_BEAM = 64  # partial assignments kept while models are added one at a time
CONSENSUS_SAME_DEG = 5.0  # candidate rotations of one model this near are one candidate


def held_poses(edge: Edge) -> np.ndarray:
    """(H,) bool: which of the edge's poses ([transform] + alternatives) its models' local
    shapes hold (align()'s local_agreement at least local_agreement_needed); none where unknown."""
    n = 1 + len(edge.alternatives)
    if edge.agreement_needed is None:
        return np.zeros(n, bool)
    shares = (list(edge.agreements) + [None] * n)[:n]
    return np.array([v is not None and v >= edge.agreement_needed for v in shares])


def pose_weights(edge: Edge) -> np.ndarray:
    """How plausible each of an edge's poses ([transform] + alternatives) is, from the edge:
    its confidence (as the global step's prior) spread over its poses. Where the models' local
    shapes hold some of them (two captures of one object, a deformed copy), over those poses by
    the share of the shapes' pairs each holds, relative to the best one; the others get none.
    Otherwise (other instances, whose local shapes do not pair) by the semantic scores relative
    to the best one; without scores all of it on the measured pose. The measured pose keeps the
    lead the tie-break gave it (its score times the switch ratio: no other pose beat that), so
    one edge alone never turns; it takes other edges agreeing with an alternative."""
    from gsa.align.semantic import SemanticCriteria

    base = max(float(edge.confidence), 0.05)
    n = 1 + len(edge.alternatives)
    held = held_poses(edge)
    if held.any():
        shares = np.array([float(v) if h else 0.0 for v, h in zip(edge.agreements, held)], np.float64)
        return base * shares / shares.max()
    scores = np.array([v if v is not None else 0.0 for v in (list(edge.scores) + [None] * n)[:n]], np.float64)
    scores = np.maximum(scores, 0.0)
    scores[0] *= SemanticCriteria().switch_ratio
    if scores.max() <= 0:
        return base * np.eye(1, n)[0]
    return base * scores / scores.max()


def _agreement(rotations: np.ndarray, relative: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(K,3,3) relative rotations R_jᵀR_i against an edge's (H,3,3) poses -> (K,) the weight of
    the most plausible pose within CONSENSUS_DEG of each (0 where none is)."""
    cos = (np.einsum("kab,hab->kh", relative, rotations) - 1.0) / 2.0
    near = cos > np.cos(np.radians(CONSENSUS_DEG))
    return np.where(near, weights[None], 0.0).max(axis=1)


def consensus_rotations(n: int, reference: int, edges: list[Edge]) -> tuple[list[np.ndarray | None], float]:
    """One rotation per model (R_ref = I; None for a model no edge reaches) maximising the
    summed plausibility (pose_weights) of the edge poses that agree with them, and that sum.
    A beam search adding models in order of their edges' weight to the models placed before."""
    rot = [_pose_rotations(e) for e in edges]
    weights = [pose_weights(e) for e in edges]
    incident = incident_edges(n, edges)
    placed, order = {reference}, []
    while True:
        pull = {
            k: sum(weights[idx].max() for idx in incident[k] if (edges[idx].source + edges[idx].target - k) in placed)
            for k in range(n)
            if k not in placed
        }
        reachable = {k: v for k, v in pull.items() if v > 0}
        if not reachable:
            break
        k = max(reachable, key=lambda m: (reachable[m], -m))
        order.append(k)
        placed.add(k)
    states: list[tuple[float, dict[int, np.ndarray]]] = [(0.0, {reference: np.eye(3)})]
    for k in order:
        grown = []
        for total, assigned in states:
            links = [idx for idx in incident[k] if (edges[idx].source + edges[idx].target - k) in assigned]
            candidates = []  # R_k through each pose of each edge to a placed model
            for idx in links:
                e = edges[idx]
                if e.source == k:  # R_ij ≈ R_jᵀ R_i  ->  R_i = R_j R_ij
                    candidates.append(np.einsum("ab,hbc->hac", assigned[e.target], rot[idx]))
                else:  # R_j = R_i R_ijᵀ
                    candidates.append(np.einsum("ab,hcb->hac", assigned[e.source], rot[idx]))
            cands = _distinct(np.concatenate(candidates))
            gain = np.zeros(len(cands))
            for idx in links:
                e = edges[idx]
                if e.source == k:
                    relative = np.einsum("ba,kbc->kac", assigned[e.target], cands)
                else:
                    relative = np.einsum("kba,bc->kac", cands, assigned[e.source])
                gain += _agreement(rot[idx], relative, weights[idx])
            grown += [(total + float(g), {**assigned, k: c}) for g, c in zip(gain, cands)]
        grown.sort(key=lambda s: -s[0])
        states = grown[:CONSENSUS_BEAM]
    best_total, best = states[0]
    return [best.get(k) for k in range(n)], best_total


def _pose_rotations(edge: Edge) -> np.ndarray:
    """(H, 3, 3): the measured pose's rotation, then each alternative's."""
    return np.stack([edge.transform.rotation] + [a.rotation for a in edge.alternatives])


def _distinct(rotations: np.ndarray) -> np.ndarray:
    """The rotations with any within CONSENSUS_SAME_DEG of an earlier one left out."""
    kept: list[np.ndarray] = []
    limit = 1.0 + 2.0 * np.cos(np.radians(CONSENSUS_SAME_DEG))
    for r in rotations:
        if all(np.sum(r * k) < limit for k in kept):
            kept.append(r)
    return np.stack(kept)


def consensus_poses(n: int, reference: int, edges: list[Edge]) -> list[int | None]:
    """Per edge, the index of the pose (0: measured, k: alternative k−1) the consensus rotations
    agree with (the most plausible such pose; the measured one on a tie), None where none does."""
    rotations, _ = consensus_rotations(n, reference, edges)
    out: list[int | None] = []
    for e in edges:
        ri, rj = rotations[e.source], rotations[e.target]
        if ri is None or rj is None:
            out.append(None)
            continue
        w = pose_weights(e)
        cos = (np.einsum("ab,hab->h", rj.T @ ri, _pose_rotations(e)) - 1.0) / 2.0
        near = np.flatnonzero(cos > np.cos(np.radians(CONSENSUS_DEG)))
        out.append(None if len(near) == 0 else int(near[np.argmax(w[near])]))
    return out


# ---------------------------------------------------------------- the global step


def _project_so3(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _solve_once(n: int, ref: int, pairs: list[tuple[int, int, Sim3]], w: np.ndarray) -> list[Sim3]:
    """Weighted least squares of X_i = X_j T_ij with X_ref = identity: chordal rotations, then
    log-scales, then translations given both."""
    others = [k for k in range(n) if k != ref]
    col = {k: c for c, k in enumerate(others)}
    m = len(others)
    sw = np.sqrt(w)
    # Rotations: R_iᵀ − R_ijᵀ R_jᵀ = 0, unknown Z_k = R_kᵀ (3×3 blocks), Z_ref = I.
    a = np.zeros((3 * len(pairs), 3 * m))
    b = np.zeros((3 * len(pairs), 3))
    for e, (i, j, t) in enumerate(pairs):
        rows = slice(3 * e, 3 * e + 3)
        for k, block in ((i, np.eye(3)), (j, -t.rotation.T)):
            if k == ref:
                b[rows] -= sw[e] * block
            else:
                a[rows, 3 * col[k] : 3 * col[k] + 3] += sw[e] * block
    z = np.linalg.lstsq(a, b, rcond=None)[0]
    rot = {ref: np.eye(3)}
    for k in others:
        rot[k] = _project_so3(z[3 * col[k] : 3 * col[k] + 3]).T
    # Log-scales: l_i − l_j = log s_ij.
    a = np.zeros((len(pairs), m))
    b = np.zeros(len(pairs))
    for e, (i, j, t) in enumerate(pairs):
        b[e] = sw[e] * np.log(t.scale)
        if i != ref:
            a[e, col[i]] += sw[e]
        if j != ref:
            a[e, col[j]] -= sw[e]
    logs = np.zeros(n)
    logs[others] = np.linalg.lstsq(a, b, rcond=None)[0]
    # Translations: t_i − t_j = s_j R_j t_ij.
    a = np.zeros((3 * len(pairs), 3 * m))
    b = np.zeros((3 * len(pairs), 1))
    for e, (i, j, t) in enumerate(pairs):
        rows = slice(3 * e, 3 * e + 3)
        b[rows, 0] = sw[e] * np.exp(logs[j]) * rot[j] @ t.translation
        for k, sign in ((i, 1.0), (j, -1.0)):
            if k != ref:
                a[rows, 3 * col[k] : 3 * col[k] + 3] += sign * sw[e] * np.eye(3)
    tr = np.linalg.lstsq(a, b, rcond=None)[0][:, 0]
    out = []
    for k in range(n):
        t = np.zeros(3) if k == ref else tr[3 * col[k] : 3 * col[k] + 3]
        out.append(Sim3(float(np.exp(logs[k])), rot[k], t))
    return out


def _oriented(edges: dict[tuple[int, int], Sim3], a: int, b: int) -> Sim3:
    return edges[(a, b)] if (a, b) in edges else edges[(b, a)].inverse()


def _triangle_support(n: int, pairs: list[tuple[int, int, Sim3]]) -> tuple[np.ndarray, list[dict]]:
    """Per edge, the share of triangles through it that close within PRUNE units (0.5 when it
    closes none: no evidence either way), and every triangle's residual."""
    by_pair = {(i, j): t for i, j, t in pairs}
    index = {}
    for e, (i, j, _) in enumerate(pairs):
        index[(i, j)] = index[(j, i)] = e
    good = np.zeros(len(pairs))
    total = np.zeros(len(pairs))
    triangles = []
    for a, b, c in itertools.combinations(range(n), 3):
        if not all(p in index for p in ((a, b), (b, c), (a, c))):
            continue
        error = _oriented(by_pair, a, c).inverse() @ _oriented(by_pair, b, c) @ _oriented(by_pair, a, b)
        r = residual_of(error)
        triangles.append({"models": [a, b, c], **r})
        for p in ((a, b), (b, c), (a, c)):
            total[index[p]] += 1
            good[index[p]] += r["units"] <= PRUNE
    support = np.where(total > 0, good / np.maximum(total, 1), 0.5)
    return support, triangles


def _spanning_tree(n: int, pairs: list[tuple[int, int, Sim3]], score: np.ndarray) -> list[int]:
    """Kruskal's maximum spanning tree (or forest): edge indices."""
    parent = list(range(n))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    tree = []
    for e in np.argsort(-score, kind="stable"):
        i, j, _ = pairs[e]
        ri, rj = root(i), root(j)
        if ri != rj:
            parent[ri] = rj
            tree.append(int(e))
    return tree


def _tree_solution(n: int, ref: int, pairs: list[tuple[int, int, Sim3]], tree: list[int]) -> list[Sim3]:
    """X along the tree from the reference (identity for models it does not reach)."""
    x: list[Sim3 | None] = [None] * n
    x[ref] = Sim3.identity()
    frontier = [ref]
    while frontier:
        k = frontier.pop()
        for e in tree:
            i, j, t = pairs[e]
            if j == k and x[i] is None:  # X_i = X_j T_ij
                x[i] = x[j] @ t
                frontier.append(i)
            elif i == k and x[j] is None:  # X_j = X_i T_ij⁻¹
                x[j] = x[i] @ t.inverse()
                frontier.append(j)
    return [Sim3.identity() if s is None else s for s in x]


def _irls(n: int, ref: int, pairs, prior: np.ndarray, x: list[Sim3]) -> tuple[list[Sim3], np.ndarray, list[dict]]:
    w = prior.copy()
    for _ in range(IRLS_ITERATIONS):
        res = [residual_of(_edge_error(x, i, j, t)) for i, j, t in pairs]
        units = np.array([r["units"] for r in res])
        # Cauchy weight inside the prune limit, the floor beyond it.
        new_w = np.where(units <= PRUNE, prior / (1.0 + units**2), WEIGHT_FLOOR)
        new_w = np.maximum(new_w, WEIGHT_FLOOR)
        x_new = _solve_once(n, ref, pairs, new_w)
        change = max(residual_of(a.inverse() @ b)["units"] for a, b in zip(x, x_new))
        x, w = x_new, new_w
        if change < 1e-4:
            break
    res = [residual_of(_edge_error(x, i, j, t)) for i, j, t in pairs]
    return x, w, res


def _cycle_stats(triangles: list[dict]) -> dict:
    if not triangles:
        return {"triangles": 0}
    out: dict = {"triangles": len(triangles)}
    for key in ("rotation_deg", "log_scale", "translation"):
        vals = np.array([t[key] for t in triangles])
        out[f"{key}_median"] = float(np.median(vals))
        out[f"{key}_max"] = float(vals.max())
    out["closing"] = int(sum(t["units"] <= PRUNE for t in triangles))
    return out


def _widest_paths(n: int, ref: int, edges: list[Edge], strength: list[float]) -> list[float]:
    """Per model, the best bottleneck strength over paths of usable edges from the reference."""
    best = [0.0] * n
    best[ref] = 1.0
    for _ in range(n):  # Bellman-Ford style: n rounds settle every path
        changed = False
        for e, s in zip(edges, strength):
            if e.status == "pruned":
                continue
            for a, b in ((e.source, e.target), (e.target, e.source)):
                v = min(best[a], s)
                if v > best[b] + 1e-12:
                    best[b] = v
                    changed = True
        if not changed:
            break
    return best


def solve_graph(
    n: int,
    edges: list[Edge],
    reference: int = 0,
    centres: Sequence[np.ndarray] | None = None,
    sizes: Sequence[float] | None = None,
    names: Sequence[str] | None = None,
    frames: FrameEvidence | None = None,
) -> ManyResult:
    """The global step: every model's Sim(3) into the reference frame, consistent with the
    edges; sets each edge's status, weight and residual. centres and sizes: each model's
    centroid and RMS radius in its own frame (residual units; default 0 and 1). frames: the
    members' frames and grid scores (many_frames.frame_evidence): the consensus is then one
    relabelling per member (many_frames.synchronise) instead of one of the edges' poses."""
    _check_graph(n, edges, reference)
    t0 = time.perf_counter()
    names = list(names) if names is not None else [f"model_{k}" for k in range(n)]
    centres = [np.zeros(3)] * n if centres is None else [np.asarray(c, np.float64) for c in centres]
    sizes = [1.0] * n if sizes is None else [float(s) for s in sizes]
    norm = [_normaliser(c, s) for c, s in zip(centres, sizes)]

    def normalised(e: Edge, t: Sim3) -> Sim3:
        return norm[e.target] @ t @ norm[e.source].inverse()

    chosen = [normalised(e, e.transform) for e in edges]
    # The consensus over each edge's poses first: an edge whose alternative the consensus agrees
    # with (and not its measured pose) enters the least squares with that alternative.
    by_consensus = set()
    agrees = np.zeros(len(edges))  # 1 where the edge enters with a pose the frames' consensus gave it
    if frames is not None:
        used, agreeing = _frame_consensus(edges, frames, reference, n, centres)
        agrees[agreeing] = 1.0
    else:
        used = [
            None if not pose else edge.alternatives[pose - 1]
            for edge, pose in zip(edges, consensus_poses(n, reference, edges))
        ]
    for e_idx, (edge, pose) in enumerate(zip(edges, used)):
        if pose is not None:
            chosen[e_idx] = normalised(edge, pose)
            edge.used = pose
            by_consensus.add(e_idx)
    pairs = [(e.source, e.target, t) for e, t in zip(edges, chosen)]
    prior = np.array([max(float(e.confidence), 0.05) for e in edges])
    support, triangles_measured = _triangle_support(n, pairs)
    # The frames' consensus first (where given), then triangle support, confidence to break ties:
    # a confident edge no cycle (or the members' relabellings) agrees with is not trusted for the
    # initial solution.
    tree = _spanning_tree(n, pairs, 2.0 * agrees + support + 0.1 * prior)
    x, w, res = _irls(n, reference, pairs, prior, _tree_solution(n, reference, pairs, tree))
    measured = [residual_of(_edge_error(x, e.source, e.target, normalised(e, e.transform))) for e in edges]

    corrected = _correct_pruned(edges, res, x, chosen, normalised)
    if corrected:
        pairs = [(e.source, e.target, t) for e, t in zip(edges, chosen)]
        x, w, res = _irls(n, reference, pairs, prior, x)
    corrected |= by_consensus
    _set_edge_outcomes(edges, res, measured, w, support, corrected)

    _, triangles_used = _triangle_support(n, [(e.source, e.target, t) for e, t in zip(edges, chosen)])
    usable = {(e.source, e.target): k for k, e in enumerate(edges) if e.status != "pruned"}
    usable.update({(j, i): k for (i, j), k in list(usable.items())})
    confidences = _widest_paths(n, reference, edges, _edge_strengths(edges, triangles_used, usable))

    transforms = [norm[reference].inverse() @ xk @ norm[k] for k, xk in enumerate(x)]
    return ManyResult(
        names=names,
        reference=reference,
        transforms=transforms,
        confidences=confidences,
        edges=edges,
        cycles=_cycles(edges, triangles_measured, triangles_used, usable),
        timings={"global": time.perf_counter() - t0},
        contested=_contested(n, reference, edges),
    )


def _frame_consensus(
    edges: list[Edge], frames: FrameEvidence, reference: int, n: int, centres: Sequence[np.ndarray]
) -> tuple[list[Sim3 | None], list[int]]:
    """Per edge, the pose it enters the least squares with when the members' relabelling
    assignment disagrees with its measured pose (None: the measured pose agrees): its most
    plausible pose within CONSENSUS_DEG of the assigned relabelling, else (doubtful edges only)
    the measured pose turned onto that relabelling about the source's centroid; and the edges
    that so agree with the assignment (they seed the least squares). A confident edge is never
    rebuilt: where the assignment overrules it, the least squares and the contest do the rest."""
    from gsa.manhattan import turned_onto

    # Each relabelling's belief: the plausibility of the edge's pose agreeing with it.
    beliefs = [_agreement(_pose_rotations(e), relabelled(e, frames), pose_weights(e)) for e in edges]
    # The grids are what other instances share; where the local shapes pair, they say more.
    held = [held_poses(e) for e in edges]
    assignment = synchronise(n, reference, edges, frames, beliefs, [not h.any() for h in held])
    out: list[Sim3 | None] = []
    agreeing = []
    cycled = on_cycles(n, edges)
    for k, (edge, target) in enumerate(zip(edges, edge_targets(edges, frames, assignment))):
        if target is None or not cycled[k]:
            out.append(None)
            continue
        cos = (np.einsum("ab,hab->h", target, _pose_rotations(edge)) - 1.0) / 2.0
        near = np.flatnonzero(cos > np.cos(np.radians(CONSENSUS_DEG)))
        if held[k].any():
            # Two captures of one object: only a pose their local shapes hold, never a turn.
            near = near[held[k][near]]
            if not len(near):
                out.append(None)
                continue
        pick = int(near[np.argmax(pose_weights(edge)[near])]) if len(near) else 0
        pose = edge.transform if pick == 0 else edge.alternatives[pick - 1]
        if edge.doubtful and not held[k].any() and on_frames(edge, frames, CONSENSUS_DEG):
            # Across instances the frames are exact where the fits drift (docs/benchmarks.md,
            # "Dominant-normal frames"): the pose is turned onto the relabelling itself.
            if cos[pick] < np.cos(np.radians(FRAME_EXACT_DEG)):
                pose = turned_onto(pose, target, centres[edge.source])
        elif not len(near):
            out.append(None)
            continue
        out.append(None if pose is edge.transform else pose)
        agreeing.append(k)
    return out, agreeing


def _contested(n: int, reference: int, edges: list[Edge]) -> dict[int, list[int]]:
    """The models an overruled edge (pruned, or corrected to an alternative) contests: its
    measured confidence is above every agreeing edge's of that model by more than
    CONTEST_MARGIN. Of the edge's two models (never the reference) the blame goes to the one
    whose transform its agreeing edges support least (both on a tie)."""
    support = [0.0] * n  # per model, its most confident edge the solution agrees with
    for e in edges:
        if e.status in ("kept", "down-weighted"):
            for k in (e.source, e.target):
                support[k] = max(support[k], float(e.confidence))
    out: dict[int, list[int]] = {}
    for i, e in enumerate(edges):
        if e.status not in ("pruned", "corrected"):
            continue
        ends = [k for k in (e.source, e.target) if k != reference and float(e.confidence) > support[k] + CONTEST_MARGIN]
        weakest = min((support[k] for k in ends), default=None)
        for k in ends:
            if support[k] == weakest:
                out.setdefault(k, []).append(i)
    return out


def _check_graph(n: int, edges: list[Edge], reference: int) -> None:
    if n < 2:
        raise ManyError("need at least two models")
    if not 0 <= reference < n:
        raise ManyError(f"reference index {reference} is not one of the {n} models")
    if not edges:
        raise ManyError("no edges")
    for e in edges:
        if not (0 <= e.source < n and 0 <= e.target < n) or e.source == e.target:
            raise ManyError(f"edge {e.source} -> {e.target} does not join two of the {n} models")


def _correct_pruned(
    edges: list[Edge], res: list[dict], x: list[Sim3], chosen: list[Sim3], normalised: Callable[[Edge, Sim3], Sim3]
) -> set[int]:
    """Pruned edges: an alternative that agrees with the solution x replaces the measured
    pose (in chosen, and as the edge's used transform). Returns the corrected edges' indices."""
    corrected = set()
    for e_idx, (edge, r) in enumerate(zip(edges, res)):
        if r["units"] <= PRUNE or not edge.alternatives:
            continue
        alts = [normalised(edge, a) for a in edge.alternatives]
        alt_res = [residual_of(_edge_error(x, edge.source, edge.target, a)) for a in alts]
        best = int(np.argmin([a["units"] for a in alt_res]))
        if alt_res[best]["units"] <= ACCEPT_ALTERNATIVE:
            chosen[e_idx] = alts[best]
            edge.used = edge.alternatives[best]
            corrected.add(e_idx)
    return corrected


def _set_edge_outcomes(
    edges: list[Edge], res: list[dict], measured: list[dict], w: np.ndarray, support: np.ndarray, corrected: set[int]
) -> None:
    """Each edge's residuals, weight, triangle support, status and used transform."""
    for e_idx, (edge, r) in enumerate(zip(edges, res)):
        edge.residual = r
        edge.measured_residual = measured[e_idx]
        edge.weight = float(w[e_idx])
        edge.triangle_support = float(support[e_idx])
        if edge.used is None:
            edge.used = edge.transform
        if r["units"] > PRUNE:
            edge.status = "pruned"
            edge.used = edge.transform
        elif e_idx in corrected:
            edge.status = "corrected"
        else:
            edge.status = "kept" if r["units"] <= 1.0 else "down-weighted"


def _edge_strengths(edges: list[Edge], triangles_used: list[dict], usable: dict[tuple[int, int], int]) -> list[float]:
    """Per edge, its strength for the per-model confidence (the widest path from the
    reference over usable edges): its own confidence or, when a triangle of usable edges
    closes through it, the weaker of that triangle's other two edges (two paths agree).
    A corrected edge has no confidence of its own: align() vouched for the pose it measured,
    not for the alternative the cycles chose, so only its triangles lend it strength."""
    own = [0.0 if e.status == "corrected" else float(e.confidence) for e in edges]
    strength = list(own)
    for tri in triangles_used:
        a, b, c = tri["models"]
        ks = [usable.get(p) for p in ((a, b), (b, c), (a, c))]
        if None in ks or tri["units"] > PRUNE:
            continue
        for k in ks:
            strength[k] = max(strength[k], min(own[o] for o in ks if o != k))
    return strength


def _cycles(
    edges: list[Edge], triangles_measured: list[dict], triangles_used: list[dict], usable: dict[tuple[int, int], int]
) -> dict:
    """Cycle statistics, measured and after the global step, and the largest usable edge residuals."""
    usable_triangles = [
        t
        for t in triangles_used
        if all(p in usable for p in ((t["models"][0], t["models"][1]), (t["models"][1], t["models"][2])))
        and (t["models"][0], t["models"][2]) in usable
    ]
    return {
        "measured": _cycle_stats(triangles_measured),
        "after": _cycle_stats(usable_triangles),
        "edge_residuals": {
            "rotation_deg_max": max(e.residual["rotation_deg"] for e in edges if e.status != "pruned"),
            "log_scale_max": max(e.residual["log_scale"] for e in edges if e.status != "pruned"),
            "translation_max": max(e.residual["translation"] for e in edges if e.status != "pruned"),
        }
        if any(e.status != "pruned" for e in edges)
        else {},
    }


# ---------------------------------------------------------------- edges


def model_frame(model: GaussianModel) -> tuple[np.ndarray, float]:
    """Centroid and RMS radius: the unit of a model's translation residuals."""
    means = np.asarray(model.means, np.float64)
    centre = means.mean(axis=0)
    size = float(np.sqrt(((means - centre) ** 2).sum(axis=1).mean()))
    return centre, max(size, 1e-12)


def descriptor(model: GaussianModel) -> np.ndarray:
    """Cheap, pose- and scale-free: the principal extents over the RMS radius, and a 4×4×4
    colour histogram (shares)."""
    means = np.asarray(model.means, np.float64)
    centred = means - means.mean(axis=0)
    eig = np.sort(np.linalg.eigvalsh(centred.T @ centred / max(len(means), 1)))[::-1]
    extent = np.sqrt(np.maximum(eig, 0)) / max(np.sqrt(eig.sum()), 1e-12)
    colours = np.clip(np.asarray(model.base_colors, np.float64), 0, 1 - 1e-9)
    bins = (colours * 4).astype(int)
    hist = np.bincount(bins[:, 0] * 16 + bins[:, 1] * 4 + bins[:, 2], minlength=64) / max(len(colours), 1)
    return np.concatenate([extent, hist])


def select_edges(models: Sequence[GaussianModel], edges: str = "auto", k: int = SPARSE_K) -> list[tuple[int, int]]:
    """Which pairs to align: all pairs (edges "all", or "auto" with at most ALL_PAIRS_MAX
    models), else each model with its k most similar by `descriptor` plus a minimum
    spanning tree over the descriptor distances, so the graph is connected."""
    n = len(models)
    if edges not in ("auto", "all", "sparse"):
        raise ManyError(f"edges must be auto, all or sparse, not {edges!r}")
    if edges == "all" or (edges == "auto" and n <= ALL_PAIRS_MAX):
        return list(itertools.combinations(range(n), 2))
    d = np.array([descriptor(m) for m in models])
    dist = np.linalg.norm(d[:, None] - d[None], axis=2)
    chosen = set()
    for i in range(n):
        for j in np.argsort(dist[i])[1 : k + 1]:
            chosen.add((min(i, int(j)), max(i, int(j))))
    all_pairs = list(itertools.combinations(range(n), 2))
    tree = _spanning_tree(n, [(i, j, None) for i, j in all_pairs], -np.array([dist[i, j] for i, j in all_pairs]))
    chosen.update(all_pairs[e] for e in tree)
    return sorted(chosen)


def edge_from_result(i: int, j: int, result, seconds: float) -> Edge:
    metrics, verdict = result.metrics, result.verdict
    alternatives, scores = [], [_score(metrics.get("semantic_score"))]
    agreements = [_score(metrics.get("local_agreement"))]
    for alt in verdict.alternatives:
        if alt.transform is None:  # an alternative we cannot read is left out
            continue
        alternatives.append(alt.transform)
        scores.append(_score(alt.details.get("semantic_score")))
        agreements.append(_score(alt.details.get("local_agreement")))
    confidence = metrics.get("confidence")
    return Edge(
        source=i,
        target=j,
        transform=result.transform,
        confidence=1.0 if confidence is None else float(confidence),
        doubtful=verdict.doubtful,
        ambiguous=verdict.ambiguous,
        alternatives=alternatives,
        scores=scores,
        agreements=agreements,
        agreement_needed=_score(metrics.get("local_agreement_needed")),
        seconds=seconds,
    )


def _score(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and np.isfinite(value) else None


def pairwise_edges(
    models: Sequence[GaussianModel],
    pairs: Sequence[tuple[int, int]],
    options=None,
    progress: Callable[[int, int], None] | None = None,
    edge_progress: Callable[[int, int, str, float], None] | None = None,
) -> list[Edge]:
    """align(models[i], models[j]) for each pair; progress(done, total) after each, and
    edge_progress(edge index, total, stage, fraction) for align()'s own reports within an edge
    (either may raise to stop: the service cancels jobs so)."""
    from gsa.align.pipeline import AlignOptions, align  # lazy: numba and scipy

    # The consensus corrects an edge from its alternatives, a confident one's too.
    options = replace(options or AlignOptions(), alternatives="always")
    out = []
    for done, (i, j) in enumerate(pairs, 1):
        t0 = time.perf_counter()
        report = None
        if edge_progress is not None:

            def report(stage: str, fraction: float, k: int = done - 1) -> None:
                edge_progress(k, len(pairs), stage, fraction)

        result = align(models[i], models[j], options, progress=report)
        out.append(edge_from_result(i, j, result, time.perf_counter() - t0))
        if progress:
            progress(done, len(pairs))
    return out


def check_models(models: Sequence[GaussianModel], names: Sequence[str]) -> None:
    """ManyError for a model the pairwise alignments cannot use (fewer than 3 Gaussians)."""
    for name, m in zip(names, models):
        if len(m) < 3:
            raise ManyError(f"{name}: {len(m)} Gaussians; at least 3 are needed")


def align_many(
    models: Sequence[GaussianModel],
    names: Sequence[str] | None = None,
    reference: int = 0,
    options=None,
    edges: str = "auto",
    progress: Callable[[int, int], None] | None = None,
    edge_progress: Callable[[int, int, str, float], None] | None = None,
) -> ManyResult:
    """Every model's Sim(3) into models[reference]'s frame (see the module's docstring).
    progress(done, total) after each edge; edge_progress(edge, total, stage, fraction) within one."""
    n = len(models)
    if n < 2:
        raise ManyError(f"align_many needs at least two models, got {n}")
    names = [f"model_{k}" for k in range(n)] if names is None else [str(s) for s in names]
    if len(names) != n or len(set(names)) != n:
        raise ManyError("names must be one distinct name per model")
    if not 0 <= reference < n:
        raise ManyError(f"reference index {reference} is not one of the {n} models")
    check_models(models, names)
    t0 = time.perf_counter()
    pairs = select_edges(models, edges)
    t_edges = time.perf_counter()
    graph = pairwise_edges(models, pairs, options, progress, edge_progress)
    t_pairwise = time.perf_counter() - t_edges
    frames = [model_frame(m) for m in models]
    t_frames = time.perf_counter()
    evidence = frame_evidence(models, pairs)
    result = solve_graph(n, graph, reference, [c for c, _ in frames], [s for _, s in frames], names, frames=evidence)
    result.timings.update(
        frames=time.perf_counter() - t_frames - result.timings["global"],
        pairwise=t_pairwise,
        per_edge=t_pairwise / max(len(graph), 1),
        edges=len(graph),
        total=time.perf_counter() - t0,
    )
    return result


def merged_model(
    models: Sequence[GaussianModel], result: ManyResult, mode: str = "concat"
) -> tuple[GaussianModel, int]:
    """Every model moved into the reference frame, as one model; returns (merged, Gaussians
    dropped). Folded in one model at a time, so dedup compares each with all merged before it."""
    from gsa.merge import merge_plan
    from gsa.model import merge_models

    merged = models[result.reference]
    removed = 0
    for k, m in enumerate(models):
        if k == result.reference:
            continue
        aligned = m.transformed(result.transforms[k])
        keep, dropped = merge_plan(aligned, merged, mode)
        merged = merge_models(aligned, merged, keep=keep)
        removed += dropped
    return merged, removed
