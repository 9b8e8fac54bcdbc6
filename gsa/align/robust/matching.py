"""Matched starts: poses from local shape descriptors paired across the two models.

The global search places each rotation by the models' centres and radii, and the placement
search by a lattice of centres; both sample rotations on a grid. Two partial captures of one
place (a street, a room, a statue each missing a side) score the truth in a peak narrower than
the grid and overlap only in part, so neither reaches it (docs/benchmarks.md, "Where the tail
comes from"). Here each anchor gets a histogram of how its neighbours lie around it (the angles
between its normal, theirs and the line joining them, and their distances, counted
sign-free so that no normal orientation is needed), anchors are paired with their most alike
across the models, and triples of pairs whose three sides keep one ratio give similarities
(RANSAC); the poses most pairs agree with become starts. Neither a centre nor a grid is
involved, only the anchors' own neighbourhoods, whose size is a number of anchors and so
follows each model's own scale.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from gsa.align.robust.anchoring import Anchors
from gsa.geometry import rotation_distance_deg
from gsa.render import steps
from gsa.sim3 import DegenerateCorrespondencesError, Sim3, solve_sim3


@dataclass(frozen=True)
class MatchOptions:
    """The tunables of the matched starts (SearchOptions.matching)."""

    normal_neighbours: int = 16  # anchors a normal is fitted to
    neighbours: int = 32  # anchors a descriptor describes (about 6 spacings across)
    bins: int = 8  # histogram bins per measured quantity (4 quantities)
    pairs_per_anchor: int = 2  # each source anchor is paired with this many most alike targets ...
    # ... and a pair is kept only where the source anchor is also among the target's most alike
    # RANSAC draws; about 1 in 20-100 keeps its side ratios within side_ratio_spread
    triples: int = 20_000
    side_ratio_spread: float = 0.15  # a triple's three side ratios (target / source) agree within this
    inlier_spacings: float = 3.0  # a pair agrees with a pose within this many target anchor spacings
    # A pose is a start only where at least this share of the pairs agree with it. Chance
    # agreement is 1-3 % (3 spacings of ~2,000 anchors); measured best poses: two captures of
    # one object 6-25 % (halves of 12 real captures, deformed copies), two instances of a
    # category 1-5 % (24 development pairs), whose local shapes do not correspond.
    min_consensus: float = 0.05
    chunk: int = 256  # poses whose agreement is counted at once (memory: chunk × pairs × 3)
    # Where the models share a palette (the search's colour trust), each descriptor also holds
    # its anchor's and its neighbourhood's CIELAB colour, in units of colour_scale ΔE, times
    # the trust: two captures of one object pair like places by their colour as well.
    colour_scale: float = 50.0
    # A triple's pose is as exact as its three pairs (10-20 degrees off where the pairs sit a
    # spacing apart); it is fitted again, least squares, to every pair agreeing with it, this many
    # times (LO-RANSAC's local optimisation): measured on the iPhone room's halves, 17-46° -> 3-12°.
    refit_rounds: int = 5
    # Where the ICP that takes a matched start on ends scoring less than slid_share of the start
    # itself, it slid off it: two halves that overlap on about half, whose median pair distance is
    # the part one lacks (a street's halves: 0.31 -> 0.013, 1.6° -> 21°; the room's 0.055 -> 0.002).
    # There the ICP runs again capped at icp_reach of the score's truncation distances
    # (poses.bidirectional_icp's reach) and the better scoring is kept (street 3.7°, room 1.7°).
    # The caps run in turn, each from where the last ended, the best scoring kept: 2 draws a
    # start in from 10-15° off, 1 then fits the pairs the score itself counts (within one
    # truncation) and climbs its peak. At 2 alone, small halves' fits stopped a degree or two off
    # the peak scoring a fifth of it, and a pose 28° off won (a street drawn to 12k Gaussians:
    # 1.75°, 0.040 against 0.133 at 28°; 1.0°, 0.226 with the second cap).
    # An ICP that keeps most of its start's score is left as it is: between a model and a
    # deformed copy of it the capped ICP scores a little higher further from the truth (a chair:
    # 0.257 at 6.2° against 0.226 at 2.6°), the score's peak not being the truth there.
    slid_share: float = 0.5
    icp_reach: tuple[float, ...] = (2.0, 1.0)
    # A doubtful answer is also held from starts turned this many degrees about 26 axes (the
    # cube's faces, edges and corners) through it (search.held_within_reach): the score's peak
    # between two partial halves is a few degrees wide, and an answer 9-10 degrees off it is
    # outside the capped ICP's reach (the iPhone room's pair 16: 9.1° -> 0.9°).
    reach_turns: tuple[float, ...] = (6.0, 12.0)
    # More triples are drawn (scored_triples) and the scored_top hypotheses most pairs agree
    # with are ranked by the search's own score, the scored_count best join the starts (0:
    # none). Agreement with the descriptor pairs is a weak proxy between two partial halves
    # (the iPhone room's: the truth agrees with 4.5 % of the pairs, a pose 14 degrees off with
    # 5.4 %), and 20,000 triples leave a few hundred hypotheses; the score peaks at the truth
    # (0.15 there, 0.03-0.07 ten degrees off). They join whether or not a pose passed the
    # consensus gate: the score picks them, not agreement (the iPhone room's pairs 21 and 25,
    # where no pose reaches min_consensus), and the caller passes a score only where it compares
    # colours (the search's colour trust). An earlier rule also asked the palettes to be wholly
    # shared where no pose passed, for two instances, whose local shapes do not correspond; the
    # scale bound below is what kept their hypotheses off (a rifle pair's), and halves of a
    # small capture weigh 0.74-0.96, not 1 (docs/benchmarks.md, "Small
    # captures: the scored hypotheses wherever colours are trusted").
    # A descriptor describes a number of anchors, so two neighbourhoods alike across the models
    # are alike at the scale their anchor spacings give (about the true scale where both models
    # are sampled alike: 0.95 of it on the iPhone room's halves). A pose whose scale lies more
    # than scale_spread times off that pairs neighbourhoods of unlike size, whose likeness is
    # chance: such triples gave the room's shifted pair 16 starts at 0.13 of its scale, and
    # the score (colours under a shifted exposure) took one 149 degrees off (1.5 without them);
    # ungated and unbounded, they took a rifle pair of two instances 178 degrees off (0.05
    # with the bound; docs/benchmarks.md, "The ungated hypotheses back, within the scale").
    # Such a pose is dropped, not replaced: a next-best in its place took the street's shifted
    # pair 0 from 2.2 to 9.2 degrees.
    scale_spread: float = 2.0
    scored_triples: int = 200_000
    scored_top: int = 1000
    scored_count: int = 2


def descriptors(
    points: np.ndarray, options: MatchOptions | None = None, lab: np.ndarray | None = None, colour: float = 0.0
) -> tuple[np.ndarray, float]:
    """(one histogram per point, the median nearest-neighbour spacing). Per point and each of
    its `neighbours`: |n·d|, |n'·d|, |n·n'| (n, n' the two normals, d the unit line between
    them) and the distance over the farthest neighbour's, each in `bins` bins; with `lab`
    (CIELAB per point) and colour > 0, the point's and its neighbours' mean colour follow,
    weighted by `colour`."""
    o = options or MatchOptions()
    n = len(points)
    k_normal, k = min(o.normal_neighbours, n), min(o.neighbours + 1, n)
    tree = cKDTree(points)
    dist, idx = tree.query(points, k=max(k_normal, k))
    spacing = float(np.median(dist[:, 1])) if dist.shape[1] > 1 else 0.0
    local = points[idx[:, :k_normal]]
    centred = local - local.mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]
    near = idx[:, 1:k]
    line = points[near] - points[:, None, :]
    length = np.linalg.norm(line, axis=2)
    unit = line / np.maximum(length, 1e-300)[:, :, None]
    reach = np.maximum(length.max(axis=1, keepdims=True), 1e-300)
    quantities = (
        np.abs(np.einsum("nkj,nj->nk", unit, normals)),
        np.abs(np.einsum("nkj,nkj->nk", unit, normals[near])),
        np.abs(np.einsum("nkj,nj->nk", normals[near], normals)),
        length / reach,
    )
    out = np.zeros((n, len(quantities) * o.bins))
    rows = np.repeat(np.arange(n), near.shape[1])
    for q, values in enumerate(quantities):
        cells = np.minimum((values * o.bins).astype(np.int64), o.bins - 1).reshape(-1)
        np.add.at(out, (rows, q * o.bins + cells), 1.0)
    out /= max(near.shape[1], 1)
    if lab is not None and colour > 0:
        tint = np.concatenate([lab, lab[near].mean(axis=1)], axis=1) * (colour / o.colour_scale)
        out = np.concatenate([out, tint], axis=1)
    return out, spacing


@dataclass(frozen=True)
class DescriptorPairs:
    """Anchors paired across the models by their descriptors (mutually most alike): where
    source[i] lies, target[i] should, and a pose agrees with a pair that it maps within
    `tolerance` (inlier_spacings target anchor spacings)."""

    source: np.ndarray  # (m, 3)
    target: np.ndarray  # (m, 3)
    tolerance: float
    colour: float = 0.0  # the colour trust the descriptors were made with
    scale: float = 1.0  # the target's anchor spacing over the source's: the scale the pairs assume

    def scale_fits(self, pose: Sim3, spread: float) -> bool:
        """Whether `pose`'s scale lies within a factor `spread` of the scale the pairs assume."""
        return 1.0 / spread <= pose.scale / self.scale <= spread

    def agreement(self, pose: Sim3) -> float:
        """The share of the pairs `pose` maps within the tolerance."""
        if not len(self.source):
            return 0.0
        return float(np.mean(np.sum((pose.apply(self.source) - self.target) ** 2, axis=1) < self.tolerance**2))


def descriptor_pairs(
    src: Anchors, dst: Anchors, options: MatchOptions | None = None, colour: float = 0.0
) -> DescriptorPairs:
    """Each source anchor paired with its pairs_per_anchor most alike target anchors, kept where
    the source anchor is also among the target's most alike. `colour`: how far the models'
    colours are trusted (the search's colour weight, 0..1)."""
    o = options or MatchOptions()
    f_src, src_spacing = descriptors(src.points, o, src.lab, colour)
    steps.step()
    f_dst, spacing = descriptors(dst.points, o, dst.lab, colour)
    steps.step()
    per = min(o.pairs_per_anchor, len(dst))
    alike = cKDTree(f_dst).query(f_src, k=per)[1].reshape(len(src), per)
    s_idx, d_idx = np.repeat(np.arange(len(src)), per), alike.reshape(-1)
    back = cKDTree(f_src).query(f_dst[d_idx], k=min(o.pairs_per_anchor, len(src)))[1].reshape(len(d_idx), -1)
    mutual = np.any(back == s_idx[:, None], axis=1)
    scale = spacing / src_spacing if src_spacing > 0 else 1.0
    pairs = (src.points[s_idx[mutual]], dst.points[d_idx[mutual]])
    return DescriptorPairs(*pairs, o.inlier_spacings * spacing, colour, scale)


def matched_poses(
    src: Anchors,
    dst: Anchors,
    rng: np.random.Generator,
    count: int,
    min_deg: float,
    options: MatchOptions | None = None,
    colour: float = 0.0,
    score: Callable[[list[Sim3]], np.ndarray] | None = None,
) -> list[Sim3]:
    """Up to `count` similarities, min_deg apart in rotation, that the most descriptor pairs
    agree with (best first), each agreed by min_consensus of the pairs at least; empty where
    none is (two instances of a category, whose local shapes do not correspond). `colour`:
    how far the models' colours are trusted (the search's colour weight, 0..1). `score`: the
    search's score of poses (given only where it compares colours); with it, the best it ranks
    of more triples follow (_scored). Every pose keeps a scale within scale_spread of the one
    the pairs assume."""
    o = options or MatchOptions()
    if len(src) < 4 or len(dst) < 4:
        return []
    pairs = descriptor_pairs(src, dst, o, colour)
    p, q = pairs.source, pairs.target
    if len(p) < 3:
        return []
    steps.step()
    poses, agree = _ransac(p, q, rng, pairs.tolerance, o)
    out: list[Sim3] = []
    least = max(3.0, o.min_consensus * len(p))
    for i in np.argsort(-agree, kind="stable"):
        if agree[i] < least:
            break
        pose = _refit(poses[i], p, q, pairs.tolerance, o.refit_rounds)
        if all(rotation_distance_deg(pose.rotation, kept.rotation) > min_deg for kept in out):
            out.append(pose)
            if len(out) == count:
                break
    if score is not None and o.scored_count:
        out += _scored(pairs, rng, o, score, out, min_deg)
    return [pose for pose in out if pairs.scale_fits(pose, o.scale_spread)]


def _scored(
    pairs: DescriptorPairs,
    rng: np.random.Generator,
    o: MatchOptions,
    score: Callable[[list[Sim3]], np.ndarray],
    found: list[Sim3],
    min_deg: float,
) -> list[Sim3]:
    """The scored_count hypotheses of scored_triples more triples that `score` ranks best
    among the scored_top most agreed with, min_deg apart from each other and from `found`."""
    poses, agree = _ransac(pairs.source, pairs.target, rng, pairs.tolerance, replace(o, triples=o.scored_triples))
    if not poses:
        return []
    top = [poses[i] for i in np.argsort(-agree, kind="stable")[: o.scored_top]]
    scores = score(top)
    out: list[Sim3] = []
    for i in np.argsort(-scores, kind="stable"):
        pose = top[i]
        if all(rotation_distance_deg(pose.rotation, kept.rotation) > min_deg for kept in [*found, *out]):
            out.append(pose)
            if len(out) == o.scored_count:
                break
    return out


def _refit(pose: Sim3, p: np.ndarray, q: np.ndarray, tolerance: float, rounds: int) -> Sim3:
    """`pose` fitted again to the pairs (p[i] -> q[i]) it maps within `tolerance`, `rounds` times
    or until its agreeing pairs stop changing."""
    agreeing = None
    for _ in range(rounds):
        now = np.sum((pose.apply(p) - q) ** 2, axis=1) < tolerance**2
        if now.sum() < 3 or (agreeing is not None and np.array_equal(now, agreeing)):
            break
        agreeing = now
        try:
            pose = solve_sim3(p[now], q[now])
        except DegenerateCorrespondencesError:
            break
    return pose


def _ransac(
    p: np.ndarray, q: np.ndarray, rng: np.random.Generator, tolerance: float, o: MatchOptions
) -> tuple[list[Sim3], np.ndarray]:
    """The similarities of random triples of pairs (p[i] -> q[i]) whose sides keep one ratio,
    each with the number of pairs it maps within `tolerance`."""
    draws = rng.integers(0, len(p), size=(o.triples, 3))
    a, b = p[draws], q[draws]  # (m, 3 points, 3)
    side_a = np.linalg.norm(a - a[:, [1, 2, 0]], axis=2)
    side_b = np.linalg.norm(b - b[:, [1, 2, 0]], axis=2)
    ok = (side_a.min(axis=1) > 1e-9) & (side_b.min(axis=1) > 1e-9)
    ratio = side_b[ok] / side_a[ok]
    ok[ok] = ratio.max(axis=1) <= (1.0 + o.side_ratio_spread) * ratio.min(axis=1)
    a, b = a[ok], b[ok]
    if not len(a):
        return [], np.zeros(0)
    ca, cb = a.mean(axis=1, keepdims=True), b.mean(axis=1, keepdims=True)
    xa, xb = a - ca, b - cb
    u, _, vt = np.linalg.svd(np.einsum("mki,mkj->mij", xa, xb))
    flip = np.sign(np.linalg.det(np.einsum("mij,mjk->mik", u, vt)))
    d = np.ones((len(a), 3))
    d[:, 2] = flip
    rotation = np.einsum("mji,mj,mkj->mik", vt, d, u)  # V diag(d) Uᵀ
    scale = np.sqrt(np.sum(xb**2, axis=(1, 2)) / np.maximum(np.sum(xa**2, axis=(1, 2)), 1e-300))
    shift = cb[:, 0] - scale[:, None] * np.einsum("mij,mj->mi", rotation, ca[:, 0])
    agree = np.empty(len(a))
    for start in range(0, len(a), o.chunk):
        sl = slice(start, start + o.chunk)
        mapped = scale[sl, None, None] * np.einsum("mij,nj->mni", rotation[sl], p) + shift[sl, None, :]
        agree[sl] = np.sum(np.sum((mapped - q) ** 2, axis=2) < tolerance**2, axis=1)
        steps.step()
    return [Sim3(float(s), r, t) for s, r, t in zip(scale, rotation, shift, strict=True)], agree


__all__ = ["DescriptorPairs", "MatchOptions", "descriptor_pairs", "descriptors", "matched_poses"]
