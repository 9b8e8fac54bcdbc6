"""`gsa bench n-way` (N-way registration): N partial captures of one generated object (random plane cuts,
floaters, exposure shifts), each in its own random Sim(3); every pair aligned (coarse), then
the global step (gsa.align.many). Measured per model against the truth in the reference
frame (model 0): RRE, scale error, translation error (centroid displacement over the
reference's RMS radius), pairwise-to-reference against after the global step; cycle
residuals; time per edge and total. Run twice on the same edges: as measured, and with the
edge 0 -> N-1 replaced by a 90° turned one, which must be named (pruned or corrected) while
every model stays right.

Full: N = 6, 5k Gaussians; --quick: N = 4, 3k. The rows print in the generic pair table
(one "pair" per non-reference model); the per-model table, the cycles and the named edge
print above it.

Then cross-instance sets ("N = 5 cross-instance members of one category"): per
category of the real meshes in DEFAULT_DATA (../shared/data/category-dev; skipped, and said
so, when missing), its first MEMBERS instances sampled as 3DGS models as benchmarks.category_real
does, each in its own random Sim(3) (≤ 180° per axis, scale 0.2–5); every pair aligned with
align()'s defaults, then the global step. Per member against the truth in member 0's frame
(RRE up to either member's own symmetries, scale error): every pair, pairwise to the
reference, after the global step; per category, and how many wrong edges hold the truth
among their alternatives. Full: every category, 5k Gaussians; --quick: every second, 3k.

write_captures writes N such captures of any size as PLY files: the `gsa align-many` timing
runs' input.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np

from benchmarks.category_real import FLOATERS, _symmetries
from benchmarks.records import SUCCESS_RRE_DEG, save_rows
from gsa.align.many import Edge, model_frame, pairwise_edges, select_edges, solve_graph
from gsa.align.many_frames import frame_evidence
from gsa.align.pipeline import AlignOptions
from gsa.geometry import euler_xyz
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3
from gsa.synth.meshes import find_meshes, load_mesh, mesh_to_gaussians
from gsa.synth.variants import add_floaters, cut_by_plane, random_exposure, shift_exposure

CATEGORY = "car"
# Cross-instance sets: MEMBERS instances of each category of the real meshes (DEFAULT_DATA,
# the project's development meshes beside the checkout), Gaussians per member (full, quick);
# --quick takes every second category.
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "category-dev"
MEMBERS = 5
MEMBER_SIZES = (5000, 3000)


def captures(quick: bool, seed: int, n: int | None = None, size: int | None = None):
    """(models, truth): truth[k] maps the object's own frame into capture k's. n and size
    (Gaussians before the cut) override the run's defaults (the timing runs: N = 50, 100k)."""
    n_default, size_default = (4, 3000) if quick else (6, 5000)
    n, size = n or n_default, size or size_default
    rng = np.random.default_rng([seed, 30])
    models, truth = [], []
    for k in range(n):
        m = make_object(CATEGORY, seed=seed, n_gaussians=size, sample_seed=1000 * seed + k)
        # Most of the object in each capture: every pair must overlap for its edge to be right.
        m = cut_by_plane(m, rng, keep=(0.7, 0.9))
        m = add_floaters(m, rng, fraction=0.05)
        m = shift_exposure(m, random_exposure(rng, stops=0.5))
        t = random_sim3(rng, scale_range=(0.2, 5.0))
        models.append(m.transformed(t))
        truth.append(t)
    return models, truth


def write_captures(folder: str | Path, n: int, gaussians: int, seed: int = 0) -> list[Path]:
    """N captures as `captures` makes them, each drawn large enough and then subsampled to
    exactly `gaussians` (a random subset), written as capture_<k>.ply into folder: the input
    of the `gsa align-many` timing runs (docs/benchmarks.md, n-way)."""
    from gsa.io.formats import write_model

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    # The cut keeps at least 70 %; floaters add 5 %: drawing gaussians / 0.7 leaves enough.
    models, _ = captures(False, seed, n=n, size=int(np.ceil(gaussians / 0.7)) + 1)
    rng = np.random.default_rng([seed, 30, 1])
    paths = []
    for k, m in enumerate(models):
        m = m.subset(np.sort(rng.choice(len(m), gaussians, replace=False)))
        path = folder / f"capture_{k:0{len(str(n - 1))}d}.ply"
        write_model(m, path, "ply")
        paths.append(path)
    return paths


def turned(edge: Edge, centre: np.ndarray, degrees: float = 90.0) -> Sim3:
    """The edge's transform after turning the source about its centroid (a wrong edge that
    still overlaps the models as well as a right one of a symmetric object would)."""
    turn = Sim3(1.0, euler_xyz(np.radians([degrees, 0.0, 0.0])), np.zeros(3))
    about = Sim3(1.0, np.eye(3), centre) @ turn @ Sim3(1.0, np.eye(3), -centre)
    return edge.transform @ about


def _errors(estimates: list[Sim3], truth: list[Sim3], frames) -> list[dict]:
    ref_size = frames[0][1]
    out = []
    for k, est in enumerate(estimates):
        want = truth[0] @ truth[k].inverse()
        centre = frames[k][0]
        out.append(
            {
                "model": k,
                "rre_deg": rre_deg(est.rotation, want.rotation),
                "scale_error_pct": abs(est.scale / want.scale - 1.0) * 100.0,
                "translation_error": float(np.linalg.norm(est.apply(centre) - want.apply(centre)) / ref_size),
            }
        )
    return out


def _pairwise_to_reference(edges: list[Edge], n: int) -> list[Sim3]:
    """Each model's transform from its own edge with the reference alone (no graph)."""
    out = [Sim3.identity()] * n
    for e in edges:
        if e.source == 0:
            out[e.target] = e.transform.inverse()
        elif e.target == 0:
            out[e.source] = e.transform
    return out


def _row(method: str, errors: list[dict], seconds_per_model: float, extra: dict) -> dict:
    judged = [e for e in errors if e["model"] != 0]
    rre = np.array([e["rre_deg"] for e in judged])
    return {
        "method": method,
        "pairs": len(judged),
        "mean_rre_deg": float(rre.mean()),
        "median_rre_deg": float(np.median(rre)),
        "mean_scale_error_pct": float(np.mean([e["scale_error_pct"] for e in judged])),
        "mean_ate_normalized": float(np.mean([e["translation_error"] for e in judged])),
        "success_rate": float(np.mean(rre < SUCCESS_RRE_DEG)),
        "seconds_per_pair": seconds_per_model,
        "time_ratio_vs_gsa_coarse": None,
        "records": judged,
        **extra,
    }


def cross_instance_sets(data: str | Path, quick: bool, seed: int) -> list[tuple[str, list, list[Sim3], list]]:
    """Per category of `data` with at least MEMBERS instances (quick: every second one): its
    first MEMBERS instances, each sampled as a 3DGS model (benchmarks.category_real's way:
    surface Gaussians, FLOATERS faint floaters) and moved by its own random Sim(3) (≤ 180° per
    axis, scale 0.2–5). Returns (category, models, truth, symmetries): truth[k] maps the shared
    canonical frame into member k's; symmetries[k] the member's own turns (category_real)."""
    groups = {c: paths for c, paths in sorted(find_meshes(data).items()) if len(paths) >= MEMBERS}
    if not groups:
        raise ValueError(f"{data}: no category with {MEMBERS} or more <category>_<i>.npz meshes")
    size = MEMBER_SIZES[1] if quick else MEMBER_SIZES[0]
    out = []
    for c, (category, paths) in enumerate(groups.items()):
        if quick and c % 2:
            continue
        rng = np.random.default_rng([seed, 30, 2, c])
        models, truth, symmetries = [], [], []
        for k, path in enumerate(paths[:MEMBERS]):
            m = mesh_to_gaussians(load_mesh(path), size, np.random.default_rng([seed, 30, 3, c, k]), FLOATERS)
            symmetries.append(_symmetries(m))
            t = random_sim3(rng, scale_range=(0.2, 5.0))
            models.append(m.transformed(t))
            truth.append(t)
        out.append((category, models, truth, symmetries))
    return out


def _judged(est: Sim3, truth: list[Sim3], symmetries: list, i: int, j: int) -> dict:
    """est (member i's frame -> member j's) against the truth, up to either member's symmetries."""
    want = truth[j] @ truth[i].inverse()
    ri, rj = truth[i].rotation, truth[j].rotation
    strict = rre_deg(est.rotation, want.rotation)
    judged = min([strict] + [rre_deg(est.rotation, rj @ g @ ri.T) for g in symmetries[i] + symmetries[j]])
    return {
        "rre_deg": judged,
        "rre_strict_deg": strict,
        "scale_error_pct": abs(est.scale / want.scale - 1.0) * 100.0,
    }


def _cross_rows(quick: bool, seed: int, data: str | Path) -> tuple[list[dict], list[str]]:
    """Every pair of each set aligned (align()'s defaults), then the global step; per member
    against the truth in member 0's frame, pairwise to the reference vs after the global step."""
    sets = cross_instance_sets(data, quick, seed)
    pair_recs, before_recs, after_recs = [], [], []
    lines = [
        "",
        f"Cross-instance sets: {MEMBERS} members of each category ({len(sets)} categories, "
        f"{MEMBER_SIZES[1] if quick else MEMBER_SIZES[0]} Gaussians each, align()'s defaults per edge); "
        "RRE judged up to each member's own symmetries",
        "",
        "| category | pairs: success | to reference: success | global: success | edges pruned / corrected | "
        "wrong edges with the truth among alternatives | s / edge |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    seconds = []
    for category, models, truth, symmetries in sets:
        n = len(models)
        frames = [model_frame(m) for m in models]
        t0 = time.perf_counter()
        edges = pairwise_edges(models, select_edges(models, "all"), AlignOptions(seed=seed))
        seconds.append((time.perf_counter() - t0) / len(edges))
        wrong = fixable = 0
        for e in edges:
            rec = _judged(e.transform, truth, symmetries, e.source, e.target)
            alts = [_judged(a, truth, symmetries, e.source, e.target)["rre_deg"] for a in e.alternatives]
            ok = rec["rre_deg"] < SUCCESS_RRE_DEG
            wrong += not ok
            fixable += (not ok) and any(a < SUCCESS_RRE_DEG for a in alts)
            pair_recs.append({"category": category, "pair": [e.source, e.target], **rec, "confidence": e.confidence})
        evidence = frame_evidence(models, [(e.source, e.target) for e in edges])
        result = solve_graph(n, edges, 0, [c for c, _ in frames], [s for _, s in frames], frames=evidence)
        before = _pairwise_to_reference(edges, n)
        set_before, set_after = [], []
        for k in range(1, n):
            b = {"category": category, "model": k, **_judged(before[k], truth, symmetries, k, 0)}
            a = {"category": category, "model": k, **_judged(result.transforms[k], truth, symmetries, k, 0)}
            a["confidence"] = result.confidences[k]
            set_before.append(b)
            set_after.append(a)
        before_recs += set_before
        after_recs += set_after
        d = result.to_dict()

        def rate(recs):
            return sum(r["rre_deg"] < SUCCESS_RRE_DEG for r in recs) / len(recs)

        lines.append(
            f"| {category} | {rate(pair_recs[-len(edges) :]) * 100:.0f} % | {rate(set_before) * 100:.0f} % | "
            f"{rate(set_after) * 100:.0f} % | {len(d['pruned'])} / {len(d['corrected'])} | {fixable} of {wrong} | "
            f"{seconds[-1]:.1f} |"
        )
    per_edge = float(np.mean(seconds))
    rows = []
    for method, recs in (
        ("cross-instance · every pair", pair_recs),
        ("cross-instance · pairwise to reference", before_recs),
        ("cross-instance · global step", after_recs),
    ):
        rre = np.array([r["rre_deg"] for r in recs])
        rows.append(
            {
                "method": method,
                "pairs": len(recs),
                "mean_rre_deg": float(rre.mean()),
                "median_rre_deg": float(np.median(rre)),
                "mean_scale_error_pct": float(np.mean([r["scale_error_pct"] for r in recs])),
                "mean_ate_normalized": None,
                "success_rate": float(np.mean(rre < SUCCESS_RRE_DEG)),
                "seconds_per_pair": per_edge,
                "time_ratio_vs_gsa_coarse": None,
                "records": recs,
                "run": "cross-instance",
            }
        )
    lines.append(
        "| all | "
        + " | ".join(f"**{r['success_rate'] * 100:.0f} %** ({r['pairs']})" for r in rows)
        + f" | | | {per_edge:.1f} |"
    )
    return rows, lines


def protocol_nway(
    quick: bool,
    seed: int,
    out: Path,
    peers: list[str] | None = None,
    data: str | Path | None = None,
    cross: bool = True,
) -> list[dict]:
    """The captures' runs, then (cross) the cross-instance sets of the meshes in `data`
    (default DEFAULT_DATA; skipped, and said so, when that folder is missing)."""
    models, truth = captures(quick, seed)
    n = len(models)
    frames = [model_frame(m) for m in models]
    centres, sizes = [c for c, _ in frames], [s for _, s in frames]
    t0 = time.perf_counter()
    edges = pairwise_edges(models, select_edges(models, "all"), AlignOptions(stages=("coarse",), seed=seed))
    pairwise_s = time.perf_counter() - t0
    per_edge = pairwise_s / len(edges)
    evidence = frame_evidence(models, [(e.source, e.target) for e in edges])

    rows = []
    lines = [
        f"N = {n} captures of one {CATEGORY} ({len(models[0])}-{max(len(m) for m in models)} Gaussians), "
        f"{len(edges)} edges, coarse: {per_edge:.1f} s per edge, {pairwise_s:.0f} s pairwise",
        "Translation error: the model's centroid displacement over the reference's RMS radius "
        "(the generic table's ATE column holds the same).",
    ]
    for label, wrong in (("as measured", None), ("one edge wrong", (0, n - 1))):
        graph = copy.deepcopy(edges)
        named = ""
        if wrong is not None:
            e = next(e for e in graph if (e.source, e.target) == wrong)
            e.transform = turned(e, centres[e.source])
            named = f"model_{wrong[0]} -> model_{wrong[1]}"
        lines += [
            "",
            "| run | model | pairwise RRE (°) | global RRE (°) | pairwise scale err (%) | global scale err (%) | "
            "pairwise transl. err | global transl. err | confidence |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        t1 = time.perf_counter()
        result = solve_graph(n, graph, 0, centres, sizes, frames=evidence)
        global_s = time.perf_counter() - t1
        before = _errors(_pairwise_to_reference(graph, n), truth, frames)
        after = _errors(result.transforms, truth, frames)
        for b, a in zip(before[1:], after[1:]):
            lines.append(
                f"| {label} | {a['model']} | {b['rre_deg']:.2f} | {a['rre_deg']:.2f} | {b['scale_error_pct']:.2f} | "
                f"{a['scale_error_pct']:.2f} | {b['translation_error']:.4f} | {a['translation_error']:.4f} | "
                f"{result.confidences[a['model']]:.2f} |"
            )
        d = result.to_dict()
        statuses = {
            s: sum(e.status == s for e in result.edges) for s in ("kept", "down-weighted", "pruned", "corrected")
        }
        flagged = d["pruned"] + d["corrected"]
        extra = {
            "run": label,
            "wrong_edge": named or None,
            "wrong_edge_named": (named in flagged) if named else None,
            "pruned": d["pruned"],
            "corrected": d["corrected"],
            "edge_status": statuses,
            "cycles": d["cycles"],
            "seconds_per_edge": per_edge,
            "pairwise_seconds": pairwise_s,
            "global_seconds": global_s,
            "total_seconds": pairwise_s + global_s,
            "edges": d["edges"],
        }
        rows.append(_row(f"pairwise to reference · {label}", before, per_edge, extra))
        rows.append(_row(f"global step · {label}", after, (pairwise_s + global_s) / (n - 1), extra))
        cyc = d["cycles"]
        lines.append("")
        lines.append(
            f"{label}: edges {statuses}; pruned {d['pruned'] or 'none'}, corrected {d['corrected'] or 'none'}"
            + (f"; the wrong edge {named} {'named' if named in flagged else 'NOT named'}" if named else "")
            + f"; triangles measured {cyc['measured'].get('closing', 0)}/{cyc['measured']['triangles']} closing "
            f"(rotation median {cyc['measured'].get('rotation_deg_median', float('nan')):.2f}°, "
            f"max {cyc['measured'].get('rotation_deg_max', float('nan')):.2f}°), "
            f"after {cyc['after'].get('closing', 0)}/{cyc['after']['triangles']} "
            f"(rotation max {cyc['after'].get('rotation_deg_max', float('nan')):.2f}°); "
            f"global step {global_s * 1000:.0f} ms"
        )
    if cross:
        folder = Path(data) if data is not None else DEFAULT_DATA
        if folder.is_dir():
            cross_rows, cross_lines = _cross_rows(quick, seed, folder)
            rows += cross_rows
            lines += cross_lines
        else:
            lines += ["", f"Cross-instance sets skipped: no folder {folder} (pass --data DIR of category meshes)"]
    print("\n".join(lines))
    save_rows(out, "n-way", rows)
    return rows
