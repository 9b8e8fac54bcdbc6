"""Placement search: starts for captures whose centroid cannot be trusted.

The global search places every rotation by matching centres and RMS radii, then
pulls it with capture steps. A capture that missed a side has its centroid up to a
radius from where it belongs, and from there the capture steps settle elsewhere:
the true rotation never becomes a start. Here each rotation of a coarse grid tries
a whole lattice of positions for the source centre over the target's box, at a few
scales, scored by loose overlap both ways (distances truncated at a quarter radius,
so a rotation ~15° off still scores); the best distinct placements become starts.
It costs about as much as the rest of the search, so the pipeline runs it only when
the first answer is doubtful.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from gsa.align.robust.anchoring import Anchors, NearestGrid, grid_index, subsample
from gsa.geometry import super_fibonacci_rotations
from gsa.kernels import KERNEL_LOCK

Capture = Callable[[np.ndarray, np.ndarray, np.ndarray, tuple[float, ...]], tuple[np.ndarray, np.ndarray]]


def placed_starts(
    src: Anchors,
    dst: Anchors,
    rng: np.random.Generator,
    *,
    rotations: int | np.ndarray,
    points: int,
    step: float,
    truncation: float,
    scales: tuple[float, ...],
    count: int,
    min_deg: float,
    capture: Capture,
    capture_steps: tuple[float, ...],
    w_colour: float = 0.0,
    colour_sigma: float = 1.0,
    centres: np.ndarray | None = None,
) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """(rotation, scale, mapped source centre) of the `count` best placements whose
    rotations are min_deg apart. rotations: coarse grid size or the rotations; points: anchors per side
    scored per placement; step: lattice step and truncation: loose score distance, both
    fractions of the target radius; scales: factors of the radius ratio; capture: the
    search's capture steps (fine truncation), run with `capture_steps` on the winners.
    w_colour > 0: a close pair counts as robust's scores count it, less as its colours
    differ (CIELAB, colour_sigma) and against the pose beyond half of that trust - where
    geometry alone cannot rank placements (a site's ground lies on itself under any yaw).
    centres: the positions tried for the source centre (None: a lattice over the target's box)."""
    coarse = super_fibonacci_rotations(rotations) if np.isscalar(rotations) else np.asarray(rotations)
    if centres is None:
        centres = box_lattice(dst.points, np.eye(3), step * dst.radius)
    scale_trials = (dst.radius / src.radius) * np.asarray(scales)
    p_rows, q_rows = subsample(rng, len(src), points), subsample(rng, len(dst), points)
    p, q = src.points[p_rows] - src.center, dst.points[q_rows]
    # Grids of their own at the loose truncation: 8× fewer cells than the scorer's
    # stay in cache through this many lookups, and the loose score needs no more.
    cell = 0.5 * truncation * dst.radius
    d = NearestGrid(dst.points, cell, dst.radius)
    r = NearestGrid(src.points, cell * src.radius / dst.radius, src.radius)
    best = np.zeros((len(coarse), 5))
    with KERNEL_LOCK:
        _place_poses(
            coarse,
            scale_trials,
            centres,
            p,
            q,
            src.center,
            d.nearest_flat,
            d.lo,
            1.0 / d.cell,
            d.shape,
            dst.points,
            r.nearest_flat,
            r.lo,
            1.0 / r.cell,
            r.shape,
            src.points,
            truncation * dst.radius,
            src.lab[p_rows],
            dst.lab[q_rows],
            src.lab,
            dst.lab,
            w_colour,
            colour_sigma,
            best,
        )
    top = _distinct_rows(np.argsort(-best[:, 0]), coarse, count, min_deg)
    scale, t = capture(coarse[top], best[top, 1], best[top, 2:], capture_steps)
    return [(coarse[i], float(scale[k]), t[k]) for k, i in enumerate(top)]


def box_lattice(points: np.ndarray, axes: np.ndarray, step: float) -> np.ndarray:
    """Positions every `step` along the rows of `axes` (orthonormal) over the points' box
    in that frame, grown by a step."""
    local = points @ axes.T
    lo, hi = local.min(0) - step, local.max(0) + step
    ticks = [np.arange(lo[a], hi[a] + 0.5 * step, step) for a in range(3)]
    return np.stack(np.meshgrid(*ticks, indexing="ij"), -1).reshape(-1, 3) @ axes


def _distinct_rows(order: np.ndarray, rotations: np.ndarray, count: int, min_deg: float) -> list[int]:
    # trace(AᵀB) = 1 + 2 cos θ: rotations at least min_deg apart have a trace below this.
    limit = 1 + 2 * np.cos(np.radians(min_deg))
    chosen: list[int] = []
    for i in order:
        if len(chosen) >= count:
            break
        if all(np.sum(rotations[i] * rotations[j]) < limit for j in chosen):
            chosen.append(int(i))
    return chosen


@numba.njit(cache=True)
def _colour_factor(a, b, w_colour, sigma):  # pragma: no cover - compiled
    """1 where colour is not trusted; else 1 for the same colour down to 1 - 2·w_colour for
    unrelated ones (the translation sweep's and robust's colour term)."""
    if w_colour <= 0.0:
        return 1.0
    de2 = (a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2
    return 1.0 - 2.0 * w_colour * (1.0 - np.exp(-0.5 * de2 / sigma**2))


@numba.njit(parallel=True, cache=True)
def _place_poses(
    rot,
    scales,
    centres,
    p,
    q,
    c_s,
    dst_nearest,
    dst_lo,
    dst_inv_cell,
    dst_shape,
    dst_pts,
    src_nearest,
    src_lo,
    src_inv_cell,
    src_shape,
    src_pts,
    tau,
    p_lab,
    q_lab,
    src_lab,
    dst_lab,
    w_colour,
    sigma,
    best,
):  # pragma: no cover - compiled
    """For each rotation k, the (score, scale, centre) maximising the truncated
    closeness both ways over all scales × centres, written to best[k]. p: source
    samples less the source centre c_s; q: target samples."""
    n_p, n_q = p.shape[0], q.shape[0]
    for k in numba.prange(rot.shape[0]):
        top = -np.inf  # a coloured score can be negative everywhere: the best is still recorded
        x = np.zeros((n_p, 3))
        for m in range(scales.shape[0]):
            s = scales[m]
            for i in range(n_p):
                for a in range(3):
                    x[i, a] = s * (rot[k, a, 0] * p[i, 0] + rot[k, a, 1] * p[i, 1] + rot[k, a, 2] * p[i, 2])
            for o in range(centres.shape[0]):
                total = 0.0
                for i in range(n_p):
                    x0, x1, x2 = x[i, 0] + centres[o, 0], x[i, 1] + centres[o, 1], x[i, 2] + centres[o, 2]
                    cell = grid_index(x0, x1, x2, dst_lo, dst_inv_cell, dst_shape)
                    if cell < 0:
                        continue
                    j = dst_nearest[cell]
                    d = np.sqrt((dst_pts[j, 0] - x0) ** 2 + (dst_pts[j, 1] - x1) ** 2 + (dst_pts[j, 2] - x2) ** 2)
                    if d < tau:
                        total += (1.0 - d / tau) * _colour_factor(p_lab[i], dst_lab[j], w_colour, sigma)
                for i in range(n_q):
                    # x_s = Rᵀ (q − centre) / s + c_s, distances back in target units (× s)
                    u0 = (q[i, 0] - centres[o, 0]) / s
                    u1 = (q[i, 1] - centres[o, 1]) / s
                    u2 = (q[i, 2] - centres[o, 2]) / s
                    x0 = rot[k, 0, 0] * u0 + rot[k, 1, 0] * u1 + rot[k, 2, 0] * u2 + c_s[0]
                    x1 = rot[k, 0, 1] * u0 + rot[k, 1, 1] * u1 + rot[k, 2, 1] * u2 + c_s[1]
                    x2 = rot[k, 0, 2] * u0 + rot[k, 1, 2] * u1 + rot[k, 2, 2] * u2 + c_s[2]
                    cell = grid_index(x0, x1, x2, src_lo, src_inv_cell, src_shape)
                    if cell < 0:
                        continue
                    j = src_nearest[cell]
                    d = s * np.sqrt((src_pts[j, 0] - x0) ** 2 + (src_pts[j, 1] - x1) ** 2 + (src_pts[j, 2] - x2) ** 2)
                    if d < tau:
                        total += (1.0 - d / tau) * _colour_factor(q_lab[i], src_lab[j], w_colour, sigma)
                if total > top:
                    top = total
                    best[k, 0] = total / (n_p + n_q)
                    best[k, 1] = s
                    for a in range(3):
                        best[k, 2 + a] = centres[o, a]
