"""Measure a canonical head on meshes it was not trained on: each instance as a 3DGS model at a
random pose, oriented (gsa.align.orient); the up and front errors, and every pair of instances
of a category aligned through the canonical frame (RRE; symmetric categories by up alone).

    python -m training.evaluate --meshes /work/train-data/meshes --head H.pt --categories chair,mug
"""

from __future__ import annotations

import argparse
import json
from itertools import combinations
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gsa.align.orient import FRONT, UP, OrientCriteria, orient, relative_pose
from gsa.align.semantic import available_backbone
from gsa.synth.meshes import load_mesh, mesh_to_gaussians
from training.render_tokens import SYMMETRIC, instance_of


def angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def rotation_error(r_est, r_true) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r_est @ r_true.T) - 1) / 2, -1, 1))))


def evaluate(meshes_dir, entries, head, seed=0, log=print) -> dict:
    backbone = available_backbone()
    rng = np.random.default_rng(seed)
    per = {}
    for e in entries:
        mesh = load_mesh(Path(meshes_dir) / e["file"])
        rot = Rotation.random(random_state=rng).as_matrix()
        model = mesh_to_gaussians(mesh, 30_000, rng, floaters=0.02, normalise=False)
        from gsa.sim3 import Sim3

        model = model.transformed(Sim3(float(np.exp(rng.uniform(-1, 1))), rot, rng.normal(0, 1, 3)))
        res = orient(model, OrientCriteria(), head_path=head, backbone=backbone)
        up_err = angle(res.up, rot @ UP)
        front_err = angle(res.front, rot @ FRONT)
        per.setdefault(e["category"], []).append(
            {"instance": instance_of(e), "rot": rot, "res": res, "up": up_err, "front": front_err}
        )
        log(
            f"{e['category']:10s} {instance_of(e)[:20]:20s} up {up_err:6.1f}  front {front_err:6.1f}  conf {res.inlier_share:.2f}"
        )
    summary = {}
    for cat, items in per.items():
        sym = cat in SYMMETRIC
        pairs = []
        for a, b in combinations(items, 2):
            for s, t in ((a, b), (b, a)):
                est = relative_pose(s["res"], t["res"]).rotation
                truth = t["rot"] @ s["rot"].T
                err = angle(est @ (s["rot"] @ UP), t["rot"] @ UP) if sym else rotation_error(est, truth)
                conf = s["res"].confident and t["res"].confident
                pairs.append((err, conf))
        errs = np.array([p[0] for p in pairs]) if pairs else np.zeros(0)
        summary[cat] = {
            "instances": len(items),
            "up_within_10": float(np.mean([i["up"] < 10 for i in items])),
            "front_within_20": None if sym else float(np.mean([i["front"] < 20 for i in items])),
            "pairs": len(pairs),
            "pairs_within_5": float(np.mean(errs < 5)) if len(errs) else None,
            "pairs_within_15": float(np.mean(errs < 15)) if len(errs) else None,
            "pairs_median": float(np.median(errs)) if len(errs) else None,
        }
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", required=True)
    ap.add_argument("--head", required=True)
    ap.add_argument("--categories", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dev-only", action="store_true", help="only the category-real bench's instances")
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    cats = set(args.categories.split(","))
    index = json.loads((Path(args.meshes) / "index.json").read_text())
    entries = [e for e in index if e["category"] in cats and (e.get("dev_instance") or not args.dev_only)]
    summary = evaluate(args.meshes, entries, args.head, args.seed)
    print(json.dumps(summary, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
