"""Leave-category-out: for each fold, train the head without the fold's categories and measure
those categories (training.evaluate); every category is measured by a head that never saw it.

    python -m training.loco --tokens /work/train-data/tokens.npz --meshes /work/train-data/meshes \
        --out /work/train-data/loco --epochs 6
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gsa.features.nocs import save_head
from training.evaluate import evaluate
from training.train_head import train

# Folds of categories, each mixing the development categories, those like the maintainers'
# held-out ones and the rest, so that no fold leaves out most of one kind.
FOLDS = (
    ("airplane", "bathtub", "dog", "spider"),
    ("chair", "bottle", "horse", "guitar"),
    ("mug", "desktop", "human", "tree"),
    ("toilet", "gun", "dolphin", "vase"),
    ("bench", "piano", "hand"),
    ("car", "rifle", "table"),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tokens", required=True)
    ap.add_argument("--meshes", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--folds", default="", help="fold numbers to run (default all), comma separated")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = dict(np.load(args.tokens))
    index = json.loads((Path(args.meshes) / "index.json").read_text())
    chosen = [int(f) for f in args.folds.split(",") if f] or range(len(FOLDS))
    for k in chosen:
        left = FOLDS[k]
        mask = ~np.isin(data["category"], left)
        print(f"fold {k}: leaving out {', '.join(left)} ({mask.sum()} views to train on)", flush=True)
        head = train(data, mask, args.epochs, args.seed, log=lambda m: print("  " + m, flush=True))
        path = save_head(head, out / f"fold{k}.pt", {"left_out_categories": list(left), "epochs": args.epochs})
        summary = evaluate(
            args.meshes, [e for e in index if e["category"] in left], path, args.seed, log=lambda m: None
        )
        (out / f"fold{k}.json").write_text(json.dumps(summary, indent=1))
        for cat, s in summary.items():
            print(f"  {cat:10s} {json.dumps(s)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
