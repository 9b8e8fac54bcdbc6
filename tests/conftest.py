import os

import numpy as np
import pytest
from hypothesis import settings

from gsa.synth import make_object

# The same generated cases on every run, with or without CI=true (Hypothesis' own `ci`
# profile is only loaded under CI): a newcomer's first `./dev.sh test` must not draw a case
# nobody has seen. Each property test also says derandomize=True itself; this covers any new
# one. The random search lives in benchmarks/service/ (fuzz_service.py); what it finds joins
# tests/service/corpus/. `pytest --hypothesis-profile=...` still overrides this.
settings.register_profile("gsa-deterministic", derandomize=True, database=None, deadline=None, print_blob=True)
settings.load_profile("gsa-deterministic")


# The semantic tie-break (gsa.align.semantic) runs a pretrained ViT on ~200 renders whenever an
# answer is doubtful: 10-20 s per alignment here, in the many tests whose pairs are doubtful on
# purpose. It is off for the CLI, server and worker processes the tests start (GSA_SEMANTIC, the
# deployment's switch) and for in-process alignments; tests marked `semantic` run it for real.
os.environ["GSA_SEMANTIC"] = "off"


def pytest_configure(config):
    config.addinivalue_line("markers", "semantic: runs the semantic tie-break with the real bundled backbone")


@pytest.fixture(autouse=True)
def semantic_off_unless_marked(request, monkeypatch):
    if request.node.get_closest_marker("semantic") is None:
        from gsa.align import semantic

        monkeypatch.setattr(semantic, "available_backbone", lambda path=None: None)


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels():
    """Compile the numba kernels (alignment search, ICP, CPU rasterizer forward and
    backward) once, before any test starts a server, worker or CLI process: those then
    load them from numba's on-disk cache instead of compiling the same kernels side by
    side on a 2-core machine (tens of seconds each when cold)."""
    import torch

    from gsa.align.pipeline import AlignOptions, align
    from gsa.render import orbit_cameras, rasterize

    model = make_object("car", seed=0, n_gaussians=600)
    align(model, model, AlignOptions(stages=("coarse",)))
    align(model, model, AlignOptions(stages=("coarse",), search="frames"))
    params = [
        torch.tensor(a, dtype=torch.float32, requires_grad=True)
        for a in (model.means, model.quats, model.log_scales, model.opacity_logits, model.sh[:, :1])
    ]
    cams = orbit_cameras(model.means.mean(0), 3.0, 1, width=24, height=16, fov=60, seed=0)
    features = torch.zeros((len(model), 3), requires_grad=True)
    out = rasterize(*params, features, cams, backend="cpu")
    (out.colors.sum() + out.features.sum()).backward()


@pytest.fixture(scope="session")
def car_model():
    return make_object("car", seed=3, n_gaussians=6000, sh_degree=3)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
