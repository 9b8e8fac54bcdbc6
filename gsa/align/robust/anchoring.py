"""Anchors: a floater-free, voxel-downsampled summary of a model (mean position, CIELAB
colour, weight per voxel), the nearest-anchor grid that scores poses in O(1) per point, and
how far two models' palettes agree. Tunables: `PaletteOptions` (colours) and `anchors`'
floater_voxel_share."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numba
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from gsa.colour import linear_to_lab, srgb_to_lab, srgb_to_linear
from gsa.model import GaussianModel
from gsa.render import steps

# anchors: share of occupied voxels that are a floater's (sparse) above which the voxel size
# is set by the surface's voxels alone (its default).
FLOATER_VOXEL_SHARE = 0.1


@dataclass(frozen=True)
class PaletteOptions:
    """How two models' colours are compared without a pose (colour_weight, match_exposure).
    Colour differences are CIELAB ΔE."""

    shared_delta_e: float = 8.0  # a colour of one model is "shared" when the other has one within this
    # colour_weight maps the shared fraction from shared_floor..shared_floor+shared_span onto 0..1.
    shared_floor: float = 0.5
    shared_span: float = 0.4
    # match_exposure: gains between two captures of one object stay within this factor per
    # channel (two stops of exposure), their white balance within max_white_balance (channel
    # gains' max/min: daylight against tungsten light), and are used only if they bring the
    # palettes exposure_closer closer (mean nearest-colour ΔE) and make them agree as captures
    # of one object do (exposure_explains, a shared fraction: colour_weight 0.9).
    # exposure_steps refinement steps on exposure_sample anchors converge to ~1 %.
    max_exposure_gain: float = 4.0
    max_white_balance: float = 2.5
    exposure_closer: float = 0.25
    exposure_explains: float = 0.86
    exposure_steps: int = 8
    exposure_sample: int = 512
    # a colour with any linear channel at or above this was clipped at white (anchors average
    # several Gaussians, so a clipped voxel's mean sits just under 1)
    clipped_linear: float = 0.9
    # A doubtful answer is aligned again in the exposure its own close pairs give (pose_gain,
    # gsa.align.exposure_retry) where that gain differs from the one the answer was scored under
    # (match_exposure's, or none) by more than this many stops in some channel (and stays within
    # the bounds above).
    retry_gain_stops: float = 0.25


_PALETTE = PaletteOptions()


@dataclass
class Anchors:
    """A voxel-downsampled, floater-free summary of a model."""

    points: np.ndarray  # (A, 3) float64, model units
    lab: np.ndarray  # (A, 3) CIELAB colour
    weights: np.ndarray  # (A,) Gaussians per anchor (normalised to mean 1)
    center: np.ndarray  # (3,) weighted centroid
    radius: float  # weighted RMS distance from the centroid
    kept: np.ndarray  # (N,) bool: Gaussians that are not floaters
    tree: cKDTree = field(repr=False)
    rgb: np.ndarray | None = field(default=None, repr=False)  # (A, 3) mean sRGB, before any correction
    # linear-RGB gains raising `lab` into one exposure (match_exposure; exposure_gain reads them)
    colour_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __len__(self) -> int:
        return len(self.points)


def floater_mask(model: GaussianModel) -> np.ndarray:
    """Gaussians worth trusting for geometry: opacity at least half the model's
    median (faint floaters go), the rest judged by density in `anchors`."""
    o = model.opacities
    keep = o >= 0.5 * float(np.median(o))
    return keep if keep.sum() >= 3 else np.ones(len(model), bool)


def anchors(
    model: GaussianModel, count: int = 2000, seed: int = 0, floater_voxel_share: float = FLOATER_VOXEL_SHARE
) -> Anchors:
    """Voxel-downsample the model to about `count` anchors, dropping floaters.

    The voxel size is found from the model's own extent (a surface's voxel count
    grows as size⁻²), so the same object at any scale gets comparable anchors.
    Voxels holding far fewer Gaussians than a typical surface voxel are floaters
    spread through space (an unpruned capture), not surface; where more than
    floater_voxel_share of the occupied voxels are such, the surface's voxels alone set the size."""
    pts = model.means.astype(np.float64)
    kept = floater_mask(model)
    x = pts[kept]
    lo, hi = x.min(0), x.max(0)
    extent = float(np.max(hi - lo))
    if not extent > 0:
        raise ValueError("all Gaussians coincide; the model has no extent to align")
    voxel = extent / np.sqrt(count)
    for _ in range(6):
        steps.step()  # a due progress report (gsa.align.pair._Repeater): ~0.3 s a pass at 3M
        inverse, counts = voxelise(x, lo, voxel)
        solid = solid_voxels(counts)
        # Opaque floaters each fill a voxel of their own: where they are many, counting them
        # would coarsen the surface's anchors by as many, so the surface's voxels alone set
        # the size. Where they are few, the sparse voxels are mostly thin parts and cut edges
        # of the surface itself, and every occupied voxel counts (as calibrated).
        floaters_many = np.mean(~solid) > floater_voxel_share
        occupied = int(solid.sum()) if floaters_many else len(counts)
        if 0.7 * count <= occupied <= 1.4 * count or len(counts) >= len(x) * 0.9:
            break
        voxel *= np.sqrt(occupied / count)
    return voxel_anchors(model, kept, x, inverse, counts, solid)


def voxel_anchors(
    model: GaussianModel, kept: np.ndarray, x: np.ndarray, inverse: np.ndarray, counts: np.ndarray, solid: np.ndarray
) -> Anchors:
    """The Anchors of voxelised Gaussians: x (the kept Gaussians' means) in voxels `inverse`
    holding `counts` each, of which the `solid` ones are surface. Per-voxel sums by
    bincount: at millions of Gaussians many times faster than np.add.at."""
    full_kept = kept.copy()
    full_kept[np.flatnonzero(kept)[~solid[inverse]]] = False
    rgb = model.base_colors[kept]
    n_vox = len(counts)
    points = np.stack([np.bincount(inverse, x[:, k], n_vox) for k in range(3)], 1)[solid] / counts[solid, None]
    colours = np.stack([np.bincount(inverse, rgb[:, k], n_vox) for k in range(3)], 1)[solid] / counts[solid, None]
    weights = counts[solid].astype(np.float64)
    weights /= weights.mean()
    w = weights / weights.sum()
    center = w @ points
    radius = float(np.sqrt(w @ np.sum((points - center) ** 2, axis=1)))
    if not radius > 0:
        raise ValueError("all Gaussians coincide; the model has no extent to align")
    return Anchors(points, srgb_to_lab(colours), weights, center, radius, full_kept, cKDTree(points), colours)


def solid_voxels(counts: np.ndarray) -> np.ndarray:
    """Surface voxels hold many Gaussians, a floater's voxel one or two: voxels with fewer
    than a tenth of a typical (Gaussian-weighted median) voxel's count are floaters."""
    typical = float(np.median(np.repeat(counts, counts)))
    solid = counts >= max(2.0, 0.1 * typical) if typical >= 8 else np.ones(len(counts), bool)
    return solid if solid.sum() >= 4 else np.ones(len(counts), bool)


def voxelise(x: np.ndarray, lo: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(voxel of each point, points per occupied voxel) on a grid of `voxel` cells from `lo`."""
    ijk = np.floor((x - lo) / voxel).astype(np.int64)
    span = ijk.max(0) + 1
    keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    return inverse.ravel(), counts


class NearestGrid:
    """Nearest-anchor index for every cell of a grid around a point set (exact
    Euclidean distance transform): a scoring lookup in O(1) per point, so
    thousands of candidate rotations are scored in one vectorised pass."""

    def __init__(self, points: np.ndarray, cell: float, pad: float):
        self.points = points
        self.lo = points.min(0) - pad
        self.cell = cell
        shape = np.ceil((points.max(0) + pad - self.lo) / cell).astype(int) + 1
        self.shape = shape
        ijk = np.floor((points - self.lo) / cell).astype(int)
        # int32 and the feature transform alone (no distances): a search builds two grids of
        # ~0.5M cells per job, and each byte of them is memory a fresh work horse first faults in.
        owner = np.full(tuple(shape), -1, np.int32)
        owner[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(points), dtype=np.int32)
        nearest = ndimage.distance_transform_edt(owner < 0, return_distances=False, return_indices=True)
        self.nearest_flat = owner.ravel()[np.ravel_multi_index(tuple(nearest), owner.shape).ravel()]
        self.shape = np.asarray(shape, np.int64)

    def lookup(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) points -> (nearest anchor index, distance); outside the grid: index -1, distance inf."""
        ijk = ((x - self.lo) * (1.0 / self.cell)).astype(np.int32)  # truncation = floor inside the grid
        inside = np.all((ijk >= 0) & (ijk < self.shape) & (x >= self.lo), axis=-1)
        flat = (ijk[..., 0] * self.shape[1] + ijk[..., 1]) * self.shape[2] + ijk[..., 2]
        idx = self.nearest_flat[np.where(inside, flat, 0)]
        diff = self.points[idx] - x
        d = np.sqrt(np.einsum("...i,...i->...", diff, diff))
        return np.where(inside, idx, -1), np.where(inside, d, np.inf)


def colour_weight(src: Anchors, dst: Anchors, options: PaletteOptions | None = None) -> float:
    """How far colour can be trusted to compare poses, from the colours alone (no
    pose): two captures of one object share their palette, and then colour is what
    tells a symmetric object's sides apart; two different instances (another paint)
    do not, and then only geometry counts. Fraction of each model's anchors with a
    colour the other also has (within shared_delta_e), both ways, mapped from
    [shared_floor, shared_floor + shared_span] to [0, 1]."""
    o = options or _PALETTE
    shared = _shared_fraction(src.lab, src.weights, dst.lab, dst.weights, o.shared_delta_e)
    return float(np.clip((shared - o.shared_floor) / o.shared_span, 0.0, 1.0))


def _shared_fraction(lab_a: np.ndarray, w_a: np.ndarray, lab_b: np.ndarray, w_b: np.ndarray, within: float) -> float:
    d1, _ = cKDTree(lab_b).query(lab_a, k=1)
    d2, _ = cKDTree(lab_a).query(lab_b, k=1)
    return float(0.5 * (np.average(d1 <= within, weights=w_a) + np.average(d2 <= within, weights=w_b)))


def match_exposure(src: Anchors, dst: Anchors, options: PaletteOptions | None = None) -> tuple[Anchors, Anchors]:
    """Both anchors with their colours in one exposure, corrected for an exposure or
    white-balance change between the two captures (another day, camera or auto-exposure):
    per-channel gains in linear RGB, the physical model of both, found from the palettes
    alone (no pose). Starts: no gain, the ratios of the two palettes' quantiles per channel
    and in luminance; each is refined by matching every colour to its nearest in the other
    palette. The gains are kept only if they bring the palettes markedly closer
    (exposure_closer) without sharing less of them, stay within max_exposure_gain and
    leave a plausible white balance (max_white_balance), so two differently painted
    instances keep their own colours (PaletteOptions).

    The colours are compared in the brighter capture's exposure, channel by channel, the
    darker capture's colours raised and clipped at white (in_one_exposure): a sensor clips
    what is brighter than white, so the brighter capture lost its brightest colours, and
    only the darker one, raised and clipped the same way, can be compared with them. Taking
    the source into the target's exposure instead made a brightened source's clipped whites
    grey: on an iPhone room whose source half was a stop brighter (37 % of its anchors
    clipped), no gain passed and the truth scored 0.014 against 0.163 as captured; in one
    exposure the estimated gain passes and the truth scores 0.152. exposure_gain tells the
    gain found."""
    o = options or _PALETTE
    if src.rgb is None or dst.rgb is None:
        return src, dst
    lin_s, lin_d = srgb_to_linear(src.rgb), srgb_to_linear(dst.rgb)
    src_w, dst_w = src.weights, dst.weights

    def palette_tree(lab: np.ndarray) -> cKDTree:
        # Anchors' colours cluster (a few paints), and a k-d tree over thousands of near-duplicates
        # is slow to query: a palette is kept to one colour per 0.5 ΔE cell.
        return cKDTree(np.unique(np.round(lab * 2.0), axis=0) / 2.0)

    def judge(gain: np.ndarray) -> tuple[float, float]:
        """(truncated mean nearest-colour ΔE both ways, shared fraction) in one exposure."""
        lab_s, lab_d = (linear_to_lab(c) for c in in_one_exposure(lin_s, lin_d, gain))
        d1, _ = palette_tree(lab_d).query(lab_s, k=1)
        d2, _ = palette_tree(lab_s).query(lab_d, k=1)
        cap = 2 * o.shared_delta_e
        distance = 0.5 * (
            np.average(np.minimum(d1, cap), weights=src_w) + np.average(np.minimum(d2, cap), weights=dst_w)
        )
        shared = 0.5 * (
            np.average(d1 <= o.shared_delta_e, weights=src_w) + np.average(d2 <= o.shared_delta_e, weights=dst_w)
        )
        return float(distance), float(shared)

    base_distance, base_shared = judge(np.ones(3))
    q = np.array([0.25, 0.5, 0.75, 0.9])
    qs = np.stack([_weighted_quantiles(lin_s[:, c], src_w, q) for c in range(3)], 1)
    qd = np.stack([_weighted_quantiles(lin_d[:, c], dst_w, q) for c in range(3)], 1)
    ratio = np.median(qd / np.maximum(qs, 1e-4), axis=0)
    lum = np.array([0.2126, 0.7152, 0.0722])
    grey = float(np.median((qd @ lum) / np.maximum(qs @ lum, 1e-4)))
    best_gain, best_distance = None, (1.0 - o.exposure_closer) * base_distance
    fit = _GainFit.between(lin_s, src_w, lin_d, dst_w, o)
    limit = o.max_exposure_gain
    for start in (np.ones(3), ratio, np.full(3, grey)):
        gain = np.clip(start, 1 / limit, limit)
        for _ in range(o.exposure_steps):
            fitted = fit.step(gain)
            if fitted is None:
                break
            fitted = np.clip(fitted, 1 / limit, limit)
            moved, gain = np.max(np.abs(np.log(fitted / gain))), fitted
            if moved < 1e-3:
                break
        if gain.max() / gain.min() > o.max_white_balance:
            continue
        distance, shared = judge(gain)
        # A gain explains the difference only if under it the palettes agree as two
        # captures of one object do; two instances of other paints may come closer, never that close.
        if distance < best_distance and shared >= max(base_shared, o.exposure_explains):
            best_gain, best_distance = gain, distance
    if best_gain is None:
        return src, dst
    in_s, in_d = in_one_exposure(lin_s, lin_d, best_gain)
    raised_s, raised_d = np.maximum(best_gain, 1.0), np.maximum(1.0 / best_gain, 1.0)
    return (
        replace(src, lab=linear_to_lab(in_s), colour_gain=tuple(float(g) for g in raised_s)),
        replace(dst, lab=linear_to_lab(in_d), colour_gain=tuple(float(g) for g in raised_d)),
    )


def exposure_gain(src: Anchors, dst: Anchors) -> tuple[float, float, float]:
    """The linear-RGB gains match_exposure found between the captures: the source's colours
    in the target's exposure (1 per channel where it found none)."""
    return tuple(float(s / d) for s, d in zip(src.colour_gain, dst.colour_gain, strict=True))


def pose_gain(src: Anchors, dst: Anchors, mapped: np.ndarray, within: float, min_pairs: int = 50) -> np.ndarray | None:
    """The linear-RGB gains (the source's colours onto the target's, per channel) that a pose's
    close pairs give: the median ratio over the source anchors (`mapped`: posed into the target)
    whose nearest target anchor lies within `within` of the target's radius. None without
    colours or with fewer than min_pairs such pairs. The palettes alone (match_exposure) cannot
    always tell an exposure change (a continuum of greens, a room's greys and browns); at the
    true pose the pairs are the same surfaces and their ratio is the exposure's."""
    if src.rgb is None or dst.rgb is None:
        return None
    d, j = dst.tree.query(mapped, k=1)
    near = d <= within * dst.radius
    if near.sum() < min_pairs:
        return None
    lin_s, lin_d = srgb_to_linear(src.rgb[near]), srgb_to_linear(dst.rgb[j[near]])
    return np.median(lin_d / np.maximum(lin_s, 1e-4), axis=0)


def in_one_exposure(lin_s: np.ndarray, lin_d: np.ndarray, gain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both captures' linear colours in the brighter one's exposure per channel (`gain`: the
    source's colours in the target's exposure): the darker side raised and clipped at white."""
    return np.minimum(lin_s * np.maximum(gain, 1.0), 1.0), np.minimum(lin_d * np.maximum(1.0 / gain, 1.0), 1.0)


@dataclass
class _GainFit:
    """One step of the gains' fit: each sampled colour of one capture paired with its nearest
    colour of the other (CIELAB, both in one exposure under the current gain), pairs within
    2·shared_delta_e where neither colour is clipped there, gain per channel = Σ w·other /
    Σ w·own over them. Clipped colours (any channel at white) say only that the truth was
    brighter, and the sampled side is the capture that clipped fewer: the other's few
    unclipped colours are its darkest, too few and too dark to pair reliably."""

    lin_q: np.ndarray  # the sampled capture's unclipped colours
    w_q: np.ndarray
    lin_r: np.ndarray
    sampled_source: bool  # whether the sampled capture is the source (gains: source onto target)
    shared_delta_e: float
    clipped_linear: float

    @classmethod
    def between(cls, lin_s: np.ndarray, w_s: np.ndarray, lin_d: np.ndarray, w_d: np.ndarray, o: PaletteOptions):
        unclipped_s, unclipped_d = lin_s.max(1) < o.clipped_linear, lin_d.max(1) < o.clipped_linear
        sampled_source = unclipped_s.mean() >= unclipped_d.mean()
        lin_q, w_q, unclipped, lin_r = (
            (lin_s, w_s, unclipped_s, lin_d) if sampled_source else (lin_d, w_d, unclipped_d, lin_s)
        )
        fitted = np.flatnonzero(unclipped)  # the fit needs few colours, and only unclipped ones
        rows = fitted[subsample(np.random.default_rng(0), len(fitted), o.exposure_sample)]
        return cls(lin_q[rows], w_q[rows], lin_r, bool(sampled_source), o.shared_delta_e, o.clipped_linear)

    def step(self, gain: np.ndarray) -> np.ndarray | None:
        """The gains (source onto target) the pairs under `gain` give; None where too few pair."""
        own_gain = gain if self.sampled_source else 1.0 / gain
        in_q, in_r = in_one_exposure(self.lin_q, self.lin_r, own_gain)
        d, j = cKDTree(linear_to_lab(in_r)).query(linear_to_lab(in_q), k=1)
        # clipped on either side, raised or as recorded, a colour tells no ratio
        unclipped = (in_q.max(1) < self.clipped_linear) & (in_r[j].max(1) < self.clipped_linear)
        near = (d <= 2 * self.shared_delta_e) & unclipped
        if near.sum() < 8:
            return None
        w = self.w_q[near, None]
        fitted = np.sum(w * self.lin_r[j[near]], 0) / np.maximum(np.sum(w * self.lin_q[near], 0), 1e-9)
        return fitted if self.sampled_source else 1.0 / fitted


def _weighted_quantiles(x: np.ndarray, w: np.ndarray, q: np.ndarray) -> np.ndarray:
    order = np.argsort(x)
    cum = np.cumsum(w[order])
    return x[order][np.minimum(np.searchsorted(cum, q * cum[-1]), len(x) - 1)]


@numba.njit(cache=True, inline="always")
def grid_index(x0, x1, x2, lo, inv_cell, shape):  # pragma: no cover - compiled
    """Flat cell index of a point in a NearestGrid's lattice, −1 outside it (numba)."""
    f0, f1, f2 = (x0 - lo[0]) * inv_cell, (x1 - lo[1]) * inv_cell, (x2 - lo[2]) * inv_cell
    if f0 < 0 or f1 < 0 or f2 < 0 or f0 >= shape[0] or f1 >= shape[1] or f2 >= shape[2]:
        return -1
    return (int(f0) * shape[1] + int(f1)) * shape[2] + int(f2)


def subsample(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """k sorted rows of n drawn without replacement (all n where k >= n): the one sampling
    helper of the aligner (robust, the pipeline, the scene path)."""
    return np.arange(n) if k >= n else np.sort(rng.choice(n, k, replace=False))
