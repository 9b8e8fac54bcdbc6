"""Fine alignment: recovers a known Sim(3) from a slightly wrong start."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsa.align.fine import FineOptions, fine_align
from gsa.sim3 import Sim3
from tests.render_scenes import blob_object

GT = Sim3(1.3, Rotation.from_euler("xyz", [40, -70, 120], degrees=True).as_matrix(), np.array([0.5, -0.2, 0.3]))


def _errors(est: Sim3):
    cos = (np.trace(est.rotation @ GT.rotation.T) - 1) / 2
    return (
        np.degrees(np.arccos(np.clip(cos, -1, 1))),
        abs(est.scale / GT.scale - 1),
        float(np.linalg.norm(est.translation - GT.translation)),
    )


@pytest.fixture(scope="module")
def pair():
    src = blob_object(2500, seed=0)
    return src, src.transformed(GT)


def _init():
    pert = Sim3(
        1.05, Rotation.from_rotvec(np.radians(5) * np.array([0.6, 0.8, 0.0])).as_matrix(), np.array([0.06, -0.05, 0.04])
    )
    return pert @ GT


def test_fine_reduces_rotation_scale_translation_error(pair):
    src, tgt = pair
    init = _init()
    r0, s0, t0 = _errors(init)
    res = fine_align(src, tgt, init, FineOptions(image_size=64))
    r1, s1, t1 = _errors(res.transform)
    assert r1 < r0 / 5 and s1 < s0 / 5 and t1 < t0 / 5, (r0, s0, t0, r1, s1, t1)
    assert len(res.loss_history) == 61
    assert res.best_loss == min(res.loss_history) < res.loss_history[0] / 10
    assert len(res.cameras) == 5 and res.cameras.width == 64
    assert res.timings["total_s"] > 0


def test_colour_ablation_runs_and_improves(pair):
    src, tgt = pair
    init = _init()
    res = fine_align(src, tgt, init, FineOptions(on="colors", image_size=64, iterations=30, loss="l1"))
    assert res.best_loss < res.loss_history[0]
    assert _errors(res.transform)[0] < _errors(init)[0]


def test_progress_callback_and_cancellation(pair):
    src, tgt = pair
    calls = []
    fine_align(
        src,
        tgt,
        _init(),
        FineOptions(iterations=4, image_size=32, views=2),
        progress=lambda stage, frac: calls.append((stage, frac)),
    )
    assert {c[0] for c in calls} == {"fine"}
    fractions = [c[1] for c in calls]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
    assert all(f in fractions for f in (0.25, 0.5, 0.75))

    class Cancelled(Exception):
        pass

    def cancel(stage, frac):
        raise Cancelled()

    with pytest.raises(Cancelled):
        fine_align(src, tgt, _init(), FineOptions(iterations=4, image_size=32, views=2), progress=cancel)


def test_keep_best_returns_init_when_init_is_exact(pair):
    src, tgt = pair
    res = fine_align(src, tgt, GT, FineOptions(iterations=5, image_size=48, views=3, loss="l2"))
    assert res.best_iteration == 0
    np.testing.assert_allclose(res.transform.matrix(), GT.matrix(), atol=1e-9)


def test_bad_input(pair):
    src, tgt = pair
    with pytest.raises(ValueError):
        fine_align(src, tgt.with_features(np.zeros((len(tgt), 5), np.float32)), GT, FineOptions(iterations=1))
    with pytest.raises(ValueError):
        fine_align(src, tgt, GT, FineOptions(loss="huber"))
    with pytest.raises(ValueError):
        fine_align(src, tgt, GT, FineOptions(on="depth"))


def test_progress_within_an_iteration_per_chunk_of_views(pair, monkeypatch):
    """Views are rendered in chunks of PIXELS_PER_REPORT pixels with a progress call after each
    chunk and before each chunk's backward pass, so a callback that raises (a cancelled job) stops
    the stage within one chunk, not one iteration; the result is the same as in one batch."""
    import gsa.align.fine as fine

    src, tgt = pair
    opts = FineOptions(iterations=3, image_size=32, views=4)
    whole = fine_align(src, tgt, _init(), opts)
    monkeypatch.setattr(fine, "PIXELS_PER_REPORT", 2 * 32 * 32)  # 2 views a chunk: 2 chunks
    calls = []
    chunked = fine_align(src, tgt, _init(), opts, progress=lambda stage, frac: calls.append(frac))
    np.testing.assert_allclose(chunked.loss_history, whole.loss_history, rtol=1e-5)
    np.testing.assert_allclose(chunked.transform.matrix(), whole.transform.matrix(), atol=1e-6)
    # Before the first iteration ends: 1 at the start, 2 target chunks, 2 forward and 2 backward.
    assert calls.index(1 / 3) == 1 + 2 + 2 + 2

    class Cancelled(Exception):
        pass

    seen = []

    def cancel_in_backward(stage, frac):
        seen.append(frac)
        if len(seen) == 6:  # the first chunk's backward pass of iteration 0
            raise Cancelled()

    with pytest.raises(Cancelled):
        fine_align(src, tgt, _init(), opts, progress=cancel_in_backward)
    assert seen == [0.0] * 6
