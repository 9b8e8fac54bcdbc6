"""gsa.colour conversions and gsa.synth.shift_exposure."""

import numpy as np

from gsa.colour import linear_to_srgb, srgb_to_lab, srgb_to_linear
from gsa.synth import make_object, shift_exposure


def test_srgb_linear_round_trip_and_lab_reference_values():
    rgb = np.random.default_rng(0).uniform(0, 1, (500, 3))
    assert np.allclose(linear_to_srgb(srgb_to_linear(rgb)), rgb, atol=1e-12)
    lab = srgb_to_lab(np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    assert np.allclose(lab[0], [100, 0, 0], atol=0.05) and np.allclose(lab[1], [0, 0, 0], atol=1e-9)
    assert np.allclose(lab[2], [53.24, 80.09, 67.20], atol=0.05)  # sRGB red, D65 reference values


def test_shift_exposure_scales_linear_colour_and_view_dependence():
    model = make_object("car", seed=1, n_gaussians=2000, sh_degree=1)
    gain = np.array([0.5, 0.8, 1.2])
    out = shift_exposure(model, gain)
    before, after = srgb_to_linear(model.base_colors), srgb_to_linear(out.base_colors)
    unclipped = before * gain < 1.0
    assert np.allclose(after[unclipped], (before * gain)[unclipped], rtol=1e-4, atol=1e-6)
    assert np.allclose(after[~unclipped], 1.0, atol=1e-5)
    assert np.array_equal(out.means, model.means) and out.metadata["exposure_gain"] == gain.tolist()
    # Higher SH bands follow the DC colour's ratio per channel.
    old = model.base_colors[:, 0]
    lit = old > 1e-3
    ratio = out.base_colors[lit, 0] / old[lit]
    assert np.allclose(out.sh[lit, 1, 0], model.sh[lit, 1, 0] * ratio, rtol=1e-4, atol=1e-6)
