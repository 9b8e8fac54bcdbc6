"""Intrinsics shared between two reconstructions of one camera (gsa.recon.calibration): the EXIF
camera identity, sizes and orientations, when reconstruct() holds them fixed, and SfM keeping them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from gsa.recon.calibration import Calibration, same_camera
from gsa.recon.photos import exif_camera, exif_orientation
from tests.exif import IPHONE, camera_jpeg


@pytest.mark.parametrize("little_endian", [False, True])
def test_exif_names_the_camera_that_took_a_photo(tmp_path, little_endian):
    p = camera_jpeg(tmp_path / "a.jpg", orientation=6, little_endian=little_endian)
    assert exif_camera(p) == IPHONE
    assert exif_orientation(p) == 6  # the orientation still reads through the same directory
    tele = camera_jpeg(
        tmp_path / "b.jpg", lens="iPhone 7 Plus back camera 6.6mm f/2.8", focal=(660, 100), focal_35mm=56
    )
    assert exif_camera(tele)[2:5] == ("iPhone 7 Plus back camera 6.6mm f/2.8", 6.6, 56)
    assert not same_camera(exif_camera(p), exif_camera(tele))  # a phone's other lens is another camera
    assert same_camera(exif_camera(p), list(IPHONE))  # report.json stores it as a list
    # no EXIF, or a PNG: unknown, and unknown cameras are never the same
    cv2.imwrite(str(tmp_path / "c.png"), np.zeros((8, 8, 3), np.uint8))
    assert exif_camera(tmp_path / "c.png") is None and not same_camera(None, None)
    # a truncated EXIF block is unknown, not an error
    data = p.read_bytes()
    broken = tmp_path / "d.jpg"
    broken.write_bytes(data[:40] + data[200:])
    assert exif_camera(broken) in (None, IPHONE)


def test_a_calibration_follows_the_image_size_and_orientation():
    cal = Calibration(425.0, 425.0, 256.0, 192.0, 512, 384, IPHONE)
    assert cal.for_size(512, 384) == (425.0, 425.0, 256.0, 192.0)
    fx, fy, cx, cy = cal.for_size(256, 192)  # the same photos stored at half the size
    assert (fx, fy, cx, cy) == (212.5, 212.5, 128.0, 96.0)
    assert cal.for_size(384, 512) == (425.0, 425.0, 192.0, 256.0)  # portrait canvas: turned
    assert cal.for_size(512, 288) is None  # 16:9: another crop of the sensor, not the same intrinsics


def test_of_cameras_needs_one_shared_camera():
    from gsa.render.cameras import Cameras

    views = np.repeat(np.eye(4)[None], 3, axis=0)
    one = Cameras(views, 300.0, 301.0, 64.0, 48.0, 128, 96)
    assert Calibration.of_cameras(one, list(IPHONE)) == Calibration(300.0, 301.0, 64.0, 48.0, 128, 96, IPHONE)
    two = Cameras(views, np.array([300.0, 300.0, 250.0]), 300.0, 64.0, 48.0, 128, 96)
    assert Calibration.of_cameras(two) is None


def _set(camera, groups=None, size=(512, 384)):
    return SimpleNamespace(camera=camera, camera_groups=groups, width=size[0], height=size[1])


def test_reconstruct_holds_the_intrinsics_only_for_the_same_camera():
    from gsa.recon.pipeline import _fixed_intrinsics

    cal = Calibration(425.0, 425.0, 256.0, 192.0, 512, 384, IPHONE)
    params, why = _fixed_intrinsics(_set(IPHONE, size=(256, 192)), cal, "same-camera")
    assert params == (212.5, 212.5, 128.0, 96.0) and why["fixed"]
    other = IPHONE[:3] + (6.6, 56, None)
    for imset, check, reason in (
        (_set(other), "same-camera", "another camera"),
        (_set(None), "same-camera", "no EXIF camera"),
        (_set(IPHONE, groups=[0, 1, 0]), "same-camera", "several cameras"),
        (_set(IPHONE, size=(512, 288)), "same-camera", "aspect"),
        (_set(None, size=(512, 288)), "none", "aspect"),
    ):
        params, why = _fixed_intrinsics(imset, cal, check)
        assert params is None and not why["fixed"] and reason in why["reason"], why
    # the user's word (gsa reconstruct --intrinsics-from): no EXIF needed
    assert _fixed_intrinsics(_set(None), cal, "none")[0] == (425.0, 425.0, 256.0, 192.0)
    assert _fixed_intrinsics(_set(IPHONE), None, "same-camera") == (
        None,
        {"fixed": False, "reason": "estimated from this set"},
    )


def test_a_photo_set_knows_its_camera_from_the_originals(tmp_path):
    """Every photo of one camera: the set's camera, also when the set is prepared into copies
    (turned shots) that lose their EXIF; a second camera in the set: none."""
    from gsa.recon.images import load_image_set

    d = tmp_path / "set"
    d.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        camera_jpeg(d / f"a{i}.jpg", size=(48, 64))
    camera_jpeg(d / "b.jpg", size=(48, 64), orientation=6)  # EXIF-turned: the set is prepared into copies
    s = load_image_set(d, min_images=3)
    assert s.camera == IPHONE and s.notes.get("exif_rotated") == ["b.jpg"]
    cv2.imwrite(str(d / "c.png"), (rng.random((48, 64, 3)) * 255).astype(np.uint8))
    assert load_image_set(d, min_images=3).camera is None


@pytest.mark.slow
def test_sfm_holds_the_given_intrinsics(tmp_path):
    """run_sfm with fixed intrinsics registers the views with exactly those (a set of one camera
    reconstructed with another reconstruction's lens)."""
    from gsa.recon.images import load_image_set
    from gsa.recon.sfm import centre_error, run_sfm
    from gsa.recon.synthetic import render_image_set

    rendered = render_image_set(tmp_path / "synth", n_views=24, size=256, orbit_seed=1)
    true = (
        float(rendered.cameras.fx[0]),
        float(rendered.cameras.fy[0]),
        float(rendered.cameras.cx[0]),
        float(rendered.cameras.cy[0]),
    )
    given = (true[0] * 1.005, true[1] * 1.005, true[2], true[3])  # a lens known to 0.5 %
    sfm = run_sfm(load_image_set(rendered.directory), tmp_path / "w", fixed_intrinsics=given)
    assert sfm.n_registered >= 20, sfm.unregistered
    assert np.allclose(sfm.cameras.fx, given[0], rtol=1e-6) and np.allclose(sfm.cameras.cy, given[3], rtol=1e-6)
    free = run_sfm(load_image_set(rendered.directory), tmp_path / "w2")
    assert not np.allclose(free.cameras.fx, given[0], rtol=1e-4)  # left free, SfM estimates its own
    idx = [rendered.names.index(n) for n in sfm.names]
    err, _ = centre_error(sfm.cameras, rendered.cameras[idx])
    assert err / rendered.radius < 0.05


def test_reconstruct_cli_refuses_a_folder_without_cameras(tmp_path):
    d = tmp_path / "set"
    d.mkdir()
    for i in range(3):
        camera_jpeg(d / f"a{i}.jpg")
    (tmp_path / "empty").mkdir()
    cmd = [
        sys.executable,
        "-m",
        "gsa.cli",
        "reconstruct",
        str(d),
        "--out",
        str(tmp_path / "o"),
        "--intrinsics-from",
        str(tmp_path / "empty"),
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("gsa: error: --intrinsics-from"), r.stderr
    assert not (tmp_path / "o" / "model.ply").exists()


def test_a_reconstruction_folder_keeps_its_camera(tmp_path):
    """read_reconstruction gives the model the EXIF camera report.json names, so that a set of the
    same camera aligned against the folder is reconstructed with its intrinsics."""
    from gsa.io.ply import write_ply
    from gsa.recon.folder import read_reconstruction
    from gsa.render.cameras import Cameras, write_cameras_json
    from gsa.synth.objects import make_object

    out = tmp_path / "recon"
    out.mkdir()
    write_ply(make_object("car", seed=0, n_gaussians=500), out / "model.ply")
    write_cameras_json(
        out / "cameras.json",
        Cameras(np.repeat(np.eye(4)[None], 2, axis=0), 300.0, 300.0, 64.0, 48.0, 128, 96),
        ["a.png", "b.png"],
    )
    (out / "report.json").write_text(json.dumps({"exif_camera": list(IPHONE)}))
    cal = Calibration.of_model(read_reconstruction(out))
    assert cal is not None and cal.camera == IPHONE and cal.fx == 300.0
    (out / "report.json").write_text("{not json")
    assert Calibration.of_model(read_reconstruction(out)).camera is None
    shutil.rmtree(out)
