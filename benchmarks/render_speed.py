"""Rasterizer speed: CPU backend vs the dense pure-torch reference, forward + backward.

    python -m benchmarks.render_speed [--gaussians 50000] [--size 256] [--repeats 5]

The reference composites every pixel against every Gaussian, so at 50k Gaussians and
256x256 it would need terabytes of intermediates; it is timed on random subsets of the
same scene at the same image size and extrapolated linearly in the number of Gaussians
(its cost is exactly O(N x pixels)). The output says so.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def _scene(n: int):
    from gsa.synth import make_object

    model = make_object("car", 0, n)
    if model.features is None:
        from gsa.canonical import canonical_features

        model = model.with_features(canonical_features(model))
    return model


def _fwd_bwd(model, cams, backend: str, index=None) -> float:
    sel = slice(None) if index is None else index
    ts = [
        torch.tensor(a[sel], requires_grad=True)
        for a in (model.means, model.quats, model.log_scales, model.opacity_logits, model.sh, model.features)
    ]
    from gsa.render import rasterize

    t = time.perf_counter()
    out = rasterize(*ts, cams, background=(1.0, 1.0, 1.0), backend=backend, depth=False)
    (out.colors.sum() + out.features.sum() + out.alpha.sum()).backward()
    return time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref-subsets", type=int, nargs=2, default=[250, 500])
    args = ap.parse_args(argv)

    import numba

    from gsa.render.cameras import cameras_around

    model = _scene(args.gaussians)
    cams = cameras_around(model.means, 1, args.size, seed=3)
    print(
        f"scene: {len(model)} Gaussians, SH degree {model.sh_degree}, {model.feature_dim}-D features; "
        f"{args.size}x{args.size}, 1 camera; torch {torch.__version__}, "
        f"{torch.get_num_threads()} torch threads, {numba.get_num_threads()} numba threads"
    )
    t = time.perf_counter()
    _fwd_bwd(model, cams, "cpu")  # warm-up: loads (or compiles) the numba kernels
    print(f"cpu backend warm-up (kernel load/compile): {time.perf_counter() - t:.2f} s")
    cpu0 = time.process_time()
    cpu = sorted(_fwd_bwd(model, cams, "cpu") for _ in range(args.repeats))
    cpu_time = (time.process_time() - cpu0) / args.repeats
    cpu_med = cpu[len(cpu) // 2]
    print(
        f"cpu backend forward+backward: median {cpu_med * 1000:.1f} ms, min {cpu[0] * 1000:.1f} ms "
        f"over {args.repeats} runs; process CPU time {cpu_time * 1000:.1f} ms per run; "
        f"1-min load average {open('/proc/loadavg').read().split()[0]}"
    )

    rng = np.random.default_rng(0)
    ref = []
    for n_sub in args.ref_subsets:
        idx = np.sort(rng.choice(len(model), n_sub, replace=False))
        _fwd_bwd(model, cams, "reference", idx)
        times = sorted(_fwd_bwd(model, cams, "reference", idx) for _ in range(2))
        ref.append((n_sub, times[0]))
        print(
            f"reference (dense torch) forward+backward, {n_sub} Gaussians at {args.size}x{args.size}: "
            f"{times[0] * 1000:.0f} ms"
        )
    (n1, t1), (n2, t2) = ref
    per_g = max((t2 - t1) / (n2 - n1), t2 / n2 * 0.5)
    ref_full = t1 + per_g * (len(model) - n1)
    print(
        f"reference extrapolated linearly to {len(model)} Gaussians (NOT measured at full size: dense "
        f"intermediates would need ~{len(model) * args.size**2 * 4 * 20 / 1e12:.1f} TB): {ref_full:.1f} s"
    )
    ratio = ref_full / cpu_med
    print(f"speed-up cpu vs reference: {ratio:.0f}x (target >= 50x) -> {'OK' if ratio >= 50 else 'BELOW TARGET'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
