"""The global search over SO(3): pose scoring through nearest-anchor grids (numba kernels),
capture steps, offset trials, the widened placement search for doubtful answers, and
successive-halving refinement of the best starts (the candidates themselves: poses.py)."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numba
import numpy as np
from scipy.spatial import cKDTree

from gsa.align.robust.anchoring import Anchors, NearestGrid, grid_index, subsample
from gsa.align.robust.matching import MatchOptions, matched_poses
from gsa.align.robust.placement import placed_starts
from gsa.align.robust.poses import (
    Candidate,
    PoseCriteria,
    SearchResult,
    bidirectional_icp,
    colour_noise,
    colour_trust,
    decide,
    dedupe,
    score_pose,
)
from gsa.canonical import SIGNED_PERMUTATIONS
from gsa.geometry import axis_rotation, rotation_distance_deg, super_fibonacci_rotations
from gsa.kernels import KERNEL_LOCK
from gsa.manhattan import turned_onto
from gsa.render import steps
from gsa.sim3 import Sim3


@dataclass(frozen=True)
class SearchOptions:
    """What the global search tries (counts, grids, schedules) and, in `criteria`, how it
    scores and decides between poses. align() sets rotations and seed from AlignOptions
    (search_rotations, seed)."""

    # super-Fibonacci samples; the default is AlignOptions.search_rotations' (a test holds them
    # equal). 2048 already put any rotation within ~10° (median), 17° (worst) of one.
    rotations: int = 4096
    score_points: int = 256  # anchors per model used to score every rotation
    # Capture radii (in units of the truncation τ) of the translation/scale steps per rotation.
    capture_steps: tuple[float, ...] = (8.0, 8.0, 6.0, 4.0, 3.0, 2.0, 1.5)
    translation_top: int = 24  # rotations that also try the offsets below
    translation_step: float = 0.25  # offset grid step, fraction of the target radius
    translation_reach: int = 2  # offsets −reach..reach steps per axis
    scale_factors: tuple[float, ...] = (0.7, 0.85, 1.0, 1.18, 1.4)
    refine_top: int = 10  # distinct rotations refined by anchor ICP
    refine_points: int = 800  # anchors per side in the starts' ICP
    early_iterations: int = 10  # ICP iterations every refined start gets
    finalists: int = 4  # starts that then run up to refine_iterations more
    refine_iterations: int = 60
    # Placement search (gsa.align.robust.placement), run when `widen_if` says so.
    place_rotations: int = 256  # coarse grid: any rotation within ~20° of one
    place_points: int = 24  # anchors per side scored per placement
    place_step: float = 0.35  # lattice of source-centre positions, fraction of the target radius
    place_truncation: float = 0.25  # loose: the coarse rotation is up to ~20° off
    place_scales: tuple[float, ...] = (0.75, 1.0, 1.33)
    place_top: int = 6  # distinct placements refined to convergence
    # Matched starts (gsa.align.robust.matching), run beside the placements: poses most
    # descriptor pairs agree with, refined to convergence (0: none).
    match_top: int = 4
    matching: MatchOptions = field(default_factory=MatchOptions)
    # Axes (target coordinates) of the half turns offered beside the best pose (_with_offers);
    # None: the target's principal axes. A search about a known up axis offers the turn about it.
    offer_turn_axes: tuple[tuple[float, float, float], ...] | None = None
    # Poses offered beside the best must put the source this share of the score's truncation
    # away from it and from each other (mean nearest distance both ways): a quarter merges the
    # spins of a turned shape (a bottle's: 0.04-0.06 of the radius apart on ~800 anchors) only
    # where they coincide, and keeps the near-symmetric twins (a table turned by 90 degrees,
    # 0.25 of the radius apart) that a person must choose between.
    offer_distinct: float = 0.25
    # Beside each offered pose (and the best), the same pose with its rotation snapped onto the
    # nearest relabelling of the principal frames (_snapped), where that moves it by more than
    # this many degrees: across instances the ICP drifts 5-20 degrees off poses whose principal
    # axes agree (a bathtub, a rifle, a table). None: no snapped poses.
    offer_snap_deg: float | None = 1.0
    rival_window: float = 0.08  # unfinished starts scoring within this of the best finished one are finished too
    sweep_degrees: float = 16.0  # _sweep_twins: rotations of ± this and half this about each axis
    seed: int = 0
    criteria: PoseCriteria = field(default_factory=PoseCriteria)  # scoring and decision (gsa.align.robust.poses)


def global_search(
    src: Anchors,
    dst: Anchors,
    frame_rotations: list[tuple[str, np.ndarray]] | None = None,
    options: SearchOptions | None = None,
    widen_if: Callable[[SearchResult], bool] | None = None,
) -> SearchResult:
    """Search SO(3) for the Sim(3) mapping `src` anchors onto `dst` anchors. If
    widen_if(result) holds (the pipeline: the answer is doubtful), placements that do
    not trust centroids join the candidates (gsa.align.robust.placement) and the best
    of all wins."""
    opts = options or SearchOptions()
    k = opts.criteria
    rng = np.random.default_rng(opts.seed)
    rotations = super_fibonacci_rotations(opts.rotations)
    origins = ["grid"] * len(rotations)
    for label, r in frame_rotations or []:
        rotations = np.concatenate([rotations, r[None]])
        origins.append(f"frame:{label}")
    scale0 = dst.radius / src.radius
    tau = k.truncation * dst.radius
    # Cells of τ/2 bound the lookup error well inside the truncation; a radius of
    # padding covers poses that overhang the other model (beyond it a point scores zero).
    dst_grid = NearestGrid(dst.points, 0.5 * tau, dst.radius)
    src_grid = NearestGrid(src.points, 0.5 * tau / scale0, src.radius)

    noise = 0.5 * (colour_noise(src, k) + colour_noise(dst, k))
    w_colour = colour_trust(src, dst, noise, k)
    scorer = _GridScorer(src, dst, dst_grid, src_grid, rng, opts.score_points, tau, w_colour, k.colour_sigma)
    # Centres and RMS radii are only a first guess: a capture that missed a side has
    # its centroid moved by up to a radius and its radius off by up to ~40 %.
    scale = np.full(len(rotations), scale0)
    t = np.broadcast_to(dst.center, (len(rotations), 3)).copy()
    scale, t = scorer.capture(rotations, scale, t, opts.capture_steps)
    # Candidates are ranked by the mean of the coloured score and the geometric one: a
    # rotation ten degrees off the truth pairs many points with the wrong colour and can
    # rank below a geometric flip; the geometric half keeps it in the running, and
    # colour decides after ICP, where the pose is exact enough for colours to compare.
    score = scorer.score(rotations, scale, t, blend=True)
    top = _distinct(np.argsort(-score), rotations, opts.translation_top, k.distinct_deg / 2)
    _try_offsets(scorer, rotations, scale, t, score, top, opts)

    # Refine the best distinct rotations, and the best frame relabelling (exact on clean copies).
    frames = np.arange(opts.rotations, len(rotations))
    first = [int(frames[np.argmax(score[frames])])] if len(frames) else []
    chosen = _distinct(
        np.concatenate([first, np.argsort(-score)]).astype(int), rotations, opts.refine_top, k.distinct_deg
    )
    starts = [
        (origins[i], Sim3(float(scale[i]), rotations[i], t[i] - scale[i] * rotations[i] @ src.center)) for i in chosen
    ]
    refined = _refine_starts(src, dst, starts, w_colour, rng, opts)
    refined = _sweep_twins(src, dst, refined, w_colour, rng, opts)
    result = decide(dedupe(refined, k), w_colour, noise, k)
    if widen_if is None or not widen_if(result):
        return _with_offers(src, dst, result, w_colour, rng, opts)
    # Placed starts begin up to ~20° off and look poor after a few iterations (a partial
    # overlap converges slowly), so each runs to convergence rather than being halved.
    src_rows = subsample(rng, len(src), opts.refine_points)
    dst_rows = subsample(rng, len(dst), opts.refine_points)

    def converged(init: Sim3, origin: str) -> Candidate:
        return _converged(src, dst, init, origin, (src_rows, dst_rows), w_colour, opts)

    placements = placed_starts(
        src,
        dst,
        rng,
        rotations=opts.place_rotations,
        points=opts.place_points,
        step=opts.place_step,
        truncation=opts.place_truncation,
        scales=opts.place_scales,
        count=opts.place_top,
        min_deg=k.distinct_deg,
        capture=scorer.capture,
        capture_steps=opts.capture_steps[-3:],
    )

    def placed(placement: tuple) -> Candidate:
        r, s_, t_ = placement
        return converged(Sim3(s_, r, t_ - s_ * r @ src.center), "placed")

    refined += steps.parallel_map(placed, placements)
    if opts.match_top:
        # their own draws: where no pose is matched, the search's later draws (the offers) stay as they were
        matching_rng = np.random.default_rng([opts.seed, 1])

        def matched(init: Sim3) -> Candidate:
            plain = converged(init, "matched")
            start = score_pose(src, dst, init, "matched", w_colour, k)
            if plain.score < opts.matching.slid_share * start.score:
                # the ICP slid off the start (two halves overlapping on about half): held within its reach
                rows = (src_rows, dst_rows)
                held = _converged(src, dst, init, "matched", rows, w_colour, opts, opts.matching.icp_reach)
                plain = max(plain, held, key=lambda c: c.score)
            return plain

        def scored(poses: list[Sim3]) -> np.ndarray:
            r = np.stack([p.rotation for p in poses])
            s = np.array([p.scale for p in poses], np.float64)
            return scorer.score(r, s, np.stack([p.apply(src.center) for p in poses]))

        # The score ranks hypotheses only where it compares colours: in shape alone two instances'
        # scores peak off the truth (a vase pair's 61 degrees off), as two captures' do not.
        ranker = scored if w_colour >= k.colour_trusted else None
        inits = matched_poses(src, dst, matching_rng, opts.match_top, k.distinct_deg, opts.matching, w_colour, ranker)
        refined += steps.parallel_map(matched, inits)
    return _with_offers(src, dst, decide(dedupe(refined, k), w_colour, noise, k), w_colour, rng, opts)


def _converged(
    src: Anchors,
    dst: Anchors,
    init: Sim3,
    origin: str,
    rows: tuple,
    w_colour: float,
    opts: SearchOptions,
    reaches: tuple[float, ...] = (),
) -> Candidate:
    """A start taken by the anchors' ICP to convergence (the early and the refine budgets) and
    scored: the widened search's placed and matched starts, and the offers' half turns.
    `reaches`: bidirectional_icp's caps on its cut-off, run in turn, each from where the last
    ended, the best scoring kept (MatchOptions.icp_reach); none: the plain cut-off."""
    k = opts.criteria
    iterations = opts.early_iterations + opts.refine_iterations
    held, best = init, None
    for reach in reaches or (None,):
        held = bidirectional_icp(src, dst, held, rows[0], rows[1], iterations, w_colour, k, reach)
        scored = score_pose(src, dst, held, origin, w_colour, k)
        best = scored if best is None or scored.score > best.score else best
    return best


# Unit axes the turned starts of held_within_reach turn about: the cube's 6 faces, 12 edges, 8 corners.
_TURN_AXES = np.array([v for v in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(v)])
_TURN_AXES /= np.linalg.norm(_TURN_AXES, axis=1)[:, None]


def held_within_reach(
    src: Anchors, dst: Anchors, pose: Sim3, w_colour: float, opts: SearchOptions, turns: tuple[float, ...] = ()
) -> tuple[Candidate, Candidate] | None:
    """The anchors' ICP from `pose` with its cut-off capped at matching.icp_reach, where `pose`
    scores under matching.slid_share of the pose it reaches: (that pose, `pose` as scored);
    None elsewhere. The matched starts' slide test, asked of the full-resolution fit: where
    two halves overlap on about half, the fit's trimmed pairs include the part one lacks and
    it slides off the search's pose (an iPhone room's halves: 5.3 degrees off at the start,
    5.7 after the fit, 0.4 within reach, the score 0.057 against 0.168); between a model and
    its bent copy the score peaks a few degrees off the truth, but not by twice. Only where colours
    agree at the held pose, or where it fits better than `pose` in geometry and in colour each.
    `turns` (degrees): the ICP runs from `pose` turned so about each of 26 axes through the
    source centroid's image too, the best scoring held."""
    k = opts.criteria
    rng = np.random.default_rng([opts.seed, 2])  # its own draws: the search's stay as they were
    rows = (subsample(rng, len(src), opts.refine_points), subsample(rng, len(dst), opts.refine_points))
    starts = [pose] + [
        turned_onto(pose, axis_rotation(axis, np.radians(deg)) @ pose.rotation, src.center)
        for deg in turns
        for axis in _TURN_AXES
    ]
    # The first cap from every start, the narrower ones from the best only (a doubtful answer
    # has 53 starts: every cap from each added a fifth to a doubtful job's time).
    first, rest = opts.matching.icp_reach[:1], opts.matching.icp_reach[1:]
    held = max(
        steps.parallel_map(
            lambda s: _converged(src, dst, s, "held within reach", rows, w_colour, opts, first),
            starts,
        ),
        key=lambda c: c.score,
    )
    if rest:
        narrowed = _converged(src, dst, held.transform, "held within reach", rows, w_colour, opts, rest)
        held = max(held, narrowed, key=lambda c: c.score)
    now = score_pose(src, dst, pose, "", w_colour, k)
    # Scores compare only where colours agree at the held pose (its coloured score keeps
    # slid_share of its geometric one): under an exposure shift the coloured scores sit near
    # or below zero at the truth, and a share of them measures the colours' noise, not a slide
    # (exposure-shifted statues: a 0.02-degree fit scoring -0.02 against 0.01 within reach).
    agree = held.score > 0 and held.score >= opts.matching.slid_share * held.geometry
    # Where colours agree less at the held pose (two small halves dealt from one capture: 0.53
    # at the truth), one that fits better in geometry and in colour each is better however the
    # two are weighed: the coloured scores compare there too.
    better = held.score > 0 and held.geometry > now.geometry and held.colour > now.colour
    return (held, now) if (agree or better) and now.score < opts.matching.slid_share * held.score else None


def _with_offers(
    src: Anchors, dst: Anchors, result: SearchResult, w_colour: float, rng: np.random.Generator, opts: SearchOptions
) -> SearchResult:
    """The result with its offers made on first use (SearchResult.offered, _offers), from the
    random state `rng` has now: the same poses whenever, and however often, they are made."""
    state = rng.bit_generator.state

    def make() -> list[Candidate]:
        replay = np.random.Generator(type(rng.bit_generator)())
        replay.bit_generator.state = state
        return _offers(src, dst, result, w_colour, replay, opts)

    return replace(result, offers=make)


def _offers(
    src: Anchors, dst: Anchors, result: SearchResult, w_colour: float, rng: np.random.Generator, opts: SearchOptions
) -> list[Candidate]:
    """The poses to offer beside the result's best: the first rival, the best
    turned by 180° about each of opts.offer_turn_axes (default: the target's principal axes),
    through the target's centre, and refined by the anchors' ICP, then the other candidates by
    score (the other rivals among them). Each after the first rival is kept only where it puts
    the source opts.offer_distinct truncations away from the best and from every pose kept before it: turns of a
    symmetric shape that land on one surface are one pose. Cross-instance misses are mostly such
    half turns (a bathtub end for end, a vase upside down) that the search did not refine; they
    are offered to pick (gsa.align.guided), never ranked, so no verdict changes. With
    opts.offer_snap_deg, each of these poses also comes snapped onto the principal frames
    (_snapped): the best's right after the first rival, the others' after all the rest."""
    best = result.best.transform
    k = opts.criteria
    src_rows = subsample(rng, len(src), opts.refine_points)
    dst_rows = subsample(rng, len(dst), opts.refine_points)

    def converged(init: Sim3, origin: str) -> Candidate:
        return _converged(src, dst, init, origin, (src_rows, dst_rows), w_colour, opts)

    if opts.offer_turn_axes is not None:
        axes = np.asarray(opts.offer_turn_axes, np.float64).reshape(-1, 3)
        axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    else:
        _, _, axes = np.linalg.svd((dst.points - dst.center) * np.sqrt(dst.weights)[:, None], full_matrices=False)
    flips = []
    for n, axis in enumerate(axes):
        turn = axis_rotation(axis, np.pi)
        # x -> turn (T(x) - c) + c: the half turn about the target's centre, after the best pose.
        start = Sim3(best.scale, turn @ best.rotation, turn @ (best.translation - dst.center) + dst.center)
        flips.append(converged(start, f"flip:axis{n}"))
    sample = src.points[src_rows]
    limit = opts.offer_distinct * k.truncation * dst.radius
    # The first rival stays whatever its surface: the turns of a symmetric shape are what the
    # person must choose between (a bottle's many spins are one choice, though).
    offered = list(result.rivals[:1])
    kept_points = [c.transform.apply(sample) for c in [result.best, *offered]]
    for c in [*flips, *result.candidates[1:]]:
        if any(c is o for o in offered):
            continue
        moved = c.transform.apply(sample)
        if all(_surface_gap(moved, other) > limit for other in kept_points):
            offered.append(c)
            kept_points.append(moved)
    if opts.offer_snap_deg is not None:
        snapped = _snapped(src, dst, [result.best, *offered], w_colour, opts)
        # The best's snapped twin right after the first rival, the others' after every offer.
        first = [c for i, c in snapped if i == 0]
        offered = [*offered[:1], *first, *offered[1:], *[c for i, c in snapped if i > 0]]
    return offered


def _snapped(
    src: Anchors, dst: Anchors, poses: list[Candidate], w_colour: float, opts: SearchOptions
) -> list[tuple[int, Candidate]]:
    """(index into `poses`, snapped pose): each pose with its rotation replaced by the nearest
    of the 24 relabellings of the source's principal axes onto the target's, turning about the
    source's mapped centre (scale kept), where that moves it by more than opts.offer_snap_deg;
    one per snapped rotation. Another instance's proportions leave the principal axes of a
    category's shapes in place (an elongated bathtub, rifle or table) where the ICP's pose
    drifts off them by 5-20 degrees."""
    src_axes, dst_axes = _principal_axes(src), _principal_axes(dst)
    frames = [dst_axes.T @ g @ src_axes for g in SIGNED_PERMUTATIONS]
    out: list[tuple[int, Candidate]] = []
    for n, c in enumerate(poses):
        gaps = [rotation_distance_deg(r, c.transform.rotation) for r in frames]
        r = frames[int(np.argmin(gaps))]
        if min(gaps) <= opts.offer_snap_deg or any(
            rotation_distance_deg(r, o.transform.rotation) <= opts.offer_snap_deg for _, o in out
        ):
            continue
        centre = c.transform.apply(src.center)
        pose = Sim3(c.transform.scale, r, centre - c.transform.scale * r @ src.center)
        out.append((n, score_pose(src, dst, pose, "snap:" + c.origin, w_colour, opts.criteria)))
    return out


def _principal_axes(a: Anchors) -> np.ndarray:
    """The anchors' weighted principal axes, the rows of a rotation (right-handed)."""
    _, _, axes = np.linalg.svd((a.points - a.center) * np.sqrt(a.weights)[:, None], full_matrices=False)
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return axes


def _surface_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Mean nearest distance between two point sets, both ways."""
    return 0.5 * float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def _try_offsets(
    scorer: _GridScorer,
    rotations: np.ndarray,
    scale: np.ndarray,
    t: np.ndarray,
    score: np.ndarray,
    top: list[int],
    opts: SearchOptions,
) -> None:
    """The most promising rotations also try a grid of translation offsets and scale
    factors around their estimate, then two capture steps (the capture can settle on
    the wrong stretch of a long part). Updates scale, t and score in place where better."""
    src = scorer.src
    step = opts.translation_step * scorer.dst.radius
    g = np.arange(-opts.translation_reach, opts.translation_reach + 1) * step
    offsets = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    factors = np.asarray(opts.scale_factors)
    k_rot, k_off, k_fac = (
        k.ravel() for k in np.meshgrid(top, np.arange(len(offsets)), np.arange(len(factors)), indexing="ij")
    )
    # Scaling about the mapped centre of the sampled anchors keeps a scale change from shifting them.
    arm = rotations[k_rot] @ (scorer.src_mean - src.center)
    trial_scale = scale[k_rot] * factors[k_fac]
    trial_t = t[k_rot] + scale[k_rot, None] * arm + offsets[k_off] - trial_scale[:, None] * arm
    trial_score = scorer.score(rotations[k_rot], trial_scale, trial_t, blend=True).reshape(len(top), -1)
    rows = np.arange(len(top)) * trial_score.shape[1] + np.argmax(trial_score, axis=1)
    s2, t2 = scorer.capture(rotations[top], trial_scale[rows], trial_t[rows], opts.capture_steps[-2:])
    new_score = scorer.score(rotations[top], s2, t2, blend=True)
    better = new_score > score[top]
    scale[top] = np.where(better, s2, scale[top])
    t[top] = np.where(better[:, None], t2, t[top])
    score[top] = np.maximum(score[top], new_score)


def _refine_starts(
    src: Anchors,
    dst: Anchors,
    starts: list[tuple[str, Sim3]],
    w_colour: float,
    rng: np.random.Generator,
    opts: SearchOptions,
) -> list[Candidate]:
    """Successive halving: every start gets a few ICP iterations, the leaders the rest."""
    crit = opts.criteria
    src_rows = subsample(rng, len(src), opts.refine_points)
    dst_rows = subsample(rng, len(dst), opts.refine_points)

    def icp(init: Sim3, origin: str, iterations: int) -> Candidate:
        transform = bidirectional_icp(src, dst, init, src_rows, dst_rows, iterations, w_colour, crit)
        return score_pose(src, dst, transform, origin, w_colour, crit)

    def finished(c: Candidate) -> Candidate:
        return icp(c.transform, c.origin, opts.refine_iterations)

    # Independent ICPs run side by side where cores are free (the same poses either way).
    early = steps.parallel_map(lambda start: icp(start[1], start[0], opts.early_iterations), starts)
    early.sort(key=lambda c: -c.score)
    refined = steps.parallel_map(finished, early[: opts.finalists])
    for c in early[opts.finalists :]:
        # Past the finalists, a start still runs to convergence if its unfinished score
        # is close to the best: a symmetric pose half-way there must not look worse
        # than it is, or a tie would pass for a clear win.
        if c.score < max(r.score for r in refined) - opts.rival_window:
            refined.append(c)
            continue
        refined.append(finished(c))
    return refined


def _sweep_twins(
    src: Anchors, dst: Anchors, refined: list[Candidate], w_colour: float, rng: np.random.Generator, opts: SearchOptions
) -> list[Candidate]:
    """Where the shape is symmetric — distinct poses whose geometry ties with the best
    (geometric twins) — and colour is trusted to tell them apart, the best-scoring poses
    also try rotations of up to opts.sweep_degrees about their centres, kept by their coloured
    score, and the anchor ICP again from the best of them. Geometry holds no such pose in place, and
    the coloured ICP's pull fades a few degrees out: on a 5-fold wheel it stopped 10° off
    the truth, and a flip that had converged outscored it."""
    k = opts.criteria
    if w_colour < k.colour_trusted or len(refined) < 2:
        return refined
    distinct = dedupe(refined, k)
    top = max(c.geometry for c in distinct)
    if sum(c.geometry >= top - k.score_tie for c in distinct) < 2:
        return refined
    src_rows = subsample(rng, len(src), opts.refine_points)
    dst_rows = subsample(rng, len(dst), opts.refine_points)

    out = list(refined)
    turns = _sweep_turns(opts.sweep_degrees)
    for c in distinct[: opts.finalists]:
        centre = c.transform.apply(src.center)
        best, best_score = c.transform, c.score
        for turn in turns:
            pose = Sim3(1.0, turn, centre - turn @ centre) @ c.transform
            score = score_pose(src, dst, pose, "", w_colour, k).score
            if score > best_score:
                best, best_score = pose, score
        if best is not c.transform:
            transform = bidirectional_icp(src, dst, best, src_rows, dst_rows, opts.refine_iterations, w_colour, k)
            swept = score_pose(src, dst, transform, c.origin + "+sweep", w_colour, k)
            if swept.score > c.score:
                out.append(swept)
    return out


def _sweep_turns(degrees: float) -> np.ndarray:
    angles = np.radians([-degrees, -degrees / 2, degrees / 2, degrees])
    return np.array([axis_rotation(axis, a) for axis in np.eye(3) for a in angles])


def _distinct(order: np.ndarray, rotations: np.ndarray, count: int, min_deg: float) -> list[int]:
    """The first `count` indices of `order` whose rotations are min_deg apart."""
    chosen: list[int] = []
    for i in order:
        if len(chosen) >= count:
            break
        if all(rotation_distance_deg(rotations[i], rotations[j]) > min_deg for j in chosen):
            chosen.append(int(i))
    return chosen


class _GridScorer:
    """Pose scoring on anchor samples through the nearest-anchor grids, many poses
    at once in compiled loops (no (poses × points) temporaries)."""

    def __init__(
        self,
        src: Anchors,
        dst: Anchors,
        dst_grid: NearestGrid,
        src_grid: NearestGrid,
        rng: np.random.Generator,
        points: int,
        tau: float,
        w_colour: float,
        sigma: float,
    ):
        self.src, self.dst, self.dst_grid, self.src_grid = src, dst, dst_grid, src_grid
        p_rows, q_rows = subsample(rng, len(src), points), subsample(rng, len(dst), points)
        self.ps, self.qs = src.points[p_rows], dst.points[q_rows]
        self.p_lab, self.q_lab = src.lab[p_rows], dst.lab[q_rows]
        self.src_mean = self.ps.mean(0)
        self.tau, self.w_colour, self.sigma = tau, w_colour, sigma

    def capture(self, rotations, scale, t, reaches):
        """Shrinking capture radii (units of τ) pull each pose's translation and scale
        onto the nearest target anchors: Horn's symmetric scale and the centroid of the
        captured pairs, rotation held."""
        scale, t = scale.astype(np.float64).copy(), t.astype(np.float64).copy()
        rotations = np.ascontiguousarray(rotations, np.float64)
        centred = np.ascontiguousarray(self.ps - self.src.center)
        g = self.dst_grid
        radii = np.asarray(reaches, np.float64) * self.tau
        with KERNEL_LOCK:
            _capture(rotations, centred, scale, t, g.nearest_flat, g.lo, 1.0 / g.cell, g.shape, self.dst.points, radii)
        return scale, t

    def score(self, rotations, scale, t, blend: bool = False) -> np.ndarray:
        """Overlap score both ways (with colour as far as trusted) of each pose;
        blend: the mean of that and the geometry-only score (one pass computes both)."""
        rotations = np.asarray(rotations, np.float64)
        lin = scale[:, None, None] * rotations
        off = t - np.einsum("rij,j->ri", lin, self.src.center)
        with KERNEL_LOCK:
            return self._scores_both_ways(rotations, scale, t, lin, off, blend)

    def _scores_both_ways(self, rotations, scale, t, lin, off, blend: bool) -> np.ndarray:
        g = self.dst_grid
        fwd = _score_poses(
            np.ascontiguousarray(lin),
            np.ascontiguousarray(off),
            np.ones(len(scale)),
            self.ps,
            self.p_lab,
            g.nearest_flat,
            g.lo,
            1.0 / g.cell,
            g.shape,
            self.dst.points,
            self.dst.lab,
            self.tau,
            self.w_colour,
            self.sigma,
        )
        # Reverse: x_s = Rᵀ (q − t) / s + c_s, distances back in target units (× s).
        inv = np.transpose(rotations, (0, 2, 1)) / scale[:, None, None]
        inv_off = self.src.center - np.einsum("rij,rj->ri", inv, t)
        g = self.src_grid
        rev = _score_poses(
            np.ascontiguousarray(inv),
            np.ascontiguousarray(inv_off),
            scale.astype(np.float64),
            self.qs,
            self.q_lab,
            g.nearest_flat,
            g.lo,
            1.0 / g.cell,
            g.shape,
            self.src.points,
            self.src.lab,
            self.tau,
            self.w_colour,
            self.sigma,
        )
        both = 0.5 * (fwd + rev)  # (poses, 2): coloured, geometric
        return both.mean(axis=1) if blend else both[:, 0]


@numba.njit(parallel=True, cache=True)
def _score_poses(
    lin, off, dist_scale, pts, lab, nearest, lo, inv_cell, shape, other, other_lab, tau, w, sigma
):  # pragma: no cover
    """Per pose k, the mean over `pts` mapped by x -> lin[k] x + off[k] of _pair_scores
    (column 0) and of the truncated closeness alone (column 1); sigma: the colour similarity's σ."""
    n_pose, n_pt = lin.shape[0], pts.shape[0]
    out = np.zeros((n_pose, 2))
    inv_2s2 = 0.5 / sigma**2
    for k in numba.prange(n_pose):
        total = 0.0
        geometric = 0.0
        a00, a01, a02, o0 = lin[k, 0, 0], lin[k, 0, 1], lin[k, 0, 2], off[k, 0]
        a10, a11, a12, o1 = lin[k, 1, 0], lin[k, 1, 1], lin[k, 1, 2], off[k, 1]
        a20, a21, a22, o2 = lin[k, 2, 0], lin[k, 2, 1], lin[k, 2, 2], off[k, 2]
        ds = dist_scale[k]
        # Most points miss: their squared distance rules them out without a square root
        # (the exact test below still decides the rest).
        miss2 = (tau / ds) ** 2
        for i in range(n_pt):
            p0, p1, p2 = pts[i, 0], pts[i, 1], pts[i, 2]
            x0 = a00 * p0 + a01 * p1 + a02 * p2 + o0
            x1 = a10 * p0 + a11 * p1 + a12 * p2 + o1
            x2 = a20 * p0 + a21 * p1 + a22 * p2 + o2
            cell = grid_index(x0, x1, x2, lo, inv_cell, shape)
            if cell < 0:
                continue
            j = nearest[cell]
            d2 = (other[j, 0] - x0) ** 2 + (other[j, 1] - x1) ** 2 + (other[j, 2] - x2) ** 2
            if d2 >= miss2:
                continue
            d = np.sqrt(d2) * ds
            if d >= tau:
                continue
            c = 1.0 - d / tau
            geometric += c
            if w > 0:
                de2 = (
                    (lab[i, 0] - other_lab[j, 0]) ** 2
                    + (lab[i, 1] - other_lab[j, 1]) ** 2
                    + (lab[i, 2] - other_lab[j, 2]) ** 2
                )
                c *= 1.0 - 2.0 * w * (1.0 - np.exp(-de2 * inv_2s2))
            total += c
        out[k, 0] = total / n_pt
        out[k, 1] = geometric / n_pt
    return out


@numba.njit(parallel=True, cache=True)
def _capture(rotations, pts, scale, t, nearest, lo, inv_cell, shape, other, radii):  # pragma: no cover - compiled
    """The capture steps of every pose (in place), one per radius in turn: pairs within the
    radius of their nearest anchor give Horn's symmetric scale and the translation, rotation
    held. `pts` are the source samples about the source centre, rotated once per pose here: a
    (poses × points × 3) array of them was the job's largest allocation (25 MB for 4,096
    rotations). Poses are independent, so each runs all its steps before the next."""
    n_pose, n_pt = rotations.shape[0], pts.shape[0]
    for k in numba.prange(n_pose):
        u = np.empty((n_pt, 3))
        for i in range(n_pt):
            for a in range(3):
                u[i, a] = (
                    rotations[k, a, 0] * pts[i, 0] + rotations[k, a, 1] * pts[i, 1] + rotations[k, a, 2] * pts[i, 2]
                )
        for reach in radii:
            _capture_step(u, k, scale, t, nearest, lo, inv_cell, shape, other, reach)


@numba.njit(cache=True)
def _capture_step(u, k, scale, t, nearest, lo, inv_cell, shape, other, reach):  # pragma: no cover - compiled
    """One capture step of pose k: its rotated samples `u` (points × 3) within `reach` of
    their nearest anchor give Horn's symmetric scale and the translation."""
    n_pt = u.shape[0]
    reach2 = reach * reach
    cnt = 0
    su0 = su1 = su2 = sy0 = sy1 = sy2 = 0.0
    suu = 0.0
    syy = 0.0
    for i in range(n_pt):
        u0, u1, u2 = u[i, 0], u[i, 1], u[i, 2]
        x0 = scale[k] * u0 + t[k, 0]
        x1 = scale[k] * u1 + t[k, 1]
        x2 = scale[k] * u2 + t[k, 2]
        cell = grid_index(x0, x1, x2, lo, inv_cell, shape)
        if cell < 0:
            continue
        j = nearest[cell]
        y0, y1, y2 = other[j, 0], other[j, 1], other[j, 2]
        if (y0 - x0) ** 2 + (y1 - x1) ** 2 + (y2 - x2) ** 2 >= reach2:
            continue
        cnt += 1
        su0 += u0
        su1 += u1
        su2 += u2
        sy0 += y0
        sy1 += y1
        sy2 += y2
        suu += u0**2 + u1**2 + u2**2
        syy += y0**2 + y1**2 + y2**2
    if cnt < 8:
        return
    var_u = suu / cnt - (su0**2 + su1**2 + su2**2) / cnt**2
    var_y = syy / cnt - (sy0**2 + sy1**2 + sy2**2) / cnt**2
    if var_u <= 0 or var_y <= 0:
        return
    # At most a factor 1.5 per step: few captured pairs give a noisy ratio.
    s_new = min(max(np.sqrt(var_y / var_u), scale[k] / 1.5), scale[k] * 1.5)
    scale[k] = s_new
    t[k, 0] = sy0 / cnt - s_new * su0 / cnt
    t[k, 1] = sy1 / cnt - s_new * su1 / cnt
    t[k, 2] = sy2 / cnt - s_new * su2 / cnt
