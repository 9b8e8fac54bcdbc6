"""Rooms (gsa.align.scene): the room test (`scene_structure`: a shell of large planes with
separate things inside it), which falls back on the site test (gsa.align.scene.sites)
where it fails, and what it saw (`Structure`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gsa.align import robust
from gsa.align.scene.common import _anchor_normals, _inner_parts
from gsa.align.scene.options import SceneOptions
from gsa.align.scene.sites import Site, site_structure


@dataclass
class Structure:
    """What the scene test saw on one model."""

    shell_planes: int
    shell_weight: float
    parts: int  # separate small things inside the shell
    parts_weight: float
    planes: list[dict]

    gaussians: int = 0
    site: Site | None = None  # the site test, where the shell test failed
    options: SceneOptions = field(default_factory=SceneOptions, repr=False)  # the thresholds the test used

    @property
    def shell(self) -> bool:
        o = self.options
        return self.shell_planes >= o.shell_planes and self.shell_weight >= o.shell_weight

    @property
    def is_room(self) -> bool:
        o = self.options
        things_inside = self.parts >= o.content_parts and self.parts_weight >= o.content_weight
        return self.shell and (things_inside or self.gaussians >= o.scene_gaussians)

    @property
    def is_site(self) -> bool:
        return not self.is_room and self.site is not None and self.site.is_site

    @property
    def is_scene(self) -> bool:
        return self.is_room or self.is_site

    def to_dict(self) -> dict:
        out = {
            "shell_planes": self.shell_planes,
            "shell_weight": round(self.shell_weight, 4),
            "parts": self.parts,
            "parts_weight": round(self.parts_weight, 4),
            "gaussians": self.gaussians,
            "is_scene": self.is_scene,
            "kind": "room" if self.is_room else "site" if self.is_site else None,
        }
        if self.site is not None:
            out["site"] = self.site.to_dict()
        return out


def scene_structure(
    anchors: robust.Anchors, seed: int = 0, gaussians: int = 0, options: SceneOptions | None = None
) -> Structure:
    """Shell planes and their weight, then the separate parts inside them (module docstring)."""
    o = options or SceneOptions()
    pts = anchors.points
    w = anchors.weights / anchors.weights.sum()
    extent = float(np.max(np.ptp(pts, axis=0)))
    # The anchor voxel. Anchors are voxel means, so those of a plane lie on it to within
    # noise: a quarter voxel separates them from things standing on it.
    voxel = extent / np.sqrt(len(pts))
    band = 0.25 * voxel
    rng = np.random.default_rng(seed)
    # Anchors sit on a voxel lattice, so any plane through a row of voxels holds a line of
    # them on every surface it crosses; a plane's inliers must also face its way.
    normals = _anchor_normals(pts)
    free = np.ones(len(pts), bool)
    planes: list[dict] = []
    for _ in range(o.max_planes):
        idx = np.flatnonzero(free)
        if len(idx) < 50:
            break
        normal, offset, inliers = _ransac_plane(pts[idx], normals[idx], w[idx], band, rng, o.facing_deg)
        if normal is None:
            break
        rows = idx[inliers]
        share = float(w[rows].sum())
        if share < 0.5 * o.shell_share:
            break
        free[rows] = False
        # Voxel anchors along an edge (a wall's bottom row of voxels holds floor too) form
        # a second layer beside the plane: it belongs to the plane found first.
        twin = next((p for p in planes if _same_plane(p, normal, offset, 2 * voxel, o.facing_deg)), None)
        if twin is not None:
            twin["share"] += share
            twin["shell"] = _is_shell(twin["share"], twin["span"], twin["outside"], o)
            continue
        signed = pts @ normal - offset
        beyond_pos, beyond_neg = float(w[signed > 2 * voxel].sum()), float(w[signed < -2 * voxel].sum())
        if beyond_neg > beyond_pos:  # orient the normal inwards (towards the model's weight)
            normal, offset = -normal, -offset
            beyond_pos, beyond_neg = beyond_neg, beyond_pos
        span = _inplane_span(pts[rows], normal) / extent
        planes.append(
            {
                "normal": normal,
                "offset": offset,
                "share": share,
                "span": span,
                "outside": beyond_neg,
                "shell": _is_shell(share, span, beyond_neg, o),
            }
        )
    shell = [p for p in planes if p["shell"]]
    on_shell = np.zeros(len(pts), bool)
    for p in shell:
        on_shell |= np.abs(pts @ p["normal"] - p["offset"]) <= voxel
    shell_weight = float(w[on_shell].sum()) if shell else 0.0
    parts, parts_weight = 0, 0.0
    if len(shell) >= o.shell_planes and shell_weight >= o.shell_weight:  # else decided: skip the parts
        parts, parts_weight = _inner_parts(pts, w, ~on_shell, shell, voxel, extent, o)
    out = Structure(len(shell), shell_weight, parts, parts_weight, planes, gaussians, options=o)
    if not out.is_room:
        out.site = site_structure(pts, w, normals, voxel, extent, gaussians, o)
    return out


def _is_shell(share: float, span: float, outside: float, o: SceneOptions) -> bool:
    return bool(share >= o.shell_share and span >= o.shell_span and outside <= o.outside_share)


def _same_plane(plane: dict, normal: np.ndarray, offset: float, gap: float, facing_deg: float) -> bool:
    cos = float(plane["normal"] @ normal)
    return abs(cos) >= np.cos(np.radians(facing_deg)) and abs(plane["offset"] - np.sign(cos) * offset) <= gap


def _ransac_plane(
    pts: np.ndarray,
    normals: np.ndarray,
    w: np.ndarray,
    band: float,
    rng: np.random.Generator,
    facing_deg: float,
    trials: int = 128,
):
    """The plane through an anchor, along its normal, holding the most anchor weight
    within `band` among anchors facing its way (within facing_deg), refitted to those
    inliers by least squares; vectorised over all trials."""
    if len(pts) < 3:
        return None, 0.0, None
    seeds = rng.integers(0, len(pts), trials)
    n, a = normals[seeds], pts[seeds]
    cos = np.cos(np.radians(facing_deg))
    inl = (np.abs(pts @ n.T - np.sum(n * a, axis=1)) <= band) & (np.abs(normals @ n.T) >= cos)
    inliers = inl[:, int(np.argmax(w @ inl))]
    # A seed's normal is a few degrees off, which over the model's extent leaves the band:
    # refit on the facing anchors within a voxel (4 bands), then count within the band.
    for grow in (4.0, 2.0, 1.0):
        if inliers.sum() < 3:
            return None, 0.0, None
        # Unweighted: an anchor's weight counts Gaussians, and the heaviest ones near a
        # floor are the furniture standing on it, whose voxel means sit above it.
        centre = pts[inliers].mean(0)
        _, _, vt = np.linalg.svd(pts[inliers] - centre, full_matrices=False)
        normal = vt[2]
        offset = float(normal @ centre)
        inliers = (np.abs(pts @ normal - offset) <= grow * band) & (np.abs(normals @ normal) >= cos)
    if inliers.sum() < 3:
        return None, 0.0, None
    return normal, offset, inliers


def _inplane_span(pts: np.ndarray, normal: np.ndarray) -> float:
    """Longer in-plane extent of a plane's inliers (5th to 95th percentile: robust to strays)."""
    if len(pts) < 3:
        return 0.0
    centred = pts - pts.mean(0)
    flat = centred - np.outer(centred @ normal, normal)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    along = flat @ vt[0]
    lo, hi = np.percentile(along, [5, 95])
    return float(hi - lo)
