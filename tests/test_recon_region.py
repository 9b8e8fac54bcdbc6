"""An object capture keeps only the region its cameras look at (gsa.recon.region, real photo sets):
far background the masks let through is dropped at init and pruned in training; a capture whose
cameras do not converge keeps everything."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from gsa.recon.density import Adam, densify_and_prune
from gsa.recon.region import object_region
from gsa.recon.train import PRESETS, filter_points_by_masks, init_selection, train_gaussians
from gsa.render.cameras import Cameras, look_at, orbit_cameras


def _object_rig(n=10, radius=4.0):
    return orbit_cameras([0.3, -0.2, 0.1], radius, n, width=48, fov=50.0, elevations=np.linspace(10, 40, n))


def _object_and_far_points(cams, n_far=8, far=6.0, seed=0):
    """Object points in a ball of 0.6 around the looked-at point, plus n_far points of distant
    background straight behind the object along some cameras' axes (so they are in view)."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.3, -0.2, 0.1])
    obj = centre + rng.normal(0, 0.25, (300, 3)).clip(-0.6, 0.6)
    axes = cams.viewmats[:n_far, 2, :3]
    far_pts = cams.centers()[:n_far] + axes * far * 4.0  # 6x the camera distance from the cameras
    return np.concatenate([obj, far_pts]), len(obj)


def _framed_masks(cams, border=2):
    """Masks that cut only a thin frame: everything in view counts as object."""
    m = np.zeros((len(cams), cams.height, cams.width), bool)
    m[:, border:-border, border:-border] = True
    return m


def test_object_capture_drops_far_init_points():
    cams = _object_rig()
    pts, n_obj = _object_and_far_points(cams)
    region = object_region(cams)
    assert region is not None
    np.testing.assert_allclose(region.centre, [0.3, -0.2, 0.1], atol=1e-6)
    assert abs(region.camera_distance - 4.0) < 1e-6 and abs(region.radius - 8.0) < 1e-6
    masks = _framed_masks(cams)
    by_masks = filter_points_by_masks(pts, cams, masks)
    assert by_masks[n_obj:].sum() >= 6  # the masks let the far points through ...
    keep, reg, info = init_selection(pts, cams, masks)
    assert reg is not None
    assert keep[:n_obj].all() and not keep[n_obj:].any()  # ... the region does not
    assert info["sfm_points_dropped"] == by_masks[n_obj:].sum()


def test_scene_like_rigs_keep_everything():
    rng = np.random.default_rng(1)
    f = 40.0
    # forward-facing: cameras side by side, parallel axes
    fwd = np.stack([look_at([x, 0.0, 0.0], [x, 0.0, 10.0], up=(0, -1, 0)) for x in np.linspace(-2, 2, 8)])
    # outward: cameras on a ring looking away from its centre (a room scanned from inside)
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros(8)], 1)
    out = np.stack([look_at(c, 3 * c) for c in ring])
    for views in (fwd, out):
        cams = Cameras(views, f, f, 24, 24, 48, 48)
        assert object_region(cams) is None
        pts = rng.normal(0, 1, (200, 3)) * [3, 3, 1] + [0, 0, 8]
        pts = np.concatenate([pts, [[0, 0, 200.0], [1, 1, 300.0]]])
        keep, reg, info = init_selection(pts, cams, np.ones((8, 48, 48), bool))
        assert reg is None and info == {}
    # an object rig with nothing masked (masks "none") keeps its background too
    cams = _object_rig()
    pts, _ = _object_and_far_points(cams)
    keep, reg, info = init_selection(pts, cams, np.ones((len(cams), cams.height, cams.width), bool))
    assert keep.all() and reg is None


def test_density_control_prunes_gaussians_that_leave_the_region():
    n = 12
    means = torch.zeros(n, 3)
    means[:3] = torch.tensor([[9.0, 0, 0], [0, -12.0, 0], [0, 0, 30.0]])  # outside a ball of 8
    params = {
        "means": means.requires_grad_(True),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1).requires_grad_(True),
        "log_scales": torch.full((n, 3), -3.0, requires_grad=True),
        "opacity": torch.zeros(n, requires_grad=True),
    }
    opt = Adam(params, dict.fromkeys(params, 1e-3))
    cfg = PRESETS["cpu"]
    rng = np.random.default_rng(0)
    assert densify_and_prune(opt, None, cfg, 100.0, rng, densify=False) == 0
    assert len(opt.params["means"]) == n
    pruned = densify_and_prune(opt, None, cfg, 100.0, rng, densify=False, region=(torch.zeros(3), 8.0))
    assert pruned == 3 and len(opt.params["means"]) == n - 3


def test_training_reports_and_keeps_no_far_background():
    cams = _object_rig(n=8)
    pts, n_obj = _object_and_far_points(cams)
    rng = np.random.default_rng(2)
    cols = rng.uniform(0, 1, (len(pts), 3))
    imgs = rng.uniform(0, 1, (len(cams), cams.height, cams.width, 3)).astype(np.float32)
    cfg = replace(
        PRESETS["cpu"], iterations=9, resolution=24, densify_from=3, densify_until=8, densify_every=3, init_points=0
    )
    masks = _framed_masks(cams)
    res = train_gaussians(imgs, masks, cams, pts, cols, cfg, features="none")
    assert res.region["sfm_points_dropped"] == filter_points_by_masks(pts, cams, masks)[n_obj:].sum() > 0
    assert res.region["gaussians_pruned"] >= 0
    centre, radius = np.array(res.region["centre"]), res.region["radius"]
    assert np.linalg.norm(res.model.means - centre, axis=1).max() <= radius
