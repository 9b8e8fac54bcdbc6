"""`gsa bench category-real --data DIR`: cross-instance pairs of REAL category meshes.

Every pair of instances within a category (`<category>_<i>.npz`, gsa.synth.meshes), each
sampled as a 3DGS model (surface Gaussians with the mesh's colours, 2 % faint floaters),
the target moved by a random Sim(3) (≤ 180° per axis, 0.1–10× scale). The instances of a
category share one canonical orientation, so the true rotation is the one applied.
Success: RRE < 5°, judged up to the instances' own symmetries: a pose that maps the source
onto the same surface as the true one is right (a bottle turned about its axis, a square
table turned by 90°). The symmetries are measured on each instance (benchmarks's
`instance_symmetries`: turns about the canonical axes that move the surface by < 1 % of its
diagonal), never read from category names; the strict error is kept as `rre_strict_deg`.

Rows: GSA as `gsa align` runs by default (stages auto), and the peers; per class mean /
median RRE and success, beside the paper's Table 2 format.
"""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.records import Pair
from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth.meshes import find_meshes, load_mesh, mesh_to_gaussians
from gsa.synth.perturb import random_sim3

# Sizes (source, target) per model: full and --quick.
SIZES = ((20_000, 30_000), (4_000, 5_000))
# The guided rows' simulated clicks: pairs per model, and how far off each click lands.
PICKED_PAIRS = 4
PICK_NOISE = 0.02
FLOATERS = 0.02
# An instance counts as symmetric under a turn about one of its canonical axes when the turn
# moves its surface by less than this share of its bounding-box diagonal (mean nearest
# distance, both ways); under every turn when SPIN_TEST_DEG all pass (a bottle, a vase).
SYMMETRY_TOLERANCE = 0.01
SPIN_TEST_DEG = (30.0, 60.0, 90.0, 135.0)
DISCRETE_TURNS_DEG = (90.0, 180.0, 270.0)


def instance_symmetries(points: np.ndarray, surface: np.ndarray | None = None) -> list[np.ndarray]:
    """Rotations about the canonical axes (through the bounding-box centre) that map the
    surface sample `points` onto itself: every 1° for a turn-symmetric axis, else the
    quarter and half turns that pass. The identity is not listed. `surface`: the dense
    surface the sample was drawn from; the turned sample is measured against it (against a
    sparse sample alone a perfect symmetry moves it by that sample's own spacing, which for a
    large vase exceeded the tolerance: see docs/benchmarks.md, the judge's fix of 2026-11-27)."""
    lo, hi = points.min(0), points.max(0)
    centre = 0.5 * (lo + hi)
    centred = points - centre
    diagonal = float(np.linalg.norm(hi - lo))
    tree = cKDTree(centred if surface is None else surface - centre)

    def moved(axis_unit: np.ndarray, deg: float) -> float:
        turned = centred @ axis_rotation(axis_unit, np.radians(deg)).T
        if surface is not None:
            return float(tree.query(turned)[0].mean()) / diagonal
        return 0.5 * (tree.query(turned)[0].mean() + cKDTree(turned).query(centred)[0].mean()) / diagonal

    out = []
    for axis in range(3):
        unit = np.eye(3)[axis]
        if max(moved(unit, deg) for deg in SPIN_TEST_DEG) < SYMMETRY_TOLERANCE:
            out += [axis_rotation(unit, np.radians(deg)) for deg in np.arange(1.0, 360.0)]
        else:
            out += [
                axis_rotation(unit, np.radians(deg))
                for deg in DISCRETE_TURNS_DEG
                if moved(unit, deg) < SYMMETRY_TOLERANCE
            ]
    return out


def category_real_pairs(data: str | Path, quick: bool, seed: int) -> list[Pair]:
    """All C(n, 2) instance pairs per category of `data` (quick: the first 3 instances).
    Labels 'category-a-b'."""
    groups = find_meshes(data)
    if not groups:
        raise ValueError(f"{data}: no <category>_<i>.npz meshes found")
    (n_src, n_dst) = SIZES[1] if quick else SIZES[0]
    pairs: list[Pair] = []
    for c, (category, paths) in enumerate(sorted(groups.items())):
        paths = paths[:3] if quick else paths
        for a, b in itertools.combinations(range(len(paths)), 2):

            def make(category=category, c=c, a=a, b=b, pa=paths[a], pb=paths[b]):
                rng = np.random.default_rng([seed, 25, c, a, b])
                truth = random_sim3(rng)
                mesh_a, mesh_b = load_mesh(pa), load_mesh(pb)
                source = mesh_to_gaussians(mesh_a, n_src, np.random.default_rng([seed, 26, c, a]), FLOATERS)
                target = mesh_to_gaussians(mesh_b, n_dst, np.random.default_rng([seed, 27, c, b]), FLOATERS)
                # A pose that maps the source onto the same surface as the truth is right:
                # the truth composed with a symmetry of either instance (canonical axes are shared).
                symmetries = _symmetries(source) + _symmetries(target)
                hints = _hints(source, target, truth, np.random.default_rng([seed, 28, c, a, b]))
                target = target.transformed(truth)
                target.metadata["symmetry_rotations"] = symmetries
                target.metadata["hints"] = hints
                return source, target, truth

            pairs.append((f"{category}-{a}-{b}", make))
    return pairs


def _hints(source, target, truth: Sim3, rng: np.random.Generator) -> dict:
    """What a person would tell the guided path (gsa.align.guided): the up axis in each model's
    coordinates (the meshes' shared canonical +Y), and PICKED_PAIRS point pairs clicked on
    corresponding parts (corner_clicks)."""
    up = np.array([0.0, 1.0, 0.0])
    src_clicks, dst_clicks = corner_clicks(source, target, rng, PICKED_PAIRS)
    return {
        "up_axes": (up.tolist(), (truth.rotation @ up).tolist()),
        "point_pairs": (src_clicks.tolist(), truth.apply(dst_clicks).tolist()),
    }


def corner_clicks(source, target, rng: np.random.Generator, count: int, noise: float = PICK_NOISE):
    """Clicks a person would make on two instances in one canonical frame: each instance's
    outermost surface point towards `count` of the bounding box's corner directions
    (front-left-top, …; the same corners on both), each click off by up to `noise` of the
    model's size. Returns (source clicks, target clicks), each (count, 3), in the models' frames."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    chosen = corners[rng.choice(len(corners), count, replace=False)]

    def clicks(model) -> np.ndarray:
        pts = surface_points(model)
        centred = (pts - 0.5 * (pts.min(0) + pts.max(0))) / np.maximum(np.ptp(pts, axis=0), 1e-12)
        picked = pts[np.argmax(centred @ chosen.T, axis=0)]
        size = float(np.linalg.norm(np.ptp(pts, axis=0)))
        return picked + rng.normal(0, noise * size / np.sqrt(3), picked.shape)

    return clicks(source), clicks(target)


def surface_points(model) -> np.ndarray:
    """The model's surface Gaussians' centres (the sampled meshes' floaters are faint), float64."""
    return model.means[model.opacities > 0.5].astype(np.float64)


def _symmetries(model) -> list[np.ndarray]:
    surface = surface_points(model)
    sample = surface[np.random.default_rng(0).choice(len(surface), min(len(surface), 4000), replace=False)]
    return instance_symmetries(sample, surface)


def category_real_judge(est: Sim3, truth: Sim3, source, target) -> dict:
    """RRE up to the instances' own symmetries (strict where they have none); the strict
    error is kept as `rre_strict_deg`."""
    symmetries = target.metadata.get("symmetry_rotations") or []
    strict = rre_deg(est.rotation, truth.rotation)
    if not symmetries:
        return {"symmetric": False}
    judged = min([strict] + [rre_deg(est.rotation, truth.rotation @ g) for g in symmetries])
    return {"rre_deg": judged, "rre_strict_deg": strict, "symmetric": True}


def category_of(label: str) -> dict:
    return {"category": label.rsplit("-", 2)[0]}


def default_align_runner(hint: str | None = None):
    """`gsa align`'s defaults (stages auto), one row; with `hint` (up_axes or point_pairs), the
    guided path given the pair's hint of that kind (target.metadata['hints'])."""
    from gsa.align.pipeline import AlignOptions, align

    label = {None: "GSA (default align)", "up_axes": "GSA, up axes given", "point_pairs": "GSA, 4 picked pairs"}[hint]

    def run(source, target):
        t0 = time.perf_counter()
        options = {hint: target.metadata["hints"][hint]} if hint else {}
        result = align(source, target, AlignOptions(**options))
        flags = {
            "confidence": float(result.metrics.get("confidence", float("nan"))),
            "ambiguous": result.verdict.ambiguous,
            "doubtful": result.verdict.doubtful,
            "alternatives": [alt.transform.matrix().tolist() for alt in result.verdict.alternatives],
        }
        return {label: (result.transform, time.perf_counter() - t0, flags)}

    return run


def per_class(records: list[dict]) -> dict[str, dict]:
    """Mean / median RRE and success per category, in order of appearance."""
    out: dict[str, dict] = {}
    for cat in dict.fromkeys(r.get("category") for r in records):
        rre = np.array([r.get("rre_deg", np.nan) for r in records if r.get("category") == cat], np.float64)
        out[cat] = {
            "pairs": int(len(rre)),
            "mean_rre_deg": float(np.nanmean(rre)) if np.isfinite(rre).any() else float("nan"),
            "median_rre_deg": float(np.nanmedian(rre)) if np.isfinite(rre).any() else float("nan"),
            "success_rate": float(np.sum(rre < 5.0) / len(rre)),
        }
    return out


def format_category_real(rows: list[dict]) -> str:
    """One table per method: class × (mean, median RRE, success); then the paper's Table 2
    layout (mean RRE per class) with every method as a row."""
    cats = list(dict.fromkeys(c for r in rows for c in r.get("per_class", {})))
    lines = [
        "| method | " + " | ".join(cats) + " | all |",
        "|---|" + "---:|" * (len(cats) + 1),
    ]
    for r in rows:
        per = r.get("per_class", {})
        cells = [
            f"{per[c]['success_rate'] * 100:.0f}% ({per[c]['median_rre_deg']:.1f}°)" if c in per else "—" for c in cats
        ]
        lines.append(
            f"| {r['method']} success (median RRE) | "
            + " | ".join(cells)
            + f" | **{r['success_rate'] * 100:.0f}%** ({r['median_rre_deg']:.1f}°) |"
        )
    lines += [
        "",
        "Paper Table 2 format, mean RRE (°) per class:",
        "",
        "| method | " + " | ".join(cats) + " | mean | s / pair |",
        "|---|" + "---:|" * (len(cats) + 2),
    ]
    for r in rows:
        per = r.get("per_class", {})
        cells = [f"{per[c]['mean_rre_deg']:.1f}" if c in per else "—" for c in cats]
        lines.append(
            f"| {r['method']} | " + " | ".join(cells) + f" | {r['mean_rre_deg']:.1f} | {r['seconds_per_pair']:.2f} |"
        )
    for r in rows:
        if "flag_results" in r:
            closest = [rec.get("closest_alternative_rre_deg") for rec in r["records"] if rec.get("rre_deg", 0) >= 5.0]
            closest = [c for c in closest if c is not None]
            within = sum(c < 5.0 for c in closest)
            lines.append(
                f"\n{r['method']}: {r['flagged']}/{r['flag_results']} flagged doubtful; unflagged success "
                f"{r['unflagged_success_rate'] * 100:.0f}%; failures flagged {r['failures_flagged_rate'] * 100:.0f}%; "
                f"misses whose truth is among the alternatives (< 5°): {within}/{len(closest)}"
            )
    return "\n".join(lines)
