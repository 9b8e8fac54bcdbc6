"""Two reconstructions of one object (real photo sets): the robust search must not take the 180° flip.

tests/data/recon_chair256.npz holds two `gsa reconstruct` models of the generated textured chair
(python -m benchmarks.recon --size 256 --category chair --seed 1: 30 views from each of two rigs,
20 and 19 registered), reduced to what the search reads (positions, colours, opacities), and the
true A -> B Sim(3) from the cameras. Their printed texture varies at the anchors' spacing, so
neighbouring anchors disagree in colour (colour_noise 0.85); with full colour trust every pose
scored below zero, the truth (overlap 0.64) -0.32 and a pose overlapping 0.28 -0.22, which won
(RRE 85°)."""

from pathlib import Path

import numpy as np
import pytest

from gsa.align import robust
from gsa.align.pipeline import AlignOptions, align
from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg, scale_error_pct
from gsa.model import GaussianModel
from gsa.sim3 import Sim3

DATA = Path(__file__).parent / "data" / "recon_chair256.npz"


def _pair():
    d = np.load(DATA)
    models = []
    for side in "ab":
        x = d[f"{side}_means"].astype(np.float64) * float(d[f"{side}_unit"]) + d[f"{side}_offset"]
        spacing = 0.005 * float(d[f"{side}_unit"])
        models.append(
            GaussianModel.from_colors(
                x.astype(np.float32),
                d[f"{side}_rgb"] / 255.0,
                scales=np.full((len(x), 3), spacing, np.float32),
                opacities=np.clip(d[f"{side}_opacity"] / 255.0, 0.01, 0.99),
            )
        )
    return models[0], models[1], Sim3.from_matrix(d["a_to_b"])


@pytest.fixture(scope="module")
def pair():
    return _pair()


def test_noisy_colour_does_not_reward_less_overlap(pair):
    """The truth must outscore the flip under the search's own scoring: the colour trust is
    capped by the models' colour noise (robust.colour_trust)."""
    a, b, truth = pair
    src = robust.anchors(a)
    dst = robust.anchors(b)
    src, dst = robust.match_exposure(src, dst)
    noise = 0.5 * (robust.colour_noise(src) + robust.colour_noise(dst))
    assert noise > robust.PoseCriteria().noise_trust  # the case this file is about: texture finer than the anchors
    w = robust.colour_trust(src, dst, noise)
    right = robust.score_pose(src, dst, truth, "truth", w)
    centre = truth.apply(src.center)
    # Wrong poses: the truth turned 90° and 180° about each axis through the object's centre.
    wrong = []
    for axis in np.eye(3):
        for angle in (np.pi / 2, np.pi):
            turn = Sim3(1.0, axis_rotation(axis, angle), np.zeros(3))
            pose = Sim3(1.0, np.eye(3), centre) @ turn @ Sim3(1.0, np.eye(3), -centre) @ truth
            wrong.append(robust.score_pose(src, dst, pose, "wrong", w))
    assert right.score > 0  # full trust: -0.32, below poses that overlap half as much
    assert right.score > max(c.score for c in wrong) + robust.PoseCriteria().score_tie


def test_reconstructions_align(pair):
    a, b, truth = pair
    r = align(a, b, AlignOptions())  # before the colour trust's cap: RRE 85°
    assert rre_deg(r.transform.rotation, truth.rotation) < 2.0
    assert scale_error_pct(r.transform.scale, truth.scale) < 2.0
