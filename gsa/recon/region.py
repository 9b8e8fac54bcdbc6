"""The region an object capture looks at: where to keep Gaussians (real photo sets).

In an object capture the cameras stand around the subject and their optical axes converge on it.
The point nearest every axis (least squares) is where the subject is, and the cameras' own
distances to it give the capture's scale. Nothing of the subject lies farther from that point
than the cameras stand, so what the SfM triangulated well beyond the camera rig (far trees,
buildings, sky seen behind the subject, kept when the object masks let them through) is distant
background: it inflates the model's extent and skews everything that normalises by it (the
alignment's scale refinement). `object_region` returns a ball of `RIG_FACTOR` x the farthest
camera's distance (twice the rig: room for a subject that reaches past the cameras in some
direction, a plinth, a table) — no number tuned to a photo set.

A capture whose cameras do not converge (a scene walked through, a forward-facing or outward
rig) has no such region: `object_region` returns None when the least-squares point is not in
front of every camera and inside its image, and nothing is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa.render.cameras import Cameras

RIG_FACTOR = 2.0  # the kept ball's radius, in units of the farthest camera's distance


@dataclass(frozen=True)
class Region:
    centre: np.ndarray  # (3,) the point the optical axes converge on
    camera_distance: float  # the median camera distance from it
    radius: float  # RIG_FACTOR x the farthest camera distance

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Bool (N,): points within the region's ball."""
        return np.linalg.norm(np.asarray(points, np.float64) - self.centre, axis=1) <= self.radius

    def as_dict(self) -> dict:
        return {
            "centre": [float(x) for x in self.centre],
            "camera_distance": self.camera_distance,
            "radius": self.radius,
        }


def converged_point(cameras: Cameras) -> np.ndarray | None:
    """The point nearest every camera's optical axis (least squares), or None when the axes
    are (numerically) parallel."""
    centres = cameras.centers()
    axes = np.asarray(cameras.viewmats[:, 2, :3], np.float64)
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # onto each axis's normal plane
    a = proj.sum(axis=0)
    if np.linalg.cond(a) > 1e8:
        return None
    return np.linalg.solve(a, np.einsum("cij,cj->i", proj, centres))


def object_region(cameras: Cameras) -> Region | None:
    """The ball an object capture looks at (module docstring), or None for a capture whose
    cameras do not converge: fewer than 3 cameras, parallel axes, or a converged point that is
    behind a camera or outside its image."""
    if len(cameras) < 3:
        return None
    point = converged_point(cameras)
    if point is None:
        return None
    vm = np.asarray(cameras.viewmats, np.float64)
    pc = np.einsum("cij,j->ci", vm[:, :3, :3], point) + vm[:, :3, 3]
    if not np.all(pc[:, 2] > 0):
        return None
    u = cameras.fx * pc[:, 0] / pc[:, 2] + cameras.cx
    v = cameras.fy * pc[:, 1] / pc[:, 2] + cameras.cy
    if not np.all((u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)):
        return None
    dist = np.linalg.norm(cameras.centers() - point, axis=1)
    return Region(point, float(np.median(dist)), RIG_FACTOR * float(dist.max()))
