"""Procedural object categories (analogues of the paper's six ShapeNet/CO3D
classes) with intra-category variation, turned into 3DGS models.

`make_object(category, seed)` is deterministic: the seed fixes the instance's
shape parameters; `sample_seed` fixes where the Gaussians land, so two
different sample seeds give two independent 3DGS models of one object.
"""

from __future__ import annotations

import numpy as np

from gsa.geometry import normalize_quats, quat_multiply
from gsa.model import GaussianModel
from gsa.synth.shapes import Box, Cylinder, Ellipsoid, Primitive

CATEGORIES = ("airplane", "bus", "boat", "car", "chair", "motorcycle")


def _color(rng: np.random.Generator, base=None, jitter=0.15) -> tuple:
    c = rng.uniform(0.1, 0.9, 3) if base is None else np.asarray(base) + rng.uniform(-jitter, jitter, 3)
    return tuple(np.clip(c, 0.02, 0.98))


def _car(rng):
    length, width, height = rng.uniform(3.8, 4.8), rng.uniform(1.6, 1.9), rng.uniform(0.55, 0.75)
    wheel_r = rng.uniform(0.3, 0.38)
    body_z = wheel_r + height / 2
    cabin_len = length * rng.uniform(0.4, 0.55)
    cabin_x = -length * rng.uniform(0.05, 0.15)  # cabin sits aft: front and back differ
    paint = _color(rng)
    parts: list[Primitive] = [
        Box((0, 0, body_z), (length / 2, width / 2, height / 2), paint),
        Box(
            (cabin_x, 0, body_z + height / 2 + 0.25), (cabin_len / 2, width * 0.42, 0.25), _color(rng, (0.2, 0.25, 0.3))
        ),
        Box((length / 2 - 0.05, 0, body_z + 0.05), (0.06, width * 0.35, 0.1), _color(rng, (0.9, 0.9, 0.8), 0.05)),
    ]
    for x in (length * 0.32, -length * 0.32):
        for y in (width / 2, -width / 2):
            parts.append(Cylinder((x, y, wheel_r), (0, 1, 0), wheel_r, 0.22, _color(rng, (0.08, 0.08, 0.08), 0.03)))
    return parts


def _bus(rng):
    length, width, height = rng.uniform(9, 12), rng.uniform(2.4, 2.6), rng.uniform(2.8, 3.4)
    wheel_r = rng.uniform(0.45, 0.55)
    z = wheel_r + height / 2
    paint = _color(rng)
    parts: list[Primitive] = [
        Box((0, 0, z), (length / 2, width / 2, height / 2), paint),
        Box((0, 0, z + height * 0.2), (length * 0.45, width / 2 + 0.02, height * 0.15), _color(rng, (0.15, 0.2, 0.25))),
        Box((length / 2 + 0.1, 0, z + height * 0.1), (0.1, width * 0.45, height * 0.3), _color(rng, (0.2, 0.25, 0.3))),
        Box((-length / 2 + 0.4, 0, z + height / 2 + 0.2), (0.5, width * 0.35, 0.2), _color(rng, (0.6, 0.6, 0.6))),
    ]
    for x in (length * 0.33, -length * 0.28, -length * 0.4):
        for y in (width / 2, -width / 2):
            parts.append(Cylinder((x, y, wheel_r), (0, 1, 0), wheel_r, 0.3, _color(rng, (0.08, 0.08, 0.08), 0.03)))
    return parts


def _airplane(rng):
    length = rng.uniform(8, 12)
    fr = length * rng.uniform(0.05, 0.07)
    span = length * rng.uniform(0.8, 1.1)
    chord = length * rng.uniform(0.12, 0.18)
    wing_x = length * rng.uniform(0.0, 0.1)
    body = _color(rng, (0.85, 0.85, 0.9), 0.1)
    accent = _color(rng)
    return [
        Ellipsoid((0, 0, 0), (length / 2, fr, fr), body),
        Box((wing_x, 0, -fr * 0.3), (chord / 2, span / 2, fr * 0.12), body),
        Box((-length * 0.42, 0, fr * 1.6), (chord * 0.35, fr * 0.1, fr * 1.5), accent),
        Box((-length * 0.42, 0, fr * 0.3), (chord * 0.25, span * 0.18, fr * 0.08), accent),
        Cylinder((wing_x + chord * 0.2, span * 0.25, -fr * 0.9), (1, 0, 0), fr * 0.35, chord * 0.8, accent),
        Cylinder((wing_x + chord * 0.2, -span * 0.25, -fr * 0.9), (1, 0, 0), fr * 0.35, chord * 0.8, accent),
    ]


def _boat(rng):
    length, width, depth = rng.uniform(6, 10), rng.uniform(2, 3), rng.uniform(0.8, 1.3)
    hull = _color(rng)
    return [
        Box((-length * 0.1, 0, 0), (length * 0.4, width / 2, depth / 2), hull),
        Ellipsoid((length * 0.3, 0, 0), (length * 0.25, width / 2, depth / 2), hull),
        Box(
            (-length * 0.15, 0, depth / 2 + 0.5),
            (length * rng.uniform(0.12, 0.2), width * 0.35, 0.5),
            _color(rng, (0.9, 0.9, 0.9), 0.08),
        ),
        Cylinder(
            (length * 0.05, 0, depth / 2 + rng.uniform(1.5, 2.5)),
            (0, 0, 1),
            0.06,
            rng.uniform(3, 5),
            _color(rng, (0.4, 0.3, 0.2)),
        ),
    ]


def _chair(rng):
    seat_w, seat_d, seat_h = rng.uniform(0.4, 0.55), rng.uniform(0.4, 0.55), rng.uniform(0.4, 0.5)
    back_h = rng.uniform(0.4, 0.6)
    leg_r = rng.uniform(0.02, 0.035)
    wood = _color(rng, (0.55, 0.35, 0.2))
    parts: list[Primitive] = [
        Box((0, 0, seat_h), (seat_d / 2, seat_w / 2, 0.03), _color(rng)),
        Box((-seat_d / 2 + 0.02, 0, seat_h + back_h / 2), (0.025, seat_w / 2, back_h / 2), wood),
    ]
    for x in (seat_d / 2 - 0.04, -seat_d / 2 + 0.04):
        for y in (seat_w / 2 - 0.04, -seat_w / 2 + 0.04):
            parts.append(Cylinder((x, y, seat_h / 2), (0, 0, 1), leg_r, seat_h, wood))
    return parts


def _motorcycle(rng):
    wheelbase, wheel_r = rng.uniform(1.3, 1.6), rng.uniform(0.28, 0.34)
    paint = _color(rng)
    tyre = _color(rng, (0.08, 0.08, 0.08), 0.03)
    return [
        Cylinder((wheelbase / 2, 0, wheel_r), (0, 1, 0), wheel_r, 0.12, tyre),
        Cylinder((-wheelbase / 2, 0, wheel_r), (0, 1, 0), wheel_r * 1.05, 0.16, tyre),
        Ellipsoid((0.1, 0, wheel_r * 2.0), (wheelbase * 0.3, 0.18, 0.16), paint),
        Box((-0.3, 0, wheel_r * 2.3), (0.25, 0.14, 0.05), _color(rng, (0.1, 0.1, 0.1), 0.05)),
        Cylinder(
            (wheelbase * 0.42, 0, wheel_r * 1.6), (0.4, 0, 1), 0.035, wheel_r * 1.8, _color(rng, (0.7, 0.7, 0.7), 0.05)
        ),
        Cylinder((wheelbase * 0.5, 0, wheel_r * 2.6), (0, 1, 0), 0.025, 0.7, _color(rng, (0.7, 0.7, 0.7), 0.05)),
        Box((-0.15, 0, wheel_r * 1.3), (0.2, 0.12, 0.12), _color(rng, (0.5, 0.5, 0.5), 0.05)),
    ]


BUILDERS = {
    "airplane": _airplane,
    "bus": _bus,
    "boat": _boat,
    "car": _car,
    "chair": _chair,
    "motorcycle": _motorcycle,
}


def object_parts(category: str, seed: int = 0) -> list[Primitive]:
    if category not in BUILDERS:
        raise ValueError(f"unknown category {category!r}; choose from {', '.join(CATEGORIES)}")
    return BUILDERS[category](np.random.default_rng([seed, CATEGORIES.index(category)]))


def _quats_from_normals(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """w,x,y,z rotating local z onto each normal, with a random spin about it."""
    z = np.array([0.0, 0.0, 1.0])
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    axis = np.cross(z, n)
    s = np.linalg.norm(axis, axis=1)
    c = n @ z
    half = 0.5 * np.arctan2(s, c)
    safe = np.where(s[:, None] > 1e-9, axis / np.maximum(s, 1e-12)[:, None], np.array([1.0, 0, 0]))
    q_align = np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * safe], axis=1)
    spin = rng.uniform(0, np.pi, len(n))
    q_spin = np.stack([np.cos(spin), np.zeros_like(spin), np.zeros_like(spin), np.sin(spin)], axis=1)
    return normalize_quats(quat_multiply(q_align, q_spin))


def surface_gaussians(
    means: np.ndarray,
    normals: np.ndarray,
    colors: np.ndarray,
    spacing: float,
    n_floaters: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Flat surface Gaussians at surface samples (`spacing` apart on average), lying in the
    surface, and `n_floaters` faint ones scattered in the padded bounding box, as real captures
    have: (means, colours, linear scales, quaternions wxyz, opacities)."""
    n_surface = len(means)
    tangent = spacing * rng.uniform(0.6, 1.0, n_surface)
    scales = np.stack([tangent, tangent * rng.uniform(0.7, 1.0, n_surface), tangent * 0.08], axis=1)
    quats = _quats_from_normals(normals, rng)
    opac = rng.uniform(0.7, 0.99, n_surface)
    if n_floaters:
        lo, hi = means.min(0), means.max(0)
        pad = 0.1 * (hi - lo)
        means = np.concatenate([means, rng.uniform(lo - pad, hi + pad, (n_floaters, 3))])
        colors = np.concatenate([colors, rng.uniform(0, 1, (n_floaters, 3))])
        scales = np.concatenate(
            [scales, np.full((n_floaters, 3), spacing * 0.5) * rng.uniform(0.5, 1.5, (n_floaters, 1))]
        )
        quats = np.concatenate([quats, normalize_quats(rng.normal(size=(n_floaters, 4)))])
        opac = np.concatenate([opac, rng.uniform(0.02, 0.2, n_floaters)])
    return means, colors, scales, quats, opac


def make_object(
    category: str,
    seed: int = 0,
    n_gaussians: int = 20_000,
    sample_seed: int | None = None,
    floaters: float = 0.0,
    sh_degree: int = 0,
    position_noise: float = 0.0,
) -> GaussianModel:
    """A 3DGS model of one procedural object instance.

    seed: which instance (shape, proportions, colours); sample_seed: where the
    Gaussians fall (defaults to seed); floaters: fraction of extra faint
    Gaussians scattered in the bounding box, as real captures have;
    position_noise: surface jitter as a fraction of the object's size.
    """
    if n_gaussians < 1:
        raise ValueError("n_gaussians must be at least 1")
    parts = object_parts(category, seed)
    rng = np.random.default_rng([seed if sample_seed is None else sample_seed, 7919, CATEGORIES.index(category)])
    n_floaters = int(round(n_gaussians * floaters))
    n_surface = n_gaussians - n_floaters
    areas = np.array([p.area() for p in parts])
    counts = rng.multinomial(n_surface, areas / areas.sum())
    pts, nrm, col = [], [], []
    for part, k in zip(parts, counts):
        if k == 0:
            continue
        p, n = part.sample(int(k), rng)
        pts.append(p)
        nrm.append(n)
        # A gentle positional pattern so renders have texture the fine stage can use.
        pattern = 0.08 * np.sin(p @ np.array([3.1, 2.3, 4.7]))[:, None]
        col.append(np.clip(np.asarray(part.color) + pattern + rng.normal(0, 0.02, (int(k), 3)), 0, 1))
    means = np.concatenate(pts)
    normals = np.concatenate(nrm)
    colors = np.concatenate(col)
    size = np.linalg.norm(means.max(0) - means.min(0))
    if position_noise > 0:
        means = means + rng.normal(0, position_noise * size, means.shape)
    spacing = np.sqrt(areas.sum() / max(n_surface, 1))
    means, colors, scales, quats, opac = surface_gaussians(means, normals, colors, spacing, n_floaters, rng)
    # Centre by the instance's shape, not by the sample, so independent samplings
    # of one instance share one frame exactly (their true relative pose is identity).
    centers = np.array([np.asarray(p.center, np.float64) for p in parts])
    means = means - (areas @ centers) / areas.sum()
    model = GaussianModel.from_colors(means, colors, quats=quats, scales=scales, opacities=opac, sh_degree=sh_degree)
    if sh_degree > 0:
        # Mild view dependence, so SH handling is exercised end to end.
        model.sh[:, 1:, :] = rng.normal(0, 0.05, model.sh[:, 1:, :].shape)
    model.metadata.update(category=category, seed=seed, sample_seed=sample_seed)
    return model
