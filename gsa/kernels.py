"""What every parallel numba kernel of gsa shares: the threading layer, and the lock around
each parallel launch.

numba's default GNU-OpenMP layer spin-waits in its barriers. Its threads then hold the cores
other work needs: after an alignment's search kernels, the semantic tie-break's backbone (torch,
with an OpenMP runtime of its own) ran 4x slower in the same process (a vase pair's tie-break
45 s against 11 s, docs/benchmarks.md, "The kernels' threading layer"), and on a busy machine
the barriers themselves become erratic. The built-in workqueue layer degrades gracefully, but
must not be entered from two Python threads at once (the service's embedded workers are
threads): KERNEL_LOCK around every parallel launch (each kernel uses all cores anyway).

Every module that defines a parallel kernel imports this one, so the layer is chosen before
the first launch, whichever entry point (the CLI, the service, a library caller) comes first.
NUMBA_THREADING_LAYER, where set, is left to decide.
"""

from __future__ import annotations

import os
import threading

import numba

if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"

KERNEL_LOCK = threading.RLock()
