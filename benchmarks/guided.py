"""`gsa bench guided [--data DIR]`: what each hint of the guided path achieves.

Pairs: one per generated category of the `partial` and `deform` protocols (two captures of one
object) and of the procedural `category` protocol (two instances), plus, with --data, the
cross-instance pairs of real category meshes (benchmarks.category_real). Each pair carries what a person would tell the
guided path, made from the truth:
- a start 20° off the truth (a random axis through the source's centre): `init_transform`;
- 3 picked point pairs far apart, each click off by PICK_NOISE of its model's size: on two
  captures of one object, points that correspond (a source point and the target's nearest
  surface point in the canonical frame: a cut or a deformation moves it); between two
  instances, the same place relative to each one's bounding box (the nose of one airliner and
  the other's), snapped to its surface (corresponding_clicks);
- the true up axis of each model: `up_axes`;
- the true up and front axes of each model: `up_axes` and `front_axes`;
- a WRONG up axis (the target's turned 90°): guidance that contradicts the models.

Rows and what counts as success (the required shares beside them in the table):
- default `align`: the truth within SUCCESS_DEG of the chosen pose or one of its `alternatives`;
- start 20° off, 3 picked pairs: RRE < FINE_SUCCESS_DEG;
- up axes given, up and front axes given: RRE < SUCCESS_DEG;
- wrong up axes: the result is flagged `doubtful` (or right despite the hint).
RRE is judged up to each instance's own measured symmetries (category_real_judge), so a
bottle turned about its axis is right.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.category_real import _symmetries, category_real_judge, category_real_pairs, surface_points
from benchmarks.pairs import category_pairs, deform_pairs, partial_pairs
from benchmarks.records import Pair, evaluate, save_rows
from gsa.geometry import axis_rotation
from gsa.sim3 import Sim3
from gsa.synth.objects import CATEGORIES

START_OFF_DEG = 20.0
PICKED = 3
PICK_NOISE = 0.02
WRONG_UP_DEG = 90.0
SUCCESS_DEG = 5.0
FINE_SUCCESS_DEG = 3.0
# The required shares (the guided path's bars), printed beside the measured shares.
BARS = {
    "default": 0.95,
    "init": 0.95,
    "pairs": 0.95,
    "up": 0.85,
    "upfront": 0.95,
    "wrong_up": 1.0,
}
ROWS = {
    "default": "GSA (default align): truth in chosen pose or alternatives",
    "init": f"GSA, start {START_OFF_DEG:.0f}° off",
    "pairs": f"GSA, {PICKED} picked pairs ({PICK_NOISE:.0%} off)",
    "up": "GSA, up axes given",
    "upfront": "GSA, up and front axes given",
    "wrong_up": f"GSA, up axis {WRONG_UP_DEG:.0f}° wrong",
}
# Generated objects stand on +Z (gsa.synth.objects); the real meshes share +Y.
GENERATED_UP = np.array([0.0, 0.0, 1.0])
MESH_UP = np.array([0.0, 1.0, 0.0])
# A horizontal axis both models of a pair share in their canonical frames: what a person calls
# the front of each (its direction across the pair is what matters, not which way it is).
FRONT_OF = {tuple(GENERATED_UP): np.array([1.0, 0.0, 0.0]), tuple(MESH_UP): np.array([0.0, 0.0, 1.0])}


def _size(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.ptp(points, axis=0)))


def _spread_indices(points: np.ndarray, count: int, rng: np.random.Generator) -> list[int]:
    """`count` indices of `points` far apart (farthest-point order from a random start): the
    kind of points a person clicks (tips, corners), not three neighbours."""
    chosen = [int(rng.integers(len(points)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return chosen


def corresponding_clicks(source, target_canonical, truth: Sim3, rng: np.random.Generator, proportional: bool):
    """PICKED picked pairs, far apart, each click off by PICK_NOISE of its model's size; the
    target's clicks in its moved frame (truth applied). Two captures of one object
    (`proportional` False): source points the target also holds (a surface point within 2 % of
    the size), paired with that nearest point. Two instances: the point of the target at the
    same place relative to its bounding box (the nose of one airliner and the other's nose),
    snapped to its surface."""
    src, dst = surface_points(source), surface_points(target_canonical)
    if proportional:
        lo_s, span_s = src.min(0), np.maximum(np.ptp(src, axis=0), 1e-12)
        lo_d, span_d = dst.min(0), np.maximum(np.ptp(dst, axis=0), 1e-12)
        dist, nearest = cKDTree((dst - lo_d) / span_d).query((src - lo_s) / span_s)
        seen = dist < 0.05
    else:
        dist, nearest = cKDTree(dst).query(src)
        seen = dist < 0.02 * _size(dst)
    src_seen, dst_seen = src[seen], dst[nearest[seen]]
    order = _spread_indices(src_seen, PICKED, rng)
    a, b = src_seen[order], dst_seen[order]
    a = a + rng.normal(0, PICK_NOISE * _size(src) / np.sqrt(3), a.shape)
    b = b + rng.normal(0, PICK_NOISE * _size(dst) / np.sqrt(3), b.shape)
    return a.tolist(), truth.apply(b).tolist()


def start_off(truth: Sim3, pivot: np.ndarray, rng: np.random.Generator, degrees: float = START_OFF_DEG) -> Sim3:
    """The truth turned by `degrees` about a random axis through the source point `pivot`."""
    axis = rng.normal(size=3)
    turn = axis_rotation(axis / np.linalg.norm(axis), np.radians(degrees))
    return truth.compose(Sim3(1.0, turn, pivot - turn @ pivot))


def _wrong_up(up: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    side = np.cross(up, rng.normal(size=3))
    return axis_rotation(side / np.linalg.norm(side), np.radians(WRONG_UP_DEG)) @ up


def with_guidance(pairs: list[Pair], kind: str, up: np.ndarray, cross_instance: bool, seed: int) -> list[Pair]:
    """The pairs of one protocol, labelled 'KIND:label', each target carrying the guided hints
    (metadata['guidance']) and the instances' own symmetries (for category_real_judge)."""
    out = []
    for k, (label, make) in enumerate(pairs):

        def guided_make(make=make, k=k):
            source, target, truth = make()
            rng = np.random.default_rng([seed, 270, k, sum(map(ord, kind))])
            canonical_target = target.transformed(truth.inverse())
            if "symmetry_rotations" not in target.metadata:
                target.metadata["symmetry_rotations"] = _symmetries(source) + _symmetries(canonical_target)
            clicks = corresponding_clicks(source, canonical_target, truth, rng, proportional=cross_instance)
            true_up = truth.rotation @ up
            front = FRONT_OF[tuple(up)]
            target.metadata["guidance"] = {
                "init": {
                    "init_transform": start_off(truth, surface_points(source).mean(axis=0), rng).matrix().tolist()
                },
                "pairs": {"point_pairs": clicks},
                "up": {"up_axes": (up.tolist(), true_up.tolist())},
                "upfront": {
                    "up_axes": (up.tolist(), true_up.tolist()),
                    "front_axes": (front.tolist(), (truth.rotation @ front).tolist()),
                },
                "wrong_up": {"up_axes": (up.tolist(), _wrong_up(true_up, rng).tolist())},
            }
            return source, target, truth

        out.append((f"{kind}:{label}", guided_make))
    return out


def guided_pairs(quick: bool, seed: int, data: str | Path | None) -> list[Pair]:
    """One pair per generated category of partial, deform and category (their quick or full
    sizes: 18 pairs) and, with `data`, category-real's pairs (--quick: 3 instances per class;
    full: all 115 of the development set)."""
    per_category = len(CATEGORIES)
    category = category_pairs(quick, seed)
    pairs = with_guidance(partial_pairs(quick, seed)[:per_category], "partial", GENERATED_UP, False, seed)
    pairs += with_guidance(deform_pairs(quick, seed)[:per_category], "deform", GENERATED_UP, False, seed)
    # category_pairs lists each category's instance pairs together: the first of each.
    firsts = category[:: len(category) // per_category]
    pairs += with_guidance(firsts, "category", GENERATED_UP, True, seed)
    if data is not None:
        pairs += with_guidance(category_real_pairs(data, quick, seed), "category-real", MESH_UP, True, seed)
    return pairs


def guided_runner(hint: str):
    """align() with the pair's hint of kind `hint` (None hint for the default row)."""
    from gsa.align.pipeline import AlignOptions, align

    def run(source, target):
        options = target.metadata["guidance"].get(hint, {})
        t0 = time.perf_counter()
        result = align(source, target, AlignOptions(**options))
        flags = {
            "confidence": float(result.metrics.get("confidence", float("nan"))),
            "doubtful": result.verdict.doubtful,
            "alternatives": [alt.transform.matrix().tolist() for alt in result.verdict.alternatives]
            if hint == "default"
            else None,
        }
        return {ROWS[hint]: (result.transform, time.perf_counter() - t0, flags)}

    return run


def _passed(hint: str, rec: dict) -> bool:
    if "error" in rec:
        return False
    rre = rec["rre_deg"]
    if hint == "default":
        return min(rre, rec.get("closest_alternative_rre_deg", np.inf)) < SUCCESS_DEG
    if hint in ("init", "pairs"):
        return rre < FINE_SUCCESS_DEG
    if hint in ("up", "upfront"):
        return rre < SUCCESS_DEG
    return rec.get("doubtful", False) or rre < SUCCESS_DEG  # wrong_up: flagged, or right anyway


def protocol_guided(
    quick: bool, seed: int, out: Path, peers: list[str] | None = None, data: str | Path | None = None
) -> list[dict]:
    """Every hint's row over every pair; per row and pair group the share that passed."""
    rows = evaluate(
        "guided",
        guided_pairs(quick, seed, data),
        [guided_runner(hint) for hint in ROWS],
        lambda label: {"group": label.split(":")[0]},
        out=out,
        judge=category_real_judge,
    )
    for row in rows:
        hint = next(h for h, name in ROWS.items() if name == row["method"])
        row["hint"] = hint
        for rec in row["records"]:
            rec["passed"] = _passed(hint, rec)
        groups = dict.fromkeys(rec["group"] for rec in row["records"])
        row["passed_by_group"] = {
            g: float(np.mean([rec["passed"] for rec in row["records"] if rec["group"] == g])) for g in groups
        }
        row["passed_rate"] = float(np.mean([rec["passed"] for rec in row["records"]]))
    save_rows(out, "guided", rows)
    return rows


def format_guided(rows: list[dict]) -> str:
    groups = list(dict.fromkeys(g for r in rows for g in r["passed_by_group"]))
    lines = [
        "| row | passes when | " + " | ".join(groups) + " | all | required |",
        "|---|---|" + "---:|" * (len(groups) + 2),
    ]
    rule = {
        "default": f"truth < {SUCCESS_DEG:.0f}° of the chosen pose or an alternative",
        "init": f"RRE < {FINE_SUCCESS_DEG:.0f}°",
        "pairs": f"RRE < {FINE_SUCCESS_DEG:.0f}°",
        "up": f"RRE < {SUCCESS_DEG:.0f}°",
        "upfront": f"RRE < {SUCCESS_DEG:.0f}°",
        "wrong_up": "flagged doubtful (or right)",
    }
    for r in rows:
        cells = [f"{r['passed_by_group'][g] * 100:.0f} %" if g in r["passed_by_group"] else "—" for g in groups]
        lines.append(
            f"| {r['method']} | {rule[r['hint']]} | "
            + " | ".join(cells)
            + f" | **{r['passed_rate'] * 100:.0f} %** | {BARS[r['hint']] * 100:.0f} % |"
        )
    lines.append("")
    lines.append(
        "Pairs per group: "
        + ", ".join(f"{g} {sum(rec['group'] == g for rec in rows[0]['records'])}" for g in groups)
        + "; median RRE per row: "
        + ", ".join(f"{r['hint']} {r['median_rre_deg']:.2f}°" for r in rows)
    )
    return "\n".join(lines)
