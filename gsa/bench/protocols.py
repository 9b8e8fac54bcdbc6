"""Benchmark protocols on generated data: each deterministic by seed, each
printing a markdown table and writing JSON.

dup       paper App. C: a model duplicated under a random Sim(3) (≤180° per axis, ≤10× scale)
same      paper Table 1 analogue: two independent samplings of one object, authors' perturbation
category  paper Table 2 analogue: different instances of one category, random Sim(3)
speed     coarse alignment time and peak memory against Gaussian count
io        PLY write/read time and memory for a 1M-Gaussian file
"""

from __future__ import annotations

import itertools
import json
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import date
from pathlib import Path

import numpy as np

from gsa.align.pipeline import AlignOptions, align
from gsa.metrics import accuracy
from gsa.synth import CATEGORIES, make_object, paper_perturbation, random_sim3

SUCCESS_RRE_DEG = 5.0


def _stages_available() -> list[tuple[str, ...]]:
    try:
        import gsa.align.fine  # noqa: F401
    except ImportError:
        return [("coarse",)]
    return [("coarse",), ("coarse", "fine")]


def _run_pairs(name: str, pairs: list[tuple[str, Callable]], stages_list, out: Path) -> list[dict]:
    """pairs: (label, make() -> (source, target, truth)). Returns one row per stages."""
    rows = []
    for stages in stages_list:
        records = []
        for label, make in pairs:
            source, target, truth = make()
            t0 = time.perf_counter()
            result = align(source, target, AlignOptions(stages=stages))
            seconds = time.perf_counter() - t0
            acc = accuracy(result.transform, truth, source.means, target.means)
            records.append({"pair": label, "seconds": seconds, **acc,
                            "inlier_fraction": result.metrics["inlier_fraction"]})
        rre = np.array([r["rre_deg"] for r in records])
        row = {
            "protocol": name,
            "stages": "+".join(stages),
            "pairs": len(records),
            "mean_rre_deg": float(rre.mean()),
            "median_rre_deg": float(np.median(rre)),
            "mean_scale_error_pct": float(np.mean([r["scale_error_pct"] for r in records])),
            "mean_ate_normalized": float(np.mean([r["ate_normalized"] for r in records])),
            "success_rate": float(np.mean(rre < SUCCESS_RRE_DEG)),
            "seconds_per_pair": float(np.mean([r["seconds"] for r in records])),
            "records": records,
        }
        rows.append(row)
    _save(out, name, rows)
    return rows


def protocol_dup(quick: bool, seed: int, out: Path) -> list[dict]:
    per_category = 1 if quick else 5
    n = 5000 if quick else 30_000
    pairs = []
    for cat, i in itertools.product(CATEGORIES, range(per_category)):

        def make(cat=cat, i=i):
            rng = np.random.default_rng([seed, i, CATEGORIES.index(cat)])
            model = make_object(cat, seed=100 + i, n_gaussians=n, sh_degree=1)
            truth = random_sim3(rng)
            return model, model.transformed(truth), truth

        pairs.append((f"{cat}-{i}", make))
    return _run_pairs("dup", pairs, _stages_available(), out)


def protocol_same(quick: bool, seed: int, out: Path) -> list[dict]:
    count = 6 if quick else 15
    pairs = []
    for i in range(count):
        cat = CATEGORIES[i % len(CATEGORIES)]

        def make(cat=cat, i=i):
            rng = np.random.default_rng([seed, 77, i])
            n_src, n_dst = (4000, 5000) if quick else (25_000, 35_000)
            truth = paper_perturbation(rng)
            source = make_object(cat, seed=200 + i, n_gaussians=n_src, sample_seed=1000 + i, floaters=0.02)
            target = make_object(cat, seed=200 + i, n_gaussians=n_dst, sample_seed=2000 + i, floaters=0.02)
            return source, target.transformed(truth), truth

        pairs.append((f"{cat}-{i}", make))
    return _run_pairs("same", pairs, _stages_available(), out)


def protocol_category(quick: bool, seed: int, out: Path) -> list[dict]:
    instances = 3 if quick else 5
    n = 3000 if quick else 15_000
    rows = []
    for cat in CATEGORIES:
        pairs = []
        for a, b in itertools.combinations(range(instances), 2):

            def make(cat=cat, a=a, b=b):
                rng = np.random.default_rng([seed, 55, a, b, CATEGORIES.index(cat)])
                truth = random_sim3(rng)
                source = make_object(cat, seed=300 + a, n_gaussians=n)
                target = make_object(cat, seed=300 + b, n_gaussians=n).transformed(truth)
                return source, target, truth

            pairs.append((f"{cat}-{a}-{b}", make))
        for row in _run_pairs(f"category-{cat}", pairs, _stages_available(), out):
            row["category"] = cat
            rows.append(row)
    _save(out, "category", rows)
    return rows


def _speed_child(n: int, seed: int) -> dict:
    """One size in a fresh process so peak RSS belongs to this size alone."""
    truth = random_sim3(np.random.default_rng(seed))
    source = make_object("car", seed=1, n_gaussians=n, sample_seed=1, floaters=0.02)
    target = make_object("car", seed=1, n_gaussians=n, sample_seed=2).transformed(truth)
    align(source.subset(np.arange(2000)), target.subset(np.arange(2000)))  # compile kernels outside the timing
    base = _rss_now_mb()
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    result = align(source, target)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    acc = accuracy(result.transform, truth, source.means, target.means)
    return {
        "gaussians": n,
        "align_seconds": seconds,
        "coarse_seconds": sum(result.timings[k] for k in ("features", "hypotheses", "coarse")),
        "timings": result.timings,
        "peak_rss_mb": peak,
        "alignment_peak_mb": max(peak - max(base, peak_before), 0.0) if peak > peak_before else 0.0,
        "process_rss_before_mb": base,
        "rre_deg": acc["rre_deg"],
    }


def _rss_now_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return 0.0


def protocol_speed(quick: bool, seed: int, out: Path) -> list[dict]:
    sizes = [10_000, 50_000] if quick else [10_000, 50_000, 100_000, 200_000]
    rows = []
    for n in sizes:
        proc = subprocess.run(
            [sys.executable, "-c", f"import json; from gsa.bench.protocols import _speed_child; "
             f"print(json.dumps(_speed_child({n}, {seed})))"],
            capture_output=True, text=True, check=True,
        )
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        row["protocol"] = "speed"
        rows.append(row)
        print(f"  {n} Gaussians: {row['align_seconds']:.2f} s, peak RSS {row['peak_rss_mb']:.0f} MB", file=sys.stderr)
    _save(out, "speed", rows)
    return rows


PROTOCOLS = {"dup": protocol_dup, "same": protocol_same, "category": protocol_category, "speed": protocol_speed}


def _save(out: Path, name: str, rows: list[dict]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = {"date": date.today().isoformat(), "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
            "python": platform.python_version()}
    (out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))


def format_table(name: str, rows: list[dict]) -> str:
    if name == "io":
        lines = ["| Gaussians (SH degree 3) | file (MB) | write (s) | read (s) | RSS growth after read (MB) |",
                 "|---:|---:|---:|---:|---:|"]
        for r in rows:
            lines.append(f"| {r['gaussians']:,} | {r['file_mb']:.0f} | {r['write_seconds']:.2f} | "
                         f"{r['read_seconds']:.2f} | {r['rss_growth_mb']:.0f} |")
        return "\n".join(lines)
    if name == "speed":
        lines = ["| Gaussians (each model) | align total (s) | coarse (s) | peak RSS (MB) | alignment's own peak (MB) | RRE (°) |",
                 "|---:|---:|---:|---:|---:|---:|"]
        for r in rows:
            lines.append(f"| {r['gaussians']:,} | {r['align_seconds']:.2f} | {r['coarse_seconds']:.2f} | "
                         f"{r['peak_rss_mb']:.0f} | {r['alignment_peak_mb']:.0f} | {r['rre_deg']:.3f} |")
        return "\n".join(lines)
    lines = ["| protocol | stages | pairs | mean RRE (°) | median RRE (°) | mean scale err (%) | mean ATE / diag | success (RRE<5°) | s / pair |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['protocol']} | {r['stages']} | {r['pairs']} | {r['mean_rre_deg']:.4f} | {r['median_rre_deg']:.4f} | "
            f"{r['mean_scale_error_pct']:.4f} | {r['mean_ate_normalized']:.5f} | {r['success_rate'] * 100:.0f}% | "
            f"{r['seconds_per_pair']:.2f} |"
        )
    return "\n".join(lines)


def run_protocols(names: list[str], quick: bool = False, out: str = "out/bench", seed: int = 0) -> int:
    unknown = [n for n in names if n not in PROTOCOLS]
    if unknown:
        raise ValueError(f"unknown protocol(s) {', '.join(unknown)}; choose from {', '.join(PROTOCOLS)}")
    out_dir = Path(out)
    print(f"GSA benchmarks — {date.today().isoformat()}, {platform.machine()}, {os.cpu_count()} CPU cores"
          f"{' (quick)' if quick else ''}")
    for name in names:
        t0 = time.perf_counter()
        rows = PROTOCOLS[name](quick, seed, out_dir)
        print(f"\n### {name} ({time.perf_counter() - t0:.0f} s)\n")
        print(format_table(name, rows))
        sys.stdout.flush()
    print(f"\nJSON: {out_dir}/")
    return 0


def _io_child(n: int) -> dict:
    import tempfile

    from gsa.io.ply import read_ply, write_ply

    model = make_object("bus", seed=1, n_gaussians=n, sh_degree=3)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "big.ply"
        t0 = time.perf_counter()
        write_ply(model, path)
        write_s = time.perf_counter() - t0
        size_mb = path.stat().st_size / 2**20
        del model
        base = _rss_now_mb()
        t0 = time.perf_counter()
        loaded = read_ply(path)
        read_s = time.perf_counter() - t0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return {"gaussians": len(loaded), "file_mb": size_mb, "write_seconds": write_s, "read_seconds": read_s,
                "rss_growth_mb": _rss_now_mb() - base, "peak_rss_mb": peak}


def protocol_io(quick: bool, seed: int, out: Path) -> list[dict]:
    n = 200_000 if quick else 1_000_000
    proc = subprocess.run(
        [sys.executable, "-c", f"import json; from gsa.bench.protocols import _io_child; print(json.dumps(_io_child({n})))"],
        capture_output=True, text=True, check=True,
    )
    rows = [json.loads(proc.stdout.strip().splitlines()[-1]) | {"protocol": "io"}]
    _save(out, "io", rows)
    return rows


PROTOCOLS["io"] = protocol_io
