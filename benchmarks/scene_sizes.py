"""Time and peak memory per scene pair vs capture size (the scene path's baseline).

Each size: `--pairs` scene pairs (benchmarks.pairs.scene_pairs, every capture of exactly
that many Gaussians before floaters), GSA's current align() coarse stage and, with
--icp, the plain-ICP peer; one line per pair and method, then a markdown table of the
medians. Peak RSS per call: benchmarks.scene.with_peak_memory.

    .venv/bin/python -m benchmarks.scene_sizes --sizes 250000 500000 1000000 --pairs 2

The captures are benchmarks.pairs.SCENE_HARD's unless --easy (the first baseline's, without SCENE_HARD).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from benchmarks.pairs import scene_pairs
from benchmarks.peers import PlainICP
from benchmarks.protocols import gsa_runner, peer_runner
from benchmarks.scene import scene_judge, with_peak_memory
from gsa.metrics import rre_deg, scale_error_pct


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[250_000, 500_000, 1_000_000])
    parser.add_argument("--pairs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--icp", action="store_true", help="run the plain-ICP peer too")
    parser.add_argument("--easy", action="store_true", help="the baseline's captures (no SCENE_HARD)")
    parser.add_argument("--scene", default="auto", choices=["auto", "on", "off"], help="align()'s scene option")
    args = parser.parse_args(argv)
    runners = [with_peak_memory(gsa_runner(False, scene=args.scene))]
    if args.icp:
        runners.append(with_peak_memory(peer_runner(PlainICP(), args.seed)))
    table: dict[tuple[int, str], list[dict]] = {}
    for size in args.sizes:
        for label, make in scene_pairs(True, args.seed, count=args.pairs, capture_size=size, hard=not args.easy):
            t0 = time.perf_counter()
            source, target, truth = make()
            build = time.perf_counter() - t0
            for run in runners:
                for method, (est, seconds, fields) in run(source, target).items():
                    rec = {"seconds": seconds, "build_seconds": build, **fields}
                    if isinstance(est, Exception):
                        rec.update(error=str(est), scene_success=False)
                    else:
                        rec.update(scene_judge(est, truth, source, target))
                        rec["rre_deg"] = rre_deg(est.rotation, truth.rotation)
                        rec["scale_error_pct"] = scale_error_pct(est.scale, truth.scale)
                    table.setdefault((size, method), []).append(rec)
                    print(f"{size:>9,} {label} {method}: {rec}", file=sys.stderr, flush=True)
    print(
        "| capture Gaussians | method | pairs | success | median RRE (°) | median t err (% extent) "
        "| median s / pair | max peak RSS (MB) | median peak growth (MB) | pair build (s) | scene path |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for (size, method), recs in table.items():

        def med(key, recs=recs):
            vals = [r[key] for r in recs if r.get(key) is not None]
            return float(np.median(vals)) if vals else float("nan")

        ok = sum(bool(r.get("scene_success")) for r in recs)
        peak = max((r["peak_rss_mb"] or 0.0) for r in recs)
        print(
            f"| {size:,} | {method} | {len(recs)} | {ok}/{len(recs)} | {med('rre_deg'):.3f} | "
            f"{med('translation_error_pct_extent'):.3f} | {med('seconds'):.2f} | {peak:.0f} | "
            f"{med('peak_growth_mb'):.0f} | {med('build_seconds'):.1f} | "
            f"{sum(bool(r.get('scene_path')) for r in recs)}/{len(recs)} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
