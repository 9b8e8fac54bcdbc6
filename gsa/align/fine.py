"""Fine alignment (paper Sec. 3.4, Alg. 4): refine a Sim(3) by inverse rendering.

Minimises the multi-view feature-consistency loss between Rend_f(T·G1, C_k) and
Rend_f(G2, C_k) with Adam. Differences from the authors' code, on purpose:
  * parameters are an so(3) increment (exp map), a log-scale and a translation
    around the initial transform (no Euler angles, no linear scale);
  * rotation and scale act about the target centroid and the translation is in
    units of the target's extent, so one learning rate suits any object size;
  * T is applied to the cameras (Rend(T·G, C) = Rend(G, C·T)), so the source's
    covariances, SH and features are never recomputed, and SH of any degree stays exact;
  * the learning rate decays exponentially to lr * lr_decay (1.0 = the paper's constant lr),
    which lets the best-loss iterate settle to a small fraction of a degree.
The target's renders are computed once; the best-loss parameters are kept.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from gsa.align.choices import FineLoss, FineSignal, RenderBackend
from gsa.canonical import canonical_features
from gsa.model import GaussianModel
from gsa.render import covariance, locality_order, render_gaussians, resolve_backend
from gsa.render.cameras import Cameras, cameras_around
from gsa.sim3 import Sim3

LOSSES: tuple[FineLoss, ...] = ("smooth_l1", "l1", "l2")
# Pixels rendered between two progress calls. Views are rendered in chunks of about this many
# pixels, so a progress callback that stops the work (e.g. a cancelled service job raising from
# it) is heard within about one chunk's forward or backward pass, however many and large the views.
PIXELS_PER_REPORT = 1 << 20


@dataclass
class FineOptions:
    iterations: int = 60
    lr: float = 0.01
    lr_decay: float = 0.1  # final lr = lr * lr_decay (exponential schedule); 1.0 keeps it constant
    views: int = 5
    image_size: int = 128
    loss: FineLoss = "smooth_l1"
    on: FineSignal = "features"  # colors: paper Table 4 ablation
    keep_best: bool = True
    alpha_threshold: float = 0.1  # a pixel is foreground where either render's alpha exceeds this
    seed: int = 0
    backend: RenderBackend = "auto"

    def validate(self) -> None:
        if self.iterations < 0:
            raise ValueError("iterations must be >= 0")
        if not self.lr > 0 or not 0 < self.lr_decay <= 1:
            raise ValueError("lr must be > 0 and lr_decay in (0, 1]")
        if self.views < 1 or self.image_size < 8:
            raise ValueError("need views >= 1 and image_size >= 8")
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if self.on not in ("features", "colors"):
            raise ValueError(f"on must be 'features' or 'colors', got {self.on!r}")


@dataclass
class FineResult:
    transform: Sim3
    initial_transform: Sim3
    loss_history: list[float]  # loss at the parameters of iteration 0..iterations (0 = init)
    best_loss: float
    best_iteration: int
    cameras: Cameras
    timings: dict = field(default_factory=dict)  # seconds: total_s, setup_s, loop_s, per_iteration_s

    @property
    def timing(self) -> dict:
        """The former name of `timings`."""
        return self.timings

    @property
    def initial_loss(self) -> float:
        return self.loss_history[0] if self.loss_history else float("nan")

    def to_dict(self) -> dict:
        return {
            "transform": self.transform.to_dict(),
            "initial_transform": self.initial_transform.to_dict(),
            "loss_history": list(self.loss_history),
            "best_loss": self.best_loss,
            "best_iteration": self.best_iteration,
            "views": len(self.cameras),
            "timings": dict(self.timings),
        }


def _signal(model: GaussianModel, on: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(features, sh) to render for `model`."""
    if on == "colors":
        return None, model.sh
    if model.features is not None:
        return model.features, None
    return np.asarray(canonical_features(model), np.float32), None


def select_cameras(target: GaussianModel, options: FineOptions, cameras: Cameras | None) -> Cameras:
    """`options.views` evenly spaced cameras of `cameras`, else orbit cameras around the target."""
    if cameras is None:
        return cameras_around(target.means, options.views, options.image_size, seed=options.seed)
    if len(cameras) > options.views:
        idx = np.round(np.linspace(0, len(cameras) - 1, options.views)).astype(int)
        cameras = cameras[idx]
    scale = options.image_size / max(cameras.width, cameras.height)
    return cameras.resized(max(1, round(cameras.width * scale)), max(1, round(cameras.height * scale)))


def _loss(kind: str, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    if a.numel() == 0:
        return a.sum()  # no foreground: zero loss, zero gradient
    if kind == "smooth_l1":
        return torch.nn.functional.smooth_l1_loss(a, b)
    if kind == "l1":
        return (a - b).abs().mean()
    return ((a - b) ** 2).mean()


def _so3_exp(omega: torch.Tensor) -> torch.Tensor:
    zero = omega.new_zeros(())
    k = torch.stack([zero, -omega[2], omega[1], omega[2], zero, -omega[0], -omega[1], omega[0], zero]).reshape(3, 3)
    return torch.linalg.matrix_exp(k)


def fine_align(
    source: GaussianModel,
    target: GaussianModel,
    init: Sim3,
    options: FineOptions | None = None,
    cameras: Cameras | None = None,
    progress: Callable[[str, float], None] | None = None,
) -> FineResult:
    """Refine `init` (source -> target) by multi-view feature (or colour) consistency.

    cameras: the target's training cameras if known (any image size; `options.views` evenly
    spaced ones are used at `options.image_size`), else orbit cameras around the target.
    progress(stage, fraction) is called as the work advances (before the target renders, after
    every chunk of views rendered forward and before its backward pass, every iteration; see
    PIXELS_PER_REPORT); an exception it raises stops the stage and propagates.
    """
    options = options or FineOptions()
    options.validate()
    source.validate("source")
    target.validate("target")
    t_start = time.perf_counter()
    backend = resolve_backend(options.backend)
    if backend == "cpu":
        # the source is rendered every iteration: store neighbours together for the CPU kernels
        source = source.subset(locality_order(source.means))
    feat_s, sh_s = _signal(source, options.on)
    feat_t, sh_t = _signal(target, options.on)
    if feat_s is not None and feat_s.shape[1] != feat_t.shape[1]:
        raise ValueError(f"feature dimensions differ: source {feat_s.shape[1]}, target {feat_t.shape[1]}")
    cams = select_cameras(target, options, cameras)
    render = dict(backend=backend)
    # The native kernels use every core; torch only does small elementwise work here, and its
    # idle OpenMP threads spinning between ops compete with them for the cores. Restored below.
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fine_align(source, target, init, options, cams, render, feat_s, sh_s, feat_t, sh_t, progress, t_start)
    finally:
        torch.set_num_threads(torch_threads)


def _covariance(model: GaussianModel, backend: str) -> torch.Tensor:
    return covariance(torch.as_tensor(model.quats), torch.as_tensor(model.log_scales), backend)


def _view_chunks(n_views: int, width: int, height: int) -> list[slice]:
    step = max(1, PIXELS_PER_REPORT // max(1, width * height))
    return [slice(i, min(i + step, n_views)) for i in range(0, n_views, step)]


def _render_views(means, cov, opacity, viewmats, intr, cams, signal, render, chunks, report):
    """(image, alpha) of every view, rendered chunk by chunk with report() after each chunk and,
    when gradients flow, again before each chunk's backward pass."""

    def before_backward(grad):
        report()

    images, alphas = [], []
    for sl in chunks:
        out = render_gaussians(means, cov, opacity, viewmats[sl], intr[sl], cams.width, cams.height, **signal, **render)
        image = out.features if signal["features"] is not None else out.colors
        if report is not None and image.requires_grad:
            image.register_hook(before_backward)
        images.append(image)
        alphas.append(out.alpha)
        if report is not None:
            report()
    if len(chunks) == 1:
        return images[0], alphas[0]
    return torch.cat(images), torch.cat(alphas)


def _fine_align(source, target, init, options, cams, render, feat_s, sh_s, feat_t, sh_t, progress, t_start):
    chunks = _view_chunks(len(cams), cams.width, cams.height)
    report_setup = None if progress is None else (lambda: progress("fine", 0.0))
    if report_setup is not None:
        report_setup()
    # fixed target renders
    with torch.no_grad():
        vm_t = torch.as_tensor(cams.viewmats, dtype=torch.float32)
        intr = torch.as_tensor(cams.intrinsics, dtype=torch.float32)
        sig_t = dict(
            sh=None if sh_t is None else torch.as_tensor(sh_t),
            features=None if feat_t is None else torch.as_tensor(feat_t),
        )
        target_cov = _covariance(target, render["backend"])
        img_t, alpha_t = _render_views(
            torch.as_tensor(target.means),
            target_cov,
            torch.sigmoid(torch.as_tensor(target.opacity_logits)),
            vm_t,
            intr,
            cams,
            sig_t,
            render,
            chunks,
            report_setup,
        )
        fg_t = alpha_t[..., 0] > options.alpha_threshold
        means_s = torch.as_tensor(source.means)
        cov_s = _covariance(source, render["backend"])
        op_s = torch.sigmoid(torch.as_tensor(source.opacity_logits))
        sig_s = dict(
            sh=None if sh_s is None else torch.as_tensor(sh_s),
            features=None if feat_s is None else torch.as_tensor(feat_s),
        )

    center = torch.as_tensor(target.means.astype(np.float64).mean(0))
    extent = float(np.percentile(np.linalg.norm(target.means - target.means.mean(0), axis=1), 90)) or 1.0
    s0, r0 = torch.tensor(init.scale, dtype=torch.float64), torch.as_tensor(init.rotation)
    t0 = torch.as_tensor(init.translation)
    w_world = torch.as_tensor(cams.viewmats)  # (C,4,4) float64

    omega = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    log_s = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    tau = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([omega, log_s, tau], lr=options.lr)
    gamma = options.lr_decay ** (1.0 / max(1, options.iterations - 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)

    def current() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # x -> c + e^{ls} exp(ω) (s0 R0 x + t0 - c) + extent τ
        rot = _so3_exp(omega) @ r0
        sc = s0 * torch.exp(log_s[0])
        tr = center + torch.exp(log_s[0]) * (_so3_exp(omega) @ (t0 - center)) + extent * tau
        return sc, rot, tr

    history: list[float] = []
    best = (float("inf"), 0, (init.scale, init.rotation, init.translation))
    t_loop = time.perf_counter()
    for it in range(options.iterations + 1):
        sc, rot, tr = current()
        m = torch.eye(4, dtype=torch.float64)
        m = torch.cat([torch.cat([sc * rot, tr[:, None]], 1), m[3:]], 0)
        vm = (w_world @ m).to(torch.float32)
        report = None
        if progress is not None:
            done = it / max(1, options.iterations)

            def report(done=done):
                progress("fine", min(done, 1.0))

        with torch.set_grad_enabled(it < options.iterations):
            img_s, alpha_s = _render_views(means_s, cov_s, op_s, vm, intr, cams, sig_s, render, chunks, report)
            mask = (alpha_s[..., 0].detach() > options.alpha_threshold) | fg_t
            loss = _loss(options.loss, img_s[mask], img_t[mask])
        value = float(loss.detach())
        history.append(value)
        if value < best[0]:
            best = (value, it, (float(sc.detach()), rot.detach().numpy().copy(), tr.detach().numpy().copy()))
        if it == options.iterations:
            break
        opt.zero_grad()
        if loss.requires_grad:
            loss.backward()
        opt.step()
        sched.step()
        if progress is not None:
            progress("fine", (it + 1) / max(1, options.iterations))
    if options.keep_best:
        transform = Sim3(*best[2])
        best_loss, best_it = best[0], best[1]
    else:
        transform = Sim3(float(sc.detach()), rot.detach().numpy(), tr.detach().numpy())
        best_loss, best_it = history[-1], len(history) - 1
    t_end = time.perf_counter()
    timings = {
        "total_s": t_end - t_start,
        "setup_s": t_loop - t_start,
        "loop_s": t_end - t_loop,
        "per_iteration_s": (t_end - t_loop) / max(1, options.iterations),
    }
    return FineResult(transform, init, history, best_loss, best_it, cams, timings)
