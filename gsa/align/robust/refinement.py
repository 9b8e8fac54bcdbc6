"""Full-resolution bidirectional trimmed ICP with an overlap estimate, the frame relabellings
that seed the search, and the GT-free verdict (confidence, ambiguity) on a final pose. Their
tunables: `RefineCriteria` and `VerdictCriteria` (None: the defaults); the verdict's colour
check and ties follow the search's PoseCriteria (SearchResult.criteria)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gsa.align.nearest import nearest_candidate
from gsa.align.robust.poses import (
    Candidate,
    Convergence,
    SearchResult,
    colour_mismatch,
    rotation_offset_deg,
)
from gsa.canonical import SIGNED_PERMUTATIONS, CanonicalFrame, relabelling_label
from gsa.geometry import axis_rotation, rotation_distance_deg
from gsa.render import steps
from gsa.sim3 import DegenerateCorrespondencesError, Sim3, solve_sim3


@dataclass(frozen=True)
class RefineCriteria:
    """The full-resolution refinement (refine, coincidence, overlap_fraction); the defaults are
    the values benchmarked in docs/benchmarks.md."""

    # Overlap estimation (overlap_fraction): Chetverikov et al. use λ = 2; a larger λ keeps
    # more pairs. Measured on the partial and deform protocols: λ = 4 keeps partial overlaps
    # precise (median 0.15°) and averages smooth deformations better than λ = 2 (success 75 %
    # vs 58 % on 12 pairs).
    overlap_lambda: float = 4.0
    # The test for models that differ everywhere (_Fit.differ_everywhere): the overlap estimate
    # keeps at least whole_overlap of the pairs (between the estimate's grid values 0.85 and
    # 0.9), and fewer than coincident_share of those lie within coincident_spacings sampling
    # spacings. Measured at final poses: the share is 0.77-1.0 for converged captures of one
    # object (partial, noisy, same), 0.17-0.44 for deformed copies; partial captures whose
    # trimmed fit stopped a few degrees off share 0.2-0.3 too, but their overlap estimate is < 0.9.
    whole_overlap: float = 0.875
    coincident_spacings: float = 2.0
    coincident_share: float = 0.5
    # Coincidence says something only where the overlap is wider than the distance it is tested
    # at: a source shrunk onto a speck of the target coincides wherever it lands (a rifle 14x too
    # small, n-way's cross-instance sets at 5k Gaussians: every pair of the speck within the
    # tolerance, share 1.0, confidence 0.53 on a pose 115 degrees off). The overlap's RMS radius
    # must reach this many tolerances (coincident_spacings spacings) for its share to count.
    resolved_overlap: float = 2.0
    # The fit of two captures of one surface holds the core_fraction closest pairs (the floor
    # of overlap_fraction's grid) from the search's pose to the end. From a pose a degree or two
    # off, residuals grow smoothly everywhere and the overlap estimate reads most pairs as
    # overlap; a fit on them drifts where one capture has parts the other lacks and real
    # captures fill volumes rather than thin surfaces. The closest pairs lie where the two
    # coincide, and their fit is exact there (docs/benchmarks.md, "real captures").
    core_fraction: float = 0.3
    plane_iterations: int = 8  # point-to-plane polish steps after the point-to-point fit converged
    # Whether a fit whose models differ everywhere goes on over every pair (opt-in). Off: the
    # core fit stands whatever the pose shows. Real captures are volumes, not thin surfaces:
    # between two partial captures of one object the overlap estimate keeps every pair and
    # fewer than half coincide at the sampling noise, as between deformed copies, and the
    # all-pairs fit pulls the parts one capture lacks onto the other. Measured on pairs 0-9 of
    # 12 public captures (both exposure variants, 240 pairs): the branch fired on 11 pairs, all
    # of them misses; without it 6 of the 11 end right (bouquet, kneeling angel, candlestick,
    # street: 16-33 deg -> 0.04-0.36 deg), and no right answer changes. It paid where models really differ
    # everywhere, little: generated deformed copies 88 -> 87 of 90 (seeds 1-3), cross-instance
    # real meshes (category-real --quick) one bottle pair lost (docs/benchmarks.md, "The
    # all-pairs fit, opt-in"). A real garden's two captures (the scene path) slid 12 degrees with it.
    deformable: bool = False
    # Steps below these sit in the sampling noise of the correspondences (point-to-point fit),
    # and end the point-to-plane polish.
    convergence: Convergence = Convergence(rotation_deg=2e-3, log_scale=2e-5)
    plane_convergence: Convergence = Convergence(rotation_deg=1e-4, log_scale=1e-6)


@dataclass(frozen=True)
class VerdictCriteria:
    """The GT-free verdict on a final pose (verdict); calibrated on all benchmark protocols
    together (docs/benchmarks.md, "confidence")."""

    confidence_threshold: float = 0.5  # a result is reported doubtful below this confidence
    # confidence = min(fit, separation): fit maps the final overlap score (truncated closeness
    # both ways, anchors) from fit_floor..fit_floor+fit_span onto 0..1, so a pose whose models
    # overlap less than fit_floor + fit_span/2 = 0.55 is doubtful; two complete captures of one
    # object score 0.6-0.8, duplicates 0.8-0.9. Separation maps the lead over the best distinct
    # alternative (units of score_tie) from 0..margin_span.
    fit_floor: float = 0.45
    fit_span: float = 0.2
    margin_span: float = 4.0
    # The overlap's coincidence (verdict's `coincide`) maps coincide_floor..+coincide_span onto
    # 0..1 where the trimmed overlap estimate keeps at least coincide_min_overlap of the pairs.
    # Measured at final poses: share 0.81-0.96 for 27 of 30 right partial captures (ξ 0.55-0.95),
    # 0.92-0.95 for complete ones, 0.25-0.6 for deformed copies; wrong poses reach 0.77-0.93 too,
    # so it only tells how well the models overlap: the margin, ties and the colour check are
    # what catch wrong poses.
    coincide_floor: float = 0.7
    coincide_span: float = 0.2
    coincide_min_overlap: float = 0.5
    # An answer judged confident whose overlap (an estimate of at least coincide_min_overlap)
    # coincides on less than this share is flagged all the same (overlap_unconfirmed): the
    # surfaces lie near each other without being one surface. Measured at answers: right ones
    # on 12 real captures 0.52-0.90 (140 of 141 unflagged pairs 0.74 or more, both exposure
    # variants), a street turned 168 deg 0.34 (confidence 0.65); docs/benchmarks.md.
    unconfirmed_share: float = 0.5
    doubt_cap: float = 0.25  # the confidence at most of a tie or a colour contradiction
    # Poses offered beside the chosen one (`alternatives`): the first rival, the chosen pose
    # snapped onto the principal frames, the three half turns, the next candidates and their
    # snapped twins; the results page steps through them.
    max_alternatives: int = 8


# A pose snapped onto the principal frames (search._snapped) is offered where it turns the
# chosen pose by more than this; the other offers must be PoseCriteria.distinct_deg away.
SNAP_DISTINCT_DEG = 1.0

_REFINE = RefineCriteria()
# Two captures of one rigid object or place: never averaged as another instance or a deformed
# copy, whatever the criteria in force opt into (AlignOptions.rigid, the scene path).
RIGID_REFINE = RefineCriteria(deformable=False)
_VERDICT = VerdictCriteria()


def verdict(
    final: Candidate,
    search: SearchResult | None,
    coincide: tuple[float, float] | None = None,
    criteria: VerdictCriteria | None = None,
    offer_always: bool = False,
) -> dict:
    """GT-free judgement of a final pose: `confidence` in [0, 1] combines how well the
    two models overlap there with how clearly the pose beat the best distinct
    alternative of the search; `ambiguous` marks a tie nothing could break
    (a colourless symmetric object), with the tied poses as `alternatives`. Those are
    listed for a doubtful answer, and for a confident one where `offer_always`.

    coincide: (ξ, share) of `coincidence` at full resolution. How well the models overlap
    is the larger of the overlap score (how much of both models lies close) and how much
    of their overlap coincides, where the overlap is at least coincide_min_overlap of the
    pairs: two captures that each missed a side overlap in part, and coincide there."""
    v = criteria or _VERDICT
    fit = float(np.clip((final.geometry - v.fit_floor) / v.fit_span, 0.0, 1.0))
    if coincide is not None and coincide[0] >= v.coincide_min_overlap:
        fit = max(fit, float(np.clip((coincide[1] - v.coincide_floor) / v.coincide_span, 0.0, 1.0)))
    ambiguous = bool(search is not None and search.ambiguous)
    separation = 1.0 if search is None else float(np.clip(search.margin / v.margin_span, 0.0, 1.0))
    confidence = min(fit, separation)
    if ambiguous:
        confidence = min(confidence, v.doubt_cap)
    # Colour contradiction: where the models share a palette, aligned captures of one
    # object disagree in colour about as much as neighbouring samples of one capture
    # (colour_noise); a pose that pairs unlike parts (a flip that overlaps well) does not.
    mismatch = None
    if (
        search is not None
        and search.colour_noise is not None
        and search.colour_weight >= search.criteria.colour_trusted
    ):
        mismatch = colour_mismatch(final, search.colour_noise, search.criteria)
        if mismatch > search.criteria.colour_mismatch_limit:
            confidence = min(confidence, v.doubt_cap)
    out = {
        "confidence": confidence,
        "ambiguous": ambiguous,
        "doubtful": ambiguous or confidence < v.confidence_threshold,
        "score": final.score,
        "margin": None if search is None else search.margin,
        "overlap_score": final.geometry,
        "overlap_fraction": final.overlap,
        "colour_agreement": final.colour,
        "colour_mismatch": mismatch,
        "overlap_estimate": None if coincide is None else coincide[0],
        "coincident_share": None if coincide is None else coincide[1],
    }
    if search is not None:
        out["colour_weight"] = search.colour_weight
        out["ranked_by"] = search.ranked_by
        # `tied`: a rival (within score_tie of the chosen pose, what makes a result ambiguous).
        offer = offer_always or out["doubtful"]
        out["alternatives"] = [
            c.to_dict(final.transform) | {"tied": any(c is r for r in search.rivals)}
            for c in (alternatives(final, search, v.max_alternatives) if offer else [])
        ]
    return out


def overlap_unconfirmed(metrics: dict, criteria: VerdictCriteria | None = None) -> bool:
    """Whether a verdict's record (verdict's keys) holds an overlap that does not coincide: the
    models overlap on at least coincide_min_overlap of their pairs, yet less than
    unconfirmed_share of that overlap coincides. A confident answer with such an overlap scored
    on surfaces that lie near each other, not on one surface (a street's ground under its
    half turn)."""
    v = criteria or _VERDICT
    estimate, share = metrics.get("overlap_estimate"), metrics.get("coincident_share")
    return (
        estimate is not None
        and share is not None
        and estimate >= v.coincide_min_overlap
        and share < v.unconfirmed_share
    )


def alternatives(
    final: Candidate, search: SearchResult, count: int = VerdictCriteria.max_alternatives
) -> list[Candidate]:
    """The poses to offer beside `final` (SearchResult.offered: the first rival, the half turns
    of the chosen pose, the other candidates, the snapped poses), at most `count` and each
    distinct from `final` (the search's distinct_deg; a snapped pose SNAP_DISTINCT_DEG). Cross-instance, the truth is often not the best-scoring pose
    but one of these (docs/benchmarks.md, category-real), and a person picks it."""
    distinct = search.criteria.distinct_deg
    # A snapped pose (search._snapped: a pose turned onto the principal frames) differs from the
    # chosen one by a few degrees where the chosen pose itself drifted; it is offered unless it
    # is the chosen pose (within SNAP_DISTINCT_DEG).
    offered = [
        c
        for c in search.offered
        if rotation_offset_deg(c.transform, final.transform)
        > (SNAP_DISTINCT_DEG if c.origin.startswith("snap:") else distinct)
    ]
    return offered[:count]


def frame_relabellings(src: CanonicalFrame, dst: CanonicalFrame) -> list[tuple[str, np.ndarray]]:
    """Rotations mapping the source's canonical axes onto the target's, under all 24
    axis relabellings: where the frames hold (clean copies) one of them is exact,
    and the search refines from it."""
    return [(relabelling_label(g), dst.axes.T @ g @ src.axes) for g in SIGNED_PERMUTATIONS]


def refine(
    source_points: np.ndarray,
    target_points: np.ndarray,
    source_tree: cKDTree,
    target_tree: cKDTree,
    init: Sim3,
    iterations: int = 40,
    neighbours: int = 6,
    target_normals: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    criteria: RefineCriteria | None = None,
) -> tuple[Sim3, list[dict]]:
    """Full-resolution trimmed ICP on correspondences from both directions.

    `source_points`/`target_points` are samples (rows of the trees' points are
    matched against); each direction's k nearest neighbours are cached and
    scanned by a compiled kernel while the pose moves little, re-queried when
    the cache stops being trustworthy, as gsa.align.coarse.icp_refine does for
    one direction. Both directions: where two captures overlap only in part, a
    one-way match pulls the overlap's boundary inwards and biases the scale.

    The fit holds the core_fraction closest pairs (RefineCriteria). With
    RefineCriteria.deformable, where its pose shows two models that coincide nowhere (see
    `coincide`: another instance, a deformed copy), the fit goes on with every
    pair, so that it averages the difference instead of locking onto one part.

    target_normals: (normals, flatness) of the target tree's points and of
    `target_points` (Gaussian.surface_normals). With them, a converged fit of two captures
    of one surface is polished point-to-plane: two independent samplings of a surface
    never share points, and point-to-point pairs between them carry the sampling's
    offsets, which a pair's distance along the normal does not."""
    k = criteria or _REFINE
    fit = _Fit(source_points, target_points, source_tree, target_tree, neighbours, k)
    core, history = fit.run(init, iterations, lambda d: k.core_fraction)
    for step in history:
        step["stage"] = "refine-core"
    if not k.deformable or not fit.differ_everywhere(core):
        if target_normals is None:
            return core, history
        transform, more = fit.polish(core, target_normals, k.plane_iterations, k.core_fraction, start=len(history))
        return transform, history + more
    # Models that coincide nowhere (a deformed copy): the fit on the estimated overlap from the
    # search's pose, then on every pair, so that it averages the difference.
    transform, more = fit.run(init, iterations, lambda d: overlap_fraction(d, k.overlap_lambda), start=len(history))
    history += more
    # Its own budget: a trimmed fit on a deformed copy wanders rather than converges.
    transform, more = fit.run(transform, iterations, lambda d: 1.0, start=len(history))
    for step in more:
        step["stage"] = "refine-all-pairs"
    return transform, history + more


class _Fit:
    def __init__(self, source_points, target_points, source_tree, target_tree, neighbours: int, criteria):
        self.p = np.ascontiguousarray(source_points, np.float64)
        self.q = np.ascontiguousarray(target_points, np.float64)
        self.src_tree, self.dst_tree = source_tree, target_tree
        self.src_all = np.ascontiguousarray(source_tree.data, np.float64)
        self.dst_all = np.ascontiguousarray(target_tree.data, np.float64)
        self.neighbours = neighbours
        self.criteria: RefineCriteria = criteria

    def run(self, transform: Sim3, iterations: int, fraction_of, start: int = 0) -> tuple[Sim3, list[dict]]:
        p, q, src_all, dst_all = self.p, self.q, self.src_all, self.dst_all
        history: list[dict] = []
        it = 0
        while it < iterations:
            k_f = min(self.neighbours, len(dst_all))
            k_s = min(self.neighbours, len(src_all))
            _, tab_f = self.dst_tree.query(transform.apply(p), k=k_f, workers=_workers(len(p)))
            _, tab_r = self.src_tree.query(transform.inverse().apply(q), k=k_s, workers=_workers(len(q)))
            tab_f = np.ascontiguousarray(tab_f.reshape(len(p), -1), np.int64)
            tab_r = np.ascontiguousarray(tab_r.reshape(len(q), -1), np.int64)
            inner = 0
            while it < iterations:
                steps.step()  # a due progress report (gsa.align.pair._Repeater)
                it += 1
                inner += 1
                d, a, b = self._pairs(transform, tab_f, tab_r)
                # The overlap fraction is estimated once per neighbour table and held while
                # the pose settles on it: re-estimated every step, its jumps between grid
                # values keep the pose from converging.
                if inner == 1:
                    fraction = fraction_of(d)
                keep = _smallest(d, fraction)
                try:
                    new = solve_sim3(a[keep], b[keep])
                except DegenerateCorrespondencesError:
                    return transform, history
                step = new @ transform.inverse()
                angle = rotation_distance_deg(step.rotation, np.eye(3))
                history.append(
                    {
                        "stage": "refine",
                        "iteration": start + it,
                        "matched": int(keep.sum()),
                        "rms_residual": float(np.sqrt(np.mean(d[keep] ** 2))),
                        "delta_rotation_deg": angle,
                        "scale": new.scale,
                    }
                )
                transform = new
                if self.criteria.convergence.reached(step, angle_deg=angle):
                    if inner <= 2:
                        return transform, history
                    break  # converged on the cached tables: re-query once to confirm
                if inner >= 10:
                    break
        return transform, history

    def polish(
        self, transform: Sim3, normals, iterations: int, fraction: float, start: int = 0
    ) -> tuple[Sim3, list[dict]]:
        """Point-to-plane Gauss-Newton steps on the `fraction` closest pairs,
        each pair along its target Gaussian's normal weighted by its flatness; a step
        that does not lower the trimmed plane residual ends the polish."""
        n_all, flat_all, n_q, flat_q = normals
        k_f, k_s = min(self.neighbours, len(self.dst_all)), min(self.neighbours, len(self.src_all))
        _, tab_f = self.dst_tree.query(transform.apply(self.p), k=k_f, workers=_workers(len(self.p)))
        _, tab_r = self.src_tree.query(transform.inverse().apply(self.q), k=k_s, workers=_workers(len(self.q)))
        tab_f = np.ascontiguousarray(tab_f.reshape(len(self.p), -1), np.int64)
        tab_r = np.ascontiguousarray(tab_r.reshape(len(self.q), -1), np.int64)
        history: list[dict] = []
        for it in range(iterations):
            steps.step()
            d, a, b, j = self._pairs(transform, tab_f, tab_r, with_rows=True)
            keep = _smallest(d, fraction)
            n = np.concatenate([n_all[j], n_q])[keep]
            w = np.concatenate([flat_all[j], flat_q])[keep]
            x = transform.apply(a[keep])
            r = np.einsum("ij,ij->i", n, x - b[keep])
            cost = float(np.sqrt(np.average(r**2, weights=w))) if w.sum() > 0 else np.inf
            step = _plane_step(x, b[keep], n, w)
            if step is None:
                return transform, history
            transform = step @ transform
            angle = rotation_distance_deg(step.rotation, np.eye(3))
            history.append(
                {
                    "stage": "refine-plane",
                    "iteration": start + it + 1,
                    "matched": int(keep.sum()),
                    "rms_residual": cost,
                    "delta_rotation_deg": angle,
                    "scale": transform.scale,
                }
            )
            if self.criteria.plane_convergence.reached(step, angle_deg=angle):
                break
        return transform, history

    def _pairs(self, transform: Sim3, tab_f: np.ndarray, tab_r: np.ndarray, with_rows: bool = False):
        d_f, j = nearest_candidate(np.ascontiguousarray(transform.apply(self.p)), self.dst_all, tab_f)
        d_r, i = nearest_candidate(np.ascontiguousarray(transform.inverse().apply(self.q)), self.src_all, tab_r)
        d = np.concatenate([d_f, d_r * transform.scale])
        a = np.concatenate([self.p, self.src_all[i]])
        b = np.concatenate([self.dst_all[j], self.q])
        return (d, a, b, j) if with_rows else (d, a, b)

    def differ_everywhere(self, transform: Sim3) -> bool:
        """Whether, at this pose, the overlap estimate keeps (nearly) every pair yet most
        of them lie apart: two captures of one object coincide at the sampling noise on
        their overlap, and where one of them misses a part the estimate stops at the
        overlap instead; another instance or a deformed copy is near everywhere and
        coincides nowhere."""
        k = self.criteria
        fraction, share = coincidence(self.p, self.q, self.src_tree, self.dst_tree, transform, k)
        return fraction >= k.whole_overlap and share < k.coincident_share


def coincidence(
    source_points: np.ndarray,
    target_points: np.ndarray,
    source_tree: cKDTree,
    target_tree: cKDTree,
    transform: Sim3,
    criteria: RefineCriteria | None = None,
) -> tuple[float, float]:
    """(ξ, share) at a pose: the overlap estimate (overlap_fraction) of the pairs both ways
    between the sampled points and the other model's tree, and the share of those overlapping
    pairs closer than coincident_spacings sampling spacings: how much of the overlap
    coincides, whatever the share of each model the overlap is."""
    k = criteria or _REFINE
    steps.step()
    moved = transform.apply(source_points)
    d_f, _ = target_tree.query(moved, workers=_workers(len(source_points)))
    steps.step()
    d_r, _ = source_tree.query(transform.inverse().apply(target_points), workers=_workers(len(target_points)))
    d_back = d_r * transform.scale  # in the target's units, as d_f
    d = np.concatenate([d_f, d_back])
    spacing = max(sampling_spacing(target_tree), sampling_spacing(source_tree) * transform.scale)
    tolerance = k.coincident_spacings * spacing
    fraction = overlap_fraction(d, k.overlap_lambda)
    kept = np.sort(d)[: max(int(fraction * len(d)), 3)]
    # ≤: where a model's median spacing is 0 (stacked duplicate Gaussians), pairs at 0 coincide.
    share = float(np.mean(kept <= tolerance))
    near = np.concatenate([moved[d_f <= tolerance], target_points[d_back <= tolerance]])
    if len(near) >= 3 and _rms_radius(near) < k.resolved_overlap * tolerance:
        share = 0.0  # an unresolved speck of overlap: its coincidence says nothing
    return fraction, share


def _rms_radius(points: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def _plane_step(x: np.ndarray, y: np.ndarray, n: np.ndarray, w: np.ndarray) -> Sim3 | None:
    """The small Sim(3) S (rotation ω, translation τ, log-scale σ about the pairs' centroid)
    minimising Σ w (n·(S(x) − y))², linearised: one Gauss-Newton step of point-to-plane
    alignment. None where the normals leave a direction undetermined (a single plane)."""
    if w.sum() <= 0:
        return None
    c = np.average(x, axis=0, weights=w)
    u = x - c
    jac = np.hstack([np.cross(u, n), n, np.einsum("ij,ij->i", n, u)[:, None]])
    r = np.einsum("ij,ij->i", n, x - y)
    a = (jac * w[:, None]).T @ jac
    g = (jac * w[:, None]).T @ r
    eig = np.linalg.eigvalsh(a)
    if eig[0] <= 1e-9 * eig[-1]:
        return None
    delta = -np.linalg.solve(a, g)
    omega, tau, sigma = delta[:3], delta[3:6], delta[6]
    angle = float(np.linalg.norm(omega))
    rot = axis_rotation(omega / angle, angle) if angle > 0 else np.eye(3)
    s = float(np.exp(sigma))
    return Sim3(s, rot, c + tau - s * rot @ c)


def sampling_spacing(points: np.ndarray | cKDTree, probes: int = 2000) -> float:
    """Median distance from a Gaussian to its nearest neighbour in its own model (its
    points, or a KD-tree of them): the scale of sampling noise, within which two captures
    of one surface coincide."""
    tree = points if isinstance(points, cKDTree) else cKDTree(points)
    if tree.n < 2:
        return 0.0
    step = max(tree.n // probes, 1)
    d, _ = tree.query(tree.data[::step], k=2)
    return float(np.median(d[:, 1]))


def _smallest(d: np.ndarray, fraction: float) -> np.ndarray:
    keep = np.zeros(len(d), bool)
    keep[np.argsort(d)[: max(int(fraction * len(d)), 3)]] = True
    return keep


def overlap_fraction(d: np.ndarray, lam: float = RefineCriteria.overlap_lambda) -> float:
    """Trimmed-ICP overlap estimate (Chetverikov et al. 2005): the fraction ξ of
    pairs with the smallest residuals that minimises RMS(ξ) / ξ^(1+λ), ξ ≥ 0.3. Where the two
    models overlap only in part the residuals jump and ξ stops at the overlap; where
    one is a deformed copy of the other they grow smoothly and ξ stays near 1, so
    the fit averages the deformation instead of locking onto one part of it."""
    cum = np.cumsum(np.sort(d) ** 2)
    xi = np.linspace(0.3, 1.0, 15)
    counts = np.maximum((xi * len(d)).astype(int), 3)
    rms = np.sqrt(cum[counts - 1] / counts)
    return float(xi[np.argmin(rms / xi ** (1.0 + lam))])


def _workers(n: int) -> int:
    return -1 if n >= 20_000 else 1
