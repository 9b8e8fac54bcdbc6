"""The per-pair state of align()'s object path, and its stages (gsa.align.pipeline's _Pair,
split by stage).

`_Pair` holds what every stage shares about one source/target pair: the models, their
points and trees (built once), the target's features, both canonical frames, the anchors,
the sampling generator, and the readings several stages ask for (normal frames, turn
symmetries, the user's constraints, the non-floater trees). Each stage is a part of it that
reads that state:
- `pair.anchor_search` (_AnchorSearch): the robust global search on the anchors, and the
  anchors' ICP from a given pose (a user's start, a turned or swept pose);
- `pair.frame_search` (_FrameSearch): the feature path's frame hypotheses, each run
  briefly, the closest kept;
- `pair.refinement` (_Refinement): the full-resolution trimmed ICP from the search's pose,
  the feature path's coarse stage (Alg. 3) and the fine stage;
- `pair.judge` (_Judge): the GT-free verdict, the overlap reading and the quality metrics.
Every part draws from the pair's one generator, in the order align() calls them.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from gsa import manhattan
from gsa.align import guided, robust, scene
from gsa.align.choices import EXTRACTOR_MODES, Progress
from gsa.align.coarse import AlignmentError, CoarseResult, coarse_align, find_candidates, icp_refine
from gsa.align.nearest import query_workers
from gsa.align.quality import quality_metrics, reverse_distances
from gsa.align.types import AlignOptions
from gsa.canonical import CanonicalFrame, canonical_features, frame_hypotheses, model_frame, relabelling_label
from gsa.model import GaussianModel
from gsa.render import steps
from gsa.sim3 import Sim3

if TYPE_CHECKING:
    from gsa.render.cameras import Cameras

# Points per model sampled for the verdict's coincidence test (robust.coincidence).
JUDGE_POINTS = 6000


@dataclass
class _Hypothesis:
    label: str
    frame: CanonicalFrame  # the source's frame, axes re-labelled
    init: Sim3  # where the coarse stage starts


@dataclass
class _Pair:
    """Everything the stages share about one source/target pair: points, trees
    (built once), target features, frames and the sampling generator; and one part per
    stage (module docstring), built on first use."""

    source: GaussianModel
    target: GaussianModel
    opts: AlignOptions
    mode: str
    src_frame: CanonicalFrame
    dst_frame: CanonicalFrame
    src_pts: np.ndarray
    dst_pts: np.ndarray
    src_tree: cKDTree
    dst_tree: cKDTree
    dst_feat: np.ndarray
    weights: np.ndarray | None
    threshold: float  # GT-free inlier distance in target units
    rng: np.random.Generator
    src_anchors: robust.Anchors | None = None
    dst_anchors: robust.Anchors | None = None
    lifted: object | None = None  # semantic.LiftedPair, once the semantic tie-break lifted features
    local_shapes: object | None = None  # robust.matching.DescriptorPairs, once asked for (pipeline._local_shapes)

    @functools.cached_property
    def normal_frames(self) -> tuple[manhattan.NormalFrame, manhattan.NormalFrame]:
        """Both models' dominant surface-normal frames (gsa.manhattan), computed once."""
        return manhattan.manhattan_frame(self.source), manhattan.manhattan_frame(self.target)

    @functools.cached_property
    def shape_agreement(self) -> np.ndarray:
        """(24,) how alike the models spread their surface under each relabelling of their frames
        (manhattan.relabelling_agreement), computed once: the settling test and the choice both ask."""
        return manhattan.relabelling_agreement(self.source, self.target, *self.normal_frames)

    @property
    def criteria(self):
        """The criteria in force (AlignOptions.criteria): every stage reads its own from them."""
        return self.opts.criteria

    @classmethod
    def build(cls, source: GaussianModel, target: GaussianModel, opts: AlignOptions) -> _Pair:
        scene.check_models(source, target)
        mode = _feature_mode(source, target, opts.features)
        src_frame = model_frame(source)
        steps.step()  # a due progress report (_Repeater), between whole-model passes
        dst_frame = model_frame(target)
        src_pts = source.means.astype(np.float64)
        dst_pts = target.means.astype(np.float64)
        dst_feat = target.features if mode == "file" else canonical_features(dst_pts, dst_frame)
        # KD-tree builds release the GIL: waited for between reports (1.3 s each at 3M Gaussians)
        src_tree = steps.waiting(lambda: cKDTree(src_pts))
        dst_tree = steps.waiting(lambda: cKDTree(dst_pts))
        return cls(
            source=source,
            target=target,
            opts=opts,
            mode=mode,
            src_frame=src_frame,
            dst_frame=dst_frame,
            src_pts=src_pts,
            dst_pts=dst_pts,
            src_tree=src_tree,
            dst_tree=dst_tree,
            dst_feat=dst_feat,
            weights=source.opacities if opts.weight_by_opacity else None,
            threshold=opts.inlier_threshold * dst_frame.radius,
            rng=np.random.default_rng(opts.seed),
        )

    @functools.cached_property
    def dst_feat_tree(self) -> cKDTree:
        """Feature-space tree of the target (only the feature-guided stage queries it)."""
        return cKDTree(np.asarray(self.dst_feat, np.float64))

    @property
    def global_search(self) -> bool:
        if self.opts.search == "auto":
            return self.mode == "canonical" and self.opts.refine != "off"
        return self.opts.search == "global"

    def anchors(self) -> tuple[robust.Anchors, robust.Anchors]:
        if self.src_anchors is None or self.dst_anchors is None:
            self.src_anchors, self.dst_anchors = robust.match_exposure(
                robust.anchors(self.source, self.opts.anchor_count),
                robust.anchors(self.target, self.opts.anchor_count),
                self.criteria.pose.palette,
            )
        return self.src_anchors, self.dst_anchors

    @functools.cached_property
    def source_symmetries(self) -> list[np.ndarray]:
        """The source's own turn symmetries (gsa.align.guided.source_symmetries), floaters left out."""
        src, _ = self.anchors()
        return guided.source_symmetries(self.src_pts[src.kept])

    @functools.cached_property
    def spins_freely(self) -> bool:
        """Whether either model turns freely onto itself about an axis (a bottle, a vase:
        guided.source_symmetries), floaters left out: its dominant-normal frame is then any
        turn about that axis, and a right answer can lie anywhere between two relabellings."""
        return bool(self.source_symmetries) or bool(self.target_symmetries)

    @functools.cached_property
    def target_symmetries(self) -> list[np.ndarray]:
        """The target's own turn symmetries, as source_symmetries (target coordinates)."""
        _, dst = self.anchors()
        return guided.source_symmetries(self.dst_pts[dst.kept])

    def constrain(self, transform: Sim3) -> Sim3:
        """The pose brought back onto the user's up axes and scale (gsa.align.guided), pivoting
        about the source's centre."""
        return guided.constrain(transform, self.opts, self.src_frame.center)

    @functools.cached_property
    def kept_trees(self) -> tuple[cKDTree, cKDTree]:
        """KD-trees of the Gaussians that are not floaters (robust.anchors), source and target."""
        src, dst = self.anchors()
        # waited for between progress reports (steps.waiting), as the pair's own trees
        src_tree = self.src_tree if src.kept.all() else steps.waiting(lambda: cKDTree(self.src_pts[src.kept]))
        dst_tree = self.dst_tree if dst.kept.all() else steps.waiting(lambda: cKDTree(self.dst_pts[dst.kept]))
        return src_tree, dst_tree

    @property
    def refine(self) -> bool:
        return self.opts.refine == "on" or (self.opts.refine == "auto" and self.mode == "canonical")

    def stages(self) -> tuple[str, ...]:
        if self.opts.stages != ("auto",):
            return self.opts.stages
        return ("coarse",) if self.refine else ("coarse", "fine")

    def source_features(self, frame: CanonicalFrame, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        if self.mode == "file":
            return self.source.features[rows]
        return canonical_features(self.src_pts[rows], frame)

    def weights_at(self, rows: np.ndarray | slice) -> np.ndarray | None:
        return None if self.weights is None else self.weights[rows]

    @functools.cached_property
    def anchor_search(self) -> _AnchorSearch:
        return _AnchorSearch(self)

    @functools.cached_property
    def frame_search(self) -> _FrameSearch:
        return _FrameSearch(self)

    @functools.cached_property
    def refinement(self) -> _Refinement:
        return _Refinement(self)

    @functools.cached_property
    def judge(self) -> _Judge:
        return _Judge(self)


class _AnchorSearch:
    """The robust global search on the pair's floater-free anchors (gsa.align.robust), and the
    anchors' ICP from a given pose."""

    def __init__(self, pair: _Pair) -> None:
        self.pair = pair

    def search(self, progress: Progress | None) -> robust.SearchResult:
        """gsa.align.robust: global rotation search on floater-free anchors, seeded also
        with every relabelling of the two canonical frames."""
        pair = self.pair
        src, dst = pair.anchors()
        k = pair.criteria
        _report(progress, "hypotheses", 0.0)
        if pair.opts.up_axes is not None:
            # Known up axes: only turns about them (and no widened search, which would tilt).
            options = k.search_options(0, pair.opts.seed, offer_turn_axes=(tuple(pair.opts.up_axes[1]),))
            starts = guided.up_rotations(*pair.opts.up_axes, criteria=k.guidance, fronts=pair.opts.front_axes)
            result = robust.global_search(src, dst, starts, options)
            if pair.opts.front_axes is not None:
                # the turns about up that the geometry cannot tell apart: the person's front decides
                fronts = pair.opts.front_axes
                result = robust.prefer_among_tied(result, lambda c: guided.front_gap_deg(c.transform.rotation, fronts))
        else:
            options = k.search_options(pair.opts.search_rotations, pair.opts.seed)
            result = robust.global_search(
                src,
                dst,
                robust.frame_relabellings(pair.src_frame, pair.dst_frame),
                options,
                widen_if=lambda first: robust.verdict(first.best, first, criteria=k.verdict)["doubtful"],
            )
        _report(progress, "hypotheses", 1.0)
        return result

    def approach(self, start: Sim3) -> Sim3:
        """The anchors' ICP from a given pose, as the search runs it on its own starts: the
        full-resolution refinement fits the closest pairs, which converges only from within a
        degree or two, and a user's pose can be tens of degrees off."""
        pair = self.pair
        src, dst = pair.anchors()
        options = pair.criteria.search_options(pair.opts.search_rotations, pair.opts.seed)
        rng = np.random.default_rng(pair.opts.seed)
        rows = [robust.subsample(rng, len(a), options.refine_points) for a in (src, dst)]
        iterations = options.early_iterations + options.refine_iterations
        k = options.criteria
        return robust.bidirectional_icp(
            src, dst, start, *rows, iterations, robust.colour_weight(src, dst, k.palette), k
        )

    def local_start(self, start: Sim3, found: robust.SearchResult, near: Callable[[Sim3], bool]) -> Sim3:
        """Where the refinement from a user's pose starts: the best-scoring (as the search ranks)
        of the anchors' ICP from it and from it turned a little each way (guided.local_turns,
        about the source's centre), and of the search's own poses, among those still `near` it.
        One ICP from a pose 20 deg off can stop in a nearer, worse minimum; no pose far from
        the user's is ever taken."""
        pair = self.pair
        src, dst = pair.anchors()
        centre = pair.src_frame.center
        starts = [start] + [
            start.compose(Sim3(1.0, turn, centre - turn @ centre))
            for turn in guided.local_turns(pair.criteria.guidance)
        ]
        poses = [pair.constrain(self.approach(s)) for s in starts]
        poses += [pair.constrain(c.transform) for c in [*found.candidates, *found.offered]]
        kept = [p for p in poses if near(p)] or [start]
        scores = [robust.score_pose(src, dst, p, "guided", found.colour_weight, pair.criteria.pose) for p in kept]
        rank = (lambda c: c.geometry) if found.ranked_by == "geometry" else (lambda c: c.score)
        return max(scores, key=rank).transform

    def check_given(self, transform: Sim3, found: robust.SearchResult) -> robust.SearchResult:
        """The automatic search's poses, with the given one first (robust.with_given_pose)."""
        pair = self.pair
        src, dst = pair.anchors()
        given = robust.score_pose(src, dst, transform, "guided", found.colour_weight, pair.criteria.pose)
        return robust.with_given_pose(given, found)


class _FrameSearch:
    """The feature path's start: one hypothesis per plausible relabelling of the canonical
    frame (and the authors' centroid start with file features), each run briefly, the
    closest kept."""

    def __init__(self, pair: _Pair) -> None:
        self.pair = pair

    def hypotheses(self) -> list[_Hypothesis]:
        """Initialisations: the authors' centroid start when the files carry
        features, and one per plausible relabelling of the canonical frame."""
        pair = self.pair
        out = []
        if pair.mode == "file":
            out.append(_Hypothesis("centroid", pair.src_frame, _centroid_init(pair.src_frame, pair.dst_frame)))
        for g in frame_hypotheses(pair.src_frame, pair.dst_frame):
            frame = pair.src_frame.rotated(g)
            out.append(_Hypothesis(relabelling_label(g), frame, _initial_transform(frame, pair.dst_frame)))
        return out

    def select(self, hypotheses: list[_Hypothesis], progress: Progress | None) -> tuple[_Hypothesis, list[dict]]:
        """Run each hypothesis briefly on a source subsample and keep the one whose
        result brings the two models closest (no ground truth needed): score
        1 − mean(min(d, τ))/τ over forward and reverse nearest-neighbour distances d,
        τ = hypothesis_truncation × the target's RMS radius. A truncated mean distance,
        not the 3 % inlier fraction: for two different instances of a category most
        points lie farther apart than 3 % whichever way round, and that count cannot
        tell a front/back flip of a near-symmetric shape from the right pose (on the
        category protocol, docs/benchmarks.md, the count chose 180° flips, this does not)."""
        pair = self.pair
        if len(hypotheses) == 1:
            return hypotheses[0], []
        opts = pair.opts
        sub = robust.subsample(pair.rng, len(pair.source), opts.hypothesis_points)
        rev_sub = robust.subsample(pair.rng, len(pair.target), opts.hypothesis_points)
        short = opts.coarse_options(opts.hypothesis_iterations)
        scored: list[dict] = []
        best, best_score = hypotheses[0], -1.0
        for h, hyp in enumerate(hypotheses):
            entry = {"hypothesis": hyp.label, "score": 0.0}
            try:
                feats = pair.source_features(hyp.frame, sub)
                cand = find_candidates(feats, pair.dst_feat, opts.tau_f, opts.max_candidates, pair.dst_feat_tree)
                res = coarse_align(pair.src_pts[sub], pair.dst_pts, cand, hyp.init, short, pair.weights_at(sub))
                if pair.refine:
                    res = icp_refine(
                        pair.src_pts[sub], pair.dst_pts, pair.dst_tree, res.transform, short, pair.weights_at(sub)
                    )
                fwd_d, _ = pair.dst_tree.query(
                    res.transform.apply(pair.src_pts[sub]), k=1, workers=query_workers(len(sub))
                )
                rev_d = reverse_distances(res.transform, pair.dst_pts[rev_sub], pair.src_tree)
                tau = opts.hypothesis_truncation * pair.dst_frame.radius
                closeness = 1.0 - 0.5 * (np.minimum(fwd_d, tau).mean() + np.minimum(rev_d, tau).mean()) / tau
                entry.update(
                    score=float(closeness),
                    inliers_forward=float(np.mean(fwd_d <= pair.threshold)),
                    inliers_reverse=float(np.mean(rev_d <= pair.threshold)),
                )
                hyp.init = res.transform
            except AlignmentError as exc:
                entry["error"] = str(exc)
            scored.append(entry)
            if entry["score"] > best_score:
                best, best_score = hyp, entry["score"]
            _report(progress, "hypotheses", (h + 1) / len(hypotheses))
        scored[hypotheses.index(best)]["chosen"] = True
        return best, scored


class _Refinement:
    """From a start to the pair's pose: the full-resolution trimmed ICP after the global
    search, the feature path's coarse stage, and the fine (rendering) stage."""

    def __init__(self, pair: _Pair) -> None:
        self.pair = pair

    def refine_global(self, init: Sim3, progress: Progress | None) -> CoarseResult:
        """Trimmed ICP at full resolution from the search's pose, on the Gaussians that
        are not floaters, with correspondences both ways (gsa.align.robust.refine)."""
        pair = self.pair
        t0 = time.perf_counter()
        src, dst = pair.anchors()
        src_tree, dst_tree = pair.kept_trees
        half = pair.opts.refine_points // 2
        p = src_tree.data[robust.subsample(pair.rng, src_tree.n, half)]
        q_rows = robust.subsample(pair.rng, dst_tree.n, half)
        q = dst_tree.data[q_rows]
        normals, flatness = pair.target.surface_normals(slice(None) if dst.kept.all() else dst.kept)
        transform, history = robust.refine(
            p,
            q,
            src_tree,
            dst_tree,
            init,
            pair.opts.refine_iterations,
            target_normals=(normals, flatness, normals[q_rows], flatness[q_rows]),
            criteria=pair.criteria.refinement(pair.opts.rigid),
        )
        _report(progress, "coarse", 1.0)
        return CoarseResult(
            transform=transform,
            iterations=len(history),
            converged=len(history) < pair.opts.refine_iterations,
            history=history,
            matched=history[-1]["matched"] if history else 0,
            seconds=time.perf_counter() - t0,
        )

    def held(
        self, transform: Sim3, search: robust.SearchResult, turns: tuple[float, ...] = ()
    ) -> tuple[robust.Candidate, robust.Candidate, dict] | None:
        """robust.held_within_reach from `transform` (and from it turned by `turns`) on the
        pair's anchors: the held pose, `transform` as scored, and the report
        (metrics.held_within_reach); None where nothing was held."""
        pair = self.pair
        src, dst = pair.anchors()
        options = pair.criteria.search_options(pair.opts.search_rotations, pair.opts.seed)
        found = robust.held_within_reach(src, dst, transform, search.colour_weight, options, turns)
        if found is None:
            return None
        held, before = found
        report = {
            "score_before": before.score,
            "score": held.score,
            "rotation_deg": robust.rotation_offset_deg(held.transform, transform),
        }
        return held, before, report

    def held_within_reach(self, coarse: CoarseResult, search: robust.SearchResult) -> tuple[CoarseResult, dict]:
        """The refined pose, or where the fit slid off the score's peak, the anchors' ICP from
        it within its reach (held), and the metrics saying so (empty: nothing held)."""
        found = self.held(coarse.transform, search)
        if found is None:
            return coarse, {}
        held, _, report = found
        return replace(coarse, transform=held.transform), {"held_within_reach": report}

    def coarse(self, best: _Hypothesis, progress: Progress | None) -> CoarseResult:
        """Alg. 3 on (a sample of) the source, then — with canonical features —
        nearest-neighbour refinement."""
        pair = self.pair
        opts = pair.opts
        rows = robust.subsample(pair.rng, len(pair.source), opts.max_points)
        feats = pair.source_features(best.frame, rows)
        cand = find_candidates(feats, pair.dst_feat, opts.tau_f, opts.max_candidates, pair.dst_feat_tree)
        feature_stage = opts.coarse_options()
        if pair.refine:
            # With canonical features the feature stage is the global initialiser: its
            # fixed point carries the two frames' estimation error, so converging it
            # tightly is wasted work; the refinement below removes what is left.
            feature_stage.rotation_tolerance = max(feature_stage.rotation_tolerance, 1e-3)
            feature_stage.scale_tolerance = max(feature_stage.scale_tolerance, 1e-4)
        coarse = coarse_align(
            pair.src_pts[rows], pair.dst_pts, cand, best.init, feature_stage, pair.weights_at(rows), progress
        )
        if pair.refine:
            # A dense target with a sampled source is as accurate as all-to-all
            # nearest neighbours and several times cheaper.
            rows = robust.subsample(pair.rng, len(pair.source), opts.refine_points)
            refined = icp_refine(
                pair.src_pts[rows],
                pair.dst_pts,
                pair.dst_tree,
                coarse.transform,
                opts.coarse_options(opts.refine_iterations),
                pair.weights_at(rows),
                progress,
            )
            coarse = replace(
                coarse,
                transform=refined.transform,
                history=coarse.history + refined.history,
                iterations=coarse.iterations + refined.iterations,
                converged=refined.converged,
                seconds=coarse.seconds + refined.seconds,
            )
        return coarse

    def fine(self, best: _Hypothesis, init: Sim3, progress: Progress | None, cameras: Cameras | None = None):
        pair = self.pair
        from gsa.align.fine import FineOptions, fine_align  # lazy: loads torch and the renderer

        src_model, dst_model = pair.source, pair.target
        if pair.mode == "canonical":
            # Each model's own canonical frame carries its estimation error, and the
            # fine loss would pull the pose back toward that error. Give the source
            # the target's canonical features at the coarse pose instead, so the two
            # agree wherever the geometry does.
            src_model = pair.source.with_features(canonical_features(init.apply(pair.src_pts), pair.dst_frame))
            dst_model = pair.target.with_features(pair.dst_feat)
        opts = pair.opts
        return fine_align(
            src_model,
            dst_model,
            init,
            FineOptions(
                iterations=opts.fine_iterations,
                lr=opts.fine_lr,
                views=opts.fine_views,
                image_size=opts.fine_image_size,
                loss=opts.fine_loss,
                on=opts.fine_on,
                seed=opts.seed,
            ),
            cameras=cameras,
            progress=progress,
        )


class _Judge:
    """GT-free readings of a pose: the verdict (confidence, ambiguity, alternatives), the
    overlap reading and the quality metrics."""

    def __init__(self, pair: _Pair) -> None:
        self.pair = pair

    def verdict(self, transform: Sim3, search: robust.SearchResult | None, offer: bool = False) -> dict:
        """Confidence in [0, 1], ambiguity and the alternative poses (GT-free); `offer` lists
        the alternatives whatever the verdict."""
        pair = self.pair
        src, dst = pair.anchors()
        k = pair.criteria
        if search is not None:
            w_colour = search.colour_weight
        else:
            noise = 0.5 * (robust.colour_noise(src, k.pose) + robust.colour_noise(dst, k.pose))
            w_colour = robust.colour_trust(src, dst, noise, k.pose)
        coincide = self._coincidence(transform)
        offer_always = offer or pair.opts.alternatives == "always" or guided.is_guided(pair.opts)
        final = robust.score_pose(src, dst, transform, "final", w_colour, k.pose)
        out = robust.verdict(final, search, coincide, k.verdict, offer_always=offer_always)
        # the source's colours in the target's exposure and white balance
        out["colour_gain"] = list(robust.exposure_gain(src, dst))
        return out

    def unconfirmed(self, transform: Sim3, search: robust.SearchResult | None, metrics: dict) -> dict:
        """A confident answer's record (metrics, verdict's keys at `transform`) flagged where its
        overlap does not coincide (robust.overlap_unconfirmed), with the alternatives listed;
        the answer itself is kept. Only the verdict changes: the doubtful chain is for answers
        the search doubted, and it moves poses."""
        criteria = self.pair.criteria.verdict
        if metrics.get("doubtful") or not robust.overlap_unconfirmed(metrics, criteria):
            return metrics
        offered = self.verdict(transform, search, offer=True).get("alternatives")
        return metrics | {
            "confidence": min(float(metrics["confidence"]), criteria.doubt_cap),
            "doubtful": True,
            "overlap_unconfirmed": True,
            **({"alternatives": offered} if offered is not None else {}),
        }

    def _coincidence(self, transform: Sim3):
        """robust.coincidence of the posed models' surfaces (floaters left out), on JUDGE_POINTS
        of each drawn by the options' seed: (overlap estimate, coincident share) or None."""
        pair = self.pair
        src_tree, dst_tree = pair.kept_trees
        rng = np.random.default_rng(pair.opts.seed)
        p = src_tree.data[robust.subsample(rng, src_tree.n, JUDGE_POINTS)]
        q = dst_tree.data[robust.subsample(rng, dst_tree.n, JUDGE_POINTS)]
        return robust.coincidence(p, q, src_tree, dst_tree, transform, criteria=pair.criteria.refine)

    def overlap_reading(self, transform: Sim3) -> dict:
        """The verdict's overlap estimate and coincident share of a pose, as verdict() reads them."""
        coincide = self._coincidence(transform)
        return {
            "overlap_estimate": None if coincide is None else coincide[0],
            "coincident_share": None if coincide is None else coincide[1],
        }

    def quality(self, transform: Sim3, best: _Hypothesis) -> dict:
        pair = self.pair
        rows = robust.subsample(pair.rng, len(pair.source), pair.opts.max_points)
        metrics = quality_metrics(
            transform,
            pair.src_pts[rows],
            pair.dst_pts,
            pair.source_features(best.frame, rows),
            pair.dst_feat,
            pair.threshold,
            pair.src_tree,
            pair.dst_tree,
            robust.subsample(pair.rng, len(pair.target), pair.opts.max_points),
        )
        metrics["inlier_threshold"] = pair.threshold
        return metrics


def _initial_transform(src: CanonicalFrame, dst: CanonicalFrame) -> Sim3:
    """Maps the source's canonical pose onto the target's."""
    return dst.to_canonical().inverse() @ src.to_canonical()


def _centroid_init(src: CanonicalFrame, dst: CanonicalFrame) -> Sim3:
    """The authors' start (centroids matched), plus the RMS-radius scale ratio."""
    s = dst.radius / src.radius
    return Sim3(s, np.eye(3), dst.center - s * src.center)


def _feature_mode(source: GaussianModel, target: GaussianModel, requested: str) -> str:
    both = source.feature_dim > 0 and source.feature_dim == target.feature_dim
    if requested in EXTRACTOR_MODES:
        raise AlignmentError(f"features={requested!r} must be lifted first (gsa.features.prepare_pair)")
    if requested == "auto":
        # Canonical features saved in a file are coordinates in that model's own frame:
        # recompute them in frames the pipeline can relabel rather than match them as they are.
        relative = source.features_frame_relative or target.features_frame_relative
        return "file" if both and not relative else "canonical"
    if requested == "file" and not both:
        raise AlignmentError(
            f"features='file' needs both models to carry features of one dimension "
            f"(source {source.feature_dim}, target {target.feature_dim})"
        )
    return requested


def _report(progress: Progress | None, stage: str, fraction: float) -> None:
    if progress is not None:
        progress(stage, float(min(max(fraction, 0.0), 1.0)))


# A stretch of align()'s work between two reports is cut to about this (plus one step).
REPEAT_S = 0.1


class _Repeater:
    """The progress callback align() hands down: passes each report on, remembers the last, and,
    installed as the thread's step callback (gsa.render.steps.between_steps), repeats it at a
    step of the library's long loops (ICP iterations, the search's starts, the relabellings'
    scores, ...) once REPEAT_S has passed without a report, so a caller whose callback raises
    (a cancelled service job) stops within a step wherever the work is. Only the calls change:
    the same work runs on the same data."""

    def __init__(self, progress: Progress, every_s: float | None = None) -> None:
        self.progress = progress
        self.every_s = REPEAT_S if every_s is None else every_s
        self.stage: str | None = None
        self.fraction = 0.0
        self.last = time.monotonic()

    def __call__(self, stage: str, fraction: float) -> None:
        self.stage, self.fraction = stage, fraction
        self.progress(stage, fraction)
        self.last = time.monotonic()

    def step(self) -> None:
        if self.stage is not None and time.monotonic() - self.last >= self.every_s:
            self(self.stage, self.fraction)
