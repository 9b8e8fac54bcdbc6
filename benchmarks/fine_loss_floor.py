"""Where the fine stage's loss has its minimum, on the two-samplings ("same") protocol.

For each pair: the default coarse result (feature stage + NN refinement), then the
minimum of the rendered loss (colours or re-anchored canonical features, full images)
found by Levenberg-Marquardt over the 7 Sim(3) parameters from that start, and the loss
at the true transform. If the minimiser lands farther from the truth than the coarse
result, no optimiser of that loss can improve on coarse: the loss itself is the limit.

    python -m benchmarks.fine_loss_floor [--views 5] [--size 128] [--pairs 4] [--on colors]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from benchmarks.protocols import same_pairs
from gsa.align.pipeline import AlignOptions, align
from gsa.canonical import canonical_features
from gsa.metrics import rre_deg, scale_error_pct
from gsa.render import render_model
from gsa.render.cameras import cameras_around
from gsa.sim3 import Sim3


def _around(init: Sim3, p: np.ndarray, center: np.ndarray, extent: float) -> Sim3:
    """The fine stage's parametrisation: rotation/scale about the target centre, translation in extents."""
    r = Rotation.from_rotvec(p[:3]).as_matrix()
    e = float(np.exp(p[3]))
    return Sim3(init.scale * e, r @ init.rotation, center + e * (r @ (init.translation - center)) + extent * p[4:7])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.fine_loss_floor")
    ap.add_argument("--views", type=int, default=5)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--on", choices=["colors", "features"], default="colors")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    print(
        "| pair | coarse RRE (°) | loss minimiser RRE (°) | coarse scale err (%) | minimiser scale err (%) "
        "| loss at coarse | at minimiser | at truth | s |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for label, make in same_pairs(False, 0)[: args.pairs]:
        source, target, truth = make()
        result = align(source, target, AlignOptions(stages=("coarse",)))
        coarse = result.transform
        cams = cameras_around(target.means, args.views, args.size, seed=0)
        features = args.on == "features"
        if features:  # as the pipeline's fine stage: the target's frame, source re-anchored at coarse
            frame = result.target_frame
            source = source.with_features(canonical_features(coarse.apply(source.means.astype(np.float64)), frame))
            target = target.with_features(canonical_features(target.means.astype(np.float64), frame))

        def image(model, sim3=None):
            out = render_model(model, cams, features=features, depth=False, sim3=sim3, background=(0, 0, 0))
            return (out.features if features else out.colors).numpy()

        goal = image(target)
        center = target.means.astype(np.float64).mean(0)
        extent = float(np.percentile(np.linalg.norm(target.means - center, axis=1), 90))

        def residual(p):
            return (image(source, _around(coarse, p, center, extent)) - goal).ravel()

        t = time.perf_counter()
        sol = least_squares(residual, np.zeros(7), diff_step=1e-4, x_scale=1e-3, max_nfev=40, method="lm")
        seconds = time.perf_counter() - t
        best = _around(coarse, sol.x, center, extent)
        loss = [
            float(np.mean(np.abs(residual(np.zeros(7))))),
            float(np.mean(np.abs(residual(sol.x)))),
            float(np.mean(np.abs(image(source, truth) - goal))),
        ]
        row = [
            rre_deg(coarse.rotation, truth.rotation),
            rre_deg(best.rotation, truth.rotation),
            scale_error_pct(coarse.scale, truth.scale),
            scale_error_pct(best.scale, truth.scale),
        ]
        rows.append(row)
        print(
            f"| {label} | "
            + " | ".join(f"{v:.4f}" for v in row)
            + " | "
            + " | ".join(f"{v:.6f}" for v in loss)
            + f" | {seconds:.1f} |",
            flush=True,
        )
    mean = np.mean(rows, 0)
    print("| mean | " + " | ".join(f"{v:.4f}" for v in mean) + " | | | | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
