"""Render, fine-stage and training timings, CPU backend beside the CUDA backend (gsplat), on one machine.

    python -m benchmarks.cuda_speed [--out FILE.json] [--sizes 50000,200000,1000000]

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


def _image_set(n_views: int, size: int):
    """A textured generated object photographed from an orbit, in memory: images, masks,
    cameras and 3,000 of its points as the SfM cloud."""
    from gsa.recon.synthetic import textured_object
    from gsa.render import orbit_cameras, render_model

    model = textured_object("car", seed=0, n_gaussians=60_000)
    centre = model.means.mean(0)
    radius = 2.2 * float(np.percentile(np.linalg.norm(model.means - centre, axis=1), 99))
    cams = orbit_cameras(centre, radius, n_views, width=size, height=size, fov=45, seed=0)
    images, alphas = [], []
    for k in range(0, n_views, 8):
        out = render_model(model, cams[k : k + 8], features=False, background=(1.0, 1.0, 1.0), depth=False)
        images.append(out.colors.cpu().numpy())
        alphas.append(out.alpha[..., 0].cpu().numpy())
    rng = np.random.default_rng(0)
    rows = rng.choice(len(model), 3000, replace=False)
    colours = np.clip(model.sh[rows, 0] * 0.28209479177387814 + 0.5, 0, 1)
    return np.concatenate(images), np.concatenate(alphas) > 0.5, cams, model.means[rows], colours


def train_rows(backends, n_views: int, size: int, iterations: int, gpu_iterations: int):
    """Feature-augmented training (canonical features lifted halfway) on each backend with the
    `cpu` preset's settings at `size` px, then the `gpu` preset (SH 3, full resolution, up to
    1M Gaussians) on CUDA, capped at `gpu_iterations`."""
    from dataclasses import replace

    from gsa.recon.train import PRESETS, train_gaussians

    images, masks, cams, points, colours = _image_set(n_views, size)
    runs = [(b, "cpu", replace(PRESETS["cpu"], iterations=iterations, resolution=size, backend=b)) for b in backends]
    if "cuda" in backends and gpu_iterations:
        gpu = PRESETS["gpu"]
        scale = gpu_iterations / gpu.iterations
        runs.append(
            (
                "cuda",
                "gpu",
                replace(
                    gpu,
                    iterations=gpu_iterations,
                    densify_from=int(gpu.densify_from * scale),
                    densify_until=int(gpu.densify_until * scale),
                    opacity_reset_every=0,
                    backend="cuda",
                ),
            )
        )
    rows = []
    for backend, preset, cfg in runs:
        res = train_gaussians(images, masks, cams, points, colours, cfg)
        rows.append(
            {
                "what": f"training, {n_views} views {size}x{size}, preset {preset}, {cfg.iterations} iterations",
                "backend": backend,
                "total_s": res.seconds,
                "gaussians_out": len(res.model),
                "psnr_heldout_db": res.psnr_heldout,
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
    ap.add_argument("--train-views", type=int, default=24)
    ap.add_argument("--train-size", type=int, default=256)
    ap.add_argument("--train-iterations", type=int, default=1000)
    ap.add_argument("--gpu-preset-iterations", type=int, default=3000, help="0: skip the gpu preset row")
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
    rows: list[dict] = []

    def save() -> None:  # after each part: a run cut short keeps what it measured
        if args.out:
            with open(args.out, "w") as f:
                json.dump({"machine": info, "rows": rows}, f, indent=1)

    rows += render_rows([int(s) for s in args.sizes.split(",")], backends, args.repeat)
    save()
    rows += fine_rows(args.fine_gaussians, backends, [int(s) for s in args.fine_sizes.split(",")])
    save()
    if args.train_iterations:
        rows += train_rows(
            backends, args.train_views, args.train_size, args.train_iterations, args.gpu_preset_iterations
        )
        save()


if __name__ == "__main__":
    main()
