"""Guided alignment over both APIs against the real stack (uvicorn + RQ worker + redis-server):
the hints as job options (init_transform, point_pairs, up_axes, front_axes, fixed_scale), their 422 /
INVALID_ARGUMENT, and POST /v1/jobs/{id}:refine / RefineJob making linked follow-up jobs."""

from __future__ import annotations

import json

import grpc
import httpx
import numpy as np
import pytest

from service.rpc.generated import alignment_pb2 as pb
from service.rpc.generated import alignment_pb2_grpc as pbg
from tests.service.conftest import ALICE, BOB, assert_problem, submit_slow_job, wait_job

pytestmark = pytest.mark.slow  # starts servers and worker processes

# A confident answer lists its alternatives only when asked: :refine takes one of them.
ALIGN = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0, "outputs": ["result"], "alternatives": "always"}
AUTH = (("authorization", "Bearer key-alice"),)
DOWN = np.array([0.0, -1.0, 0.0])  # the generated objects' up (-y, the RDF convention)
FRONT = np.array([1.0, 0.0, 0.0])  # an axis across it: what a person would call the chair's front


@pytest.fixture(scope="module")
def guided_pair(tmp_path_factory):
    """A generated chair (3k Gaussians) and its copy moved by a random Sim(3): the truth."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object
    from gsa.synth.perturb import random_sim3

    d = tmp_path_factory.mktemp("guided")
    src = make_object("chair", seed=5, n_gaussians=3000)
    gt = random_sim3(np.random.default_rng(7), scale_range=(0.5, 2.0), translation=1.0)
    write_ply(src, d / "source.ply")
    write_ply(src.transformed(gt), d / "target.ply")
    return {"source": d / "source.ply", "target": d / "target.ply", "gt": gt, "means": src.means}


@pytest.fixture(scope="module")
def assets(stack, guided_pair):
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        ids = {}
        for k in ("source", "target"):
            with open(guided_pair[k], "rb") as fh:
                r = c.post("/v1/assets", files={"file": (f"{k}.ply", fh)})
            assert r.status_code == 201, r.text
            ids[k] = r.json()["id"]
    return ids


def rre_deg(matrix, truth) -> float:
    rot = np.asarray(matrix, np.float64)[:3, :3]
    rot = rot / np.cbrt(np.linalg.det(rot))
    cos = (np.trace(rot.T @ truth.rotation) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def picked_pairs(guided_pair, seed=0) -> dict:
    """Four source points and where the truth puts them. Exact: the service is under test here,
    not the library's tolerance of noisy clicks (gsa.align.guided, its own tests and benchmarks)."""
    means, gt = guided_pair["means"], guided_pair["gt"]
    src = means[np.random.default_rng(seed).choice(len(means), 4, replace=False)].astype(np.float64)
    return {"source": src.tolist(), "target": gt.apply(src).tolist()}


def job_json(http, assets, options) -> httpx.Response:
    return http.post("/v1/jobs", json={"source": assets["source"], "target": assets["target"], "options": options})


def test_up_axes_job_over_http(http, guided_pair):
    up = [DOWN.tolist(), (guided_pair["gt"].rotation @ DOWN).tolist()]
    with open(guided_pair["source"], "rb") as s, open(guided_pair["target"], "rb") as t:
        r = http.post(
            "/v1/jobs",
            files=[("source", ("source.ply", s)), ("target", ("target.ply", t))],
            data={"options": json.dumps({**ALIGN, "up_axes": up})},
        )
    assert r.status_code == 202, r.text
    assert r.json()["options"]["up_axes"] == up
    done = wait_job(http, r.json()["id"], timeout=120)
    assert done["state"] == "succeeded", done
    res = done["result"]
    assert rre_deg(res["transform"], guided_pair["gt"]) < 2.0
    guidance = res["metrics"]["guidance"]
    np.testing.assert_allclose(guidance["up_axes"][1], up[1], atol=1e-9)  # PLY: file frame = internal frame
    assert guidance["point_pairs"] is None and guidance["init_transform"] is False
    assert "parent_job" not in res and done["children"] == [] and done["parent_job"] is None


def test_point_pairs_and_fixed_scale_job(http, assets, guided_pair):
    pairs = picked_pairs(guided_pair)
    r = job_json(http, assets, {**ALIGN, "point_pairs": pairs, "fixed_scale": guided_pair["gt"].scale})
    assert r.status_code == 202, r.text
    done = wait_job(http, r.json()["id"], timeout=120)
    assert done["state"] == "succeeded", done
    res = done["result"]
    assert rre_deg(res["transform"], guided_pair["gt"]) < 2.0
    assert res["scale"] == pytest.approx(guided_pair["gt"].scale, rel=1e-9)
    guidance = res["metrics"]["guidance"]
    assert guidance["point_pairs"] == 4 and guidance["start"]["from"] == "point_pairs"
    assert guidance["fixed_scale"] == pytest.approx(guided_pair["gt"].scale)


def up_and_front(guided_pair) -> dict:
    """The true up and front axes of the pair (PLY: the files' coordinates are the internal ones)."""
    rotation = guided_pair["gt"].rotation
    return {
        "up_axes": [DOWN.tolist(), (rotation @ DOWN).tolist()],
        "front_axes": [FRONT.tolist(), (rotation @ FRONT).tolist()],
    }


@pytest.fixture(scope="module")
def front_parent(stack, assets, guided_pair):
    """A finished job given the true up and front axes."""
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        r = job_json(c, assets, {**ALIGN, **up_and_front(guided_pair)})
        assert r.status_code == 202, r.text
        assert r.json()["options"]["front_axes"] == up_and_front(guided_pair)["front_axes"]
        return wait_job(c, r.json()["id"], timeout=120)


def test_up_and_front_axes_job(front_parent, guided_pair):
    assert front_parent["state"] == "succeeded", front_parent
    res = front_parent["result"]
    assert rre_deg(res["transform"], guided_pair["gt"]) < 2.0
    guidance = res["metrics"]["guidance"]
    hints = up_and_front(guided_pair)
    np.testing.assert_allclose(guidance["front_axes"], hints["front_axes"], atol=1e-9)  # already across up, unit
    np.testing.assert_allclose(guidance["up_axes"], hints["up_axes"], atol=1e-9)


def test_refine_keeps_or_drops_the_parents_front_axes(http, front_parent, guided_pair):
    """Kept with the parent's up axes; dropped by null, and by new up axes that come without
    fronts (the parent's fronts are stated about its own up); replaced when given."""
    hints = up_and_front(guided_pair)
    url = f"/v1/jobs/{front_parent['id']}:refine"
    pairs = {"point_pairs": picked_pairs(guided_pair, seed=5)}
    made = []

    def refine(body) -> dict:
        r = http.post(url, json={**pairs, **body})
        assert r.status_code == 202, r.text
        made.append(r.json()["id"])
        return r.json()["options"]

    kept = refine({})
    assert kept["front_axes"] == hints["front_axes"] and kept["up_axes"] == hints["up_axes"]
    assert refine({"up_axes": hints["up_axes"]})["front_axes"] == hints["front_axes"]  # the same up
    assert "front_axes" not in refine({"front_axes": None})
    new_up = refine({"up_axes": [[0, -1, 0], [0, -1, 0]]})
    assert "front_axes" not in new_up and new_up["up_axes"] == [[0, -1, 0], [0, -1, 0]]
    no_up = refine({"up_axes": None})
    assert "front_axes" not in no_up and "up_axes" not in no_up
    turned = [hints["front_axes"][0], [-v for v in hints["front_axes"][1]]]
    assert refine({"front_axes": turned})["front_axes"] == turned
    # A front the parent's up makes invalid, given with the refine: 422 naming it, nothing made.
    along_up = {**pairs, "front_axes": [DOWN.tolist(), hints["front_axes"][1]]}
    body = assert_problem(http.post(url, json=along_up), 422, "invalid-input")
    assert body["option"] == "front_axes" and "within 20 deg" in body["detail"], body
    assert http.get(f"/v1/jobs/{front_parent['id']}").json()["children"] == made
    # The kept one runs as its parent did: the fronts reach the library.
    done = wait_job(http, made[0], timeout=120)
    assert done["state"] == "succeeded", done
    np.testing.assert_allclose(done["result"]["metrics"]["guidance"]["front_axes"], hints["front_axes"], atol=1e-9)
    for job_id in made[1:]:
        http.post(f"/v1/jobs/{job_id}:cancel")
    for job_id in made[1:]:
        wait_job(http, job_id, timeout=120)


BAD_HINTS = [
    ({"init_transform": [[1, 0, 0, 0]]}, "init_transform", "4×4"),
    ({"init_transform": np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}, "init_transform", "determinant"),
    ({"init_transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 1]]}, "init_transform", "last row"),
    ({"point_pairs": {"source": [[0, 0, 0], [1, 0, 0]], "target": [[0, 0, 0], [1, 0, 0]]}}, "point_pairs", "3.."),
    ({"point_pairs": {"source": [[0, 0, 0], [1, 0, 0], [2, 0, 0]], "target": [[0, 0, 0]] * 3}}, "point_pairs", ""),
    ({"point_pairs": {"from": []}}, "point_pairs", "source"),
    ({"up_axes": [[0, 0, 0], [0, 1, 0]]}, "up_axes", "zero"),
    ({"up_axes": [[0, 1, 0]]}, "up_axes", "two vectors"),
    ({"front_axes": [[1, 0, 0], [1, 0, 0]]}, "front_axes", "needs up_axes"),
    ({"up_axes": [[0, 1, 0], [0, 1, 0]], "front_axes": [[0, 0, 0], [1, 0, 0]]}, "front_axes", "zero"),
    ({"up_axes": [[0, 1, 0], [0, 1, 0]], "front_axes": [[1, 0, 0], [0, -1, 0.1]]}, "front_axes", "within 20 deg"),
    ({"up_axes": [[0, 1, 0], [0, 1, 0]], "front_axes": [[1, 0, 0]]}, "front_axes", "two vectors"),
    ({"up_axes": [[0, 0, 0], [0, 1, 0]], "front_axes": [[1, 0, 0], [1, 0, 0]]}, "up_axes", "zero"),
    ({"fixed_scale": 0}, "fixed_scale", "1e-06"),
    ({"fixed_scale": -2.5}, "fixed_scale", ""),
    (
        {
            "init_transform": np.eye(4).tolist(),
            "point_pairs": {"source": np.eye(3).tolist(), "target": np.eye(3).tolist()},
        },
        "point_pairs",
        "not both",
    ),
]


@pytest.mark.parametrize(("options", "option", "words"), BAD_HINTS)
def test_bad_hints_are_422_naming_the_option(http, assets, options, option, words):
    before = len(http.get("/v1/jobs", params={"limit": 200}).json()["items"])
    body = assert_problem(job_json(http, assets, {**ALIGN, **options}), 422, "invalid-input")
    assert body["option"] == option and words in body["detail"], body
    assert option in body["detail"], body
    assert len(http.get("/v1/jobs", params={"limit": 200}).json()["items"]) == before  # nothing created


def test_bad_hint_in_multipart_is_422(http, guided_pair):
    with open(guided_pair["source"], "rb") as s, open(guided_pair["target"], "rb") as t:
        r = http.post(
            "/v1/jobs",
            files=[("source", ("source.ply", s)), ("target", ("target.ply", t))],
            data={"options": json.dumps({**ALIGN, "up_axes": [[0, 0, 0], [0, 1, 0]]})},
        )
    assert assert_problem(r, 422)["option"] == "up_axes"


@pytest.fixture(scope="module")
def parent(stack, assets):
    """A finished automatic job on the pair, with its alternatives."""
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        r = job_json(c, assets, ALIGN)
        assert r.status_code == 202, r.text
        done = wait_job(c, r.json()["id"], timeout=120)
    assert done["state"] == "succeeded", done
    assert done["result"]["metrics"]["alternatives"], done["result"]["metrics"]
    return done


def test_refine_from_an_alternative_then_from_pairs(http, stack, assets, guided_pair, parent):
    from gsa.align.pipeline import AlignOptions, align
    from gsa.io.ply import read_ply
    from gsa.sim3 import Sim3

    assert rre_deg(parent["result"]["transform"], guided_pair["gt"]) < 2.0
    alternative = parent["result"]["metrics"]["alternatives"][1]
    r = http.post(f"/v1/jobs/{parent['id']}:refine", json={"alternative": 1})
    assert r.status_code == 202, r.text
    child = r.json()
    assert child["parent_job"] == parent["id"] and r.headers["location"] == f"/v1/jobs/{child['id']}"
    assert child["links"]["parent"] == f"/v1/jobs/{parent['id']}"
    assert (child["sources"], child["target"]) == (parent["sources"], parent["target"])  # the same inputs
    np.testing.assert_allclose(child["options"]["init_transform"], alternative["transform"], atol=1e-12)
    assert {k: v for k, v in child["options"].items() if k != "init_transform"} == parent["options"]
    got = http.get(f"/v1/jobs/{parent['id']}").json()
    assert got["children"] == [child["id"]]

    done = wait_job(http, child["id"], timeout=120)
    assert done["state"] == "succeeded", done
    res = done["result"]
    assert res["parent_job"] == parent["id"]
    assert res["metrics"]["guidance"]["init_transform"] is True
    assert res["metrics"]["guidance"]["start"]["from"] == "init_transform"
    # A local refinement of the chosen pose (not a jump back to the automatic answer) ...
    start = Sim3.from_matrix(np.asarray(alternative["transform"]))
    assert rre_deg(res["transform"], start) < 5.0
    # ... and exactly what the library does from it.
    opts = AlignOptions(stages=("coarse",), coarse_iterations=30, seed=0, init_transform=alternative["transform"])
    lib = align(read_ply(guided_pair["source"]), read_ply(guided_pair["target"]), opts)
    np.testing.assert_allclose(np.asarray(res["transform"]), lib.transform.matrix(), atol=1e-6)

    # The alternative was wrong: pairs picked on the child's page put it right. Also the
    # /refine spelling, and an Idempotency-Key replay.
    pairs = picked_pairs(guided_pair, seed=1)
    key = {"Idempotency-Key": "refine-pairs-1"}
    r = http.post(f"/v1/jobs/{child['id']}/refine", json={"point_pairs": pairs}, headers=key)
    assert r.status_code == 202, r.text
    grandchild = r.json()
    again = http.post(f"/v1/jobs/{child['id']}:refine", json={"point_pairs": pairs}, headers=key)
    assert again.json()["id"] == grandchild["id"] and again.headers["idempotent-replayed"] == "true"
    assert "init_transform" not in grandchild["options"] and grandchild["options"]["point_pairs"] == pairs
    done = wait_job(http, grandchild["id"], timeout=120)
    assert done["state"] == "succeeded", done
    assert rre_deg(done["result"]["transform"], guided_pair["gt"]) < 2.0
    assert done["result"]["parent_job"] == child["id"] and done["result"]["metrics"]["guidance"]["point_pairs"] == 4
    assert http.get(f"/v1/jobs/{child['id']}").json()["children"] == [grandchild["id"]]
    # result.json, as downloaded, says whose follow-up it is too
    assert http.get(f"/v1/jobs/{grandchild['id']}/artifacts/result.json").json()["parent_job"] == child["id"]


def test_refine_keeps_or_drops_the_parents_up_axes(http, assets, guided_pair):
    up = [DOWN.tolist(), (guided_pair["gt"].rotation @ DOWN).tolist()]
    parent = wait_job(http, job_json(http, assets, {**ALIGN, "up_axes": up}).json()["id"], timeout=120)
    assert parent["state"] == "succeeded", parent
    pairs = picked_pairs(guided_pair, seed=2)
    kept = http.post(f"/v1/jobs/{parent['id']}:refine", json={"point_pairs": pairs}).json()
    assert kept["options"]["up_axes"] == up
    dropped = http.post(f"/v1/jobs/{parent['id']}:refine", json={"point_pairs": pairs, "up_axes": None}).json()
    assert "up_axes" not in dropped["options"]
    assert http.get(f"/v1/jobs/{parent['id']}").json()["children"] == [kept["id"], dropped["id"]]
    for j in (kept, dropped):
        done = wait_job(http, j["id"], timeout=120)
        assert done["state"] == "succeeded" and rre_deg(done["result"]["transform"], guided_pair["gt"]) < 2.0


def test_refine_errors(http, stub, pair, parent):
    n_alt = len(parent["result"]["metrics"]["alternatives"])
    url = f"/v1/jobs/{parent['id']}:refine"
    children = http.get(f"/v1/jobs/{parent['id']}").json()["children"]
    body = assert_problem(http.post(url, json={"alternative": n_alt}), 422, "invalid-input")
    assert body["option"] == "alternative" and body["maximum"] == n_alt - 1
    assert assert_problem(http.post(url, json={"alternative": -1}), 422)["option"] == "alternative"
    assert assert_problem(http.post(url, json={"alternative": "1"}), 422)["option"] == "alternative"
    both = {"alternative": 0, "init_transform": np.eye(4).tolist()}
    assert "exactly one" in assert_problem(http.post(url, json=both), 422)["detail"]
    assert "exactly one" in assert_problem(http.post(url, json={"up_axes": [[0, 1, 0], [0, 1, 0]]}), 422)["detail"]
    bad_up = {"alternative": 0, "up_axes": [[0, 0, 0], [0, 1, 0]]}
    assert assert_problem(http.post(url, json=bad_up), 422)["option"] == "up_axes"
    assert_problem(http.post(url, json={"alternative": 0, "colour": 1}), 422)  # unknown field
    assert_problem(http.post(url, json={"alternative": 0}, headers=BOB), 404, "not-found")  # another owner
    assert_problem(http.post("/v1/jobs/job_nope:refine", json={"alternative": 0}), 404, "not-found")
    assert http.get(f"/v1/jobs/{parent['id']}").json()["children"] == children  # none of them made a job
    # A job still queued or running: 409, and nothing made.
    slow, _ = submit_slow_job(http, pair, 2)
    try:
        assert_problem(http.post(f"/v1/jobs/{slow['id']}:refine", json={"point_pairs": picked_pairs_any()}), 409)
        with pytest.raises(grpc.RpcError) as e:
            stub.RefineJob(pb.RefineRequest(job_id=slow["id"], alternative=0), metadata=AUTH)
        assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert http.get(f"/v1/jobs/{slow['id']}").json()["children"] == []
    finally:
        http.post(f"/v1/jobs/{slow['id']}:cancel")
    wait_job(http, slow["id"], timeout=60)


def picked_pairs_any() -> dict:
    pts = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    return {"source": pts, "target": pts}


# ------------------------------------------------------------------------------------ gRPC


@pytest.fixture
def stub(stack):
    ch = grpc.insecure_channel(stack["grpc"])
    yield pbg.AlignmentServiceStub(ch)
    ch.close()


def _pt(v) -> pb.Point:
    return pb.Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _header(assets, guidance: pb.Guidance | None = None, options=ALIGN) -> pb.SubmitRequest:
    h = pb.SubmitHeader(
        source_asset_ids=[assets["source"]], target_asset_id=assets["target"], options_json=json.dumps(options)
    )
    if guidance is not None:
        h.guidance.CopyFrom(guidance)
    return pb.SubmitRequest(header=h)


def _invalid(call) -> dict:
    with pytest.raises(grpc.RpcError) as e:
        call()
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, e.value
    return json.loads(dict(e.value.trailing_metadata())["gsa-problem"])


def test_grpc_guidance_and_refine(stub, assets, guided_pair, parent):
    up = pb.UpAxes(source=_pt(DOWN), target=_pt(guided_pair["gt"].rotation @ DOWN))
    job = stub.SubmitAlignment(iter([_header(assets, pb.Guidance(up_axes=up))]), metadata=AUTH)
    assert json.loads(job.options_json)["up_axes"][1] == pytest.approx(list(guided_pair["gt"].rotation @ DOWN))
    final = list(stub.WatchJob(pb.JobRef(job_id=job.id), metadata=AUTH, timeout=120))[-1]
    assert final.state == pb.JOB_STATE_SUCCEEDED, final.error
    assert rre_deg(np.reshape(final.transform.matrix, (4, 4)), guided_pair["gt"]) < 2.0
    assert json.loads(final.result_json)["metrics"]["guidance"]["up_axes"]

    # RefineJob from an alternative of the (HTTP) parent: linked both ways, visible over HTTP too.
    child = stub.RefineJob(pb.RefineRequest(job_id=parent["id"], alternative=0), metadata=AUTH)
    assert child.parent_job == parent["id"]
    assert child.id in stub.GetJob(pb.JobRef(job_id=parent["id"]), metadata=AUTH).children
    final = list(stub.WatchJob(pb.JobRef(job_id=child.id), metadata=AUTH, timeout=120))[-1]
    assert final.state == pb.JOB_STATE_SUCCEEDED and json.loads(final.result_json)["parent_job"] == parent["id"]
    # ... and from pairs, as Guidance.point_pairs
    pairs = picked_pairs(guided_pair, seed=3)
    pp = pb.PointPairs(source=[_pt(p) for p in pairs["source"]], target=[_pt(p) for p in pairs["target"]])
    child2 = stub.RefineJob(pb.RefineRequest(job_id=child.id, guidance=pb.Guidance(point_pairs=pp)), metadata=AUTH)
    final = list(stub.WatchJob(pb.JobRef(job_id=child2.id), metadata=AUTH, timeout=120))[-1]
    assert final.state == pb.JOB_STATE_SUCCEEDED, final.error
    assert final.parent_job == child.id and json.loads(final.result_json)["parent_job"] == child.id
    assert rre_deg(np.reshape(final.transform.matrix, (4, 4)), guided_pair["gt"]) < 2.0


def test_grpc_front_axes(stub, http, assets, guided_pair, front_parent):
    """Guidance.front_axes as the option front_axes (with up_axes), its INVALID_ARGUMENT naming it,
    and RefineJob replacing the parent's."""
    hints = up_and_front(guided_pair)
    up = pb.UpAxes(source=_pt(hints["up_axes"][0]), target=_pt(hints["up_axes"][1]))
    front = pb.FrontAxes(source=_pt(hints["front_axes"][0]), target=_pt(hints["front_axes"][1]))
    job = stub.SubmitAlignment(iter([_header(assets, pb.Guidance(up_axes=up, front_axes=front))]), metadata=AUTH)
    np.testing.assert_allclose(json.loads(job.options_json)["front_axes"], hints["front_axes"], atol=1e-12)
    # (the same job over HTTP ran in front_parent: cancelled here, only its options are under test)
    http.post(f"/v1/jobs/{job.id}:cancel")
    wait_job(http, job.id, timeout=120)

    alone = pb.Guidance(front_axes=front)
    problem = _invalid(lambda: stub.SubmitAlignment(iter([_header(assets, alone)]), metadata=AUTH))
    assert problem["option"] == "front_axes" and "needs up_axes" in problem["detail"]
    along_up = pb.Guidance(up_axes=up, front_axes=pb.FrontAxes(source=_pt(DOWN), target=front.target))
    problem = _invalid(lambda: stub.SubmitAlignment(iter([_header(assets, along_up)]), metadata=AUTH))
    assert problem["option"] == "front_axes" and "within 20 deg" in problem["detail"]
    twice = _header(assets, pb.Guidance(up_axes=up, front_axes=front), {**ALIGN, "front_axes": hints["front_axes"]})
    assert _invalid(lambda: stub.SubmitAlignment(iter([twice]), metadata=AUTH))["option"] == "front_axes"

    turned = pb.FrontAxes(source=front.source, target=_pt(-np.asarray(hints["front_axes"][1])))
    pairs = picked_pairs(guided_pair, seed=6)
    pp = pb.PointPairs(source=[_pt(p) for p in pairs["source"]], target=[_pt(p) for p in pairs["target"]])
    guidance = pb.Guidance(point_pairs=pp, front_axes=turned)
    child = stub.RefineJob(pb.RefineRequest(job_id=front_parent["id"], guidance=guidance), metadata=AUTH)
    options = json.loads(child.options_json)
    assert options["front_axes"][1] == pytest.approx([-v for v in hints["front_axes"][1]])
    assert options["up_axes"] == hints["up_axes"] and child.parent_job == front_parent["id"]
    stub.CancelJob(pb.JobRef(job_id=child.id), metadata=AUTH)
    wait_job(http, child.id, timeout=120)


def test_grpc_bad_guidance_is_invalid_argument(stub, assets, parent):
    zero_up = pb.Guidance(up_axes=pb.UpAxes(source=pb.Point(), target=pb.Point(y=1)))
    problem = _invalid(lambda: stub.SubmitAlignment(iter([_header(assets, zero_up)]), metadata=AUTH))
    assert problem["option"] == "up_axes" and "zero" in problem["detail"]
    short = pb.Guidance(init_transform=[1, 0, 0])
    assert _invalid(lambda: stub.SubmitAlignment(iter([_header(assets, short)]), metadata=AUTH))["option"] == (
        "init_transform"
    )
    scale = pb.Guidance(fixed_scale=0)
    assert _invalid(lambda: stub.SubmitAlignment(iter([_header(assets, scale)]), metadata=AUTH))["option"] == (
        "fixed_scale"
    )
    # the same hint in options_json and in guidance
    twice = _header(assets, pb.Guidance(fixed_scale=2), {**ALIGN, "fixed_scale": 2})
    assert _invalid(lambda: stub.SubmitAlignment(iter([twice]), metadata=AUTH))["option"] == "fixed_scale"
    in_json = _header(assets, None, {**ALIGN, "up_axes": [[0, 0, 0], [0, 1, 0]]})
    assert _invalid(lambda: stub.SubmitAlignment(iter([in_json]), metadata=AUTH))["option"] == "up_axes"
    # RefineJob: an alternative the result does not have, and no start at all
    n_alt = len(parent["result"]["metrics"]["alternatives"])
    req = pb.RefineRequest(job_id=parent["id"], alternative=n_alt)
    assert _invalid(lambda: stub.RefineJob(req, metadata=AUTH))["option"] == "alternative"
    assert (
        "exactly one"
        in _invalid(lambda: stub.RefineJob(pb.RefineRequest(job_id=parent["id"]), metadata=AUTH))["detail"]
    )
    with pytest.raises(grpc.RpcError) as e:
        stub.RefineJob(
            pb.RefineRequest(job_id=parent["id"], alternative=0), metadata=(("authorization", "Bearer key-bob"),)
        )
    assert e.value.code() == grpc.StatusCode.NOT_FOUND


def test_refine_in_embedded_mode(tmp_path, guided_pair):
    """The SQLite store (no Redis): concurrent refines of one parent all end up in its children."""
    from concurrent.futures import ThreadPoolExecutor

    from tests.service.conftest import service_env, start_api

    env = service_env(tmp_path, GSA_EMBEDDED_WORKERS=1)
    api, url, _ = start_api(tmp_path, env, name="embedded-guided")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = {}
            for k in ("source", "target"):
                with open(guided_pair[k], "rb") as fh:
                    ids[k] = c.post("/v1/assets", files={"file": (f"{k}.ply", fh)}).json()["id"]
            parent = wait_job(c, job_json(c, ids, ALIGN).json()["id"], timeout=120)
            assert parent["state"] == "succeeded", parent
            pairs = picked_pairs(guided_pair, seed=4)
            with ThreadPoolExecutor(4) as pool:
                made = list(
                    pool.map(lambda _: c.post(f"/v1/jobs/{parent['id']}:refine", json={"point_pairs": pairs}), range(4))
                )
            assert all(r.status_code == 202 for r in made), [r.text for r in made]
            children = sorted(r.json()["id"] for r in made)
            assert sorted(c.get(f"/v1/jobs/{parent['id']}").json()["children"]) == children
            done = wait_job(c, children[0], timeout=120)
            assert done["state"] == "succeeded" and done["result"]["parent_job"] == parent["id"]
            assert rre_deg(done["result"]["transform"], guided_pair["gt"]) < 2.0
            for j in children[1:]:
                wait_job(c, j, timeout=120)
    finally:
        api.stop()
