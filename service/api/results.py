"""The typed `result` of a job (OpenAPI): what the worker stores, from
gsa.align's AlignmentResult.to_dict() plus the service's own fields.

Every model allows extra members: a newer library may add metrics or stages,
and a stored result must never fail to serialise (JobOut.from_job falls back to
the stored dict if one does not validate)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_serializer

Matrix = list[list[float]]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")

    @model_serializer(mode="wrap")
    def _as_stored(self, handler):
        # Members the stored result does not have stay absent (not null): the JSON is the stored one.
        return {k: v for k, v in handler(self).items() if v is not None or k in self.model_fields_set}


class Sim3Out(_Open):
    """A similarity transform x_target = scale · R · x_source + t."""

    transform: Matrix | None = Field(None, description="4×4, row-major")
    scale: float | None = None
    rotation: Matrix | None = Field(None, description="3×3")
    quaternion: list[float] | None = Field(None, description="(w, x, y, z)")
    translation: list[float] | None = None


class Pose(_Open):
    """A candidate pose the coarse stage scored (hypotheses, metrics.alternatives)."""

    origin: str | None = None
    score: float | None = None
    geometry: float | None = None
    colour: float | None = None
    overlap: float | None = None
    rotation_offset_deg: float | None = None
    scale_ratio: float | None = None
    transform: Matrix | None = None
    chosen: bool | None = None


class SceneStructure(_Open):
    """What the scene test saw on one model (gsa.align.scene.Structure)."""

    shell_planes: int | None = Field(None, description="large planes of the enclosing shell (floor, walls, ceiling)")
    shell_weight: float | None = None
    parts: int | None = Field(None, description="separate small things inside the shell")
    parts_weight: float | None = None
    gaussians: int | None = None
    is_scene: bool | None = None


class SceneTest(_Open):
    source: SceneStructure | None = None
    target: SceneStructure | None = None


class SceneMetrics(_Open):
    """Whether align() took the scene path (rooms, sites: scene-scale registration) and why."""

    ran: bool | None = None
    reason: str | None = None
    test: SceneTest | None = None
    anchors: list[int] | None = Field(None, description="(source, target) anchors of the scene path")
    refine_cloud: list[int] | None = Field(None, description="(source, target) points of its refinement")
    exposure_gains: list[float] | None = Field(
        None, description="linear RGB gains that put the source's colours in the target's exposure"
    )


class CoarseVerdict(_Open):
    """The verdict at the coarse pose, where the fine stage ran after it."""

    confidence: float | None = None
    ambiguous: bool | None = None
    doubtful: bool | None = None


class Guidance(_Open):
    """The hints a guided job used (gsa.align.guided.describe), and where it started from."""

    init_transform: bool | None = Field(None, description="started from a given pose")
    point_pairs: int | None = Field(None, description="how many picked pairs were given")
    up_axes: list[list[float]] | None = Field(None, description="(source up, target up), unit length, internal frame")
    front_axes: list[list[float]] | None = Field(
        None, description="(source front, target front), across their up axes, unit length, internal frame"
    )
    fixed_scale: float | None = None
    start: dict[str, Any] | None = Field(
        None,
        description="where the local refinement started: from init_transform or point_pairs (their "
        "residuals and the index of a pair left out as wrong)",
    )
    doubt: str | None = Field(
        None, description="why the guided result is doubtful (guidance the models contradict), else null"
    )


class Metrics(_Open):
    """GT-free quality numbers; trust the transform only when `doubtful` is false."""

    confidence: float | None = Field(None, description="0..1")
    ambiguous: bool | None = None
    doubtful: bool | None = Field(None, description="ambiguous or confidence < 0.5")
    alternatives: list[Pose] | None = None
    hypothesis: str | None = None
    score: float | None = None
    margin: float | None = None
    overlap_score: float | None = None
    overlap_fraction: float | None = None
    colour_agreement: float | None = None
    colour_weight: float | None = None
    colour_gain: list[float] | None = Field(
        None, description="linear-RGB gains that put the source's colours in the target's exposure and white balance"
    )
    colour_mismatch: float | None = Field(
        None,
        description="colour disagreement of the overlapping pairs over the models' own colour noise; > 2: doubtful",
    )
    overlap_estimate: float | None = Field(
        None, description="trimmed share of the pairs (both ways, full resolution) that overlap at the pose"
    )
    coincident_share: float | None = Field(
        None, description="share of the overlapping pairs within two sampling spacings: how well the overlap coincides"
    )
    ranked_by: Literal["score", "geometry"] | None = Field(
        None,
        description="what chose among the poses: 'score' (overlap, with colour as far as the palettes are shared) "
        "or 'geometry' (no pose made the colours agree: another instance or another paint)",
    )
    inlier_fraction: float | None = None
    inlier_fraction_forward: float | None = None
    inlier_fraction_reverse: float | None = None
    inlier_threshold: float | None = None
    rms_residual: float | None = None
    feature_agreement: float | None = None
    feature_distance_median: float | None = None
    coarse_verdict: CoarseVerdict | None = Field(
        None,
        description="confidence, ambiguous, doubtful where the fine stage started (the coarse answer, after a doubtful answer's chain), where it ran",
    )
    scene: SceneMetrics | None = None
    guidance: Guidance | None = Field(None, description="present when the job was given hints (guided alignment)")


class CoarseStage(Sim3Out):
    iterations: int | None = None
    converged: bool | None = None
    matched: int | None = None
    candidate_pairs: int | None = None
    history: list[dict[str, Any]] | None = None


class FineStage(Sim3Out):
    loss_history: list[float] | None = None
    best_loss: float | None = None
    best_iteration: int | None = None


class Stages(_Open):
    coarse: CoarseStage | None = None
    fine: FineStage | None = None


class Frame(_Open):
    """How a model file's coordinates are meant (docs/formats.md)."""

    format: str | None = Field(None, description="ply, compressed-ply, splat, ksplat, spz, sog or glb")
    convention: str | None = Field(None, description="RDF (x right, y down, z forward) or RUB (x right, y up, z back)")
    handedness: str | None = None
    up_axis: str | None = None
    units: str | None = None


class Frames(_Open):
    source: Frame | None = None
    target: Frame | None = None
    internal: Frame | None = None
    transform_maps: str | None = None
    gltf_node_matrix_maps: str | None = None


class SourceResult(Sim3Out):
    """One source model aligned to the target. The transform maps source FILE coordinates
    to target FILE coordinates (the transform contract, docs/formats.md)."""

    quaternion_xyzw: list[float] | None = Field(None, description="(x, y, z, w), glTF order")
    inverse_transform: Matrix | None = Field(None, description="4×4, row-major, target -> source")
    gltf_node_matrix: list[float] | None = Field(None, description="16 numbers, column-major (glTF node matrix)")
    frames: Frames | None = None
    transform_internal: Matrix | None = Field(None, description="only when the files' axes differ from RDF")
    source_asset_id: str | None = None
    metrics: Metrics | None = None
    timings: dict[str, float] | None = Field(None, description="seconds per stage")
    features: str | None = Field(None, description="the feature backend used")
    stages_run: list[str] | None = None
    hypotheses: list[Pose] | None = None
    stages: Stages | None = None
    lifting: list[dict[str, Any]] | None = None


class ManyResidual(_Open):
    """An edge's disagreement with the solution: rotation (degrees), |log scale|, centroid
    displacement over the model's size, and the largest of the three in tolerance units."""

    rotation_deg: float | None = None
    log_scale: float | None = None
    translation: float | None = None
    units: float | None = None


class ManyModel(Sim3Out):
    """A many job's model: its Sim(3) into the reference's frame (gsa's internal frame)."""

    name: str | None = None
    index: int | None = None
    asset_id: str | None = None
    filename: str | None = None
    format: str | None = None
    file_transform: Matrix | None = Field(None, description="the same map in the files' own coordinates")
    confidence: float | None = None
    doubtful: bool | None = None
    contested_by: list[str] | None = Field(
        None,
        description="edges (source -> target) the global step overruled though align() was surer of them than "
        "of every edge that agrees with this model's transform: doubtful whatever its confidence",
    )


class ManyEdge(_Open):
    """One aligned pair of a many job: target ≈ transform(source), and what the global step made of it."""

    source: str | None = None
    target: str | None = None
    source_index: int | None = None
    target_index: int | None = None
    transform: Matrix | None = None
    used_transform: Matrix | None = Field(None, description="an alternative's when corrected")
    confidence: float | None = None
    doubtful: bool | None = None
    ambiguous: bool | None = None
    alternatives: int | None = None
    status: Literal["kept", "down-weighted", "pruned", "corrected"] | None = None
    weight: float | None = None
    residual: ManyResidual | None = None
    measured_residual: ManyResidual | None = None
    triangle_support: float | None = None
    seconds: float | None = None


class JobResult(SourceResult):
    """A succeeded job's result. A pair job carries its one source's fields at the top
    level too; `results` always lists one entry per source. A many job (POST /v1/many-jobs)
    has many.json's members instead: reference, models, edges, pruned, corrected, cycles."""

    results: list[SourceResult] | None = None
    reconstructions: dict[str, dict[str, Any]] | None = Field(
        None, description="summaries of the models reconstructed from image-set inputs"
    )
    notes: list[str] | None = None
    parent_job: str | None = Field(None, description="the job this one refines (POST /v1/jobs/{id}:refine)")
    reference: str | None = Field(None, description="many job: the reference asset")
    models: list[ManyModel] | None = Field(None, description="many job: each model into the reference's frame")
    edges: list[ManyEdge] | None = Field(None, description="many job: the aligned pairs")
    pruned: list[str] | None = Field(None, description="many job: edges the cycles contradict (source -> target)")
    corrected: list[str] | None = Field(None, description="many job: pruned edges an alternative replaced")
    cycles: dict[str, Any] | None = None
    merge: dict[str, Any] | None = Field(None, description="many job with merged: {mode, removed, gaussians}")
