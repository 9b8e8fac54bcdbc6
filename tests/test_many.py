"""N-way registration: the global step on exact synthetic edges, align_many end to
end on small partial captures, and `gsa align-many`."""

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from gsa.align.many import Edge, ManyError, align_many, select_edges, solve_graph
from gsa.align.pipeline import AlignOptions
from gsa.cli import main
from gsa.geometry import euler_xyz
from gsa.io.ply import read_ply, write_ply
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3
from gsa.synth.variants import cut_by_plane


def _graph(n: int, seed: int, noise_deg: float = 0.5):
    """Truth X_k (model k -> reference frame, where the object sits at 0 with size 1) and
    all-pairs edges T_ij = X_j⁻¹ ∘ noise ∘ X_i."""
    rng = np.random.default_rng(seed)
    truth = [Sim3.identity()] + [random_sim3(rng) for _ in range(n - 1)]
    centres = [t.inverse().apply(np.zeros(3)) for t in truth]
    sizes = [1.0 / t.scale for t in truth]
    edges = []
    for i, j in itertools.combinations(range(n), 2):
        noise = Sim3(
            np.exp(rng.normal(0, 0.005)),
            euler_xyz(rng.normal(0, np.radians(noise_deg), 3)),
            rng.normal(0, 0.005, 3),
        )
        edges.append(Edge(i, j, truth[j].inverse() @ noise @ truth[i], confidence=0.8))
    return truth, centres, sizes, edges


def _turned(t: Sim3, axis: int, degrees: float) -> Sim3:
    angles = np.zeros(3)
    angles[axis] = np.radians(degrees)
    return Sim3(1.0, euler_xyz(angles), np.zeros(3)) @ t


def _errors(result, truth, reference=0):
    out = []
    for k, t in enumerate(truth):
        want = truth[reference].inverse() @ t  # model k -> the reference model's frame
        got = result.transforms[k]
        out.append((rre_deg(got.rotation, want.rotation), abs(np.log(got.scale / want.scale))))
    return out


def test_global_step_recovers_truth_and_names_the_corrupted_edge():
    truth, centres, sizes, edges = _graph(6, seed=3)
    bad = 4
    edges[bad].transform = _turned(edges[bad].transform, 0, 90.0)
    edges[bad].confidence = 0.99  # align() was sure of it: only the cycles can tell
    result = solve_graph(6, edges, 0, centres, sizes)
    for rot, log_s in _errors(result, truth):
        assert rot < 1.5 and log_s < 0.02
    assert [k for k, e in enumerate(result.edges) if e.status == "pruned"] == [bad]
    d = result.to_dict()
    name = f"model_{edges[bad].source} -> model_{edges[bad].target}"
    assert d["pruned"] == [name] and d["corrected"] == []
    assert d["cycles"]["measured"]["closing"] < d["cycles"]["measured"]["triangles"]
    assert d["cycles"]["after"]["closing"] == d["cycles"]["after"]["triangles"] > 0


def test_the_corrupted_edge_would_break_a_chain_without_the_cycles():
    # The same corrupted edge, alone on the path to its model (a tree: no cycles), is taken
    # as it is: what the test above relies on the cycles for.
    truth, centres, sizes, edges = _graph(3, seed=4)
    tree = [e for e in edges if (e.source, e.target) in ((0, 1), (1, 2))]
    tree[1].transform = _turned(tree[1].transform, 0, 90.0)
    result = solve_graph(3, tree, 0, centres, sizes)
    assert _errors(result, truth)[2][0] > 80
    assert all(e.status == "kept" for e in result.edges)


def test_a_wrong_edge_with_a_consistent_alternative_is_corrected():
    truth, centres, sizes, edges = _graph(5, seed=5)
    bad = 6
    right = edges[bad].transform
    edges[bad].transform = _turned(right, 1, 180.0)  # a flipped pair
    edges[bad].doubtful = True
    edges[bad].alternatives = [_turned(right, 2, 90.0), right]
    result = solve_graph(5, edges, 0, centres, sizes)
    edge = result.edges[bad]
    assert edge.status == "corrected"
    assert np.allclose(edge.used.matrix(), right.matrix())
    assert edge.measured_residual["rotation_deg"] > 170 and edge.residual["rotation_deg"] < 3
    assert len(result.to_dict()["corrected"]) == 1
    for rot, _ in _errors(result, truth):
        assert rot < 1.5


def _flip_member(edges, member, centre, turned_edges, half_turn=None):
    """Model `member` turned half a turn about its centroid (about its y axis, or the rotation
    half_turn), as seen by turned_edges (indices): those measure the turned frame, with the
    right pose as their alternative; the others measure the right frame, with the turned one
    as theirs."""
    half = Sim3(1.0, euler_xyz(np.array([0.0, np.pi, 0.0])) if half_turn is None else half_turn, np.zeros(3))
    flip = Sim3(1.0, np.eye(3), centre) @ half @ Sim3(1.0, np.eye(3), -centre)
    for k, e in enumerate(edges):
        if member not in (e.source, e.target):
            continue
        right = e.transform
        turned = right @ flip if e.source == member else flip.inverse() @ right
        e.transform, e.alternatives = (turned, [right]) if k in turned_edges else (right, [turned])


def test_the_most_plausible_frame_wins_where_the_cycles_tie():
    # Model 2 measured turned half a turn on two of its four edges, right on the other two: the
    # turned edges agree with each other around their triangle (0, 1, 2) as the right ones do
    # around (2, 3, 4), so the cycles tie. Every edge doubtful, its poses scored by the semantic
    # tie-break, which kept each measured pose (no alternative scored 1.5x it) but scored the
    # right pose nearly as high on the turned edges and the turned one low on the right edges:
    # summed over model 2's edges, the right frame is the more plausible one.
    truth, centres, sizes, edges = _graph(5, seed=6)
    turned_edges = {k for k, e in enumerate(edges) if (e.source, e.target) in ((0, 2), (1, 2))}
    _flip_member(edges, 2, centres[2], turned_edges)
    for k, e in enumerate(edges):
        e.confidence, e.doubtful = 0.05, True
        e.scores = [0.3, 0.28] if k in turned_edges else [0.3] + [0.15] * len(e.alternatives)
    result = solve_graph(5, edges, 0, centres, sizes)
    for rot, _ in _errors(result, truth):
        assert rot < 1.5
    assert {k for k, e in enumerate(result.edges) if e.status == "corrected"} == turned_edges
    # The scores the other way round: the turned frame is the more plausible one, and taken.
    for k, e in enumerate(edges):
        e.used, e.status = None, "kept"
        e.scores = [0.3, 0.15] if k in turned_edges else [0.3] + [0.28] * len(e.alternatives)
    flipped = solve_graph(5, edges, 0, centres, sizes)
    assert _errors(flipped, truth)[2][0] > 170


def test_one_edge_keeps_the_pose_it_measured_whatever_its_alternatives_score():
    # A lone edge has no cycle to outvote it: its alternatives, scored below the tie-break's
    # switch ratio times the measured pose, do not replace it.
    truth, centres, sizes, edges = _graph(2, seed=7)
    _flip_member(edges, 1, centres[1], set())
    edges[0].scores = [0.2, 0.29]
    result = solve_graph(2, edges, 0, centres, sizes)
    assert result.edges[0].status == "kept" and _errors(result, truth)[1][0] < 1.5


def test_a_corrected_edge_lends_no_confidence_of_its_own():
    # align() was sure (0.99) of the pose it measured, not of the alternative the cycles chose:
    # model 4, reached otherwise only by weak edges, is only as sure as those.
    truth, centres, sizes, edges = _graph(5, seed=5)
    bad = 6
    assert (edges[bad].source, edges[bad].target) == (1, 4)
    right = edges[bad].transform
    edges[bad].transform = _turned(right, 1, 180.0)
    edges[bad].confidence = 0.99
    edges[bad].alternatives = [right]
    for e in edges:
        if 4 in (e.source, e.target) and e is not edges[bad]:
            e.confidence = 0.2
    result = solve_graph(5, edges, 0, centres, sizes)
    assert result.edges[bad].status == "corrected"
    for rot, _ in _errors(result, truth):
        assert rot < 1.5
    assert result.confidences[4] == pytest.approx(0.2)
    assert result.to_dict()["models"][4]["doubtful"]
    assert min(result.confidences[:4]) == pytest.approx(0.8)


def test_a_model_whose_most_confident_edge_is_overruled_is_contested():
    # Three weak edges of model 4 agree on a half turn of it, the one confident edge is right:
    # the cycles side with the three (they agree with each other everywhere), so the result for
    # model 4 is wrong. It must not be a confident wrong result: model 4 is contested, doubtful.
    truth, centres, sizes, edges = _graph(5, seed=6)
    flip = Sim3(1.0, euler_xyz(np.array([0.0, np.pi, 0.0])), np.zeros(3))
    for e in edges:
        if e.target == 4:
            if e.source == 3:
                e.confidence = 1.0  # the right one
                e.alternatives = [flip.inverse() @ e.transform]
            else:
                e.transform = flip.inverse() @ e.transform  # model 4 measured half-turned by three edges
                e.confidence = 0.7
    result = solve_graph(5, edges, 0, centres, sizes)
    assert _errors(result, truth)[4][0] > 170  # the cycles' answer: wrong, as set up
    right = next(k for k, e in enumerate(edges) if (e.source, e.target) == (3, 4))
    assert result.edges[right].status in ("pruned", "corrected")
    assert result.contested == {4: [right]}
    model = result.to_dict()["models"][4]
    assert model["doubtful"] and model["confidence"] >= 0.5  # flagged by the contest, not the number
    assert model["contested_by"] == ["model_3 -> model_4"]
    assert not any(m["doubtful"] for m in result.to_dict()["models"][:4])


def test_an_overruled_edge_no_surer_than_the_agreeing_ones_contests_nothing():
    truth, centres, sizes, edges = _graph(6, seed=3)
    bad = 4
    edges[bad].transform = _turned(edges[bad].transform, 0, 90.0)
    edges[bad].confidence = 0.85  # as sure as the others (0.8), within the margin
    result = solve_graph(6, edges, 0, centres, sizes)
    assert result.edges[bad].status == "pruned" and result.contested == {}
    edges[bad].confidence = 0.99
    assert solve_graph(6, edges, 0, centres, sizes).contested == {edges[bad].target: [bad]}


def test_reference_other_than_the_first_and_per_model_confidence():
    truth, centres, sizes, edges = _graph(4, seed=6)
    for e in edges:
        if 3 in (e.source, e.target):
            e.confidence = 0.2
    result = solve_graph(4, edges, 2, centres, sizes)
    assert np.allclose(result.transforms[2].matrix(), np.eye(4))
    for rot, _ in _errors(result, truth, reference=2):
        assert rot < 1.5
    # model 3 rests on weak edges only; a triangle of confident edges lifts the others
    assert result.confidences[2] == 1.0
    assert result.confidences[3] == pytest.approx(0.2)
    assert min(result.confidences[:2]) == pytest.approx(0.8)


def test_solve_graph_refuses_bad_input():
    with pytest.raises(ManyError):
        solve_graph(1, [Edge(0, 0, Sim3.identity())])
    with pytest.raises(ManyError):
        solve_graph(2, [Edge(0, 1, Sim3.identity())], reference=5)
    with pytest.raises(ManyError):
        solve_graph(3, [Edge(0, 3, Sim3.identity())])


def test_sparse_edges_are_connected_and_fewer_than_all_pairs():
    models = [make_object(c, seed=s, n_gaussians=300) for c in ("car", "chair", "boat") for s in range(4)]
    pairs = select_edges(models, "auto")
    assert len(pairs) < 12 * 11 // 2
    parent = list(range(12))

    def root(k):
        while parent[k] != k:
            k = parent[k]
        return k

    for i, j in pairs:
        parent[root(i)] = root(j)
    assert len({root(k) for k in range(12)}) == 1
    assert len(select_edges(models[:5], "auto")) == 10


@pytest.fixture(scope="module")
def captures():
    """Three partial captures of one object, each in its own Sim(3)."""
    rng = np.random.default_rng(11)
    models, truth = [], []
    for k in range(3):
        m = cut_by_plane(make_object("car", seed=2, n_gaussians=2000, sample_seed=20 + k), rng, keep=(0.75, 0.9))
        t = random_sim3(rng, scale_range=(0.5, 2.0))
        models.append(m.transformed(t))
        truth.append(t)
    return models, truth


def test_align_many_end_to_end(captures):
    models, truth = captures
    result = align_many(models, ["a", "b", "c"], reference=1, options=AlignOptions(stages=("coarse",)))
    for k in range(3):
        want = truth[1] @ truth[k].inverse()
        assert rre_deg(result.transforms[k].rotation, want.rotation) < 2.0
        assert abs(np.log(result.transforms[k].scale / want.scale)) < 0.02
    assert len(result.edges) == 3 and all(e.status == "kept" for e in result.edges)
    d = result.to_dict()
    assert d["reference"] == "b" and [m["name"] for m in d["models"]] == ["a", "b", "c"]
    assert d["timings"]["edges"] == 3 and d["cycles"]["measured"]["triangles"] == 1
    json.dumps(d)  # all plain JSON


def test_align_many_refuses_one_model(captures):
    with pytest.raises(ManyError):
        align_many(captures[0][:1])
    with pytest.raises(ManyError):
        align_many(captures[0][:2], names=["x", "x"])


def _gsa(*args):
    return subprocess.run([sys.executable, "-m", "gsa.cli", *map(str, args)], capture_output=True, text=True)


def test_cli_writes_many_json_and_merged_model(captures, tmp_path):
    # Two of the captures (one edge): the graph work is tested above, this is the command.
    models, truth = captures
    folder = tmp_path / "in"
    folder.mkdir()
    for name, m in zip(("a", "b"), models):
        write_ply(m, folder / f"{name}.ply")
    out = tmp_path / "out"
    r = _gsa(
        "align-many", folder, "--out", out, "--reference", "b", "--stages", "coarse", "--merged-out", out / "m.ply"
    )
    assert r.returncode == 0, r.stderr
    data = json.loads((out / "many.json").read_text())
    assert data["reference"] == "b" and len(data["edges"]) == 1
    for m in data["models"]:
        k = "ab".index(m["name"])
        want = truth[1] @ truth[k].inverse()
        assert rre_deg(np.asarray(m["rotation"]), want.rotation) < 2.0
    assert len(read_ply(out / "m.ply")) == len(models[0]) + len(models[1])


@pytest.mark.parametrize(
    "args, message",
    [
        (["nowhere.ply", "nowhere2.ply"], "no such file"),
        (["{a}"], "at least two models"),
        (["{a}", "{b}", "--reference", "zzz"], "--reference zzz"),
        (["{dir}/*.nothing"], "no file matches"),
    ],
)
def test_cli_bad_input_is_one_error_line(tmp_path, capsys, args, message):
    m = make_object("car", seed=1, n_gaussians=200)
    a, b = write_ply(m, tmp_path / "a.ply"), write_ply(m, tmp_path / "b.ply")
    args = [x.format(a=a, b=b, dir=tmp_path) for x in args]
    assert main(["align-many", *args, "--out", str(tmp_path / "out")]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gsa: error:") and message in lines[0]
    assert not (tmp_path / "out" / "many.json").exists()


def test_bench_n_way_names_the_wrong_edge(monkeypatch, tmp_path, capsys):
    # The protocol's bookkeeping on exact edges (the pairwise alignments are what the real run
    # measures; here they are built from the truth so the test stays fast).
    from benchmarks import nway

    _, truth = nway.captures(True, 0)

    def exact_edges(models, pairs, options=None, progress=None):
        return [Edge(i, j, truth[j] @ truth[i].inverse(), confidence=0.9) for i, j in pairs]

    monkeypatch.setattr(nway, "pairwise_edges", exact_edges)
    rows = nway.protocol_nway(True, 0, tmp_path, cross=False)
    by = {r["method"]: r for r in rows}
    assert by["pairwise to reference · one edge wrong"]["success_rate"] < 1.0
    wrong = by["global step · one edge wrong"]
    assert wrong["success_rate"] == 1.0 and wrong["mean_rre_deg"] < 1e-3
    assert wrong["wrong_edge_named"] and wrong["pruned"] == [wrong["wrong_edge"]]
    assert by["global step · as measured"]["pruned"] == []
    assert (tmp_path / "n-way.json").exists()
    assert "the wrong edge model_0 -> model_3 named" in capsys.readouterr().out


def test_global_step_on_a_sparse_graph_with_two_wrong_edges():
    # 12 models, each joined to its next three (a ring with chords, as the sparse graph is):
    # 36 edges instead of 66; two wrong ones, far apart.
    truth, centres, sizes, all_edges = _graph(12, seed=8)
    keep = {(i, (i + d) % 12) for i in range(12) for d in (1, 2, 3)}
    edges = [e for e in all_edges if (e.source, e.target) in keep or (e.target, e.source) in keep]
    assert len(edges) == 36
    wrong = {3, 20}
    for k in wrong:
        edges[k].transform = _turned(edges[k].transform, 2, 120.0)
    result = solve_graph(12, edges, 0, centres, sizes)
    assert {k for k, e in enumerate(result.edges) if e.status == "pruned"} == wrong
    for rot, log_s in _errors(result, truth):
        assert rot < 1.5 and log_s < 0.02


def _tetra_meshes(folder, category: str, count: int) -> None:
    """count irregular tetrahedra (no turn maps one onto itself), one proportion each."""
    for k in range(count):
        v = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]], np.float32) * (1.0 + 0.1 * k)
        f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
        c = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], np.float16)
        np.savez(folder / f"{category}_{k}.npz", V=v, F=f, C=c)


def test_bench_n_way_cross_instance_sets(monkeypatch, tmp_path):
    # The cross-instance bookkeeping on exact edges (built from the truth) with one edge to the
    # reference turned 90° and the right pose among its alternatives: the pairwise-to-reference
    # row counts that member wrong, the global step corrects it; a category with too few
    # instances is left out.
    from benchmarks import nway

    _tetra_meshes(tmp_path, "tetra", nway.MEMBERS)
    _tetra_meshes(tmp_path, "few", nway.MEMBERS - 1)
    sets = nway.cross_instance_sets(tmp_path, True, 0)
    assert [s[0] for s in sets] == ["tetra"] and len(sets[0][1]) == nway.MEMBERS
    _, models, truth, symmetries = sets[0]
    assert symmetries == [[]] * nway.MEMBERS
    assert all(abs(np.log(t.scale)) <= np.log(5.0) + 1e-9 for t in truth)

    def exact_edges(models, pairs, options=None, progress=None):
        out = []
        for i, j in pairs:
            right = truth[j] @ truth[i].inverse()
            e = Edge(i, j, right, confidence=0.9)
            if (i, j) == (0, 4):
                e.transform, e.alternatives = _turned(right, 0, 90.0), [right]
            out.append(e)
        return out

    monkeypatch.setattr(nway, "pairwise_edges", exact_edges)
    rows, lines = nway._cross_rows(True, 0, tmp_path)
    by = {r["method"]: r for r in rows}
    assert by["cross-instance · every pair"]["success_rate"] == pytest.approx(0.9)
    assert by["cross-instance · pairwise to reference"]["success_rate"] == pytest.approx(0.75)
    after = by["cross-instance · global step"]
    assert after["success_rate"] == 1.0 and after["mean_rre_deg"] < 1e-3 and after["mean_scale_error_pct"] < 1e-6
    assert any(line.startswith("| tetra | 90 % | 75 % | 100 % | 0 / 1 | 1 of 1 |") for line in lines)


def test_write_captures_gives_exactly_the_count_asked(tmp_path):
    from benchmarks import nway

    paths = nway.write_captures(tmp_path, 3, 1500)
    assert [p.name for p in paths] == ["capture_0.ply", "capture_1.ply", "capture_2.ply"]
    assert [len(read_ply(p)) for p in paths] == [1500] * 3


def _frame_evidence(truth, seed: int, misleading: dict | None = None):
    """Frames that move with the members (model k's axes: a random relabelling of the truth's
    rotation into the reference) and grid scores that favour each edge's true relabelling by
    one standard deviation, except `misleading` edges {(i, j): by how much the half turn about
    the first axis leads instead}."""
    from gsa.align import many_frames
    from gsa.canonical import SIGNED_PERMUTATIONS
    from gsa.manhattan import NormalFrame

    rng = np.random.default_rng(seed)
    perms = [np.eye(3)] + [SIGNED_PERMUTATIONS[rng.integers(24)] for _ in truth[1:]]
    frames = [NormalFrame(p @ t.rotation, 0.5) for p, t in zip(perms, truth)]
    shape = {}
    for i, j in itertools.combinations(range(len(truth)), 2):
        true = many_frames._index_of(perms[j] @ perms[i].T)
        z = np.zeros(24)
        z[true] = 1.0
        if misleading and (i, j) in misleading:
            z[many_frames._index_of(np.diag([1.0, -1.0, -1.0]) @ perms[j] @ perms[i].T)] = 1.0 + misleading[(i, j)]
        shape[(i, j)] = z
    return many_frames.FrameEvidence(frames, shape)


def test_frames_put_right_a_member_flipped_on_every_edge():
    # Model 2 measured turned half a turn on all four of its edges (doubtful, nothing else
    # offered): the cycles cannot tell (the flips agree with one another), and without the
    # frames it stays turned. Its frames' grid scores favour the right relabelling on three of
    # its edges and the turn on one: one relabelling per member, summed over its edges, puts it
    # right, its edges turned onto that relabelling and marked corrected.
    truth, centres, sizes, edges = _graph(5, seed=8, noise_deg=0.0)
    evidence = _frame_evidence(truth, seed=8, misleading={(0, 2): 0.5})
    flipped = {k for k, e in enumerate(edges) if 2 in (e.source, e.target)}
    axes = evidence.frames[2].axes  # the half turn about one of model 2's frame axes: a relabelling
    _flip_member(edges, 2, centres[2], flipped, axes.T @ np.diag([1.0, -1.0, -1.0]) @ axes)
    for e in edges:
        e.alternatives, e.confidence = [], 0.05
        e.doubtful = True
    import copy

    alone = solve_graph(5, copy.deepcopy(edges), 0, centres, sizes)
    assert _errors(alone, truth)[2][0] > 170
    result = solve_graph(5, edges, 0, centres, sizes, frames=evidence)
    for rot, log_s in _errors(result, truth):
        assert rot < 1.5 and log_s < 0.02
    assert {k for k, e in enumerate(result.edges) if e.status == "corrected"} == flipped


def test_a_confident_edge_outweighs_the_frames_grid_scores():
    # Every grid score of model 3's edges favours its half turn by half a standard deviation,
    # but its edges are confident (0.8) and right: they keep their poses and model 3 stays right.
    truth, centres, sizes, edges = _graph(4, seed=9)
    misleading = {(i, j): 0.5 for i, j in itertools.combinations(range(4), 2) if 3 in (i, j)}
    result = solve_graph(4, edges, 0, centres, sizes, frames=_frame_evidence(truth, seed=9, misleading=misleading))
    for rot, _ in _errors(result, truth):
        assert rot < 1.5
    assert all(e.status == "kept" for e in result.edges)


def test_edges_the_local_shapes_hold_are_not_turned_by_the_frames_grid_scores():
    # Model 3's grid scores favour its half turn by two standard deviations on each of its
    # edges, and every edge is doubtful and barely confident: the frames turn model 3 over.
    # Where the models' local shapes hold each edge's measured pose (two captures of one object:
    # align()'s local_agreement over the share needed), the grids are not what decides and no
    # edge is turned onto a relabelling: every model stays right.
    import copy

    truth, centres, sizes, edges = _graph(4, seed=9, noise_deg=0.0)
    misleading = {(i, j): 2.0 for i, j in itertools.combinations(range(4), 2) if 3 in (i, j)}
    evidence = _frame_evidence(truth, seed=9, misleading=misleading)
    for e in edges:
        e.alternatives, e.confidence, e.doubtful = [], 0.05, True
    turned = solve_graph(4, copy.deepcopy(edges), 0, centres, sizes, frames=evidence)
    assert _errors(turned, truth)[3][0] > 170
    for e in edges:
        e.agreements, e.agreement_needed = [0.12], 0.05
    result = solve_graph(4, edges, 0, centres, sizes, frames=evidence)
    for rot, log_s in _errors(result, truth):
        assert rot < 1.5 and log_s < 0.02
    assert all(e.status == "kept" for e in result.edges)


def test_the_local_shapes_weigh_an_edges_poses_where_they_hold_any():
    from gsa.align.many import held_poses, pose_weights

    edge = Edge(0, 1, Sim3.identity(), confidence=0.5, alternatives=[Sim3.identity()] * 3, scores=[0.1, 0.4, 0.2, 0.3])
    by_scores = pose_weights(edge)
    assert np.argmax(by_scores) == 1 and not held_poses(edge).any()  # unknown shares: the semantic scores
    edge.agreements, edge.agreement_needed = [0.14, 0.07, 0.02, None], 0.05
    assert held_poses(edge).tolist() == [True, True, False, False]
    assert pose_weights(edge) == pytest.approx([0.5, 0.25, 0.0, 0.0])
    edge.agreements = [0.01, 0.02, 0.03, 0.04]  # none held (other instances): the scores again
    assert pose_weights(edge) == pytest.approx(by_scores)


def test_the_members_relabellings_are_the_best_assignment():
    # The beam search against every assignment of 4 members (24³), on random grid scores and
    # no belief of the edges' own (so the scores alone decide).
    from gsa.align import many_frames
    from gsa.manhattan import NormalFrame

    rng = np.random.default_rng(11)
    frames = [NormalFrame(np.eye(3), 0.5)] * 4
    shape = {p: rng.normal(size=24) for p in itertools.combinations(range(4), 2)}
    evidence = many_frames.FrameEvidence(frames, shape)
    edges = [Edge(i, j, Sim3.identity()) for i, j in shape]
    got = many_frames.synchronise(4, 0, edges, evidence, [np.zeros(24)] * len(edges))

    def total(g):
        return sum(z[many_frames.RELATIVE[g[j], g[i]]] for (i, j), z in shape.items())

    best = max(((many_frames.IDENTITY, *rest) for rest in itertools.product(range(24), repeat=3)), key=total)
    assert got[0] == many_frames.IDENTITY
    assert total(got) == pytest.approx(total(best))


def test_an_edge_off_its_members_frames_or_on_no_cycle_is_not_turned():
    # The same flipped member, but its edges' half turn is about an axis of no frame (the
    # frames do not explain the edges): nothing is turned onto the frames, and the member stays
    # as the cycles left it. And a lone edge (no cycle) keeps its pose whatever the grid says.
    truth, centres, sizes, edges = _graph(5, seed=8, noise_deg=0.0)
    evidence = _frame_evidence(truth, seed=8)
    flipped = {k for k, e in enumerate(edges) if 2 in (e.source, e.target)}
    off_axis = (
        evidence.frames[2].axes.T @ euler_xyz(np.radians([180.0, 0.0, 0.0])) @ euler_xyz(np.radians([0, 0, 35.0]))
    )
    _flip_member(edges, 2, centres[2], flipped, off_axis)
    for e in edges:
        e.alternatives, e.confidence, e.doubtful = [], 0.05, True
    result = solve_graph(5, edges, 0, centres, sizes, frames=evidence)
    assert _errors(result, truth)[2][0] > 30 and result.doubtful(2)
    assert not any(e.status == "corrected" for e in result.edges)

    truth, centres, sizes, edges = _graph(2, seed=9, noise_deg=0.0)
    edges[0].confidence, edges[0].doubtful = 0.05, True
    lone = _frame_evidence(truth, seed=9, misleading={(0, 1): 2.0})
    result = solve_graph(2, edges, 0, centres, sizes, frames=lone)
    assert result.edges[0].status == "kept" and _errors(result, truth)[1][0] < 1.5
