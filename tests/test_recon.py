"""Reconstruction from image sets: input checks, SfM vs true cameras, masks, training."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from gsa.geometry import axis_rotation
from gsa.io.ply import read_ply  # noqa: E402
from gsa.recon.images import ImageSetError, load_image_set  # noqa: E402
from gsa.recon.masks import compute_masks, grabcut_mask, key_mask  # noqa: E402
from gsa.recon.sfm import SfMError, centre_error  # noqa: E402
from gsa.render import render_model  # noqa: E402
from gsa.sim3 import Sim3


def _write(path, img):
    cv2.imwrite(str(path), (np.clip(img, 0, 1) * 255).astype(np.uint8))


def _noise_images(d, n, size=(32, 24)):
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        _write(d / f"im{i}.png", rng.uniform(0, 1, (size[1], size[0], 3)))
    return d


# ------------------------------------------------------------------ image sets
def test_too_few_images(tmp_path):
    with pytest.raises(ImageSetError, match="at least 3"):
        load_image_set(_noise_images(tmp_path / "a", 2))


def test_non_image_file(tmp_path):
    d = _noise_images(tmp_path / "a", 4)
    (d / "notes.txt").write_text("hello")
    with pytest.raises(ImageSetError, match="notes.txt"):
        load_image_set(d)


def test_unreadable_image(tmp_path):
    d = _noise_images(tmp_path / "a", 4)
    (d / "broken.png").write_bytes(b"\x89PNG not really")
    with pytest.warns(UserWarning, match="1 file.s. are not readable images and are left out: broken.png"):
        s = load_image_set(d)
    assert "broken.png" not in s.names and len(s) == 4 and s.notes["unreadable"] == ["broken.png"]
    for i in range(2):
        (d / f"im{i}.png").write_bytes(b"\x89PNG cut")
    with pytest.raises(ImageSetError, match="2 readable image.s.*at least 3.*not readable images: broken.png"):
        load_image_set(d)


def test_a_few_blurred_views_are_left_out(tmp_path):
    d = _noise_images(tmp_path / "a", 9, size=(96, 64))
    for name in ("im2.png", "im7.png"):  # camera shake: a 2-pixel blur
        img = cv2.imread(str(d / name))
        cv2.imwrite(str(d / name), cv2.GaussianBlur(img, (0, 0), 2.0))
    with pytest.warns(UserWarning, match="2 blurred view.s. left out .*: im2.png, im7.png"):
        s = load_image_set(d)
    assert s.notes["blurred"] == ["im2.png", "im7.png"]
    assert len(s) == 7 and "im2.png" not in s.names and "im7.png" not in s.names


def test_blur_is_judged_against_the_set_itself(tmp_path, recwarn):
    # A set soft throughout loses nothing; nor does one where the "blurred" are not a few.
    soft = _noise_images(tmp_path / "soft", 6, size=(96, 64))
    for p in soft.iterdir():
        cv2.imwrite(str(p), cv2.GaussianBlur(cv2.imread(str(p)), (0, 0), 2.0))
    assert len(load_image_set(soft)) == 6
    half = _noise_images(tmp_path / "half", 6, size=(96, 64))
    for name in ("im0.png", "im1.png", "im2.png"):
        cv2.imwrite(str(half / name), cv2.GaussianBlur(cv2.imread(str(half / name)), (0, 0), 2.0))
    s = load_image_set(half)
    assert len(s) == 6 and "blurred" not in s.notes
    assert not [w for w in recwarn if "blurred" in str(w.message)]


def _exif_jpeg(path, bgr, orientation):
    """A JPEG of `bgr` (as stored) whose EXIF says how to turn it for display (1-8)."""
    import struct

    ok, buf = cv2.imencode(".jpg", (np.clip(bgr, 0, 1) * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95])
    tiff = b"MM\x00*" + struct.pack(">IH", 8, 1) + struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0) + bytes(4)
    payload = b"Exif\x00\x00" + tiff
    data = buf.tobytes()
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:])


def test_exif_orientation_is_applied(tmp_path):
    from gsa.recon.images import read_rgb
    from gsa.recon.photos import exif_orientation

    img = np.zeros((24, 32, 3))
    img[:8, :8] = 1.0  # a white corner, top left as stored
    for o in (1, 3, 6, 8):
        _exif_jpeg(tmp_path / f"o{o}.jpg", img, o)
        assert exif_orientation(tmp_path / f"o{o}.jpg") == o
    seen = {o: read_rgb(tmp_path / f"o{o}.jpg").mean(axis=2) > 0.5 for o in (1, 3, 6, 8)}
    assert seen[1].shape == (24, 32) and seen[1][:8, :8].all()
    assert seen[3].shape == (24, 32) and seen[3][-8:, -8:].all()  # turned 180°
    assert seen[6].shape == (32, 24) and seen[6][:8, -8:].all()  # turned 90° clockwise
    assert seen[8].shape == (32, 24) and seen[8][-8:, :8].all()  # turned 90° counter-clockwise
    assert exif_orientation(_noise_images(tmp_path / "p", 1) / "im0.png") == 1


def test_phone_set_portrait_landscape_exif_and_a_second_camera(tmp_path):
    """Landscape shots, portrait shots (turned pixels, or landscape pixels with EXIF 6), and a
    second camera of another size and aspect: one size, one camera per camera size."""
    from gsa.recon.images import read_rgb

    d = tmp_path / "phone"
    d.mkdir()
    rng = np.random.default_rng(1)
    shots = [rng.uniform(0, 1, (48, 64, 3)) for _ in range(7)]
    for i in range(3):  # landscape 64x48
        _write(d / f"a{i}.png", shots[i])
    _write(d / "b0.png", np.rot90(shots[3]))  # portrait 48x64, pixels turned
    _exif_jpeg(d / "b1.jpg", shots[4], 6)  # portrait by EXIF: stored landscape
    _write(d / "c0.png", cv2.resize(shots[5], (100, 50)))  # a second camera, 2:1
    _write(d / "c1.png", cv2.resize(shots[6], (100, 50)))
    s = load_image_set(d)
    assert (s.width, s.height) == (64, 48) and len(s) == 7
    assert s.directory != d  # a prepared copy: SfM and training read the same pixels
    assert s.read_all().shape == (7, 48, 64, 3)
    groups = dict(zip(s.names, s.camera_groups))
    assert groups["a0.png"] == groups["b0.png"] == groups["b1.jpg"] != groups["c0.png"] == groups["c1.png"]
    assert s.notes["turned_90"] == ["b0.png", "b1.jpg"] and s.notes["exif_rotated"] == ["b1.jpg"]
    assert s.notes["rescaled"] == ["c0.png", "c1.png"] and s.notes["cameras"] == 2
    # a portrait shot turned back is its landscape pixels, rolled by 180° at most
    b0 = read_rgb(s.directory / "b0.png")
    truth = shots[3][..., ::-1].astype(np.float32)  # BGR written, RGB read
    assert min(np.abs(b0 - truth).mean(), np.abs(b0 - truth[::-1, ::-1]).mean()) < 0.01
    # the 2:1 camera is scaled to cover 64x48 and cropped about its centre (pixels stay square)
    c0 = read_rgb(s.directory / "c0.png")
    cover = cv2.resize(cv2.resize(shots[5], (100, 50)), (96, 48), interpolation=cv2.INTER_AREA)[:, 16:80]
    assert np.abs(c0 - cover[..., ::-1]).mean() < 0.02


def test_one_size_set_is_used_where_it_lies(tmp_path):
    d = _noise_images(tmp_path / "a", 4)
    s = load_image_set(d)
    assert s.directory == d and s.camera_groups is None and s.notes == {}


def test_zip_ok_and_unsafe(tmp_path):
    d = _noise_images(tmp_path / "a", 4)
    good = tmp_path / "good.zip"
    with zipfile.ZipFile(good, "w") as zf:
        for p in sorted(d.iterdir()):
            zf.write(p, f"photos/{p.name}")
    s = load_image_set(good)
    assert len(s) == 4 and (s.width, s.height) == (32, 24)
    assert s.read_all().shape == (4, 24, 32, 3)
    for bad_name in ("../evil.png", "/abs.png"):
        bad = tmp_path / "bad.zip"
        with zipfile.ZipFile(bad, "w") as zf:
            for p in sorted(d.iterdir()):
                zf.write(p, p.name)
            zf.writestr(bad_name, b"x")
        with pytest.raises(ImageSetError, match="unsafe path"):
            load_image_set(bad)


def test_zip_bomb_ratio(tmp_path):
    bomb = tmp_path / "bomb.zip"
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("a.png", b"\0" * (8 * 1024 * 1024))
    with pytest.raises(ImageSetError, match="compression ratio"):
        load_image_set(bomb)


# ------------------------------------------------------------------ rendered set + one reconstruction
@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from gsa.recon.synthetic import render_image_set

    root = tmp_path_factory.mktemp("synth")
    return render_image_set(root, n_views=24, size=256, orbit_seed=1)


def _quick_reconstruction(images, out, **kwargs):
    from dataclasses import replace

    from gsa.recon.pipeline import reconstruct
    from gsa.recon.train import PRESETS

    cfg = replace(
        PRESETS["cpu"],
        iterations=60,
        resolution=64,
        densify_from=20,
        densify_until=50,
        densify_every=15,
        init_points=1500,
        feature_start=0.5,
        holdout_every=8,
    )
    return reconstruct(images, out, preset=cfg, **kwargs)


@pytest.fixture(scope="module")
def recon(rendered, tmp_path_factory):
    return _quick_reconstruction(rendered.directory, tmp_path_factory.mktemp("out"))


# The same object photographed again by a second rig, in a frame of its own.
SECOND_RIG = Sim3(1.7, axis_rotation(np.array([0.6, 0.0, 0.8]), 2.5), np.array([0.4, -1.0, 2.0]))


@pytest.fixture(scope="module")
def second(tmp_path_factory):
    from gsa.recon.synthetic import render_image_set

    rendered = render_image_set(tmp_path_factory.mktemp("synth2"), n_views=24, size=256, orbit_seed=2, rig=SECOND_RIG)
    return rendered, _quick_reconstruction(rendered.directory, tmp_path_factory.mktemp("out2"))


@pytest.mark.slow
def test_sfm_registers_and_matches_true_cameras(rendered, recon):
    sfm = recon.sfm
    assert sfm.n_registered >= 20, sfm.unregistered
    idx = [rendered.names.index(n) for n in sfm.names]
    err, t = centre_error(sfm.cameras, rendered.cameras[idx])
    assert err / rendered.radius < 0.03, err / rendered.radius
    # a deliberately wrong correspondence (shuffled truth) does not fit: the check can fail
    perm = np.roll(np.arange(len(idx)), 3)
    bad, _ = centre_error(sfm.cameras, rendered.cameras[np.asarray(idx)[perm]])
    assert bad / rendered.radius > 0.1
    cams = json.loads(recon.cameras_path.read_text())
    assert cams["camera_model"] == "PINHOLE" and len(cams["images"]) == sfm.n_registered
    assert (recon.out_dir / "sfm" / "sparse" / "model" / "cameras.txt").exists()


@pytest.mark.slow
def test_two_reconstructions_register_by_their_photos(rendered, recon, second):
    """Photo anchors kept beside each model (anchors.npz and metadata) register two
    reconstructions of one object at the precision of their SfM points (gsa.align.photo)."""
    from gsa.align.pipeline import AlignOptions, align
    from gsa.metrics import rre_deg, scale_error_pct
    from gsa.recon.folder import is_reconstruction, read_reconstruction

    rendered_b, recon_b = second
    anchors = recon.model.metadata["photo_anchors"]
    assert anchors.descriptors.dtype == np.uint8 and anchors.descriptors.shape[1] == 128
    assert np.allclose(anchors.points, recon.sfm.points)  # one row per SfM point, in the model's frame
    assert len(anchors) >= len(anchors.points)  # each point seen in 2+ photos, up to 4 kept
    # the truth: each SfM frame onto its rig's true frame by its cameras, then the rig between
    _, t_a = centre_error(recon.sfm.cameras, rendered.cameras[[rendered.names.index(n) for n in recon.sfm.names]])
    _, t_b = centre_error(
        recon_b.sfm.cameras, rendered_b.cameras[[rendered_b.names.index(n) for n in recon_b.sfm.names]]
    )
    truth = t_b.inverse().compose(SECOND_RIG.compose(t_a))
    r = align(recon.model, recon_b.model)
    assert r.stages == ("photo",), r.diagnostics.get("photo_match")
    assert rre_deg(r.transform.rotation, truth.rotation) < 0.5
    assert scale_error_pct(r.transform.scale, truth.scale) < 1.0
    assert not r.verdict.doubtful and r.diagnostics["photo_match"]["inliers"] >= 100
    # what `gsa align DIR_A DIR_B` reads: the folders, anchors included
    assert is_reconstruction(recon.out_dir) and not is_reconstruction(rendered.directory)
    again = align(read_reconstruction(recon.out_dir), read_reconstruction(recon_b.out_dir))
    assert again.stages == ("photo",)
    assert rre_deg(again.transform.rotation, r.transform.rotation) < 1e-6
    # without the photos, the Gaussians alone decide
    assert align(recon.model, recon_b.model, AlignOptions(photo_matches="off")).stages != ("photo",)


@pytest.mark.slow
def test_intrinsics_that_do_not_fit_the_photos_cost_nothing(rendered, recon, tmp_path):
    """A calibration held fixed where SfM cannot start with it (a lens 100x off) is dropped, the
    set's own intrinsics are estimated, and report.json says why."""
    from dataclasses import replace

    wrong = replace(recon.calibration, fx=recon.calibration.fx * 100, fy=recon.calibration.fy * 100)
    res = _quick_reconstruction(rendered.directory, tmp_path / "out", calibration=wrong, calibration_check="none")
    assert not res.intrinsics["fixed"] and "with the other set's camera" in res.intrinsics["reason"]
    assert res.n_registered >= 20 and abs(res.sfm.cameras.fx[0] / recon.sfm.cameras.fx[0] - 1) < 0.05
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["intrinsics"] == res.intrinsics and report["exif_camera"] is None  # rendered PNGs: no EXIF


def test_too_few_register(tmp_path):
    from gsa.recon.sfm import run_sfm

    s = load_image_set(_noise_images(tmp_path / "n", 4, size=(64, 64)))
    with pytest.raises(SfMError, match="registered"):
        run_sfm(s, tmp_path / "w")


@pytest.mark.slow
def test_mapping_retries_until_every_view_registers(rendered, tmp_path):
    from gsa.recon.sfm import run_sfm

    d = tmp_path / "set"
    d.mkdir()
    for n in rendered.names:
        shutil.copy(rendered.directory / n, d / n)
    noise = _noise_images(tmp_path / "noise", 1, size=(256, 256))
    shutil.copy(next(p for p in noise.iterdir()), d / "zz_noise.png")
    sfm = run_sfm(load_image_set(d), tmp_path / "w", min_registered=0.5, mapping_attempts=2)
    assert sfm.mapping_attempts == 2  # a view that cannot register is retried, not silently dropped
    assert "zz_noise.png" in sfm.unregistered and sfm.n_registered >= len(rendered.names) // 2


@pytest.mark.slow
def test_phone_like_set_registers_with_a_camera_per_size(rendered, tmp_path, capsys):
    """The rendered views as a phone set: 4:3 landscape crops, some turned to portrait (pixels,
    or EXIF), a second camera (16:9, other size), one blurred view, one broken file."""
    from gsa.recon.images import read_rgb
    from gsa.recon.sfm import run_sfm

    d = tmp_path / "phone"
    d.mkdir()
    size = rendered.cameras.width
    wide = []
    for i, n in enumerate(rendered.names):
        img = read_rgb(rendered.directory / n)[..., ::-1]  # BGR for writing
        if i % 6 == 5:  # second camera: a 16:9 crop at 0.75 of the size (covers 4:3 at f x 4/3)
            crop = img[(size - size * 9 // 16) // 2 :][: size * 9 // 16]
            _write(d / n, cv2.resize(crop, (size * 3 // 4, size * 27 // 64), interpolation=cv2.INTER_AREA))
            wide.append(n)
            continue
        img = img[size // 8 : size - size // 8]  # 4:3 landscape
        if i % 6 == 1:
            img = np.rot90(img)  # portrait, pixels turned
        if i % 6 == 3:
            _exif_jpeg(d / (n[:-4] + ".jpg"), img, 8)  # portrait by EXIF
            continue
        if i == 4:
            img = cv2.GaussianBlur(img, (0, 0), 1.5)
        _write(d / n, img)
    (d / "zz_broken.jpg").write_bytes(b"\xff\xd8 not really")
    with pytest.warns(UserWarning, match="zz_broken.jpg"):
        s = load_image_set(d)
    assert (s.width, s.height) == (size, size * 3 // 4) and s.notes["cameras"] == 2
    assert s.notes["blurred"] == [rendered.names[4]] and len(s) == len(rendered.names) - 1
    sfm = run_sfm(s, tmp_path / "w")
    assert sfm.n_registered >= 2 / 3 * len(s), sfm.unregistered  # the square set: 21 of 24
    stem = {Path(n).stem: i for i, n in enumerate(rendered.names)}
    idx = [stem[Path(n).stem] for n in sfm.names]
    err, _ = centre_error(sfm.cameras, rendered.cameras[idx])
    assert err / rendered.radius < 0.03, err / rendered.radius
    f_true = float(rendered.cameras.fx[0])
    for n, fx in zip(sfm.names, sfm.cameras.fx):  # each camera its own focal length
        expected = f_true * 4 / 3 if n in wide else f_true
        assert abs(fx / expected - 1) < 0.05, (n, fx, expected)

    # and the whole pipeline, briefly, through the CLI's reconstruct verb
    from gsa.cli import main

    out = tmp_path / "out"
    rc = main(["reconstruct", str(d), "--out", str(out), "--iterations", "40", "--features", "none"])
    assert rc == 0
    warned = [ln for ln in capsys.readouterr().err.splitlines() if "gsa: warning:" in ln]
    assert len(warned) == 2 and "left out: zz_broken.jpg" in warned[0], warned
    assert "1 blurred view(s) left out" in warned[1] and warned[1].endswith(rendered.names[4]), warned
    report = json.loads((out / "report.json").read_text())
    assert report["registered"] >= 2 / 3 * len(s) and report["gaussians"] > 100
    assert report["image_set"]["unreadable"] == ["zz_broken.jpg"] and report["image_set"]["cameras"] == 2
    assert report["image_set"]["blurred"] == [rendered.names[4]]


def test_masks_separate_object(rendered):
    cams = rendered.cameras[:3]
    imgs = np.stack(
        [cv2.cvtColor(cv2.imread(str(rendered.directory / n)), cv2.COLOR_BGR2RGB) / 255.0 for n in rendered.names[:3]]
    ).astype(np.float32)
    alpha = render_model(rendered.model, cams, features=False, depth=False, backend="cpu").alpha[..., 0].numpy()
    truth = alpha > 0.5
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    for img, t in zip(imgs, truth):
        assert iou(key_mask(img), t) > 0.9
        assert iou(grabcut_mask(img), t) > 0.8
    m, used = compute_masks(imgs, "auto")
    assert used == ["key"] * 3
    with pytest.raises(Exception, match="SAM|onnx"):
        compute_masks(imgs, "sam")


def test_training_lowers_loss_and_writes_features(recon):
    curve = recon.train.curve
    first = np.mean([c["rgb"] for c in curve[:2]])
    last = np.mean([c["rgb"] for c in curve[-2:]])
    assert last < 0.8 * first, (first, last)
    feat = [c["feat"] for c in curve if c["feat"] > 0]
    assert len(feat) >= 2 and feat[-1] < feat[0]
    m = read_ply(recon.model_path)
    assert m.feature_dim == 3 and len(m) > 100
    assert m.metadata["features"] == "lifted:canonical"  # so `gsa align` recomputes them
    assert max(c["n"] for c in curve) > curve[0]["n"], "densification never added a Gaussian"
    assert np.linalg.norm(m.features, axis=1).min() >= 0.1  # App. E pruning
    assert recon.train.psnr_heldout is not None and recon.train.psnr_heldout > 15
    rep = json.loads((recon.out_dir / "report.json").read_text())
    assert rep["registered"] == recon.sfm.n_registered
    # an orbit around one object: its region is found and nothing of the object lies beyond it
    far = rep["far_background"]
    assert far["radius"] > 0 and far["sfm_points_dropped"] == 0 and far["gaussians_pruned"] == 0


def test_cli_bad_input(tmp_path, capsys):
    from gsa.recon.command import main

    rc = main(["reconstruct", str(_noise_images(tmp_path / "x", 2)), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and err[-1].startswith("gsa: error: ") and "at least 3" in err[-1]


@pytest.mark.slow
def test_cli_aligns_two_reconstruction_folders_by_their_photos(recon, second, tmp_path):
    import subprocess
    import sys

    _, recon_b = second
    out = tmp_path / "r.json"
    cmd = [sys.executable, "-m", "gsa.cli", "align", str(recon.out_dir), str(recon_b.out_dir), "--out", str(out)]
    run = subprocess.run(cmd + ["--quiet"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "photos       the pose:" in run.stdout
    data = json.loads(out.read_text())
    assert data["stages_run"] == ["photo"] and data["metrics"]["photo_match"]["accepted"]
    # asked not to, the CLI aligns the same folders by their Gaussians
    off = subprocess.run(cmd + ["--quiet", "--photo-matches", "off"], capture_output=True, text=True, timeout=600)
    assert off.returncode == 0, off.stderr[-2000:]
    assert "photos" not in off.stdout and json.loads(out.read_text())["stages_run"] != ["photo"]


@pytest.mark.slow
def test_align_many_takes_reconstruction_folders(rendered, recon, second, tmp_path):
    from gsa.align.many_command import expand_models
    from gsa.cli import main
    from gsa.metrics import rre_deg

    rendered_b, recon_b = second
    # a reconstruction folder is one model; a folder of model files is its files
    assert expand_models([str(recon.out_dir), str(recon_b.out_dir)]) == [recon.out_dir, recon_b.out_dir]
    out = tmp_path / "many"
    assert main(["align-many", str(recon.out_dir), str(recon_b.out_dir), "--out", str(out), "--quiet"]) == 0
    data = json.loads((out / "many.json").read_text())
    _, t_a = centre_error(recon.sfm.cameras, rendered.cameras[[rendered.names.index(n) for n in recon.sfm.names]])
    _, t_b = centre_error(
        recon_b.sfm.cameras, rendered_b.cameras[[rendered_b.names.index(n) for n in recon_b.sfm.names]]
    )
    b_to_a = t_b.inverse().compose(SECOND_RIG.compose(t_a)).inverse()  # into the reference's (A's) frame
    second_model = data["models"][1]
    assert rre_deg(np.asarray(second_model["rotation"]), b_to_a.rotation) < 0.5
    assert second_model["scale"] == pytest.approx(b_to_a.scale, rel=0.01)
