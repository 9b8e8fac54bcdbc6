"""`gsa orient MODEL --out result.json [--aligned-out MODEL]`: which way is up and which way the
object faces, from the learned canonical head (gsa.align.orient)."""

from __future__ import annotations

import json
from pathlib import Path


def add_orient_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "orient",
        help="a model's up and front, and the transform into its category's canonical frame (+Y up, +Z front)",
    )
    p.add_argument("model", help="3DGS file (any format gsa reads)")
    p.add_argument("--out", help="write the result JSON here (it is printed either way)")
    p.add_argument(
        "--aligned-out",
        help="write the model turned upright and facing +Z (its centre at the origin, its scale kept)",
    )
    p.add_argument("--head", help="canonical head weights (default: the ones shipped in the package)")
    p.add_argument("--views", type=int, default=24, help="orbit views rendered for the head (default 24)")
    p.add_argument("--seed", type=int, default=0, help="seed of the camera placement and of RANSAC")
    p.set_defaults(func=cmd_orient)


def cmd_orient(args) -> int:
    from dataclasses import replace

    from gsa.align.orient import OrientCriteria, orient
    from gsa.features.nocs import head_provenance
    from gsa.io import read_model, write_model
    from gsa.sim3 import Sim3

    if args.views < 4:
        raise ValueError("--views must be at least 4")
    model = read_model(args.model)
    model.validate(args.model)
    criteria = OrientCriteria()
    criteria = replace(criteria, canonical=replace(criteria.canonical, views=args.views))
    result = orient(model, criteria, head_path=args.head, seed=args.seed)
    out = {"model": str(args.model), **result.to_dict()}
    out["head"] = head_provenance(args.head).get("command", "")
    if args.aligned_out:
        t = result.transform
        turned = Sim3(1.0, t.rotation, t.translation / t.scale)  # canonical frame, the model's own units
        write_model(model.transformed(turned), args.aligned_out)
        out["aligned"] = str(args.aligned_out)
    text = json.dumps(out, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0
