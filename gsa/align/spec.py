"""The one description of each alignment option: `OPTIONS[name]` says, for the AlignOptions
field of that name (gsa.align.types, which keeps its type and default), what it does (`help`),
the values it may take (`choices`, `bounds`: checked by AlignOptions itself), what a service job
may ask for (`limits`: work and memory caps) and its `gsa align` flag (`cli`).

Everything else is made from it: AlignOptions' own checks (`check_option_values`), the CLI's
arguments (gsa.align.command), the service's bounds, choices and its pydantic model of the
options (service.jobs.options). A leaf module (no numpy): the service reads it at start-up."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, get_args

from gsa.align.choices import (
    FEATURE_MODES,
    STAGE_CHOICES,
    FineLoss,
    FineSignal,
    RefineMode,
    SceneMode,
    SearchMode,
)

__all__ = ["OPTIONS", "Bound", "Cli", "OptionSpec", "check_option_values", "choice_error"]

Kind = Literal["int", "float", "bool", "choice", "stages", "hint", "settings"]


@dataclass(frozen=True)
class Bound:
    """The values one numeric option may take: `kind` int or float, lo..hi inclusive
    (None: open), `lo_open`: lo itself excluded (a positive float)."""

    kind: type
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def contains(self, v: Any) -> bool:
        """Whether v is within the bound (NaN is not); a non-number raises TypeError."""
        if self.lo is not None and not (v > self.lo if self.lo_open else v >= self.lo):
            return False
        return self.hi is None or v <= self.hi

    def describe(self) -> str:
        """The service's words: "an integer in [1, 1000]", "a number > 0"."""
        kind = "an integer" if self.kind is int else "a number"
        if self.lo is not None and self.hi is not None:
            return f"{kind} in {'(' if self.lo_open else '['}{self.lo}, {self.hi}]"
        if self.lo is not None:
            return f"{kind} {'>' if self.lo_open else '≥'} {self.lo}"
        return f"{kind} ≤ {self.hi}"

    def brief(self) -> str:
        """The library's words: "positive", "at least 1", "in 100..20000"."""
        if self.lo is not None and self.hi is not None:
            return f"in {self.lo}..{self.hi}" if not self.lo_open else f"in ({self.lo}, {self.hi}]"
        if self.lo is not None:
            if self.lo == 0 and self.lo_open:
                return "positive"
            return f"{'above' if self.lo_open else 'at least'} {self.lo}"
        return f"at most {self.hi}"

    def json_schema(self) -> dict[str, Any]:
        """The bound in OpenAPI terms."""
        out: dict[str, Any] = {}
        if self.lo is not None:
            out["exclusiveMinimum" if self.lo_open else "minimum"] = self.lo
        if self.hi is not None:
            out["maximum"] = self.hi
        return out


LIBRARY_DEFAULT: Any = "library default"  # Cli.default: the AlignOptions field's own default


@dataclass(frozen=True)
class Cli:
    """The option's `gsa align` flag: `flag` (else --name-with-dashes), its `default`
    (LIBRARY_DEFAULT: the field's; None: left to the library, or to the command), its own
    `help` where the CLI words it differently (flags, environment variables), `metavar`, and
    its argument group: "main" or "guidance"."""

    flag: str | None = None
    default: Any = LIBRARY_DEFAULT
    help: str | None = None
    metavar: str | None = None
    group: Literal["main", "guidance"] = "main"


@dataclass(frozen=True)
class OptionSpec:
    """One AlignOptions field. kind: int, float, bool, choice (one of `choices`), stages
    (a pipeline of STAGE_CHOICES), hint (guidance, its shape checked by gsa.align.guided) or
    settings (the deployment's, never a client's). bounds: what AlignOptions accepts;
    limits: what a service job may ask for (default: bounds); none_ok: None is a value
    (not "unset") a client may send."""

    kind: Kind
    help: str
    choices: tuple = ()
    bounds: Bound | None = None
    limits: Bound | None = None
    none_ok: bool = False
    cli: Cli | None = None

    @property
    def job_bounds(self) -> Bound | None:
        return self.limits or self.bounds

    @property
    def flag(self) -> str | None:
        return None if self.cli is None else self.cli.flag


AUTO_OFF = ("auto", "off")
_GUIDANCE = Cli(group="guidance")

# In AlignOptions' field order; the CLI's order is gsa.align.command's. tests/test_option_spec.py
# checks that every field has its entry and that the choices are the fields' Literal types.
OPTIONS: dict[str, OptionSpec] = {
    "stages": OptionSpec(
        "stages",
        "auto | coarse | coarse,fine",
        choices=STAGE_CHOICES,
        cli=Cli(
            help="auto, coarse or coarse,fine (default: %(default)s = coarse,fine unless the "
            "nearest-neighbour refinement ran, see README)"
        ),
    ),
    "features": OptionSpec(
        "choice",
        "feature backend: auto | file | canonical | spheremap | dinov2",
        choices=FEATURE_MODES,
        cli=Cli(
            help="auto: the files' own features when both have them, else the configured extractor "
            "(GSA_FEATURES_EXTRACTOR + weights), else canonical; spheremap/dinov2 lift 2D features first"
        ),
    ),
    "feature_settings": OptionSpec("settings", "the extractors' weights and lifting (the deployment's)"),
    "tau_f": OptionSpec(
        "float", "feature distance threshold τ_f", bounds=Bound(float, 0, None, lo_open=True), cli=Cli()
    ),
    "coarse_iterations": OptionSpec(
        "int",
        "coarse iteration limit",
        bounds=Bound(int, 1, None),
        limits=Bound(int, 1, 1000),
        cli=Cli(flag="--iterations"),
    ),
    "max_candidates": OptionSpec(
        "int",
        "feature candidates kept per source Gaussian",
        bounds=Bound(int, 1, None),
        limits=Bound(int, 1, 256),
        cli=Cli(),
    ),
    "weight_by_opacity": OptionSpec("bool", "weight correspondences by opacity", cli=Cli()),
    "trim": OptionSpec(
        "float",
        "the feature-guided ICP drops matches beyond trim × the median residual (None: keeps all)",
        limits=Bound(float, 0, None, lo_open=True),
        none_ok=True,
    ),
    "refine": OptionSpec(
        "choice",
        "nearest-neighbour ICP after the feature stage (auto: with canonical features)",
        choices=get_args(RefineMode),
        cli=Cli(),
    ),
    "hypothesis_points": OptionSpec(
        "int",
        "ambiguous canonical frames: each hypothesis is tried on a source subsample of this many Gaussians",
        limits=Bound(int, 10, 100_000),
    ),
    "hypothesis_iterations": OptionSpec(
        "int", "feature-stage iterations of each hypothesis' trial", limits=Bound(int, 1, 200)
    ),
    "refine_points": OptionSpec("int", "Gaussians sampled for the refinement ICP", limits=Bound(int, 10, 200_000)),
    "refine_iterations": OptionSpec("int", "iterations of the refinement ICP", limits=Bound(int, 1, 1000)),
    "max_points": OptionSpec(
        "int",
        "the feature stage and the quality metrics use at most this many source Gaussians",
        limits=Bound(int, 10, 200_000),
    ),
    "inlier_threshold": OptionSpec(
        "float",
        "GT-free inlier distance, as a fraction of the target's RMS radius",
        bounds=Bound(float, 0, None, lo_open=True),
        limits=Bound(float, 0, 10, lo_open=True),
    ),
    "hypothesis_truncation": OptionSpec(
        "float",
        "hypotheses are ranked by the symmetric nearest-neighbour distance truncated at this "
        "fraction of the target's RMS radius",
        bounds=Bound(float, 0, None, lo_open=True),
        limits=Bound(float, 0, 10, lo_open=True),
    ),
    "search": OptionSpec(
        "choice",
        "coarse initialisation without learned features: global (robust SO(3) search on "
        "floater-free anchors, overlap and colour scored), frames (one canonical frame per "
        "model, the earlier default); auto: global unless refine is off",
        choices=get_args(SearchMode),
        cli=Cli(
            help="coarse initialisation without learned features: global (robust SO(3) search on "
            "floater-free anchors, overlap and colour scored), frames (one canonical frame per "
            "model, the earlier default); auto: global unless --refine off"
        ),
    ),
    "scene": OptionSpec(
        "choice",
        "the scene path for rooms and sites (more anchors, no frame relabellings, "
        "exposure-normalised colours, bounded refinement clouds); auto: when both models "
        "pass the scene test (README, 'Scenes'); result metrics.scene says whether it ran and why",
        choices=get_args(SceneMode),
        cli=Cli(),
    ),
    # Bounded in the library too: both set the size of arrays the search holds at once.
    "anchor_count": OptionSpec("int", "anchors per model of the global search", bounds=Bound(int, 100, 20_000)),
    "search_rotations": OptionSpec("int", "rotations sampled by the global search", bounds=Bound(int, 64, 20_000)),
    "seed": OptionSpec(
        "int",
        "seed of every random choice (subsamples, search, fine-stage cameras)",
        limits=Bound(int, 0, 2**63 - 1),
        cli=Cli(),
    ),
    "fine_iterations": OptionSpec(
        "int", "fine stage: optimiser steps", limits=Bound(int, 0, 5000), cli=Cli(default=None)
    ),
    "fine_views": OptionSpec("int", "fine stage: rendered views", limits=Bound(int, 1, 64), cli=Cli(default=None)),
    "fine_lr": OptionSpec(
        "float", "fine stage: learning rate", limits=Bound(float, 0, 1, lo_open=True), cli=Cli(default=None)
    ),
    "fine_image_size": OptionSpec(
        "int", "fine stage: render size in pixels (square)", limits=Bound(int, 8, 1024), cli=Cli(default=None)
    ),
    "fine_loss": OptionSpec("choice", "fine stage: the image loss", choices=get_args(FineLoss)),
    "fine_on": OptionSpec(
        "choice",
        "fine stage: what it renders (paper Table 4 ablation)",
        choices=get_args(FineSignal),
        cli=Cli(default=None),
    ),
    # Guidance (gsa.align.guided): the CLI reads the hints from files (gsa.align.command).
    "init_transform": OptionSpec("hint", "start from this pose; only a local refinement runs"),
    "point_pairs": OptionSpec("hint", "picked point pairs: their Sim(3), then a local refinement"),
    "up_axes": OptionSpec("hint", "every pose keeps these up axes aligned"),
    "front_axes": OptionSpec("hint", "with up_axes: the turns about up are kept within 45° of these fronts agreeing"),
    "fixed_scale": OptionSpec(
        "float",
        "the answer's scale, kept through every stage",
        limits=Bound(float, 1e-6, 1e6),
        cli=Cli(flag="--scale", default=None, help="fix the scale of the answer", metavar="S", group="guidance"),
    ),
    "rigid": OptionSpec(
        "bool",
        "the two models are captures of one rigid object (two reconstructions, two scans), "
        "never another instance or a deformed copy",
        cli=_GUIDANCE,
    ),
    "semantic": OptionSpec(
        "choice",
        "a doubtful answer's pose is picked among its alternatives by pretrained DINOv2 features "
        "when a backbone is installed (auto), or never (off)",
        choices=AUTO_OFF,
        cli=Cli(
            default=None,
            group="guidance",
            help="a doubtful answer: pretrained DINOv2 features pick among the chosen pose and its "
            "alternatives (auto: when a backbone is installed or --backbone given; off: never; "
            "default: env GSA_SEMANTIC, else auto)",
        ),
    ),
    "photo_matches": OptionSpec(
        "choice",
        "two reconstructions (image sets, or folders `gsa reconstruct` wrote): register them "
        "by their photos' shared texture where enough matched SfM points agree (auto), or by "
        "their Gaussians alone (off)",
        choices=AUTO_OFF,
        cli=_GUIDANCE,
    ),
    "frame_snap": OptionSpec(
        "choice",
        "a doubtful answer between other instances: turned onto the relabellings of the two "
        "models' dominant surface-normal frames and checked among them (auto), or left as refined (off)",
        choices=AUTO_OFF,
        cli=_GUIDANCE,
    ),
    "learned": OptionSpec(
        "choice",
        "a doubtful answer: decided by the learned canonical head (each model's pose in its "
        "category's canonical frame, `gsa orient`) where both models' poses are sure (auto), or never (off)",
        choices=AUTO_OFF,
        cli=_GUIDANCE,
    ),
    "alternatives": OptionSpec(
        "choice",
        "list the poses worth picking (metrics alternatives) for doubtful and guided answers "
        "(doubtful), or for every answer (always)",
        choices=("doubtful", "always"),
        cli=_GUIDANCE,
    ),
    "criteria": OptionSpec("settings", "the thresholds every stage decides by (the library caller's)"),
}


def choice_error(name: str, choices: tuple, value: Any) -> str:
    """ "search must be auto, global or frames, got 'x'" (one of …, for more than three)."""
    words = [str(c) for c in choices]
    listed = f"one of {', '.join(words)}" if len(words) > 3 else " or ".join([", ".join(words[:-1]), words[-1]])
    return f"{name} must be {listed}, got {value!r}"


def check_option_values(options: Any) -> None:
    """AlignOptions' checks of its choices, bounds and true/false options (ValueError naming
    the option; a value of the wrong type may raise TypeError). Guidance and stages are
    checked by AlignOptions itself."""
    for name, spec in OPTIONS.items():
        if not hasattr(options, name):
            continue
        v = getattr(options, name)
        if spec.kind == "choice" and v not in spec.choices:
            raise ValueError(choice_error(name, spec.choices, v))
        if spec.kind == "bool" and not isinstance(v, bool):
            raise ValueError(f"{name} must be true or false, got {v!r}")
        if spec.bounds is not None and not (v is None and spec.none_ok) and not spec.bounds.contains(v):
            raise ValueError(f"{name} must be {spec.bounds.brief()}, got {v!r}")
