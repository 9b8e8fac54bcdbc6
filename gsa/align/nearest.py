"""Nearest-neighbour lookups shared by the ICP loops of the coarse stage and the robust search.

`nearest_candidate` scans a fixed (N, K) table of candidate target indices (feature-compatible
candidates, or a cached k-nearest table) for the one closest to each moved source point, so
that an ICP iteration is a compiled gather and argmin instead of a KD-tree query.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(parallel=True, cache=True)
def nearest_candidate(x, q, table):  # pragma: no cover - compiled
    """Per row i: the candidate table[i, k] (-1 = none) closest to x[i]."""
    n, k = table.shape
    dist = np.empty(n)
    index = np.empty(n, np.int64)
    for i in numba.prange(n):
        best = np.inf
        arg = -1
        for j in range(k):
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
    return dist, index


def query_workers(n_queries: int, workers: int = -1) -> int:
    """scipy starts fresh threads on every parallel query; below ~20k queries
    that costs more than it saves."""
    return workers if n_queries >= 20_000 else 1
