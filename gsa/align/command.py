"""`gsa align SOURCE TARGET`: its parser, options from the arguments (guidance included), the
handler and what it prints (the transform, the doubt warning)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gsa.cli_base import FORMAT_CHOICES, CliError, ProgressPrinter


def _load_model(path: str, role: str = "model", args: argparse.Namespace | None = None, calibration=None):
    """A 3DGS file in any supported format, a folder `gsa reconstruct` wrote (its model, with the
    photo anchors that let align() register two reconstructions by their photos), or an image
    set (folder or .zip) reconstructed first — with `calibration` (gsa.recon.calibration) held
    fixed when its photos are of that camera."""
    from gsa.io.formats import read_model
    from gsa.recon.folder import is_reconstruction, read_reconstruction

    p = Path(path)
    if is_reconstruction(p):
        return read_reconstruction(p)
    if p.is_dir() or p.suffix.lower() == ".zip":
        try:
            from gsa.recon.pipeline import reconstruct
        except ImportError as exc:
            raise CliError(f"{path}: image sets need the recon extra (pip install 'gsa[recon]'): {exc}") from None
        out = Path(args.out).parent / f"recon_{role}" if args is not None else Path(f"recon_{role}")
        preset = getattr(args, "preset", "cpu")
        print(f"[gsa] reconstructing {role} from {path} into {out} (preset {preset})", file=sys.stderr)
        res = reconstruct(
            p, out, preset=preset, progress=ProgressPrinter(not getattr(args, "quiet", False)), calibration=calibration
        )
        if res.intrinsics.get("fixed"):
            print(f"[gsa] {role}: the source's camera (EXIF): its intrinsics held fixed", file=sys.stderr)
        return res.model
    return read_model(p)


def _align_options(args: argparse.Namespace):
    """AlignOptions from the arguments: the flags made from gsa.align.spec (those left unset
    take the library's defaults), --stages' comma list, the extractor's settings and the guidance."""
    from gsa.align.pipeline import AlignOptions
    from gsa.align.spec import OPTIONS

    fields = {
        "stages": tuple(s.strip() for s in args.stages.split(",") if s.strip()),
        "feature_settings": _feature_settings(args),
    }
    for name in (*CLI_OPTIONS, *CLI_GUIDANCE_OPTIONS):
        value = getattr(args, _dest(OPTIONS[name].flag or _flag(name)), None)
        if value is not None:
            fields[name] = value
    if "semantic" not in fields:
        fields["semantic"] = _semantic_default()
    fields.update(_guidance_fields(args))
    try:
        return AlignOptions(**fields)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _read_json_arg(path: str, flag: str):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise CliError(f"{flag} {path}: {exc}") from None


def _guidance_fields(args: argparse.Namespace) -> dict:
    """--pairs / --up / --front in each file's own coordinates (converted once the files are
    read, gsa.align.contract.hints_from_files); --init is resolved in `_init_transform`; --scale
    is an option of gsa.align.spec."""
    fields: dict = {}
    if getattr(args, "pairs", None):
        data = _read_json_arg(args.pairs, "--pairs")
        if not isinstance(data, dict) or "source" not in data or "target" not in data:
            raise CliError(f'--pairs {args.pairs}: expected {{"source": [[x, y, z], …], "target": [[x, y, z], …]}}')
        fields["point_pairs"] = (data["source"], data["target"])
    if getattr(args, "up", None):
        fields["up_axes"] = _axis_pair(args.up, "--up", "up")
    if getattr(args, "front", None):
        fields["front_axes"] = _axis_pair(args.front, "--front", "front")
    return fields


def _axis_pair(value: str, flag: str, what: str) -> tuple:
    """X,Y,Z:X,Y,Z -> (source vector, target vector); the library checks their values."""
    expected = f"{flag} {value}: expected X,Y,Z:X,Y,Z (source {what} : target {what})"
    try:
        pair = tuple(tuple(float(x) for x in part.split(",")) for part in value.split(":"))
    except ValueError:
        raise CliError(expected) from None
    if len(pair) != 2:
        raise CliError(expected)
    return pair


def _init_transform(args: argparse.Namespace) -> tuple[list | None, bool]:
    """(4×4, internal?) from --init [--alternative N]: a result.json (its `transform_internal`
    when present, an alternative's `transform` with --alternative: both in align()'s internal
    frame) or any JSON with a 4×4 `transform` in the files' own coordinates."""
    if not getattr(args, "init", None):
        if getattr(args, "alternative", None) is not None:
            raise CliError("--alternative needs --init RESULT_JSON")
        return None, False
    data = _read_json_arg(args.init, "--init")
    if not isinstance(data, dict):
        raise CliError(f"--init {args.init}: expected a JSON object with a 4×4 `transform`")
    if args.alternative is not None:
        alternatives = (data.get("metrics") or {}).get("alternatives") or []
        if not 0 <= args.alternative < len(alternatives):
            raise CliError(f"--alternative {args.alternative}: {args.init} lists {len(alternatives)} alternative(s)")
        return alternatives[args.alternative]["transform"], True
    if "transform_internal" in data:
        return data["transform_internal"], True
    if "transform" not in data:
        raise CliError(f"--init {args.init}: no `transform` (a 4×4 source → target matrix) in it")
    return data["transform"], False


def _options_for_files(options, args: argparse.Namespace, source, target):
    """The guidance re-expressed from the files' coordinates into the internal frame."""
    from dataclasses import replace

    from gsa.align.contract import hints_from_files

    matrix, internal = _init_transform(args)
    try:
        if matrix is not None and not internal:
            options = replace(options, init_transform=matrix)
        options = hints_from_files(options, source.metadata.get("format", "ply"), target.metadata.get("format", "ply"))
        if matrix is not None and internal:
            options = replace(options, init_transform=matrix)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    return options


def _semantic_default() -> str:
    from gsa.settings_env import semantic_env

    try:
        return semantic_env()
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _feature_settings(args: argparse.Namespace):
    """FeatureSettings from --backbone/--head and GSA_FEATURES_* / GSA_LIFT_* (the library reads
    no environment), unless the features come from the files or the canonical frame."""
    if args.features in ("file", "canonical"):
        return None
    from gsa.features.settings import FeatureSettings
    from gsa.settings_env import feature_settings_env

    return FeatureSettings(**feature_settings_env(backbone=args.backbone, head=args.head))


# The AlignOptions fields with a flag (gsa.align.spec.OPTIONS[name].cli), in the order --help
# lists them: after --stages, --features and the extractor's weights; then the guidance group's.
CLI_OPTIONS = (
    "tau_f",
    "coarse_iterations",
    "max_candidates",
    "weight_by_opacity",
    "refine",
    "search",
    "scene",
    "seed",
    "fine_iterations",
    "fine_views",
    "fine_lr",
    "fine_image_size",
    "fine_on",
)
CLI_GUIDANCE_OPTIONS = ("fixed_scale", "rigid", "semantic", "learned", "frame_snap", "alternatives", "photo_matches")


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _dest(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_")


def add_option_argument(p, name: str, defaults) -> None:
    """The flag of option `name` as gsa.align.spec describes it: type, choices, default
    (`defaults`: an AlignOptions), help; a true/false option is a store_true flag."""
    from gsa.align.spec import LIBRARY_DEFAULT, OPTIONS

    spec = OPTIONS[name]
    cli = spec.cli
    kw: dict = {}
    if spec.kind == "bool":
        kw["action"] = "store_true"
    else:
        if spec.kind in ("int", "float"):
            kw["type"] = int if spec.kind == "int" else float
        if spec.choices:
            kw["choices"] = spec.choices
        kw["default"] = getattr(defaults, name) if cli.default is LIBRARY_DEFAULT else cli.default
    if cli.metavar:
        kw["metavar"] = cli.metavar
    p.add_argument(cli.flag or _flag(name), help=cli.help or spec.help, **kw)


def add_align_arguments(p: argparse.ArgumentParser) -> None:
    from gsa.align.pipeline import AlignOptions
    from gsa.align.spec import OPTIONS

    d = AlignOptions()
    p.add_argument("--stages", default=",".join(d.stages), help=OPTIONS["stages"].cli.help)  # a comma list
    p.add_argument(
        "--target-cameras",
        default=None,
        metavar="CAMERAS_JSON",
        help="the target's training cameras (a reconstruction's cameras.json): the fine stage "
        "renders from them instead of orbit cameras",
    )
    add_option_argument(p, "features", d)
    p.add_argument(
        "--backbone",
        "--weights",
        dest="backbone",
        default=None,
        help="DINOv2 weights: Hugging Face folder or torch.hub .pth (env GSA_FEATURES_BACKBONE)",
    )
    p.add_argument("--head", default=None, help="sphere_mapper head checkpoint (env GSA_FEATURES_HEAD)")
    for name in CLI_OPTIONS:
        add_option_argument(p, name, d)
    g = p.add_argument_group("guidance (when the automatic answer is doubtful; README 'Guided alignment')")
    g.add_argument(
        "--init", metavar="JSON", help="start from this pose (a result.json or a JSON with a 4×4 `transform`)"
    )
    g.add_argument("--alternative", type=int, metavar="N", help="with --init RESULT: start from its alternative N")
    g.add_argument(
        "--pairs", metavar="JSON", help='≥ 3 picked point pairs: {"source": [[x,y,z],…], "target": [[x,y,z],…]}'
    )
    g.add_argument("--up", metavar="X,Y,Z:X,Y,Z", help="the up vector in the source's and in the target's coordinates")
    g.add_argument(
        "--front",
        metavar="X,Y,Z:X,Y,Z",
        help="with --up: the way each model faces, in the source's and in the target's coordinates "
        "(the turns about up kept within 45° of the fronts agreeing)",
    )
    for name in CLI_GUIDANCE_OPTIONS:
        add_option_argument(g, name, d)
    g.add_argument(
        "--own-intrinsics",
        action="store_true",
        help="two image sets of one camera (by their EXIF): reconstruct each with its own estimated "
        "focal length instead of the target with the source's (shared by default: two estimates "
        "of one lens differ by ~1 %%, and so would the models' scale)",
    )


def cmd_align(args: argparse.Namespace) -> int:
    from gsa.align.outputs import result_dict, write_json, write_outputs
    from gsa.align.pipeline import align
    from gsa.io.formats import format_for_path, write_model
    from gsa.merge import merge

    options = _align_options(args)
    source = _load_model(args.source, "source", args)
    shared = None
    if not getattr(args, "own_intrinsics", False):
        from gsa.recon.calibration import Calibration

        shared = Calibration.of_model(source)  # one lens, one focal length: the models' scales agree
    target = _load_model(args.target, "target", args, calibration=shared)
    options = _options_for_files(options, args, source, target)
    cameras = None
    if args.target_cameras:
        from gsa.render.cameras import read_cameras_json

        try:
            cameras, _ = read_cameras_json(args.target_cameras)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    result = align(source, target, options, progress=ProgressPrinter(not args.quiet), target_cameras=cameras)
    data = result_dict(result, source, target)
    source_format = source.metadata.get("format", "ply")
    if args.aligned_out or args.merged_out:
        # --format, else the output name's extension, else the source's own format
        def fmt_for(path: str) -> str:
            return args.format or format_for_path(path) or source_format

        aligned = source.transformed(result.transform)
        if args.aligned_out:
            data["aligned_out"] = str(write_model(aligned, args.aligned_out, fmt_for(args.aligned_out)))
        if args.merged_out:
            merged, removed = merge(aligned, target, args.merge)
            data["merge"] = {"mode": args.merge, "removed": removed, "gaussians": len(merged)}
            data["merged_out"] = str(write_model(merged, args.merged_out, fmt_for(args.merged_out)))
            if args.merge != "concat":
                print(f"merge        {removed} duplicated Gaussians removed ({args.merge})", file=sys.stderr)
    if args.renders:
        renders = write_outputs(result, source, target, args.renders, outputs={"renders"})
        data["renders"] = sorted(str(p) for p in renders.values())
    data["inputs"] = {"source": str(args.source), "target": str(args.target)}  # `gsa view` reads them
    if args.preview:
        previews = write_outputs(result, source, target, Path(args.out).parent, outputs={"preview"})
        data["preview"] = {Path(name).stem: str(p) for name, p in previews.items()}
    write_json(data, Path(args.out))
    _print_transform(result, args.out)
    return 0


def _print_transform(result, out: str | None = None) -> None:
    t = result.transform
    m, d, v = result.metrics, result.diagnostics, result.verdict
    print(f"scale        {t.scale:.6g}")
    print(
        f"rotation     {np.array2string(t.rotation, precision=6, suppress_small=True).replace(chr(10), chr(10) + ' ' * 13)}"
    )
    print(f"quaternion   {np.array2string(t.quaternion(), precision=6)} (w, x, y, z)")
    print(f"translation  {np.array2string(t.translation, precision=6)}")
    features = (
        f", feature agreement {m['feature_agreement']:.3f} ({result.features} features)"
        if "feature_agreement" in m
        else ""  # the scene path compares no features
    )
    print(f"quality      inliers {m['inlier_fraction']:.3f}, rms residual {m['rms_residual']:.4g}{features}")
    if (d.get("scene") or {}).get("ran"):
        print(f"scene path   {d['scene']['reason']}")
    if "photo_match" in d:  # two reconstructions: whether their photos decided the pose
        pm = d["photo_match"]
        print(f"photos       {'the pose' if pm['accepted'] else 'not used'}: {pm['reason']}")
    if "confidence" in m:
        verdict = "ambiguous" if v.ambiguous else ("doubtful" if v.doubtful else "confident")
        print(
            f"confidence   {m['confidence']:.2f} ({verdict}; overlap {m.get('overlap_score', float('nan')):.3f}, "
            f"colour agreement {m.get('colour_agreement', float('nan')):.2f})"
        )
    print(f"time         {result.timings['total']:.2f} s")
    if out:
        print(f"result       {out}")
    warning = doubt_warning(result.record(), out)
    if warning:
        sys.stdout.flush()
        print(warning, file=sys.stderr, flush=True)


def _number(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _colour_mismatch_limit() -> float:
    from gsa.align.robust.poses import PoseCriteria  # lazy: the robust stage loads numba

    return PoseCriteria().colour_mismatch_limit


def doubt_warning(metrics: dict | None, out: str | None = None) -> str | None:
    """One stderr line when align() judged its own result doubtful (metrics "doubtful":
    a tie between distinct poses, or low confidence), else None. Only `.get`: results
    without these keys give None."""
    if not metrics or not metrics.get("doubtful"):
        return None
    confidence = _number(metrics.get("confidence"))
    conf = "unknown" if confidence is None else f"{confidence:.2f}"
    alternatives = [a for a in metrics.get("alternatives") or [] if isinstance(a, dict)]
    where = f'; see "alternatives" in {out or "result.json"}' if alternatives else ""
    guidance = metrics.get("guidance")
    if isinstance(guidance, dict) and isinstance(guidance.get("doubt"), str):
        return f"gsa: warning: doubtful guided alignment (confidence {conf}): {guidance['doubt']}{where}"
    if metrics.get("ambiguous") and alternatives:
        best = _number(metrics.get("score"))
        scores = [_number(a.get("score")) for a in alternatives]
        gaps = [best - v for v in scores if v is not None] if best is not None else []
        within = f" within {max(0.0, max(gaps)):.3g} of the best" if gaps else " as well as the best"
        offsets = [_number(a.get("rotation_offset_deg")) for a in alternatives]
        turned = ", ".join(f"{v:.0f}°" for v in offsets if v is not None)
        away = f", rotated {turned} away" if turned else ""
        return (
            f"gsa: warning: ambiguous alignment: {len(alternatives) + 1} poses score{within} "
            f"(confidence {conf}{away}){where}"
        )
    mismatch = _number(metrics.get("colour_mismatch"))
    why = ""
    if mismatch is not None and mismatch > _colour_mismatch_limit():
        why = f" (the two models' colours disagree at this pose, {mismatch:.1f}x their own colour noise)"
    return f"gsa: warning: low confidence ({conf}): the alignment may be wrong{why}{where}"


def add_align_parser(sub) -> None:
    """`gsa align`: the parser and its handler."""
    p = sub.add_parser("align", help="align SOURCE onto TARGET (3DGS PLY files or image sets)")
    p.add_argument(
        "source",
        help="3DGS model in any supported format (see gsa convert), or a folder / .zip of images (reconstructed first)",
    )
    p.add_argument(
        "target",
        help="3DGS model in any supported format (see gsa convert), or a folder / .zip of images (reconstructed first)",
    )
    p.add_argument("--preset", default="cpu", choices=["cpu", "gpu"], help="reconstruction preset for image sets")
    p.add_argument("--out", default="result.json", help="result JSON path (default: %(default)s)")
    p.add_argument("--aligned-out", help="write the source mapped into the target frame (format: see --format)")
    p.add_argument("--merged-out", help="write aligned source + target as one model (format: see --format)")
    p.add_argument("--renders", help="write before/after PNG renders into this folder")
    p.add_argument("--preview", action="store_true", help="write .splat previews for `gsa view` beside --out")
    p.add_argument(
        "--format",
        choices=FORMAT_CHOICES,
        help="format of --aligned-out/--merged-out (default: the output name's extension, else the source's format)",
    )
    p.add_argument(
        "--merge",
        choices=["concat", "dedup"],
        default="concat",
        help="dedup: drop Gaussians duplicated between the aligned source and the target (the more opaque stays)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    add_align_arguments(p)
    p.set_defaults(func=cmd_align)
