"""Benchmark records: the method labels, one protocol's evaluation loop (every runner
on every pair, one record per method and pair), the per-method summary row with its
confidence calibration, and the JSON each protocol writes.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from collections.abc import Callable
from datetime import date
from pathlib import Path

import numpy as np

from gsa.align.semantic import MODEL_VIEWS
from gsa.metrics import accuracy, rre_deg
from gsa.sim3 import Sim3

SUCCESS_RRE_DEG = 5.0
GSA_COARSE = "GSA coarse"
GSA_FINE = "GSA coarse+fine"
# The paper's pipeline: feature-guided ICP (Alg. 3) alone, then the fine stage.
GSA_PAPER_COARSE = "GSA feature-stage coarse (paper Alg. 3, no NN refinement)"
GSA_PAPER_FINE = "GSA feature-stage coarse + fine"
NOISE_NOTE = (
    "Timings: 2 shared CPU cores, other jobs running; seconds are noisy "
    "(compare ratios measured in one run, not absolute values across runs)."
)

Pair = tuple[str, Callable[[], tuple]]  # (label, make() -> (source, target, truth))
# (source, target) -> {method: (Sim3 | Exception, seconds[, extra fields for the record])}
Runner = Callable[[object, object], dict]

# --quick keeps the fine stage but makes it cheap enough for a smoke run.
QUICK_FINE = dict(fine_iterations=10, fine_image_size=64, fine_views=3)


def evaluate(
    name: str,
    pairs: list[Pair],
    runners: list[Runner],
    extra: Callable[[str], dict] | None = None,
    out: Path | None = None,
    judge: Callable[[Sim3, Sim3, object, object], dict] | None = None,
) -> list[dict]:
    """Every runner on every pair (generated once, in turn); one row per method.
    With `out`, the rows so far are saved after each pair (as NAME.partial.json),
    so a run cut short still leaves its numbers. `judge(estimate, truth, source,
    target)` adds fields to the record of each successful estimate."""
    records: dict[str, list[dict]] = {}
    for done, (label, make) in enumerate(pairs, 1):
        source, target, truth = make()
        for run in runners:
            # every run timed as a lone alignment: a model met again (one source in several pairs,
            # one pair under several runners) would find its views kept from the run before
            MODEL_VIEWS.clear()
            for method, (est, seconds, *fields) in run(source, target).items():
                rec = {"pair": label, "seconds": seconds, **(extra(label) if extra else {})}
                if fields:
                    rec.update(fields[0])
                alternatives = rec.pop("alternatives", None)
                if isinstance(est, Sim3):
                    rec.update(accuracy(est, truth, source.means, target.means))
                    if judge is not None:
                        rec.update(judge(est, truth, source, target))
                    if alternatives:
                        rec["closest_alternative_rre_deg"] = _closest_alternative(
                            alternatives, truth, source, target, judge
                        )
                else:
                    rec.update(
                        error=f"{type(est).__name__}: {est}",
                        rre_deg=float("nan"),
                        scale_error_pct=float("nan"),
                        ate=float("nan"),
                        ate_normalized=float("nan"),
                    )
                records.setdefault(method, []).append(rec)
        print(f"  {name}: {label} done ({done}/{len(pairs)})", file=sys.stderr, flush=True)
        if out is not None and done < len(pairs):
            partial = [summarise(name, method, recs) for method, recs in records.items()]
            add_time_ratio(partial)
            save_rows(out, f"{name}.partial", partial)
    rows = [summarise(name, method, recs) for method, recs in records.items()]
    add_time_ratio(rows)
    if out is not None:
        (out / f"{name}.partial.json").unlink(missing_ok=True)
    return rows


def _closest_alternative(alternatives: list, truth: Sim3, source, target, judge) -> float:
    """RRE of the alternative pose nearest the truth (as the judge measures it, if any): can a
    person who is shown the alternatives pick the right one?"""
    errors = []
    for matrix in alternatives:
        alt = Sim3.from_matrix(np.asarray(matrix, np.float64))
        judged = judge(alt, truth, source, target) if judge is not None else {}
        errors.append(float(judged.get("rre_deg", rre_deg(alt.rotation, truth.rotation))))
    return min(errors)


def summarise(protocol: str, method: str, records: list[dict]) -> dict:
    ok = [r for r in records if "error" not in r]
    rre = np.array([r["rre_deg"] for r in ok]) if ok else np.array([np.nan])

    def mean(key):
        return float(np.mean([r[key] for r in ok])) if ok else float("nan")

    row = {
        "protocol": protocol,
        "method": method,
        "pairs": len(records),
        "failed": len(records) - len(ok),
        "mean_rre_deg": float(rre.mean()),
        "median_rre_deg": float(np.median(rre)),
        "mean_scale_error_pct": mean("scale_error_pct"),
        "mean_ate_normalized": mean("ate_normalized"),
        # A failed pair is not a success.
        "success_rate": float(np.sum(rre < SUCCESS_RRE_DEG) / len(records)),
        "seconds_per_pair": float(np.mean([r["seconds"] for r in records])),
        "records": records,
    }
    if any("category" in r for r in records):
        row["per_category_mean_rre_deg"] = per_category(records)
    if any("rre_any_symmetric_deg" in r for r in records):
        any_rre = np.array([r.get("rre_any_symmetric_deg", np.nan) for r in records], np.float64)
        row["mean_rre_any_symmetric_deg"] = float(np.nanmean(any_rre)) if np.isfinite(any_rre).any() else float("nan")
        row["success_rate_any_symmetric"] = float(np.sum(any_rre < SUCCESS_RRE_DEG) / len(records))
    row.update(calibration(records))
    return row


def _is_success(rec: dict) -> bool:
    return "error" not in rec and bool(rec.get("rre_deg", np.nan) < SUCCESS_RRE_DEG)


def calibration(records: list[dict]) -> dict:
    """How well the `doubtful` flag (align()'s metrics, GSA rows only) tracks
    failure (RRE ≥ 5° or an error), over the records that carry it; {} if none do.
    flagged_rate: share flagged; unflagged_success_rate: share of the unflagged
    that succeeded; failures_flagged_rate: share of the failures that were
    flagged (NaN where the denominator is empty)."""
    recs = [r for r in records if "doubtful" in r]
    if not recs:
        return {}
    flagged = np.array([bool(r["doubtful"]) for r in recs])
    success = np.array([_is_success(r) for r in recs])
    unflagged, failures = success[~flagged], flagged[~success]
    conf = [r["confidence"] for r in recs if r.get("confidence") is not None]
    return {
        "flag_results": len(recs),
        "flagged": int(flagged.sum()),
        "flagged_rate": float(flagged.mean()),
        "unflagged": len(unflagged),
        "unflagged_success_rate": float(unflagged.mean()) if len(unflagged) else float("nan"),
        "failures": len(failures),
        "failures_flagged_rate": float(failures.mean()) if len(failures) else float("nan"),
        "confidence_reported": len(conf),
        "mean_confidence": float(np.mean(conf)) if conf else float("nan"),
    }


def add_time_ratio(rows: list[dict], reference: str = GSA_COARSE) -> None:
    ref = next((r["seconds_per_pair"] for r in rows if r["method"] == reference), None)
    for r in rows:
        r["time_ratio_vs_gsa_coarse"] = r["seconds_per_pair"] / ref if ref else float("nan")


def per_category(records: list[dict]) -> dict:
    """Mean RRE per category, in the order the categories first appear."""
    out = {}
    for cat in dict.fromkeys(r["category"] for r in records if "category" in r):
        out[cat] = float(np.mean([r["rre_deg"] for r in records if r.get("category") == cat]))
    return out


def save_rows(out: Path, name: str, rows: list[dict]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "date": date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
        "python": platform.python_version(),
        "note": NOISE_NOTE,
    }
    (out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2, default=str))
