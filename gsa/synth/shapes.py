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


@dataclass
class RegularPrism:
    """A regular k-gon prism, or frustum when `top_radius` differs from `radius`.

    The polygon's vertices lie at angles `phase + 2πj/sides` (j = 0..sides-1),
    measured in the plane spanned by `_frame(axis)[0]` (angle 0) and
    `_frame(axis)[1]` (angle π/2); `radius` is the circumradius at the bottom
    (−length/2 along the axis), `top_radius` at the top. `caps` = (bottom, top)
    says which end polygons are part of the surface (leave out ends that sit
    flush against another part). Exactly `sides`-fold rotationally symmetric.
    """

    center: tuple
    axis: tuple
    radius: float
    length: float
    sides: int
    color: tuple
    top_radius: float | None = None
    phase: float = 0.0
    caps: tuple = (True, True)

    def _radii(self) -> tuple[float, float]:
        return float(self.radius), float(self.radius if self.top_radius is None else self.top_radius)

    def _part_areas(self) -> np.ndarray:
        """Side (all faces together), bottom cap, top cap."""
        k = int(self.sides)
        r0, r1 = self._radii()
        half = np.pi / k
        slant = np.hypot(self.length, (r1 - r0) * np.cos(half))
        side = k * (r0 + r1) * np.sin(half) * slant  # k trapezoids, parallel edges 2r·sin(π/k)
        cap = 0.5 * k * np.sin(2 * half)
        return np.array([side, cap * r0**2 * bool(self.caps[0]), cap * r1**2 * bool(self.caps[1])])

    def area(self) -> float:
        return float(self._part_areas().sum())

    def face_angle(self, j: int = 0) -> float:
        """Angle (in the frame of the class docstring) of side face j's outward normal."""
        return self.phase + (2 * j + 1) * np.pi / self.sides

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        if self.sides < 3:
            raise ValueError("a regular prism needs at least 3 sides")
        f = _frame(self.axis)
        k = int(self.sides)
        r0, r1 = self._radii()
        h = 0.5 * self.length
        areas = self._part_areas()
        part = rng.choice(3, n, p=areas / areas.sum())
        j = rng.integers(0, k, n)  # which face / which cap triangle: all have equal area
        a0 = self.phase + 2 * np.pi * j / k
        a1 = a0 + 2 * np.pi / k
        # local (u, v, w) coordinates; w along the axis
        e0 = np.stack([np.cos(a0), np.sin(a0)], axis=1)
        e1 = np.stack([np.cos(a1), np.sin(a1)], axis=1)
        local = np.zeros((n, 3))
        normals = np.zeros((n, 3))
        # side: trapezoid between the bottom edge (radius r0) and top edge (radius r1);
        # its width is linear in the height t, a mixture of densities 2(1−t) and 2t.
        side = part == 0
        ns = int(side.sum())
        if ns:
            u1, u2 = rng.uniform(size=ns), rng.uniform(size=ns)
            top_heavy = rng.uniform(size=ns) < r1 / (r0 + r1)
            t = np.where(top_heavy, np.sqrt(u1), 1 - np.sqrt(u1))
            r = r0 + (r1 - r0) * t
            s = u2[:, None]
            xy = r[:, None] * ((1 - s) * e0[side] + s * e1[side])
            local[side, :2] = xy
            local[side, 2] = -h + 2 * h * t
            mid = 0.5 * (e0[side] + e1[side])
            mid /= np.linalg.norm(mid, axis=1, keepdims=True)
            # outward normal: radial (apothem direction) tilted by the taper
            apo = np.cos(np.pi / k)
            nrm = np.concatenate([mid * self.length, np.full((ns, 1), (r0 - r1) * apo)], axis=1)
            normals[side] = _unit(nrm)
        for which, (r, w, sign) in ((1, (r0, -h, -1.0)), (2, (r1, h, 1.0))):
            m = part == which
            nm = int(m.sum())
            if not nm:
                continue
            # uniform in the triangle (centre, vertex j, vertex j+1)
            u1, u2 = np.sqrt(rng.uniform(size=nm)), rng.uniform(size=nm)
            local[m, :2] = r * (u1 * (1 - u2))[:, None] * e0[m] + r * (u1 * u2)[:, None] * e1[m]
            local[m, 2] = w
            normals[m, 2] = sign
        return local @ f + np.asarray(self.center, np.float64), normals @ f


@dataclass
class Torus:
    """A torus about `axis`: tube radius `minor` around a circle of radius `major`."""

    center: tuple
    axis: tuple
    major: float
    minor: float
    color: tuple

    def area(self) -> float:
        return 4 * np.pi**2 * self.major * self.minor

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        f = _frame(self.axis)
        R, r = float(self.major), float(self.minor)
        vs, need = [], n
        while need > 0:  # the area element is ∝ R + r·cos(v)
            v = rng.uniform(0, 2 * np.pi, 2 * need + 16)
            keep = rng.uniform(0, R + r, len(v)) < R + r * np.cos(v)
            vs.append(v[keep])
            need -= int(keep.sum())
        v = np.concatenate(vs)[:n]
        u = rng.uniform(0, 2 * np.pi, n)
        radial = np.stack([np.cos(u), np.sin(u), np.zeros(n)], axis=1)
        normal = np.cos(v)[:, None] * radial + np.sin(v)[:, None] * np.array([0.0, 0.0, 1.0])
        local = R * radial + r * normal
        return local @ f + np.asarray(self.center, np.float64), normal @ f


Primitive = Box | Ellipsoid | Cylinder | RegularPrism | Torus
