import json
import subprocess
import sys

import numpy as np
import pytest

from gsa.io.ply import read_ply, write_ply
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3


def gsa(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "gsa.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    truth = random_sim3(np.random.default_rng(42))
    src = make_object("airplane", seed=5, n_gaussians=5000, sample_seed=1, sh_degree=1)
    tgt = make_object("airplane", seed=5, n_gaussians=5000, sample_seed=2, sh_degree=1).transformed(truth)
    return write_ply(src, d / "src.ply"), write_ply(tgt, d / "tgt.ply"), truth


def test_align_writes_result_and_models(pair, tmp_path):
    src, tgt, truth = pair
    r = gsa("align", src, tgt, "--out", tmp_path / "r.json", "--aligned-out", tmp_path / "a.ply",
            "--merged-out", tmp_path / "m.ply", "--quiet")
    assert r.returncode == 0, r.stderr
    data = json.loads((tmp_path / "r.json").read_text())
    est = Sim3.from_matrix(np.array(data["transform"]))
    assert rre_deg(est.rotation, truth.rotation) < 1.0
    assert est.scale == pytest.approx(truth.scale, rel=0.01)
    assert np.allclose(data["quaternion"], est.quaternion(), atol=1e-6)
    assert set(data) >= {"scale", "rotation", "translation", "metrics", "timings"}
    aligned = read_ply(tmp_path / "a.ply")
    assert np.allclose(aligned.means, est.apply(read_ply(src).means), atol=1e-3 * truth.scale)
    assert len(read_ply(tmp_path / "m.ply")) == 10_000
    assert "scale" in r.stdout


def test_progress_is_shown_on_stderr(pair, tmp_path):
    src, tgt, _ = pair
    r = gsa("align", src, tgt, "--out", tmp_path / "r.json")
    assert r.returncode == 0 and "coarse" in r.stderr


@pytest.mark.parametrize(
    "make_bad, message",
    [
        (lambda p: p.write_text("not a ply"), "not a PLY"),
        (lambda p: p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n"),
         "missing properties"),
        (lambda p: None, "cannot open"),
    ],
    ids=["garbage", "not-3dgs", "missing"],
)
def test_bad_input_is_one_line_and_nonzero(pair, tmp_path, make_bad, message):
    bad = tmp_path / "bad.ply"
    make_bad(bad)
    r = gsa("align", bad, pair[1], "--out", tmp_path / "r.json", "--quiet")
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gsa: error:") and message in lines[0]
    assert not (tmp_path / "r.json").exists()


def test_bad_option_is_rejected(pair, tmp_path):
    r = gsa("align", pair[0], pair[1], "--stages", "fine", "--out", tmp_path / "r.json")
    assert r.returncode != 0 and "stages" in r.stderr and "Traceback" not in r.stderr


def test_unreadable_target_cameras_are_one_line(pair, tmp_path):
    (tmp_path / "cams.json").write_text("not json")
    r = gsa("align", pair[0], pair[1], "--target-cameras", tmp_path / "cams.json", "--out", tmp_path / "r.json")
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert "cams.json" in r.stderr and "cameras.json" in r.stderr


def test_demo_prints_error_against_truth(tmp_path):
    r = gsa("demo", "--out", tmp_path / "demo", "--gaussians", "4000", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "RRE" in r.stdout and "aligned" in r.stdout
    data = json.loads((tmp_path / "demo" / "result.json").read_text())
    assert data["ground_truth"]["accuracy"]["rre_deg"] < 2.0
