"""Benchmark protocols on generated data: each deterministic by seed, each
printing a markdown table and writing JSON. Peers (benchmarks.peers) run in the
same loop as GSA on the very same pairs.

dup       paper App. C: 30 models (5 per category), each duplicated under a random
          Sim(3) (≤180° per axis, ≤10× scale); GSA coarse, coarse+fine and peers
same      paper Table 1 analogue: 15 objects, two independent samplings each,
          the authors' perturbation; RRE, ATE, scale error
category  paper Table 2 analogue: 6 categories × 5 instances, all 10 pairs per
          category (60 pairs), random Sim(3); RRE per category
ablation  paper Table 4 / Sec. 4.5: coarse iterations (1, 3, until convergence),
          fine views (3 similar, 3 diverse, 30), fine on colours, features off
speed     coarse, fine, lifting and rendering time and peak memory vs Gaussian count
io        PLY write/read time and memory for a 1M-Gaussian file

Robustness (real captures; gsa.synth.variants). Each: 30 pairs, 20k/30k Gaussians
(--quick: 6 pairs, 3k); source and target are two independent samplings, the
target moved by a random Sim(3) (≤180° per axis, 0.1–10× scale):
partial   each model cut by its own random plane, 60–80 % of it kept
noisy     each model with 20 % bright, faint floaters around it
opaque    each model with 10 % floaters as opaque as its surface (no opacity cut removes them)
symmetric 4- to 8-fold symmetric objects (prism, wheel, bottle) whose colour
          marks one sector; strict success against the true pose, plus
          `rre_any_symmetric_deg` (the best of the k symmetric poses)
deform    target = a stretched, tapered and bent copy of the instance
deform-symmetric  the symmetric pairs with the target bent (deform): two captures of one
          object whose frames move with the bend and whose k poses only the colour tells apart
exposure  the symmetric pairs, each capture under its own exposure (±1 stop) and
          white balance (gsa.synth.shift_exposure): colour must be compared through
          the gains between the captures (strict success, as symmetric)

scene     scene-scale: two partial captures of a generated furnished room (gsa.synth.scenes;
          50–80 % overlap, floaters, each capture under its own Sim(3), scale 0.2–5).
          Full: 20 pairs of 1–2M Gaussians per capture; --quick: 3 pairs of ~100k.
          Success: RRE < 2° and translation error < 2 % of the room's extent; peak
          memory per method (benchmarks.scene). GSA rows are align()'s coarse stage.
guided    each hint of the guided path (a start 20° off, 3 picked pairs, the up
          axes, a wrong up axis) on partial, deform and category pairs, and with --data on
          category-real's (benchmarks.guided)
site      the same on outdoor sites without walls (benchmarks.site): generated
          terrain with things on it, and SfM point files (--data, default
          ../shared/data/real-dev) made into Gaussians. Full: 12 + 4 per file pairs of
          1–2M Gaussians per capture; --quick: 3 pairs of ~100k. Judged as scene.

GSA rows carry align()'s `confidence` and `doubtful` (metrics) per pair; tables
then add how well the flag tracks failure (flagged rate, success among the
unflagged, share of failures flagged), and `run_protocols` ends with that
calibration over all protocols run, for the GSA coarse row.

Modules: benchmarks.records (evaluation loop, summary rows, JSON), benchmarks.pairs,
benchmarks.ablation, benchmarks.speed (speed and io, measured in child processes) and
benchmarks.tables (markdown); this one holds the GSA and peer runners, the protocol
registry and run_protocols, and re-exports the names of those modules.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from datetime import date
from pathlib import Path

from benchmarks import speed as _speed
from benchmarks.ablation import ABLATION_COARSE, ABLATION_REFERENCE, FINE_BASE, ablation_runner, similar_cameras
from benchmarks.category_real import category_of as real_category_of
from benchmarks.category_real import category_real_judge, category_real_pairs, default_align_runner, per_class
from benchmarks.guided import protocol_guided
from benchmarks.nway import protocol_nway
from benchmarks.pairs import (
    ROBUST_COUNT,
    ROBUST_SIZES,
    category_of,
    category_pairs,
    deform_pairs,
    deform_symmetric_pairs,
    dup_pairs,
    exposure_pairs,
    noisy_pairs,
    opaque_pairs,
    partial_pairs,
    same_pairs,
    scene_pairs,
    symmetric_fields,
    symmetric_judge,
    symmetric_pairs,
)
from benchmarks.peers import Peer, available_peers
from benchmarks.real_captures import capture_of, per_capture, real_split_pairs, variants
from benchmarks.records import (
    GSA_COARSE,
    GSA_FINE,
    GSA_PAPER_COARSE,
    GSA_PAPER_FINE,
    NOISE_NOTE,
    QUICK_FINE,
    SUCCESS_RRE_DEG,
    Pair,
    Runner,
    add_time_ratio,
    calibration,
    evaluate,
    per_category,
    save_rows,
    summarise,
)
from benchmarks.scene import add_scene_summary, scene_judge, with_peak_memory
from benchmarks.speed import io_child, protocol_io, rss_now_mb, speed_child, speed_stages
from benchmarks.tables import calibration_summary, format_table
from gsa.align.pipeline import AlignOptions, align
from gsa.synth import random_sim3

__all__ = [
    "ABLATION_COARSE",
    "ABLATION_REFERENCE",
    "FINE_BASE",
    "FINE_ROWS",
    "GSA_COARSE",
    "GSA_FINE",
    "GSA_PAPER_COARSE",
    "GSA_PAPER_FINE",
    "NOISE_NOTE",
    "PROTOCOLS",
    "QUICK_FINE",
    "ROBUST_COUNT",
    "ROBUST_SIZES",
    "SUCCESS_RRE_DEG",
    "Pair",
    "Runner",
    "ablation_runner",
    "add_time_ratio",
    "align",
    "calibration",
    "calibration_summary",
    "category_of",
    "category_pairs",
    "default_runners",
    "deform_pairs",
    "deform_symmetric_pairs",
    "dup_pairs",
    "evaluate",
    "exposure_pairs",
    "format_table",
    "gsa_runner",
    "io_child",
    "noisy_pairs",
    "opaque_pairs",
    "partial_pairs",
    "peer_runner",
    "per_category",
    "protocol_ablation",
    "protocol_category",
    "protocol_deform",
    "protocol_dup",
    "protocol_exposure",
    "protocol_io",
    "protocol_noisy",
    "protocol_opaque",
    "protocol_partial",
    "protocol_same",
    "protocol_scene",
    "protocol_site",
    "protocol_speed",
    "protocol_symmetric",
    "random_sim3",
    "rss_now_mb",
    "run_protocols",
    "same_pairs",
    "save_rows",
    "scene_pairs",
    "similar_cameras",
    "speed_child",
    "speed_stages",
    "summarise",
    "symmetric_fields",
    "symmetric_judge",
    "symmetric_pairs",
]


# The protocols below look up the pair generators, default_runners, align and FINE_ROWS in
# this module when they run, so a test can replace them here (monkeypatch.setattr(P, ...)).

# Rows that run the fine stage (it renders, so they dominate a protocol's time). Always on in
# a real run; unit tests of the protocol tables switch it off.
FINE_ROWS = True


# ---------------------------------------------------------------- runners


def gsa_runner(fine: bool, labels: tuple[str, str] = (GSA_COARSE, GSA_FINE), **options) -> Runner:
    """One align() call gives both rows: the coarse transform is kept on the
    result, and its time is the total less the fine stage."""
    coarse_label, fine_label = labels

    def run(source, target):
        stages = ("coarse", "fine") if fine else ("coarse",)
        t0 = time.perf_counter()
        result = align(source, target, AlignOptions(stages=stages, **options))
        total = time.perf_counter() - t0
        # The confidence of the whole result (both rows: one align() call); None/False
        # when align() does not report one.
        flags = {
            "confidence": _float_or_none(result.metrics.get("confidence")),
            "ambiguous": result.verdict.ambiguous,
            "doubtful": result.verdict.doubtful,
            # whether align() took the scene path (gsa.align.scene)
            "scene_path": bool((result.diagnostics.get("scene") or {}).get("ran", False)),
            # what the confidence is made of, kept for calibration
            **{
                k: _float_or_none(result.metrics.get(k))
                for k in (
                    "margin",
                    "overlap_score",
                    "score",
                    "colour_weight",
                    "colour_mismatch",
                    "overlap_estimate",
                    "coincident_share",
                )
            },
        }
        # The coarse row is judged at the coarse pose (align() reports that verdict beside the final one).
        coarse_flags = dict(flags)
        if verdict := result.diagnostics.get("coarse_verdict"):
            coarse_flags.update(
                confidence=_float_or_none(verdict["confidence"]),
                ambiguous=bool(verdict["ambiguous"]),
                doubtful=bool(verdict["doubtful"]),
            )
        out = {coarse_label: (result.coarse.transform, total - result.timings.get("fine", 0.0), coarse_flags)}
        if fine:
            out[fine_label] = (result.transform, total, dict(flags))
        return out

    return run


def _float_or_none(x) -> float | None:
    return None if x is None else float(x)


def peer_runner(peer: Peer, seed: int) -> Runner:
    def run(source, target):
        t0 = time.perf_counter()
        try:
            est = peer.register(source, target, seed=seed)
        except Exception as exc:  # noqa: BLE001 -- a peer failing on a pair is a result, not a crash
            est = exc
        return {peer.label: (est, time.perf_counter() - t0)}

    return run


def default_runners(seed: int, peers: list[str] | None, quick: bool) -> list[Runner]:
    runners = [gsa_runner(FINE_ROWS, **(QUICK_FINE if quick else {}))]
    if not FINE_ROWS:
        print("note: fine-stage rows off; GSA rows are coarse only")
    runners += [peer_runner(p, seed) for p in available_peers(peers)]
    return runners


# ---------------------------------------------------------------- protocols


def protocol_dup(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    rows = evaluate("dup", dup_pairs(quick, seed), default_runners(seed, peers, quick), out=out)
    save_rows(out, "dup", rows)
    return rows


def protocol_same(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    runners = default_runners(seed, peers, quick)
    if FINE_ROWS:
        # What the fine stage adds to the paper's coarse stage (the default pipeline's NN
        # refinement already ends below the fine loss's floor on this protocol).
        runners.insert(
            1, gsa_runner(True, (GSA_PAPER_COARSE, GSA_PAPER_FINE), refine="off", **(QUICK_FINE if quick else {}))
        )
    rows = evaluate("same", same_pairs(quick, seed), runners, out=out)
    save_rows(out, "same", rows)
    return rows


def protocol_category(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    rows = evaluate("category", category_pairs(quick, seed), default_runners(seed, peers, quick), category_of, out=out)
    for row in rows:
        row["per_category_mean_rre_deg"] = per_category(row["records"])
    save_rows(out, "category", rows)
    return rows


def _pair_protocol(name: str, fields=category_of, judge=None):
    """A protocol over NAME_pairs (looked up when run) with the default runners: partial,
    noisy, opaque and deform (categories cycled); symmetric and exposure (strict success,
    plus the best of the k symmetric poses)."""

    def protocol(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
        pairs = globals()[f"{name}_pairs"](quick, seed)
        rows = evaluate(name, pairs, default_runners(seed, peers, quick), fields, out=out, judge=judge)
        save_rows(out, name, rows)
        return rows

    protocol.__name__ = f"protocol_{name}"
    return protocol


protocol_partial = _pair_protocol("partial")
protocol_noisy = _pair_protocol("noisy")
protocol_opaque = _pair_protocol("opaque")
protocol_deform = _pair_protocol("deform")
protocol_symmetric = _pair_protocol("symmetric", symmetric_fields, symmetric_judge)
protocol_exposure = _pair_protocol("exposure", symmetric_fields, symmetric_judge)
protocol_deform_symmetric = _pair_protocol("deform_symmetric", symmetric_fields, symmetric_judge)


def protocol_ablation(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    # Cross-instance pairs like Table 4. Full: 3 instances per category (18 pairs)
    # rather than 5 (60): 9 configurations per pair, 4 of them rendering.
    pairs = category_pairs(quick, seed, instances=2 if quick else 3)
    if not FINE_ROWS:
        print("note: fine-stage rows off; fine-stage ablation rows skipped")
    rows = evaluate("ablation", pairs, [ablation_runner(seed, quick, FINE_ROWS)], category_of, out=out)
    add_time_ratio(rows, ABLATION_REFERENCE)  # no "GSA coarse" row here: ratio vs the default pipeline
    for row in rows:
        row["per_category_mean_rre_deg"] = per_category(row["records"])
    save_rows(out, "ablation", rows)
    return rows


def protocol_scene(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    # Coarse only (align()'s default stages here): the fine stage renders every Gaussian of
    # both models per view; what the scene path refines on is for it to decide.
    runners = [
        with_peak_memory(r) for r in [gsa_runner(False)] + [peer_runner(p, seed) for p in available_peers(peers)]
    ]
    rows = evaluate("scene", scene_pairs(quick, seed), runners, out=out, judge=scene_judge)
    add_scene_summary(rows)
    save_rows(out, "scene", rows)
    return rows


def protocol_site(
    quick: bool, seed: int, out: Path, peers: list[str] | None = None, data: str | Path | None = None
) -> list[dict]:
    # As protocol_scene: coarse only, peak memory per method.
    from benchmarks.site import site_of, site_pairs

    runners = [
        with_peak_memory(r) for r in [gsa_runner(False)] + [peer_runner(p, seed) for p in available_peers(peers)]
    ]
    rows = evaluate("site", site_pairs(quick, seed, data), runners, site_of, out=out, judge=scene_judge)
    add_scene_summary(rows)
    save_rows(out, "site", rows)
    return rows


def protocol_category_real(
    quick: bool, seed: int, out: Path, peers: list[str] | None = None, data: str | Path | None = None
) -> list[dict]:
    """Cross-instance pairs of real category meshes from `data` (benchmarks.category_real)."""
    if data is None:
        raise ValueError("category-real needs --data DIR (a folder of <category>_<i>.npz meshes)")
    runners = [default_align_runner(hint) for hint in (None, "up_axes", "point_pairs")]
    runners += [peer_runner(p, seed) for p in available_peers(peers)]
    pairs = category_real_pairs(data, quick, seed)
    rows = evaluate("category-real", pairs, runners, real_category_of, out=out, judge=category_real_judge)
    for row in rows:
        row["per_class"] = per_class(row["records"])
    save_rows(out, "category-real", rows)
    return rows


def protocol_real(
    quick: bool, seed: int, out: Path, peers: list[str] | None = None, data: str | Path | None = None
) -> list[dict]:
    """Split pairs of real captures from `data` (benchmarks.real_captures), as captured and with
    the source's exposure shifted; one row per method and variant."""
    if data is None:
        raise ValueError("real needs --data DIR (a folder of 3DGS captures)")
    runners = [default_align_runner()] + [peer_runner(p, seed) for p in available_peers(peers)]
    rows = []
    for exposure in variants():
        name = "real-exposure" if exposure else "real"
        sizes: dict[str, dict] = {}
        pairs = real_split_pairs(data, quick, seed, exposure=exposure, sizes=sizes)
        variant = evaluate(
            name, pairs, runners, lambda label, sizes=sizes: {**capture_of(label), **sizes.get(label, {})}, out=out
        )
        for row in variant:
            row["variant"] = "exposure shifted" if exposure else "as captured"
            row["method"] += f" · {row['variant']}"
            row["per_capture_mean_rre_deg"] = row.pop("per_category_mean_rre_deg", {})
            row["per_capture"] = per_capture(row["records"])
        rows += variant
    save_rows(out, "real", rows)
    return rows


def protocol_speed(quick: bool, seed: int, out: Path, peers: list[str] | None = None) -> list[dict]:
    return _speed.protocol_speed(quick, seed, out, peers, fine=FINE_ROWS)


PROTOCOLS = {
    "dup": protocol_dup,
    "same": protocol_same,
    "category": protocol_category,
    "ablation": protocol_ablation,
    "speed": protocol_speed,
    "io": protocol_io,
    "partial": protocol_partial,
    "noisy": protocol_noisy,
    "opaque": protocol_opaque,
    "symmetric": protocol_symmetric,
    "deform": protocol_deform,
    "exposure": protocol_exposure,
    "deform-symmetric": protocol_deform_symmetric,
    "scene": protocol_scene,
    "site": protocol_site,
    "category-real": protocol_category_real,
    "real": protocol_real,
    "n-way": protocol_nway,
    "guided": protocol_guided,
}
# Protocols over the user's own data (--data DIR).
DATA_PROTOCOLS = {"category-real", "real", "site", "guided"}


def run_protocols(
    names: list[str],
    quick: bool = False,
    out: str = "out/bench",
    seed: int = 0,
    peers: list[str] | None = None,
    data: str | None = None,
) -> int:
    unknown = [n for n in names if n not in PROTOCOLS]
    if unknown:
        raise ValueError(f"unknown protocol(s) {', '.join(unknown)}; choose from {', '.join(PROTOCOLS)}")
    out_dir = Path(out)
    print(
        f"GSA benchmarks — {date.today().isoformat()}, {platform.machine()}, {os.cpu_count()} CPU cores"
        f"{' (quick)' if quick else ''}\n{NOISE_NOTE}"
    )
    start = time.perf_counter()
    results = {}
    for name in names:
        t0 = time.perf_counter()
        extra = {"data": data} if name in DATA_PROTOCOLS else {}
        rows = results[name] = PROTOCOLS[name](quick, seed, out_dir, peers, **extra)
        print(f"\n### {name} ({time.perf_counter() - t0:.0f} s wall)\n")
        print(format_table(name, rows))
        sys.stdout.flush()
    summary = calibration_summary(results)
    if summary:
        print(f"\n{summary}")
    print(f"\nTotal wall time {time.perf_counter() - start:.0f} s. JSON: {out_dir}/")
    return 0
