"""The tunables of the scene test and the scene path (gsa.align.scene)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneOptions:
    """The tunables of the scene test and the scene path (module docstring); the defaults
    are the values benchmarked in docs/benchmarks.md ("Scenes", "Outdoor sites"). The
    tests' quantities are fractions of the model's own extent or anchor weight, so the
    tests are scale-free."""

    # The room test (scene_structure).
    shell_span: float = 0.5  # a shell plane's inliers span this much of the extent: floors and walls cross a room
    shell_share: float = 0.03  # and hold this much of the weight (half of it ends the plane search)
    outside_share: float = 0.03  # weight beyond a shell plane at most: it bounds the model, strays aside
    shell_planes: int = 3  # shell planes a room needs: a floor and two walls at the least
    shell_weight: float = 0.4  # weight on the shell planes a room needs: most of a room's surface is its shell
    content_parts: int = 3  # parts inside the shell a room needs: a box-like object (a bus) has none
    content_weight: float = 0.03  # weight a room's (or a site's) parts hold together: more than a few strays
    part_weight: float = 0.005  # weight one part holds at least: smaller groups are noise, not furniture
    part_size: float = 0.35  # a part's length at most: longer is the room's structure, not a thing inside it
    max_planes: int = 8  # planes sought: a box room's six and two tries for edge layers merged into one
    facing_deg: float = 25.0  # a plane's inliers face its way within this: lattice rows lie on any plane
    test_density: int = 16  # Gaussians per test anchor at least: sparser voxels break surfaces into fragments
    test_sample: int = 200_000  # Gaussians the test runs on at most: it costs the same at any size
    # A shell or ground this large is a scene whatever its parts: the object path's trees stop scaling there.
    scene_gaussians: int = 400_000
    voxel_probe: int = 200_000  # Gaussians the anchor voxel is searched on: a few thousand voxels fill alike
    # The site test (site_structure).
    # Ground normals within this of the up axis: slopes are ground too. At 30 a third of rolling
    # hills (gsa.synth.terrain) fell off the ground and 2 of 16 terrain pairs failed the test.
    ground_deg: float = 40.0
    # What covers a ground column (an object's top over its underside, a canopy): a surface
    # facing up or down within this, above the ground. Steeper slopes of what stands on a
    # site (cone and ball flanks) cover nothing: the sky share was set on objects at 30.
    cover_deg: float = 30.0
    ground_band: float = 1.5  # the ground's band above each column's lowest up-facing anchor, in anchor voxels
    ground_share: float = 0.25  # weight on the ground a site needs: a site is mostly its ground
    sky_share: float = 0.8  # ground columns open to the sky a site needs: an object's underside has its top above it
    ground_span: float = 0.3  # the ground's span across (the smaller horizontal side) over the extent, at least
    site_height: float = 0.5  # a site's height over its width at most: a site is flat
    site_parts: int = 1  # things standing on the ground a site needs (trees, rocks, benches)
    site_anchors: int = 300  # test anchors a site needs: with fewer, a thin object (a wing) is one layer like a ground
    sky_open: float = 0.95  # ground columns open to the sky that make a site with nothing on it (a lawn)
    ground_fit_rounds: int = 2  # the site path's up axis refitted to its ground plane this often (_site_of)
    ground_fit_keep: float = 0.8  # share of the ground's anchors nearest the plane it is refitted on
    # The scene path (align_scene).
    scene_anchors: int = 6000  # anchors per model at least: the furniture that breaks a shell's symmetries must show
    site_yaw_deg: float = 5.0  # yaw step of the site search's up-aligned rotations
    site_ground_keep: float = 0.35  # the ground's share of the site search's anchors: what stands on it decides
    # The doubtful site answer's placed starts (_placed).
    site_place_points: int = 48  # anchors per side scored per placed position (robust.placed_starts)
    site_place_step: float = 0.25  # its lattice step in the target site's frame, fraction of the target radius
    site_place_yaw_deg: float = 5.0  # its yaw step
    site_place_truncation: float = 0.2  # its score distance, coloured as the sweep: within a step of any offset
    # Its scales, times the radius ratio: the radii of partial captures are ~30 % off.
    site_place_scales: tuple[float, ...] = (0.75, 1.0, 1.33)
    site_place_top: int = 6  # distinct placements refined by the anchor ICP
    climb_anchors: int = 3000  # anchors per side the climbs score on at most
    climb_top: int = 2  # best placed starts of a doubtful site answer that climb the score (_climb), beside its best
    climb_rounds: int = 6  # step halvings of each climb
    climb_turn_deg: float = 4.0  # its first turn
    climb_shift: float = 0.1  # its first shift, fraction of the target radius
    climb_scale: float = 0.08  # its first log-scale step
    refine_cloud: int = 400_000  # Gaussians per capture the refinement runs on at most: trees and tables stay bounded
    # translation_sweep; lengths are fractions of the target's anchor radius.
    sweep_top: int = 3  # the search's best distinct rotations slid over the target
    sweep_step: float = 0.15  # lattice step, below the truncation so no offset falls between
    sweep_truncation: float = 0.3  # truncation of the offsets' score
    sweep_points: int = 128  # source anchors scored per offset
    sweep_keep: int = 2  # best distinct offsets per rotation refined by the anchor ICP
    sweep_icp: int = 60  # iterations of that ICP
