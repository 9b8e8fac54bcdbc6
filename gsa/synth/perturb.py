"""Random similarity transforms for the paper's evaluation protocols."""

from __future__ import annotations

import numpy as np

from gsa.geometry import euler_xyz
from gsa.sim3 import Sim3


def random_sim3(
    rng: np.random.Generator,
    max_angle_deg: float = 180.0,
    min_angle_deg: float = 0.0,
    scale_range: tuple[float, float] = (0.1, 10.0),
    translation: float = 5.0,
) -> Sim3:
    """Euler angles with |angle| in [min, max] per axis (random sign), scale
    log-uniform in scale_range, translation uniform in [-t, t]³.

    App. C: max 180°, scale up to 10× (0.1..10). Table 1/2 protocol of the
    authors: angles in [45°, 180°], scale 0.5..1.5, translation in [-1, 1]³.
    """
    mags = rng.uniform(min_angle_deg, max_angle_deg, 3)
    signs = rng.choice([-1.0, 1.0], 3)
    lo, hi = scale_range
    s = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    return Sim3(s, euler_xyz(np.radians(mags * signs)), rng.uniform(-translation, translation, 3))


def paper_perturbation(rng: np.random.Generator) -> Sim3:
    """The authors' evaluation perturbation (Tables 1 and 2)."""
    lo, hi = 0.5, 1.5
    mags = rng.uniform(45.0, 180.0, 3) * rng.choice([-1.0, 1.0], 3)
    return Sim3(float(rng.uniform(lo, hi)), euler_xyz(np.radians(mags)), rng.uniform(-1.0, 1.0, 3))
