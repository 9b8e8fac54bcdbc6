import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gsa.io.ply import read_ply, write_ply
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3


def gsa(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "gsa.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300
    )


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    truth = random_sim3(np.random.default_rng(42))
    src = make_object("airplane", seed=5, n_gaussians=5000, sample_seed=1, sh_degree=1)
    tgt = make_object("airplane", seed=5, n_gaussians=5000, sample_seed=2, sh_degree=1).transformed(truth)
    return write_ply(src, d / "src.ply"), write_ply(tgt, d / "tgt.ply"), truth


def test_align_writes_result_and_models(pair, tmp_path):
    src, tgt, truth = pair
    r = gsa(
        "align",
        src,
        tgt,
        "--out",
        tmp_path / "r.json",
        "--aligned-out",
        tmp_path / "a.ply",
        "--merged-out",
        tmp_path / "m.ply",
        "--quiet",
    )
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
    assert "warning" not in r.stderr  # a clear, coloured pair is not doubtful


def _colourless_ellipsoid(n, seed):
    """Gaussians on an ellipsoid with three distinct axes, all one colour: four poses
    (the 180° turns about its axes) fit equally well and nothing can tell them apart."""
    from gsa.model import GaussianModel

    v = np.random.default_rng(seed).normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return GaussianModel(
        means=v * [3.0, 2.0, 1.0],
        quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        log_scales=np.full((n, 3), np.log(0.03)),
        opacity_logits=np.full(n, 2.0),
        sh=np.full((n, 1, 3), 0.5),
    )


def test_symmetric_colourless_pair_warns_once(tmp_path):
    src = write_ply(_colourless_ellipsoid(3000, 1), tmp_path / "s.ply")
    tgt = write_ply(
        _colourless_ellipsoid(3000, 2).transformed(random_sim3(np.random.default_rng(1))), tmp_path / "t.ply"
    )
    r = gsa("align", src, tgt, "--out", tmp_path / "r.json", "--quiet")
    assert r.returncode == 0, r.stderr
    metrics = json.loads((tmp_path / "r.json").read_text())["metrics"]
    assert metrics["doubtful"] and metrics["alternatives"]
    warnings = [line for line in r.stderr.splitlines() if line.startswith("gsa: warning:")]
    assert len(warnings) == 1 and "alternatives" in warnings[0], r.stderr


@pytest.mark.parametrize(
    "make_bad, message",
    [
        (lambda p: p.write_text("not a ply"), "not a PLY"),
        (
            lambda p: p.write_bytes(
                b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n"
            ),
            "missing properties",
        ),
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


def test_rigid_flag_reaches_the_options():
    from gsa.align.command import _align_options, add_align_arguments

    parser = argparse.ArgumentParser()
    add_align_arguments(parser)
    assert _align_options(parser.parse_args(["--rigid"])).rigid is True
    assert _align_options(parser.parse_args([])).rigid is False


def test_frame_snap_flag_reaches_the_options():
    from gsa.align.command import _align_options, add_align_arguments

    parser = argparse.ArgumentParser()
    add_align_arguments(parser)
    assert _align_options(parser.parse_args(["--frame-snap", "off"])).frame_snap == "off"
    assert _align_options(parser.parse_args([])).frame_snap == "auto"
    with pytest.raises(SystemExit):  # argparse refuses other values with its usage line
        parser.parse_args(["--frame-snap", "sometimes"])


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


def _doubtful(**extra):
    metrics = {
        "doubtful": True,
        "ambiguous": True,
        "confidence": 0.25,
        "score": 0.61,
        "alternatives": [{"rotation_offset_deg": 180.0, "score": 0.60}, {"rotation_offset_deg": 90.0, "score": 0.598}],
    }
    return {**metrics, **extra}


@pytest.mark.parametrize(
    "metrics, expected",
    [
        (
            _doubtful(),
            ["ambiguous alignment", "3 poses", "within 0.012", "confidence 0.25", "180°", '"alternatives" in r.json'],
        ),
        (_doubtful(ambiguous=False, confidence=0.32), ["low confidence (0.32)", '"alternatives" in r.json']),
        ({"doubtful": True, "confidence": 0.1}, ["low confidence (0.10)"]),
        (
            {"doubtful": True, "confidence": 0.25, "colour_mismatch": 2.49},
            ["low confidence (0.25)", "colours disagree", "2.5x their own colour noise"],
        ),
        (
            _doubtful(guidance={"doubt": "the models fit better at another pose 87° from this one"}),
            ["doubtful guided alignment", "confidence 0.25", "87° from this one", '"alternatives" in r.json'],
        ),
        (_doubtful(doubtful=False), None),
        ({"inlier_fraction": 0.9}, None),  # a result from before these keys existed
    ],
    ids=["ambiguous", "low-confidence", "no-alternatives", "colour-mismatch", "guided", "confident", "old-metrics"],
)
def test_doubt_warning(metrics, expected):
    from gsa.align.command import doubt_warning

    line = doubt_warning(metrics, "r.json")
    if expected is None:
        assert line is None
    else:
        assert line is not None and line.startswith("gsa: warning:") and "\n" not in line
        for part in expected:
            assert part in line


@pytest.mark.parametrize("doubtful", [True, False])
def test_doubtful_result_prints_one_warning_on_stderr(doubtful, capsys):
    from gsa.align.command import _print_transform
    from gsa.align.result import AlignmentResult

    metrics = {"inlier_fraction": 0.9, "rms_residual": 0.01, "feature_agreement": 0.9, **_doubtful(doubtful=doubtful)}
    result = AlignmentResult(Sim3.identity(), None, "canonical", metrics=metrics, timings={"total": 1.0})
    _print_transform(result, "r.json")
    out, err = capsys.readouterr()
    assert "scale" in out and "warning" not in out
    warnings = [line for line in err.splitlines() if line.startswith("gsa: warning:")]
    assert len(warnings) == (1 if doubtful else 0)


def test_version_prints_and_exits_0():
    """`gsa --version` (it exited 2, "the following arguments are required: COMMAND"): the
    installed distribution's version, on stdout, through the installed entry point too."""
    from importlib.metadata import version

    import gsa as package

    assert package.__version__ == version("gsa")  # the code and the installed metadata agree
    r = gsa("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"gsa {version('gsa')}", (r.returncode, r.stdout, r.stderr)
    script = Path(sys.executable).with_name("gsa")
    if script.exists():  # the console script an install made
        r = subprocess.run([str(script), "--version"], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0 and r.stdout.strip() == f"gsa {version('gsa')}", (r.stdout, r.stderr)


def test_parser_does_not_import_other_verbs_modules():
    """`gsa align` start-up: building the parser loads the alignment, not OpenCV (recon),
    torch (features, renderer), the generator or the service."""
    code = (
        "import sys; from gsa.cli import build_parser; build_parser()\n"
        "heavy = [m for m in ('cv2', 'torch', 'transformers', 'gsa.synth', 'gsa.recon.images', 'fastapi', 'grpc',"
        " 'benchmarks')"
        " if m in sys.modules]\n"
        "assert not heavy, heavy"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def _forget_benchmarks(monkeypatch):
    for name in [m for m in sys.modules if m == "benchmarks" or m.startswith("benchmarks.")]:
        monkeypatch.delitem(sys.modules, name)


def test_bench_finds_the_checkouts_benchmarks(monkeypatch):
    """`gsa bench` from a checkout: benchmarks/ is found beside the gsa/ the command runs from,
    with the repository on no path (an editable install maps only gsa and service)."""
    import gsa.cli

    root = Path(gsa.cli.__file__).resolve().parents[1]
    if not (root / "benchmarks" / "__init__.py").is_file():
        pytest.skip("gsa is not imported from a checkout")
    monkeypatch.setattr(sys, "path", [p for p in sys.path if Path(p or ".").resolve() != root])
    _forget_benchmarks(monkeypatch)
    peers = gsa.cli._benchmarks("peers")
    assert Path(peers.__file__).resolve() == root / "benchmarks" / "peers.py"


def test_bench_outside_a_checkout_is_one_line(monkeypatch, tmp_path, capsys):
    """An installed wheel has no benchmarks/: `gsa bench` says they run from a checkout."""
    import gsa.cli
    from gsa.cli_base import EXIT_FAILED

    root = Path(gsa.cli.__file__).resolve().parents[1]
    monkeypatch.setattr(gsa.cli, "__file__", str(tmp_path / "site-packages" / "gsa" / "cli.py"))
    monkeypatch.setattr(sys, "path", [p for p in sys.path if Path(p or ".").resolve() != root])
    _forget_benchmarks(monkeypatch)
    assert gsa.cli.main(["bench", "dup", "--quick", "--out", str(tmp_path / "out")]) == EXIT_FAILED
    err = capsys.readouterr().err
    assert err.startswith("gsa: error: gsa bench runs from a checkout") and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_category_choices_are_checked_and_listed(capsys):
    from gsa.cli import build_parser
    from gsa.synth import CATEGORIES

    parser = build_parser()
    assert parser.parse_args(["synth", "chair", "--out", "x.ply"]).category == "chair"
    with pytest.raises(SystemExit):
        parser.parse_args(["synth", "sofa", "--out", "x.ply"])
    assert "invalid choice: 'sofa'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parser.parse_args(["demo", "--help"])
    assert "{" + ",".join(CATEGORIES) + "}" in capsys.readouterr().out
