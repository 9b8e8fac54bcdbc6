"""A model's dominant surface-normal frame ("Manhattan" frame) and the 24 relabellings between
two such frames.

Man-made objects are built along three orthogonal directions: flat tops, sides, fronts and
bases. The directions most of the surface faces along are a frame that moves with the object,
whatever its proportions, where principal axes (moments) swap or tilt once proportions differ.
Between two instances of one category the true rotation is then one of the 24 ways of mapping
one frame's axes onto the other's (docs/benchmarks.md, "Dominant-normal frames"): which of the
24 is the cross-instance question that remains, but each candidate is exact, where the ICP
between two different shapes drifts by 5-20 degrees.

Normals come from the Gaussians themselves: a surface Gaussian is flat, its shortest axis is
its normal, and its two longer axes give its area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa.canonical import SIGNED_PERMUTATIONS
from gsa.geometry import rotation_distance_deg
from gsa.model import GaussianModel
from gsa.render import steps
from gsa.sim3 import Sim3

# Coarse search: directions on a half sphere (a normal and its opposite count alike), each
# counting the surface within COARSE_DEG of it; then the frame is refitted to the normals
# within each of REFINE_DEG of an axis (a least-squares rotation, tightening).
COARSE_DIRECTIONS = 1000
COARSE_DEG = 8.0
REFINE_DEG = (10.0, 6.0, 4.0, 4.0)
SUPPORT_DEG = 6.0
MAX_NORMALS = 10_000  # normals sampled (by area) for the search: the frame is a few numbers
# How alike two models look under a relabelling (relabelling_agreement): each model's surface
# area on a MASS_CELLS^3 grid in its own frame, centred on its centroid and spanning MASS_REACH
# standard deviations per axis each way (so instances of other proportions compare part to
# part), blurred by MASS_BLUR cells.
MASS_CELLS = 16
MASS_REACH = 2.5
MASS_BLUR = 1.0
# How alike the models' parts look under a relabelling (feature_agreement): the lifted semantic
# features on a coarser FEATURE_CELLS^3 grid in the same coordinates (features are sparser than
# surface: only the Gaussians the views saw), blurred by FEATURE_BLUR cells, each cell's mean
# feature direction compared (a cell is a part, whatever its share of the surface).
FEATURE_CELLS = 6
FEATURE_BLUR = 0.7
# A signed permutation of a model's frame is one of its own symmetries (self_relabellings) when
# it moves a SELF_SAMPLE-point sample of the surface, turned about the surface's centroid, by at
# most SELF_SPACINGS of the surface's own sampling spacing (mean distance to the surface): on
# category-real meshes the symmetric turns moved 1.0-1.3 spacings, every other one 2.2 or more.
SELF_SAMPLE = 4000
SELF_SPACINGS = 1.5


@dataclass(frozen=True)
class NormalFrame:
    axes: np.ndarray  # (3, 3) rows: the dominant normal directions, right-handed
    support: float  # share of the surface area whose normal is within SUPPORT_DEG of an axis


def surface_normals(model: GaussianModel) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) unit normals (each Gaussian's shortest axis) and (N,) area weights summing to 1,
    of the opaque Gaussians (floaters left out)."""
    keep = _opaque(model)
    normals, _ = model.surface_normals(keep)
    return normals, _area_weights(model, keep)


def _opaque(model: GaussianModel) -> np.ndarray:
    """The surface Gaussians (floaters are faint); all of them where fewer than 3 are opaque."""
    keep = model.opacities > 0.5
    return keep if keep.sum() >= 3 else np.ones(len(model), bool)


def _area_weights(model: GaussianModel, keep: np.ndarray) -> np.ndarray:
    """The kept Gaussians' areas (their two longer axes), summing to 1."""
    scales = np.exp(np.clip(np.asarray(model.log_scales[keep], np.float64), -30, 30))
    ordered = np.sort(scales, axis=1)
    area = ordered[:, 1] * ordered[:, 2]
    total = area.sum()
    return area / total if np.isfinite(total) and total > 0 else np.full(len(area), 1.0 / len(area))


def manhattan_frame(model: GaussianModel, seed: int = 0) -> NormalFrame:
    """The frame of the model's dominant normal directions (module docstring)."""
    normals, weights = surface_normals(model)
    if len(normals) > MAX_NORMALS:
        rows = np.random.default_rng(seed).choice(len(normals), MAX_NORMALS, replace=False, p=weights)
        normals, weights = normals[rows], np.full(MAX_NORMALS, 1.0 / MAX_NORMALS)
    return frame_of_normals(normals, weights)


def frame_of_normals(normals: np.ndarray, weights: np.ndarray) -> NormalFrame:
    """NormalFrame of (N, 3) unit normals with (N,) weights."""
    normals = np.asarray(normals, np.float64)
    weights = np.asarray(weights, np.float64)
    first = _densest(normals, weights, _half_sphere(COARSE_DIRECTIONS))
    # The second axis: the densest direction on the great circle orthogonal to the first.
    a = np.cross(first, [1.0, 0.0, 0.0] if abs(first[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(first, a)
    t = np.linspace(0.0, np.pi, 360, endpoint=False)
    second = _densest(normals, weights, np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)
    axes = np.stack([first, second, np.cross(first, second)])
    for degrees in REFINE_DEG:
        axes = _refit(normals, weights, axes, degrees)
    near = np.abs(normals @ axes.T).max(axis=1) > np.cos(np.radians(SUPPORT_DEG))
    return NormalFrame(axes, float(weights[near].sum() / max(weights.sum(), 1e-300)))


def relabellings(source: NormalFrame, target: NormalFrame) -> np.ndarray:
    """(24, 3, 3) rotations mapping the source's frame onto the target's, one per way of
    matching its signed axes."""
    return np.stack([target.axes.T @ g @ source.axes for g in SIGNED_PERMUTATIONS])


def self_relabellings(model: GaussianModel, frame: NormalFrame, seed: int = 0) -> np.ndarray:
    """(24,) bool over SIGNED_PERMUTATIONS: which of them, applied in the model's own frame,
    map its opaque surface onto itself (the identity always; a box's half turns, a vase's
    quarter turns). Two relabellings between models that differ by such a turn of either
    place the surfaces alike: the same answer."""
    from scipy.spatial import cKDTree

    keep = _opaque(model)
    weights = _area_weights(model, keep)
    surface = np.asarray(model.means[keep], np.float64)
    centred = surface - weights @ surface
    rng = np.random.default_rng(seed)
    sample = centred[rng.choice(len(centred), min(len(centred), SELF_SAMPLE), replace=False)]
    tree = cKDTree(centred)
    spacing = float(np.mean(tree.query(sample, k=2)[0][:, 1]))
    out = np.zeros(len(SIGNED_PERMUTATIONS), bool)
    for m, g in enumerate(SIGNED_PERMUTATIONS):
        turn = frame.axes.T @ g @ frame.axes
        out[m] = float(np.mean(tree.query(sample @ turn.T)[0])) <= SELF_SPACINGS * max(spacing, 1e-300)
    return out


def equivalent_relabellings(k: int, source_self: np.ndarray, target_self: np.ndarray) -> np.ndarray:
    """(24,) bool: the relabellings that place the surfaces as relabelling k does, up to a
    symmetry of either model (self_relabellings' masks): j where G_k^T G_j is one of the
    source's or G_j G_k^T one of the target's."""
    perms = np.asarray(SIGNED_PERMUTATIONS)
    source_turns = [perms[m] for m in np.flatnonzero(source_self)]
    target_turns = [perms[m] for m in np.flatnonzero(target_self)]
    g = perms[k]
    return np.array(
        [
            any(np.array_equal(g.T @ h, t) for t in source_turns)
            or any(np.array_equal(h @ g.T, t) for t in target_turns)
            for h in perms
        ]
    )


def relabelling_agreement(
    source: GaussianModel, target: GaussianModel, source_frame: NormalFrame, target_frame: NormalFrame
) -> np.ndarray:
    """(24,) cosine in [0, 1] between the target's surface-mass grid and the source's moved by
    each relabelling (in relabellings' order): 1 where the two models spread their surface alike.
    Where the frames leave the question of which relabelling open, this is the shape's answer:
    which end is heavy, where the parts sit, in proportion to each model's own spread."""
    source_coords = _spread_coords(source, source_frame)
    target_grid = _mass_grid(*_spread_coords(target, target_frame))
    points, weights = source_coords
    out = []
    for g in SIGNED_PERMUTATIONS:
        steps.step()  # a due progress report (gsa.align.pair._Repeater): 24 passes over the source
        out.append(float(np.sum(_mass_grid(points @ g.T, weights) * target_grid)))
    return np.array(out)


def feature_agreement(
    source: GaussianModel,
    target: GaussianModel,
    source_frame: NormalFrame,
    target_frame: NormalFrame,
    source_features: tuple[np.ndarray, np.ndarray],
    target_features: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """(24,) agreement of the models' lifted features under each relabelling (relabellings'
    order): each model's (points, unit features) of its Gaussians (gsa.align.semantic), gridded
    in the coordinates the surface-mass grids use (its own frame, centred on its centroid, per
    axis in standard deviations), each cell's features averaged to a direction; the score is
    the cosine of the two grids. Where the mass grids compare where the surface lies, this
    compares what lies there, part to part across proportions (a tub's taps end, a vase's
    mouth); a pretrained network's nearest-neighbour agreement between posed models compares
    parts that proportions have moved apart (docs/benchmarks.md, "Parts compared in the
    frames")."""
    source_grid = _feature_grid(_frame_coords(source, source_frame, source_features[0]), source_features[1])
    target_grid = _feature_grid(_frame_coords(target, target_frame, target_features[0]), target_features[1])
    out = []
    for g in SIGNED_PERMUTATIONS:
        steps.step()  # a due progress report (gsa.align.pair._Repeater)
        out.append(float(np.sum(_relabelled_grid(source_grid, g) * target_grid)))
    return np.array(out)


def _frame_coords(model: GaussianModel, frame: NormalFrame, points: np.ndarray) -> np.ndarray:
    """`points` in the coordinates of _spread_coords (centred on the model's opaque surface's
    centroid, per axis in MASS_REACH of its standard deviations)."""
    keep = _opaque(model)
    weights = _area_weights(model, keep)
    surface = np.asarray(model.means[keep], np.float64)
    return _standardised_in(frame, surface, weights, np.asarray(points, np.float64))


def _feature_grid(coords: np.ndarray, features: np.ndarray) -> np.ndarray:
    """(n, n, n, k) unit-norm grid of the features at coords in [-1, 1]^3, blurred, each cell's
    sum turned to a unit direction (empty cells stay 0)."""
    from scipy.ndimage import gaussian_filter

    n = FEATURE_CELLS
    features = np.asarray(features, np.float64)
    cells = np.clip(((coords + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1)
    flat = (cells[:, 0] * n + cells[:, 1]) * n + cells[:, 2]
    sums = np.stack([np.bincount(flat, features[:, c], n**3) for c in range(features.shape[1])], axis=-1)
    grid = gaussian_filter(sums.reshape(n, n, n, -1), (FEATURE_BLUR, FEATURE_BLUR, FEATURE_BLUR, 0))
    grid = grid / (np.linalg.norm(grid, axis=-1, keepdims=True) + 1e-9)
    return grid / max(float(np.linalg.norm(grid)), 1e-300)


def _relabelled_grid(grid: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The grid of points moved by the signed permutation g (x -> g x): its axis i is the
    source's axis j where g[i, j] = ±1, reversed where -1 (the cells are symmetric about 0)."""
    axes = [int(np.flatnonzero(g[i])[0]) for i in range(3)]
    out = np.transpose(grid, axes + list(range(3, grid.ndim)))
    for i in range(3):
        if g[i, axes[i]] < 0:
            out = np.flip(out, i)
    return out


def _spread_coords(model: GaussianModel, frame: NormalFrame) -> tuple[np.ndarray, np.ndarray]:
    """The opaque Gaussians' centres in the frame, centred on the area-weighted centroid and
    divided per axis by MASS_REACH standard deviations, and their area weights."""
    keep = _opaque(model)
    weights = _area_weights(model, keep)
    points = np.asarray(model.means[keep], np.float64)
    return _standardised_in(frame, points, weights, points), weights


def _standardised_in(frame: NormalFrame, surface: np.ndarray, weights: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`points` in the frame, centred on the weighted centroid of `surface` and divided per axis
    by MASS_REACH of its standard deviations."""
    centre = weights @ surface
    spread = np.sqrt(weights @ ((surface - centre) @ frame.axes.T) ** 2)
    return ((points - centre) @ frame.axes.T) / np.maximum(MASS_REACH * spread, 1e-12)


def _mass_grid(coords: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Unit-norm blurred grid of the weights at coords in [-1, 1]^3 (outliers on the border)."""
    from scipy.ndimage import gaussian_filter

    n = MASS_CELLS
    cells = np.clip(((coords + 1.0) * 0.5 * n).astype(np.int64), 0, n - 1)
    flat = (cells[:, 0] * n + cells[:, 1]) * n + cells[:, 2]
    grid = gaussian_filter(np.bincount(flat, weights, n**3).reshape(n, n, n), MASS_BLUR)
    return grid / max(float(np.linalg.norm(grid)), 1e-300)


def _half_sphere(n: int) -> np.ndarray:
    """About n Fibonacci directions with z >= 0."""
    i = np.arange(2 * n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / (2 * n))
    azimuth = np.pi * (1.0 + 5**0.5) * i
    d = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)
    return d[d[:, 2] >= 0]


def _densest(normals: np.ndarray, weights: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The direction (either sign) the most normal weight lies within COARSE_DEG of."""
    limit = np.cos(np.radians(COARSE_DEG))
    mass = np.zeros(len(directions))
    for start in range(0, len(directions), 256):  # bounded memory: 256 x N
        block = directions[start : start + 256]
        mass[start : start + 256] = (np.abs(normals @ block.T) > limit).T.astype(np.float64) @ weights
    return directions[int(np.argmax(mass))]


def _refit(normals: np.ndarray, weights: np.ndarray, axes: np.ndarray, degrees: float) -> np.ndarray:
    """The rotation that best maps the axes onto the normals within `degrees` of them (each
    normal's sign turned towards its axis): orthogonal Procrustes."""
    proj = normals @ axes.T
    nearest = np.argmax(np.abs(proj), axis=1)
    cos = np.abs(proj[np.arange(len(nearest)), nearest])
    near = cos > np.cos(np.radians(degrees))
    if near.sum() < 3:
        return axes
    signs = np.sign(proj[near, nearest[near]])
    targets = np.eye(3)[nearest[near]] * signs[:, None]
    u, _, vt = np.linalg.svd((normals[near] * weights[near, None]).T @ targets)
    fit = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt  # normal ≈ fit @ axis
    return fit.T


def snapped(
    pose: Sim3, source: NormalFrame, target: NormalFrame, centre: np.ndarray, source_turns=()
) -> tuple[Sim3, float]:
    """`pose` with its rotation replaced by the nearest relabelling, turning about the source
    point `centre` (it stays where the pose put it; scale kept), and the turn in degrees.
    `source_turns`: rotations that map the source onto itself (a vase's spins about its axis);
    each relabelling composed with them places the surface alike, so the nearest of those is
    taken (a pose tilted 8 deg off a relabelling and turned 35 deg about the vase's axis is 8 deg
    from the frames, not 36)."""
    candidates = relabellings(source, target)
    turns = [np.eye(3), *source_turns]
    composed = np.einsum("kij,tjl->ktil", candidates, np.asarray(turns)).reshape(-1, 3, 3)
    cosine = (np.einsum("nij,ij->n", composed, pose.rotation) - 1.0) / 2.0  # trace(Aᵀ B): the angle between
    k = int(np.argmax(cosine))
    gap = rotation_distance_deg(composed[k], pose.rotation)
    return turned_onto(pose, composed[k], centre), float(gap)


def turned_onto(pose: Sim3, rotation: np.ndarray, centre: np.ndarray) -> Sim3:
    """`pose` with its rotation replaced by `rotation`, turning about the source point
    `centre` (it stays where the pose put it; scale kept)."""
    centre = np.asarray(centre, np.float64)
    return Sim3(pose.scale, rotation, pose.apply(centre) - pose.scale * rotation @ centre)


def fit_shift(
    pose: Sim3, source_points: np.ndarray, target_points: np.ndarray, reach: float, iterations: int = 8
) -> Sim3:
    """The pose's rotation and scale kept, its translation refitted to the target's nearest
    points within `reach` (an ICP that only shifts: the turn about the centre leaves a snapped
    pose's placement a little off; a one-way nearest-point scale would shrink it)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.asarray(target_points, np.float64))
    moved = pose.scale * np.asarray(source_points, np.float64) @ pose.rotation.T
    shift = pose.translation.copy()
    for _ in range(iterations):
        steps.step()  # a due progress report (gsa.align.pair._Repeater)
        dist, nearest = tree.query(moved + shift, distance_upper_bound=reach)
        near = np.isfinite(dist)
        if near.sum() < 3:
            break
        shift = shift + (tree.data[nearest[near]] - (moved[near] + shift)).mean(axis=0)
    return Sim3(pose.scale, pose.rotation, shift)
