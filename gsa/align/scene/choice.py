"""Whether align() takes the scene path (gsa.align.scene): the scene test on both models
under `scene` auto/on/off, and the pipeline's input checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa.align import robust
from gsa.align.coarse import AlignmentError
from gsa.align.scene.common import scene_anchors
from gsa.align.scene.options import SceneOptions
from gsa.align.scene.rooms import Structure, scene_structure
from gsa.model import GaussianModel, ModelError


@dataclass
class SceneChoice:
    """Whether align() takes the scene path, and why (result metrics["scene"])."""

    run: bool
    reason: str
    source: Structure | None = None
    target: Structure | None = None

    def to_dict(self) -> dict:
        out: dict = {"ran": self.run, "reason": self.reason}
        if self.source is not None and self.target is not None:
            out["test"] = {"source": self.source.to_dict(), "target": self.target.to_dict()}
        return out


def check_models(source: GaussianModel, target: GaussianModel) -> None:
    """The pipeline's input checks (AlignmentError with the reason)."""
    try:
        source.validate("source")
        target.validate("target")
    except ModelError as exc:
        raise AlignmentError(str(exc)) from None
    for name, m in (("source", source), ("target", target)):
        if len(m) < 3:
            raise AlignmentError(f"{name} has {len(m)} Gaussians; at least 3 are needed")


def choose(
    source: GaussianModel,
    target: GaussianModel,
    mode: str,
    eligible: bool,
    anchor_count: int,
    seed: int = 0,
    options: SceneOptions | None = None,
):
    """The scene test under `mode` (auto/on/off). eligible: the object path would run its
    robust global search (no learned features); auto only tests then."""
    if mode == "off":
        return SceneChoice(False, "scene=off")
    if mode == "on":
        return SceneChoice(True, "scene=on")
    if not eligible:
        return SceneChoice(False, "auto: learned features or a non-global search requested")
    check_models(source, target)
    # scene_anchors, not robust.anchors: the same summary, many times faster at millions
    # of Gaussians; the object path makes its own.
    o = options or SceneOptions()
    s, t = (scene_structure(_test_anchors(m, anchor_count, seed, o), seed, len(m), o) for m in (source, target))
    if s.is_room and t.is_room:
        reason = "auto: both models are shells of large planes with things inside (scene test passed)"
    elif s.is_scene and t.is_scene:
        reason = "auto: both models are open grounds with things standing on them (site test passed)"
    else:
        which = [name for name, st in (("source", s), ("target", t)) if not st.is_scene]
        reason = f"auto: the {' and '.join(which)} failed the scene test"
    return SceneChoice(s.is_scene and t.is_scene, reason, s, t)


def _test_anchors(model: GaussianModel, anchor_count: int, seed: int, o: SceneOptions) -> robust.Anchors:
    """The test's anchors, from at most test_sample Gaussians drawn at random: the test
    costs the same at any size, and anchors of a few thousand voxels do not change."""
    if len(model) > o.test_sample:
        model = model.subset(np.sort(np.random.default_rng(seed).choice(len(model), o.test_sample, replace=False)))
    return scene_anchors(model, test_anchor_count(len(model), anchor_count, o), seed, o)


def test_anchor_count(gaussians: int, anchor_count: int, options: SceneOptions | None = None) -> int:
    """The object path's anchor count, but at least test_density Gaussians per anchor: the
    test follows surfaces through neighbouring anchors, and a voxel of one or two
    Gaussians leaves holes that break a surface into fragments."""
    return int(max(min(anchor_count, gaussians // (options or SceneOptions()).test_density), 100))
