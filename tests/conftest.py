import numpy as np
import pytest

from gsa.synth import make_object


@pytest.fixture(scope="session")
def car_model():
    return make_object("car", seed=3, n_gaussians=6000, sh_degree=3)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
