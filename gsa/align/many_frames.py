"""The members' frames as evidence for the global step of many models (N-way registration).

Between two instances of one category the true rotation is one of the 24 relabellings of
their dominant surface-normal frames (gsa.manhattan; docs/benchmarks.md, "Dominant-normal
frames"), and each pair's surface-mass grids score all 24 (manhattan.relabelling_agreement).
Pair by pair, the best-scored relabelling is wrong on a quarter of the edges; but over N
members the relabellings must compose: give each member one signed permutation G_k of its
frame's axes into a shared frame (the reference's G = I), and the edge i -> j must be
P_ij = G_jᵀ G_i. A member then draws on all its edges at once, and an edge whose own scores
preferred a wrong end is outvoted by the cycles through it, where the edges' own poses, half
turns of one another, could not be (their errors are themselves consistent: a flipped
member shows its flip on every edge).

The assignment maximises, summed over the edges, each relabelling's grid score (standardised
over the 24, as frame_snap's choice does) plus the edge's own belief in it: POSE_GAIN times
the plausibility (many.pose_weights, computed by the caller) of the edge's pose, measured or
alternative, that lies within many.CONSENSUS_DEG of it. A confident edge's measured pose so
counts as much as a standard deviation of the shapes. What the global step does with the
assignment (gsa.align.many._frame_consensus): a doubtful edge on its frames is turned onto the
relabelling it is given; an edge off its frames or on no cycle is left as measured. An edge
whose models' local shapes hold one of its poses (two captures of one object: many.held_poses)
is judged by those poses alone: its grid scores, made for other instances, do not count, and
it is never turned onto a relabelling, only moved to another pose the local shapes hold.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gsa import manhattan
from gsa.canonical import SIGNED_PERMUTATIONS
from gsa.model import GaussianModel

# How much the edge's own poses count against the shapes' standardised grid scores: a
# confident edge (weight ~1) is worth POSE_GAIN standard deviations of the grid. 0, 1 and 3
# measured alike on the cross-instance sets (docs/benchmarks.md, n-way; 3 one member fewer).
POSE_GAIN = 1.0
# Spread floor of the standardisation (as frame_snap.CHOICE_SPREAD_FLOOR): between two
# frameless blobs every relabelling scores alike, and noise must not read as a preference.
SPREAD_FLOOR = 0.02
# Gaussians per member the frames and grids are computed from.
MAX_GAUSSIANS = 30_000
# Partial assignments kept while members are added one at a time.
BEAM = 256

_PERMS = np.stack(SIGNED_PERMUTATIONS)


def _index_of(g: np.ndarray) -> int:
    return int(np.argmin(np.abs(_PERMS - g).sum(axis=(1, 2))))


IDENTITY = _index_of(np.eye(3))
# RELATIVE[a, b]: the index of P_aᵀ P_b, the relabelling i -> j when G_j = P_a and G_i = P_b.
RELATIVE = np.array([[_index_of(_PERMS[a].T @ _PERMS[b]) for b in range(24)] for a in range(24)])


@dataclass
class FrameEvidence:
    """Each member's dominant-normal frame and, per aligned pair (i, j), the (24,) standardised
    agreement of their surface-mass grids under each relabelling i -> j (manhattan's order)."""

    frames: list[manhattan.NormalFrame]
    shape: dict[tuple[int, int], np.ndarray]

    def relabelling(self, i: int, j: int, index: int) -> np.ndarray:
        """The rotation of relabelling `index` from member i's frame onto member j's."""
        return self.frames[j].axes.T @ _PERMS[index] @ self.frames[i].axes


def frame_evidence(models: Sequence[GaussianModel], pairs: Sequence[tuple[int, int]]) -> FrameEvidence:
    """Frames of every member and grid agreements of every pair (at 100k Gaussians: 0.12 s a
    model, 0.025 s a pair)."""
    models = [_sampled(m) for m in models]
    frames = [manhattan.manhattan_frame(m) for m in models]
    shape = {}
    for i, j in pairs:
        raw = manhattan.relabelling_agreement(models[i], models[j], frames[i], frames[j])
        shape[(i, j)] = (raw - raw.mean()) / max(float(np.std(raw)), SPREAD_FLOOR)
    return FrameEvidence(frames, shape)


def _sampled(model: GaussianModel) -> GaussianModel:
    """At most MAX_GAUSSIANS of the model (a fixed random subset): frames and grids are a few
    numbers each, and N = 50 members of 100k Gaussians must not pay for every one."""
    if len(model) <= MAX_GAUSSIANS:
        return model
    rows = np.random.default_rng(0).choice(len(model), MAX_GAUSSIANS, replace=False)
    return model.subset(np.sort(rows))


def _edge_gains(edge, evidence: FrameEvidence, belief: np.ndarray, grid: bool = True) -> np.ndarray:
    """(24,) what the edge says of each relabelling: its grid score (where `grid`) plus
    POSE_GAIN times the edge's own belief in it (the plausibility of its pose agreeing with it,
    from the caller)."""
    i, j = edge.source, edge.target
    if not grid:
        gains = np.zeros(24)
    elif (i, j) in evidence.shape:
        gains = np.array(evidence.shape[(i, j)], np.float64)
    elif (j, i) in evidence.shape:  # the pair scored the other way
        back = evidence.shape[(j, i)]
        gains = np.array([back[_index_of(_PERMS[k].T)] for k in range(24)])
    else:
        gains = np.zeros(24)
    return gains + POSE_GAIN * np.asarray(belief, np.float64)


def relabelled(edge, evidence: FrameEvidence) -> np.ndarray:
    """(24, 3, 3) the edge's relabellings, source member's frame onto the target's."""
    return manhattan.relabellings(evidence.frames[edge.source], evidence.frames[edge.target])


def incident_edges(n: int, edges: Sequence) -> dict[int, list[int]]:
    """Per member, the indices of the edges that join it."""
    incident: dict[int, list[int]] = {k: [] for k in range(n)}
    for idx, e in enumerate(edges):
        incident[e.source].append(idx)
        incident[e.target].append(idx)
    return incident


def synchronise(
    n: int,
    reference: int,
    edges: Sequence,
    evidence: FrameEvidence,
    beliefs: Sequence[np.ndarray],
    grids: Sequence[bool] | None = None,
) -> list[int | None]:
    """One relabelling index G_k per member (the reference's the identity; None for a member no
    edge reaches) maximising the summed edge gains of P_ij = G_jᵀ G_i (beliefs: per edge, (24,)
    its own belief in each relabelling; grids: per edge, whether its grid scores count, all by
    default): a beam search adding the members in order of how many edges join them to those
    placed before."""
    grids = [True] * len(edges) if grids is None else grids
    gains = [_edge_gains(e, evidence, b, g) for e, b, g in zip(edges, beliefs, grids)]
    incident = incident_edges(n, edges)
    placed, order = {reference}, []
    while True:
        links = {
            k: sum((edges[idx].source + edges[idx].target - k) in placed for idx in incident[k])
            for k in range(n)
            if k not in placed
        }
        reachable = {k: v for k, v in links.items() if v}
        if not reachable:
            break
        k = max(reachable, key=lambda m: (reachable[m], -m))
        order.append(k)
        placed.add(k)
    states = np.full((1, n), -1)
    states[0, reference] = IDENTITY
    totals = np.zeros(1)
    candidates = np.arange(24)
    for k in order:
        grown = np.repeat(states, 24, axis=0)
        grown[:, k] = np.tile(candidates, len(states))
        total = np.repeat(totals, 24)
        for idx in incident[k]:
            e = edges[idx]
            other = e.source + e.target - k
            if states[0, other] < 0:
                continue
            total = total + gains[idx][RELATIVE[grown[:, e.target], grown[:, e.source]]]
        keep = np.argsort(-total, kind="stable")[:BEAM]
        states, totals = grown[keep], total[keep]
    best = states[0]
    return [None if g < 0 else int(g) for g in best]


def edge_targets(edges: Sequence, evidence: FrameEvidence, assignment: Sequence[int | None]) -> list[np.ndarray | None]:
    """Per edge, the rotation the assignment gives it (None where a member is unplaced)."""
    out = []
    for e in edges:
        gi, gj = assignment[e.source], assignment[e.target]
        out.append(None if gi is None or gj is None else evidence.relabelling(e.source, e.target, RELATIVE[gj, gi]))
    return out


def on_frames(edge, evidence: FrameEvidence, degrees: float) -> bool:
    """Whether the edge's measured pose lies within `degrees` of one of the 24 relabellings of
    its members' frames: the frames explain it, and only which relabelling is in question. Off
    them (a partial capture whose dominant normals moved, a frameless blob), the frames cannot
    say what the edge should have been."""
    cos = (np.einsum("kab,ab->k", relabelled(edge, evidence), edge.transform.rotation) - 1.0) / 2.0
    return bool(cos.max() > np.cos(np.radians(degrees)))


def on_cycles(n: int, edges: Sequence) -> list[bool]:
    """Per edge, whether a cycle runs through it (its two members stay joined without it). An
    edge on no cycle has nothing but itself to be judged by, and align() already weighed the
    same grid scores (frame_snap.choose_relabelling) for it."""
    out = []
    for skip in range(len(edges)):
        parent = list(range(n))
        for idx, e in enumerate(edges):
            if idx != skip:
                parent[_root(parent, e.source)] = _root(parent, e.target)
        out.append(_root(parent, edges[skip].source) == _root(parent, edges[skip].target))
    return out


def _root(parent: list[int], k: int) -> int:
    while parent[k] != k:
        parent[k] = parent[parent[k]]
        k = parent[k]
    return k
