"""The RQ worker's warm-up (service.worker.runners._warm_up): the parent loads the aligner
and the renderer's kernels, so a forked work horse neither compiles nor hangs."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from tests.service.conftest import ROOT

pytestmark = pytest.mark.slow  # a fresh interpreter that imports torch and numba

CHILD = textwrap.dedent(
    """
    import os, sys, time
    from service.worker import horse, runners
    runners._warm_up()
    import torch
    from gsa.render.cpu import composite
    assert composite._forward.signatures, "the render kernels were not loaded in the parent"
    assert horse.torch_threads() and torch.get_num_threads() == 1
    pid = os.fork()
    if pid == 0:  # what run_job does in a work horse, then parallel torch work
        horse.restore_torch_threads()
        a = torch.randn(1500, 1500)
        (a @ a).sum()
        torch.randn(4_000_000).exp().sum()
        os._exit(0 if composite._forward.signatures else 3)
    _, status = os.waitpid(pid, 0)
    sys.exit(os.waitstatus_to_exitcode(status))
    """
)


def test_a_horse_forked_after_warm_up_runs_parallel_torch_and_inherits_the_kernels():
    # An OpenMP thread team started in the parent would make the child's first
    # parallel op hang: the timeout turns that into a failure.
    r = subprocess.run([sys.executable, "-c", CHILD], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
