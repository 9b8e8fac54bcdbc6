"""Files the CLI writes get the permissions of a normal file (0666 & ~umask), not the 0600
of the temp file they are renamed from."""

import os
import stat
import subprocess
import sys

import numpy as np
import pytest

from gsa.io.atomic import current_umask
from gsa.io.ply import write_ply
from gsa.synth import make_object, random_sim3


def gsa_under_umask(umask: int, *args):
    return subprocess.run(
        [sys.executable, "-m", "gsa.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=lambda: os.umask(umask),
    )


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("modes")
    truth = random_sim3(np.random.default_rng(3))
    src = make_object("car", seed=5, n_gaussians=1500, sample_seed=1)
    tgt = make_object("car", seed=5, n_gaussians=1500, sample_seed=2).transformed(truth)
    return write_ply(src, d / "src.ply"), write_ply(tgt, d / "tgt.ply")


@pytest.mark.parametrize(("umask", "expected"), [(0o022, 0o644), (0o027, 0o640)])
def test_align_outputs_respect_the_umask(pair, tmp_path, umask, expected):
    src, tgt = pair
    outs = [tmp_path / "r.json", tmp_path / "a.ply", tmp_path / "m.spz"]
    r = gsa_under_umask(
        umask, "align", src, tgt, "--out", outs[0], "--aligned-out", outs[1], "--merged-out", outs[2], "--quiet"
    )
    assert r.returncode == 0, r.stderr
    assert {p.name: oct(mode(p)) for p in outs} == {p.name: oct(expected) for p in outs}


@pytest.mark.parametrize("ext", [".ply", ".spz", ".splat", ".glb"])
def test_convert_output_respects_the_umask(pair, tmp_path, ext):
    out = tmp_path / f"c{ext}"
    r = gsa_under_umask(0o022, "convert", pair[0], out)
    assert r.returncode == 0, r.stderr
    assert oct(mode(out)) == oct(0o644)


def test_current_umask_reads_without_changing_it():
    old = os.umask(0o027)
    try:
        assert current_umask() == 0o027
        assert os.umask(0o027) == 0o027  # unchanged
    finally:
        os.umask(old)
