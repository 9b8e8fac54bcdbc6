"""A cancel in the semantic stage stops within one renderer kernel: the stage's renders
and lifting passes call the job's progress callback between the CPU renderer's steps
(gsa.render.steps), not only after each renderer call. One view of a 3M-Gaussian model is one
call of seconds; here a small model is split the way a 3M one is (one view a call, the lifting's
channels in groups), and every kernel launch is counted against the reports around it."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import gsa.render.cpu as cpu
import gsa.render.cpu.composite as composite
from gsa.align import semantic
from gsa.kernels import KERNEL_LOCK
from gsa.render.steps import between_steps, step
from gsa.synth import make_object
from tests.tiny_vit import tiny_vit

KERNELS = ("_footprints", "_depth_order", "_bin", "_pack", "_forward", "_backward", "_reduce")


@pytest.fixture
def events(monkeypatch):
    """Every CPU kernel launch appended as ("kernel", name); the stage's split made that of a
    3M-Gaussian model (one view a renderer call, the lifting's 9 values in groups of 3 or 4: 3 passes a view)."""
    log: list[tuple[str, object]] = []

    def counted(name, kernel):
        def run(*args, **kwargs):
            log.append(("kernel", name))
            return kernel(*args, **kwargs)

        return run

    for name in KERNELS:
        monkeypatch.setattr(composite, name, counted(name, getattr(composite, name)))
    for name in ("covariance_cpu", "project_cpu"):
        monkeypatch.setattr(cpu, name, counted(name, getattr(cpu, name)))
    monkeypatch.setattr(semantic, "VIEW_GAUSSIANS_PER_CALL", 1)
    monkeypatch.setattr(semantic, "LIFT_VIEW_GAUSSIANS_PER_CALL", 1)
    monkeypatch.setattr(semantic, "LIFT_VALUES_PER_PASS", 6000)
    monkeypatch.setattr(semantic, "MODEL_VIEWS", semantic.ModelViewCache())
    return log


CRITERIA = semantic.SemanticCriteria(views=3, rolls=1, batch=3, components=8, lift_size=64)


def _models():
    return make_object("chair", seed=2, n_gaussians=2000), make_object("chair", seed=3, n_gaussians=1500)


def test_the_semantic_stage_reports_between_every_two_kernels_of_its_renders(events):
    """Between two reports of the stage at most one kernel runs: a cancelled job (the service's
    callback raises at a report) waits for one kernel, not for a whole view or lifting pass.
    The reports' fractions still only grow, and the features are those lifted without the
    callback (the same kernels on the same data)."""
    source, target = _models()
    backbone = tiny_vit()

    def progress(stage, fraction):
        events.append(("report", fraction))

    lifted = semantic.lifted_features(source, target, backbone, CRITERIA, progress=progress)
    kernels = [name for kind, name in events if kind == "kernel"]
    assert kernels.count("_backward") == 2 * 3 * 3  # each model's 3 views x 3 groups of its 9 values
    assert kernels.count("_forward") == 2 * 3 + 2 * 3 * 3  # the views, and the lifting passes
    since, longest = 0, 0
    for kind, _ in events:
        since = since + 1 if kind == "kernel" else 0
        longest = max(longest, since)
    assert longest <= 1, f"{longest} kernels ran between two reports"
    fractions = [f for kind, f in events if kind == "report"]
    assert fractions == sorted(fractions)

    semantic.MODEL_VIEWS.clear()
    quiet = semantic.lifted_features(source, target, backbone, CRITERIA)  # no callback: no step reports
    for (f, w), (g, v) in zip(lifted, quiet):
        assert np.array_equal(f, g) and np.array_equal(w, v)


@pytest.mark.parametrize("at", ["render", "lifting"])
def test_a_callback_that_raises_within_a_render_stops_it_there(events, at):
    """The first report inside a renderer call (a view's render, or a lifting pass's backward)
    that raises unwinds the stage: no kernel runs after it, and the kernel lock is free for
    the service's other job threads."""
    source, target = _models()

    class Cancelled(Exception):
        pass

    armed = [False]

    def progress(stage, fraction):
        if armed[0]:
            raise Cancelled()
        events.append(("report", fraction))

    def arm_at_kernel(name):
        kernel = getattr(composite, name)

        def run(*args, **kwargs):
            armed[0] = True  # the cancel arrives while this kernel runs
            return kernel(*args, **kwargs)

        return run

    target_kernel = "_depth_order" if at == "render" else "_backward"
    composite_kernel = getattr(composite, target_kernel)
    setattr(composite, target_kernel, arm_at_kernel(target_kernel))
    try:
        with pytest.raises(Cancelled):
            semantic.lifted_features(source, target, tiny_vit(), CRITERIA, progress=progress)
    finally:
        setattr(composite, target_kernel, composite_kernel)
    last = [name for kind, name in events if kind == "kernel"][-1]
    assert last == target_kernel  # nothing ran after the kernel the cancel came in
    free = []

    def take_the_lock():
        free.append(KERNEL_LOCK.acquire(timeout=5))
        if free[-1]:
            KERNEL_LOCK.release()

    other = threading.Thread(target=take_the_lock)
    other.start()
    other.join()
    assert free == [True]


def test_between_steps_is_per_thread_and_restores_the_outer_callback():
    calls = []
    with between_steps(lambda: calls.append("outer")):
        step()
        with between_steps(None):  # None keeps the callback installed
            step()
        with between_steps(lambda: calls.append("inner")):
            step()
            other = threading.Thread(target=step)  # another thread's renders report nothing here
            other.start()
            other.join()
        step()
    step()
    assert calls == ["outer", "outer", "inner", "outer"]
