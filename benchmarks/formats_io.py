"""`gsa bench io`: every format's round trip (time, memory, quantisation error per attribute)
and alignment across format pairs.

Each format is measured in its own child process (`python -m benchmarks.formats_io FORMAT N`)
so one format's peak memory does not hide another's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gsa.model import GaussianModel
from gsa.sh import SH_C0

# Formats whose writer reorders the Gaussians (SOG sorts them along a space-filling curve).
REORDERING = frozenset({"sog"})
PAIR_FORMATS = ("ply", "spz", "compressed-ply", "splat", "glb")
# A fixed mmap threshold: glibc otherwise raises it after the model's generation frees its
# arrays, later allocations reuse freed heap, and the RSS growth of a read or write hides.
MEASURED_ENV = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "131072"}


def matched(original: GaussianModel, read_back: GaussianModel, fmt: str) -> GaussianModel:
    """The original Gaussians in the read-back file's order."""
    if fmt not in REORDERING:
        return original
    # Nearest position alone mismatches Gaussians closer together than the quantisation:
    # of the 4 nearest, the one that also agrees best in size, colour and orientation.
    dist, idx = cKDTree(original.means).query(read_back.means, k=4)
    size = np.abs(original.log_scales[idx] - read_back.log_scales[:, None, :]).sum(axis=2)
    colour = np.abs(original.sh[idx, 0] - read_back.sh[:, None, 0]).sum(axis=2)
    q = original.quats[idx] / np.linalg.norm(original.quats[idx], axis=2, keepdims=True)
    turn = 1 - np.abs((q * read_back.quats[:, None, :]).sum(axis=2))
    cost = dist / max(float(dist[:, 0].max()), 1e-12) + size + colour + turn
    return original.subset(idx[np.arange(len(idx)), cost.argmin(axis=1)])


def attribute_errors(original: GaussianModel, read_back: GaussianModel, fmt: str) -> dict:
    """Largest and RMS error per attribute after a round trip through `fmt`. Positions are
    in model units and relative to the bounding-box diagonal; rotations in degrees;
    scales as |Δ log scale| (relative size); opacity and colours on [0, 1]; SH as
    coefficients (bands the format does not store are not counted)."""
    o = matched(original, read_back, fmt)
    diag = float(np.linalg.norm(np.ptp(o.means, axis=0)))
    pos = np.linalg.norm(o.means.astype(np.float64) - read_back.means, axis=1)
    q1, q2 = o.quats.astype(np.float64), read_back.quats.astype(np.float64)
    dq = np.minimum(np.linalg.norm(q1 - q2, axis=1), np.linalg.norm(q1 + q2, axis=1))
    rot = np.degrees(4 * np.arcsin(np.clip(dq / 2, 0, 1)))
    errors = {
        "position": pos,
        "position_rel": pos / diag,
        "rotation_deg": rot,
        "log_scale": np.abs(o.log_scales.astype(np.float64) - read_back.log_scales).ravel(),
        "opacity": np.abs(o.opacities - read_back.opacities),
        "colour": np.abs(SH_C0 * (o.sh[:, 0].astype(np.float64) - read_back.sh[:, 0])).ravel(),
    }
    k = min(o.sh.shape[1], read_back.sh.shape[1])
    if k > 1:
        errors["sh_rest"] = np.abs(o.sh[:, 1:k].astype(np.float64) - read_back.sh[:, 1:k]).ravel()
    return {name: {"max": float(v.max()), "rms": float(np.sqrt(np.mean(v**2)))} for name, v in errors.items() if v.size}


def rss_now_mb() -> float:
    """Resident memory now (benchmarks.speed has the same; speed imports this module)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return 0.0


class PeakRss:
    """Peak resident memory above the level at entry, sampled every 2 ms by a thread (the
    process's high-water mark would hide an operation behind the model's generation; C++
    allocations are invisible to tracemalloc)."""

    def __enter__(self) -> PeakRss:
        self.base = self.peak = rss_now_mb()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, rss_now_mb())

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_now_mb())

    @property
    def growth_mb(self) -> float:
        return self.peak - self.base


def roundtrip_child(fmt: str, n: int) -> dict:
    """Write and read back a generated n-Gaussian SH-3 model as `fmt` (one child process)."""
    from gsa.io.formats import EXTENSIONS, read_model, write_model
    from gsa.synth import make_object

    model = make_object("bus", seed=1, n_gaussians=n, sh_degree=3)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"big{EXTENSIONS[fmt]}"
        with PeakRss() as write_mem:
            t0 = time.perf_counter()
            write_model(model, path, fmt)
            write_s = time.perf_counter() - t0
        with PeakRss() as read_mem:
            t0 = time.perf_counter()
            loaded = read_model(path)
            read_s = time.perf_counter() - t0
        return {
            "format": fmt,
            "gaussians": len(loaded),
            "sh_degree_kept": loaded.sh_degree,
            "file_mb": path.stat().st_size / 2**20,
            "write_seconds": write_s,
            "read_seconds": read_s,
            "write_peak_growth_mb": write_mem.growth_mb,
            "read_peak_growth_mb": read_mem.growth_mb,
            "errors": attribute_errors(model, loaded, fmt),
        }


def align_pair(source_format: str, target_format: str, n: int, seed: int, work: Path) -> dict:
    """A generated pair stored as the two formats with a random Sim(3), aligned from the files;
    the error against the truth in the internal frame (gsa.io.frames)."""
    from gsa.align.pipeline import AlignOptions, align
    from gsa.io.formats import EXTENSIONS, read_model, write_model
    from gsa.metrics import accuracy
    from gsa.synth import make_object, random_sim3

    truth = random_sim3(np.random.default_rng(seed))
    src = make_object("car", seed=seed, n_gaussians=n, sample_seed=seed + 1000, sh_degree=3)
    tgt = make_object("car", seed=seed, n_gaussians=n, sample_seed=seed, sh_degree=3).transformed(truth)
    sp = write_model(src, work / f"s{seed}{EXTENSIONS[source_format]}", source_format)
    tp = write_model(tgt, work / f"t{seed}{EXTENSIONS[target_format]}", target_format)
    s, t = read_model(sp), read_model(tp)
    result = align(s, t, AlignOptions(seed=seed))
    acc = accuracy(result.transform, truth, s.means, t.means)
    return {"source": source_format, "target": target_format, "seed": seed, **acc}


def pair_rows(quick: bool, seeds: tuple[int, ...] = (0, 1, 2)) -> list[dict]:
    n = 5000 if quick else 20000
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for i, a in enumerate(PAIR_FORMATS):
            for b in PAIR_FORMATS[i:]:
                runs = [align_pair(a, b, n, seed, Path(d)) for seed in seeds]
                rows.append(
                    {
                        "source": a,
                        "target": b,
                        "gaussians": n,
                        "pairs": len(runs),
                        "rre_deg_mean": float(np.mean([r["rre_deg"] for r in runs])),
                        "rre_deg_max": float(np.max([r["rre_deg"] for r in runs])),
                        "scale_error_pct_mean": float(np.mean([r["scale_error_pct"] for r in runs])),
                        "ate_normalized_mean": float(np.mean([r["ate_normalized"] for r in runs])),
                    }
                )
                print(f"  {a} -> {b}: RRE {rows[-1]['rre_deg_mean']:.4f}°", file=sys.stderr, flush=True)
    return rows


def protocol_formats(quick: bool) -> tuple[list[dict], list[dict]]:
    from gsa.io.formats import FORMATS

    n = 200_000 if quick else 1_000_000
    roundtrips = []
    for fmt in FORMATS:
        proc = subprocess.run(
            [sys.executable, "-m", "benchmarks.formats_io", fmt, str(n)],
            capture_output=True,
            text=True,
            check=True,
            env=MEASURED_ENV,
        )
        roundtrips.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = roundtrips[-1]
        print(
            f"  {fmt}: write {r['write_seconds']:.2f} s, read {r['read_seconds']:.2f} s, {r['file_mb']:.0f} MB",
            file=sys.stderr,
            flush=True,
        )
    return roundtrips, pair_rows(quick)


def format_tables(roundtrips: list[dict], pairs: list[dict]) -> str:
    lines = [
        "| format | Gaussians | SH kept | file (MB) | write (s) | read (s) | write peak RSS growth (MB) | read peak RSS growth (MB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in roundtrips:
        lines.append(
            f"| {r['format']} | {r['gaussians']:,} | {r['sh_degree_kept']} | {r['file_mb']:.0f} | "
            f"{r['write_seconds']:.2f} | {r['read_seconds']:.2f} | {r['write_peak_growth_mb']:.0f} | "
            f"{r['read_peak_growth_mb']:.0f} |"
        )
    lines += [
        "",
        "| format | position max (rel. to diagonal) | rotation max (°) | log-scale max | opacity max | colour max | SH max |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in roundtrips:
        e = r["errors"]
        sh = f"{e['sh_rest']['max']:.3g}" if "sh_rest" in e else "not stored"
        lines.append(
            f"| {r['format']} | {e['position_rel']['max']:.2e} | {e['rotation_deg']['max']:.3g} | "
            f"{e['log_scale']['max']:.3g} | {e['opacity']['max']:.3g} | {e['colour']['max']:.3g} | {sh} |"
        )
    lines += [
        "",
        "| source | target | pairs | RRE mean (°) | RRE max (°) | scale error mean (%) | ATE / diagonal |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in pairs:
        lines.append(
            f"| {r['source']} | {r['target']} | {r['pairs']} | {r['rre_deg_mean']:.4f} | {r['rre_deg_max']:.4f} | "
            f"{r['scale_error_pct_mean']:.4f} | {r['ate_normalized_mean']:.2e} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """One format's round trip: one JSON row on stdout."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.formats_io", description=main.__doc__)
    parser.add_argument("format")
    parser.add_argument("n", type=int)
    args = parser.parse_args(argv)
    print(json.dumps(roundtrip_child(args.format, args.n)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
