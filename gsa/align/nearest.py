"""Nearest-neighbour lookups shared by the ICP loops of the coarse stage and the robust search.

`nearest_candidate` scans a fixed (N, K) table of candidate target indices (feature-compatible
candidates, or a cached k-nearest table) for the one closest to each moved source point, so
that an ICP iteration is a compiled gather and argmin instead of a KD-tree query.
"""

from __future__ import annotations

import numba
import numpy as np

from gsa.kernels import KERNEL_LOCK

# Candidate scans below which one thread does the table: a parallel region is worth its
# hand-off only for large tables. On 2 shared cores a 6k × 6 scan took 0.1 ms on one thread
# and 0.7–7 ms in parallel whenever another process (or a spinning BLAS thread) held a core:
# the region waits for its descheduled worker.
PARALLEL_SCANS = 1_000_000


def nearest_candidate(x: np.ndarray, q: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row i: (distance to, index of) the candidate table[i, k] (-1 = none) closest to
    x[i] among the rows of q."""
    if table.size < PARALLEL_SCANS:
        return _scan_serial(x, q, table)
    with KERNEL_LOCK:
        return _scan_parallel(x, q, table)


@numba.njit(cache=True, inline="always")
def _scan_row(i, x, q, table, dist, index):  # pragma: no cover - compiled
    best = np.inf
    arg = -1
    for j in range(table.shape[1]):
        t = table[i, j]
        if t < 0:
            continue
        d0 = x[i, 0] - q[t, 0]
        d1 = x[i, 1] - q[t, 1]
        d2 = x[i, 2] - q[t, 2]
        d = d0 * d0 + d1 * d1 + d2 * d2
        if d < best:
            best = d
            arg = t
    dist[i] = np.sqrt(best)
    index[i] = arg


@numba.njit(cache=True)
def _scan_serial(x, q, table):  # pragma: no cover - compiled
    n = table.shape[0]
    dist = np.empty(n)
    index = np.empty(n, np.int64)
    for i in range(n):
        _scan_row(i, x, q, table, dist, index)
    return dist, index


@numba.njit(parallel=True, cache=True)
def _scan_parallel(x, q, table):  # pragma: no cover - compiled
    n = table.shape[0]
    dist = np.empty(n)
    index = np.empty(n, np.int64)
    for i in numba.prange(n):
        _scan_row(i, x, q, table, dist, index)
    return dist, index


def query_workers(n_queries: int, workers: int = -1) -> int:
    """scipy starts fresh threads on every parallel query; below ~20k queries
    that costs more than it saves."""
    return workers if n_queries >= 20_000 else 1
