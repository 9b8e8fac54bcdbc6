"""Pose candidates of the robust search: the overlap score of one pose (truncated
closeness both ways, colour as far as the models share it), the bidirectional coloured
ICP on the anchors, and the decision between refined poses (ties -> ambiguous).

The thresholds are the fields of `PoseCriteria`; the functions take one (None: the
defaults), and a SearchResult keeps the criteria it was decided under."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from gsa.align.robust.anchoring import Anchors, PaletteOptions, colour_weight
from gsa.geometry import rotation_distance_deg
from gsa.render import steps
from gsa.sim3 import DegenerateCorrespondencesError, Sim3, solve_sim3


@dataclass(frozen=True)
class Convergence:
    """When an iterative fit stops: its last step turned by less than rotation_deg, changed
    the scale by less than log_scale (|log s|) and, where translation is given, moved by less
    than that fraction of the target's radius."""

    rotation_deg: float
    log_scale: float
    translation: float | None = None

    def reached(self, step: Sim3, radius: float = 1.0, angle_deg: float | None = None) -> bool:
        """Whether `step` (the last update) is below every tolerance; angle_deg: its rotation
        angle where the caller has it already."""
        angle = rotation_distance_deg(step.rotation, np.eye(3)) if angle_deg is None else angle_deg
        if not (angle < self.rotation_deg and abs(np.log(step.scale)) < self.log_scale):
            return False
        return self.translation is None or bool(np.linalg.norm(step.translation) < self.translation * radius)


@dataclass(frozen=True)
class PoseCriteria:
    """How poses are scored, refined on the anchors and decided between. Lengths are fractions
    of the target's anchor RMS radius; colour differences are CIELAB ΔE. The defaults are the
    values benchmarked in docs/benchmarks.md."""

    # Truncation of distances in the overlap score: far enough to count near misses, near
    # enough that a wrong pose gains nothing from points that merely lie inside the other
    # model's box.
    truncation: float = 0.1
    colour_pair_distance: float = 0.05  # pairs closer than this compare colours
    colour_sigma: float = 12.0  # colour similarity of a pair: exp(−ΔE² / 2σ²)
    # In coloured matching (bidirectional_icp), a ΔE of colour_sigma weighs like this
    # fraction of the truncation distance.
    colour_match: float = 0.5
    # Poses whose scores differ by less than this are a tie (a symmetric shape whose colours
    # cannot tell its sides apart): the result is ambiguous.
    score_tie: float = 0.03
    distinct_deg: float = 15.0  # rotations closer than this are one pose, not alternatives
    distinct_log_scale: float = 0.2  # ... and scales within this (|log ratio|, ~20 %)
    # The colour check (colour_mismatch), where the models share a palette (colour weight at
    # least colour_trusted): a pose whose overlapping pairs disagree in colour more than
    # colour_mismatch_limit times the models' own neighbour-to-neighbour colour noise
    # (floored at colour_noise_floor) pairs unlike parts. Measured on 11 sampled pairs
    # (docs/benchmarks.md): 0.35-1.24 at right poses, 2.27-2.49 at two partial airplane flips
    # (verdict). decide() prefers a pose to one scoring at most colour_switch_ties × score_tie
    # more whose mismatch is beyond the noise and colour_switch_ratio times its own.
    colour_trusted: float = 0.5
    colour_mismatch_limit: float = 2.0
    colour_noise_floor: float = 0.02
    colour_switch_ties: float = 2.0
    colour_switch_ratio: float = 2.0
    # A pair's colour factor is 1 − 2w(1 − k) (_pair_scores). Two captures of one surface,
    # aligned, disagree about as much as each model's neighbouring anchors do (colour_noise n),
    # so a right pose's pairs get 1 − 2wn on average. Where a texture varies at the anchors'
    # spacing (n ≈ 0.75 on reconstructions of a finely printed object) full trust made that
    # negative: every pose scored below zero and the one overlapping least won (a 180° flip).
    # colour_trust caps w at noise_trust / n, where the right pose's pairs stop counting against
    # it; no capture the protocols use has n above 0.5 (docs/benchmarks.md, reconstruction).
    noise_trust: float = 0.5
    # The anchors' ICP (bidirectional_icp): Tukey cut-off in median pair distances, and when it
    # stops (anchors are a summary: the full-resolution refinement does the last digits).
    icp_trim: float = 4.0
    icp_convergence: Convergence = Convergence(rotation_deg=0.01, log_scale=1e-4, translation=1e-4)
    palette: PaletteOptions = field(default_factory=PaletteOptions)  # how the palettes are compared (no pose)

    @property
    def colour_switch_window(self) -> float:
        return self.colour_switch_ties * self.score_tie


_DEFAULT = PoseCriteria()


@dataclass
class Candidate:
    transform: Sim3
    origin: str  # "grid" or "frame:<relabelling>"
    score: float = 0.0  # what poses are ranked by: overlap, with colour as far as the models share it
    geometry: float = 0.0  # overlap alone: truncated closeness both ways, in [0, 1]
    colour: float = 0.0  # colour agreement of overlapping pairs in [0, 1]
    overlap: float = 0.0  # fraction of anchors (both ways) with a partner within colour_pair_distance

    def to_dict(self, reference: Sim3 | None = None) -> dict:
        out = {
            "origin": self.origin,
            "score": self.score,
            "geometry": self.geometry,
            "colour": self.colour,
            "overlap": self.overlap,
        }
        if reference is not None:
            out["rotation_offset_deg"] = rotation_offset_deg(self.transform, reference)
            out["scale_ratio"] = self.transform.scale / reference.scale
        out["transform"] = self.transform.matrix().tolist()
        return out


def rotation_offset_deg(a: Sim3, b: Sim3) -> float:
    return rotation_distance_deg(a.rotation, b.rotation)


@dataclass
class SearchResult:
    candidates: list[Candidate]  # refined and de-duplicated, the chosen one first
    colour_weight: float  # how far colour counted in the scores (0: not shared by the models)
    margin: float  # lead over the best distinct alternative, in units of score_tie
    rivals: list[Candidate]  # the poses tied with the best
    colour_noise: float | None = None  # the models' own colour noise (colour_noise), when colour was checked
    # "score", or "geometry" where no pose made the colours agree (decide): colour told nothing apart
    ranked_by: str = "score"
    # The distinct poses to offer beside the best, in order (search._with_offers): the first
    # rival, the best turned half-way about the target's principal axes, the other candidates.
    # Offered to a person (alternatives), never ranked against the others. A list, or a
    # function that makes it on first use (`offered`): the half turns cost three ICPs, which
    # a confident answer nobody asks alternatives of need not pay.
    offers: list[Candidate] | Callable[[], list[Candidate]] = field(default_factory=list, repr=False)
    criteria: PoseCriteria = field(default=_DEFAULT, repr=False)  # what the poses were scored and decided by

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    @property
    def offered(self) -> list[Candidate]:
        """The poses to offer beside the best (made on first use where `offers` is a function)."""
        if callable(self.offers):
            self.offers = self.offers()
        return self.offers

    @property
    def ambiguous(self) -> bool:
        """A distinct pose ties with the best."""
        return bool(self.rivals)


def _pair_scores(
    d: np.ndarray, lab_a: np.ndarray, lab_b: np.ndarray, tau: float, w_colour: float, sigma: float
) -> np.ndarray:
    """Per point: truncated closeness to its partner, c·(1 − 2w(1 − k)) with k the
    colour similarity and w the trust in colour. With trusted colour a close pair of
    the wrong colour counts against a pose (one object cannot disagree with itself),
    while a point with no partner counts nothing (the other capture may lack it):
    a partial capture's flip can overlap more than its true pose, never in colour."""
    closeness = 1.0 - np.minimum(d, tau) / tau
    if w_colour <= 0:
        return closeness
    de2 = np.sum((lab_a - lab_b) ** 2, axis=-1)
    return closeness * (1.0 - 2.0 * w_colour * (1.0 - np.exp(-0.5 * de2 / sigma**2)))


def bidirectional_icp(
    src: Anchors,
    dst: Anchors,
    init: Sim3,
    src_rows: np.ndarray,
    dst_rows: np.ndarray,
    iterations: int,
    w_colour: float = 0.0,
    criteria: PoseCriteria | None = None,
    reach: float | None = None,
) -> Sim3:
    """Robust ICP with Horn's symmetric scale on correspondences from both
    directions: a source anchor's nearest target anchor, and a target anchor's
    nearest mapped source anchor. One direction alone lets a partial model's
    scale drift (it matches into the other's interior); both pin it. Pairs get
    Tukey weights (cut-off icp_trim × median distance) times their colour similarity
    as far as colour is trusted: where two partial captures do not overlap, the
    nearest partner is close in space but the wrong colour. `reach` (in units of the
    score's truncation distance) caps that cut-off: where two halves overlap on about half,
    the median distance is the part one lacks, and the plain cut-off takes those pairs in."""
    c = criteria or _DEFAULT
    p, q = src.points[src_rows], dst.points[dst_rows]
    transform = init
    # With trusted colour, partners are searched in (position, λ·Lab): a colour
    # difference of colour_sigma weighs like a fraction of the truncation distance,
    # so matches reach across a misalignment towards the same-coloured part.
    lam = c.colour_match * c.truncation * dst.radius / c.colour_sigma * w_colour
    if lam > 0:
        dst_tree = cKDTree(np.hstack([dst.points, lam * dst.lab]))
        # In source units the colour axis shrinks with the scale; the start's scale is
        # close enough for choosing partners (distances below are exact).
        lam_src = lam / init.scale
        src_tree = cKDTree(np.hstack([src.points, lam_src * src.lab]))
        p_lab, q_lab = lam * src.lab[src_rows], lam_src * dst.lab[dst_rows]
    for _ in range(iterations):
        steps.step()  # a due progress report (gsa.align.pair._Repeater)
        if lam > 0:
            mapped = transform.apply(p)
            _, j = dst_tree.query(np.hstack([mapped, p_lab]), k=1)
            _, i = src_tree.query(np.hstack([transform.inverse().apply(q), q_lab]), k=1)
            d_f = np.linalg.norm(mapped - dst.points[j], axis=1)
            d_r = np.linalg.norm(q - transform.apply(src.points[i]), axis=1)
        else:
            d_f, j = dst.tree.query(transform.apply(p), k=1)
            d_r, i = src.tree.query(transform.inverse().apply(q), k=1)
            d_r = d_r * transform.scale
        a = np.concatenate([p, src.points[i]])
        b = np.concatenate([dst.points[j], q])
        d = np.concatenate([d_f, d_r])
        cut = c.icp_trim * max(float(np.median(d)), 1e-12 * dst.radius)
        if reach is not None:
            cut = min(cut, reach * c.truncation * dst.radius)
        weight = np.clip(1.0 - (d / cut) ** 2, 0.0, None) ** 2
        if w_colour > 0:
            de2 = np.concatenate(
                [np.sum((src.lab[src_rows] - dst.lab[j]) ** 2, 1), np.sum((dst.lab[dst_rows] - src.lab[i]) ** 2, 1)]
            )
            colour = (1.0 - w_colour) + w_colour * np.exp(-0.5 * de2 / c.colour_sigma**2)
            weight = weight * colour
        keep = weight > 1e-6
        try:
            new = solve_sim3(a[keep], b[keep], weight[keep])
        except DegenerateCorrespondencesError:
            break
        step = new @ transform.inverse()
        transform = new
        if c.icp_convergence.reached(step, dst.radius):
            break
    return transform


def score_pose(
    src: Anchors,
    dst: Anchors,
    transform: Sim3,
    origin: str = "",
    w_colour: float = 0.0,
    criteria: PoseCriteria | None = None,
) -> Candidate:
    """Score, overlap-only geometry, colour agreement and overlap fraction of a pose (all anchors)."""
    c = criteria or _DEFAULT
    steps.step()
    tau = c.truncation * dst.radius
    d_f, j = dst.tree.query(transform.apply(src.points), k=1)
    d_r, i = src.tree.query(transform.inverse().apply(dst.points), k=1)
    d_r = d_r * transform.scale

    def both(fwd: np.ndarray, rev: np.ndarray) -> float:
        return float(0.5 * (np.average(fwd, weights=src.weights) + np.average(rev, weights=dst.weights)))

    score = both(
        _pair_scores(d_f, src.lab, dst.lab[j], tau, w_colour, c.colour_sigma),
        _pair_scores(d_r, dst.lab, src.lab[i], tau, w_colour, c.colour_sigma),
    )
    geometry = both(1 - np.minimum(d_f, tau) / tau, 1 - np.minimum(d_r, tau) / tau)
    near = c.colour_pair_distance * dst.radius
    pair_f, pair_r = d_f <= near, d_r <= near
    de = np.concatenate(
        [
            np.linalg.norm(src.lab[pair_f] - dst.lab[j[pair_f]], axis=1),
            np.linalg.norm(dst.lab[pair_r] - src.lab[i[pair_r]], axis=1),
        ]
    )
    colour = float(np.mean(np.exp(-0.5 * (de / c.colour_sigma) ** 2))) if len(de) else 0.0
    overlap = float(0.5 * (pair_f.mean() + pair_r.mean()))
    return Candidate(transform, origin, score, geometry, colour, overlap)


def colour_trust(src: Anchors, dst: Anchors, noise: float, criteria: PoseCriteria | None = None) -> float:
    """How far colour counts in the scores: the palettes' agreement (colour_weight), capped
    where the models' own colour noise (mean colour_noise) would make a right pose's pairs
    count against it (noise_trust)."""
    c = criteria or _DEFAULT
    weight = colour_weight(src, dst, c.palette)
    return min(weight, c.noise_trust / noise) if noise > 0 else weight


def colour_noise(a: Anchors, criteria: PoseCriteria | None = None) -> float:
    """1 − the colour agreement (as in score_pose) of each anchor with its nearest
    neighbour in its own model: how much one capture's colour varies between
    neighbouring samples of its surface. Two captures of one object, aligned, disagree
    about as much; a wrong pose pairs different parts and disagrees more (verdict)."""
    if len(a) < 2:
        return 0.0
    _, j = a.tree.query(a.points, k=2)
    de2 = np.sum((a.lab - a.lab[j[:, 1]]) ** 2, axis=1)
    sigma = (criteria or _DEFAULT).colour_sigma
    return float(1.0 - np.average(np.exp(-0.5 * de2 / sigma**2), weights=a.weights))


def dedupe(cands: list[Candidate], criteria: PoseCriteria | None = None) -> list[Candidate]:
    """Several starts converge to one pose: keep the best-scoring copy of each (best first;
    one pose: rotations within distinct_deg and scales within distinct_log_scale)."""
    k = criteria or _DEFAULT
    cands = sorted(cands, key=lambda c: -c.score)
    out: list[Candidate] = []
    for c in cands:
        if all(
            rotation_offset_deg(c.transform, o.transform) > k.distinct_deg
            or abs(np.log(c.transform.scale / o.transform.scale)) > k.distinct_log_scale
            for o in out
        ):
            out.append(c)
    return out


def colour_mismatch(c: Candidate, noise: float, criteria: PoseCriteria | None = None) -> float:
    """How many times the models' own colour noise (colour_noise) the pose's overlapping
    pairs disagree in colour: about 1 or less for captures of one object aligned."""
    return (1.0 - c.colour) / max(noise, (criteria or _DEFAULT).colour_noise_floor)


def decide(
    cands: list[Candidate], w_colour: float, noise: float | None = None, criteria: PoseCriteria | None = None
) -> SearchResult:
    """The best score wins; a distinct pose within score_tie of it makes the result ambiguous.

    With a shared palette and the models' colour noise, colour also vetoes: a pose whose
    pairs disagree beyond the noise, colour_switch_ratio times more than another pose
    within colour_switch_window of its score, yields to that pose, and such contradicted
    poses are no rivals. A partial capture's flip can overlap the other capture better
    than the truth does, but one object does not disagree with itself.

    Where even the pose whose colours agree best disagrees beyond the noise, the models
    do not share their colours where they overlap (another instance with another paint,
    a repainted object) whatever their palettes share: poses are ranked by geometry. So too
    where the best score ties with a pose that overlaps nothing (scores zero): then every
    pose's close pairs disagree about as much as the noise or more (a small capture's colours
    under an exposure shift), and the coloured score would only reward overlapping less."""
    k = criteria or _DEFAULT
    ranked_by = "score"
    if noise is not None and w_colour > 0 and cands and _colour_ranks_nothing(cands, noise, k):
        cands = sorted((replace(c, score=c.geometry) for c in cands), key=lambda c: -c.score)
        ranked_by = "geometry"
    if ranked_by == "score" and noise is not None and w_colour >= k.colour_trusted and len(cands) > 1:
        near = [c for c in cands if c.score >= cands[0].score - k.colour_switch_window]
        cleanest = min(near, key=lambda c: colour_mismatch(c, noise, k))
        if _contradicted(cands[0], cleanest, noise, k):
            cands = [cleanest] + [c for c in cands if c is not cleanest]
        best = cands[0]
        others = [c for c in cands[1:] if not _contradicted(c, best, noise, k)]
    else:
        best, others = cands[0], cands[1:]
    rivals = [c for c in others if c.score >= best.score - k.score_tie]
    margin = (best.score - max(c.score for c in others)) / k.score_tie if others else float("inf")
    return SearchResult(cands, w_colour, float(margin), rivals, noise, ranked_by, criteria=k)


def with_given_pose(given: Candidate, found: SearchResult) -> SearchResult:
    """The search's result re-judged around a pose the user gave (gsa.align.guided): `given`
    comes first whatever it scores, and its margin over the distinct poses the search found
    is negative where one of them beats it, so the verdict says so (and lists it); the
    criteria are the search's."""
    k = found.criteria
    others = [c for c in found.candidates if rotation_offset_deg(c.transform, given.transform) > k.distinct_deg]

    def key(c: Candidate) -> float:
        return c.geometry if found.ranked_by == "geometry" else c.score

    rivals = [c for c in others if key(c) >= key(given) - k.score_tie]
    margin = (key(given) - max(key(c) for c in others)) / k.score_tie if others else float("inf")
    return SearchResult(
        [given, *others],
        found.colour_weight,
        float(margin),
        rivals,
        found.colour_noise,
        found.ranked_by,
        lambda: [
            c
            for c in [found.best, *found.offered]
            if rotation_offset_deg(c.transform, given.transform) > k.distinct_deg
        ],
        k,
    )


def prefer_among_tied(found: SearchResult, key: Callable[[Candidate], float]) -> SearchResult:
    """The search's result with, of the best and the poses tied with it, the one of least
    `key` first: where the models' geometry cannot tell poses apart (a mug turned about its
    body), what a person said (which way it faces) decides. The others keep their order; the
    margin and rivals are taken again around the pose now first."""
    tied = [found.best, *found.rivals]
    chosen = min(tied, key=key)
    if chosen is found.best:
        return found
    k = found.criteria

    def measure(c: Candidate) -> float:
        return c.geometry if found.ranked_by == "geometry" else c.score

    others = [c for c in found.candidates if c is not chosen]
    rivals = [c for c in others if measure(c) >= measure(chosen) - k.score_tie]
    margin = (measure(chosen) - max(measure(c) for c in others)) / k.score_tie
    return SearchResult(
        [chosen, *others],
        found.colour_weight,
        float(margin),
        rivals,
        found.colour_noise,
        found.ranked_by,
        lambda: [found.best, *(c for c in found.offered if c is not chosen)],
        k,
    )


def _colour_ranks_nothing(cands: list[Candidate], noise: float, criteria: PoseCriteria) -> bool:
    """Whether the coloured scores cannot rank `cands` (decide): even the pose whose colours
    agree best disagrees beyond the noise, or no pose scores a tie above zero. Measured on the
    public captures drawn to 12k Gaussians, exposure-shifted (docs/benchmarks.md, "Colour
    trust on small captures"): the statue massa's held-out pairs 35-49 14 -> 15 / 15, pairs
    30-34 of every capture 56 / 60 either way."""
    if max(c.score for c in cands) < criteria.score_tie:
        return True
    return min(colour_mismatch(c, noise, criteria) for c in cands) > criteria.colour_mismatch_limit


def _contradicted(pose: Candidate, reference: Candidate, noise: float, criteria: PoseCriteria) -> bool:
    """Whether `pose` disagrees in colour beyond the noise and colour_switch_ratio times
    more than `reference`."""
    m = colour_mismatch(pose, noise, criteria)
    return m > 1.0 and m >= criteria.colour_switch_ratio * colour_mismatch(reference, noise, criteria)
