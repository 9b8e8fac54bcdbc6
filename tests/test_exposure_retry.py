"""gsa.align.exposure_retry: a doubtful answer aligned again in the exposure its close pairs give."""

from dataclasses import replace

import numpy as np

from gsa.align import exposure_retry, robust
from gsa.align.pipeline import align
from gsa.align.types import AlignOptions
from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object
from gsa.synth.variants import shift_exposure

GAIN = np.array([0.5, 0.55, 0.45])  # a stop darker, a little warmer


def _pair(n: int = 3000):
    truth = Sim3(2.0, axis_rotation(np.array([0.3, 1.0, 0.2]), 2.0), np.array([0.5, -1.0, 2.0]))
    source = shift_exposure(make_object("car", seed=3, n_gaussians=n, sample_seed=1), GAIN)
    target = make_object("car", seed=3, n_gaussians=n, sample_seed=2).transformed(truth)
    return source, target, truth


def _palettes_blind() -> AlignOptions:
    """Options under which no pose-free gain passes match_exposure (as on a room's greys and
    browns): a gain must explain more of the palettes than there is."""
    opts = AlignOptions()
    pose = opts.criteria.pose
    palette = replace(pose.palette, exposure_explains=1.01)
    return replace(opts, criteria=replace(opts.criteria, pose=replace(pose, palette=palette)))


def _turned(pose: Sim3, deg: float) -> Sim3:
    turn = axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(deg))
    return Sim3(pose.scale, turn @ pose.rotation, pose.translation)


def _gain(source, target, result, opts):
    n = opts.anchor_count
    return exposure_retry.gain_to_try(robust.anchors(source, n), robust.anchors(target, n), result, opts)


def _doubtful(result, transform: Sim3):
    result.transform = transform
    result.set_record(result.record() | {"doubtful": True})
    return result


def test_pose_gain_reads_the_exposure_where_the_pose_pairs_the_same_surfaces():
    a = robust.anchors(make_object("car", seed=3, n_gaussians=8000, sample_seed=1))
    b = robust.anchors(shift_exposure(make_object("car", seed=3, n_gaussians=8000, sample_seed=2), GAIN))
    gain = robust.pose_gain(b, a, b.points, 0.05)  # the identity pose: the same surfaces
    assert np.allclose(gain, 1 / GAIN, rtol=0.1)
    assert robust.pose_gain(b, a, b.points + 10 * a.radius, 0.05) is None  # nothing pairs


def test_a_doubtful_answer_off_the_truth_is_aligned_again_in_its_exposure():
    source, target, truth = _pair()
    opts = _palettes_blind()
    first = align(source, target, opts)
    wrong = _turned(first.transform, 20.0)
    first = _doubtful(first, wrong)
    gain = _gain(source, target, first, opts)
    # even 20° off, the answer's pairs read the source's exposure (the source onto the target)
    assert gain is not None and np.allclose(gain, 1 / GAIN, rtol=0.15)
    result = exposure_retry.retried(source, target, opts, first, lambda shifted: align(shifted, target, opts))
    report = result.record()["exposure_retry"]
    assert report["kept"] == "second" and report["second_score"] > report["first_score"]
    assert rre_deg(result.transform.rotation, truth.rotation) < 2.0
    # the answer it replaced is offered
    offered = [a for a in result.record()["alternatives"] if a["origin"] == exposure_retry.FIRST]
    assert len(offered) == 1 and np.allclose(offered[0]["transform"], wrong.matrix())


def test_the_retry_leaves_confident_answers_and_told_exposures_alone():
    source, target, _ = _pair()
    opts = _palettes_blind()
    first = align(source, target, opts)
    assert not first.verdict.doubtful
    assert _gain(source, target, first, opts) is None
    # the palettes tell this exposure (the defaults): the answer was already scored under it
    assert _gain(source, target, _doubtful(first, first.transform), AlignOptions()) is None
    # no gain to speak of: both captures in one exposure
    plain = make_object("car", seed=3, n_gaussians=3000, sample_seed=1)
    same = align(plain, target, opts)
    assert _gain(plain, target, _doubtful(same, same.transform), opts) is None


def test_the_retry_takes_the_answers_gain_where_it_differs_from_the_one_scored_under():
    palette = AlignOptions().criteria.pose.palette
    quarter = 2.0**palette.retry_gain_stops
    # the palettes found none: the answer's gain where it is more than a quarter stop off 1
    assert np.allclose(exposure_retry.gain_to_retry(np.ones(3), GAIN, palette), GAIN)
    assert exposure_retry.gain_to_retry(np.ones(3), np.full(3, 0.95 * quarter), palette) is None
    # the palettes found a gain a third of a stop off the answer's (a partial half's palette)
    found = GAIN * np.array([1.0, 1.3, 1.0])
    assert np.allclose(exposure_retry.gain_to_retry(found, GAIN, palette), GAIN)
    # ... or within a quarter stop of it: the answer was scored under its own exposure
    assert exposure_retry.gain_to_retry(GAIN * 1.1, GAIN, palette) is None
    # beyond match_exposure's bounds (two paints, not an exposure): left alone
    too_dark = np.full(3, 0.9 / palette.max_exposure_gain)
    assert exposure_retry.gain_to_retry(np.ones(3), too_dark, palette) is None
    off_white = np.array([1.0, 1.0, 0.9 / palette.max_white_balance])
    assert exposure_retry.gain_to_retry(np.ones(3), off_white, palette) is None


def test_align_reports_done_once_and_last():
    source, target, _ = _pair(1500)
    reports = []
    align(source, target, _palettes_blind(), progress=lambda stage, f: reports.append(stage))
    assert reports[-1] == "done" and reports.count("done") == 1
