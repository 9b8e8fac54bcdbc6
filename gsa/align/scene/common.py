"""What the room and site halves of the scene package share: the path's anchors
(scene_anchors), the anchors' normals and the parts standing apart from a shell or a
ground (both tests), and the translation sweep (both searches).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gsa.align import robust
from gsa.align.coarse import AlignmentError
from gsa.align.scene.options import SceneOptions
from gsa.model import GaussianModel
from gsa.render import steps
from gsa.sim3 import Sim3


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


def _anchor_normals(pts: np.ndarray, k: int = 10) -> np.ndarray:
    """Unit normal per anchor: the least-variance axis of its k nearest anchors."""
    _, nn = cKDTree(pts).query(pts, k=min(k, len(pts)))
    nb = pts[nn] - pts[nn].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return vecs[:, :, 0]


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
    inits: list[Sim3] = []
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
        r, sc = cand.transform.rotation, cand.transform.scale
        inits += [Sim3(sc, r, centre - sc * r @ src.center) for centre in kept]

    def refined(init: Sim3) -> robust.Candidate:
        pose = robust.bidirectional_icp(src, dst, init, src_rows, dst_rows, o.sweep_icp, w_colour, crit)
        return robust.score_pose(src, dst, pose, "sweep", w_colour, crit)

    # The ICPs are independent: run side by side where cores are free (the same poses).
    found = list(search.candidates) + steps.parallel_map(refined, inits)
    # One per pose (robust.dedupe): a slid copy of a pose is that pose.
    return robust.decide(robust.dedupe(found, crit), w_colour, None, crit)
