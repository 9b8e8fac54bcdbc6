"""Benchmark output: a protocol's rows as a markdown table, and the confidence
calibration lines under it and over all protocols run.
"""

from __future__ import annotations

import numpy as np

from benchmarks.records import GSA_COARSE, calibration
from gsa.synth import (
    CATEGORIES,
)


def _f(x: float, digits: int) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _own_table(name: str, rows: list[dict]) -> str | None:
    """The table of a protocol that formats its own rows, else None."""
    if name in ("scene", "site"):
        from benchmarks.scene import format_scene_table

        return format_scene_table(rows)
    if name == "category-real":
        from benchmarks.category_real import format_category_real

        return format_category_real(rows)
    if name == "real":
        from benchmarks.real_captures import per_capture_table

        return "\n\n".join(t for t in (format_table("real-rows", rows), per_capture_table(rows)) if t)
    if name == "guided":
        from benchmarks.guided import format_guided

        return format_guided(rows)
    return None


def format_table(name: str, rows: list[dict]) -> str:
    own = _own_table(name, rows)
    if own is not None:
        return own
    if name == "io":
        lines = [
            "| Gaussians (SH degree 3) | file (MB) | write (s) | read (s) | RSS growth after read (MB) |",
            "|---:|---:|---:|---:|---:|",
        ]
        for r in rows:
            if "kind" not in r:
                lines.append(
                    f"| {r['gaussians']:,} | {r['file_mb']:.0f} | {r['write_seconds']:.2f} | "
                    f"{r['read_seconds']:.2f} | {r['rss_growth_mb']:.0f} |"
                )
        roundtrips = [r for r in rows if r.get("kind") == "roundtrip"]
        pairs = [r for r in rows if r.get("kind") == "pair"]
        if roundtrips or pairs:
            from benchmarks.formats_io import format_tables

            lines += ["", format_tables(roundtrips, pairs)]
        return "\n".join(lines)
    if name == "speed":
        lines = [
            "| Gaussians (each model) | stage | s | peak RSS (MB) | stage's own peak (MB) | note |",
            "|---:|---|---:|---:|---:|---|",
        ]
        for r in rows:
            if "error" in r:
                lines.append(f"| {r['gaussians']:,} | {r['stage']} | — | — | — | failed: {r['error'][:60]} |")
                continue
            note = ", ".join(f"{k} {r[k]}" for k in ("views", "image_size", "iterations") if k in r)
            if "rre_deg" in r:
                note = f"RRE {r['rre_deg']:.3f}°"
            lines.append(
                f"| {r['gaussians']:,} | {r['stage']} | {r['seconds']:.2f} | {r['peak_rss_mb']:.0f} | "
                f"{r['stage_peak_mb']:.0f} | {note} |"
            )
        return "\n".join(lines)
    if name in ("category", "ablation"):
        cats = [c for c in CATEGORIES if any(c in r.get("per_category_mean_rre_deg", {}) for r in rows)]
        head = "method" if name == "category" else "configuration"
        ratio = "time ratio vs GSA coarse" if name == "category" else "time ratio vs default coarse"
        lines = [
            f"| {head} | "
            + " | ".join(f"{c} RRE (°)" for c in cats)
            + f" | mean RRE (°) | success (RRE<5°) | s / pair | {ratio} |",
            "|---|" + "---:|" * (len(cats) + 4),
        ]
        for r in rows:
            per = r["per_category_mean_rre_deg"]
            lines.append(
                f"| {r['method']} | "
                + " | ".join(_f(per.get(c, float("nan")), 2) for c in cats)
                + f" | {_f(r['mean_rre_deg'], 2)} | {r['success_rate'] * 100:.0f}% | "
                f"{r['seconds_per_pair']:.2f} | {_f(r['time_ratio_vs_gsa_coarse'], 2)} |"
            )
        return "\n".join(lines + _calibration_lines(rows))
    symmetric = any("success_rate_any_symmetric" in r for r in rows)
    sym_head, sym_rule = (" success, any symmetric pose (RRE<5°) |", "---:|") if symmetric else ("", "")
    lines = [
        "| method | pairs | mean RRE (°) | median RRE (°) | mean scale err (%) | mean ATE / diag | "
        "success (RRE<5°) |" + sym_head + " s / pair | time ratio vs GSA coarse |",
        "|---|---:|---:|---:|---:|---:|---:|" + sym_rule + "---:|---:|",
    ]
    for r in rows:
        failed = f" ({r['failed']} failed)" if r.get("failed") else ""
        sym = f" {_pct(r.get('success_rate_any_symmetric'))} |" if symmetric else ""
        lines.append(
            f"| {r['method']} | {r['pairs']}{failed} | {_f(r['mean_rre_deg'], 4)} | {_f(r['median_rre_deg'], 4)} | "
            f"{_f(r['mean_scale_error_pct'], 4)} | {_f(r['mean_ate_normalized'], 5)} | {r['success_rate'] * 100:.0f}% |"
            f"{sym} {r['seconds_per_pair']:.2f} | {_f(r['time_ratio_vs_gsa_coarse'], 2)} |"
        )
    return "\n".join(lines + _calibration_lines(rows))


def _pct(x: float | None) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x * 100:.0f}%"


def _calibration_text(c: dict) -> str:
    text = (
        f"{c['flagged']}/{c['flag_results']} flagged doubtful ({_pct(c['flagged_rate'])}); "
        f"unflagged: {c['unflagged']}, {_pct(c['unflagged_success_rate'])} succeed; "
        f"failures: {c['failures']}, {_pct(c['failures_flagged_rate'])} flagged"
    )
    if not c.get("confidence_reported"):
        text += " (align() reported no confidence)"
    return text


def _calibration_lines(rows: list[dict]) -> list[str]:
    """Lines under a table: the doubtful flag against success, for rows that carry it."""
    cal = [r for r in rows if "flagged_rate" in r]
    if not cal:
        return []
    return ["", "Confidence calibration (success = RRE < 5°):"] + [
        f"- {r['method']}: {_calibration_text(r)}" for r in cal
    ]


def calibration_summary(results: dict[str, list[dict]], method: str = GSA_COARSE) -> str | None:
    """One line over all protocols run: `method`'s doubtful flag against success."""
    names = [n for n, rows in results.items() if any(r.get("method") == method and "flagged_rate" in r for r in rows)]
    records = [rec for n in names for r in results[n] if r.get("method") == method for rec in r["records"]]
    c = calibration(records)
    if not c:
        return None
    return (
        f"Confidence calibration, {method}, over {', '.join(names)}: {c['flag_results']} results; "
        + _calibration_text(c)
    )
