"""The criteria in force: every threshold align()'s stages decide by, in one frozen bundle
(`AlignOptions.criteria`; None: these defaults). The pipeline hands each stage the part it
reads, and no stage makes fresh defaults where the caller's are available: a criterion
changed here moves the search, the refinement, the verdict, the frame snap, the open ends,
the guidance and the scene path alike.

    from dataclasses import replace
    from gsa.align.criteria import Criteria
    from gsa.align.robust import PoseCriteria

    opts = AlignOptions(criteria=Criteria(pose=replace(PoseCriteria(), score_tie=0.01)))

The search's own counts live in `search` (robust.SearchOptions); its `rotations` and `seed`
come from AlignOptions (search_rotations, seed) and its pose criteria from `pose`, so those
three stay at their defaults here (one way to set each)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from gsa.align.guided import GuidanceCriteria
from gsa.align.learned import LearnedCriteria
from gsa.align.open_ends import OpenEndCriteria
from gsa.align.robust import PoseCriteria, RefineCriteria, SearchOptions, VerdictCriteria
from gsa.align.scene.options import SceneOptions
from gsa.align.semantic import SemanticCriteria
from gsa.align.spin import SpinCriteria

__all__ = ["Criteria"]


@dataclass(frozen=True)
class Criteria:
    """Every stage's criteria (module docstring); the defaults are the benchmarked values."""

    pose: PoseCriteria = field(default_factory=PoseCriteria)  # how poses are scored and decided (robust.poses)
    search: SearchOptions = field(default_factory=SearchOptions)  # what the global search tries (robust.search)
    refine: RefineCriteria = field(default_factory=RefineCriteria)  # the full-resolution refinement
    verdict: VerdictCriteria = field(default_factory=VerdictCriteria)  # confidence and doubt
    guidance: GuidanceCriteria = field(default_factory=GuidanceCriteria)  # a user's hints (gsa.align.guided)
    scene: SceneOptions = field(default_factory=SceneOptions)  # the scene test and path (gsa.align.scene)
    open_ends: OpenEndCriteria = field(default_factory=OpenEndCriteria)  # gsa.align.open_ends
    semantic: SemanticCriteria = field(default_factory=SemanticCriteria)  # the semantic tie-break
    learned: LearnedCriteria = field(default_factory=LearnedCriteria)  # the learned canonical head's route
    spin: SpinCriteria = field(default_factory=SpinCriteria)  # the turn about a nearly turn-symmetric axis

    def __post_init__(self) -> None:
        defaults = SearchOptions()
        for name, where in (
            ("rotations", "AlignOptions.search_rotations"),
            ("seed", "AlignOptions.seed"),
            ("criteria", "Criteria.pose"),
        ):
            if getattr(self.search, name) != getattr(defaults, name):
                raise ValueError(f"Criteria.search.{name} is set by {where}, not here")

    def search_options(self, rotations: int, seed: int, **changes) -> SearchOptions:
        """The global search's options: `search` with the rotations and seed of AlignOptions
        and the pose criteria in force (changes: the path's own, such as offer_turn_axes)."""
        return replace(self.search, rotations=rotations, seed=seed, criteria=self.pose, **changes)

    def refinement(self, rigid: bool) -> RefineCriteria:
        """The refinement's criteria; `rigid` (captures of one rigid object or place): never
        averaged as a deformed copy (robust.RIGID_REFINE's one change)."""
        return replace(self.refine, deformable=False) if rigid else self.refine


DEFAULT = Criteria()
