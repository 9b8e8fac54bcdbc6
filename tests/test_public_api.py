"""The library's front door: `gsa` exports its main API, cheaply."""

import subprocess
import sys

import numpy as np

import gsa
from gsa.synth import make_object
from gsa.synth.perturb import random_sim3


def test_align_from_the_package_recovers_a_transform():
    from gsa import AlignmentResult, AlignOptions
    from gsa.align import align

    model = make_object("car", seed=2, n_gaussians=1500)
    truth = random_sim3(np.random.default_rng(5))
    result = align(model, model.transformed(truth), AlignOptions(stages=("coarse",)))
    assert isinstance(result, AlignmentResult)
    assert np.allclose(result.transform.matrix(), truth.matrix(), atol=1e-3 * max(1.0, truth.scale))


def test_gsa_align_is_the_subpackage_and_align_its_function():
    import gsa.align.pipeline
    from gsa import align as package
    from gsa.align import AlignOptions, align

    assert package is gsa.align and not callable(package)  # no callable module
    assert align is gsa.align.pipeline.align and AlignOptions is gsa.AlignOptions
    assert {"align", "AlignOptions"} <= set(dir(gsa.align))


def test_import_gsa_does_not_load_the_alignment_stack():
    code = "import sys, gsa; print(any(m.startswith(('numba', 'scipy', 'gsa.align.pipeline')) for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_unknown_attribute_is_an_attribute_error():
    try:
        gsa.no_such_thing  # noqa: B018
    except AttributeError as exc:
        assert "no_such_thing" in str(exc)
    else:
        raise AssertionError("gsa.no_such_thing resolved")
