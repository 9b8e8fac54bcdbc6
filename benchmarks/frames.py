"""Dominant-normal frames across instances (a diagnostic for the relabelling choice and the guided path's up axes): on category-real's
pairs, is the true rotation one of the 24 relabellings between the two models' Manhattan frames
(gsa.manhattan), and how near?

    python -m benchmarks.frames --data ../shared/data/category-dev [--quick]

Prints, per pair, the relabelling nearest the truth (RRE judged up to each instance's own
symmetries, as category-real judges) and both frames' support, then per class the share within
5 and 10 degrees. No alignment runs: it asks whether the candidates hold the answer, not which
one an aligner would pick.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from benchmarks.category_real import category_real_judge, category_real_pairs
from gsa.manhattan import manhattan_frame, relabellings
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3


def nearest_relabelling(source, target, truth: Sim3) -> dict:
    """The relabelling nearest the truth, judged as category-real judges, and both supports."""
    src, dst = manhattan_frame(source), manhattan_frame(target)
    errors = []
    for rotation in relabellings(src, dst):
        pose = Sim3(1.0, rotation, np.zeros(3))
        errors.append(
            category_real_judge(pose, truth, source, target).get("rre_deg", rre_deg(rotation, truth.rotation))
        )
    return {"rre_deg": float(min(errors)), "source_support": src.support, "target_support": dst.support}


def frame_coverage(data, quick: bool = False, seed: int = 0) -> list[dict]:
    out = []
    for label, make in category_real_pairs(data, quick, seed):
        source, target, truth = make()
        t0 = time.perf_counter()
        rec = nearest_relabelling(source, target, truth)
        out.append({"pair": label, "category": label.rsplit("-", 2)[0], **rec, "seconds": time.perf_counter() - t0})
    return out


def summary(records: list[dict]) -> list[str]:
    lines = [
        "| class | pairs | within 5° | within 10° | median (°) | max (°) | median support |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    classes = list(dict.fromkeys(r["category"] for r in records)) + ["all"]
    for cat in classes:
        rows = [r for r in records if cat in ("all", r["category"])]
        rre = np.array([r["rre_deg"] for r in rows])
        support = np.median([min(r["source_support"], r["target_support"]) for r in rows])
        lines.append(
            f"| {cat} | {len(rows)} | {np.mean(rre < 5) * 100:.0f} % | {np.mean(rre < 10) * 100:.0f} % | "
            f"{np.median(rre):.2f} | {rre.max():.2f} | {support:.2f} |"
        )
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.frames")
    ap.add_argument("--data", required=True, help="a folder of <category>_<i>.npz meshes (category-real's)")
    ap.add_argument("--quick", action="store_true", help="the first 3 instances per class")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="also write the per-pair records here")
    args = ap.parse_args(argv)
    records = frame_coverage(args.data, args.quick, args.seed)
    for r in records:
        print(
            f"{r['pair']}: nearest relabelling {r['rre_deg']:.2f}°, support {r['source_support']:.2f} / "
            f"{r['target_support']:.2f}, {r['seconds']:.2f} s"
        )
    print("\n".join(summary(records)))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
