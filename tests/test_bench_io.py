"""`gsa bench io`'s pieces on small models: a format's round-trip child reports time, memory
and errors within the format's bounds, and the tables render every row."""

from __future__ import annotations

import json
import subprocess
import sys

from benchmarks.formats_io import MEASURED_ENV, format_tables
from benchmarks.tables import format_table
from gsa.io.formats import ROUNDTRIP_BOUNDS


def test_roundtrip_child_reports_errors_within_bounds_and_tables_render():
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.formats_io", "spz", "3000"],
        capture_output=True,
        text=True,
        timeout=300,
        env=MEASURED_ENV,
    )
    assert proc.returncode == 0, proc.stderr
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    assert row["format"] == "spz" and row["gaussians"] == 3000 and row["sh_degree_kept"] == 3
    assert row["write_seconds"] > 0 and row["read_seconds"] > 0 and row["file_mb"] > 0
    for name, bound in ROUNDTRIP_BOUNDS["spz"].items():
        assert 0 < row["errors"][name]["max"] <= bound, name  # quantised: never exactly 0
    pair = {"source": "ply", "target": "spz", "gaussians": 10, "pairs": 1, "rre_deg_mean": 0.1}
    pair |= {"rre_deg_max": 0.1, "scale_error_pct_mean": 0.01, "ate_normalized_mean": 1e-4}
    text = format_tables([row], [pair])
    assert "| spz | 3,000 | 3 |" in text and "| ply | spz | 1 | 0.1000 |" in text
    rows = [{"gaussians": 5, "file_mb": 1, "write_seconds": 1, "read_seconds": 1, "rss_growth_mb": 1}]
    rows += [row | {"kind": "roundtrip"}, pair | {"kind": "pair"}]
    assert format_table("io", rows).count("\n|") >= 8
