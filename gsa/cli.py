"""`gsa` command line: align, demo, synth, bench, and the service verbs.

Over 400 lines on purpose: the parser and handlers of the core verbs in the one module the
`gsa` entry point imports (its start-up is measured, python -m gsa.bench.cli_speed); verbs that belong
to a subpackage already live beside it (render, lift, reconstruct, the service's).

Every failure the user can cause ends as one line on stderr and a non-zero
exit code, never a traceback.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import json
import os
import sys
import warnings
from collections.abc import Sequence
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np

from gsa.errors import GSAError

EXIT_FAILED = 1
# gsa.io.formats.FORMATS, spelled out so building the parser imports nothing (a test checks they agree)
FORMAT_CHOICES = ("ply", "compressed-ply", "splat", "ksplat", "spz", "sog", "glb")


class CliError(GSAError):
    """An error to show as one line."""


class _LazyChoices(Sequence):
    """argparse `choices` read from a module on first use (validation, help), so that
    building the parser does not import it (gsa.synth for `gsa align`)."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name
        self._values: tuple | None = None

    def _load(self) -> tuple:
        if self._values is None:
            self._values = tuple(getattr(importlib.import_module(self.module), self.name))
        return self._values

    def __getitem__(self, index):
        return self._load()[index]

    def __len__(self) -> int:
        return len(self._load())

    def __repr__(self) -> str:
        return repr(self._load())


def _lazy_choices(action: argparse.Action, module: str, name: str) -> None:
    """Set after add_argument, which formats (so iterates) any choices it is given."""
    action.choices = _LazyChoices(module, name)


class ProgressPrinter:
    """Stage and percentage on stderr: rewritten in place on a terminal, a line
    per stage change (and per 25%) otherwise so logs stay short."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.last: tuple[str, int] | None = None

    def __call__(self, stage: str, fraction: float) -> None:
        if not self.enabled:
            return
        pct = int(fraction * 100)
        if self.tty:
            sys.stderr.write(f"\r{stage:<12} {pct:3d}%")
            if stage == "done":
                sys.stderr.write("\n")
            sys.stderr.flush()
            return
        bucket = pct // 25
        if self.last is None or self.last[0] != stage or self.last[1] != bucket:
            print(f"[gsa] {stage} {pct}%", file=sys.stderr, flush=True)
            self.last = (stage, bucket)


def _load_model(path: str, role: str = "model", args: argparse.Namespace | None = None):
    """A 3DGS file in any supported format, or an image set (folder or .zip) reconstructed first."""
    from gsa.io.formats import read_model

    p = Path(path)
    if p.is_dir() or p.suffix.lower() == ".zip":
        try:
            from gsa.recon.pipeline import reconstruct
        except ImportError as exc:
            raise CliError(f"{path}: image sets need the recon extra (pip install 'gsa[recon]'): {exc}") from None
        out = Path(args.out).parent / f"recon_{role}" if args is not None else Path(f"recon_{role}")
        preset = getattr(args, "preset", "cpu")
        print(f"[gsa] reconstructing {role} from {path} into {out} (preset {preset})", file=sys.stderr)
        return reconstruct(p, out, preset=preset, progress=ProgressPrinter(not getattr(args, "quiet", False))).model
    return read_model(p)


def _align_options(args: argparse.Namespace):
    from gsa.align.pipeline import AlignOptions

    fields = {
        "stages": tuple(s.strip() for s in args.stages.split(",") if s.strip()),
        "features": args.features,
        "feature_settings": _feature_settings(args),
        "tau_f": args.tau_f,
        "coarse_iterations": args.iterations,
        "max_candidates": args.max_candidates,
        "weight_by_opacity": args.weight_by_opacity,
        "seed": args.seed,
        "refine": args.refine,
        "search": args.search,
        "scene": args.scene,
    }
    for name in ("fine_iterations", "fine_views", "fine_lr", "fine_image_size", "fine_on"):
        value = getattr(args, name, None)
        if value is not None:
            fields[name] = value
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
    """--pairs / --up / --scale in each file's own coordinates (converted once the files are
    read, gsa.align.contract.hints_from_files); --init is resolved in `_init_transform`."""
    fields: dict = {}
    if getattr(args, "pairs", None):
        data = _read_json_arg(args.pairs, "--pairs")
        if not isinstance(data, dict) or "source" not in data or "target" not in data:
            raise CliError(f'--pairs {args.pairs}: expected {{"source": [[x, y, z], …], "target": [[x, y, z], …]}}')
        fields["point_pairs"] = (data["source"], data["target"])
    if getattr(args, "up", None):
        try:
            fields["up_axes"] = tuple(tuple(float(x) for x in part.split(",")) for part in args.up.split(":"))
        except ValueError:
            raise CliError(f"--up {args.up}: expected X,Y,Z:X,Y,Z (source up : target up)") from None
        if len(fields["up_axes"]) != 2:
            raise CliError(f"--up {args.up}: expected X,Y,Z:X,Y,Z (source up : target up)")
    if getattr(args, "scale", None) is not None:
        fields["fixed_scale"] = args.scale
    return fields


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


def _feature_settings(args: argparse.Namespace):
    """FeatureSettings from --backbone/--head and GSA_FEATURES_* / GSA_LIFT_* (the library reads
    no environment), unless the features come from the files or the canonical frame."""
    if args.features in ("file", "canonical"):
        return None
    from gsa.features.settings import FeatureSettings
    from gsa.settings_env import feature_settings_env

    return FeatureSettings(**feature_settings_env(backbone=args.backbone, head=args.head))


def add_align_arguments(p: argparse.ArgumentParser) -> None:
    from gsa.align.pipeline import FEATURE_MODES, AlignOptions

    d = AlignOptions()
    p.add_argument(
        "--stages",
        default=",".join(d.stages),
        help="auto, coarse or coarse,fine (default: %(default)s = coarse,fine unless the "
        "nearest-neighbour refinement ran, see README)",
    )
    p.add_argument(
        "--target-cameras",
        default=None,
        metavar="CAMERAS_JSON",
        help="the target's training cameras (a reconstruction's cameras.json): the fine stage "
        "renders from them instead of orbit cameras",
    )
    p.add_argument(
        "--features",
        default=d.features,
        choices=list(FEATURE_MODES),
        help="auto: the files' own features when both have them, else the configured extractor "
        "(GSA_FEATURES_EXTRACTOR + weights), else canonical; spheremap/dinov2 lift 2D features first",
    )
    p.add_argument(
        "--backbone",
        "--weights",
        dest="backbone",
        default=None,
        help="DINOv2 weights: Hugging Face folder or torch.hub .pth (env GSA_FEATURES_BACKBONE)",
    )
    p.add_argument("--head", default=None, help="sphere_mapper head checkpoint (env GSA_FEATURES_HEAD)")
    p.add_argument("--tau-f", type=float, default=d.tau_f, help="feature distance threshold τ_f")
    p.add_argument("--iterations", type=int, default=d.coarse_iterations, help="coarse iteration limit")
    p.add_argument(
        "--max-candidates", type=int, default=d.max_candidates, help="feature candidates kept per source Gaussian"
    )
    p.add_argument("--weight-by-opacity", action="store_true", help="weight correspondences by opacity")
    p.add_argument(
        "--refine",
        default=d.refine,
        choices=["auto", "on", "off"],
        help="nearest-neighbour ICP after the feature stage (auto: with canonical features)",
    )
    p.add_argument(
        "--search",
        default=d.search,
        choices=["auto", "global", "frames"],
        help="coarse initialisation without learned features: global (robust SO(3) search on "
        "floater-free anchors, overlap and colour scored), frames (one canonical frame per "
        "model, the earlier default); auto: global unless --refine off",
    )
    p.add_argument(
        "--scene",
        default=d.scene,
        choices=["auto", "on", "off"],
        help="the scene path for rooms and sites (more anchors, no frame relabellings, "
        "exposure-normalised colours, bounded refinement clouds); auto: when both models "
        "pass the scene test (README, 'Scenes'); result metrics.scene says whether it ran and why",
    )
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--fine-iterations", type=int, default=None)
    p.add_argument("--fine-views", type=int, default=None)
    p.add_argument("--fine-lr", type=float, default=None)
    p.add_argument("--fine-image-size", type=int, default=None)
    p.add_argument("--fine-on", choices=["features", "colors"], default=None)
    g = p.add_argument_group("guidance (when the automatic answer is doubtful; README 'Guided alignment')")
    g.add_argument(
        "--init", metavar="JSON", help="start from this pose (a result.json or a JSON with a 4×4 `transform`)"
    )
    g.add_argument("--alternative", type=int, metavar="N", help="with --init RESULT: start from its alternative N")
    g.add_argument(
        "--pairs", metavar="JSON", help='≥ 3 picked point pairs: {"source": [[x,y,z],…], "target": [[x,y,z],…]}'
    )
    g.add_argument("--up", metavar="X,Y,Z:X,Y,Z", help="the up vector in the source's and in the target's coordinates")
    g.add_argument("--scale", type=float, metavar="S", help="fix the scale of the answer")


def cmd_align(args: argparse.Namespace) -> int:
    from gsa.align.outputs import result_dict, write_json, write_outputs
    from gsa.align.pipeline import align
    from gsa.io.formats import format_for_path, write_model
    from gsa.merge import merge

    options = _align_options(args)
    source = _load_model(args.source, "source", args)
    target = _load_model(args.target, "target", args)
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
    m = result.metrics
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
    if (m.get("scene") or {}).get("ran"):
        print(f"scene path   {m['scene']['reason']}")
    if "confidence" in m:
        verdict = "ambiguous" if m.get("ambiguous") else ("doubtful" if m.get("doubtful") else "confident")
        print(
            f"confidence   {m['confidence']:.2f} ({verdict}; overlap {m.get('overlap_score', float('nan')):.3f}, "
            f"colour agreement {m.get('colour_agreement', float('nan')):.2f})"
        )
    print(f"time         {result.timings['total']:.2f} s")
    if out:
        print(f"result       {out}")
    warning = doubt_warning(m, out)
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


def cmd_demo(args: argparse.Namespace) -> int:
    """Generate a pair with a known Sim(3), align it, print the error."""
    from gsa.align.outputs import write_outputs
    from gsa.align.pipeline import AlignOptions, align
    from gsa.io.ply import read_ply, write_ply
    from gsa.metrics import accuracy
    from gsa.synth import make_object, random_sim3

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    truth = random_sim3(rng)  # App. C: up to 180° per axis, up to 10× scale
    print(f"== GSA demo: a generated {args.category}, two independent samplings, a random Sim(3)")
    source = make_object(
        args.category,
        seed=args.seed,
        n_gaussians=args.gaussians,
        sample_seed=args.seed + 1000,
        floaters=0.02,
        sh_degree=3,
    )
    target = make_object(
        args.category, seed=args.seed, n_gaussians=args.gaussians, sample_seed=args.seed, sh_degree=3
    ).transformed(truth)
    write_ply(source, out / "source.ply")
    write_ply(target, out / "target.ply")
    print(f"source       {out / 'source.ply'} ({len(source)} Gaussians)")
    print(f"target       {out / 'target.ply'} ({len(target)} Gaussians)")
    print(
        f"true Sim(3)  scale {truth.scale:.6g}, rotation {np.degrees(np.arccos(np.clip((np.trace(truth.rotation) - 1) / 2, -1, 1))):.2f}°, "
        f"translation {np.array2string(truth.translation, precision=4)}"
    )
    # Align the files as a user would, so the demo exercises the readers too.
    src_file, dst_file = read_ply(out / "source.ply"), read_ply(out / "target.ply")
    options = AlignOptions(stages=tuple(args.stages.split(",")), seed=args.seed)
    result = align(src_file, dst_file, options, progress=ProgressPrinter(not args.quiet))
    acc = accuracy(result.transform, truth, src_file.means, dst_file.means)
    extra = {"ground_truth": {**truth.to_dict(), "accuracy": acc}}
    outputs = {"result", "aligned", "merged"}
    write_outputs(result, src_file, dst_file, out, outputs=outputs, extra=extra)
    print("== recovered Sim(3)")
    _print_transform(result, str(out / "result.json"))
    print("== error against the known truth")
    print(f"RRE          {acc['rre_deg']:.4f}°")
    print(f"scale error  {acc['scale_error_pct']:.4f} %")
    print(f"ATE          {acc['ate']:.4g} ({acc['ate_normalized'] * 100:.4f} % of the target's bounding-box diagonal)")
    print(f"outputs      {out / 'aligned.ply'}, {out / 'merged.ply'}")
    ok = acc["rre_deg"] < 2.0 and acc["scale_error_pct"] < 2.0
    print("== " + ("aligned" if ok else "ALIGNMENT FAILED"))
    return 0 if ok else EXIT_FAILED


def cmd_synth(args: argparse.Namespace) -> int:
    from gsa.io.ply import write_ply
    from gsa.synth import make_object, random_sim3

    model = make_object(
        args.category,
        seed=args.seed,
        n_gaussians=args.gaussians,
        sample_seed=args.sample_seed,
        floaters=args.floaters,
        sh_degree=args.sh_degree,
    )
    if args.perturb:
        truth = random_sim3(np.random.default_rng(args.seed))
        model = model.transformed(truth)
        if args.truth_out:
            Path(args.truth_out).write_text(json.dumps(truth.to_dict(), indent=2))
    write_ply(model, args.out)
    print(f"{args.out}: {len(model)} Gaussians ({args.category}, seed {args.seed})")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from gsa.io.formats import MAX_SH_DEGREE, format_for_path, read_model, write_model

    fmt = args.format or format_for_path(args.output)
    if fmt is None:
        raise CliError(f"{args.output}: no known extension; name the output format with --format")
    model = read_model(args.input)
    path = write_model(model, args.output, fmt, sh_degree=args.sh_degree)
    wanted = model.sh_degree if args.sh_degree is None else args.sh_degree
    if wanted > MAX_SH_DEGREE[fmt]:
        print(f"gsa: note: {fmt} stores SH up to degree {MAX_SH_DEGREE[fmt]}; higher bands dropped", file=sys.stderr)
    print(f"{path}: {len(model)} Gaussians, {model.metadata['format']} -> {fmt}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from gsa.bench.peers import PEERS
    from gsa.bench.protocols import run_protocols

    names = {"all": list(PEERS), "default": None, "none": []}
    peers = names[args.peers] if args.peers in names else [p for p in args.peers.split(",") if p]
    return run_protocols(args.protocols, quick=args.quick, out=args.out, seed=args.seed, peers=peers, data=args.data)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gsa", description="Gaussian Splatting Alignment (GSA)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

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

    p = sub.add_parser("convert", help="convert a 3DGS file between formats (sniffed from the bytes)")
    p.add_argument("input", help="ply, compressed PLY, .splat, .ksplat, .spz, .sog or .glb (KHR_gaussian_splatting)")
    p.add_argument("output")
    p.add_argument("--format", choices=FORMAT_CHOICES, help="output format (default: from the output's extension)")
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], help="truncate or zero-pad SH to this degree")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("demo", help="align generated example data with a known answer")
    p.add_argument("--out", default="out/demo")
    _lazy_choices(p.add_argument("--category", default="car"), "gsa.synth", "CATEGORIES")
    p.add_argument("--gaussians", type=int, default=50_000)
    p.add_argument("--stages", default="auto", help="auto, coarse or coarse,fine (as gsa align)")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("synth", help="write a generated object as a 3DGS PLY")
    _lazy_choices(p.add_argument("category"), "gsa.synth", "CATEGORIES")
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int, default=0, help="which instance")
    p.add_argument("--sample-seed", type=int, default=None, help="where its Gaussians fall")
    p.add_argument("--gaussians", type=int, default=20_000)
    p.add_argument("--floaters", type=float, default=0.0)
    p.add_argument("--sh-degree", type=int, default=0, choices=[0, 1, 2, 3])
    p.add_argument("--perturb", action="store_true", help="apply a random Sim(3) (App. C protocol)")
    p.add_argument("--truth-out", help="with --perturb: write the applied Sim(3) as JSON")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("bench", help="run benchmark protocols and print tables")
    p.add_argument("protocols", nargs="*", default=["dup", "same", "speed"])
    p.add_argument("--quick", action="store_true", help="small sizes, a few minutes")
    p.add_argument("--out", default="out/bench", help="folder for the JSON results")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--data",
        help="category-real: a folder of <category>_<i>.npz meshes (V, F, optional C); real: a folder of 3DGS captures; "
        "site: SfM point files (.npz with means3d, colors; default ../shared/data/real-dev)",
    )
    p.add_argument(
        "--peers", default="default", help="comma list of icp,open3d,splatreg, or default (icp,open3d), all, none"
    )
    p.set_defaults(func=cmd_bench)

    _add_module_commands(sub)
    return parser


def _add_module_commands(sub) -> None:
    """Commands defined beside their modules; the service verbs only with the service extra."""
    from gsa.align.many_command import add_align_many_parser
    from gsa.features.command import add_lift_parser
    from gsa.recon.command import add_reconstruct_parser
    from gsa.render.command import add_render_parser
    from gsa.viewer.command import add_view_parser

    add_render_parser(sub)
    add_lift_parser(sub)
    add_reconstruct_parser(sub)
    add_view_parser(sub)
    add_align_many_parser(sub)
    # Verbs of other packages (the service's `serve`, `worker`, `submit`, ...) come through
    # the "gsa.commands" entry point group: service/ depends on gsa/, never the reverse.
    for entry in entry_points(group="gsa.commands"):
        try:
            add_parsers = entry.load()
        except ImportError:  # that package's extra is not installed
            continue
        add_parsers(sub)


def _use_workqueue_threads() -> None:
    """numba's workqueue threading layer unless NUMBA_THREADING_LAYER says otherwise, as
    gsa.render.cpu and the service worker already choose. The default GNU OpenMP layer
    spin-waits in its barriers, which makes alignments markedly slower and erratic when other
    work shares the cores.
    Must be set before the first kernel launches the threads; later it has no effect
    (gsa.render.cpu's own setting came too late after the coarse kernels), and after
    numba's import the environment variable is no longer read (the service worker's
    setdefault came too late under `gsa worker`, which then skipped its warm-up)."""
    if "NUMBA_THREADING_LAYER" in os.environ:
        return
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.THREADING_LAYER = "workqueue"
    else:
        os.environ["NUMBA_THREADING_LAYER"] = "workqueue"


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A reader's warning (gsa.io.ply.ReaderWarning: what it changed to read a file) as one
    `gsa: warning:` line; any other warning as Python shows it."""
    ply = sys.modules.get("gsa.io.ply")
    reader_warning = getattr(ply, "ReaderWarning", None) if ply is not None else None
    if isinstance(reader_warning, type) and issubclass(category, reader_warning):
        print(f"gsa: warning: {message}", file=sys.stderr, flush=True)
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def main(argv: list[str] | None = None) -> int:
    # argv None: this is the `gsa` process itself (console script, python -m gsa.cli).
    program = argv is None
    parser = build_parser()
    args = parser.parse_args(argv)
    if program:  # process-wide settings: not for a caller's process (tests call main(argv))
        _use_workqueue_threads()
        # The imported modules (numpy, scipy, numba: ~70k objects) live until exit: keep
        # the garbage collector from walking them again in every full collection.
        gc.freeze()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("gsa: interrupted", file=sys.stderr)
        return 130
    except (GSAError, ValueError) as exc:  # the library's errors; a ValueError: an argument refused
        print(f"gsa: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except OSError as exc:
        print(f"gsa: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_FAILED
    finally:
        if program:
            # Exit without the interpreter's final collections over that heap: they cost
            # 0.2-0.3 s after an alignment (numba's target context). Nothing of ours waits
            # for them: outputs are written and closed, atexit handlers still run.
            gc.freeze()


if __name__ == "__main__":
    sys.exit(main())
