"""A scene pair (scene-scale registration) through the real service end to end, at CI size: two partial
captures of a generated room (~100k Gaussians each, their own Sim(3)) uploaded over HTTP,
one job asking for the aligned and merged models, the transform checked against the truth
and both artifacts read back. benchmarks/service/bench_service_scene.py runs the same at 2M."""

from __future__ import annotations

import numpy as np
import pytest

from tests.service.conftest import MAX_UPLOAD, wait_job

CAPTURE = 100_000  # SH 0: ~7 MB per PLY, under the harness's 8 MiB upload limit


@pytest.fixture(scope="module")
def scene_pair(tmp_path_factory):
    from gsa.io.ply import write_ply
    from gsa.synth import make_scene, scene_captures

    d = tmp_path_factory.mktemp("scene")
    rng = np.random.default_rng([7, 18])
    scene = make_scene(seed=1807, n_gaussians=int(CAPTURE / 0.6) + 1)
    cap = scene_captures(scene, rng, sizes=(CAPTURE, CAPTURE))
    src, tgt = write_ply(cap.source, d / "room_a.ply"), write_ply(cap.target, d / "room_b.ply")
    assert max(src.stat().st_size, tgt.stat().st_size) < MAX_UPLOAD
    return {"source": src, "target": tgt, "cap": cap}


def test_scene_pair_uploaded_aligned_and_merged(http, scene_pair, tmp_path):
    from gsa.io.ply import read_ply
    from gsa.metrics import rre_deg
    from gsa.sim3 import Sim3

    cap = scene_pair["cap"]
    ids = []
    for role in ("source", "target"):
        with open(scene_pair[role], "rb") as fh:
            r = http.post("/v1/assets", files={"file": (scene_pair[role].name, fh)})
        assert r.status_code == 201, r.text
        assert r.json()["n_gaussians"] == len(getattr(cap, role))
        ids.append(r.json()["id"])
    r = http.post(
        "/v1/jobs",
        json={"source": ids[0], "target": ids[1], "options": {"outputs": ["result", "aligned", "merged"], "seed": 0}},
    )
    assert r.status_code == 202, r.text
    job = wait_job(http, r.json()["id"], timeout=150)
    assert job["state"] == "succeeded", job
    assert job["progress"] == 1.0 and job["attempts"] == 1
    # Reading the inputs and storing the artifacts are stages of their own (a cancel stops them).
    metrics = http.get("/metrics").text
    assert 'gsa_stage_duration_seconds_count{stage="loading"}' in metrics
    assert 'gsa_stage_duration_seconds_count{stage="storing"}' in metrics

    # The transform is right: the scene protocol's success test (RRE < 2°, translation error at the
    # source's centroid < 2 % of the room's diagonal) and the scale within 1 %.
    res = job["result"]
    est = Sim3(float(res["scale"]), np.array(res["rotation"]), np.array(res["translation"]))
    truth = cap.truth
    centre = cap.source.means.mean(axis=0, dtype=np.float64)
    assert rre_deg(est.rotation, truth.rotation) < 2.0
    assert np.linalg.norm(est.apply(centre) - truth.apply(centre)) < 0.02 * cap.extent_target
    assert abs(est.scale / truth.scale - 1) < 0.01
    # The scene path's report is part of the typed result (service/api/results.py).
    from service.api.results import JobResult

    scene = JobResult.model_validate(res).metrics.scene
    assert scene is not None and isinstance(scene.ran, bool) and scene.reason

    # The artifacts load, and are the source moved by the job's transform and source + target.
    arts = {a["name"]: a for a in job["artifacts"]}
    models = {}
    for name in ("aligned.ply", "merged.ply"):
        d = http.get(arts[name]["href"])
        assert d.status_code == 200 and len(d.content) == arts[name]["size"]
        (tmp_path / name).write_bytes(d.content)
        models[name] = read_ply(tmp_path / name)
    aligned, merged = models["aligned.ply"], models["merged.ply"]
    source, target = read_ply(scene_pair["source"]), read_ply(scene_pair["target"])
    assert len(aligned) == len(source) and aligned.sh_degree == source.sh_degree
    tol = 1e-5 * cap.extent_target
    np.testing.assert_allclose(aligned.means, est.apply(source.means), atol=tol)
    assert len(merged) == len(source) + len(target)
    np.testing.assert_allclose(merged.means[: len(source)], aligned.means, atol=tol)
    np.testing.assert_array_equal(merged.means[len(source) :], target.means)

    # A converted download streams too, and a merged model may hold more than max_gaussians.
    r = http.get(arts["merged.ply"]["href"], params={"format": "splat"})
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content) == 32 * len(merged)


def test_a_merged_artifact_over_max_gaussians_still_converts(tmp_path, scene_pair):
    """The service wrote it: aligned source + target, each within GSA_MAX_GAUSSIANS."""
    import asyncio
    from types import SimpleNamespace

    from gsa.io.formats import read_model
    from service.models import Artifact
    from service.settings import Settings
    from service.storage import LocalStorage
    from service.worker.convert import Conversions

    storage = LocalStorage(tmp_path / "data")
    with open(scene_pair["source"], "rb") as fh:
        size = storage.put("jobs/j/t/merged.ply", fh)
    n = len(scene_pair["cap"].source)
    b = SimpleNamespace(storage=storage, settings=Settings(max_gaussians=n // 2 + 1))
    art = Artifact(name="merged.ply", key="jobs/j/t/merged.ply", size=size, content_type="application/x-ply")
    converted = asyncio.run(Conversions(1).converted(b, art, "spz"))  # in a child process
    (tmp_path / converted.name).write_bytes(b"".join(storage.open(converted.key)))
    assert converted.name == "merged.spz" and (tmp_path / converted.name).stat().st_size == converted.size
    assert len(read_model(tmp_path / converted.name)) == n
    b.settings = Settings(max_gaussians=n // 2 - 1)  # past twice the limit: refused, one clear problem
    with pytest.raises(Exception, match="exceeds the limit") as info:
        asyncio.run(Conversions(1).converted(b, art, "ply"))
    assert getattr(info.value, "status", None) == 422
