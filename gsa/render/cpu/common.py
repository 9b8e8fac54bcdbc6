"""Shared by the CPU kernels: tile size, work split, the kernel lock (gsa.kernels)."""

from __future__ import annotations

import numpy as np
import torch

from gsa.kernels import KERNEL_LOCK

TILE = 16
_CHUNKS = 64  # work items per camera for loops over Gaussians (load balance across threads)

# The threading layer and the lock every parallel launch takes (gsa.kernels: numba's OpenMP
# layer spin-waits and starves torch; the workqueue layer must not be entered from two threads).
_KERNEL_LOCK = KERNEL_LOCK


def _np(t: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))
