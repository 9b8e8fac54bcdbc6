"""Guided alignment: what a person knows, used where the automatic answer is doubtful.

Hints (AlignOptions fields; each optional):
- init_transform: a 4×4 Sim(3) to start from; only the local refinement runs from it.
- point_pairs: ≥ 3 picked pairs, one point in each model's own coordinates: the closed-form
  Sim(3) of the pairs (with ≥ 4 pairs, the one pair that disagrees with the rest is left
  out), then the same local refinement.
- up_axes: the up vector of each model: the search only turns about it, and every later pose
  is brought back onto it (a cross-instance refinement can tilt).
- front_axes (with up_axes): the way each model faces: the turns about up are those that keep
  the fronts within front_reach_deg (up alone cannot tell a nose from a tail), and of the turns
  the geometry ties (a mug's body fits any), the one nearest the fronts wins.
- fixed_scale: the answer's scale, kept through every stage.

Functions taking `opts` take a gsa.align.AlignOptions (not imported here: it imports this module);
the tunables of the pairs' fit, the up-axis search and the refinement's leash are the fields of
`GuidanceCriteria`, taken by the functions that use them (None: the defaults).
`check_guidance` validates and normalises the hints once (AlignOptions.__post_init__), so the
CLI, both APIs and the library refuse the same things with the same words.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gsa.geometry import axis_rotation, rotation_distance_deg
from gsa.sim3 import Sim3, solve_sim3

# The origin of the alternative that is the pose a person gave (or their picked pairs' fit).
GIVEN_START = "the given start"
# Picked pairs accepted at most: a bound on the input (the CLI, both APIs), not a tunable.
MAX_PAIRS = 1000
# A turn is a symmetry of the source when the turned surface lies within this many sample
# spacings of the unturned one (mean distance to the nearest point). Measured on real meshes:
# bottles and vases turned about their axis 1.0-1.6 spacings, a rifle rolled half a turn 4-12,
# tables and bathtubs 4+; a share of the size would call every thin object symmetric.
SYMMETRY_SPACINGS = 2.0


@dataclass(frozen=True)
class GuidanceCriteria:
    """The tunables of guided alignment; the defaults are the values benchmarked in
    docs/benchmarks.md (category-real, guided rows)."""

    up_step_deg: float = 2.0  # turns about the up axis tried by the constrained search (degrees apart)
    # A pair the others' fit misses by outlier_ratio times their median residual, and by
    # misclick_share of the pairs' spread, is a misclick (pairs_transform) ...
    outlier_ratio: float = 4.0
    misclick_share: float = 0.25
    misfit_share: float = 0.05  # ... looked for only where the fit of all pairs misses them by this share (RMS)
    well_spread: float = 0.25  # pairs left after a misclick spread this far off a line (2nd/1st singular value)
    # The local refinement from a user's pose stays the user's: within start_leash_deg of a given
    # pose; with picked pairs, missing no kept click by more than the pairs' fit misses its worst
    # one plus pairs_leash_share of the clicks' spread (between two instances the clicks fit no
    # similarity exactly, and the fit of three is often 5-30 deg off; a turn to another side of
    # the object misses them by about their spread).
    start_leash_deg: float = 30.0
    pairs_leash_share: float = 0.5
    # ... and never more than pairs_max_turn_deg from the pairs' fit: clicks nearly on a line
    # do not pin the turn about it (a rifle rolled half a turn still meets clicks along its length).
    pairs_max_turn_deg: float = 90.0
    # The local search also starts from the given pose turned by this about each axis, both ways
    # (the anchors' ICP from one start can stop in a nearer, worse minimum).
    local_turn_deg: float = 15.0
    # Given fronts keep the turn about up within this of agreeing, through the search and every
    # later pose: a front says which side faces which way (the page offers the six axis
    # directions, up to 45 deg off an object's true front), so a nose is never turned to a tail
    # nor to a side; within it the geometry decides, and where it ties, the nearest to the fronts. Measured at 15 deg: one held-out mug pair
    # more within 5 deg (docs/benchmarks.md, "Up and front"), and an axis-picked front held 25 deg off.
    front_reach_deg: float = 45.0
    # A front within this of its model's up says nothing about the turn about up.
    front_tilt_min_deg: float = 20.0


_DEFAULT = GuidanceCriteria()


def is_guided(opts) -> bool:
    return any(
        x is not None for x in (opts.init_transform, opts.point_pairs, opts.up_axes, opts.front_axes, opts.fixed_scale)
    )


def _finite(values, name: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        arr = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must hold numbers") from None
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name} must have shape {'×'.join(map(str, shape))}, got {'×'.join(map(str, arr.shape))}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} holds NaN or Inf")
    return arr


def check_guidance(opts) -> None:
    """Validate the hints and store them normalised (tuples of floats, up vectors unit length),
    by the guidance criteria of opts.criteria where it holds them (else the defaults)."""
    if opts.init_transform is not None and opts.point_pairs is not None:
        raise ValueError("give init_transform or point_pairs, not both")
    if opts.init_transform is not None:
        opts.init_transform = _tuple(init_sim3(opts.init_transform).matrix())
    if opts.point_pairs is not None:
        src, dst = pair_arrays(opts.point_pairs)
        opts.point_pairs = (_tuple(src), _tuple(dst))
    if opts.up_axes is not None:
        try:
            src_up, dst_up = opts.up_axes
        except (TypeError, ValueError):
            raise ValueError("up_axes must be two vectors: the source's up and the target's up") from None
        ups = []
        for name, v in (("source up axis", src_up), ("target up axis", dst_up)):
            v = _finite(v, name, (3,))
            if not np.linalg.norm(v) > 1e-12:
                raise ValueError(f"{name} must not be zero")
            ups.append(v / np.linalg.norm(v))
        opts.up_axes = (_tuple(ups[0]), _tuple(ups[1]))
    if opts.front_axes is not None:
        criteria = getattr(opts, "criteria", None)
        opts.front_axes = _checked_fronts(opts.front_axes, opts.up_axes, criteria.guidance if criteria else None)
    if opts.fixed_scale is not None:
        scale = float(_finite(opts.fixed_scale, "fixed_scale", ()))
        if not 1e-6 <= scale <= 1e6:
            raise ValueError("fixed_scale must be in 1e-6..1e6")
        opts.fixed_scale = scale


def _checked_fronts(front_axes, up_axes, criteria: GuidanceCriteria | None = None) -> tuple:
    """The fronts across their models' up axes, unit length; up_axes must be given, and each
    front must lean at least front_tilt_min_deg off its up."""
    if up_axes is None:
        raise ValueError("front_axes needs up_axes: the front says which way to turn about up")
    try:
        src_front, dst_front = front_axes
    except (TypeError, ValueError):
        raise ValueError("front_axes must be two vectors: the source's front and the target's front") from None
    tilt_min = (criteria or _DEFAULT).front_tilt_min_deg
    fronts = []
    for name, v, up in (("source front axis", src_front, up_axes[0]), ("target front axis", dst_front, up_axes[1])):
        v = _finite(v, name, (3,))
        up = np.asarray(up, np.float64)
        across = v - (v @ up) * up
        norm = float(np.linalg.norm(v))
        if not norm > 1e-12 or np.linalg.norm(across) < np.sin(np.radians(tilt_min)) * norm:
            raise ValueError(f"{name} must not be zero or within {tilt_min:g} deg of that model's up axis")
        fronts.append(across / np.linalg.norm(across))
    return (_tuple(fronts[0]), _tuple(fronts[1]))


def _tuple(a: np.ndarray):
    return tuple(_tuple(x) for x in a) if np.ndim(a) > 1 else tuple(float(x) for x in a)


def init_sim3(matrix) -> Sim3:
    """A 4×4 similarity (rotation × positive scale, translation, last row 0 0 0 1) as Sim3."""
    m = _finite(matrix, "init_transform", (4, 4))
    if not np.allclose(m[3], (0, 0, 0, 1), atol=1e-6):
        raise ValueError("init_transform's last row must be 0 0 0 1")
    try:
        return Sim3.from_matrix(m)
    except ValueError as exc:
        raise ValueError(f"init_transform: {exc}") from None


def pair_arrays(point_pairs) -> tuple[np.ndarray, np.ndarray]:
    """(source points, target points) as (n, 3) arrays; n ≥ 3, not all on one line."""
    try:
        src, dst = (point_pairs["source"], point_pairs["target"]) if isinstance(point_pairs, dict) else point_pairs
    except (TypeError, ValueError, KeyError):
        raise ValueError("point_pairs must be {source: [[x, y, z], …], target: [[x, y, z], …]}") from None
    src, dst = _finite(src, "point_pairs.source"), _finite(dst, "point_pairs.target")
    for name, pts in (("source", src), ("target", dst)):
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"point_pairs.{name} must be a list of [x, y, z] points")
    if len(src) != len(dst):
        raise ValueError(f"point_pairs has {len(src)} source and {len(dst)} target points: they must pair up")
    if not 3 <= len(src) <= MAX_PAIRS:
        raise ValueError(f"point_pairs needs 3..{MAX_PAIRS} pairs, got {len(src)}")
    for name, pts in (("source", src), ("target", dst)):
        sv = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
        if not sv[1] > 1e-6 * max(sv[0], 1e-300):
            raise ValueError(f"point_pairs.{name} points lie on one line: they fix no rotation")
    return src, dst


def pairs_transform(
    src: np.ndarray, dst: np.ndarray, fixed_scale: float | None = None, criteria: GuidanceCriteria | None = None
) -> tuple[Sim3, dict]:
    """Closed-form Sim(3) of picked pairs. With ≥ 4 pairs, the fit without each pair in turn
    is tried; where one pair's residual under the fit of the others stands out, it is left out
    (a misclick), and the report names it."""
    k = criteria or _DEFAULT
    fit = _fit(src, dst, fixed_scale)
    report: dict = {"pairs": len(src), "left_out": None}
    full_rms = float(np.sqrt(np.mean(np.sum((fit.apply(src) - dst) ** 2, axis=1))))
    spread = float(np.sqrt(np.mean(np.sum((dst - dst.mean(0)) ** 2, axis=1))))
    # Only a fit that misses its own pairs visibly has a misclick to look for.
    if len(src) >= 4 and full_rms > k.misfit_share * spread:
        # A pair is a misclick when the fit of the others misses it by far more than it misses
        # them, and by a visible share of the pairs' spread: three pairs fit each other almost
        # exactly, so a noisy click's leave-one-out residual alone looks large (not a misclick).
        best = None
        for i in range(len(src)):
            keep = np.arange(len(src)) != i
            sv = np.linalg.svd(src[keep] - src[keep].mean(0), compute_uv=False)
            if sv[1] < k.well_spread * sv[0]:
                continue  # the others nearly on a line: their fit says nothing about pair i
            sub = _fit(src[keep], dst[keep], fixed_scale)
            miss = float(np.linalg.norm(sub.apply(src[i]) - dst[i]))
            typical = float(np.median(np.linalg.norm(sub.apply(src[keep]) - dst[keep], axis=1)))
            if (
                miss > k.outlier_ratio * typical
                and miss > k.misclick_share * spread
                and (best is None or miss > best[1])
            ):
                best = (i, miss, sub)
        if best is not None:
            fit = best[2]
            report["left_out"] = int(best[0])
    residuals = np.linalg.norm(fit.apply(src) - dst, axis=1)
    report["residuals"] = [float(r) for r in residuals]
    return fit, report


def _fit(src: np.ndarray, dst: np.ndarray, fixed_scale: float | None) -> Sim3:
    fit = solve_sim3(src, dst)
    if fixed_scale is None:
        return fit
    return Sim3(fixed_scale, fit.rotation, dst.mean(0) - fixed_scale * fit.rotation @ src.mean(0))


def up_rotations(src_up, dst_up, criteria: GuidanceCriteria | None = None, fronts=None) -> list[tuple[str, np.ndarray]]:
    """Every rotation taking the source's up onto the target's, turned about it in steps of
    up_step_deg; with `fronts` (source front, target front), those that keep them within
    front_reach_deg."""
    k = criteria or _DEFAULT
    base = _min_rotation(np.asarray(src_up, np.float64), np.asarray(dst_up, np.float64))
    rotations = [
        (f"up:{deg:g}", axis_rotation(dst_up, np.radians(deg)) @ base) for deg in np.arange(0.0, 360.0, k.up_step_deg)
    ]
    if fronts is None:
        return rotations
    return [(name, r) for name, r in rotations if keeps_front(r, fronts, k)]


def _front_held(rotation: np.ndarray, dst_up: np.ndarray, fronts, criteria: GuidanceCriteria | None = None):
    """`rotation` (already keeping the up axes) turned about the target's up, as little as
    needed, to map the source's front within front_reach_deg of the target's."""
    src_front, dst_front = (np.asarray(v, np.float64) for v in fronts)
    mapped = rotation @ src_front
    # signed angle from the target's front to the mapped front, about the target's up
    angle = float(np.arctan2(np.cross(dst_front, mapped) @ dst_up, dst_front @ mapped))
    reach = np.radians((criteria or _DEFAULT).front_reach_deg)
    if abs(angle) <= reach:
        return rotation
    return axis_rotation(dst_up, np.sign(angle) * reach - angle) @ rotation


def keeps_front(rotation: np.ndarray, fronts, criteria: GuidanceCriteria | None = None) -> bool:
    """Whether `rotation` maps the source's front within front_reach_deg of the target's."""
    src_front, dst_front = (np.asarray(v, np.float64) for v in fronts)
    reach = (criteria or _DEFAULT).front_reach_deg
    return bool((rotation @ src_front) @ dst_front >= np.cos(np.radians(reach)))


def front_gap_deg(rotation: np.ndarray, fronts) -> float:
    """Degrees between the source's front as `rotation` maps it and the target's front."""
    src_front, dst_front = (np.asarray(v, np.float64) for v in fronts)
    return float(np.degrees(np.arccos(np.clip((rotation @ src_front) @ dst_front, -1.0, 1.0))))


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a onto unit vector b."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: half a turn about any axis perpendicular to a
        perp = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
        return axis_rotation(perp, np.pi)
    return axis_rotation(axis / s, np.arctan2(s, c))


def constrain(transform: Sim3, opts, pivot: np.ndarray) -> Sim3:
    """`transform` brought back onto the hints: its rotation tilted so the up axes agree, its
    scale set to fixed_scale; the source point `pivot` (its centre) stays where it was mapped."""
    rotation, scale = transform.rotation, transform.scale
    if opts.up_axes is not None:
        src_up, dst_up = (np.asarray(v, np.float64) for v in opts.up_axes)
        rotation = _min_rotation(rotation @ src_up, dst_up) @ rotation
        if opts.front_axes is not None:
            rotation = _front_held(rotation, dst_up, opts.front_axes, opts.criteria.guidance)
    if opts.fixed_scale is not None:
        scale = opts.fixed_scale
    if rotation is transform.rotation and scale == transform.scale:
        return transform
    mapped = transform.apply(pivot[None])[0]
    return Sim3(scale, rotation, mapped - scale * rotation @ pivot)


def start_transform(opts, criteria: GuidanceCriteria | None = None) -> tuple[Sim3, dict] | None:
    """Where a local refinement starts: init_transform or the pairs' fit (None: neither given)."""
    if opts.init_transform is not None:
        return init_sim3(opts.init_transform), {"from": "init_transform"}
    if opts.point_pairs is not None:
        src, dst = (np.asarray(p, np.float64) for p in opts.point_pairs)
        fit, report = pairs_transform(src, dst, opts.fixed_scale, criteria)
        return fit, {"from": "point_pairs", **report}
    return None


def near_start(
    pose: Sim3,
    start: Sim3,
    opts,
    report: dict,
    criteria: GuidanceCriteria | None = None,
    symmetries: list[np.ndarray] = (),
) -> bool:
    """Whether `pose` is still the answer the user pointed at (start_transform's `start` and
    `report`): within start_leash_deg of a given pose, up to the source's own `symmetries`
    (source_symmetries: a bottle turned about its own axis is the same answer); with picked
    pairs, a rotation that maps every kept source click near its target click
    (pairs_leash_share), at the scale and shift that fit the clicks best, and within
    pairs_max_turn_deg of their fit. The local refinement
    corrects a pose 20 deg off or clicks a few % off, and between two instances of different
    proportions it finds the pose better than the clicks do; it must not carry the answer to
    another side of the object, away from what the user gave."""
    k = criteria or _DEFAULT
    if report.get("from") != "point_pairs":
        return start_distance_deg(pose.rotation, start, symmetries) <= k.start_leash_deg
    if rotation_distance_deg(pose.rotation, start.rotation) > k.pairs_max_turn_deg:
        return False
    _, dst = kept_clicks(opts, report)
    spread = float(np.sqrt(np.mean(np.sum((dst - dst.mean(0)) ** 2, axis=1))))
    return (
        click_miss(pose.rotation, opts, report)
        <= click_miss(start.rotation, opts, report) + k.pairs_leash_share * spread
    )


def kept_clicks(opts, report: dict) -> tuple[np.ndarray, np.ndarray]:
    """The picked pairs (source, target) less the misclick start_transform left out."""
    src, dst = (np.asarray(p, np.float64) for p in opts.point_pairs)
    if report.get("left_out") is not None:
        keep = np.arange(len(src)) != report["left_out"]
        src, dst = src[keep], dst[keep]
    return src, dst


def click_miss(rotation: np.ndarray, opts, report: dict) -> float:
    """How far a pose with this rotation misses the worst kept click, at the scale and shift
    that fit the clicks best. The clicks pin which way the object faces; where it sits and how
    large it is the refinement judges better between two instances (the clicks' own fit is
    off in both)."""
    src, dst = kept_clicks(opts, report)
    turned, centred = (src - src.mean(0)) @ np.asarray(rotation).T, dst - dst.mean(0)
    scale = max(float(np.sum(turned * centred) / max(np.sum(turned**2), 1e-300)), 0.0)
    return float(np.max(np.linalg.norm(scale * turned - centred, axis=1)))


def start_distance_deg(rotation: np.ndarray, start: Sim3, symmetries: list[np.ndarray] = ()) -> float:
    """Degrees between a rotation and a given pose's, up to the source's own `symmetries`."""
    return min(rotation_distance_deg(rotation @ g, start.rotation) for g in [np.eye(3), *symmetries])


def source_symmetries(points: np.ndarray, sample_size: int = 3000, dense_size: int = 50_000) -> list[np.ndarray]:
    """Turns about the principal axes of `points` (the source's surface, source coordinates)
    that map it onto itself, as rotation matrices: every 2 deg about the axis it turns freely
    about (a bottle, a vase), when exactly one axis is free. Two poses that differ by one place
    the surface identically, so the leash of a given pose is measured up to them. Quarter and
    half turns are not listed: a table passes them on the mean distance while a drawer or a
    foot does not, and a leash that let them through took real pairs 50-80 deg off
    (docs/benchmarks.md)."""
    if len(points) < 10:
        return []
    rng = np.random.default_rng(0)
    if len(points) > dense_size:  # spacings are measured within whatever density is kept
        points = points[rng.choice(len(points), dense_size, replace=False)]
    sample = points[rng.choice(len(points), min(len(points), sample_size), replace=False)]
    centre = points.mean(0)
    tree = cKDTree(points - centre)  # the dense set: a turned sample lands on its surface
    spacing = float(np.mean(tree.query(sample - centre, k=2)[0][:, 1]))
    # every point for the axes: a sample's axis is off by a degree or two, which a long object
    # turned by 135 deg about it shows as a move of two spacings
    axes = np.linalg.eigh(np.cov((points - centre).T))[1].T

    def moves_off(axis: np.ndarray, deg: float) -> bool:
        turned = (sample - centre) @ axis_rotation(axis, np.radians(deg)).T
        return float(np.mean(tree.query(turned)[0])) >= SYMMETRY_SPACINGS * spacing

    free = [axis for axis in axes if not any(moves_off(axis, deg) for deg in (30.0, 60.0, 90.0, 135.0))]
    if len(free) != 1:  # none, or a near-sphere (its principal axes are noise): no turn is free
        return []
    return [axis_rotation(free[0], np.radians(deg)) for deg in np.arange(2.0, 360.0, 2.0)]


def local_turns(criteria: GuidanceCriteria | None = None) -> list[np.ndarray]:
    """The turns the local search starts from (besides none): local_turn_deg about each axis, both ways."""
    angle = np.radians((criteria or _DEFAULT).local_turn_deg)
    return [axis_rotation(sign * axis, angle) for axis in np.eye(3) for sign in (1.0, -1.0)]


def doubt_reason(metrics: dict, start_report: dict | None) -> str | None:
    """Why a guided result is doubtful, in words (metrics['guidance']['doubt']; None where it is
    not): guidance that contradicts the models (pairs no pose satisfies, a wrong up axis) ends
    here, flagged with the reason rather than passed off as an answer."""
    if not metrics.get("doubtful"):
        return None
    reasons = []
    if start_report and start_report.get("refinement"):
        reasons.append("the refinement moved away from what was given, so the nearest pose to it is kept")
    margin, alternatives = metrics.get("margin"), metrics.get("alternatives") or []
    # the first alternative the models offer (the given start, offered first, is the person's own)
    index = next((i for i, a in enumerate(alternatives) if a.get("origin") != GIVEN_START), None)
    if margin is not None and margin < 0 and index is not None:
        offset = alternatives[index].get("rotation_offset_deg")
        where = f" {offset:.0f}° from this one" if offset is not None else ""
        reasons.append(
            f"the models fit better at another pose{where} (alternatives[{index}]): the guidance may be wrong"
        )
    elif metrics.get("ambiguous"):
        reasons.append("another pose fits the models as well as this one (see alternatives)")
    share = metrics.get("coincident_share")
    if share is not None and not reasons:
        reasons.append(
            f"the models coincide on little of their surface at this pose (coincident share {share:.2f}, "
            f"confidence {metrics.get('confidence', float('nan')):.2f})"
        )
    return "; ".join(reasons) or f"low confidence ({metrics.get('confidence', float('nan')):.2f})"


def describe(opts) -> dict:
    """metrics['guidance']: which hints were used."""
    return {
        "init_transform": opts.init_transform is not None,
        "point_pairs": None if opts.point_pairs is None else len(opts.point_pairs[0]),
        "up_axes": None if opts.up_axes is None else [list(v) for v in opts.up_axes],
        "front_axes": None if opts.front_axes is None else [list(v) for v in opts.front_axes],
        "fixed_scale": opts.fixed_scale,
    }


__all__ = [
    "GuidanceCriteria",
    "check_guidance",
    "click_miss",
    "constrain",
    "describe",
    "front_gap_deg",
    "doubt_reason",
    "init_sim3",
    "is_guided",
    "keeps_front",
    "local_turns",
    "near_start",
    "pair_arrays",
    "pairs_transform",
    "start_distance_deg",
    "start_transform",
    "up_rotations",
]
