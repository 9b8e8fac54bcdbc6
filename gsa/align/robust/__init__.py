"""Robust global registration for models without learned features.

One canonical frame per model (gsa.canonical) moves as soon as a capture
misses a side, carries floaters or is a different instance, and colour plays no
part in it. This module does not trust any single frame:

1. `anchors`: floaters are dropped (low opacity, or alone in their voxel) and
   each model is voxel-downsampled to ~2k anchors with a mean position, a mean
   CIELAB colour and a weight. The voxel size follows each model's own size, so
   anchors are scale-free.
2. `global_search`: every rotation of a near-uniform SO(3) sample (super-Fibonacci,
   plus the canonical-frame relabellings, which make duplicates exact) is placed by
   matching centres and RMS radii, pulled by vectorised capture steps (translation and
   Horn scale from the anchors within a shrinking radius), and scored through a grid of
   nearest-anchor indices (an exact distance transform), both ways round; the leaders
   also try a grid of offsets and scale factors.
3. The best distinct rotations are refined by a robust, bidirectional, colour-matched
   ICP with Horn's symmetric scale on the anchors (both directions, so a partial model
   cannot shrink into the other), and scored by how much of the two models overlap
   (truncated distances both ways), a close pair of the wrong colour counting against
   a pose as far as the two models share a palette: colour is what tells the sides of
   a symmetric object apart. Where poses tie in geometry (a symmetric shape), the best
   also try small turns by their coloured score, which the ICP's pull misses.
4. The margin to the best distinct alternative and the overlap itself (how much, and how
   well it coincides at full resolution) give a confidence; near-ties are reported as
   ambiguous with their poses. Where the palettes are shared, a pose whose colours disagree
   beyond the models' own colour noise yields to a consistent one and is doubtful
   (`colour_mismatch`); where no pose makes them agree (another paint), geometry ranks.

Colours are compared after `match_exposure` (both models' anchors in one exposure and
white balance, the brighter capture's, the darker raised and clipped at white), and the
full-resolution refinement ends point-to-plane on the target Gaussians' normals where the
two captures coincide.

Modules: anchoring (1, and the colour trust), search (2-3, with the numba scoring and
capture kernels), placement (the widened search for doubtful answers), poses (one
pose's score, the anchor ICP, the decision), refinement (`refine`: the full-resolution refinement,
frame relabellings, verdict).

Tunables are fields of frozen option dataclasses, each function taking one (None: the defaults):
SearchOptions (what the search tries) holds PoseCriteria (how poses are scored and decided,
with the PaletteOptions of the colour comparison); RefineCriteria (the full-resolution
refinement), VerdictCriteria (confidence and doubt).
"""

from gsa.align.robust.anchoring import (
    Anchors,
    NearestGrid,
    PaletteOptions,
    anchors,
    colour_weight,
    exposure_gain,
    floater_mask,
    in_one_exposure,
    match_exposure,
    pose_gain,
    solid_voxels,
    srgb_to_lab,
    subsample,
    voxel_anchors,
    voxelise,
)
from gsa.align.robust.matching import matched_poses
from gsa.align.robust.placement import box_lattice, placed_starts
from gsa.align.robust.poses import (
    Candidate,
    Convergence,
    PoseCriteria,
    SearchResult,
    bidirectional_icp,
    colour_noise,
    colour_trust,
    decide,
    dedupe,
    prefer_among_tied,
    rotation_offset_deg,
    score_pose,
    with_given_pose,
)
from gsa.align.robust.refinement import (
    RIGID_REFINE,
    RefineCriteria,
    VerdictCriteria,
    coincidence,
    frame_relabellings,
    overlap_fraction,
    overlap_unconfirmed,
    refine,
    verdict,
)
from gsa.align.robust.search import SearchOptions, global_search, held_within_reach

__all__ = [
    "RIGID_REFINE",
    "Anchors",
    "Candidate",
    "Convergence",
    "NearestGrid",
    "PaletteOptions",
    "PoseCriteria",
    "RefineCriteria",
    "SearchOptions",
    "SearchResult",
    "VerdictCriteria",
    "anchors",
    "bidirectional_icp",
    "coincidence",
    "colour_noise",
    "colour_trust",
    "colour_weight",
    "decide",
    "dedupe",
    "prefer_among_tied",
    "floater_mask",
    "frame_relabellings",
    "global_search",
    "held_within_reach",
    "match_exposure",
    "pose_gain",
    "exposure_gain",
    "in_one_exposure",
    "box_lattice",
    "matched_poses",
    "placed_starts",
    "overlap_fraction",
    "overlap_unconfirmed",
    "refine",
    "rotation_offset_deg",
    "score_pose",
    "solid_voxels",
    "srgb_to_lab",
    "subsample",
    "verdict",
    "with_given_pose",
    "voxel_anchors",
    "voxelise",
]
