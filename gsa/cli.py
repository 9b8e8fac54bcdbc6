"""`gsa` command line: the parser, demo, synth, convert, bench, and the process-wide set-up.

Verbs that belong to a subpackage live beside it (align: gsa.align.command; align-many, render,
lift, reconstruct, view, and the service's through the "gsa.commands" entry points); what they
share is gsa.cli_base. The entry point's start-up is measured (python -m benchmarks.cli_speed).

Every failure the user can cause ends as one line on stderr and a non-zero
exit code, never a traceback.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import json
import sys
import warnings
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np

from gsa.align.command import _print_transform, add_align_parser
from gsa.cli_base import EXIT_FAILED, FORMAT_CHOICES, CliError, ProgressPrinter, VectorArgumentParser, lazy_choices
from gsa.errors import GSAError


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


def _benchmarks(module: str):
    """benchmarks.<module>: the benchmarks live beside gsa/ in a checkout of the repository and are
    not part of the installed package. Looked up by name (the library never imports them:
    tests/test_import_graph.py); an editable install maps only gsa and service, so the checkout
    gsa was imported from is put on the path."""
    checkout = Path(__file__).resolve().parents[1]
    if (checkout / "benchmarks" / "__init__.py").is_file() and str(checkout) not in sys.path:
        sys.path.insert(0, str(checkout))
    try:
        return importlib.import_module(f"benchmarks.{module}")
    except ModuleNotFoundError as exc:
        if exc.name != "benchmarks":
            raise
        raise CliError(
            "gsa bench runs from a checkout of the repository (its benchmarks/ folder is not part of the "
            "installed package): clone it, install it with pip install -e ., and run gsa bench there"
        ) from None


def cmd_bench(args: argparse.Namespace) -> int:
    run_protocols = _benchmarks("protocols").run_protocols
    names = {"all": list(_benchmarks("peers").PEERS), "default": None, "none": []}
    peers = names[args.peers] if args.peers in names else [p for p in args.peers.split(",") if p]
    return run_protocols(args.protocols, quick=args.quick, out=args.out, seed=args.seed, peers=peers, data=args.data)


def build_parser() -> argparse.ArgumentParser:
    from gsa import __version__

    parser = VectorArgumentParser(prog="gsa", description="Gaussian Splatting Alignment (GSA)")
    parser.add_argument("--version", action="version", version=f"gsa {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    add_align_parser(sub)

    p = sub.add_parser("convert", help="convert a 3DGS file between formats (sniffed from the bytes)")
    p.add_argument("input", help="ply, compressed PLY, .splat, .ksplat, .spz, .sog or .glb (KHR_gaussian_splatting)")
    p.add_argument("output")
    p.add_argument("--format", choices=FORMAT_CHOICES, help="output format (default: from the output's extension)")
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], help="truncate or zero-pad SH to this degree")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("demo", help="align generated example data with a known answer")
    p.add_argument("--out", default="out/demo")
    lazy_choices(p.add_argument("--category", default="car"), "gsa.synth", "CATEGORIES")
    p.add_argument("--gaussians", type=int, default=50_000)
    p.add_argument("--stages", default="auto", help="auto, coarse or coarse,fine (as gsa align)")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("synth", help="write a generated object as a 3DGS PLY")
    lazy_choices(p.add_argument("category"), "gsa.synth", "CATEGORIES")
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
        "site: SfM point files (.npz with means3d, colors; default ../shared/data/real-dev); "
        "guided: optional, category-real's meshes added to its generated pairs",
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
    from gsa.align.orient_command import add_orient_parser
    from gsa.features.command import add_lift_parser
    from gsa.recon.command import add_reconstruct_parser
    from gsa.render.command import add_render_parser
    from gsa.viewer.command import add_view_parser

    add_render_parser(sub)
    add_lift_parser(sub)
    add_reconstruct_parser(sub)
    add_view_parser(sub)
    add_align_many_parser(sub)
    add_orient_parser(sub)
    # Verbs of other packages (the service's `serve`, `worker`, `submit`, ...) come through
    # the "gsa.commands" entry point group: service/ depends on gsa/, never the reverse.
    for entry in entry_points(group="gsa.commands"):
        try:
            add_parsers = entry.load()
        except ImportError:  # that package's extra is not installed
            continue
        add_parsers(sub)


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
        # numba's workqueue threading layer (gsa.kernels): the default GNU OpenMP layer
        # spin-waits in its barriers, which makes alignments markedly slower and erratic when
        # other work shares the cores. Before any command imports numba: the environment
        # variable is read at numba's import.
        from gsa.kernels import use_workqueue_layer

        use_workqueue_layer()
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
