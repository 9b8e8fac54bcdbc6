"""The frame snap (docs/how-it-works.md, "Frame snap"): a doubtful answer between other
instances, and its alternatives, turned onto the nearest relabelling of the two models'
dominant surface-normal frames (gsa.manhattan). Across instances the refinement drifts 5-37
degrees off the frame both objects are built along, where one of the 24 relabellings is within
5 degrees of the truth on every category-real pair (docs/benchmarks.md, "Dominant-normal
frames"). `pair` is the pipeline's _Pair (gsa.align.pair): its models, anchors and quality metrics.
"""

from __future__ import annotations

import numpy as np

from gsa import manhattan
from gsa.align import guided, robust
from gsa.geometry import rotation_distance_deg
from gsa.sim3 import Sim3

# The dominant-normal frames are a frame only where they hold much of both surfaces: boxy things
# (tables, pianos, desktops, rifles, bathtubs, benches, guitars: median 0.59-0.86 of the area
# within manhattan.SUPPORT_DEG of an axis) and not curved ones (spiders, dogs, horses, dolphins,
# people, trees, hands: 0.03-0.12; mugs, chairs, airplanes 0.23-0.25), measured on the 248
# training meshes (training/manifest.json). Below it the 24 relabellings are arbitrary turns: on
# deformed copies of real meshes nobody tuned on, turning answers onto them took mugs, dolphins,
# trees and horses 22-180 deg off (docs/benchmarks.md, "Frames that hold the surface").
FRAME_SUPPORT_MIN = 0.3
# A doubtful pose this near a relabelling of the dominant-normal frames is turned onto it:
# across instances the refinement drifts 5-20 degrees off the frame both are built along
# (docs/benchmarks.md, "Dominant-normal frames"), while a pose farther off meant another one.
FRAME_SNAP_DEG = 20.0
# Alternatives that land this near the chosen pose or an earlier alternative once snapped are that pose.
FRAME_SNAP_SAME_DEG = 2.0
# Scores over the relabellings count in standard deviations, but never of less than
# CHOICE_SPREAD_FLOOR (between two boxes every relabelling scores alike, to sampling noise), and
# another relabelling replaces the answer's only when its summed score leads by CHOICE_MARGIN.
CHOICE_SPREAD_FLOOR = 0.02
CHOICE_MARGIN = 0.5
# The relabelling a given pose points at lies at most this far from it: a rough start (the guided
# path's "20 deg off", the snap's reach) plus the frames' own error (within 5 deg of the truth on
# every category-real pair). A pose farther from every relabelling is the user's own answer.
GUIDED_REACH_DEG = FRAME_SNAP_DEG + 5.0
# A guided answer whose surfaces coincide on fewer of the overlap's pairs than this is not two
# converged captures of one object: those share 0.77-1.0 (generated protocols,
# robust.RefineCriteria) and 0.82-0.87 (real captures split in two, docs/benchmarks.md). Other
# instances share anything from 0.05 to near copies' 0.99; the refinement's own 0.5 (the
# ceiling of deformed copies) left similar instances at 0.52-0.58 (bathtubs, rifles, pianos)
# refined 4-5 deg off the frames that hold the truth.
SAME_SURFACE_SHARE = 0.7
# Two whole instances whose parts differ in length (a rifle's stock, a table's legs) read an
# overlap estimate of 0.70-0.85 even at the true pose, under the whole-model 0.875 of two
# captures of one object; where their surfaces are apart (SAME_SURFACE_SHARE), this much is
# whole enough for the relabelling choice (docs/benchmarks.md, "Instances that read partial").
# Two captures of one object cut apart coincide where they overlap, so they stay out.
INSTANCES_OVERLAP = 0.7
# A relabelling keeps a user's up axes when it maps the source's within this of the target's
# (the frames' own error is a degree or two; a relabelling that tilts up is another answer).
UP_KEPT_DEG = 10.0
# An answer farther than this from every relabelling is not on the frames: it is kept (the
# relabellings are only offered as alternatives). Wider than the snap's reach: across instances
# the refinement drifts up to ~30 deg off the frames (rifles rolled about their length), and
# the choice weighs all 24 relabellings anyway; at 45 deg a turn-symmetric vase, whose frame
# is any turn about its axis, was switched off a right answer (docs/benchmarks.md). Where
# neither model spins freely and the surfaces are other instances', no reach applies: a right
# answer then lies within a few degrees of a relabelling, and one farther off is turned onto the
# frames (choose_relabelling's frames_hold; docs/benchmarks.md, "Answers off the frames").
CHOICE_MAX_DEG = 30.0
# The shapes alone settle the choice (shape_settled: the semantic tie-break is not needed) where
# the best relabelling's surface-mass score leads every relabelling that is another answer by
# SHAPE_DECISIVE_SIGMA standard deviations, and fewer than SHAPE_SETTLES_BELOW relabellings are
# that same answer up to the models' own symmetries. On the category-real pairs a lead of 0.75
# was right on 30 / 30 such pairs (0.5: 38 / 39). Where 4 or more are alike (a vase, a bottle, a
# square table: turn-symmetric) the question left is which way up, the one thing instances'
# mass profiles differ on (a vase wide at its mouth or at its foot): the shapes were wrong there
# at leads of 1.4-2.5 on 8 pairs (docs/benchmarks.md, "Shapes that settle the choice").
SHAPE_DECISIVE_SIGMA = 1.0
SHAPE_SETTLES_BELOW = 4


def frames_supported(pair) -> bool:
    """Whether both models' dominant-normal frames hold FRAME_SUPPORT_MIN of their surface, or a
    model spins freely (a bottle, a vase: its frame's axis is the spin axis, whatever its normals
    hold, and the relabellings about it are its own turns; up against down is what is left)."""
    return pair.spins_freely or min(frame.support for frame in pair.normal_frames) >= FRAME_SUPPORT_MIN


def unsupported(metrics: dict, pair) -> dict:
    """metrics with the report (`frames`) that the frames were too weak to turn anything onto."""
    support = [round(float(frame.support), 3) for frame in pair.normal_frames]
    reason = f"the dominant-normal frames hold {support[0]:.0%} / {support[1]:.0%} of the surfaces: not a frame"
    return metrics | {"frames": {"used": False, "support": support, "reason": reason}}


def guided_snap(pair, best, transform: Sim3, metrics: dict, start: dict, symmetries) -> tuple[Sim3, dict]:
    """A doubtful answer refined from a user's pose or picked pairs, between surfaces that do
    not coincide (other instances, or parts of them): turned onto the relabelling of the frames
    nearest it (as a search answer is) where that one is still the answer the user pointed at
    (guided.near_start); else onto the relabelling the guidance points at (guided_relabelling):
    across instances the refinement can drift 20-80 deg away from the frame the user started
    on, where the relabelling nearest a start 20 deg off was within 3.2 deg of the truth on
    every category-real pair (docs/benchmarks.md, "The guided snap"). A user's up axes are
    kept as given: no turn then."""
    opts = pair.opts
    if opts.frame_snap == "off" or opts.up_axes is not None or not surfaces_apart(metrics):
        return transform, metrics
    if not frames_supported(pair):
        return transform, unsupported(metrics, pair)
    # the leash reads the rotation alone: the nearest relabelling is judged before any refit
    nearest, gap = manhattan.snapped(transform, *pair.normal_frames, pair.anchors()[0].center)
    guidance = pair.criteria.guidance
    if 1e-6 < gap <= FRAME_SNAP_DEG and guided.near_start(
        nearest, best.init, opts, dict(start), criteria=guidance, symmetries=symmetries
    ):
        return snap_to_frames(pair, best, transform, metrics)
    rotation = guided_relabelling(pair, best.init, start, symmetries)
    if rotation is None:
        return transform, metrics
    return snap_to_frames(pair, best, transform, metrics, onto=rotation)


def up_snap(pair, best, transform: Sim3, metrics: dict) -> tuple[Sim3, dict]:
    """A doubtful answer searched about a user's up axes, between surfaces that do not coincide:
    the relabellings of the frames that keep the up axes (within UP_KEPT_DEG) are quarter turns
    about them, and every answer lies within 45 deg of one: turned onto the nearest, then
    checked against the others by shape (choose_relabelling restricted to them). Between
    instances the turn about the up axis drifts (pianos, tables 7-40 deg) or piles the heavy
    ends together (a bathtub end for end). Every pose is brought back onto the given up axes."""
    opts = pair.opts
    if opts.frame_snap == "off" or opts.up_axes is None or not surfaces_apart(metrics):
        return transform, metrics
    if not frames_supported(pair):
        return transform, unsupported(metrics, pair)
    src_up, dst_up = (np.asarray(v, np.float64) / np.linalg.norm(v) for v in opts.up_axes)
    rotations = manhattan.relabellings(*pair.normal_frames)
    keeps = np.array([(r @ src_up) @ dst_up >= np.cos(np.radians(UP_KEPT_DEG)) for r in rotations])
    if opts.front_axes is not None:
        keeps &= np.array([guided.keeps_front(r, opts.front_axes, pair.criteria.guidance) for r in rotations])
    if not keeps.any():  # no relabelling keeps the given up axes (a wrong hint): nothing for the frames to say
        return transform, metrics
    candidates = np.flatnonzero(keeps)
    nearest = min(candidates, key=lambda k: rotation_distance_deg(rotations[k], transform.rotation))
    turned, updated = snap_to_frames(
        pair,
        best,
        transform,
        metrics,
        onto=rotations[nearest],
        hold=pair.constrain,
        why="the nearest relabelling that keeps the up axes",
    )
    return choose_relabelling(pair, best, turned, updated, allowed=keeps, hold=pair.constrain)


def replaced(pair, best, transform: Sim3, chosen: Sim3, metrics: dict, origin: str) -> dict:
    """metrics for `chosen` taking the answer's place: its quality, the answer replaced as the
    first alternative (`origin` names the step), then the alternatives that are not `chosen`."""
    alternatives = [replaced_pose(transform, metrics, origin)]
    alternatives += [
        alt
        for alt in metrics.get("alternatives") or []
        if robust.rotation_offset_deg(Sim3.from_matrix(np.asarray(alt["transform"], np.float64)), chosen)
        > FRAME_SNAP_SAME_DEG
    ]
    return metrics | pair.judge.quality(chosen, best) | {"alternatives": alternatives}


def guided_relabelling(pair, start_pose: Sim3, start: dict, symmetries) -> np.ndarray | None:
    """The relabelling of the two models' frames the guidance points at: of those on its leash
    (guided.near_start), the one nearest a given pose (up to the source's turn symmetry) where
    it is within GUIDED_REACH_DEG, or the one that misses the picked pairs least; None where
    none is."""
    opts = pair.opts
    on_leash = [
        rotation
        for rotation in manhattan.relabellings(*pair.normal_frames)
        if guided.near_start(
            Sim3(1.0, rotation, np.zeros(3)),
            start_pose,
            opts,
            dict(start),
            criteria=pair.criteria.guidance,
            symmetries=symmetries,
        )
    ]
    if not on_leash:
        return None
    if start.get("from") == "point_pairs":
        return min(on_leash, key=lambda rotation: guided.click_miss(rotation, opts, start))
    nearest = min(on_leash, key=lambda rotation: guided.start_distance_deg(rotation, start_pose, symmetries))
    return nearest if guided.start_distance_deg(nearest, start_pose, symmetries) <= GUIDED_REACH_DEG else None


def surfaces_apart(metrics: dict) -> bool:
    """Whether the answer's surfaces do not coincide as two captures of one object do (fewer
    than SAME_SURFACE_SHARE of the overlap's pairs within the sampling): another instance,
    whole or in part. Two captures of one object that a user's pose or clicks brought
    together coincide; their fit stands."""
    share = metrics.get("coincident_share")
    return share is not None and share < SAME_SURFACE_SHARE


def other_instances(metrics: dict, criteria: robust.RefineCriteria | None = None) -> bool:
    """Whether the answer's models differ everywhere (robust.refinement's test: the overlap
    estimate keeps nearly every pair yet fewer than half coincide at the sampling): another
    instance or a deformed copy, where the refinement's fit is not exact. Two captures of one
    object coincide where they overlap: their fit stands. criteria: the refinement's in force
    (AlignOptions.criteria.refine; None: the defaults)."""
    fraction, share = metrics.get("overlap_estimate"), metrics.get("coincident_share")
    k = criteria or robust.RefineCriteria()
    return fraction is not None and share is not None and fraction >= k.whole_overlap and share < k.coincident_share


def whole_models(metrics: dict, criteria: robust.RefineCriteria | None = None) -> bool:
    """Whether the answer's models overlap wholly (robust.refinement's overlap estimate keeps
    nearly every pair, or INSTANCES_OVERLAP of them where the surfaces are apart): two
    instances, or two full captures, not a part of one in the other (whose mass and spread
    differ by what is missing). criteria: the refinement's in force (None: the defaults)."""
    fraction = metrics.get("overlap_estimate")
    if fraction is None:
        return False
    return fraction >= (criteria or robust.RefineCriteria()).whole_overlap or (
        surfaces_apart(metrics) and fraction >= INSTANCES_OVERLAP
    )


def snap_to_frames(
    pair,
    best,
    transform: Sim3,
    metrics: dict,
    onto: np.ndarray | None = None,
    hold=None,
    why: str = "the relabelling the guidance points at",
) -> tuple[Sim3, dict]:
    """A doubtful answer and its alternatives turned onto the nearest relabelling of the two
    models' dominant-normal frames (gsa.manhattan; up to the source's spins, where it turns
    freely about an axis: the spin is kept, the tilt taken out) where that turn is at most FRAME_SNAP_DEG
    (the answer onto the relabelling `onto` where given, however far; every turned pose passed
    through `hold`, which brings it back onto the user's hints); the pose as refined becomes
    the first alternative. The answer stays doubtful: which of the relabellings is
    right is the question the snap does not answer."""
    frames = pair.normal_frames
    src, dst = pair.anchors()
    reach = pair.criteria.pose.truncation * dst.radius
    report = {"support": [frames[0].support, frames[1].support], "max_deg": FRAME_SNAP_DEG}
    hold = hold or (lambda pose: pose)

    # up to the source's spins (a vase, a bottle): a spin about its axis is the same answer
    turns = pair.source_symmetries

    def snap(pose: Sim3) -> tuple[Sim3, float]:
        turned, gap = manhattan.snapped(pose, *frames, src.center, turns)
        return hold(turned), gap

    kept: list[Sim3] = []
    alternatives = []
    if onto is None:
        chosen, gap = snap(transform)
    else:
        chosen = hold(manhattan.turned_onto(transform, onto, src.center))
        gap = robust.rotation_offset_deg(transform, chosen)
        report["onto"] = why
    snapping = 1e-6 < gap <= (FRAME_SNAP_DEG if onto is None else 180.0)
    if snapping:
        chosen = manhattan.fit_shift(chosen, src.points, dst.points, reach)
        kept.append(chosen)
        alternatives.append(replaced_pose(transform, metrics, "before the frame snap"))
    else:
        kept.append(transform)
    for alt in metrics.get("alternatives") or []:
        pose = Sim3.from_matrix(np.asarray(alt["transform"], np.float64))
        turned, alt_gap = snap(pose)
        if 1e-6 < alt_gap <= FRAME_SNAP_DEG:
            pose = manhattan.fit_shift(turned, src.points, dst.points, reach)
            alt = alt | {"transform": pose.matrix().tolist(), "snapped_deg": alt_gap}
        if all(robust.rotation_offset_deg(pose, k) > FRAME_SNAP_SAME_DEG for k in kept):
            kept.append(pose)
            alternatives.append(alt | {"rotation_offset_deg": robust.rotation_offset_deg(pose, kept[0])})
    if not snapping:
        return transform, metrics | {"frame_snap": report | {"used": False, "deg": gap}, "alternatives": alternatives}
    updated = metrics | pair.judge.quality(chosen, best) | {"alternatives": alternatives}
    return chosen, updated | {"frame_snap": report | {"used": True, "deg": gap}}


def choose_relabelling(
    pair, best, transform: Sim3, metrics: dict, allowed: np.ndarray | None = None, hold=None
) -> tuple[Sim3, dict]:
    """A doubtful answer between whole models that lies within CHOICE_MAX_DEG of a relabelling
    of their frames (snapped onto it where they are other instances; at any distance where
    neither spins freely about an axis, turned onto the nearest): the relabelling the
    models' shapes and, once lifted, their semantic features agree on most. Each of the 24 is
    scored by the surface-mass grids (manhattan.relabelling_agreement) and, where the semantic
    tie-break lifted features (pair.lifted), by their agreement between the posed models and by
    their grids in the frames (manhattan.feature_agreement: part to part across proportions);
    each score is standardised over the 24 and the sums compared (a lead of CHOICE_MARGIN to
    switch).
    Across instances the geometric fit piles surface together (a bathtub end for end, a bottle
    upside down), where part-to-part mass and what a pretrained network sees tell the ends
    apart (docs/benchmarks.md, "Choosing among the relabellings"). The answer stays doubtful; the pose replaced becomes the first
    alternative, and every other relabelling joins after the existing ones, best-scored first (also
    where the answer lies off the frames and is kept). `allowed`: a (24,) mask of the
    relabellings that may be chosen or offered (those that keep a user's up axes); `hold`
    brings every relabelled pose back onto the user's hints."""
    frames = pair.normal_frames
    src, dst = pair.anchors()
    reach = pair.criteria.pose.truncation * dst.radius
    hold = hold or (lambda pose: pose)
    poses = [
        manhattan.fit_shift(
            hold(manhattan.turned_onto(transform, rotation, src.center)),
            src.points,
            dst.points,
            reach,
        )
        for rotation in manhattan.relabellings(*frames)
    ]
    allowed = np.ones(len(poses), bool) if allowed is None else np.asarray(allowed, bool)
    shape = pair.shape_agreement
    total = _standardised(shape)
    semantic = parts = None
    if pair.lifted is not None:
        lifted = pair.lifted
        semantic = np.asarray(lifted.scores(poses))
        parts = manhattan.feature_agreement(
            pair.source, pair.target, *frames, (lifted.src_pts, lifted.src_f), (lifted.dst_pts, lifted.dst_f)
        )
        total = total + _standardised(semantic) + _standardised(parts)
    offsets = np.array([robust.rotation_offset_deg(transform, p) for p in poses])
    current = int(np.argmin(np.where(allowed, offsets, np.inf)))
    order = [int(k) for k in np.argsort(-total, kind="stable") if allowed[k]]
    # Beyond the snap's reach the answer is off the frames. Where neither model spins freely
    # about an axis and the surfaces are other instances', the frames hold the truth wherever the
    # answer lies: it is turned onto the relabelling nearest it unless another scores better.
    # Elsewhere an answer farther than CHOICE_MAX_DEG is kept (the relabellings still offered).
    off_frames = bool(offsets[current] > FRAME_SNAP_DEG)
    frames_hold = off_frames and surfaces_apart(metrics) and not pair.spins_freely
    on_frames = frames_hold or bool(offsets[current] <= CHOICE_MAX_DEG)
    pick = order[0] if on_frames and total[order[0]] > total[current] + CHOICE_MARGIN else current
    turned = pick != current or frames_hold
    geometry = geometry_prefers(pair, transform, poses[pick], metrics) if turned else None
    if geometry is not None and geometry["answer_wins"]:
        turned, pick = False, current
    report = {
        "used": on_frames,
        "frames_hold": frames_hold,
        "deg": float(offsets[current]),
        "shape": shape.round(4).tolist(),
        "semantic": None if semantic is None else semantic.round(4).tolist(),
        "parts": None if parts is None else parts.round(4).tolist(),
        "on": current,  # the nearest relabelling to the answer
        "picked": pick,
        "switched": turned,
        "geometry": geometry,
    }
    chosen = poses[pick] if turned else transform
    offered = [chosen]
    alternatives = []
    if turned:
        alternatives.append(replaced_pose(transform, metrics, "before the relabelling choice"))
        offered.append(transform)
    for alt in metrics.get("alternatives") or []:
        pose = Sim3.from_matrix(np.asarray(alt["transform"], np.float64))
        if all(robust.rotation_offset_deg(pose, p) > FRAME_SNAP_SAME_DEG for p in offered):
            offered.append(pose)
            alternatives.append(alt)
    # Every other relabelling is offered, best-scored first: where the shapes mislead the scores
    # (a grand piano and an upright, two desktops) the truth ranked 13th-17th of 24, and a person
    # stepping through the alternatives (or narrowing them with the up axes) finds it there.
    for k in order:
        if all(robust.rotation_offset_deg(poses[k], p) > FRAME_SNAP_SAME_DEG for p in offered):
            offered.append(poses[k])
            alternatives.append(
                {
                    "origin": "frame relabelling",
                    "tied": False,
                    "shape_agreement": float(shape[k]),
                    "semantic_score": None if semantic is None else float(semantic[k]),
                    "rotation_offset_deg": robust.rotation_offset_deg(poses[k], chosen),
                    "transform": poses[k].matrix().tolist(),
                }
            )
    updated = metrics | (pair.judge.quality(chosen, best) if turned else {}) | {"alternatives": alternatives}
    if semantic is not None and turned:
        updated["semantic_score"] = float(semantic[pick])
    return chosen, updated | {"frame_choice": report}


def geometry_prefers(pair, answer: Sim3, turned: Sim3, metrics: dict) -> dict:
    """Whether the models' own geometry keeps the answer against a turn onto the frames: the
    turned pose taken on by the anchors' ICP (as the search takes its starts) and both scored
    as the search ranks its poses; the answer wins where it leads by more than a tie
    (PoseCriteria.score_tie). The frames' rules break ties the geometry leaves between other
    instances; where the answer fits clearly better (two captures of one object, a deformed
    copy whose frames moved with the bend) no rule made for other instances may turn it off."""
    src, dst = pair.anchors()
    weight = float(metrics.get("colour_weight") or 0.0)
    k = pair.criteria.pose
    kept = robust.score_pose(src, dst, answer, "answer", weight, k)
    rival = robust.score_pose(src, dst, pair.constrain(pair.anchor_search.approach(turned)), "turned", weight, k)
    measure = (lambda c: c.geometry) if metrics.get("ranked_by") == "geometry" else (lambda c: c.score)
    lead = measure(kept) - measure(rival)
    return {
        "answer": round(measure(kept), 4),
        "turned": round(measure(rival), 4),
        "answer_wins": bool(lead > k.score_tie),
    }


def replaced_pose(transform: Sim3, metrics: dict, origin: str) -> dict:
    """The alternative a doubtful answer becomes when a later step replaces it (`origin` names
    the step), with the scores it was given."""
    return {
        "origin": origin,
        "tied": False,
        "score": metrics.get("score"),
        "geometry": metrics.get("overlap_score"),
        "semantic_score": metrics.get("semantic_score"),
        "transform": transform.matrix().tolist(),
    }


def shape_settled(pair) -> tuple[int, dict] | None:
    """The relabelling of the two models' frames their surface-mass grids settle on their own
    (SHAPE_DECISIVE_SIGMA, SHAPE_SETTLES_BELOW), with the report of why (its lead over every
    other answer, the relabellings alike); None where the shapes leave it open."""
    shape = _standardised(pair.shape_agreement)
    top = int(np.argmax(shape))
    # With fewer than SHAPE_SETTLES_BELOW alike, the one that many places down is another answer:
    # where even it is within reach, the models' symmetries (about a second a pair) need not be measured.
    if shape[top] - np.sort(shape)[-SHAPE_SETTLES_BELOW] < SHAPE_DECISIVE_SIGMA:
        return None
    source_self, target_self = (
        manhattan.self_relabellings(model, frame)
        for model, frame in zip((pair.source, pair.target), pair.normal_frames)
    )
    alike = manhattan.equivalent_relabellings(top, source_self, target_self)
    if alike.sum() >= SHAPE_SETTLES_BELOW:
        return None
    lead = float(shape[top] - shape[~alike].max())
    if lead < SHAPE_DECISIVE_SIGMA:
        return None
    return top, {"lead_sigma": round(lead, 3), "alike": int(alike.sum())}


def _standardised(scores: np.ndarray) -> np.ndarray:
    """Scores over the relabellings as standard deviations from their mean (two scores of
    different spread weigh alike), the deviation floored at CHOICE_SPREAD_FLOOR."""
    return (scores - scores.mean()) / max(float(np.std(scores)), CHOICE_SPREAD_FLOOR)
