"""`gsa align-many MODEL… --out DIR [--reference NAME] [--merged-out FILE]`: N-way registration.

Beside its module, as `gsa render` is: building the parser imports nothing heavy.
"""

from __future__ import annotations

import glob
import json
import sys
from pathlib import Path

from gsa.errors import GSAError

MODEL_SUFFIXES = (".ply", ".splat", ".ksplat", ".spz", ".sog", ".glb")


class AlignManyError(GSAError, ValueError):
    """Input `gsa align-many` refuses (shown as one `gsa: error:` line)."""


def add_align_many_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "align-many", help="align several 3DGS models into one frame (pairwise edges + cycle-consistent global step)"
    )
    p.add_argument(
        "models",
        nargs="+",
        metavar="MODEL",
        help="3DGS files, folders of them, folders `gsa reconstruct` wrote (one model each), or glob patterns",
    )
    p.add_argument("--out", required=True, help="output folder (many.json)")
    p.add_argument("--reference", help="the model whose frame all go into (file name or stem; default: the first)")
    p.add_argument("--merged-out", help="write all models in the reference frame as one model (format by extension)")
    p.add_argument("--merge", choices=["concat", "dedup"], default="concat", help="dedup: drop duplicated Gaussians")
    p.add_argument("--edges", choices=["auto", "all", "sparse"], default="auto", help="auto: all pairs up to 8 models")
    p.add_argument("--stages", default="auto", help="align()'s stages per edge: auto, coarse or coarse,fine")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_align_many)


def expand_models(items: list[str]) -> list[Path]:
    """Files as given; a folder `gsa reconstruct` wrote: that one model (with its photo anchors);
    another folder: its model files (sorted); a pattern: its matching files and reconstruction
    folders (sorted)."""
    from gsa.recon.folder import is_reconstruction

    out: list[Path] = []
    for item in items:
        path = Path(item)
        if any(ch in item for ch in "*?["):
            matches = sorted(Path(m) for m in glob.glob(item) if Path(m).is_file() or is_reconstruction(m))
            if not matches:
                raise AlignManyError(f"{item}: no file matches")
            out += matches
        elif is_reconstruction(path):
            out.append(path)
        elif path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.name.lower().endswith(MODEL_SUFFIXES))
            if not found:
                raise AlignManyError(f"{item}: no 3DGS model files in this folder")
            out += found
        elif path.is_file():
            out.append(path)
        else:
            raise AlignManyError(f"{item}: no such file or folder")
    seen: set[Path] = set()
    unique = [p for p in out if not (p.resolve() in seen or seen.add(p.resolve()))]
    if len(unique) < 2:
        raise AlignManyError(f"align-many needs at least two models, got {len(unique)}")
    return unique


def _names(paths: list[Path]) -> list[str]:
    """File names (stems when those are distinct); paths when names clash."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    names = [p.name for p in paths]
    return names if len(set(names)) == len(names) else [str(p) for p in paths]


def _reference_index(reference: str | None, paths: list[Path], names: list[str]) -> int:
    if reference is None:
        return 0
    for k, (p, name) in enumerate(zip(paths, names)):
        if reference in (name, p.name, p.stem, str(p)):
            return k
    raise AlignManyError(f"--reference {reference}: not one of the models ({', '.join(names)})")


def cmd_align_many(args) -> int:
    from dataclasses import replace

    from gsa.align.many import align_many, merged_model
    from gsa.align.outputs import write_json
    from gsa.align.pipeline import AlignOptions
    from gsa.io.formats import format_for_path, read_model, write_model
    from gsa.recon.folder import is_reconstruction, read_reconstruction

    stages = tuple(s.strip() for s in args.stages.split(",") if s.strip())
    if args.merged_out and format_for_path(args.merged_out) is None:
        raise AlignManyError(f"--merged-out {args.merged_out}: no known model extension")
    paths = expand_models(args.models)
    names = _names(paths)
    reference = _reference_index(args.reference, paths, names)
    # a reconstruction folder with its photo anchors: two reconstructions' edges take their photos
    models = [read_reconstruction(p) if is_reconstruction(p) else read_model(p) for p in paths]
    for p, m in zip(paths, models):
        m.validate(str(p))
    options = replace(AlignOptions(), stages=stages, seed=args.seed)

    def progress(done: int, total: int) -> None:
        if not args.quiet:
            print(f"edge {done}/{total}", file=sys.stderr, flush=True)

    result = align_many(models, names, reference, options, edges=args.edges, progress=progress)
    data = result.to_dict()
    data["files"] = [str(p) for p in paths]
    out = Path(args.out)
    if args.merged_out:
        merged, removed = merged_model(models, result, args.merge)
        write_model(merged, args.merged_out, format_for_path(args.merged_out))
        data["merge"] = {"mode": args.merge, "removed": removed, "gaussians": len(merged), "path": args.merged_out}
    write_json(data, out / "many.json")
    summary = {
        "many.json": str(out / "many.json"),
        "models": {m["name"]: round(m["confidence"], 3) for m in data["models"]},
        "pruned": data["pruned"],
        "corrected": data["corrected"],
    }
    print(json.dumps(summary, indent=2))
    return 0
