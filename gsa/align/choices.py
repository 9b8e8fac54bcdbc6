"""The choices of the alignment options, as `typing.Literal` types (a leaf module: the
option types, the fine stage and the CLI import it without importing each other)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, get_args

Progress = Callable[[str, float], None]  # progress(stage, fraction in [0, 1])
StageName = Literal["auto", "coarse", "fine"]
FeatureMode = Literal["auto", "file", "canonical", "spheremap", "dinov2"]
ExtractorMode = Literal["spheremap", "dinov2"]
SearchMode = Literal["auto", "global", "frames"]
RefineMode = Literal["auto", "on", "off"]
SceneMode = Literal["auto", "on", "off"]
FineLoss = Literal["smooth_l1", "l1", "l2"]
FineSignal = Literal["features", "colors"]
RenderBackend = Literal["auto", "cpu", "cuda", "reference"]  # gsa.render.BACKENDS
FEATURE_MODES: tuple[FeatureMode, ...] = get_args(FeatureMode)
EXTRACTOR_MODES: tuple[ExtractorMode, ...] = get_args(ExtractorMode)
STAGE_CHOICES: tuple[tuple[StageName, ...], ...] = (("auto",), ("coarse",), ("coarse", "fine"))
