"""What every parallel numba kernel of gsa shares: the threading layer, and the lock around
each parallel launch.

numba's default GNU-OpenMP layer spin-waits in its barriers. Its threads then hold the cores
other work needs: after an alignment's search kernels, the semantic tie-break's backbone (torch,
with an OpenMP runtime of its own) ran 4x slower in the same process (a vase pair's tie-break
45 s against 11 s, docs/benchmarks.md, "The kernels' threading layer"), and on a busy machine
the barriers themselves become erratic. The built-in workqueue layer degrades gracefully, but
must not be entered from two Python threads at once (the service's embedded workers are
threads): KERNEL_LOCK around every parallel launch (each kernel uses all cores anyway).

The layer is chosen here only (use_workqueue_layer): every module that defines a parallel kernel
imports this one, so the layer is chosen before the first launch, whichever entry point (the
CLI, the service, a library caller) comes first; the `gsa` CLI and the service's RQ worker
(whose forked work horses need a fork-safe layer) call it before importing anything else.
NUMBA_THREADING_LAYER, where set, is left to decide. Standard library only (numba is not
imported here), so the CLI's start-up can call it.
"""

from __future__ import annotations

import os
import sys
import threading

THREADING_LAYER_ENV = "NUMBA_THREADING_LAYER"


def use_workqueue_layer() -> None:
    """numba's workqueue threading layer unless NUMBA_THREADING_LAYER says otherwise.
    Must happen before the first kernel launches the threads; later it has no effect. Before
    numba's import, the environment variable (numba reads it once, at import; child processes
    inherit it); after it, numba's config."""
    if THREADING_LAYER_ENV in os.environ:
        return
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.THREADING_LAYER = "workqueue"
    else:
        os.environ[THREADING_LAYER_ENV] = "workqueue"


use_workqueue_layer()

KERNEL_LOCK = threading.RLock()
