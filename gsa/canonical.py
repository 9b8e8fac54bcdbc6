"""The weight-free default feature: each Gaussian's direction in the model's own
canonical frame, encoded like GSA's spherical maps.

A canonical frame is the opacity- and size-weighted centroid, the principal
axes ordered by extent, signs fixed by the third moments and made
right-handed. Every step is Sim(3)-covariant, so an exact duplicate of a model
under any similarity transform gets identical features. Where the frame is
ambiguous (near-equal extents, near-zero skew) `frame_hypotheses` lists the
plausible alternatives instead of gambling on one.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from gsa.model import GaussianModel
from gsa.render import steps
from gsa.sim3 import Sim3

# An axis order is trusted only when extents differ by more than this fraction,
# an axis sign only when |normalised third moment| exceeds this value.
EXTENT_TOLERANCE = 0.15
SKEW_TOLERANCE = 0.15


@dataclass(frozen=True)
class CanonicalFrame:
    center: np.ndarray  # (3,) weighted centroid
    axes: np.ndarray  # (3, 3) rows = principal axes, descending extent, det +1
    extents: np.ndarray  # (3,) weighted standard deviation along each axis
    skews: np.ndarray  # (3,) normalised third moment along each (sign-fixed) axis
    radius: float  # weighted RMS distance from the centre

    def to_canonical(self) -> Sim3:
        """x -> axes (x - c) / radius: the model in a unit-size canonical pose."""
        s = 1.0 / self.radius
        return Sim3(s, self.axes, -s * (self.axes @ self.center))

    def rotated(self, g: np.ndarray) -> CanonicalFrame:
        """The frame with axes re-labelled by the signed permutation g (det +1)."""
        perm = np.abs(g).argmax(axis=1)
        sign = g[np.arange(3), perm]
        return CanonicalFrame(self.center, g @ self.axes, self.extents[perm], self.skews[perm] * sign, self.radius)


def gaussian_weights(model: GaussianModel) -> np.ndarray:
    """Opacity × area-like size: floaters (faint, tiny) hardly move the frame."""
    size = np.exp(np.clip(model.log_scales.astype(np.float64), -30, 30).sum(axis=1) * (2.0 / 3.0))
    w = model.opacities * size
    total = w.sum()
    if not np.isfinite(total) or total <= 0:
        return np.full(len(model), 1.0 / len(model))
    return w / total


def canonical_frame(points: np.ndarray, weights: np.ndarray | None = None) -> CanonicalFrame:
    """Canonical frame of weighted points (N, 3)."""
    x = np.asarray(points, np.float64)
    w = np.full(len(x), 1.0 / len(x)) if weights is None else np.asarray(weights, np.float64) / np.sum(weights)
    center = w @ x
    xc = x - center
    cov = (xc * w[:, None]).T @ xc
    evals, evecs = np.linalg.eigh(cov)
    order = np.argsort(evals)[::-1]
    axes = evecs[:, order].T.copy()
    extents = np.sqrt(np.maximum(evals[order], 0.0))
    proj = xc @ axes.T
    third = w @ proj**3
    skews = third / np.maximum(extents, 1e-300) ** 3
    signs = np.where(skews < 0, -1.0, 1.0)
    axes *= signs[:, None]
    skews *= signs
    if np.linalg.det(axes) < 0:
        # Flip the axis whose sign we trust least to make the frame right-handed.
        weakest = int(np.argmin(np.abs(skews)))
        axes[weakest] *= -1
        skews[weakest] *= -1
    steps.step()  # a due progress report (gsa.align.pair._Repeater)
    axes, extents, skews = _settle_close_pair(axes, extents, skews, xc, w)
    radius = float(np.sqrt(w @ np.einsum("ij,ij->i", xc, xc)))
    if not radius > 0:
        raise ValueError("all Gaussians coincide; the model has no extent to align")
    return CanonicalFrame(center, axes, extents, skews, radius)


def _settle_close_pair(axes, extents, skews, xc, w):
    """When two extents are near-equal, second moments leave the axes in their
    plane undetermined (eigen-solvers return an arbitrary pair). Third moments
    still fix them: turn the pair so the first axis maximises the third moment
    in the plane. This is covariant, so it holds across samplings and poses."""
    gaps = [abs(extents[i] - extents[i + 1]) / max(extents[i], 1e-300) for i in range(2)]
    i = int(np.argmin(gaps))
    if gaps[i] >= EXTENT_TOLERANCE:
        return axes, extents, skews
    j = i + 1
    u, v = xc @ axes[i], xc @ axes[j]
    m = np.array([w @ u**3, w @ (u * u * v), w @ (u * v * v), w @ v**3])
    theta = np.linspace(0.0, 2 * np.pi, 1441)
    c, s = np.cos(theta), np.sin(theta)
    m3 = m[0] * c**3 + 3 * m[1] * c * c * s + 3 * m[2] * c * s * s + m[3] * s**3
    k = int(np.argmax(m3))
    sigma = np.sqrt(max(w @ (c[k] * u + s[k] * v) ** 2, 1e-300))
    if m3[k] / sigma**3 < SKEW_TOLERANCE:
        return axes, extents, skews  # no usable asymmetry either: hypotheses cover it
    axes = axes.copy()
    a_i = c[k] * axes[i] + s[k] * axes[j]
    a_j = -s[k] * axes[i] + c[k] * axes[j]  # a rotation in the plane keeps det +1
    axes[i], axes[j] = a_i, a_j
    proj = xc @ axes.T
    extents = np.sqrt(np.maximum(w @ proj**2, 0.0))
    skews = (w @ proj**3) / np.maximum(extents, 1e-300) ** 3
    return axes, extents, skews


def model_frame(model: GaussianModel) -> CanonicalFrame:
    return canonical_frame(model.means, gaussian_weights(model))


def canonical_features(model_or_points, frame: CanonicalFrame | None = None) -> np.ndarray:
    """(N, 3) float32 features in [0, 1]: unit direction from the centre in the
    canonical frame, encoded (v + 1) / 2 as GSA encodes spherical-map features."""
    if isinstance(model_or_points, GaussianModel):
        points = model_or_points.means
        frame = frame or model_frame(model_or_points)
    else:
        points = np.asarray(model_or_points)
        frame = frame or canonical_frame(points)
    v = (np.asarray(points, np.float64) - frame.center) @ frame.axes.T
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)
    return ((v + 1.0) * 0.5).astype(np.float32)


def _signed_permutations() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            g = np.zeros((3, 3))
            g[np.arange(3), perm] = signs
            if np.linalg.det(g) > 0:
                out.append(g)
    return out


SIGNED_PERMUTATIONS = _signed_permutations()  # the 24 rotations of a cube


def relabelling_label(g: np.ndarray) -> str:
    """A signed permutation as text, e.g. '+y-x+z' (row i: which axis, with which sign)."""
    axes = "xyz"
    return "".join(("-" if g[i, j] < 0 else "+") + axes[j] for i in range(3) for j in range(3) if g[i, j] != 0)


def frame_hypotheses(
    *frames: CanonicalFrame,
    extent_tolerance: float = EXTENT_TOLERANCE,
    skew_tolerance: float = SKEW_TOLERANCE,
) -> list[np.ndarray]:
    """Signed permutations g (3x3, det +1, identity first) by which two frames of
    the same shape may plausibly disagree: axes swapped only where extents are
    near-equal, signs flipped only where the third moment is near zero, in any
    of the given frames."""

    def close(i: int, j: int) -> bool:
        for f in frames:
            lo, hi = sorted((f.extents[i], f.extents[j]))
            if hi <= 0 or lo >= hi * (1.0 - extent_tolerance):
                return True
        return False

    def weak(i: int) -> bool:
        return any(abs(f.skews[i]) < skew_tolerance for f in frames)

    out = []
    for g in SIGNED_PERMUTATIONS:
        perm = np.abs(g).argmax(axis=1)
        sign = g[np.arange(3), perm]
        ok = all(i == j or close(i, j) for i, j in enumerate(perm))
        ok = ok and all(s > 0 or weak(i) or weak(j) for i, (j, s) in enumerate(zip(perm, sign)))
        if ok:
            out.append(g)
    out.sort(key=lambda g: not np.allclose(g, np.eye(3)))
    return out
