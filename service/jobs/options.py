"""Job options: which ones a client may set, which the server sets, which outputs exist."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Annotated, Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, WithJsonSchema, create_model, model_validator

from gsa.align.choices import StageName
from gsa.align.spec import OPTIONS, Bound  # a leaf module: safe at API start-up
from gsa.features.settings import FeatureSettings  # torch-free: safe at API start-up
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
    # criteria: the library caller's decision thresholds (gsa.align.criteria), never a client's
    return name in ("device", "feature_settings", "criteria") or name.endswith(("_weights", "_path", "_dir", "_device"))


def server_options(settings, known: set[str]) -> dict:
    """Deployment settings for AlignOptions fields that exist in this library build:
    extractor weights (DINOv2 backbone, sphere-mapper head) live on the worker."""
    out = {}
    if "device" in known and settings.worker_device:
        out["device"] = settings.worker_device
    if "semantic" in known and settings.semantic == "off":
        out["semantic"] = "off"
    feature_kw = settings.feature_settings_kwargs() if "feature_settings" in known else None
    if feature_kw is not None:
        out["feature_settings"] = FeatureSettings(**feature_kw)
    return out


def align_options(settings, options: dict[str, Any], *, only_known: bool = False):
    """The AlignOptions of a job's options (the names this library build knows; the rest, such
    as a many job's own fields, are not align()'s: with `only_known`, a 422 naming them), with
    the deployment's server options."""
    from gsa.align.pipeline import AlignOptions  # lazy: see align_option_names

    known = align_option_names()
    unknown = sorted(set(options) - known)
    if only_known and unknown:  # a job stored by a library build that knew them
        raise invalid_input(f"unknown alignment options: {', '.join(unknown)}")
    opts = {k: v for k, v in options.items() if k in known}  # AlignOptions makes stages a tuple
    opts.update(server_options(settings, known))
    try:
        return AlignOptions(**opts)
    except (TypeError, ValueError) as exc:
        raise invalid_input(f"invalid options: {exc}") from None


def align_option_names() -> set[str]:
    """The option names this library build's AlignOptions accepts."""
    from gsa.align.pipeline import AlignOptions  # lazy: ~1 s of imports, kept off API start-up

    return {f.name for f in dataclasses.fields(AlignOptions)}


# Bounds on every numeric option a client may set, from each option's spec (gsa.align.spec:
# a job's `limits`, else the library's own `bounds`), and the service's own: the HTTP schema
# documents them from here, HTTP and gRPC submissions are checked against them. The upper bounds
# cap the work and memory one job can ask for; the lower ones are the library's own minimums,
# checked here so a bad value is a 422 at submission, not a failed job.
OPTION_BOUNDS: dict[str, Bound] = {
    **{name: spec.job_bounds for name, spec in OPTIONS.items() if spec.job_bounds is not None},
    "recon_iterations": Bound(int, 10, 100_000),
}
# The choices of every choice option, from its spec (AlignOptions checks them too; here a bad
# one is a 422 naming the option and its choices).
OPTION_CHOICES: dict[str, tuple[str, ...]] = {
    name: spec.choices for name, spec in OPTIONS.items() if spec.kind == "choice"
}
STAGE_NAMES: tuple[str, ...] = get_args(StageName)
BOOL_OPTIONS = {"renders"} | {name for name, spec in OPTIONS.items() if spec.kind == "bool"}
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
# The fine stage's work, fine_views × fine_image_size² × fine_iterations, with the library's
# defaults for the ones a job leaves out.
FINE_OPTIONS = ("fine_views", "fine_image_size", "fine_iterations")


@functools.cache
def library_defaults() -> dict[str, Any]:
    """The AlignOptions fields' defaults (for the options a job leaves out)."""
    from gsa.align.pipeline import AlignOptions  # lazy: see align_option_names

    return {f.name: f.default for f in dataclasses.fields(AlignOptions) if f.default is not dataclasses.MISSING}


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
            if v is None and name in OPTIONS and OPTIONS[name].none_ok:  # trim: keep all
                continue
            number = isinstance(v, int | float) and not isinstance(v, bool)
            if not number or (bound.kind is int and not isinstance(v, int)):
                raise _out_of_range(name, bound)
            if not bound.contains(v) or not math.isfinite(v):
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
    d = library_defaults()
    v = {k: options.get(k, d[k]) for k in FINE_OPTIONS}
    return int(v["fine_views"]) * int(v["fine_image_size"]) ** 2 * int(v["fine_iterations"])


# Learned feature extractors and the weights each needs (the workers read them from these
# settings: server_options); canonical, file and auto need none.
FEATURE_WEIGHTS = {"dinov2": ("features_backbone",), "spheremap": ("features_backbone", "features_head")}


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


# The JSON types of the options' kinds (gsa.align.spec.OptionSpec.kind).
_JSON_TYPES = {"int": "integer", "float": "number", "bool": "boolean", "choice": "string"}
_PYTHON_TYPES = {"int": int, "float": float, "bool": bool, "choice": str}
# The options API 1.0 declared with pydantic types, which also take "5" or 5.0 for 5 (and answer a
# value of another type with a validation-error problem): kept so. The others are checked as sent,
# by check_option_values (an invalid-input problem naming the option).
_COERCED = frozenset(
    {"features", "tau_f", "coarse_iterations", "seed", "fine_views", "fine_image_size", "fine_iterations"}
    | {"fixed_scale", "semantic", "learned", "frame_snap", "alternatives"}
)
# What the service adds to an option's description.
_SERVICE_NOTES = {
    "fine_iterations": "fine_views × fine_image_size² × fine_iterations is also capped per job (GSA_MAX_FINE_WORK)",
}


def option_field(name: str) -> tuple[Any, Any]:
    """(type, Field) of the client option `name` in AlignOptionsIn, from its spec (gsa.align.spec):
    its help as the description, its job bounds (OPTION_BOUNDS) and choices in the schema."""
    spec = OPTIONS[name]
    description = "; ".join(filter(None, [spec.help, _SERVICE_NOTES.get(name)]))
    if spec.kind == "stages":
        return list[str] | None, Field(None, examples=[["coarse", "fine"]], description=description)
    if spec.kind == "hint":
        return Any, hint_field(name, description)
    schema: dict[str, Any] = {"type": _JSON_TYPES[spec.kind]}
    if spec.choices:
        schema["enum"] = list(spec.choices)
    if name in _COERCED:
        kind: Any = (
            Annotated[_PYTHON_TYPES[spec.kind], WithJsonSchema(schema)] if spec.choices else _PYTHON_TYPES[spec.kind]
        )
        kind = kind | None
    else:
        kind = Annotated[Any, WithJsonSchema({"anyOf": [schema, {"type": "null"}]})]
    bound = OPTION_BOUNDS.get(name)
    return kind, Field(None, description=description, json_schema_extra=bound.json_schema() if bound else None)


def client_option_names() -> tuple[str, ...]:
    """The options of gsa.align.spec a client may set (not the deployment's)."""
    return tuple(name for name, spec in OPTIONS.items() if spec.kind != "settings" and not server_only_option(name))


class _AlignOptionsModel(BaseModel):
    model_config = ConfigDict(extra="allow")

    @model_validator(mode="after")
    def _check(self):
        check_option_values(self.to_dict())  # raises a 422 Problem (not a pydantic error)
        return self

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True)


AlignOptionsIn = create_model(
    "AlignOptionsIn",
    __base__=_AlignOptionsModel,
    __doc__="""Alignment options: each of the library's (gsa.align.spec.OPTIONS, made into these
    fields), and the service's own (outputs, renders, recon_iterations). Options this library
    build does not know are rejected with 422. Types, bounds and choices are checked here (422
    invalid-input naming the option and its bound). The HTTP schema (service.api.schemas) and
    gRPC's options_json both parse with it.""",
    __module__=__name__,
    **{name: option_field(name) for name in client_option_names()},
    renders=(bool | None, Field(None, description="produce before/after renders (default true)")),
    outputs=(list[OutputName] | None, Field(None, description="artifacts wanted (default: all)")),
    recon_iterations=(
        int | None,
        Field(
            None,
            description="3DGS training iterations for image-set inputs",
            json_schema_extra=OPTION_BOUNDS["recon_iterations"].json_schema(),
        ),
    ),
)


def parse_options(raw: str | dict[str, Any], error: str) -> dict[str, Any]:
    """Options as a client sent them (a JSON text or an object) -> their dict, or a 422
    invalid-input "<error>: <why>" for a wrong type or shape."""
    try:
        if isinstance(raw, str):
            return AlignOptionsIn.model_validate_json(raw).to_dict()
        return AlignOptionsIn.model_validate(raw).to_dict()
    except ValueError as exc:
        raise invalid_input(f"{error}: {exc}") from None
