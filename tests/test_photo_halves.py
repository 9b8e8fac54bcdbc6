"""benchmarks.photo_halves: the pieces around the reconstructions (photo scaling, interleaved halves,
the truth from a joint SfM), on tiny generated images and cameras. The protocol itself runs
minutes per half and is measured by `python -m benchmarks.photo_halves`, not here."""

import cv2
import numpy as np

from benchmarks.photo_halves import halves, looked_at, scaled_photos, to_joint, within
from gsa.metrics import rre_deg, scale_error_pct
from gsa.render.cameras import orbit_cameras
from gsa.synth.perturb import random_sim3


def test_scaled_photos_long_side_and_names(tmp_path):
    src = tmp_path / "photos"
    src.mkdir()
    for i, (h, w) in enumerate([(40, 80), (80, 40), (10, 20)]):
        cv2.imwrite(str(src / f"p{i}.jpg"), np.full((h, w, 3), 100 + i, np.uint8))
    (src / "notes.txt").write_text("not a photo")
    names = scaled_photos(src, tmp_path / "out", 20)
    assert names == ["p0.png", "p1.png", "p2.png"]
    shapes = [cv2.imread(str(tmp_path / "out" / n)).shape[:2] for n in names]
    assert shapes == [(10, 20), (20, 10), (10, 20)]  # never enlarged


def test_halves_interleave():
    a, b = halves([f"{i}.png" for i in range(7)])
    assert a == ["0.png", "2.png", "4.png", "6.png"] and b == ["1.png", "3.png", "5.png"]


def test_truth_from_joint_frame():
    joint = orbit_cameras(np.zeros(3), 3.0, 10, width=32, height=24)
    names = [f"{i}.png" for i in range(10)]
    rng = np.random.default_rng(0)
    # Each half sees the joint frame through its own Sim(3), and registered only some views.
    frames = [random_sim3(rng, scale_range=(0.5, 2.0), translation=2.0) for _ in range(2)]
    parts = [[0, 2, 4, 8], [1, 3, 5, 7, 9]]
    fits = []
    for f, part in zip(frames, parts):
        # Cameras that see the half's frame f(joint) as `joint` sees the joint frame.
        cams = joint[part].for_transformed_model(f.inverse())
        t, row = to_joint(cams, [names[i] for i in part], joint, names)
        assert row["views_fitted"] == len(part) and row["centre_fit_rms_pct_of_spread"] < 1e-6
        fits.append(t)
    gt = fits[1].inverse().compose(fits[0])
    want = frames[1].compose(frames[0].inverse())
    assert rre_deg(gt.rotation, want.rotation) < 1e-6
    assert scale_error_pct(gt.scale, want.scale) < 1e-6


def test_looked_at_and_within():
    centre = np.array([1.0, -2.0, 0.5])
    cams = orbit_cameras(centre, 4.0, 12, width=32, height=24)
    point, distance = looked_at(cams)
    assert np.allclose(point, centre, atol=1e-6) and abs(distance - 4.0) < 1e-6

    class Means:  # within() reads only .means
        means = centre + np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 11.0], [0.0, 13.0, 0.0]])

    assert within(Means(), cams, 3.0).tolist() == [True, True, False]


def test_a_few_views_placed_off_do_not_tilt_the_truth():
    """trimmed_centre_fit: 2 of 12 cameras placed off by their SfM; the fit on all of them
    tilts, the trimmed one recovers the frame and keeps the 10 others."""
    from gsa.recon.sfm import centre_error, trimmed_centre_fit

    true = orbit_cameras(np.zeros(3), 3.0, 12, width=32, height=24)
    frame = random_sim3(np.random.default_rng(1), scale_range=(0.5, 2.0), translation=2.0)
    est = true.for_transformed_model(frame.inverse())  # the SfM's frame: frame(true) seen as true
    viewmats = est.viewmats.copy()
    viewmats[[3, 8], :3, 3] += np.array([0.0, 0.9, 0.4]) * frame.scale  # two views off
    est = type(est)(viewmats, est.fx, est.fy, est.cx, est.cy, est.width, est.height)
    want = frame.inverse()  # est frame -> true frame
    _, plain = centre_error(est, true)
    trimmed, kept = trimmed_centre_fit(est, true)
    assert kept == 10
    assert rre_deg(plain.rotation, want.rotation) > 1.0  # the check can fail
    assert rre_deg(trimmed.rotation, want.rotation) < 1e-6
    assert scale_error_pct(trimmed.scale, want.scale) < 1e-6
