"""Surface primitives that can be sampled uniformly by area.

Each primitive samples (points, normals) on its surface; objects are unions of
primitives with a colour each. Coordinates: x forward, y left, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _frame(axis) -> np.ndarray:
    """Rows: two unit vectors orthogonal to `axis`, then `axis` itself."""
    a = _unit(np.asarray(axis, np.float64))
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = _unit(np.cross(a, helper))
    return np.stack([u, np.cross(a, u), a])


@dataclass
class Box:
    center: tuple
    half: tuple  # half-extents along x, y, z
    color: tuple

    def area(self) -> float:
        hx, hy, hz = self.half
        return 8 * (hx * hy + hy * hz + hx * hz)

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        h = np.asarray(self.half, np.float64)
        face_area = np.array([h[1] * h[2], h[1] * h[2], h[0] * h[2], h[0] * h[2], h[0] * h[1], h[0] * h[1]])
        face = rng.choice(6, n, p=face_area / face_area.sum())
        axis = face // 2
        sign = np.where(face % 2 == 0, 1.0, -1.0)
        p = rng.uniform(-1, 1, (n, 3)) * h
        p[np.arange(n), axis] = sign * h[axis]
        normals = np.zeros((n, 3))
        normals[np.arange(n), axis] = sign
        return p + np.asarray(self.center), normals


@dataclass
class Ellipsoid:
    center: tuple
    radii: tuple
    color: tuple

    def area(self) -> float:
        a, b, c = self.radii  # Knud Thomsen's approximation
        p = 1.6075
        return 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(self.radii, np.float64)
        # Rejection on the area element keeps the density uniform on elongated shapes.
        out_p, out_n, need = [], [], n
        while need > 0:
            u = _unit(rng.normal(size=(2 * need + 16, 3)))
            grad = u / r  # normal direction of the ellipsoid at r*u, up to scale
            density = np.linalg.norm(grad * np.prod(r), axis=1)
            keep = rng.uniform(0, density.max(), len(u)) < density
            out_p.append(u[keep] * r)
            out_n.append(_unit(grad[keep]))
            need -= int(keep.sum())
        return np.concatenate(out_p)[:n] + np.asarray(self.center), np.concatenate(out_n)[:n]


@dataclass
class Cylinder:
    center: tuple
    axis: tuple
    radius: float
    length: float
    color: tuple

    def area(self) -> float:
        return 2 * np.pi * self.radius * self.length + 2 * np.pi * self.radius**2

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        f = _frame(self.axis)
        side = 2 * np.pi * self.radius * self.length
        on_side = rng.uniform(0, self.area(), n) < side
        theta = rng.uniform(0, 2 * np.pi, n)
        radial = np.cos(theta)[:, None] * f[0] + np.sin(theta)[:, None] * f[1]
        along = rng.uniform(-0.5, 0.5, n) * self.length
        cap_sign = np.where(rng.uniform(size=n) < 0.5, -1.0, 1.0)
        cap_r = self.radius * np.sqrt(rng.uniform(size=n))
        p = np.where(
            on_side[:, None],
            radial * self.radius + along[:, None] * f[2],
            radial * cap_r[:, None] + (cap_sign * 0.5 * self.length)[:, None] * f[2],
        )
        normals = np.where(on_side[:, None], radial, cap_sign[:, None] * f[2])
        return p + np.asarray(self.center), normals


Primitive = Box | Ellipsoid | Cylinder
