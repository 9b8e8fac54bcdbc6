"""Scene-scale registration: the test that tells a room from an object, and
the scene path align() takes for rooms.

*The test* (`scene_structure`, on each model's floater-free anchors - at least
test_density Gaussians each, so surfaces stay connected - hence scale-free and
O(anchors)): a captured room is a shell of large planes (floor, walls, ceiling) with
separate things standing inside it; an object is its parts alone, or (a bus, a box) a
shell with nothing inside. Planes are found by sequential RANSAC on the anchors (inliers
within a quarter voxel that face the plane's way). A *shell plane* is large (its inliers
span at least shell_span of the extent and hold at least shell_share of the anchor
weight) and bounds the model (at most outside_share of the weight beyond it). The
anchors off the shell planes are then grouped into connected *parts* (linked within 1.5
voxels); a part counts when it holds at least part_weight of the weight, has a body (at
least a voxel thick: not the sliver a plane's band leaves), is at most part_size of the
extent long and lies inside every shell plane. The model is a scene when at least
shell_planes shell planes hold shell_weight of the weight and either at least
content_parts parts hold content_weight, or the model holds at least scene_gaussians
Gaussians: a planar shell that large is a site whichever way its parts fall, and the
object path's full-resolution trees are what stop scaling there (a large box-like
object then takes the scene path too, which aligns it without the frame relabellings).
The test runs on at most test_sample Gaussians, so it costs the same at any size.
Under `scene="auto"` both models must pass; `"on"` forces the path, `"off"` never
takes it. Measured (docs/benchmarks.md, "Scenes"): no pair of the object protocols
(dup, same, category, partial, noisy, deform, symmetric; quick and full sizes) passes;
on small rooms the parts condition is conservative (a capture holding two or three
pieces of furniture can miss it), and a room it misses still gets the object path.

*The scene path* (`align_scene`) differs from the object path where rooms differ from
objects:
- more anchors (scene_anchors): 2000 voxels over a 9 m room are 20 cm wide, and the
  furniture that breaks the shell's symmetries is what the search must see;
- no canonical-frame relabellings: a room's principal axes carry no meaning for another
  partial capture of it;
- a translation sweep after the search (`translation_sweep`): the best rotations slide
  over the whole target, since partial captures' centroids lie far apart and planes let
  a pose slide;
- colours compared under one exposure (`robust.match_exposure`, as on the object path): two captures taken apart
  differ in exposure and white balance, and the object path's colour trust would drop
  to zero, leaving geometry alone to tell a room's mirror-like halves apart;
- the full-resolution refinement (robust.refine: bidirectional trimmed ICP, stopping at
  the overlap) runs on at most refine_cloud Gaussians per capture drawn at random from
  the floater-free ones, with their full-resolution positions: trees and neighbour
  tables stay bounded, so time and memory grow linearly only through the O(N)
  anchoring and sampling passes; it ends point-to-plane on the target Gaussians' normals
  where the captures coincide, as on the object path;
- no canonical features (and no feature metrics) and no fine stage, which renders
  every Gaussian per view.

The tunables named above in lower case are the fields of `SceneOptions`; `choose` (and the
functions it and the scene path call) take one, None meaning the defaults; `align_scene`
reads every criterion from AlignOptions.criteria (its `scene`, and the search's, pose,
refinement and verdict criteria, as the object path does).

The package, by what each part aligns: `options` (SceneOptions), `choice` (the scene
test on both models and the choice it makes: SceneChoice, choose, check_models),
`rooms` (the room test: scene_structure, Structure), `sites` (the site test and the
site search: site_structure, Site, site_search), `common` (what both share: the path's
anchors, the tests' normals and parts, the translation sweep) and `path` (align_scene,
the path both take). Every public name is importable from here.
"""

from gsa.align.scene.choice import SceneChoice, check_models, choose, test_anchor_count
from gsa.align.scene.common import scene_anchors, translation_sweep
from gsa.align.scene.options import SceneOptions
from gsa.align.scene.path import align_scene
from gsa.align.scene.rooms import Structure, scene_structure
from gsa.align.scene.sites import Site, site_search, site_structure

__all__ = [
    "SceneChoice",
    "SceneOptions",
    "Site",
    "Structure",
    "align_scene",
    "check_models",
    "choose",
    "scene_anchors",
    "scene_structure",
    "site_search",
    "site_structure",
    "test_anchor_count",
    "translation_sweep",
]
