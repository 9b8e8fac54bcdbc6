"""Shared by the CPU kernels: tile size, work split, numba's threading layer and the kernel lock."""

from __future__ import annotations

import os
import threading

import numba
import numpy as np
import torch

TILE = 16
_CHUNKS = 64  # work items per camera for loops over Gaussians (load balance across threads)

# numba's OpenMP layer shares libgomp with torch; on a busy machine spinning torch threads and
# descheduled numba threads make its barriers orders of magnitude slower. The built-in
# workqueue layer degrades gracefully. It must not be entered from two Python
# threads at once, hence _KERNEL_LOCK around every kernel call (the kernels use all cores anyway).
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"
_KERNEL_LOCK = threading.RLock()
# Every kernel module of this package imports this one, so the setting above precedes their
# first launch.


def _np(t: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))
