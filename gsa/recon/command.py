"""`gsa reconstruct IMAGES_DIR_OR_ZIP --out DIR [--preset cpu|gpu]`."""

from __future__ import annotations

import argparse
import json
import sys


def add_reconstruct_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "reconstruct",
        help="build a feature-augmented 3DGS model from an image set",
        description="SfM (pycolmap) -> masks -> feature-augmented 3DGS training.",
    )
    p.add_argument("images", help="directory of images or a .zip archive")
    p.add_argument("--out", required=True, help="output directory (model.ply, cameras.json, report.json, ...)")
    p.add_argument(
        "--preset",
        choices=("cpu", "gpu"),
        default="cpu",
        help="cpu: 128 px, 600 iterations (minutes on 2 cores); gpu: full resolution, 7000 iterations",
    )
    p.add_argument("--iterations", type=int, default=None, help="override the preset's iteration count")
    p.add_argument("--masks", choices=("auto", "key", "grabcut", "sam", "none"), default="auto")
    p.add_argument("--matching", choices=("exhaustive", "sequential"), default="exhaustive")
    p.add_argument("--features", choices=("canonical", "none"), default="canonical")
    p.add_argument("--sam-encoder", default=None, help="local SAM encoder .onnx (masks=sam)")
    p.add_argument("--sam-decoder", default=None, help="local SAM decoder .onnx (masks=sam)")
    p.add_argument(
        "--intrinsics-from",
        default=None,
        metavar="DIR",
        help="a folder `gsa reconstruct` wrote from photos of the same camera: its intrinsics are held "
        "fixed (scaled to this set's size) so that the two models share one lens and one scale",
    )
    p.set_defaults(func=run_reconstruct)
    return p


def run_reconstruct(args) -> int:
    from gsa.recon import ImageSetError, MaskError, SfMError
    from gsa.recon.pipeline import reconstruct
    from gsa.settings_env import sam_paths_env

    line_open = False  # a progress line is on stderr (ended before an error line)

    def progress(stage, frac):
        nonlocal line_open
        line_open = True
        print(f"\r{stage:14s} {100 * frac:5.1f}%", end="", file=sys.stderr, flush=True)

    sam_encoder, sam_decoder = sam_paths_env(args.sam_encoder, args.sam_decoder)
    calibration = None
    if args.intrinsics_from:
        calibration = _calibration_from(args.intrinsics_from)
        if calibration is None:
            return 1
    try:
        res = reconstruct(
            args.images,
            args.out,
            preset=args.preset,
            features=args.features,
            progress=progress,
            masks=args.masks,
            matching=args.matching,
            iterations=args.iterations,
            sam_encoder=sam_encoder,
            sam_decoder=sam_decoder,
            calibration=calibration,
            calibration_check="none",  # the user says it is the same camera
        )
    except (ImageSetError, SfMError, MaskError) as exc:
        print(("\n" if line_open else "") + f"gsa: error: {exc}", file=sys.stderr)
        return 1
    print(file=sys.stderr)
    far = res.train.region
    if far.get("sfm_points_dropped") or far.get("gaussians_pruned"):
        print(
            f"gsa: distant background left out: {far['sfm_points_dropped']} SfM point(s) and "
            f"{far['gaussians_pruned']} Gaussian(s) beyond {far['radius']:.3g} (twice the farthest camera's "
            "distance) from the point the cameras look at",
            file=sys.stderr,
        )
    if calibration is not None and not res.intrinsics.get("fixed"):
        print(f"gsa: --intrinsics-from not used: {res.intrinsics['reason']}", file=sys.stderr)
    print(json.dumps(res.summary(), indent=1))
    return 0


def _calibration_from(folder: str):
    """The intrinsics of a folder `gsa reconstruct` wrote; None (one error line printed) when
    it holds none a set could share."""
    from gsa.recon.calibration import Calibration
    from gsa.render.cameras import read_cameras_json

    try:
        cameras, _ = read_cameras_json(f"{folder}/cameras.json")
    except (OSError, ValueError, KeyError) as exc:
        print(f"gsa: error: --intrinsics-from {folder}: {exc}", file=sys.stderr)
        return None
    calibration = Calibration.of_cameras(cameras)
    if calibration is None:
        print(f"gsa: error: --intrinsics-from {folder}: its views have several cameras", file=sys.stderr)
    return calibration


def main(argv=None) -> int:  # `python -m gsa.recon.command ...` without the main CLI
    parser = argparse.ArgumentParser(prog="gsa")
    sub = parser.add_subparsers(dest="command", required=True)
    add_reconstruct_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
