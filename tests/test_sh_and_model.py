import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import gsa.model
from gsa.geometry import normalize_quats, quat_to_rotation
from gsa.model import GaussianModel, ModelError, merge_models
from gsa.sh import eval_sh, rotate_sh, sh_basis
from gsa.sim3 import Sim3
from gsa.synth import make_object


def _random_dirs(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_sh_matches_least_squares_reference(degree, rng):
    """Reference: fit new coefficients to the rotated colour field at random
    directions by least squares; the exact rotation must agree with it."""
    r = Rotation.random(random_state=degree).as_matrix()
    sh = rng.normal(size=(3, (degree + 1) ** 2, 3))
    dirs = _random_dirs(rng, 500)
    basis = sh_basis(dirs, degree)
    for n in range(len(sh)):
        field = sh_basis(dirs @ r, degree) @ sh[n]  # colour of the rotated model at d = old colour at Rᵀd
        ref, *_ = np.linalg.lstsq(basis, field, rcond=None)
        assert np.abs(rotate_sh(sh, r)[n] - ref).max() < 1e-5


def test_band_one_is_the_rotation_in_permuted_coordinates():
    # Band 1 in the 3DGS basis is (-y, z, -x): a rotation about z by 90° must mix
    # exactly the x and y coefficients.
    r = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    sh = np.zeros((1, 4, 3))
    sh[0, 3, 0] = 1.0  # coefficient of -x
    out = rotate_sh(sh, r)
    # x maps to y: the field -x becomes -y, i.e. coefficient 1 (of -y).
    assert np.allclose(out[0, :, 0], [0, 1, 0, 0], atol=1e-6)


def test_transformed_model_keeps_view_dependent_colour(car_model, rng):
    t = Sim3(2.5, Rotation.random(random_state=5).as_matrix(), [1, 2, 3])
    moved = car_model.transformed(t)
    d = _random_dirs(rng, len(car_model))
    assert np.allclose(eval_sh(moved.sh, d @ t.rotation.T), eval_sh(car_model.sh, d), atol=1e-5)
    assert np.allclose(moved.means, t.apply(car_model.means), atol=1e-4)
    assert np.allclose(moved.log_scales, car_model.log_scales + np.log(2.5), atol=1e-5)
    # Each Gaussian's covariance axes turn with the model.
    assert np.allclose(quat_to_rotation(moved.quats), t.rotation @ quat_to_rotation(car_model.quats), atol=1e-5)
    assert np.array_equal(moved.opacity_logits, car_model.opacity_logits)


def test_merge_keeps_features_and_pads_sh():
    a = GaussianModel.from_colors(np.zeros((2, 3)), np.full((2, 3), 0.5), sh_degree=0, features=np.ones((2, 3)))
    b = GaussianModel.from_colors(np.ones((3, 3)), np.full((3, 3), 0.2), sh_degree=2, features=np.zeros((3, 3)))
    m = merge_models(a, b)
    assert len(m) == 5 and m.sh_degree == 2 and m.features.shape == (5, 3)
    assert np.allclose(m.features[:2], 1) and np.allclose(m.features[2:], 0)
    assert merge_models(a, b.with_features(None)).features is None


def test_validate_rejects_nan_and_empty():
    m = GaussianModel.from_colors(np.zeros((2, 3)), np.zeros((2, 3)))
    m.means[1, 0] = np.nan
    with pytest.raises(ModelError, match="NaN"):
        m.validate()
    with pytest.raises(ModelError, match="zero Gaussians"):
        m.subset(np.zeros(2, bool)).validate()


def test_merge_models_selects_rows_pads_sh_and_matches_concatenation(car_model):
    """Filled block by block (blocks of 7 rows here), with per-model row selections."""
    import gsa.model as modelmod

    a = car_model.subset(np.arange(40)).with_features(np.arange(120.0).reshape(40, 3))
    b = car_model.subset(np.arange(40, 70)).with_sh_degree(1).with_features(-np.arange(90.0).reshape(30, 3))
    mask = np.zeros(40, bool)
    mask[[0, 5, 6, 7, 8, 9, 10, 11, 12, 39]] = True
    idx = np.array([29, 3, 4, 17])
    old = modelmod.ROW_BLOCK
    modelmod.ROW_BLOCK = 7
    try:
        whole = merge_models(a, b)
        picked = merge_models(a, b, keep=(mask, idx))
    finally:
        modelmod.ROW_BLOCK = old
    assert whole.sh_degree == a.sh_degree and len(whole) == 70
    np.testing.assert_array_equal(whole.means, np.concatenate([a.means, b.means]))
    np.testing.assert_array_equal(whole.sh[40:, :4], b.sh)
    assert not whole.sh[40:, 4:].any()  # padded bands are zero
    np.testing.assert_array_equal(whole.features, np.concatenate([a.features, b.features]))
    sub = merge_models(a.subset(mask), b.subset(idx))
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh", "features"):
        np.testing.assert_array_equal(getattr(picked, name), getattr(sub, name))


def test_surface_normals_in_blocks_equal_one_pass(monkeypatch):
    # surface_normals runs its rotation pass in blocks (a progress report between them): the
    # normals must be those of one pass over every Gaussian, for any rows asked for.
    model = make_object("car", seed=2, n_gaussians=5000)
    scales = model.log_scales.astype(np.float64)
    rot = quat_to_rotation(normalize_quats(model.quats.astype(np.float64)))
    one_pass = np.take_along_axis(rot, np.argsort(scales, axis=1)[:, None, :1], axis=2)[:, :, 0]
    monkeypatch.setattr(gsa.model, "NORMALS_BLOCK", 700)
    rows = np.random.default_rng(0).random(len(model)) < 0.6
    assert np.array_equal(model.surface_normals()[0], one_pass)
    assert np.array_equal(model.surface_normals(rows)[0], one_pass[rows])
    assert np.array_equal(model.surface_normals(np.arange(10, 4000, 3))[0], one_pass[10:4000:3])
