"""The numba kernels' threading layer and lock (gsa.kernels), as a library caller meets them:
no CLI or service has chosen the layer first. Each case runs in a fresh interpreter, since the
layer is fixed at the first parallel launch of a process."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

ALIGN_TWO = """
import numpy as np
from gsa.align.pipeline import AlignOptions, align
from gsa.synth import make_object
from gsa.sim3 import Sim3
from gsa.geometry import axis_rotation

def pair(seed):
    source = make_object("car", seed=seed, n_gaussians=3000)
    truth = Sim3(1.5, axis_rotation(np.array([0.0, 1.0, 0.0]), 2.0), np.array([0.3, 0.0, -0.2]))
    return source, source.transformed(truth)
"""


def _python(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)


def test_a_library_alignment_runs_its_kernels_on_the_workqueue_layer():
    # numba's default (GNU OpenMP) spin-waits and made the backbone after it 4x slower.
    done = _python(
        ALIGN_TWO
        + """
import numba
align(*pair(1), AlignOptions(semantic="off", stages=("coarse",)))
print("layer", numba.threading_layer())
"""
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "layer workqueue" in done.stdout


def test_the_threading_layer_set_in_the_environment_is_kept():
    done = _python(
        "import os; os.environ['NUMBA_THREADING_LAYER'] = 'omp'\n"
        + ALIGN_TWO
        + """
import numba
align(*pair(1), AlignOptions(semantic="off", stages=("coarse",)))
print("layer", numba.threading_layer())
"""
    )
    if done.returncode != 0 and "omp" in done.stderr.lower() and "not" in done.stderr.lower():
        pytest.skip("this numba has no OpenMP threading layer to choose")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "layer omp" in done.stdout


def test_two_threads_align_at_once_without_aborting():
    # The workqueue layer aborts a process that enters it from two threads at once; the
    # service's embedded workers are threads, so every parallel launch takes the kernel lock.
    done = _python(
        ALIGN_TWO
        + """
import threading
errors, results = [], []
def run(seed):
    try:
        result = align(*pair(seed), AlignOptions(semantic="off", stages=("coarse",)))
        results.append(result.transform)
    except Exception as exc:
        errors.append(repr(exc))
threads = [threading.Thread(target=run, args=(seed,)) for seed in (1, 2, 3)]
for t in threads: t.start()
for t in threads: t.join()
print("finished", len(results), errors)
"""
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "finished 3 []" in done.stdout
