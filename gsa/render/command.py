"""`gsa render MODEL.ply --out DIR [--views N] [--features]`."""

from __future__ import annotations

import json


def add_render_parser(subparsers) -> None:
    p = subparsers.add_parser("render", help="render PNG views of a 3DGS model")
    p.add_argument("model", help="3DGS PLY file")
    p.add_argument("--out", required=True, help="output folder for PNGs")
    p.add_argument("--views", type=int, default=8, help="number of orbit views (default 8)")
    p.add_argument(
        "--features",
        action="store_true",
        help="also render feature maps (the model's semantic_* features, else canonical features)",
    )
    p.add_argument("--size", type=int, default=256, help="image width and height in pixels (default 256)")
    p.add_argument("--backend", default="auto", choices=["auto", "cpu", "cuda"], help="rasterizer backend")
    p.add_argument("--seed", type=int, default=0, help="seed for the orbit camera placement")
    p.set_defaults(func=cmd_render)


def cmd_render(args) -> int:
    from gsa.io.ply import read_ply
    from gsa.render.views import render_model_views

    if args.views < 1 or args.size < 8:
        raise ValueError("--views must be >= 1 and --size >= 8")
    model = read_ply(args.model)
    model.validate(args.model)
    if args.features and model.features is None:
        from gsa.canonical import canonical_features

        model = model.with_features(canonical_features(model))
    paths = render_model_views(
        model, args.out, views=args.views, features=args.features, size=args.size, backend=args.backend, seed=args.seed
    )
    print(json.dumps({"renders": sorted(str(p) for p in paths.values())}, indent=2))
    return 0
