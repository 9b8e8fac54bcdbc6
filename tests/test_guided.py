"""Guided alignment (gsa.align.guided): start poses, picked pairs, up and front axes, fixed scale."""

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsa.align.contract import hints_from_files
from gsa.align.guided import GuidanceCriteria, near_start, pairs_transform, source_symmetries, up_rotations
from gsa.align.pipeline import AlignOptions, align
from gsa.geometry import axis_rotation
from gsa.io import frames
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3


@pytest.fixture(scope="module")
def pair():
    truth = random_sim3(np.random.default_rng(4))
    source = make_object("car", seed=3, n_gaussians=4000, sample_seed=1)
    target = make_object("car", seed=3, n_gaussians=5000, sample_seed=2).transformed(truth)
    return source, target, truth


def _picks(source, truth, count, rng):
    rows = rng.choice(len(source), count, replace=False)
    return source.means[rows].astype(np.float64), truth.apply(source.means[rows])


def test_pairs_solve_in_closed_form_and_leave_out_one_wrong_pair():
    rng = np.random.default_rng(0)
    truth = random_sim3(rng)
    src = rng.normal(size=(6, 3))
    dst = truth.apply(src) + rng.normal(0, 0.005, (6, 3)) * truth.scale
    dst[2] = dst[4] + 3.0 * truth.scale  # a misclick
    fit, report = pairs_transform(src, dst)
    assert report["left_out"] == 2
    assert rre_deg(fit.rotation, truth.rotation) < 1.0
    assert abs(fit.scale / truth.scale - 1) < 0.02
    fixed, _ = pairs_transform(src[:3], truth.apply(src[:3]), fixed_scale=2.5)
    assert fixed.scale == 2.5
    # The thresholds are options: a misclick must miss by more than the pairs' spread here.
    _, lenient = pairs_transform(src, dst, criteria=GuidanceCriteria(misclick_share=100.0))
    assert lenient["left_out"] is None


def test_guidance_criteria_take_effect():
    up = (0.0, 0.0, 1.0)
    assert len(up_rotations(up, up)) == 360 / GuidanceCriteria().up_step_deg
    assert len(up_rotations(up, up, GuidanceCriteria(up_step_deg=10.0))) == 36
    turned = Sim3(1.0, axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(40.0)), np.zeros(3))
    given = {"from": "init_transform"}
    assert not near_start(turned, Sim3.identity(), None, given)
    assert near_start(turned, Sim3.identity(), None, given, GuidanceCriteria(start_leash_deg=45.0))


def test_a_pose_that_misses_the_picked_pairs_is_not_the_users():
    """With picked pairs, the leash is the clicks: a pose that maps them a little off is still
    the user's, one turned to another side of the object (half a turn) is not."""
    from types import SimpleNamespace

    rng = np.random.default_rng(5)
    src = rng.normal(size=(4, 3))
    opts = SimpleNamespace(point_pairs=(src, src + rng.normal(0, 0.05, src.shape)))
    report = {"from": "point_pairs", "left_out": None}
    fit = Sim3.identity()
    nudged = Sim3(1.0, axis_rotation(np.array([1.0, 0.0, 0.0]), np.radians(10.0)), np.zeros(3))
    flipped = Sim3(1.0, axis_rotation(np.array([1.0, 0.0, 0.0]), np.pi), np.zeros(3))
    assert near_start(nudged, fit, opts, report)
    assert not near_start(flipped, fit, opts, report)
    assert near_start(flipped, fit, opts, report, GuidanceCriteria(pairs_leash_share=10.0, pairs_max_turn_deg=180.0))


def test_clicks_along_a_line_do_not_let_the_object_roll_over():
    """Three clicks nearly on one line (along a rifle) are met as well by the object rolled half
    a turn about that line: the clicks' fit, not only the clicks, bounds the turn."""
    from types import SimpleNamespace

    src = np.array([[-1.0, 0.0, 0.0], [0.0, 0.01, 0.0], [1.0, 0.0, 0.01]])
    opts = SimpleNamespace(point_pairs=(src, src.copy()))
    report = {"from": "point_pairs", "left_out": None}
    rolled = Sim3(1.0, axis_rotation(np.array([1.0, 0.0, 0.0]), np.pi), np.zeros(3))
    lenient_clicks = GuidanceCriteria(pairs_leash_share=0.5)
    assert not near_start(rolled, Sim3.identity(), opts, report, lenient_clicks)
    assert near_start(rolled, Sim3.identity(), opts, report, GuidanceCriteria(pairs_max_turn_deg=180.0))


def _surface_of_revolution(n: int, seed: int) -> np.ndarray:
    """A vase-like surface about the z axis (radius varying with height), n points."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(-1.0, 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    r = 0.4 + 0.15 * np.sin(2.5 * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _box_surface(lo: np.ndarray, hi: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points uniform on the surface of the box [lo, hi]."""
    size = hi - lo
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]]).repeat(2)
    face = rng.choice(6, n, p=areas / areas.sum())
    points = lo + rng.uniform(size=(n, 3)) * size
    axis = face // 2
    points[np.arange(n), axis] = np.where(face % 2 == 0, lo[axis], hi[axis])
    return points


def test_source_symmetries_find_a_free_axis_and_nothing_on_a_thin_object():
    vase = _surface_of_revolution(20000, 0)
    turns = source_symmetries(vase)
    z = np.array([0.0, 0.0, 1.0])
    # every turn is about the vase's axis (as the sample's principal axis finds it: within 3 deg)
    axes = Rotation.from_matrix(np.array(turns)).as_rotvec()
    assert len(turns) >= 170 and np.all(np.abs(axes @ z) / np.linalg.norm(axes, axis=1) > np.cos(np.radians(3)))
    # a rifle-like thin barrel with a grip on one side: turned half a turn about any axis the
    # grip moves by a small share of the size but many sample spacings (not a symmetry)
    rng = np.random.default_rng(1)
    rifle = np.concatenate(
        [
            _box_surface(np.array([-1.0, -0.04, -0.02]), np.array([1.0, 0.04, 0.02]), 16000, rng),
            _box_surface(np.array([0.3, -0.25, -0.02]), np.array([0.45, -0.04, 0.02]), 4000, rng),
        ]
    )
    assert source_symmetries(rifle) == []


def test_a_start_turned_about_the_objects_own_axis_is_still_the_users():
    """A given pose and one turned 90 deg about a vase's axis place it identically: near."""
    vase = _surface_of_revolution(20000, 2)
    given = {"from": "init_transform"}
    spun = Sim3(1.0, axis_rotation(np.array([0.0, 0.0, 1.0]), np.radians(90.0)), np.zeros(3))
    tilted = Sim3(1.0, axis_rotation(np.array([1.0, 0.0, 0.0]), np.radians(90.0)), np.zeros(3))
    turns = source_symmetries(vase)
    assert not near_start(spun, Sim3.identity(), None, given)
    assert near_start(spun, Sim3.identity(), None, given, symmetries=turns)
    assert not near_start(tilted, Sim3.identity(), None, given, symmetries=turns)


def test_picked_pairs_align_a_model_and_say_so(pair):
    source, target, truth = pair
    src, dst = _picks(source, truth, 4, np.random.default_rng(1))
    size = np.linalg.norm(np.ptp(target.means, axis=0))
    dst = dst + np.random.default_rng(2).normal(0, 0.02 * size / np.sqrt(3), dst.shape)  # clicks 2 % off
    result = align(source, target, AlignOptions(point_pairs={"source": src.tolist(), "target": dst.tolist()}))
    assert rre_deg(result.transform.rotation, truth.rotation) < 1.0
    guidance = result.diagnostics["guidance"]
    assert guidance["point_pairs"] == 4 and guidance["start"]["from"] == "point_pairs"
    assert len(guidance["start"]["residuals"]) == 4


def test_init_refines_locally_and_never_jumps(pair):
    source, target, truth = pair
    near = Sim3(truth.scale * 1.05, axis_rotation([1, 1, 0], np.radians(8)) @ truth.rotation, truth.translation)
    result = align(source, target, AlignOptions(init_transform=near.matrix().tolist()))
    assert rre_deg(result.transform.rotation, truth.rotation) < 0.5
    assert result.diagnostics["guidance"]["init_transform"] is True and result.hypotheses == []
    # the answer left the given pose: that pose is the first alternative, one step back to it
    given = result.verdict.alternatives[0].details
    assert given["origin"] == "the given start" and np.allclose(given["transform"], near.matrix())
    assert given["rotation_offset_deg"] > 5.0
    # Half a turn away: the answer stays near where it was told to start (and is doubtful).
    far = Sim3(truth.scale, truth.rotation @ axis_rotation([0, 0, 1], np.pi), truth.translation)
    stay = align(source, target, AlignOptions(init_transform=far.matrix()))
    assert rre_deg(stay.transform.rotation, far.rotation) < 30.0
    assert stay.verdict.doubtful
    assert "fit better at another pose" in stay.diagnostics["guidance"]["doubt"]
    # the pose the doubt points at is one the models offer, never the given start
    index = int(stay.diagnostics["guidance"]["doubt"].split("(alternatives[")[1].split("]")[0])
    assert stay.verdict.alternatives[index].origin != "the given start"
    assert result.diagnostics["guidance"]["doubt"] is None or result.verdict.doubtful


def test_a_wrong_up_axis_gives_a_flagged_result_with_its_reason(pair):
    source, target, truth = pair
    up = np.array([0.0, 0.0, 1.0])
    wrong = axis_rotation([1, 0, 0], np.radians(90.0)) @ truth.rotation @ up
    result = align(source, target, AlignOptions(up_axes=(up, wrong)))
    assert result.verdict.doubtful
    assert result.diagnostics["guidance"]["doubt"]


def test_up_axes_hold_and_fixed_scale_is_kept(pair):
    source, target, truth = pair
    up = np.array([0.0, 0.0, 1.0])
    result = align(source, target, AlignOptions(up_axes=(up, truth.rotation @ up)))
    assert rre_deg(result.transform.rotation, truth.rotation) < 2.0
    assert np.allclose(result.transform.rotation @ up, truth.rotation @ up, atol=1e-9)
    hypotheses = [np.asarray(h["transform"])[:3, :3] for h in result.hypotheses]
    assert all(np.allclose(h @ up / np.linalg.norm(h @ up), truth.rotation @ up, atol=0.3) for h in hypotheses)
    fixed = align(source, target, AlignOptions(fixed_scale=truth.scale * 1.1))
    assert fixed.transform.scale == pytest.approx(truth.scale * 1.1)
    assert rre_deg(fixed.transform.rotation, truth.rotation) < 2.0


def test_up_and_front_axes_decide_which_way_the_model_faces(pair):
    """Up alone leaves the turn about it to the models; the front says which way it faces: the
    answer follows the given fronts, even where they point a half turn away from the truth."""
    source, target, truth = pair
    up, front = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    ups = (up, truth.rotation @ up)
    right = align(source, target, AlignOptions(up_axes=ups, front_axes=(front, truth.rotation @ front)))
    assert rre_deg(right.transform.rotation, truth.rotation) < 2.0
    assert right.diagnostics["guidance"]["front_axes"] is not None
    # A person who says the target faces the other way gets the answer that faces the other way.
    reversed_front = align(source, target, AlignOptions(up_axes=ups, front_axes=(front, -(truth.rotation @ front))))
    turned = truth.rotation @ axis_rotation(up, np.pi)
    assert rre_deg(reversed_front.transform.rotation, turned) < 20.0
    assert rre_deg(reversed_front.transform.rotation, truth.rotation) > 140.0


def test_fronts_keep_only_the_turns_about_up_that_face_them():
    up, front = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    everything = up_rotations(up, up)
    kept = up_rotations(up, up, fronts=(front, front))
    assert len(everything) == 180 and 0 < len(kept) < len(everything) / 3
    assert all((r @ front) @ front >= np.cos(np.radians(GuidanceCriteria().front_reach_deg)) for _, r in kept)
    # in file coordinates the fronts turn with the files' frames as the up axes do
    fronts = hints_from_files(
        AlignOptions(up_axes=([0, 1, 0], [0, 1, 0]), front_axes=([0, 0, 1], [0, 0, 1])), "spz", "ply"
    )
    assert np.allclose(fronts.front_axes[0], [0, 0, -1]) and np.allclose(fronts.front_axes[1], [0, 0, 1])


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(init_transform=np.eye(3)), "shape 4×4"),
        (dict(init_transform=np.diag([1.0, 1, -1, 1])), "determinant"),
        (dict(init_transform=[[1, 2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "scaled rotation"),
        (dict(point_pairs=([[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [1, 0, 0]])), "3..1000 pairs"),
        (dict(point_pairs=([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 0, 0], [0, 1, 0], [0, 0, 1]])), "one line"),
        (dict(point_pairs=([[0, 0, 0]] * 3, [[0, 0, 0]] * 4)), "pair up"),
        (dict(point_pairs={"source": [[0, 0, float("nan")]] * 3, "target": [[0, 0, 0]] * 3}), "NaN"),
        (dict(up_axes=([0, 0, 0], [0, 0, 1])), "must not be zero"),
        (dict(up_axes=[[0, 0, 1]]), "two vectors"),
        (dict(fixed_scale=-1.0), "fixed_scale"),
        (dict(front_axes=([1, 0, 0], [1, 0, 0])), "needs up_axes"),
        (dict(up_axes=([0, 0, 1], [0, 0, 1]), front_axes=([0, 0.1, 1], [1, 0, 0])), "within 20 deg"),
        (dict(up_axes=([0, 0, 1], [0, 0, 1]), front_axes=[[1, 0, 0]]), "two vectors"),
        (dict(init_transform=np.eye(4), point_pairs=([[0, 0, 0], [1, 0, 0], [0, 1, 0]],) * 2), "not both"),
    ],
)
def test_bad_hints_are_refused_with_a_reason(options, message):
    with pytest.raises(ValueError, match=message):
        AlignOptions(**options)


def test_hints_in_file_coordinates_become_internal():
    internal = random_sim3(np.random.default_rng(5))
    in_files = frames.file_transform(internal, "spz", "ply")
    converted = hints_from_files(AlignOptions(init_transform=in_files.matrix()), "spz", "ply")
    assert np.allclose(np.asarray(converted.init_transform), internal.matrix(), atol=1e-9)
    up = hints_from_files(AlignOptions(up_axes=([0, 1, 0], [0, 1, 0])), "spz", "ply").up_axes
    assert np.allclose(up[0], [0, -1, 0]) and np.allclose(up[1], [0, 1, 0])


def test_cli_init_from_a_result_and_its_alternatives(pair, tmp_path):
    from gsa.io import write_ply

    source, target, truth = pair
    write_ply(source, tmp_path / "a.ply")
    write_ply(target, tmp_path / "b.ply")
    result = tmp_path / "r.json"
    result.write_text(json.dumps({"transform": truth.matrix().tolist(), "metrics": {"alternatives": []}}))
    cmd = [sys.executable, "-m", "gsa.cli", "align", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--quiet"]
    ok = subprocess.run(
        cmd + ["--out", str(tmp_path / "o.json"), "--init", str(result)], capture_output=True, text=True
    )
    assert ok.returncode == 0, ok.stderr
    out = json.loads((tmp_path / "o.json").read_text())
    assert rre_deg(np.asarray(out["transform"])[:3, :3] / out["scale"], truth.rotation) < 0.5
    assert out["metrics"]["guidance"]["init_transform"] is True
    bad = subprocess.run(cmd + ["--init", str(result), "--alternative", "2"], capture_output=True, text=True)
    assert bad.returncode == 1
    assert bad.stderr.strip().splitlines() == [f"gsa: error: --alternative 2: {result} lists 0 alternative(s)"]


def test_noisy_clicks_are_not_misclicks():
    rng = np.random.default_rng(3)
    for trial in range(20):
        truth = random_sim3(np.random.default_rng(100 + trial))
        src = rng.uniform(-1, 1, (4, 3))
        spread = np.sqrt(np.mean(np.sum((src - src.mean(0)) ** 2, axis=1)))
        dst = truth.apply(src + rng.normal(0, 0.02 * spread, src.shape))
        fit, report = pairs_transform(src, dst)
        assert report["left_out"] is None
        assert rre_deg(fit.rotation, truth.rotation) < 5.0


@pytest.mark.parametrize(
    "value, expected",
    [
        ("-0.1,0.99,0:0,1,0", ((-0.1, 0.99, 0.0), (0.0, 1.0, 0.0))),
        ("-1e-3,-1,0:0,-1,-0", ((-1e-3, -1.0, 0.0), (0.0, -1.0, 0.0))),
        (".5,1,0:-.5,1,0", ((0.5, 1.0, 0.0), (-0.5, 1.0, 0.0))),
    ],
)
def test_up_axes_that_begin_with_a_minus_sign_are_values_not_options(value, expected):
    """argparse took `--up -0.1,...` for an option ("expected one argument"); half of real up
    vectors begin with a minus sign."""
    from gsa.align.command import _guidance_fields
    from gsa.cli import build_parser

    args = build_parser().parse_args(["align", "a.ply", "b.ply", "--up", value])
    assert _guidance_fields(args)["up_axes"] == expected


def test_front_axes_on_the_command_line_reach_the_options():
    """--front X,Y,Z:X,Y,Z beside --up, minus signs and all, becomes AlignOptions.front_axes (in
    the internal frame once the files' formats are known); without --up it is one error line."""
    from gsa.align.command import _align_options, _guidance_fields
    from gsa.cli import build_parser
    from gsa.cli_base import CliError

    argv = ["align", "a.spz", "b.ply", "--up", "0,1,0:0,-1,0", "--front", "-2,.5,0:-0,0,-1", "--seed", "3"]
    args = build_parser().parse_args(argv)
    assert args.seed == 3 and _guidance_fields(args)["front_axes"] == ((-2.0, 0.5, 0.0), (0.0, 0.0, -1.0))
    options = _align_options(args)
    assert options.front_axes == ((-1.0, 0.0, 0.0), (0.0, 0.0, -1.0))  # across up, unit length
    internal = hints_from_files(options, "spz", "ply")  # SPZ: a half turn about x
    assert np.allclose(internal.front_axes[0], [-1, 0, 0]) and np.allclose(internal.front_axes[1], [0, 0, -1])
    assert np.allclose(internal.up_axes[0], [0, -1, 0])
    for bad, words in (
        (["--front", "1,0,0:1,0,0"], "front_axes needs up_axes"),
        (["--up", "0,1,0:0,1,0", "--front", "1,0,0"], "--front 1,0,0: expected X,Y,Z:X,Y,Z"),
        (["--up", "0,1,0:0,1,0", "--front", "0,1,0:1,0,0"], "within 20 deg"),
    ):
        with pytest.raises(CliError, match=words):
            _align_options(build_parser().parse_args(["align", "a.ply", "b.ply", *bad]))


def test_an_option_after_a_vector_is_still_an_option():
    from gsa.cli import build_parser

    args = build_parser().parse_args(["align", "a.ply", "b.ply", "--up", "-0,1,0:0,1,0", "--seed", "3"])
    assert args.up == "-0,1,0:0,1,0" and args.seed == 3
    with pytest.raises(SystemExit):  # a real unknown option is still refused
        build_parser().parse_args(["align", "a.ply", "b.ply", "--up", "-x"])
