"""Speed and I/O protocols: each (size, stage) measured in a fresh process so that its
peak RSS belongs to it alone. The child processes run this module:

    python -m benchmarks.speed stage N SEED STAGE [--quick]   # one JSON row on stdout
    python -m benchmarks.speed io N
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.records import QUICK_FINE, save_rows
from gsa.align.pipeline import AlignOptions, align
from gsa.canonical import canonical_features
from gsa.metrics import accuracy
from gsa.render.cameras import cameras_around
from gsa.synth import (
    make_object,
    random_sim3,
)


def speed_child(n: int, seed: int, stage: str, quick: bool = False) -> dict:
    """One (size, stage) in a fresh process so peak RSS belongs to it alone."""
    truth = random_sim3(np.random.default_rng(seed))
    source = make_object("car", seed=1, n_gaussians=n, sample_seed=1, floaters=0.02)
    target = make_object("car", seed=1, n_gaussians=n, sample_seed=2).transformed(truth)
    small_s, small_t = source.subset(np.arange(2000)), target.subset(np.arange(2000))
    row = {"gaussians": n, "stage": stage}
    if stage == "coarse":
        align(small_s, small_t)  # compile kernels outside the timing
        fn = lambda: align(source, target)  # noqa: E731
    elif stage == "fine":
        align(small_s, small_t, AlignOptions(stages=("coarse", "fine"), fine_iterations=1))
        coarse = align(source, target)
        from gsa.align.fine import FineOptions, fine_align  # lazy: torch, only this stage's child process

        src = source.with_features(canonical_features(source.means.astype(np.float64), coarse.source_frame))
        dst = target.with_features(canonical_features(target.means.astype(np.float64), coarse.target_frame))
        d = AlignOptions(**(QUICK_FINE if quick else {}))
        opts = FineOptions(iterations=d.fine_iterations, lr=d.fine_lr, views=d.fine_views, image_size=d.fine_image_size)
        row.update(views=d.fine_views, image_size=d.fine_image_size, iterations=d.fine_iterations)
        fn = lambda: fine_align(src, dst, coarse.transform, opts)  # noqa: E731
    elif stage == "render":
        from gsa.render import render_model  # lazy: torch, only this stage's child process

        cams = cameras_around(target.means, 1, 256)
        render_model(small_t, cams, features=False)
        row.update(views=1, image_size=256)
        fn = lambda: render_model(target, cams, features=False)  # noqa: E731
    elif stage == "lift":
        from gsa.features import CanonicalExtractor, lift_features

        lift_features(small_t, CanonicalExtractor("cpu"), views=2, image_size=32, iterations=1, backend="cpu")
        views, size, iters = (6, 64, 20) if quick else (24, 128, 150)  # lifting's own defaults when full
        row.update(views=views, image_size=size, iterations=iters)

        def fn():
            return lift_features(
                target, CanonicalExtractor("cpu"), views=views, image_size=size, iterations=iters, backend="cpu"
            )
    else:
        raise ValueError(stage)
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    base = rss_now_mb()
    t0 = time.perf_counter()
    result = fn()
    row["seconds"] = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row["peak_rss_mb"] = peak
    row["stage_peak_mb"] = max(peak - base, 0.0) if peak > peak_before else 0.0
    if stage == "coarse":
        row["rre_deg"] = accuracy(result.transform, truth, source.means, target.means)["rre_deg"]
    return row


def rss_now_mb() -> float:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return 0.0


def speed_stages(fine: bool = True) -> list[str]:
    stages = ["coarse"]
    if fine:
        stages.append("fine")
    else:
        print("note: speed: fine-stage rows off, fine timing skipped")
    return [*stages, "render", "lift"]


def protocol_speed(quick: bool, seed: int, out: Path, peers: list[str] | None = None, fine: bool = True) -> list[dict]:
    """Each size × stage (`fine` False: no fine-stage rows) in its own child process."""
    sizes = [2_000, 5_000] if quick else [10_000, 50_000, 100_000, 200_000]
    rows = []
    for n, stage in itertools.product(sizes, speed_stages(fine)):
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "benchmarks.speed",
                "stage",
                str(n),
                str(seed),
                stage,
                *(["--quick"] if quick else []),
            ],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
            print(f"note: speed {stage} at {n} failed: {tail}")
            rows.append({"protocol": "speed", "gaussians": n, "stage": stage, "error": tail})
            continue
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        row["protocol"] = "speed"
        rows.append(row)
        print(
            f"  {n} Gaussians, {stage}: {row['seconds']:.2f} s, peak RSS {row['peak_rss_mb']:.0f} MB",
            file=sys.stderr,
            flush=True,
        )
    save_rows(out, "speed", rows)
    return rows


# ---------------------------------------------------------------- io


def io_child(n: int) -> dict:
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
        base = rss_now_mb()
        t0 = time.perf_counter()
        loaded = read_ply(path)
        read_s = time.perf_counter() - t0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return {
            "gaussians": len(loaded),
            "file_mb": size_mb,
            "write_seconds": write_s,
            "read_seconds": read_s,
            "rss_growth_mb": rss_now_mb() - base,
            "peak_rss_mb": peak,
        }


def protocol_io(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    n = 200_000 if quick else 1_000_000
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.speed", "io", str(n)],
        capture_output=True,
        text=True,
        check=True,
    )
    rows = [json.loads(proc.stdout.strip().splitlines()[-1]) | {"protocol": "io"}]
    from benchmarks.formats_io import protocol_formats  # every format's round trip and format pairs

    roundtrips, pairs = protocol_formats(quick)
    rows += [r | {"protocol": "io", "kind": "roundtrip"} for r in roundtrips]
    rows += [r | {"protocol": "io", "kind": "pair"} for r in pairs]
    save_rows(out, "io", rows)
    return rows


def main(argv: list[str] | None = None) -> int:
    """A child process of the speed and io protocols: one JSON row on stdout."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed", description=main.__doc__)
    sub = parser.add_subparsers(dest="what", required=True)
    stage = sub.add_parser("stage", help="one (size, stage) of the speed protocol")
    stage.add_argument("n", type=int)
    stage.add_argument("seed", type=int)
    stage.add_argument("stage", choices=("coarse", "fine", "render", "lift"))
    stage.add_argument("--quick", action="store_true")
    io = sub.add_parser("io", help="PLY write/read of N Gaussians")
    io.add_argument("n", type=int)
    args = parser.parse_args(argv)
    row = speed_child(args.n, args.seed, args.stage, args.quick) if args.what == "stage" else io_child(args.n)
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
