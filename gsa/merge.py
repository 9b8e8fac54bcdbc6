"""Merging an aligned source into its target without doubling the density in the overlap.

Two captures of one surface both hold Gaussians there; concatenated, the overlap renders
twice as dense (and twice as opaque). `merge_dedup` pairs each aligned source Gaussian
with its nearest target Gaussian and treats the pair as one surface element when they lie
within `radius` × their (geometric-mean) size and their base colours differ by at most
`colour_tol` (RGB in [0, 1], largest channel); of each such pair the more opaque Gaussian
stays. Each target Gaussian pairs at most once (the closest source wins).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gsa.model import GaussianModel, merge_models

MERGE_MODES = ("concat", "dedup")


def duplicate_pairs(
    source: GaussianModel, target: GaussianModel, *, radius: float = 0.5, colour_tol: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """(source index, target index) of the duplicated pairs."""
    dist, j = cKDTree(target.means).query(source.means, k=1, workers=-1)
    size_s = np.exp(source.log_scales.astype(np.float64).mean(axis=1))
    size_t = np.exp(target.log_scales.astype(np.float64).mean(axis=1))
    close = dist <= radius * np.sqrt(size_s * size_t[j])
    similar = np.abs(source.base_colors - target.base_colors[j]).max(axis=1) <= colour_tol
    i = np.flatnonzero(close & similar)
    j = j[i]
    # one pair per target Gaussian: the closest source
    order = np.lexsort((dist[i], j))
    i, j = i[order], j[order]
    first = np.ones(len(j), bool)
    first[1:] = j[1:] != j[:-1]
    return i[first], j[first]


def merge_plan(
    source: GaussianModel, target: GaussianModel, mode: str = "concat"
) -> tuple[tuple[np.ndarray | None, np.ndarray | None], int]:
    """Which rows of (source, target) the merged model keeps (None: all), and how many
    duplicates were removed. `merge_models(source, target, keep=...)` builds the merged
    model; `gsa.io.ply.write_ply((source, target), path, keep=...)` writes it without
    building it (scene-size merges)."""
    if mode == "concat":
        return (None, None), 0
    if mode != "dedup":
        raise ValueError(f"unknown merge mode {mode!r}; choose from {', '.join(MERGE_MODES)}")
    return _dedup_keep(source, target)


def _dedup_keep(
    source: GaussianModel, target: GaussianModel, radius: float = 0.5, colour_tol: float = 0.1
) -> tuple[tuple[np.ndarray, np.ndarray], int]:
    i, j = duplicate_pairs(source, target, radius=radius, colour_tol=colour_tol)
    source_wins = source.opacity_logits[i] >= target.opacity_logits[j]
    keep_s = np.ones(len(source), bool)
    keep_t = np.ones(len(target), bool)
    keep_s[i[~source_wins]] = False
    keep_t[j[source_wins]] = False
    return (keep_s, keep_t), int(len(i))


def merge_dedup(
    source: GaussianModel, target: GaussianModel, *, radius: float = 0.5, colour_tol: float = 0.1
) -> tuple[GaussianModel, int]:
    """source + target with each duplicated pair reduced to its more opaque Gaussian;
    returns the merged model and how many Gaussians were removed."""
    keep, removed = _dedup_keep(source, target, radius, colour_tol)
    # Rows selected while merging: subsets first would hold the merged data twice.
    return merge_models(source, target, keep=keep), removed


def merge(source: GaussianModel, target: GaussianModel, mode: str = "concat") -> tuple[GaussianModel, int]:
    keep, removed = merge_plan(source, target, mode)
    return merge_models(source, target, keep=keep), removed
