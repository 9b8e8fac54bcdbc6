"""A second outdoor generator, written apart from gsa.synth.sites so that the site path is
measured on scenes it was not designed on: a rolling heightfield (a sum of plane waves,
slopes past 30 degrees), primitive props (boxes, balls, pillars, cones) in solid colours
standing on it, isotropic Gaussians in random orientations, and Y up (make_site is Z up).

make_terrain        one sampling of a terrain scene (deterministic by layout and sample seed)
terrain_captures    two partial captures of it: independent samplings, each keeping 60-80 %
                    of the scene along one horizontal direction, the target under a random
                    Sim(3) (any rotation, scale 0.2-5)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa.model import GaussianModel
from gsa.sh import rgb_to_sh_dc
from gsa.sim3 import Sim3

PROP_SHARE = 0.45  # share of the Gaussians on props: the ground is a little more than half


@dataclass
class TerrainCaptures:
    source: GaussianModel
    target: GaussianModel  # truth.apply(source's frame) = target's frame
    truth: Sim3
    extent: float  # the scene's horizontal diagonal, in the source's units


def _height(layout: np.random.Generator, size: float):
    """A heightfield of six plane waves of random direction, wavelength and amplitude."""
    k = 6
    freqs = layout.normal(0, 1, (k, 2)) * (2 * np.pi / size) * layout.uniform(0.5, 3, (k, 1))
    amps = layout.uniform(0.2, 1.5, k) * size / 40
    phases = layout.uniform(0, 2 * np.pi, k)
    return lambda xz: np.sin(xz @ freqs.T + phases) @ amps


def _prop_surface(kind: str, dims: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """m points on a prop's surface, standing on y = 0, centred on the Y axis."""
    if kind == "box":
        p = rng.uniform(-1, 1, (m, 3))
        face = rng.integers(0, 3, m)
        p[np.arange(m), face] = np.sign(p[np.arange(m), face])
        p = p * dims / 2
        p[:, 1] += dims[1] / 2
        return p
    if kind == "ball":
        v = rng.normal(size=(m, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        p = v * dims[0] / 2
        p[:, 1] += dims[0] / 2
        return p
    t = rng.uniform(0, 2 * np.pi, m)
    if kind == "pillar":
        return np.column_stack([np.cos(t) * dims[0] / 2, rng.uniform(0, dims[1] * 1.5, m), np.sin(t) * dims[0] / 2])
    u = np.sqrt(rng.uniform(0, 1, m))  # cone: uniform over its mantle
    r = u * dims[0] / 2
    return np.column_stack([np.cos(t) * r, (1 - u) * dims[1] * 2, np.sin(t) * r])


def make_terrain(layout_seed: int, sample_seed: int, n: int) -> tuple[GaussianModel, float]:
    """n Gaussians of the terrain scene `layout_seed` (its Gaussians drawn by `sample_seed`)
    and the scene's side length."""
    layout = np.random.default_rng(layout_seed)
    rng = np.random.default_rng(sample_seed)
    size = float(layout.uniform(30, 80))
    height = _height(layout, size)
    n_props = int(layout.integers(15, 50))
    kinds = layout.choice(["box", "ball", "pillar", "cone"], n_props)
    centres = layout.uniform(-0.45 * size, 0.45 * size, (n_props, 2))
    dims = layout.uniform(0.5, 3.0, (n_props, 3)) * size / 40
    yaws = layout.uniform(0, 2 * np.pi, n_props)
    colours = layout.uniform(0, 1, (n_props, 3))
    tone = np.array([0.35, 0.5, 0.2]) if layout.uniform() < 0.5 else np.array([0.55, 0.45, 0.3])

    n_ground = int(n * (1 - PROP_SHARE))
    xz = rng.uniform(-size / 2, size / 2, (n_ground, 2))
    points = [np.column_stack([xz[:, 0], height(xz), xz[:, 1]])]
    shade = 0.08 * np.sin(0.7 * xz[:, :1]) * np.cos(0.5 * xz[:, 1:])
    rgb = [tone + shade + rng.normal(0, 0.04, (n_ground, 3))]
    areas = 2 * (dims[:, 0] * dims[:, 1] + dims[:, 1] * dims[:, 2] + dims[:, 0] * dims[:, 2])
    counts = rng.multinomial(n - n_ground, areas / areas.sum())
    for kind, centre, d, yaw, colour, m in zip(kinds, centres, dims, yaws, colours, counts):
        if m == 0:
            continue
        c, s = np.cos(yaw), np.sin(yaw)
        p = _prop_surface(str(kind), d, int(m), rng) @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T
        p += [centre[0], height(centre[None])[0] - 0.05, centre[1]]  # sunk a little into the ground
        points.append(p)
        rgb.append(colour + rng.normal(0, 0.03, (int(m), 3)))
    means = np.concatenate(points).astype(np.float32)
    count = len(means)
    sh = np.zeros((count, 1, 3), np.float32)
    sh[:, 0] = rgb_to_sh_dc(np.clip(np.concatenate(rgb), 0, 1)).astype(np.float32)
    quats = rng.normal(size=(count, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    spacing = 0.7 * size / np.sqrt(n)
    log_scales = (np.log(spacing) + rng.normal(0, 0.2, (count, 3))).astype(np.float32)
    model = GaussianModel(
        means=means, quats=quats, log_scales=log_scales, opacity_logits=np.full(count, 3.0, np.float32), sh=sh
    )
    return model, size


def terrain_captures(layout_seed: int, n: int, rng: np.random.Generator) -> TerrainCaptures:
    """Two captures of terrain `layout_seed`, each an independent sampling of n Gaussians
    keeping a share drawn in 60-80 % of it, from either end of one random horizontal
    direction; the target then moved by a random Sim(3): a uniform rotation, scale
    log-uniform in 0.2-5, translation within the scene's side."""
    a, size = make_terrain(layout_seed, 1, n)
    b, _ = make_terrain(layout_seed, 2, n)
    angle = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(angle), 0.0, np.sin(angle)])
    keep_a, keep_b = rng.uniform(0.6, 0.8, 2)
    along_a, along_b = a.means @ direction, b.means @ direction
    source = a.subset(np.flatnonzero(along_a <= np.quantile(along_a, keep_a)))
    target = b.subset(np.flatnonzero(along_b >= np.quantile(along_b, 1 - keep_b)))
    quat = rng.normal(size=4)  # a uniform rotation
    scale = float(np.exp(rng.uniform(np.log(0.2), np.log(5.0))))
    truth = Sim3.from_quaternion(scale, quat, rng.uniform(-1, 1, 3) * size)
    return TerrainCaptures(source, target.transformed(truth), truth, size * np.sqrt(2))
