"""The option and result types of `align()` (gsa.align.pipeline re-exports them):
AlignOptions, checked against the choices of gsa.align.choices, and AlignmentResult."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from gsa.align.choices import (
    EXTRACTOR_MODES,
    FEATURE_MODES,
    STAGE_CHOICES,
    ExtractorMode,
    FeatureMode,
    FineLoss,
    FineSignal,
    Progress,
    RefineMode,
    SceneMode,
    SearchMode,
    StageName,
)
from gsa.align.coarse import CoarseOptions
from gsa.align.criteria import Criteria
from gsa.align.result import AlignmentResult
from gsa.align.spec import check_option_values
from gsa.features.settings import FeatureSettings  # torch-free, so typing.get_type_hints(AlignOptions) resolves

__all__ = [
    "EXTRACTOR_MODES",
    "FEATURE_MODES",
    "STAGE_CHOICES",
    "AlignOptions",
    "AlignmentResult",
    "ExtractorMode",
    "FeatureMode",
    "FineLoss",
    "FineSignal",
    "Progress",
    "RefineMode",
    "SceneMode",
    "SearchMode",
    "StageName",
]

if TYPE_CHECKING:
    pass


@dataclass
class AlignOptions:
    """How `align()` runs. Every choice is checked when the options are made, against each
    option's one description in gsa.align.spec.OPTIONS (its help, choices, bounds, CLI flag).

    Args:
        stages: ("auto",), ("coarse",) or ("coarse", "fine"). auto: coarse+fine when the
            coarse stage ends at the feature-guided ICP (the paper's pipeline: files'
            features, or refine off), which the fine stage still improves; coarse alone after
            the nearest-neighbour refinement, which already ends below what the fine loss can
            resolve (docs/benchmarks.md "fine stage").
        features: auto, file, canonical, spheremap or dinov2. auto: the files' own features
            when both have them, else the extractor of feature_settings (the CLI reads
            GSA_FEATURES_* into them) when its weights are set, else canonical.
        feature_settings: gsa.features.FeatureSettings for spheremap/dinov2 (weights, lifting).
        tau_f: feature distance threshold τ_f of the candidate correspondences.
        coarse_iterations: iteration limit of the feature-guided stage.
        max_candidates: feature candidates kept per source Gaussian.
        weight_by_opacity: weight correspondences by the source Gaussians' opacity.
        trim: the feature-guided ICP drops matches beyond trim × the median residual
            (None: keeps all).
        refine: auto, on or off. Nearest-neighbour ICP after the feature-guided stage;
            auto: only with the weight-free canonical features (see gsa.align.coarse.icp_refine).
        hypothesis_points: ambiguous canonical frames: each hypothesis is tried on a source
            subsample of this many Gaussians.
        hypothesis_iterations: feature-stage iterations of that trial.
        refine_points: Gaussians sampled for the refinement ICP (half per side in the robust path).
        refine_iterations: iterations of the refinement ICP; cheap: cached neighbour tables
            (icp_refine, robust.refine).
        max_points: the feature stage and the quality metrics use at most this many source
            Gaussians (the authors subsample to 30k-50k); the target is always used whole.
        inlier_threshold: GT-free inlier distance, as a fraction of the target's RMS radius.
        hypothesis_truncation: hypotheses are ranked by the symmetric nearest-neighbour
            distance truncated at this fraction of the target's RMS radius (see gsa.align.pair._FrameSearch.select).
        search: auto, global or frames: the coarse initialisation with canonical features.
            "global": the robust search of gsa.align.robust (SO(3) sample + frame relabellings
            on floater-free anchors, scored by overlap and colour); "frames": one canonical
            frame per model and its plausible relabellings, then the feature-guided stage (the
            earlier default). auto: global, except with refine off, which asks for the
            feature stage alone.
        scene: auto, on or off: the scene path for rooms and sites (gsa.align.scene: more
            anchors, no frame relabellings, exposure-normalised colours, refinement on
            bounded clouds, no fine stage). auto: when both models pass the scene test (large
            bounding planes holding much of the surface, sampled finely for their extent) and
            the global search would run; on: always (learned features are then not used).
        anchor_count: anchors per model of the global search (100..20000).
        search_rotations: rotations sampled by the global search (64..20000).
        seed: seed of every random choice (subsamples, search, fine-stage cameras).
        fine_iterations: iterations of the fine stage.
        fine_views: cameras the fine stage renders from.
        fine_lr: learning rate of the fine stage.
        fine_image_size: side of the fine stage's rendered images, in pixels.
        fine_loss: smooth_l1, l1 or l2: the fine stage's image loss.
        fine_on: "features" or "colors" (paper Table 4 ablation): what the fine stage renders.

    Guidance (gsa.align.guided), for when the automatic answer is doubtful; each is optional:
        init_transform: 4×4 source → target Sim(3) to start from (a previous result, or one of
            its alternatives): only a local refinement runs from it, never a global search.
        point_pairs: ((source points), (target points)), ≥ 3 pairs of [x, y, z] in each model's
            own coordinates: closed-form Sim(3) (Umeyama; with ≥ 4 pairs one wrong pair is
            found and left out), then the same local refinement.
        up_axes: (source up, target up), one vector each in its model's coordinates: every pose
            keeps them aligned (the search turns about the up axis only).
        front_axes: (source front, target front), with up_axes: which way each model faces
            (its nose, its front door), so a nose-for-tail turn about up is ruled out: the
            search turns about up only within GuidanceCriteria.front_reach_deg of the fronts
            agreeing. Only their parts across the up axes count.
        fixed_scale: the scale s of the answer, when the user knows it.
        rigid: the two models are captures of one rigid object (two reconstructions, two
            scans), never another instance or a deformed copy: the refinement keeps its trimmed
            fit even where `criteria` opt into averaging every pair of models that coincide
            nowhere (RefineCriteria.deformable, off by default: it took partial real captures
            off their answer). The scene path always takes its pairs so.

    photo_matches: "auto" registers two reconstructions (gsa.recon.reconstruct keeps each
        one's SfM points and their SIFT descriptors, model.metadata["photo_anchors"]) by their
        photos' shared texture (gsa.align.photo) where enough matched points agree, and skips
        the geometric search then; "off" never does. Hints take precedence over it.
    learned: "auto" lets the learned canonical head (gsa.align.learned) decide a doubtful
        global-search answer where both models' canonical poses are sure; "off" never does.
    frame_snap: "auto" turns a doubtful global-search answer (and its alternatives) onto the
        nearest of the 24 relabellings of the two models' dominant surface-normal frames where
        that turn is at most 20 degrees (gsa.manhattan): across instances the refinement drifts
        off the frame both objects are built along; "off" leaves the poses as refined.
    alternatives: "doubtful" lists the poses worth picking (result.verdict.alternatives;
        result.json's metrics["alternatives"]) where the answer is doubtful or guided, an empty
        list where it is confident (the half turns offered cost three ICPs a job); "always" lists them for every answer (gsa.align.many
        weighs every edge's alternatives).
    criteria: the thresholds every stage decides by (gsa.align.criteria.Criteria: the search's
        pose criteria and counts, the refinement's, the verdict's, the guidance's, the scene
        test's and path's, the open ends', the semantic tie-break's and the learned route's);
        None: the defaults. A library setting, not a job option.
    """

    stages: tuple[StageName, ...] = ("auto",)
    features: FeatureMode = "auto"
    feature_settings: FeatureSettings | None = None
    tau_f: float = 0.01
    coarse_iterations: int = 30
    max_candidates: int = 32
    weight_by_opacity: bool = False
    trim: float | None = 3.0
    refine: RefineMode = "auto"
    hypothesis_points: int = 2000
    hypothesis_iterations: int = 8
    refine_points: int = 12_000
    refine_iterations: int = 40
    max_points: int = 30_000
    inlier_threshold: float = 0.03
    hypothesis_truncation: float = 0.1
    search: SearchMode = "auto"
    scene: SceneMode = "auto"
    anchor_count: int = 2000
    search_rotations: int = 4096
    seed: int = 0
    fine_iterations: int = 60
    fine_views: int = 5
    fine_lr: float = 0.01
    fine_image_size: int = 128
    fine_loss: FineLoss = "smooth_l1"
    fine_on: FineSignal = "features"
    init_transform: tuple | None = None
    point_pairs: tuple | None = None
    up_axes: tuple | None = None
    front_axes: tuple | None = None
    fixed_scale: float | None = None
    rigid: bool = False
    semantic: Literal["auto", "off"] = "auto"
    photo_matches: Literal["auto", "off"] = "auto"
    frame_snap: Literal["auto", "off"] = "auto"
    learned: Literal["auto", "off"] = "auto"
    alternatives: Literal["doubtful", "always"] = "doubtful"
    criteria: Criteria | None = None

    def __post_init__(self) -> None:
        from gsa.align.guided import check_guidance  # one place checks every hint's shape

        if self.criteria is None:
            self.criteria = Criteria()
        elif not isinstance(self.criteria, Criteria):
            raise ValueError(f"criteria must be a gsa.align.criteria.Criteria, got {type(self.criteria).__name__}")
        check_guidance(self)
        self.stages = tuple(self.stages)
        if self.stages not in STAGE_CHOICES:
            raise ValueError(f"stages must be auto, coarse or coarse,fine, got {','.join(self.stages) or 'nothing'}")
        check_option_values(self)  # the choices, bounds and true/false of gsa.align.spec.OPTIONS

    def coarse_options(self, iterations: int | None = None) -> CoarseOptions:
        return CoarseOptions(
            tau_f=self.tau_f,
            max_iterations=iterations or self.coarse_iterations,
            max_candidates=self.max_candidates,
            trim=self.trim,
        )
