"""Alignment across file formats: a generated pair stored as PLY / SPZ / compressed PLY /
.splat / GLB with a random Sim(3) is recovered as accurately as the same pair as PLY ↔ PLY,
within the formats' quantisation (axes mapped by the readers, gsa.io.frames)."""

from __future__ import annotations

import pytest

from benchmarks.formats_io import PAIR_FORMATS, align_pair

N = 4000
PAIRS = [(a, b) for i, a in enumerate(PAIR_FORMATS) for b in PAIR_FORMATS[i:] if (a, b) != ("ply", "ply")]


@pytest.fixture(scope="module")
def ply_baseline(tmp_path_factory):
    return align_pair("ply", "ply", N, 0, tmp_path_factory.mktemp("ply"))


@pytest.mark.parametrize(("source", "target"), PAIRS, ids=[f"{a}-{b}" for a, b in PAIRS])
def test_pair_is_recovered_as_well_as_ply(ply_baseline, tmp_path, source, target):
    got = align_pair(source, target, N, 0, tmp_path)
    assert ply_baseline["rre_deg"] < 0.5  # the PLY pair itself is recovered
    # quantisation moves Gaussians by < 3e-4 of the diagonal and rotations by < 1°:
    # the recovered pose may differ from the PLY pair's by a few hundredths of a degree
    assert got["rre_deg"] <= ply_baseline["rre_deg"] + 0.1, got
    assert got["scale_error_pct"] <= ply_baseline["scale_error_pct"] + 0.1, got
    assert got["ate_normalized"] <= 2 * ply_baseline["ate_normalized"] + 1e-4, got
