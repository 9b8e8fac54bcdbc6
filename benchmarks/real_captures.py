"""`gsa bench real --data DIR`: split pairs from a folder of REAL 3DGS captures.

Every capture the folder holds (any format gsa.io reads, sniffed from the bytes) gives
PAIRS_PER_CAPTURE pairs. For each pair its Gaussians are dealt at random into two disjoint
halves (no Gaussian in both), each half is cut by its own random plane (60–90 % kept), and the
target half is moved by a random Sim(3) (≤ 180° per axis, 0.1–10× scale). What a real capture
brings is kept as exported: SH degree, floaters, ground, quantised positions, alpha = 1.

Two variants, one table each: as captured, and with the source under another exposure and
white balance (±1 stop, gsa.synth.shift_exposure), as a second capture on another day would
record it. Success: RRE < 5° (strict: a real capture has no known symmetry).

GSA_REAL_PAIRS=N sets the pairs per capture (default PAIRS_PER_CAPTURE, full or --quick; FIRST:END
deals pairs FIRST..END-1 only, to continue a run), GSA_REAL_CAPTURES=GLOB[,GLOB] runs the captures
whose file names match (their pairs unchanged), and
GSA_REAL_GAUSSIANS=N draws each capture down to N Gaussians before the split, full or --quick
(--quick alone: QUICK_GAUSSIANS), as small as the captures whose pairs missed (4.6k-45k
Gaussians a half);
GSA_REAL_VARIANTS=as-captured or exposure runs one variant only (default both), for a long run
over many captures (benchmarks.fetch_captures). The report gives a table per capture
(per_capture_table): success, the misses with their RRE and whether align() flagged them
doubtful, median time, and the Gaussians per half.
"""

from __future__ import annotations

import os
from fnmatch import fnmatch
from functools import cache
from pathlib import Path

import numpy as np

from benchmarks.records import SUCCESS_RRE_DEG, Pair
from gsa.io.formats import EXTENSIONS, format_for_path, read_model
from gsa.synth.perturb import random_sim3
from gsa.synth.variants import cut_by_plane, random_exposure, shift_exposure

PAIRS_PER_CAPTURE = (8, 2)  # full, --quick
KEEP = (0.6, 0.9)
# --quick draws each half from at most this many Gaussians of the capture.
QUICK_GAUSSIANS = 40_000
VARIANTS = ("as-captured", "exposure")


def pair_range(quick: bool) -> range:
    """The pair indices k dealt per capture: range(PAIRS_PER_CAPTURE) by default; GSA_REAL_PAIRS=N
    for range(N), or FIRST:END for range(FIRST, END) (a long run continued: pair k of a capture is
    the same whatever the range)."""
    value = os.environ.get("GSA_REAL_PAIRS", "").strip()
    if not value:
        return range(PAIRS_PER_CAPTURE[1] if quick else PAIRS_PER_CAPTURE[0])
    first, sep, end = value.rpartition(":") if ":" in value else ("0", "", value)
    if not (first.isdigit() and end.isdigit()) or int(end) <= int(first):
        raise ValueError(f"GSA_REAL_PAIRS={value!r}: give a number of pairs per capture, or FIRST:END (END > FIRST)")
    return range(int(first), int(end))


def gaussian_cap(quick: bool) -> int | None:
    """The Gaussians a capture is drawn down to before it is split: GSA_REAL_GAUSSIANS=N in
    either mode, else QUICK_GAUSSIANS with --quick, else none (the capture as exported)."""
    value = os.environ.get("GSA_REAL_GAUSSIANS", "").strip()
    if not value:
        return QUICK_GAUSSIANS if quick else None
    if not value.isdigit() or int(value) < 100:
        raise ValueError(f"GSA_REAL_GAUSSIANS={value!r}: give the Gaussians per capture, at least 100")
    return int(value)


def chosen(name: str) -> bool:
    """Whether GSA_REAL_CAPTURES (comma-separated file-name globs; default all) picks capture `name`."""
    globs = [g.strip() for g in os.environ.get("GSA_REAL_CAPTURES", "").split(",") if g.strip()]
    return not globs or any(fnmatch(name, g) for g in globs)


def variants() -> list[bool]:
    """The exposure flags to run: GSA_REAL_VARIANTS (comma-separated names of VARIANTS), else both."""
    value = os.environ.get("GSA_REAL_VARIANTS", "").strip()
    names = [v.strip() for v in value.split(",") if v.strip()] if value else list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise ValueError(f"GSA_REAL_VARIANTS: unknown {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
    return [name == "exposure" for name in VARIANTS if name in names]


def find_captures(folder: str | Path) -> list[Path]:
    """The 3DGS files of a folder (by extension; the reader sniffs the bytes), sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    return sorted(p for p in folder.iterdir() if p.is_file() and format_for_path(p) in EXTENSIONS)


@cache
def _load(path: Path):
    return read_model(path)


def split_pair(model, rng: np.random.Generator, keep: tuple[float, float] = KEEP):
    """Two disjoint halves of `model` (each Gaussian dealt to one at random), each cut by
    its own random plane keeping a share in `keep`."""
    to_source = rng.random(len(model)) < 0.5
    source = cut_by_plane(model.subset(to_source), rng, keep)
    target = cut_by_plane(model.subset(~to_source), rng, keep)
    return source, target


def real_split_pairs(
    data: str | Path, quick: bool, seed: int, exposure: bool = False, sizes: dict | None = None
) -> list[Pair]:
    """pair_range() split pairs per capture of `data`; labels '<file name>-<k>'. With
    `sizes`, each pair made records its halves' Gaussian counts there under its label."""
    captures = find_captures(data)
    if not captures:
        raise ValueError(f"{data}: no 3DGS files found ({', '.join(sorted(set(EXTENSIONS.values())))})")
    ks = pair_range(quick)
    cap = gaussian_cap(quick)
    pairs: list[Pair] = []
    # c counts every capture of the folder, so a capture's pairs stay the same when others are left out
    for c, path in enumerate(captures):
        if not chosen(path.name):
            continue
        for k in ks:

            def make(c=c, k=k, path=path, label=f"{path.name}-{k}"):
                rng = np.random.default_rng([seed, 26, c, k])
                model = _load(path)
                if cap is not None and len(model) > cap:
                    model = model.subset(np.sort(rng.choice(len(model), cap, replace=False)))
                source, target = split_pair(model, rng)
                truth = random_sim3(rng)
                if exposure:
                    source = shift_exposure(source, random_exposure(rng))
                if sizes is not None:
                    sizes[label] = {"source_gaussians": len(source), "target_gaussians": len(target)}
                return source, target.transformed(truth), truth

            pairs.append((f"{path.name}-{k}", make))
    return pairs


def capture_of(label: str) -> dict:
    return {"category": label.rsplit("-", 1)[0]}


def per_capture(records: list[dict]) -> dict[str, dict]:
    """Per capture, in order of appearance: pairs, success (RRE < 5°), the misses (pair, RRE,
    flagged doubtful), median seconds and median Gaussians per half."""
    out: dict[str, dict] = {}
    for cap in dict.fromkeys(r["category"] for r in records):
        recs = [r for r in records if r["category"] == cap]
        ok = [r for r in recs if _success(r)]
        halves = [r[k] for r in recs for k in ("source_gaussians", "target_gaussians") if k in r]
        out[cap] = {
            "pairs": len(recs),
            "successes": len(ok),
            "success_rate": len(ok) / len(recs),
            "misses": [
                {"pair": r["pair"], "rre_deg": float(r.get("rre_deg", np.nan)), "doubtful": bool(r.get("doubtful"))}
                | ({"error": r["error"]} if "error" in r else {})
                for r in recs
                if not _success(r)
            ],
            "median_seconds": float(np.median([r["seconds"] for r in recs])),
            "median_gaussians_per_half": int(np.median(halves)) if halves else None,
        }
    return out


def _success(rec: dict) -> bool:
    return "error" not in rec and bool(rec.get("rre_deg", np.nan) < SUCCESS_RRE_DEG)


def per_capture_table(rows: list[dict]) -> str:
    """One markdown table per row (method · variant) of its per_capture breakdown."""
    blocks = []
    for row in rows:
        caps = row.get("per_capture") or {}
        if not caps:
            continue
        lines = [
            f"{row['method']}, per capture:",
            "",
            "| capture | Gaussians / half (median) | pairs | success (RRE<5°) | misses: RRE ° (D = flagged doubtful) "
            "| median s / pair |",
            "|---|---:|---:|---:|---|---:|",
        ]
        for cap, c in caps.items():
            misses = ", ".join(
                ("failed" if "error" in m else f"{m['rre_deg']:.1f}") + (" D" if m["doubtful"] else "")
                for m in c["misses"]
            )
            half = "—" if c["median_gaussians_per_half"] is None else f"{c['median_gaussians_per_half']:,}"
            lines.append(
                f"| {cap} | {half} | {c['pairs']} | {c['successes']}/{c['pairs']} ({100 * c['success_rate']:.0f} %) "
                f"| {misses or '—'} | {c['median_seconds']:.1f} |"
            )
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)
