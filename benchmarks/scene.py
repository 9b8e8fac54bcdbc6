"""The `scene` protocol's judge, per-call peak memory and table.

Success on a scene pair: RRE < 2° and translation error < 2 % of the room's extent.
The translation error is measured where it matters, at the source capture's centroid:
‖est(c) − truth(c)‖ over the room's diagonal in the target's units (a Sim(3)'s
translation vector alone depends on where the origin happens to be).

Peak memory per method: the kernel's high-water mark of this process (VmHWM), reset
before each call (/proc/self/clear_refs), so each method's peak is its own; the growth
column is that peak less the resident size before the call (the pair already loaded,
freed heap pages first handed back to the kernel with glibc's malloc_trim).
"""

from __future__ import annotations

import ctypes
import gc
from pathlib import Path

import numpy as np

from benchmarks.records import Runner
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3

SCENE_RRE_DEG = 2.0
SCENE_TRANSLATION_PCT = 2.0


def scene_judge(est: Sim3, truth: Sim3, source, target) -> dict:
    centre = source.means.mean(axis=0, dtype=np.float64)
    extent = float(target.metadata["scene_extent"])
    err_pct = float(np.linalg.norm(est.apply(centre) - truth.apply(centre)) / extent * 100.0)
    rre = rre_deg(est.rotation, truth.rotation)
    return {
        "translation_error_pct_extent": err_pct,
        "scene_success": bool(rre < SCENE_RRE_DEG and err_pct < SCENE_TRANSLATION_PCT),
        "source_gaussians": len(source),
        "target_gaussians": len(target),
        "overlap": target.metadata.get("pair_overlap"),
    }


def _status_mb(key: str) -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _trim_heap() -> None:
    """Give freed heap pages back to the kernel (glibc), so that the resident size before
    a call is its live data and memory freed by the previous method cannot hide this
    method's growth."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")  # Linux: VmHWM := current RSS
        return True
    except OSError:
        return False


def with_peak_memory(run: Runner) -> Runner:
    """`run` whose records gain peak_rss_mb and peak_growth_mb (None where the kernel
    cannot reset the high-water mark: not Linux)."""

    def measured(source, target):
        gc.collect()
        _trim_heap()
        before = _status_mb("VmRSS")
        peak = None
        reset = _reset_peak()
        out = run(source, target)
        if reset:
            peak = _status_mb("VmHWM")
        fields = {
            "peak_rss_mb": peak,
            "peak_growth_mb": None if peak is None or before is None else max(peak - before, 0.0),
        }
        return {m: (est, secs, {**(extra[0] if extra else {}), **fields}) for m, (est, secs, *extra) in out.items()}

    return measured


def add_scene_summary(rows: list[dict]) -> None:
    """Each row gains the scene success rate and medians (a failed call is a failure)."""
    for row in rows:
        recs = row["records"]
        ok = [r for r in recs if "error" not in r]

        def median(key, ok=ok):
            vals = [r[key] for r in ok if r.get(key) is not None]
            return float(np.median(vals)) if vals else float("nan")

        peaks = [r["peak_rss_mb"] for r in recs if r.get("peak_rss_mb") is not None]
        row.update(
            scene_success_rate=float(sum(bool(r.get("scene_success")) for r in recs) / max(len(recs), 1)),
            median_scale_error_pct=median("scale_error_pct"),
            median_translation_error_pct_extent=median("translation_error_pct_extent"),
            max_peak_rss_mb=max(peaks) if peaks else float("nan"),
            median_peak_growth_mb=median("peak_growth_mb"),
            scene_path_pairs=sum(bool(r.get("scene_path")) for r in recs),
            median_source_gaussians=median("source_gaussians"),
            median_target_gaussians=median("target_gaussians"),
        )


def _f(x, digits: int) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def format_scene_table(rows: list[dict]) -> str:
    lines = [
        "| method | pairs | success (RRE<2°, t<2% extent) | median RRE (°) | mean RRE (°) | median scale err (%) "
        "| median t err (% extent) | s / pair | max peak RSS (MB) | median peak growth (MB) | scene path |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        failed = f" ({r['failed']} failed)" if r.get("failed") else ""
        lines.append(
            f"| {r['method']} | {r['pairs']}{failed} | {r['scene_success_rate'] * 100:.0f}% | "
            f"{_f(r['median_rre_deg'], 3)} | {_f(r['mean_rre_deg'], 2)} | {_f(r['median_scale_error_pct'], 3)} | "
            f"{_f(r['median_translation_error_pct_extent'], 3)} | {r['seconds_per_pair']:.2f} | "
            f"{_f(r['max_peak_rss_mb'], 0)} | {_f(r['median_peak_growth_mb'], 0)} | "
            f"{r.get('scene_path_pairs', 0)}/{r['pairs']} |"
        )
    sizes = [r for r in rows if np.isfinite(r.get("median_source_gaussians", float("nan")))]
    if sizes:
        r = sizes[0]
        lines += [
            "",
            f"Median capture sizes: source {r['median_source_gaussians']:,.0f}, "
            f"target {r['median_target_gaussians']:,.0f} Gaussians.",
        ]
    return "\n".join(lines)
