"""The native CPU rasterizer against the dense torch reference and against finite differences."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gsa.model import GaussianModel
from gsa.render import Cameras, orbit_cameras, rasterize, render_gaussians, render_model
from gsa.render.projection import covariance_3d
from tests.render_scenes import random_scene


def _cams(n=3, w=40, h=32, seed=1):
    return orbit_cameras(np.zeros(3), 3.0, n, width=w, height=h, fov=60, seed=seed)


KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh", "features")


def _render_and_grads(scene, cams, backend, dtype=torch.float64, **kw):
    ts = {k: torch.tensor(scene[k], dtype=dtype, requires_grad=True) for k in KEYS}
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=dtype, requires_grad=True)
    vm = torch.tensor(cams.viewmats, dtype=dtype, requires_grad=True)
    out = rasterize(
        ts["means"],
        ts["quats"],
        ts["log_scales"],
        ts["opacity_logits"],
        ts["sh"],
        ts["features"],
        cams,
        background=bg,
        feature_background=(0.1, -0.2, 0.0),
        backend=backend,
        viewmats=vm,
        **kw,
    )
    imgs = [out.colors, out.features, out.alpha, out.depth]
    rng = np.random.default_rng(7)
    loss = sum((im * torch.tensor(rng.normal(size=im.shape), dtype=dtype)).sum() for im in imgs)
    loss.backward()
    grads = {k: t.grad for k, t in ts.items()}
    grads["background"] = bg.grad
    grads["viewmats"] = vm.grad
    return [im.detach() for im in imgs], grads


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_values_and_gradients_match_reference(sh_degree):
    scene = random_scene(70, sh_degree, seed=sh_degree)
    cams = _cams()
    ref_imgs, ref_grads = _render_and_grads(scene, cams, "reference")
    cpu_imgs, cpu_grads = _render_and_grads(scene, cams, "cpu")
    assert ref_imgs[2].max() > 0.5, "scene should cover part of the image"
    for name, a, b in zip(("colors", "features", "alpha", "depth"), ref_imgs, cpu_imgs):
        assert a.shape == b.shape
        np.testing.assert_allclose(b.numpy(), a.numpy(), rtol=1e-9, atol=1e-9, err_msg=name)
    for name, g in ref_grads.items():
        assert g is not None and torch.isfinite(g).all(), name
        assert g.abs().max() > 0, f"reference gradient for {name} is identically zero"
        np.testing.assert_allclose(cpu_grads[name].numpy(), g.numpy(), rtol=1e-7, atol=1e-8, err_msg=name)


def test_float32_close_to_float64_reference():
    scene = random_scene(50, 1, seed=3)
    cams = _cams(2)
    ref_imgs, ref_grads = _render_and_grads(scene, cams, "reference")
    cpu_imgs, cpu_grads = _render_and_grads(scene, cams, "cpu", dtype=torch.float32)
    for a, b in zip(ref_imgs, cpu_imgs):
        np.testing.assert_allclose(b.numpy(), a.numpy(), atol=2e-4 * max(1.0, float(a.abs().max())))
    for name, g in ref_grads.items():
        scale = float(g.abs().max())
        np.testing.assert_allclose(cpu_grads[name].numpy(), g.numpy(), atol=2e-3 * scale + 1e-6, err_msg=name)


def test_cpu_gradients_match_finite_differences():
    """gradcheck of the native backward (float64): no autograd inside the kernels."""
    scene = random_scene(8, 0, seed=11, dim=2)
    scene["opacity_logits"] = np.clip(scene["opacity_logits"], -1.0, 1.5)  # stay below the 0.99 clamp
    scene["log_scales"] = np.log(np.random.default_rng(2).uniform(0.2, 0.4, size=(8, 3)))
    cams = orbit_cameras(np.zeros(3), 3.0, 2, width=14, height=12, fov=60, seed=4)
    colors = np.random.default_rng(5).uniform(size=(8, 3))
    vm0 = torch.tensor(cams.viewmats)
    w = [
        torch.tensor(np.random.default_rng(9).normal(size=s))
        for s in [(2, 12, 14, 3), (2, 12, 14, 2), (2, 12, 14, 1), (2, 12, 14, 1)]
    ]

    def f(means, quats, log_scales, logits, cols, feats, vm_delta):
        vm = vm0 + torch.nn.functional.pad(vm_delta, (0, 0, 0, 1))
        out = rasterize(
            means, quats, log_scales, logits, cols, feats, cams, background=(0.3, 0.1, 0.2), backend="cpu", viewmats=vm
        )
        return sum((im * wi).sum() for im, wi in zip((out.colors, out.features, out.alpha, out.depth), w))

    inputs = [torch.tensor(scene[k], requires_grad=True) for k in ("means", "quats", "log_scales", "opacity_logits")]
    inputs += [
        torch.tensor(colors, requires_grad=True),
        torch.tensor(scene["features"], requires_grad=True),
        torch.zeros(2, 3, 4, dtype=torch.float64, requires_grad=True),
    ]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_sim3_gradient_through_cameras_equals_through_model():
    """Rend(T·G, C) = Rend(G, C·T): same images and same gradient w.r.t. (ω, log s, t)."""
    scene = random_scene(40, 0, seed=5)
    cams = _cams(2)
    r0 = torch.tensor(Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix())

    def params():
        return (
            torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64, requires_grad=True),
            torch.tensor(0.2, dtype=torch.float64, requires_grad=True),
            torch.tensor([0.1, 0.2, -0.1], dtype=torch.float64, requires_grad=True),
        )

    def transform(omega, log_s, t):
        k = torch.zeros(3, 3, dtype=torch.float64)
        k = k.index_put(
            (torch.tensor([2, 1, 0, 2, 1, 0]), torch.tensor([1, 2, 2, 0, 0, 1])),
            torch.stack([omega[0], -omega[0], omega[1], -omega[1], omega[2], -omega[2]]),
        )
        return torch.linalg.matrix_exp(k) @ r0, torch.exp(log_s), t

    def quat_of(rot):
        # rotation matrix -> wxyz (rot is far from 180°)
        w = torch.sqrt(1 + rot[0, 0] + rot[1, 1] + rot[2, 2]) / 2
        return torch.stack(
            [w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w), (rot[1, 0] - rot[0, 1]) / (4 * w)]
        )

    def qmul(a, b):
        aw, ax, ay, az = a.unbind(-1)
        bw, bx, by, bz = b.unbind(-1)
        return torch.stack(
            [
                aw * bw - ax * bx - ay * by - az * bz,
                aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx,
                aw * bz + ax * by - ay * bx + az * bw,
            ],
            -1,
        )

    p1 = params()
    rot, s, t = transform(*p1)
    m = torch.tensor(scene["means"])
    out1 = rasterize(
        s * m @ rot.T + t,
        qmul(quat_of(rot)[None], torch.tensor(scene["quats"])),
        torch.tensor(scene["log_scales"]) + torch.log(s),
        scene["opacity_logits"],
        torch.tensor(scene["sh"]),
        torch.tensor(scene["features"]),
        cams,
        backend="cpu",
    )
    (out1.features.sum() + out1.colors.sum()).backward()

    p2 = params()
    rot, s, t = transform(*p2)
    tm = torch.eye(4, dtype=torch.float64)
    tm = torch.cat([torch.cat([s * rot, t[:, None]], 1), tm[3:]], 0)
    vm = torch.tensor(cams.viewmats) @ tm
    out2 = rasterize(
        torch.tensor(scene["means"]),
        scene["quats"],
        torch.tensor(scene["log_scales"]),
        scene["opacity_logits"],
        torch.tensor(scene["sh"]),
        torch.tensor(scene["features"]),
        cams,
        backend="cpu",
        viewmats=vm,
    )
    (out2.features.sum() + out2.colors.sum()).backward()
    np.testing.assert_allclose(out2.features.detach().numpy(), out1.features.detach().numpy(), atol=1e-9)
    for a, b in zip(p1, p2):
        assert a.grad.abs().max() > 0
        np.testing.assert_allclose(b.grad.numpy(), a.grad.numpy(), rtol=1e-6, atol=1e-8)


def test_result_does_not_depend_on_tile_size():
    scene = random_scene(60, 2, seed=8)
    cams = _cams(2, 37, 29)
    ts = [torch.tensor(scene[k], dtype=torch.float64) for k in KEYS]
    cov = covariance_3d(ts[1], ts[2])
    outs = [
        render_gaussians(
            ts[0],
            cov,
            torch.sigmoid(ts[3]),
            torch.tensor(cams.viewmats),
            torch.tensor(cams.intrinsics),
            cams.width,
            cams.height,
            sh=ts[4],
            features=ts[5],
            backend="cpu",
            tile=tile,
        )
        for tile in (8, 16, 32)
    ]
    for o in outs[1:]:
        np.testing.assert_allclose(o.colors.numpy(), outs[0].colors.numpy(), atol=1e-12)
        np.testing.assert_allclose(o.alpha.numpy(), outs[0].alpha.numpy(), atol=1e-12)


def test_orbit_cameras_look_at_center_opencv_convention():
    cams = orbit_cameras([1.0, 2.0, 3.0], 4.0, 6, width=64, height=48, fov=60, seed=3)
    assert len(cams) == 6 and cams.width == 64 and cams.height == 48
    np.testing.assert_allclose(np.linalg.norm(cams.centers() - [1, 2, 3], axis=1), 4.0)
    p = cams.viewmats[:, :3, :3] @ np.array([1.0, 2.0, 3.0]) + cams.viewmats[:, :3, 3]
    np.testing.assert_allclose(p[:, :2], 0, atol=1e-9)  # centre on the optical axis
    assert (p[:, 2] > 0).all()  # in front (z forward)
    # a single Gaussian at the centre lands in the middle of every image
    model = GaussianModel.from_colors(
        np.array([[1.0, 2.0, 3.0]]), np.array([[1.0, 0.0, 0.0]]), scales=np.full((1, 3), 0.05)
    )
    out = render_model(model, cams, features=False, background=(0, 0, 0), backend="cpu")
    a = out.alpha[..., 0].numpy()
    for img in a:
        y, x = np.unravel_index(np.argmax(img), img.shape)
        assert abs(x + 0.5 - 32) <= 1 and abs(y + 0.5 - 24) <= 1


def test_bad_input_raises_value_error():
    scene = random_scene(5, 0, seed=1)
    cams = _cams(1, 16, 16)
    with pytest.raises(ValueError):
        rasterize(
            np.zeros((0, 3)),
            np.zeros((0, 4)),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros((0, 1, 3)),
            None,
            cams,
            backend="cpu",
        )
    with pytest.raises(ValueError):
        rasterize(
            scene["means"],
            scene["quats"],
            scene["log_scales"],
            scene["opacity_logits"],
            scene["sh"],
            np.zeros((4, 3)),
            cams,
            backend="cpu",
        )
    with pytest.raises(ValueError):
        rasterize(
            scene["means"],
            scene["quats"],
            scene["log_scales"],
            scene["opacity_logits"],
            scene["sh"],
            None,
            cams,
            backend="nope",
        )
    with pytest.raises(ValueError):
        Cameras(np.eye(4)[None], -1.0, 1.0, 0, 0, 8, 8)


def test_concurrent_renders_from_threads_agree():
    """Service workers may render from several threads; kernels are serialised, results identical."""
    from concurrent.futures import ThreadPoolExecutor

    scene = random_scene(200, 0, seed=4)
    cams = _cams(2, 48, 48)

    def job(_):
        ts = [torch.tensor(scene[k], requires_grad=(k == "means")) for k in KEYS]
        out = rasterize(*ts, cams, backend="cpu")
        out.features.sum().backward()
        return out.colors.detach().numpy(), ts[0].grad.numpy()

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(job, range(8)))
    for colors, grad in results[1:]:
        np.testing.assert_array_equal(colors, results[0][0])
        np.testing.assert_array_equal(grad, results[0][1])


def test_locality_order_groups_neighbours_and_leaves_renders_unchanged():
    from gsa.render.cpu import locality_order
    from tests.render_scenes import blob_object

    model = blob_object(4000, seed=3)
    shuffled = model.subset(np.random.default_rng(0).permutation(len(model)))
    order = locality_order(shuffled.means)
    assert np.array_equal(np.sort(order), np.arange(len(model)))
    step = lambda p: np.linalg.norm(np.diff(p, axis=0), axis=1).mean()  # noqa: E731
    assert step(shuffled.means[order]) < 0.2 * step(shuffled.means)
    cams = orbit_cameras(np.zeros(3), 3.0, 3, width=48, height=40, fov=50, seed=2)
    a = render_model(shuffled, cams, backend="cpu")
    b = render_model(shuffled.subset(order), cams, backend="cpu")
    for name in ("colors", "features", "alpha", "depth"):
        np.testing.assert_allclose(getattr(b, name).numpy(), getattr(a, name).numpy(), atol=1e-5, err_msg=name)
