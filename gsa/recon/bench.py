"""`python -m gsa.recon.bench`: the issue's measurements on a generated object.

1. 30 views at 256x256 -> reconstruct (cpu preset): views registered, camera-centre
   error after a Sim(3) fit (% of orbit radius), held-out PSNR, wall time.
2. The same object captured by a second camera rig placed in a random Sim(3) frame
   -> reconstruct -> gsa.align.pipeline.align(A, B) against the true relative Sim(3):
   T_gt = T_B^-1 ∘ rig ∘ T_A where T_X maps SfM frame X onto its true world frame.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _measure(name, syn, res) -> dict:
    from gsa.recon.sfm import centre_error

    idx = [syn.names.index(n) for n in res.sfm.names]
    err, t = centre_error(res.sfm.cameras, syn.cameras[idx])
    row = {
        "set": name,
        "views": len(syn.names),
        "registered": res.n_registered,
        "centre_error_pct_of_radius": 100 * err / syn.radius,
        "psnr_heldout_db": res.train.psnr_heldout,
        "psnr_heldout_masked_db": res.train.psnr_heldout_masked,
        "gaussians": len(res.model),
        "wall_s": res.timings["total"],
        "sfm_s": res.timings["sfm"],
        "train_s": res.timings["train"],
    }
    print(json.dumps(row), flush=True)
    return row, t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gsa.recon.bench")
    ap.add_argument("--category", default="car")
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-align", action="store_true")
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args(argv)

    from gsa.align.pipeline import AlignOptions, align
    from gsa.metrics import rre_deg, scale_error_pct
    from gsa.recon.pipeline import reconstruct
    from gsa.recon.synthetic import render_image_set, textured_object
    from gsa.synth.perturb import random_sim3

    root = Path(args.workdir or tempfile.mkdtemp(prefix="gsa-recon-bench-"))
    model = textured_object(args.category, args.seed)
    t = time.perf_counter()
    syn_a = render_image_set(root / "a", model=model, n_views=args.views, size=args.size, orbit_seed=args.seed)
    print(f"rendered {args.views} views in {time.perf_counter() - t:.1f}s -> {syn_a.directory}", flush=True)
    res_a = reconstruct(syn_a.directory, root / "a_out", preset=args.preset, iterations=args.iterations)
    row_a, t_a = _measure("A", syn_a, res_a)
    out = {"A": row_a}
    if not args.skip_align:
        rig = random_sim3(np.random.default_rng(args.seed + 100), scale_range=(0.5, 2.0), translation=2.0)
        syn_b = render_image_set(
            root / "b", model=model, n_views=args.views, size=args.size, orbit_seed=args.seed + 1, rig=rig
        )
        res_b = reconstruct(syn_b.directory, root / "b_out", preset=args.preset, iterations=args.iterations)
        row_b, t_b = _measure("B", syn_b, res_b)
        gt = t_b.inverse().compose(rig.compose(t_a))
        for feats in ("auto", "canonical"):
            t = time.perf_counter()
            r = align(res_a.model, res_b.model, AlignOptions(features=feats))
            row = {
                "align_features": r.features,
                "requested": feats,
                "rre_deg": rre_deg(r.transform.rotation, gt.rotation),
                "scale_error_pct": scale_error_pct(r.transform.scale, gt.scale),
                "align_s": time.perf_counter() - t,
            }
            print(json.dumps(row), flush=True)
            out[f"align_{feats}"] = row
        out["B"] = row_b
    (root / "bench.json").write_text(json.dumps(out, indent=1))
    print(f"results: {root / 'bench.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
