"""Render and fine-stage timings, CPU backend beside the CUDA backend (gsplat), on one machine.

    python -m gsa.bench.cuda_speed [--out FILE.json] [--sizes 50000,200000,1000000]

Needs a CUDA device and gsplat for the CUDA rows (without them it prints the CPU rows only).
Each figure is the median of `--repeat` timed runs after one warm-up run; CUDA times are taken
after torch.cuda.synchronize(). The images come back to the CPU in both cases (the backends'
common contract), so the CUDA figures include that copy.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def _timed(fn, repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        t = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def render_rows(sizes, backends, repeat):
    from gsa.render import orbit_cameras, rasterize
    from gsa.synth import make_object

    rows = []
    for n in sizes:
        model = make_object("car", seed=1, n_gaussians=n)
        cams = orbit_cameras(model.means.mean(0), 3.0, 5, width=256, height=256, fov=50, seed=0)
        feats = np.random.default_rng(0).uniform(size=(n, 3)).astype(np.float32)
        for backend in backends:
            params = [
                torch.tensor(a, dtype=torch.float32, requires_grad=True)
                for a in (model.means, model.quats, model.log_scales, model.opacity_logits, model.sh[:, :1], feats)
            ]

            def forward(params=params, backend=backend, cams=cams):
                with torch.no_grad():
                    rasterize(*params, cams, backend=backend, depth=False)

            def forward_backward(params=params, backend=backend, cams=cams):
                out = rasterize(*params, cams, backend=backend, depth=False)
                (out.colors.sum() + out.features.sum()).backward()

            rows.append(
                {
                    "what": "render 5 views 256x256 (colour + 3 features)",
                    "gaussians": n,
                    "backend": backend,
                    "forward_s": _timed(forward, repeat),
                    "forward_backward_s": _timed(forward_backward, repeat),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def fine_rows(n, backends, image_sizes):
    from gsa.align.fine import FineOptions, fine_align
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    truth = Sim3(1.5, Rotation.from_euler("xyz", [30, -50, 100], degrees=True).as_matrix(), np.array([0.3, -0.2, 0.1]))
    src = make_object("car", seed=2, n_gaussians=n)
    tgt = src.transformed(truth)
    pert = Sim3(1.03, Rotation.from_rotvec(np.radians(3) * np.array([0.6, 0.8, 0.0])).as_matrix(), np.zeros(3))
    rows = []
    for size in image_sizes:
        for backend in backends:
            res = fine_align(src, tgt, pert @ truth, FineOptions(image_size=size, backend=backend))
            cos = (np.trace(res.transform.rotation @ truth.rotation.T) - 1) / 2
            rows.append(
                {
                    "what": f"fine stage, 60 iterations, 5 views {size}x{size}",
                    "gaussians": n,
                    "backend": backend,
                    "total_s": res.timings["total_s"],
                    "per_iteration_s": res.timings["per_iteration_s"],
                    "rre_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="50000,200000,1000000")
    ap.add_argument("--fine-gaussians", type=int, default=100_000)
    ap.add_argument("--fine-sizes", default="128,512")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    from gsa.render import cuda_available

    backends = ["cpu"] + (["cuda"] if cuda_available() else [])
    info = {
        "cpu": platform.processor() or platform.machine(),
        "cpu_threads": torch.get_num_threads(),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "torch": torch.__version__,
    }
    print(json.dumps(info), flush=True)
    rows = render_rows([int(s) for s in args.sizes.split(",")], backends, args.repeat)
    rows += fine_rows(args.fine_gaussians, backends, [int(s) for s in args.fine_sizes.split(",")])
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": info, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
