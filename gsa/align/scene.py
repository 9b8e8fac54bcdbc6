"""Scene-scale registration: the test that tells a room from an object, and
the scene path align() takes for rooms.

*The test* (`scene_structure`, on each model's floater-free anchors - at least
test_density Gaussians each, so surfaces stay connected - hence scale-free and
O(anchors)): a captured room is a shell of large planes (floor, walls, ceiling) with
separate things standing inside it; an object is its parts alone, or (a bus, a box) a
shell with nothing inside. Planes are found by sequential RANSAC on the anchors (inliers
within a quarter voxel that face the plane's way). A *shell plane* is large (its inliers
span at least shell_span of the extent and hold at least shell_share of the anchor
weight) and bounds the model (at most outside_share of the weight beyond it). The
anchors off the shell planes are then grouped into connected *parts* (linked within 1.5
voxels); a part counts when it holds at least part_weight of the weight, has a body (at
least a voxel thick: not the sliver a plane's band leaves), is at most part_size of the
extent long and lies inside every shell plane. The model is a scene when at least
shell_planes shell planes hold shell_weight of the weight and either at least
content_parts parts hold content_weight, or the model holds at least scene_gaussians
Gaussians: a planar shell that large is a site whichever way its parts fall, and the
object path's full-resolution trees are what stop scaling there (a large box-like
object then takes the scene path too, which aligns it without the frame relabellings).
The test runs on at most test_sample Gaussians, so it costs the same at any size.
Under `scene="auto"` both models must pass; `"on"` forces the path, `"off"` never
takes it. Measured (docs/benchmarks.md, "Scenes"): no pair of the object protocols
(dup, same, category, partial, noisy, deform, symmetric; quick and full sizes) passes;
on small rooms the parts condition is conservative (a capture holding two or three
pieces of furniture can miss it), and a room it misses still gets the object path.

*The scene path* (`align_scene`) differs from the object path where rooms differ from
objects:
- more anchors (scene_anchors): 2000 voxels over a 9 m room are 20 cm wide, and the
  furniture that breaks the shell's symmetries is what the search must see;
- no canonical-frame relabellings: a room's principal axes carry no meaning for another
  partial capture of it;
- a translation sweep after the search (`translation_sweep`): the best rotations slide
  over the whole target, since partial captures' centroids lie far apart and planes let
  a pose slide;
- colours compared under one exposure (`robust.match_exposure`, as on the object path): two captures taken apart
  differ in exposure and white balance, and the object path's colour trust would drop
  to zero, leaving geometry alone to tell a room's mirror-like halves apart;
- the full-resolution refinement (robust.refine: bidirectional trimmed ICP, stopping at
  the overlap) runs on at most refine_cloud Gaussians per capture drawn at random from
  the floater-free ones, with their full-resolution positions: trees and neighbour
  tables stay bounded, so time and memory grow linearly only through the O(N)
  anchoring and sampling passes; it ends point-to-plane on the target Gaussians' normals
  where the captures coincide, as on the object path;
- no canonical features (and no feature metrics) and no fine stage, which renders
  every Gaussian per view.

The tunables named above in lower case are the fields of `SceneOptions`; `choose` (and the
functions it and the scene path call) take one, None meaning the defaults; `align_scene`
reads every criterion from AlignOptions.criteria (its `scene`, and the search's, pose,
refinement and verdict criteria, as the object path does).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gsa.align import robust
from gsa.align.choices import Progress
from gsa.align.coarse import AlignmentError, CoarseResult
from gsa.colour import linear_to_lab, srgb_to_linear
from gsa.geometry import axis_rotation
from gsa.model import GaussianModel, ModelError
from gsa.sim3 import Sim3


@dataclass(frozen=True)
class SceneOptions:
    """The tunables of the scene test and the scene path (module docstring); the defaults
    are the values benchmarked in docs/benchmarks.md ("Scenes", "Outdoor sites"). The
    tests' quantities are fractions of the model's own extent or anchor weight, so the
    tests are scale-free."""

    # The room test (scene_structure).
    shell_span: float = 0.5  # a shell plane's inliers span this much of the extent: floors and walls cross a room
    shell_share: float = 0.03  # and hold this much of the weight (half of it ends the plane search)
    outside_share: float = 0.03  # weight beyond a shell plane at most: it bounds the model, strays aside
    shell_planes: int = 3  # shell planes a room needs: a floor and two walls at the least
    shell_weight: float = 0.4  # weight on the shell planes a room needs: most of a room's surface is its shell
    content_parts: int = 3  # parts inside the shell a room needs: a box-like object (a bus) has none
    content_weight: float = 0.03  # weight a room's (or a site's) parts hold together: more than a few strays
    part_weight: float = 0.005  # weight one part holds at least: smaller groups are noise, not furniture
    part_size: float = 0.35  # a part's length at most: longer is the room's structure, not a thing inside it
    max_planes: int = 8  # planes sought: a box room's six and two tries for edge layers merged into one
    facing_deg: float = 25.0  # a plane's inliers face its way within this: lattice rows lie on any plane
    test_density: int = 16  # Gaussians per test anchor at least: sparser voxels break surfaces into fragments
    test_sample: int = 200_000  # Gaussians the test runs on at most: it costs the same at any size
    # A shell or ground this large is a scene whatever its parts: the object path's trees stop scaling there.
    scene_gaussians: int = 400_000
    voxel_probe: int = 200_000  # Gaussians the anchor voxel is searched on: a few thousand voxels fill alike
    # The site test (site_structure).
    ground_deg: float = 30.0  # ground normals within this of the up axis: slopes are ground too
    ground_band: float = 1.5  # the ground's band above each column's lowest up-facing anchor, in anchor voxels
    ground_share: float = 0.25  # weight on the ground a site needs: a site is mostly its ground
    sky_share: float = 0.8  # ground columns open to the sky a site needs: an object's underside has its top above it
    ground_span: float = 0.3  # the ground's span across (the smaller horizontal side) over the extent, at least
    site_height: float = 0.5  # a site's height over its width at most: a site is flat
    site_parts: int = 1  # things standing on the ground a site needs (trees, rocks, benches)
    site_anchors: int = 300  # test anchors a site needs: with fewer, a thin object (a wing) is one layer like a ground
    sky_open: float = 0.95  # ground columns open to the sky that make a site with nothing on it (a lawn)
    ground_fit_rounds: int = 2  # the site path's up axis refitted to its ground plane this often (_site_of)
    ground_fit_keep: float = 0.8  # share of the ground's anchors nearest the plane it is refitted on
    # The scene path (align_scene).
    scene_anchors: int = 6000  # anchors per model at least: the furniture that breaks a shell's symmetries must show
    site_yaw_deg: float = 5.0  # yaw step of the site search's up-aligned rotations
    site_ground_keep: float = 0.35  # the ground's share of the site search's anchors: what stands on it decides
    # The doubtful site answer's placed starts (_placed).
    site_place_points: int = 48  # anchors per side scored per placed position (robust.placed_starts)
    site_place_step: float = 0.25  # its lattice step in the target site's frame, fraction of the target radius
    site_place_yaw_deg: float = 5.0  # its yaw step
    site_place_truncation: float = 0.2  # its score distance, coloured as the sweep: within a step of any offset
    # Its scales, times the radius ratio: the radii of partial captures are ~30 % off.
    site_place_scales: tuple[float, ...] = (0.75, 1.0, 1.33)
    site_place_top: int = 6  # distinct placements refined by the anchor ICP
    climb_top: int = 2  # best placed starts of a doubtful site answer that climb the score (_climb), beside its best
    climb_rounds: int = 6  # step halvings of each climb
    climb_turn_deg: float = 4.0  # its first turn
    climb_shift: float = 0.1  # its first shift, fraction of the target radius
    climb_scale: float = 0.08  # its first log-scale step
    refine_cloud: int = 400_000  # Gaussians per capture the refinement runs on at most: trees and tables stay bounded
    # translation_sweep; lengths are fractions of the target's anchor radius.
    sweep_top: int = 3  # the search's best distinct rotations slid over the target
    sweep_step: float = 0.15  # lattice step, below the truncation so no offset falls between
    sweep_truncation: float = 0.3  # truncation of the offsets' score
    sweep_points: int = 128  # source anchors scored per offset
    sweep_keep: int = 2  # best distinct offsets per rotation refined by the anchor ICP
    sweep_icp: int = 60  # iterations of that ICP


@dataclass
class Structure:
    """What the scene test saw on one model."""

    shell_planes: int
    shell_weight: float
    parts: int  # separate small things inside the shell
    parts_weight: float
    planes: list[dict]

    gaussians: int = 0
    site: Site | None = None  # the site test, where the shell test failed
    options: SceneOptions = field(default_factory=SceneOptions, repr=False)  # the thresholds the test used

    @property
    def shell(self) -> bool:
        o = self.options
        return self.shell_planes >= o.shell_planes and self.shell_weight >= o.shell_weight

    @property
    def is_room(self) -> bool:
        o = self.options
        things_inside = self.parts >= o.content_parts and self.parts_weight >= o.content_weight
        return self.shell and (things_inside or self.gaussians >= o.scene_gaussians)

    @property
    def is_site(self) -> bool:
        return not self.is_room and self.site is not None and self.site.is_site

    @property
    def is_scene(self) -> bool:
        return self.is_room or self.is_site

    def to_dict(self) -> dict:
        out = {
            "shell_planes": self.shell_planes,
            "shell_weight": round(self.shell_weight, 4),
            "parts": self.parts,
            "parts_weight": round(self.parts_weight, 4),
            "gaussians": self.gaussians,
            "is_scene": self.is_scene,
            "kind": "room" if self.is_room else "site" if self.is_site else None,
        }
        if self.site is not None:
            out["site"] = self.site.to_dict()
        return out


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


def scene_structure(
    anchors: robust.Anchors, seed: int = 0, gaussians: int = 0, options: SceneOptions | None = None
) -> Structure:
    """Shell planes and their weight, then the separate parts inside them (module docstring)."""
    o = options or SceneOptions()
    pts = anchors.points
    w = anchors.weights / anchors.weights.sum()
    extent = float(np.max(np.ptp(pts, axis=0)))
    # The anchor voxel. Anchors are voxel means, so those of a plane lie on it to within
    # noise: a quarter voxel separates them from things standing on it.
    voxel = extent / np.sqrt(len(pts))
    band = 0.25 * voxel
    rng = np.random.default_rng(seed)
    # Anchors sit on a voxel lattice, so any plane through a row of voxels holds a line of
    # them on every surface it crosses; a plane's inliers must also face its way.
    normals = _anchor_normals(pts)
    free = np.ones(len(pts), bool)
    planes: list[dict] = []
    for _ in range(o.max_planes):
        idx = np.flatnonzero(free)
        if len(idx) < 50:
            break
        normal, offset, inliers = _ransac_plane(pts[idx], normals[idx], w[idx], band, rng, o.facing_deg)
        if normal is None:
            break
        rows = idx[inliers]
        share = float(w[rows].sum())
        if share < 0.5 * o.shell_share:
            break
        free[rows] = False
        # Voxel anchors along an edge (a wall's bottom row of voxels holds floor too) form
        # a second layer beside the plane: it belongs to the plane found first.
        twin = next((p for p in planes if _same_plane(p, normal, offset, 2 * voxel, o.facing_deg)), None)
        if twin is not None:
            twin["share"] += share
            twin["shell"] = _is_shell(twin["share"], twin["span"], twin["outside"], o)
            continue
        signed = pts @ normal - offset
        beyond_pos, beyond_neg = float(w[signed > 2 * voxel].sum()), float(w[signed < -2 * voxel].sum())
        if beyond_neg > beyond_pos:  # orient the normal inwards (towards the model's weight)
            normal, offset = -normal, -offset
            beyond_pos, beyond_neg = beyond_neg, beyond_pos
        span = _inplane_span(pts[rows], normal) / extent
        planes.append(
            {
                "normal": normal,
                "offset": offset,
                "share": share,
                "span": span,
                "outside": beyond_neg,
                "shell": _is_shell(share, span, beyond_neg, o),
            }
        )
    shell = [p for p in planes if p["shell"]]
    on_shell = np.zeros(len(pts), bool)
    for p in shell:
        on_shell |= np.abs(pts @ p["normal"] - p["offset"]) <= voxel
    shell_weight = float(w[on_shell].sum()) if shell else 0.0
    parts, parts_weight = 0, 0.0
    if len(shell) >= o.shell_planes and shell_weight >= o.shell_weight:  # else decided: skip the parts
        parts, parts_weight = _inner_parts(pts, w, ~on_shell, shell, voxel, extent, o)
    out = Structure(len(shell), shell_weight, parts, parts_weight, planes, gaussians, options=o)
    if not out.is_room:
        out.site = site_structure(pts, w, normals, voxel, extent, gaussians, o)
    return out


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
    sky_share of its columns (no other up- or down-facing surface above it: an object's
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
        covered[col[facing & (rel > band)]] = True  # another horizontal surface above the ground
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


def _inner_parts(pts, w, rest_mask, shell, voxel: float, extent: float, o: SceneOptions) -> tuple[int, float]:
    """Separate things inside the shell: connected groups of the anchors off the shell
    planes (linked within 1.5 voxels), each holding at least part_weight of the weight,
    with a body (at least a voxel thick) and at most part_size of the extent long, with
    its centre a voxel inside every shell plane."""
    rest = np.flatnonzero(rest_mask)
    if len(rest) < 2:
        return 0, 0.0
    x, wx = pts[rest], w[rest]
    tree = cKDTree(x)
    n, label = connected_components(tree.sparse_distance_matrix(tree, 1.5 * voxel, output_type="coo_matrix"))
    weight = np.bincount(label, wx, n)
    centre = np.stack([np.bincount(label, wx * x[:, k], n) for k in range(3)], 1) / np.maximum(weight, 1e-300)[:, None]
    inside = np.ones(n, bool)
    for p in shell:
        inside &= centre @ p["normal"] - p["offset"] >= voxel
    part = np.zeros(n, bool)
    for k in np.flatnonzero((weight >= o.part_weight) & inside):
        y = x[label == k]
        if len(y) < 4:
            continue
        # Principal extents (4 sigma ~ the full width of a uniform spread): a thing has a
        # body; what is left of a plane's band after the shell is removed is a sliver.
        sigma = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(y.T)), 0.0))
        part[k] = 4 * sigma[0] >= voxel and 4 * sigma[2] <= o.part_size * extent
    return int(part.sum()), float(weight[part].sum())


def _is_shell(share: float, span: float, outside: float, o: SceneOptions) -> bool:
    return bool(share >= o.shell_share and span >= o.shell_span and outside <= o.outside_share)


def _same_plane(plane: dict, normal: np.ndarray, offset: float, gap: float, facing_deg: float) -> bool:
    cos = float(plane["normal"] @ normal)
    return abs(cos) >= np.cos(np.radians(facing_deg)) and abs(plane["offset"] - np.sign(cos) * offset) <= gap


def _anchor_normals(pts: np.ndarray, k: int = 10) -> np.ndarray:
    """Unit normal per anchor: the least-variance axis of its k nearest anchors."""
    _, nn = cKDTree(pts).query(pts, k=min(k, len(pts)))
    nb = pts[nn] - pts[nn].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return vecs[:, :, 0]


def _ransac_plane(
    pts: np.ndarray,
    normals: np.ndarray,
    w: np.ndarray,
    band: float,
    rng: np.random.Generator,
    facing_deg: float,
    trials: int = 128,
):
    """The plane through an anchor, along its normal, holding the most anchor weight
    within `band` among anchors facing its way (within facing_deg), refitted to those
    inliers by least squares; vectorised over all trials."""
    if len(pts) < 3:
        return None, 0.0, None
    seeds = rng.integers(0, len(pts), trials)
    n, a = normals[seeds], pts[seeds]
    cos = np.cos(np.radians(facing_deg))
    inl = (np.abs(pts @ n.T - np.sum(n * a, axis=1)) <= band) & (np.abs(normals @ n.T) >= cos)
    inliers = inl[:, int(np.argmax(w @ inl))]
    # A seed's normal is a few degrees off, which over the model's extent leaves the band:
    # refit on the facing anchors within a voxel (4 bands), then count within the band.
    for grow in (4.0, 2.0, 1.0):
        if inliers.sum() < 3:
            return None, 0.0, None
        # Unweighted: an anchor's weight counts Gaussians, and the heaviest ones near a
        # floor are the furniture standing on it, whose voxel means sit above it.
        centre = pts[inliers].mean(0)
        _, _, vt = np.linalg.svd(pts[inliers] - centre, full_matrices=False)
        normal = vt[2]
        offset = float(normal @ centre)
        inliers = (np.abs(pts @ normal - offset) <= grow * band) & (np.abs(normals @ normal) >= cos)
    if inliers.sum() < 3:
        return None, 0.0, None
    return normal, offset, inliers


def _inplane_span(pts: np.ndarray, normal: np.ndarray) -> float:
    """Longer in-plane extent of a plane's inliers (5th to 95th percentile: robust to strays)."""
    if len(pts) < 3:
        return 0.0
    centred = pts - pts.mean(0)
    flat = centred - np.outer(centred @ normal, normal)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    along = flat @ vt[0]
    lo, hi = np.percentile(along, [5, 95])
    return float(hi - lo)


# --- the choice -------------------------------------------------------------------------


@dataclass
class SceneChoice:
    """Whether align() takes the scene path, and why (result metrics["scene"])."""

    run: bool
    reason: str
    source: Structure | None = None
    target: Structure | None = None

    def to_dict(self) -> dict:
        out: dict = {"ran": self.run, "reason": self.reason}
        if self.source is not None and self.target is not None:
            out["test"] = {"source": self.source.to_dict(), "target": self.target.to_dict()}
        return out


def check_models(source: GaussianModel, target: GaussianModel) -> None:
    """The pipeline's input checks (AlignmentError with the reason)."""
    try:
        source.validate("source")
        target.validate("target")
    except ModelError as exc:
        raise AlignmentError(str(exc)) from None
    for name, m in (("source", source), ("target", target)):
        if len(m) < 3:
            raise AlignmentError(f"{name} has {len(m)} Gaussians; at least 3 are needed")


def choose(
    source: GaussianModel,
    target: GaussianModel,
    mode: str,
    eligible: bool,
    anchor_count: int,
    seed: int = 0,
    options: SceneOptions | None = None,
):
    """The scene test under `mode` (auto/on/off). eligible: the object path would run its
    robust global search (no learned features); auto only tests then."""
    if mode == "off":
        return SceneChoice(False, "scene=off")
    if mode == "on":
        return SceneChoice(True, "scene=on")
    if not eligible:
        return SceneChoice(False, "auto: learned features or a non-global search requested")
    check_models(source, target)
    # scene_anchors, not robust.anchors: the same summary, many times faster at millions
    # of Gaussians; the object path makes its own.
    o = options or SceneOptions()
    s, t = (scene_structure(_test_anchors(m, anchor_count, seed, o), seed, len(m), o) for m in (source, target))
    if s.is_room and t.is_room:
        reason = "auto: both models are shells of large planes with things inside (scene test passed)"
    elif s.is_scene and t.is_scene:
        reason = "auto: both models are open grounds with things standing on them (site test passed)"
    else:
        which = [name for name, st in (("source", s), ("target", t)) if not st.is_scene]
        reason = f"auto: the {' and '.join(which)} failed the scene test"
    return SceneChoice(s.is_scene and t.is_scene, reason, s, t)


def _test_anchors(model: GaussianModel, anchor_count: int, seed: int, o: SceneOptions) -> robust.Anchors:
    """The test's anchors, from at most test_sample Gaussians drawn at random: the test
    costs the same at any size, and anchors of a few thousand voxels do not change."""
    if len(model) > o.test_sample:
        model = model.subset(np.sort(np.random.default_rng(seed).choice(len(model), o.test_sample, replace=False)))
    return scene_anchors(model, test_anchor_count(len(model), anchor_count, o), seed, o)


def test_anchor_count(gaussians: int, anchor_count: int, options: SceneOptions | None = None) -> int:
    """The object path's anchor count, but at least test_density Gaussians per anchor: the
    test follows surfaces through neighbouring anchors, and a voxel of one or two
    Gaussians leaves holes that break a surface into fragments."""
    return int(max(min(anchor_count, gaussians // (options or SceneOptions()).test_density), 100))


# --- the scene path ---------------------------------------------------------------------


def scene_anchors(
    model: GaussianModel, count: int | None = None, seed: int = 0, options: SceneOptions | None = None
) -> robust.Anchors:
    """robust.anchors' summary (robust.voxel_anchors), with the voxel size searched on a
    sample: occupancy at a few thousand voxels is the same on 200k Gaussians as on millions,
    and one pass over all of them follows. count: the anchors sought (None: scene_anchors)."""
    o = options or SceneOptions()
    count = o.scene_anchors if count is None else count
    kept = robust.floater_mask(model)
    x = model.means[kept].astype(np.float64)
    lo = x.min(0)
    extent = float(np.max(x.max(0) - lo))
    if not extent > 0:
        raise AlignmentError("all Gaussians coincide; the model has no extent to align")
    voxel = extent / np.sqrt(count)
    probe = (
        x if len(x) <= o.voxel_probe else x[np.random.default_rng(seed).choice(len(x), o.voxel_probe, replace=False)]
    )
    for _ in range(4):
        _, counts = robust.voxelise(probe, lo, voxel)
        if 0.7 * count <= len(counts) <= 1.4 * count or len(counts) >= 0.9 * len(probe):
            break
        voxel *= np.sqrt(len(counts) / count)
    inverse, counts = robust.voxelise(x, lo, voxel)
    return robust.voxel_anchors(model, kept, x, inverse, counts, robust.solid_voxels(counts))


def align_scene(
    source: GaussianModel,
    target: GaussianModel,
    opts,
    choice: SceneChoice,
    progress: Progress | None = None,
):
    """The scene path (module docstring): anchors, global search without frame
    relabellings, trimmed refinement on thinned full-resolution clouds, verdict; by the
    criteria in force (opts.criteria)."""
    from gsa.align.result import AlignmentResult

    k = opts.criteria
    o = k.scene
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    check_models(source, target)
    _report(progress, "features", 0.0)
    t = time.perf_counter()
    count = max(opts.anchor_count, o.scene_anchors)
    dst = scene_anchors(target, count, opts.seed, o)
    src = robust.match_exposure(scene_anchors(source, count, opts.seed, o), dst, k.pose.palette)
    timings["anchors"] = time.perf_counter() - t
    _report(progress, "features", 1.0)

    _report(progress, "hypotheses", 0.0)
    t = time.perf_counter()
    sites = _sites(src, dst, o)
    if sites is None:
        search = robust.global_search(
            src,
            dst,
            None,
            k.search_options(opts.search_rotations, opts.seed),
            widen_if=lambda first: robust.verdict(first.best, first, criteria=k.verdict)["doubtful"],
        )
        search = translation_sweep(src, dst, search, opts.seed, o)
    else:
        search = site_search(src, dst, *sites, opts.seed, o, k.search_options(0, opts.seed), k.verdict)
    timings["hypotheses"] = time.perf_counter() - t
    _report(progress, "hypotheses", 1.0)
    scored = [c.to_dict(search.best.transform) | {"chosen": c is search.best} for c in search.candidates]

    t = time.perf_counter()
    rng = np.random.default_rng(opts.seed)
    p_idx, q_idx = (_thinned(a.kept, o.refine_cloud, rng) for a in (src, dst))
    p_cloud, q_cloud = source.means[p_idx].astype(np.float64), target.means[q_idx].astype(np.float64)
    p_tree, q_tree = cKDTree(p_cloud), cKDTree(q_cloud)
    half = opts.refine_points // 2
    p = p_cloud[robust.subsample(rng, len(p_cloud), half)]
    q_rows = robust.subsample(rng, len(q_cloud), half)
    q = q_cloud[q_rows]
    normals, flatness = target.surface_normals(q_idx)
    start = search.best if sites is None else _site_polish(src, dst, search, rng)
    transform, history = robust.refine(
        p,
        q,
        p_tree,
        q_tree,
        start.transform,
        opts.refine_iterations,
        target_normals=(normals, flatness, normals[q_rows], flatness[q_rows]),
        criteria=k.refinement(rigid=True),  # two captures of one place are never deformed copies
    )
    refine_kept = True
    if sites is not None:
        # On a site whose Gaussians are far denser in one part (an SfM garden's table) the
        # full-resolution refinement can slide to a pose that the anchors - the whole
        # site, in colour - score clearly lower: the start is kept then.
        refined = robust.score_pose(src, dst, transform, "refined", search.colour_weight, search.criteria)
        if refined.score < start.score - search.criteria.score_tie:
            transform, refine_kept = start.transform, False
    coarse = CoarseResult(
        transform=transform,
        iterations=len(history),
        converged=len(history) < opts.refine_iterations,
        history=history,
        matched=history[-1]["matched"] if history else 0,
        seconds=time.perf_counter() - t,
    )
    timings["coarse"] = time.perf_counter() - t
    _report(progress, "coarse", 1.0)

    t = time.perf_counter()
    metrics = _inliers(transform, p, q, p_tree, q_tree, opts.inlier_threshold * dst.radius)
    final = robust.score_pose(src, dst, transform, "final", search.colour_weight, search.criteria)
    coincide = robust.coincidence(p, q, p_tree, q_tree, transform, criteria=k.refine)
    metrics.update(robust.verdict(final, search, coincide, k.verdict, offer_always=opts.alternatives == "always"))
    metrics["hypothesis"] = search.best.origin
    metrics["scene"] = choice.to_dict() | {
        "kind": "room" if sites is None else "site",
        "refinement_kept": refine_kept,
        "anchors": [len(src), len(dst)],
        "refine_cloud": [len(p_cloud), len(q_cloud)],
        "exposure_gains": list(src.colour_gain),  # linear RGB gains: the source's colours in the target's exposure
    }
    timings["metrics"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    _report(progress, "done", 1.0)
    return AlignmentResult(
        transform=transform,
        coarse=coarse,
        features="none",
        stages=("coarse",),
        metrics=metrics,
        timings=timings,
        hypotheses=scored,
    )


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
    that answer is doubtful, placed starts and climbs join (below). search_options: the
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
    result = robust.decide(
        robust.dedupe([_pose_gain_score(src, dst, c, w, k) for c in search.candidates], k), w, None, k
    )
    if not robust.verdict(result.best, result, criteria=verdict)["doubtful"]:
        return result
    # A doubtful answer: starts that trust no centroid join (_placed), and the best placed
    # starts - before the anchors' ICP moves them and the dedup merges them into a pose
    # that scores higher there - climb the score, as does the best pose. Both compare
    # chromaticity alone (_chroma): where the palettes did not tell the exposure apart,
    # the full colours disagree at the truth itself.
    starts, refined = _placed(_chroma(s_thin), _chroma(d_thin), src_site, dst_site, search, rng, o)
    scored = [_pose_gain_score(src, dst, c, w, k) for c in starts + refined]
    result = robust.decide(robust.dedupe(result.candidates + scored, k), w, None, k)
    climbers = [result.best, *starts[: o.climb_top]]  # the placement's own order: by chromaticity
    src_chroma, dst_chroma = _chroma(src), _chroma(dst)
    climbed = [_pose_gain_score(src, dst, _climb(src_chroma, dst_chroma, c, w, k, o), w, k) for c in climbers]
    return robust.decide(robust.dedupe(climbed + result.candidates, k), w, None, k)


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
    starts, refined = [], []
    for r, s_, t_ in placements:
        init = Sim3(s_, r, t_ - s_ * r @ src.center)
        pose = robust.bidirectional_icp(src, dst, init, *rows, o.sweep_icp, search.colour_weight, k)
        starts.append(robust.Candidate(init, "placed"))
        refined.append(robust.score_pose(src, dst, pose, "placed", search.colour_weight, k))
    return starts, refined


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
    d, j = dst.tree.query(cand.transform.apply(src.points), k=1)
    near = d <= criteria.colour_pair_distance * dst.radius
    if near.sum() < 50:
        return plain
    lin_s = srgb_to_linear(src.rgb)
    lin_d = srgb_to_linear(dst.rgb)
    ratio = np.median(lin_d[j[near]] / np.maximum(lin_s[near], 1e-4), axis=0)
    limit = criteria.palette.max_exposure_gain
    gain = np.clip(ratio, 1 / limit, limit)
    shifted = replace(src, lab=linear_to_lab(np.clip(lin_s * gain, 0.0, 1.0)))
    gained = robust.score_pose(shifted, dst, cand.transform, cand.origin, w_colour, criteria)
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
    rows = np.sort(np.concatenate([rest, rng.choice(g, keep, replace=False)]))
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


def translation_sweep(
    src: robust.Anchors,
    dst: robust.Anchors,
    search: robust.SearchResult,
    seed: int = 0,
    options: SceneOptions | None = None,
) -> robust.SearchResult:
    """The search's best distinct rotations, each slid over a lattice of translations
    covering the target, then refined; the best of all poses wins.

    The object search places a rotation by centres and radii and corrects it within
    about half a radius; two captures of a room overlapping in 50-80 % have centroids a
    good part of the room apart, and their planes (floor, walls) let a pose slide along
    them: the right rotation then ends a metre or two off, scoring low in colour. Here
    the source's mapped centre runs over the target's box grown by half its radius, in
    steps of sweep_step radii; each offset is scored one way (source anchors onto the
    target's nearest-anchor grid, truncated at sweep_truncation radii, with the colour
    term of robust's score), and the sweep_keep best distinct offsets per rotation run
    the anchor ICP and robust's score like the search's own candidates."""
    o = options or SceneOptions()
    crit = search.criteria
    rng = np.random.default_rng(seed)
    w_colour = search.colour_weight
    tau = o.sweep_truncation * dst.radius
    grid = robust.NearestGrid(dst.points, 0.25 * tau, tau)
    rows = robust.subsample(rng, len(src), o.sweep_points)
    p, p_lab = src.points[rows] - src.center, src.lab[rows]
    step = o.sweep_step * dst.radius
    lo, hi = dst.points.min(0) - 0.5 * dst.radius, dst.points.max(0) + 0.5 * dst.radius
    axes = [np.arange(a, b + step, step) for a, b in zip(lo, hi)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    src_rows, dst_rows = robust.subsample(rng, len(src), 800), robust.subsample(rng, len(dst), 800)
    found = list(search.candidates)
    for cand in search.candidates[: o.sweep_top]:
        u = cand.transform.scale * p @ cand.transform.rotation.T
        score = np.empty(len(centres))
        for a in range(0, len(centres), 1024):
            c = centres[a : a + 1024]
            idx, d = grid.lookup(c[:, None, :] + u[None])
            closeness = np.where(idx >= 0, 1.0 - np.minimum(d, tau) / tau, 0.0)
            if w_colour > 0:
                de2 = np.sum((p_lab[None] - dst.lab[np.maximum(idx, 0)]) ** 2, axis=-1)
                closeness *= 1.0 - 2.0 * w_colour * (1.0 - np.exp(-0.5 * de2 / crit.colour_sigma**2))
            score[a : a + 1024] = closeness.mean(axis=1)
        kept: list[np.ndarray] = []
        for k in np.argsort(-score):
            if len(kept) == o.sweep_keep:
                break
            if all(np.linalg.norm(centres[k] - o) > 3 * step for o in kept):
                kept.append(centres[k])
        for centre in kept:
            r, sc = cand.transform.rotation, cand.transform.scale
            init = Sim3(sc, r, centre - sc * r @ src.center)
            pose = robust.bidirectional_icp(src, dst, init, src_rows, dst_rows, o.sweep_icp, w_colour, crit)
            found.append(robust.score_pose(src, dst, pose, "sweep", w_colour, crit))
    # One per pose (robust.dedupe): a slid copy of a pose is that pose.
    return robust.decide(robust.dedupe(found, crit), w_colour, None, crit)


def _report(progress: Progress | None, stage: str, fraction: float) -> None:
    if progress is not None:
        progress(stage, fraction)


def _thinned(kept: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    """Rows of at most `limit` of the floater-free Gaussians, uniformly at random: a
    fixed-size cloud whatever the capture's size, with the full-resolution positions."""
    idx = np.flatnonzero(kept)
    if len(idx) > limit:
        idx = np.sort(rng.choice(idx, limit, replace=False))
    return idx


def _inliers(transform: Sim3, p, q, p_tree: cKDTree, q_tree: cKDTree, threshold: float) -> dict:
    """GT-free inlier fractions both ways (on the refinement's samples) and the forward
    inliers' RMS residual, in target units."""
    d_f, _ = q_tree.query(transform.apply(p), workers=-1)
    d_r, _ = p_tree.query(transform.inverse().apply(q), workers=-1)
    d_r = d_r * transform.scale
    fwd, rev = d_f <= threshold, d_r <= threshold
    return {
        "inlier_fraction": float(0.5 * (fwd.mean() + rev.mean())),
        "inlier_fraction_forward": float(fwd.mean()),
        "inlier_fraction_reverse": float(rev.mean()),
        "rms_residual": float(np.sqrt(np.mean(d_f[fwd] ** 2))) if fwd.any() else float("inf"),
        "inlier_threshold": threshold,
    }
