"""Outdoor sites (gsa.align.scene): the site test (`site_structure`: an open ground with
things standing on it) and the scene path's search for sites (`site_search`: up-aligned
rotations, a thinned ground, placed starts and climbs where the answer is doubtful).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from gsa.align import robust
from gsa.align.scene.common import _anchor_normals, _inner_parts, translation_sweep
from gsa.align.scene.options import SceneOptions
from gsa.colour import linear_to_lab, srgb_to_linear
from gsa.geometry import axis_rotation
from gsa.render import steps
from gsa.sim3 import Sim3


@dataclass
class Site:
    """What the site test saw on one model (site_structure)."""

    up: np.ndarray  # unit up axis, signed so that things stand on the ground
    ground: np.ndarray  # (A,) bool: anchors of the ground
    ground_share: float  # anchor weight on the ground
    sky: float  # share of the ground's columns with no up/down-facing surface above the ground
    span: float  # the ground's horizontal span over the model's extent (the smaller side)
    height: float  # the model's extent along up over its horizontal extent
    parts: int  # separate things standing on the ground
    parts_weight: float
    gaussians: int = 0
    anchors: int = 0
    options: SceneOptions = field(default_factory=SceneOptions, repr=False)  # the thresholds the test used

    @property
    def open_ground(self) -> bool:
        """A ground open to the sky (what the path's search relies on), whatever its span."""
        o = self.options
        return bool(
            self.anchors >= o.site_anchors
            and self.ground_share >= o.ground_share
            and self.sky >= o.sky_share
            and self.height <= o.site_height
        )

    @property
    def is_site(self) -> bool:
        o = self.options
        things_on_it = self.parts >= o.site_parts and self.parts_weight >= o.content_weight
        # A ground open almost everywhere is a site with nothing on it (a lawn, a field):
        # what came closest among objects, an airplane from below, has sky 0.86.
        open_ground = self.sky >= o.sky_open
        return bool(
            self.anchors >= o.site_anchors
            and self.ground_share >= o.ground_share
            and self.sky >= o.sky_share
            and self.span >= o.ground_span
            and self.height <= o.site_height
            and (things_on_it or open_ground or self.gaussians >= o.scene_gaussians)
        )

    def to_dict(self) -> dict:
        return {
            "ground_share": round(self.ground_share, 4),
            "sky": round(self.sky, 4),
            "span": round(self.span, 4),
            "height": round(self.height, 4),
            "parts": self.parts,
            "parts_weight": round(self.parts_weight, 4),
            "anchors": self.anchors,
            "is_site": self.is_site,
        }


def site_structure(
    pts: np.ndarray,
    w: np.ndarray,
    normals: np.ndarray,
    voxel: float,
    extent: float,
    gaussians: int = 0,
    options: SceneOptions | None = None,
) -> Site:
    """The site test on anchors (weights w summing to 1, unit normals, the anchor voxel):
    an outdoor site has no shell; it is a ground - an open heightfield - with things
    standing on it. The up axis is the dominant normal direction (the weighted normals'
    principal axis). Seen along it, the ground is each column's lowest anchors that face
    up (within ground_deg), up to ground_band voxels above the lowest (columns two voxels
    wide). A site's ground holds ground_share of the weight, lies open to the sky in
    sky_share of its columns (no other surface facing up or down within cover_deg above it: an object's
    underside has its top above it, a site's ground has the sky), spans ground_span of
    the extent across (the smaller horizontal side), is at most site_height as tall as
    wide, and has site_parts separate things standing on it (trees, rocks, benches: as
    the room test's parts), or is open to the sky in sky_open of its columns (a lawn),
    or has scene_gaussians Gaussians, as a room; and the test sees
    at least site_anchors anchors (test_density Gaussians each): with fewer, a thin
    object (a wing, a wheel face-on) is one layer of columns like a ground. Measured
    (docs/benchmarks.md, "Outdoor sites"): an airplane seen from below comes closest
    (sky 0.67: its fuselage's top covers the columns under it). Both signs of the axis are tried; the site's up is the one
    that passes (else the one with the more ground)."""
    o = options or SceneOptions()
    m = np.einsum("n,ni,nj->ij", w, normals, normals)
    return _site_along(np.linalg.eigh(m)[1][:, 2], pts, w, normals, voxel, extent, gaussians, o)


def _site_along(
    axis: np.ndarray,
    pts: np.ndarray,
    w: np.ndarray,
    normals: np.ndarray,
    voxel: float,
    extent: float,
    gaussians: int,
    o: SceneOptions,
) -> Site:
    """site_structure's test with its axis given (either sign is tried)."""
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    xy = np.stack([pts @ u, pts @ v], 1)
    facing = np.abs(normals @ axis) >= np.cos(np.radians(o.ground_deg))
    covering = np.abs(normals @ axis) >= np.cos(np.radians(o.cover_deg))
    cell = 2.0 * voxel
    ij = np.floor((xy - xy.min(0)) / cell).astype(np.int64)
    _, col = np.unique(ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1], return_inverse=True)
    col = col.ravel()
    n_col = int(col.max()) + 1
    band = o.ground_band * voxel
    horizontal = float(np.max(np.ptp(xy, axis=0)))
    best = None
    for sign in (1.0, -1.0):
        h = sign * (pts @ axis)
        lowest = np.full(n_col, np.inf)
        np.minimum.at(lowest, col[facing], h[facing])
        has_ground = np.isfinite(lowest)
        rel = h - lowest[col]
        ground = facing & (rel <= band)
        covered = np.zeros(n_col, bool)
        covered[col[covering & (rel > band)]] = True  # another horizontal surface above the ground
        n_ground_cols = max(int(has_ground.sum()), 1)
        sky = float(np.sum(has_ground & ~covered) / n_ground_cols)
        g_xy = xy[ground]
        if len(g_xy) >= 3:
            lo, hi = np.percentile(g_xy, [2, 98], axis=0)
            span = float(np.min(hi - lo) / extent)
        else:
            span = 0.0
        height = float(np.ptp(h) / max(horizontal, 1e-12))
        # Things standing on the ground: the room test's parts, off the ground and above it.
        standing = ~ground & (rel > -band)
        parts, parts_weight = _inner_parts(pts, w, standing, [], voxel, extent, o)
        site = Site(
            sign * axis, ground, float(w[ground].sum()), sky, span, height, parts, parts_weight, gaussians, len(pts), o
        )
        if site.is_site:
            return site
        if best is None or site.ground_share > best.ground_share:
            best = site
    return best


def _sites(src: robust.Anchors, dst: robust.Anchors, options: SceneOptions | None = None) -> tuple[Site, Site] | None:
    """Both models' site test on the path's own anchors, its ground alone (Site.open_ground:
    the pair is already taken as scenes, and far background anchors of a real capture
    can shrink the ground's span against the extent): a pair whose grounds both lie open
    to the sky is searched as sites, whichever test took it - a walled garden passes the room
    test too, and the room search, blind to the ground, misses it. A room with its ceiling
    has no sky."""
    found = tuple(_site_of(a, options or SceneOptions()) for a in (src, dst))
    return found if all(f.open_ground for f in found) else None


def _site_of(a: robust.Anchors, o: SceneOptions) -> Site:
    """The site test on the path's anchors, its up axis then refitted to the ground
    (_ground_up) and the ground found again along it, ground_fit_rounds times; kept
    while the ground stays open to the sky."""
    w = a.weights / a.weights.sum()
    extent = float(np.max(np.ptp(a.points, axis=0)))
    voxel = extent / np.sqrt(len(a.points))
    normals = _anchor_normals(a.points)
    site = site_structure(a.points, w, normals, voxel, extent, o.scene_gaussians, o)
    for _ in range(o.ground_fit_rounds):
        if not site.open_ground or site.ground.sum() < 3:
            break
        refit = _site_along(
            _ground_up(a.points[site.ground], w[site.ground], site.up, o),
            a.points,
            w,
            normals,
            voxel,
            extent,
            o.scene_gaussians,
            o,
        )
        if not refit.open_ground:
            break
        site = refit
    return site


def _ground_up(ground: np.ndarray, w: np.ndarray, up: np.ndarray, o: SceneOptions) -> np.ndarray:
    """The normal of the plane through the ground's anchors (weighted least squares,
    refitted on the ground_fit_keep of them nearest the plane, so that a hollow, a hedge's
    foot or a path's kerb does not tilt it), signed as `up`. The mean of the anchors'
    normals, which the site test starts from, leans towards whatever else faces one way
    (slopes, tree crowns, walls): on two partial captures of one real garden the two
    starting axes disagreed by 7-18 degrees, the refitted ones by 0.6-2.7 (docs/benchmarks.md,
    "Outdoor sites") - beyond the search's tilts, the truth was not among its rotations."""
    keep = np.ones(len(ground), bool)
    for _ in range(3):
        centre = np.average(ground[keep], axis=0, weights=w[keep])
        d = ground - centre
        normal = np.linalg.eigh(np.einsum("n,ni,nj->ij", w[keep], d[keep], d[keep]))[1][:, 0]
        residual = np.abs(d @ normal)
        keep = residual <= np.quantile(residual, o.ground_fit_keep)
    return normal if normal @ up > 0 else -normal


def site_search(
    src: robust.Anchors,
    dst: robust.Anchors,
    src_site: Site,
    dst_site: Site,
    seed: int = 0,
    options: SceneOptions | None = None,
    search_options: robust.SearchOptions | None = None,
    verdict: robust.VerdictCriteria | None = None,
) -> robust.SearchResult:
    """The scene path's search for sites. Two things differ from a room's:
    - the ground fixes two of the three rotation angles: only rotations taking the
      source's up axis onto the target's (either sign: the test's sign can be fooled by
      tree crowns seen from above), turned about it in site_yaw_deg steps, are searched
      (robust.global_search with these as its only rotations; no widening: these rotations
      are all a site can be in; the ups are refitted to the grounds' planes, _site_of);
    - the ground, which holds most of the weight and which any turn of the site lays on
      itself within the search's truncation, is thinned to site_ground_keep of the
      anchors the search scores on, so the things standing on it decide.
    The translation sweep follows, as for rooms; the verdict scores on all anchors. Where
    that answer is doubtful, placed and matched starts and climbs join (below). search_options: the
    search's (its rotations are these, its seed `seed`), verdict: what makes an answer
    doubtful (None: the defaults)."""
    o = options or SceneOptions()
    rng = np.random.default_rng(seed)
    s_thin, d_thin = (_ground_thinned(a, site.ground, rng, o) for a, site in ((src, src_site), (dst, dst_site)))
    rotations = _site_rotations(src_site.up, dst_site.up, o)
    search = robust.global_search(
        s_thin,
        d_thin,
        [("site", r) for r in rotations],
        replace(search_options or robust.SearchOptions(), rotations=0, seed=seed),
    )
    search = translation_sweep(s_thin, d_thin, search, seed, o)
    # Re-scored on all anchors, so the verdict and the alternatives read what rooms' do,
    # each pose's colours compared under the exposure that pose implies.
    w, k = search.colour_weight, search.criteria
    result = robust.decide(robust.dedupe(_gain_scored(src, dst, search.candidates, w, k), k), w, None, k)
    if not robust.verdict(result.best, result, criteria=verdict)["doubtful"]:
        return result
    # A doubtful answer: starts that trust no centroid (_placed) or no up axis (_matched)
    # join, and the best of each - before the anchors' ICP moves them and the dedup merges
    # them into a pose that scores higher there - climb the score, as does the best pose. Both compare
    # chromaticity alone (_chroma): where the palettes did not tell the exposure apart,
    # the full colours disagree at the truth itself.
    # Independent (each its own draws): run side by side where cores are free.
    (starts, refined), matched = steps.parallel(
        [
            lambda: _placed(_chroma(s_thin), _chroma(d_thin), src_site, dst_site, search, rng, o),
            lambda: _matched(src, dst, search, seed, search_options or robust.SearchOptions()),
        ]
    )
    scored = _gain_scored(src, dst, starts + refined + matched, w, k)
    result = robust.decide(robust.dedupe(result.candidates + scored, k), w, None, k)
    # the placement's own order (by chromaticity), then the matches' (by consensus)
    climbers = _apart([result.best, *starts[: o.climb_top], *matched[: o.climb_top]], src, dst, o)
    # The climbs score on a sample of the anchors: each is hundreds of scores, and a site's
    # anchors are thousands (a 1M terrain's 7k: 3.4 s a climb on all of them)
    src_chroma, dst_chroma = (_chroma(_rows_of(a, robust.subsample(rng, len(a), o.climb_anchors))) for a in (src, dst))
    climbed = steps.parallel_map(
        lambda c: _pose_gain_score(src, dst, _climb(src_chroma, dst_chroma, c, w, k, o), w, k), climbers
    )
    return robust.decide(robust.dedupe(climbed + result.candidates, k), w, None, k)


def _apart(
    starts: list[robust.Candidate],
    src: robust.Anchors,
    dst: robust.Anchors,
    o: SceneOptions,
) -> list[robust.Candidate]:
    """The starts less any that lies within one first climb step of an earlier one (turn,
    shift of the source's centre, scale), which would climb the same hill: a matched start is
    often the search's best pose already, and each climb costs seconds at a site's anchors."""
    out: list[robust.Candidate] = []
    for c in starts:
        near = any(
            robust.rotation_offset_deg(c.transform, kept.transform) <= o.climb_turn_deg
            and abs(np.log(c.transform.scale / kept.transform.scale)) <= o.climb_scale
            and np.linalg.norm(c.transform.apply(src.center) - kept.transform.apply(src.center))
            <= o.climb_shift * dst.radius
            for kept in out
        )
        if not near:
            out.append(c)
    return out


def _placed(
    src: robust.Anchors,
    dst: robust.Anchors,
    src_site: Site,
    dst_site: Site,
    search: robust.SearchResult,
    rng: np.random.Generator,
    o: SceneOptions,
) -> tuple[list[robust.Candidate], list[robust.Candidate]]:
    """Starts that trust neither centroid nor radius: each up-aligned yaw (no tilt) tries a
    lattice of positions at site_place_scales of the radius ratio (robust's placement
    search); the site_place_top best distinct ones (unscored), and each after the anchor
    ICP (scored), which can slide off a placement where two partial captures overlap in
    half (on a real garden it left the truth itself by 3-16 degrees). Such captures have
    centroids far apart and radii ~30 % off; the search places by them, so the right yaw
    can end outside the translation sweep's few rotations, or at a scale its lattice
    cannot reach."""
    k = search.criteria
    placements = robust.placed_starts(
        src,
        dst,
        rng,
        rotations=_site_rotations(src_site.up, dst_site.up, o, yaw_deg=o.site_place_yaw_deg),
        points=o.site_place_points,
        step=o.site_place_step,
        truncation=o.site_place_truncation,
        scales=o.site_place_scales,
        count=o.site_place_top,
        min_deg=k.distinct_deg,
        capture=lambda rotations, scale, t, steps: (scale, t),
        capture_steps=(),
        w_colour=search.colour_weight,
        colour_sigma=k.colour_sigma,
        # In the target site's own frame its box is flat: a fraction of the world box's positions.
        centres=robust.box_lattice(dst.points, _site_frame(dst_site.up), o.site_place_step * dst.radius),
    )
    rows = robust.subsample(rng, len(src), 2000), robust.subsample(rng, len(dst), 2000)
    starts = [robust.Candidate(Sim3(s_, r, t_ - s_ * r @ src.center), "placed") for r, s_, t_ in placements]

    def refined(start: robust.Candidate) -> robust.Candidate:
        pose = robust.bidirectional_icp(src, dst, start.transform, *rows, o.sweep_icp, search.colour_weight, k)
        return robust.score_pose(src, dst, pose, "placed", search.colour_weight, k)

    return starts, steps.parallel_map(refined, starts)


def _matched(
    src: robust.Anchors, dst: robust.Anchors, search: robust.SearchResult, seed: int, so: robust.SearchOptions
) -> list[robust.Candidate]:
    """Starts that trust no up axis: poses most local-shape pairs agree with
    (robust.matched_poses), unscored and not moved by the ICP (on two partial captures it
    slides them, as it does placements; the climb takes them on). The search's rotations
    take one capture's up onto the other's, and the ups of two partial captures of a hilly
    site are each their own part's ground plane: 5-11 degrees apart on generated terrains
    (docs/benchmarks.md, "Sites whose ups disagree"), where no searched rotation is near the truth."""
    rng = np.random.default_rng([seed, 1])  # their own draws, as the object path's matched starts
    poses = robust.matched_poses(
        src, dst, rng, so.match_top, search.criteria.distinct_deg, so.matching, search.colour_weight
    )
    return [robust.Candidate(p, "matched") for p in poses]


def _chroma(a: robust.Anchors) -> robust.Anchors:
    """The anchors with every CIELAB lightness set to one value: an exposure change moves
    L* and leaves a* and b* nearly where they were. On a real garden pair whose exposure
    gains the palettes could not tell (robust.match_exposure kept 1), the score at the
    truth was 0.03 in full colour and 0.27 in chromaticity, 0.19 five degrees off."""
    lab = a.lab.copy()
    lab[:, 0] = 50.0
    return replace(a, lab=lab)


def _climb(
    src: robust.Anchors,
    dst: robust.Anchors,
    start: robust.Candidate,
    w_colour: float,
    criteria: robust.PoseCriteria,
    o: SceneOptions,
) -> robust.Candidate:
    """The pose moved uphill on robust's score (turns about three axes through the overlap's
    centre, shifts along three axes, scale about it), steps halved climb_rounds
    times from climb_turn_deg, climb_shift radii and climb_scale. On partial captures
    of a real garden the anchors' ICP and the full-resolution refinement both slid away
    from the truth (to 3-16 degrees), while the coloured score peaked at it."""

    def score(t: Sim3) -> float:
        return robust.score_pose(src, dst, t, start.origin, w_colour, criteria).score

    best, top = start.transform, score(start.transform)
    turn, shift, grow = np.radians(o.climb_turn_deg), o.climb_shift * dst.radius, o.climb_scale
    for _ in range(o.climb_rounds):
        while True:
            c = _overlap_centre(src, dst, best, criteria)
            moves = []
            for axis in np.eye(3):
                for sign in (1.0, -1.0):
                    r = axis_rotation(axis, sign * turn)
                    moves.append(Sim3(best.scale, r @ best.rotation, r @ (best.translation - c) + c))
                    moves.append(Sim3(best.scale, best.rotation, best.translation + sign * shift * axis))
            for sign in (1.0, -1.0):
                f = float(np.exp(sign * grow))
                moves.append(Sim3(best.scale * f, best.rotation, f * (best.translation - c) + c))
            scores = [score(m) for m in moves]
            i = int(np.argmax(scores))
            if scores[i] <= top:
                break
            best, top = moves[i], scores[i]
        turn, shift, grow = turn / 2, shift / 2, grow / 2
    return robust.Candidate(best, start.origin)


def _overlap_centre(src: robust.Anchors, dst: robust.Anchors, pose: Sim3, criteria: robust.PoseCriteria) -> np.ndarray:
    """Where the mapped source meets the target (its anchors within the score's truncation
    of one): turns about it keep the overlap in place; turns about the source centre,
    far from a partial overlap, sweep it away."""
    mapped = pose.apply(src.points)
    d, _ = dst.tree.query(mapped, k=1)
    near = d <= criteria.truncation * dst.radius
    return mapped[near].mean(axis=0) if near.sum() >= 10 else pose.apply(src.center)


def _gain_scored(
    src: robust.Anchors, dst: robust.Anchors, cands: list, w_colour: float, criteria: robust.PoseCriteria
) -> list[robust.Candidate]:
    """_pose_gain_score of each pose, side by side where cores are free (the same scores)."""
    return steps.parallel_map(lambda c: _pose_gain_score(src, dst, c, w_colour, criteria), cands)


def _pose_gain_score(
    src: robust.Anchors, dst: robust.Anchors, cand, w_colour: float, criteria: robust.PoseCriteria
) -> robust.Candidate:
    """robust.score_pose with the source's colours under the linear-RGB gains that the
    pose's own close pairs give (per channel, the median ratio). The palettes alone
    (robust.match_exposure) often cannot tell an exposure change on a site: grass and
    foliage are a continuum of greens that any gain maps onto itself, and the colour term
    then counts the truth's pairs as disagreeing. At the true pose the pairs are the same
    surfaces and the gains are the exposure's; a wrong pose pairs unrelated surfaces, and
    no gain makes them agree. The gains are held within robust's exposure bounds."""
    plain = robust.score_pose(src, dst, cand.transform, cand.origin, w_colour, criteria)
    if src.rgb is None or dst.rgb is None or w_colour <= 0:
        return plain
    ratio = robust.pose_gain(src, dst, cand.transform.apply(src.points), criteria.colour_pair_distance)
    if ratio is None:
        return plain
    limit = criteria.palette.max_exposure_gain
    gain = np.clip(ratio, 1 / limit, limit)
    # as match_exposure compares them
    in_s, in_d = robust.in_one_exposure(srgb_to_linear(src.rgb), srgb_to_linear(dst.rgb), gain)
    in_one = replace(src, lab=linear_to_lab(in_s)), replace(dst, lab=linear_to_lab(in_d))
    gained = robust.score_pose(*in_one, cand.transform, cand.origin, w_colour, criteria)
    return gained if gained.score > plain.score else plain


def _site_polish(
    src: robust.Anchors, dst: robust.Anchors, search: robust.SearchResult, rng: np.random.Generator
) -> robust.Candidate:
    """The search's best pose run on to convergence by the anchor ICP on all anchors (the
    search's ICP ran on the ground-thinned ones), kept if it scores better."""
    rows = robust.subsample(rng, len(src), 2000), robust.subsample(rng, len(dst), 2000)
    k = search.criteria
    pose = robust.bidirectional_icp(src, dst, search.best.transform, *rows, 100, search.colour_weight, k)
    polished = robust.score_pose(src, dst, pose, search.best.origin, search.colour_weight, k)
    return polished if polished.score > search.best.score else search.best


def _ground_thinned(a: robust.Anchors, ground: np.ndarray, rng: np.random.Generator, o: SceneOptions) -> robust.Anchors:
    """The anchors with the ground's cut to site_ground_keep of them (at random); centre
    and radius stay the whole model's."""
    g, rest = np.flatnonzero(ground), np.flatnonzero(~ground)
    keep = int(o.site_ground_keep / (1 - o.site_ground_keep) * len(rest))
    if keep >= len(g) or len(rest) < 50:
        return a
    return _rows_of(a, np.sort(np.concatenate([rest, rng.choice(g, keep, replace=False)])))


def _rows_of(a: robust.Anchors, rows: np.ndarray) -> robust.Anchors:
    """The anchors of `rows`; centre and radius stay the whole model's."""
    return replace(
        a,
        points=a.points[rows],
        lab=a.lab[rows],
        weights=a.weights[rows],
        tree=cKDTree(a.points[rows]),
        rgb=None if a.rgb is None else a.rgb[rows],
    )


def _site_rotations(
    up_src: np.ndarray, up_dst: np.ndarray, options: SceneOptions | None = None, yaw_deg: float | None = None
) -> np.ndarray:
    """Rotations taking up_src onto ±up_dst, each turned about up_dst in yaw_deg (None:
    site_yaw_deg) steps. No tilts: the ups refitted to the grounds' planes agree within a
    few degrees (0.6-2.7 on a real garden), which the ICP and the climb take up."""
    o = options or SceneOptions()
    yaws = [axis_rotation(up_dst, y) for y in np.radians(np.arange(0.0, 360.0, yaw_deg or o.site_yaw_deg))]
    out = []
    for sign in (1.0, -1.0):
        base = _rotation_between(up_src, sign * up_dst)
        out += [yaw @ base for yaw in yaws]
    return np.asarray(out)


def _site_frame(up: np.ndarray) -> np.ndarray:
    """Rows: two unit axes across `up`, then `up`."""
    helper = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a), up])


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit a onto unit b (a half turn about an axis across a
    when they are opposite)."""
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:
        helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
        axis = np.cross(a, helper)
        return axis_rotation(axis / np.linalg.norm(axis), np.pi)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)
