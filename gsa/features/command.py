"""`gsa lift MODEL.ply --out lifted.ply --features canonical|spheremap|dinov2 [...]`
(registered by gsa.cli)."""

from __future__ import annotations

import json
import sys


def add_lift_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "lift",
        help="give a 3DGS model features: extract 2D features from rendered "
        "views, lift them onto the Gaussians, prune background Gaussians",
    )
    p.add_argument("model", help="3DGS PLY file")
    p.add_argument("--out", required=True, help="output PLY (with semantic_0..2)")
    p.add_argument(
        "--features",
        default="canonical",
        choices=["canonical", "spheremap", "dinov2"],
        help="2D feature extractor (default canonical: weight-free)",
    )
    p.add_argument(
        "--backbone",
        "--weights",
        dest="backbone",
        default=None,
        help="DINOv2 weights: Hugging Face Dinov2 folder or torch.hub .pth state dict "
        "(spheremap, dinov2; env GSA_FEATURES_BACKBONE)",
    )
    p.add_argument("--head", default=None, help="sphere_mapper head checkpoint (spheremap; env GSA_FEATURES_HEAD)")
    p.add_argument("--views", type=int, default=None, help="rendered views (default 24)")
    p.add_argument("--size", type=int, default=None, help="view width and height in pixels (default 128)")
    p.add_argument("--iterations", type=int, default=None, help="Adam iterations (default 150)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default 0.02)")
    p.add_argument(
        "--prune",
        type=float,
        default=None,
        help="remove Gaussians with feature magnitude below this (default 0.1; 0 keeps all)",
    )
    p.add_argument("--backend", default=None, choices=["auto", "cpu", "cuda"], help="rasterizer backend")
    p.add_argument("--report", default=None, help="also write the lifting report as JSON here")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_lift)


def cmd_lift(args) -> int:
    from gsa.features import FeatureSettings, make_extractor, prune_background
    from gsa.features.prepare import lift_with_settings
    from gsa.io.ply import read_ply, write_ply
    from gsa.settings_env import feature_settings_env

    s = FeatureSettings(
        **feature_settings_env(
            backbone=args.backbone,
            head=args.head,
            lift_views=args.views,
            lift_image_size=args.size,
            lift_iterations=args.iterations,
            lift_lr=args.lr,
            prune_threshold=args.prune,
            backend=args.backend,
        )
    )
    if s.lift_views < 1 or s.lift_image_size < 8 or s.lift_iterations < 0:
        raise ValueError("--views must be >= 1, --size >= 8 and --iterations >= 0")
    extractor = make_extractor(args.features, s)  # fails fast, before reading a large model
    model = read_ply(args.model)
    model.validate(args.model)

    last = [None]

    def progress(stage: str, frac: float) -> None:
        # One line per stage change and per 25%, so logs stay short.
        key = (stage, int(frac * 100) // 25)
        if not args.quiet and key != last[0]:
            last[0] = key
            print(f"[gsa] {stage} {int(frac * 100)}%", file=sys.stderr, flush=True)

    lifted, report = lift_with_settings(model, extractor, s, progress)
    removed = 0
    if s.prune_threshold > 0:
        lifted, removed = prune_background(lifted, s.prune_threshold)
    write_ply(lifted, args.out)
    summary = {k: v for k, v in report.to_dict().items() if k != "loss_curve"}
    summary.update(out=str(args.out), pruned=removed, kept=len(lifted), loss_curve_every_10=report.loss_curve[::10])
    if args.report:
        with open(args.report, "w") as fh:
            json.dump({**report.to_dict(), "pruned": removed, "kept": len(lifted)}, fh, indent=2)
    print(json.dumps(summary, indent=2))
    return 0
