"""Job options: which ones a client may set, which the server sets, which outputs exist."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal, NamedTuple, get_args

from pydantic import BaseModel, ConfigDict, Field, model_validator

from gsa.features.settings import FeatureSettings  # torch-free: safe at API start-up
from gsa.settings_env import feature_settings_env
from service.problems import invalid_input

SERVICE_OPTIONS = {"outputs", "renders", "recon_iterations"}
# The artifacts a job can produce: the one definition (the HTTP schema's enum,
# validation and the worker's default all come from it).
OutputName = Literal["result", "aligned", "merged", "renders", "preview"]
OUTPUT_NAMES: tuple[str, ...] = get_args(OutputName)
# A request may name an output more than once (deduplicated), but not without end: 100,000
# duplicates made a 923 KB job record.
MAX_OUTPUT_ENTRIES = 64
DEFAULT_OUTPUTS = OUTPUT_NAMES  # a job that names no outputs gets all of them


def server_only_option(name: str) -> bool:
    return name in ("device", "feature_settings") or name.endswith(("_weights", "_path", "_dir", "_device"))


def server_options(settings, known: set[str]) -> dict:
    """Deployment settings for AlignOptions fields that exist in this library build:
    extractor weights (DINOv2 backbone, sphere-mapper head) live on the worker."""
    out = {}
    if "device" in known and settings.worker_device:
        out["device"] = settings.worker_device
    if "semantic" in known and settings.semantic == "off":
        out["semantic"] = "off"
    if "feature_settings" in known and (settings.dinov2_weights or settings.spheremap_weights):
        out["feature_settings"] = FeatureSettings(
            **feature_settings_env(
                backbone=str(settings.dinov2_weights) if settings.dinov2_weights else None,
                head=str(settings.spheremap_weights) if settings.spheremap_weights else None,
            )
        )
    return out


def align_options(settings, options: dict[str, Any]):
    """The AlignOptions of a job's options (the names this library build knows; the rest, such
    as a many job's own fields, are not align()'s), with the deployment's server options."""
    from gsa.align.pipeline import AlignOptions  # lazy: see align_option_names

    known = align_option_names()
    opts = {k: v for k, v in options.items() if k in known}
    if isinstance(opts.get("stages"), list):
        opts["stages"] = tuple(opts["stages"])
    opts.update(server_options(settings, known))
    try:
        return AlignOptions(**opts)
    except (TypeError, ValueError) as exc:
        raise invalid_input(f"invalid options: {exc}") from None


def align_option_names() -> set[str]:
    """The option names this library build's AlignOptions accepts."""
    from gsa.align.pipeline import AlignOptions  # lazy: ~1 s of imports, kept off API start-up

    return {f.name for f in dataclasses.fields(AlignOptions)}


class Bound(NamedTuple):
    """The values one numeric option may take: `kind` int or float, lo..hi
    inclusive (None: open), `lo_open`: lo itself excluded (a positive float)."""

    kind: type
    lo: float | None
    hi: float | None
    lo_open: bool = False

    def describe(self) -> str:
        kind = "an integer" if self.kind is int else "a number"
        if self.lo is not None and self.hi is not None:
            return f"{kind} in {'(' if self.lo_open else '['}{self.lo}, {self.hi}]"
        if self.lo is not None:
            return f"{kind} {'>' if self.lo_open else '≥'} {self.lo}"
        return f"{kind} ≤ {self.hi}"

    def json_schema(self) -> dict[str, Any]:
        """The bound in OpenAPI terms (documentation only: enforcement is check_option_values)."""
        out: dict[str, Any] = {}
        if self.lo is not None:
            out["exclusiveMinimum" if self.lo_open else "minimum"] = self.lo
        if self.hi is not None:
            out["maximum"] = self.hi
        return out


# Bounds on every numeric option a client may set: the one place they live (the HTTP
# schema documents them from here, HTTP and gRPC submissions are checked against them).
# The upper bounds cap the work and memory one job can ask for; the lower ones are the
# library's own minimums, checked here so a bad value is a 422 at submission, not a failed job.
OPTION_BOUNDS: dict[str, Bound] = {
    "tau_f": Bound(float, 0, None, lo_open=True),
    "coarse_iterations": Bound(int, 1, 1000),
    "max_candidates": Bound(int, 1, 256),
    "trim": Bound(float, 0, None, lo_open=True),
    "hypothesis_points": Bound(int, 10, 100_000),
    "hypothesis_iterations": Bound(int, 1, 200),
    "refine_points": Bound(int, 10, 200_000),
    "refine_iterations": Bound(int, 1, 1000),
    "max_points": Bound(int, 10, 200_000),
    "inlier_threshold": Bound(float, 0, 10, lo_open=True),
    "hypothesis_truncation": Bound(float, 0, 10, lo_open=True),
    "anchor_count": Bound(int, 100, 20_000),
    "search_rotations": Bound(int, 64, 20_000),
    "seed": Bound(int, 0, 2**63 - 1),
    "fine_iterations": Bound(int, 0, 5000),
    "fine_views": Bound(int, 1, 64),
    "fine_lr": Bound(float, 0, 1, lo_open=True),
    "fine_image_size": Bound(int, 8, 1024),
    "recon_iterations": Bound(int, 10, 100_000),
    "fixed_scale": Bound(float, 1e-6, 1e6),
}
# Choices the library checks only when the fine stage starts (gsa.align.fine.FineOptions,
# whose module loads torch): repeated here so a typo is refused at submission.
OPTION_CHOICES: dict[str, tuple[str, ...]] = {
    "fine_loss": ("smooth_l1", "l1", "l2"),
    "fine_on": ("features", "colors"),
    "semantic": ("auto", "off"),
    "photo_matches": ("auto", "off"),
    "frame_snap": ("auto", "off"),
    "learned": ("auto", "off"),
    "alternatives": ("doubtful", "always"),
}
STAGE_NAMES = ("auto", "coarse", "fine")
BOOL_OPTIONS = {"renders", "weight_by_opacity", "rigid"}
# Guidance (gsa.align.guided, docs/service.md "Guided alignment"): what a person knows about the
# pose, each in the input FILES' own coordinates (as the result states its transform). Their
# shapes are checked by the library's own check_guidance, one hint at a time so a 422 names it.
GUIDANCE_OPTIONS = ("init_transform", "point_pairs", "up_axes", "front_axes", "fixed_scale")
GUIDANCE_SHAPES = {
    "init_transform": "4×4 nested list, a Sim(3) source → target: rows [[r, r, r, t], …, [0, 0, 0, 1]]",
    "point_pairs": '{"source": [[x, y, z], …], "target": [[x, y, z], …]}, 3..1000 pairs',
    "up_axes": "[[x, y, z], [x, y, z]]: the source's up, the target's up",
    "front_axes": "[[x, y, z], [x, y, z]]: the way the source faces, the way the target faces",
    "fixed_scale": "the answer's scale s",
}
# The fine stage's work, fine_views × fine_image_size² × fine_iterations, with the
# library's defaults for the ones a job leaves out.
FINE_DEFAULTS = {"fine_views": 5, "fine_image_size": 128, "fine_iterations": 60}


def _out_of_range(name: str, bound: Bound) -> Exception:
    extra: dict[str, Any] = {"option": name}
    if bound.lo is not None:
        extra["exclusive_minimum" if bound.lo_open else "minimum"] = bound.lo
    if bound.hi is not None:
        extra["maximum"] = bound.hi
    return invalid_input(f"option {name!r} must be {bound.describe()}", **extra)


def check_option_values(options: dict[str, Any]) -> None:
    """Types, bounds and choices of the options a client set (no settings needed):
    422 invalid-input naming the option and its bound."""
    for name, v in options.items():
        bound = OPTION_BOUNDS.get(name)
        if bound is not None:
            if name == "trim" and v is None:
                continue
            number = isinstance(v, int | float) and not isinstance(v, bool)
            if not number or (bound.kind is int and not isinstance(v, int)):
                raise _out_of_range(name, bound)
            too_low = bound.lo is not None and not (v > bound.lo if bound.lo_open else v >= bound.lo)
            too_high = bound.hi is not None and not v <= bound.hi
            if too_low or too_high or not math.isfinite(v):
                raise _out_of_range(name, bound)
        elif name in OPTION_CHOICES and v not in OPTION_CHOICES[name]:
            choices = OPTION_CHOICES[name]
            raise invalid_input(f"option {name!r} must be one of {', '.join(choices)}", option=name, allowed=choices)
        elif name in BOOL_OPTIONS and not isinstance(v, bool):
            raise invalid_input(f"option {name!r} must be true or false", option=name)
    if "stages" in options:
        _check_stages(options["stages"])
    if any(options.get(k) is not None for k in GUIDANCE_OPTIONS):
        check_guidance_options(options)


def check_guidance_options(options: dict[str, Any]) -> None:
    """The hints' shapes, with the library's words (gsa.align.guided.check_guidance), each
    hint alone first so the 422 names the one that is wrong, then together."""
    from types import SimpleNamespace

    from gsa.align.guided import check_guidance  # numpy only: no torch, no numba

    given = {k: options[k] for k in GUIDANCE_OPTIONS if options.get(k) is not None}
    empty = dict.fromkeys(GUIDANCE_OPTIONS)
    for name, value in given.items():
        # A front is checked against its up axes (it needs them); a bad up_axes was named before.
        alone = {name: value, "up_axes": given.get("up_axes")} if name == "front_axes" else {name: value}
        try:
            check_guidance(SimpleNamespace(**(empty | alone)))
        except (TypeError, ValueError) as exc:
            detail = str(exc) if str(exc).startswith(name) else f"option {name!r}: {exc}"
            raise invalid_input(detail, option=name, expected=GUIDANCE_SHAPES[name]) from None
    try:
        check_guidance(SimpleNamespace(**(empty | given)))
    except (TypeError, ValueError) as exc:  # init_transform and point_pairs: one start, not two
        raise invalid_input(str(exc), option="point_pairs", conflicts_with="init_transform") from None


def _check_stages(stages: Any) -> None:
    from gsa.align.pipeline import STAGE_CHOICES  # lazy, as in align_option_names

    combos = " | ".join(",".join(c) for c in STAGE_CHOICES)
    if not isinstance(stages, list | tuple) or not all(isinstance(x, str) for x in stages):
        raise invalid_input(f"option 'stages' must be a list of stage names ({combos})", option="stages")
    unknown = sorted({x for x in stages if x not in STAGE_NAMES})
    if unknown:
        raise invalid_input(
            f"unknown stage(s): {', '.join(unknown)}; stages must be one of {combos}",
            option="stages",
            allowed=[list(c) for c in STAGE_CHOICES],
        )
    if tuple(stages) not in STAGE_CHOICES:
        raise invalid_input(
            f"stages {','.join(stages) or '(none)'} is not a pipeline; stages must be one of {combos}",
            option="stages",
            allowed=[list(c) for c in STAGE_CHOICES],
        )


def fine_work(options: dict[str, Any]) -> int:
    """fine_views × fine_image_size² × fine_iterations for these options (defaults filled in)."""
    v = {k: options.get(k, d) for k, d in FINE_DEFAULTS.items()}
    return int(v["fine_views"]) * int(v["fine_image_size"]) ** 2 * int(v["fine_iterations"])


# Learned feature extractors and the weights each needs (the workers read them from these
# settings: server_options); canonical, file and auto need none.
FEATURE_WEIGHTS = {"dinov2": ("dinov2_weights",), "spheremap": ("dinov2_weights", "spheremap_weights")}


def check_feature_weights(options: dict[str, Any], settings) -> None:
    """`features: dinov2 | spheremap` on a deployment without those weights: a 422 at
    submission, not a job that fails in the worker (the message names no server paths)."""
    mode = options.get("features")
    needs = FEATURE_WEIGHTS.get(mode) if isinstance(mode, str) else None
    if needs and not all(getattr(settings, n, None) for n in needs):
        available = ["auto", "file", "canonical"] + [
            m for m, ns in FEATURE_WEIGHTS.items() if all(getattr(settings, n, None) for n in ns)
        ]
        raise invalid_input(
            f"option 'features': {mode!r} needs model weights this server does not have; "
            f"available: {', '.join(available)}",
            option="features",
            allowed=available,
        )


def validate_options(options: dict[str, Any], settings=None) -> dict[str, Any]:
    """The one check of a job's options (HTTP JSON and multipart, gRPC): server-only
    and unknown names, types and bounds, the library's own consistency checks and,
    given settings, the per-job work budget (`max_fine_work`)."""
    fixed = sorted(k for k in options if server_only_option(k))
    if fixed:
        # Paths and devices are the server's business: a client path must never reach the filesystem.
        raise invalid_input(f"option(s) set by the server, not the client: {', '.join(fixed)}")
    known = align_option_names()
    unknown = sorted(set(options) - known - SERVICE_OPTIONS)
    if unknown:
        raise invalid_input(
            f"unknown option(s): {', '.join(unknown)}",
            allowed=sorted(known | SERVICE_OPTIONS),
        )
    outs = options.get("outputs")
    if outs is not None:
        if isinstance(outs, (list, tuple)) and len(outs) > MAX_OUTPUT_ENTRIES:
            raise invalid_input(
                f"'outputs' has {len(outs)} entries; at most {MAX_OUTPUT_ENTRIES} (each of "
                f"{', '.join(OUTPUT_NAMES)} once)",
                option="outputs",
                maximum=MAX_OUTPUT_ENTRIES,
            )
        bad = sorted(set(outs) - set(OUTPUT_NAMES))
        if bad:
            raise invalid_input(f"unknown output(s): {', '.join(bad)}")
        options["outputs"] = list(dict.fromkeys(outs))  # stored once each, in the order given
    check_option_values(options)
    # The library's own checks (AlignOptions.__post_init__) at submission, not in the worker.
    from gsa.align.pipeline import AlignOptions  # lazy, as in align_option_names

    try:
        AlignOptions(**{k: v for k, v in options.items() if k in known})
    except (TypeError, ValueError) as exc:
        raise invalid_input(f"invalid options: {exc}") from None
    if settings is not None:
        check_feature_weights(options, settings)
    budget = getattr(settings, "max_fine_work", None)
    if budget is not None:
        work = fine_work(options)
        if work > budget:
            raise invalid_input(
                f"fine_views × fine_image_size² × fine_iterations = {work} exceeds the per-job budget of {budget}",
                option="fine_views × fine_image_size² × fine_iterations",
                maximum=budget,
                value=work,
            )
    return options


def bounded_field(name: str, description: str | None = None, **kw):
    """A field whose documented bounds come from OPTION_BOUNDS (which check_option_values enforces)."""
    return Field(None, description=description, json_schema_extra=OPTION_BOUNDS[name].json_schema(), **kw)


_HINT_SCHEMAS: dict[str, dict[str, Any]] = {
    "init_transform": {
        "type": "array",
        "items": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
        "minItems": 4,
        "maxItems": 4,
    },
    "point_pairs": {
        "type": "object",
        "properties": {
            k: {"type": "array", "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}}
            for k in ("source", "target")
        },
        "required": ["source", "target"],
    },
    "up_axes": {
        "type": "array",
        "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "minItems": 2,
        "maxItems": 2,
    },
    "front_axes": {
        "type": "array",
        "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "minItems": 2,
        "maxItems": 2,
    },
}


def hint_field(name: str, description: str):
    """A guidance field: documented in OpenAPI, checked by check_guidance_options."""
    return Field(None, description=f"{description}; {GUIDANCE_SHAPES[name]}", json_schema_extra=_HINT_SCHEMAS[name])


class AlignOptionsIn(BaseModel):
    """Alignment options; fields not listed (e.g. fine_*) pass through to the
    library's AlignOptions and are rejected with 422 if it does not know them.
    Types, bounds and choices are checked here (422 invalid-input naming the
    option and its bound). The HTTP schema (service.api.schemas) and gRPC's
    options_json both parse with it."""

    model_config = ConfigDict(extra="allow")
    stages: list[str] | None = Field(None, examples=[["coarse", "fine"]], description="auto | coarse | coarse,fine")
    features: str | None = Field(None, description="feature backend: auto | canonical | spheremap | dinov2")
    tau_f: float | None = bounded_field("tau_f", "feature-match threshold τ_f")
    coarse_iterations: int | None = bounded_field("coarse_iterations")
    seed: int | None = bounded_field("seed")
    fine_views: int | None = bounded_field("fine_views", "fine stage: rendered views")
    fine_image_size: int | None = bounded_field("fine_image_size", "fine stage: render size in pixels (square)")
    fine_iterations: int | None = bounded_field(
        "fine_iterations",
        "fine stage: optimiser steps; fine_views × fine_image_size² × fine_iterations is also capped "
        "per job (GSA_MAX_FINE_WORK)",
    )
    renders: bool | None = Field(None, description="produce before/after renders (default true)")
    outputs: list[OutputName] | None = Field(None, description="artifacts wanted (default: all)")
    recon_iterations: int | None = bounded_field("recon_iterations", "3DGS training iterations for image-set inputs")
    # Guidance (docs/service.md "Guided alignment"), in the input files' own coordinates. Typed
    # loosely here: their shapes are checked by the library's check_guidance (422 naming the option).
    init_transform: Any = hint_field("init_transform", "start from this pose; only a local refinement runs")
    point_pairs: Any = hint_field("point_pairs", "picked point pairs: their Sim(3), then a local refinement")
    up_axes: Any = hint_field("up_axes", "every pose keeps these up axes aligned")
    front_axes: Any = hint_field(
        "front_axes", "with up_axes: the turns about up are kept within 45° of these fronts agreeing"
    )
    fixed_scale: float | None = bounded_field("fixed_scale", "the answer's scale, kept through every stage")
    semantic: str | None = Field(
        None,
        description="auto | off: a doubtful answer's pose is picked among its alternatives by pretrained "
        "DINOv2 features when the deployment has a backbone (default auto)",
    )
    learned: str | None = Field(
        None,
        description="auto | off: a doubtful answer is decided by the learned canonical head (each model's "
        "pose in its category's canonical frame) where both models' poses are sure (default auto)",
    )
    frame_snap: str | None = Field(
        None,
        description="auto | off: a doubtful answer between other instances is turned onto the nearest "
        "relabelling of the models' dominant surface-normal frames and checked against the others; off "
        "keeps the poses as refined (default auto)",
    )
    alternatives: str | None = Field(
        None,
        description="doubtful | always: metrics.alternatives lists the poses worth picking for a doubtful "
        "or guided answer and is empty for a confident one (default doubtful); always lists them for "
        "every answer",
    )

    @model_validator(mode="after")
    def _check(self):
        check_option_values(self.to_dict())  # raises a 422 Problem (not a pydantic error)
        return self

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True)


def parse_options(raw: str | dict[str, Any], error: str) -> dict[str, Any]:
    """Options as a client sent them (a JSON text or an object) -> their dict, or a 422
    invalid-input "<error>: <why>" for a wrong type or shape."""
    try:
        if isinstance(raw, str):
            return AlignOptionsIn.model_validate_json(raw).to_dict()
        return AlignOptionsIn.model_validate(raw).to_dict()
    except ValueError as exc:
        raise invalid_input(f"{error}: {exc}") from None
