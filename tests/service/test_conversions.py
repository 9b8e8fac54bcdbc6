"""Artifacts converted on request (`?format=`): in a child process, at most
GSA_MAX_CONVERSIONS at once (then 503 conversions-busy with Retry-After), kept in storage and
served like any artifact (ETag, If-None-Match, Range, If-Range, HEAD); the API's memory stays flat.
Real uvicorn processes (embedded and with Redis + a worker) over HTTP."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import httpx
import numpy as np
import pytest

from gsa.io.formats import read_model
from tests.service.conftest import ALICE, assert_problem, service_env, start_api, start_worker, wait_job
from tests.service.harness import rss_bytes

pytestmark = pytest.mark.slow  # starts servers and worker processes


def _run_job(c: httpx.Client, source: Path, target: Path, outputs: list[str]) -> dict:
    with open(source, "rb") as s, open(target, "rb") as t:
        r = c.post(
            "/v1/jobs",
            files=[("source", ("source.ply", s)), ("target", ("target.ply", t))],
            data={"options": json.dumps({"stages": ["coarse"], "outputs": outputs})},
        )
    assert r.status_code == 202, r.text
    done = wait_job(c, r.json()["id"], timeout=300)
    assert done["state"] == "succeeded", done
    return {a["name"]: a for a in done["artifacts"]}


def _concurrently(fn, args: list) -> list:
    out: list = [None] * len(args)

    def run(i):
        out[i] = fn(args[i])

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(args))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    return out


@pytest.fixture(scope="module", params=["embedded", "redis"])
def deployment(request, tmp_path_factory, redis_url):
    """One conversion slot, and a short wait for it, so that a second conversion is refused."""
    tmp = tmp_path_factory.mktemp(f"conv-{request.param}")
    extra = dict(GSA_MAX_CONVERSIONS=1, GSA_CONVERSION_WAIT_S=0.3, GSA_MAX_UPLOAD_BYTES=200 * 2**20)
    if request.param == "redis":
        extra.update(GSA_REDIS_URL=redis_url + "/8", GSA_QUEUE_NAME="conversions")
    env = service_env(tmp, **extra)
    api, url, _ = start_api(tmp, env, name="api-conv")
    worker = start_worker(tmp, env, name="worker-conv") if request.param == "redis" else None
    try:
        yield {"url": url, "api": api, "tmp": tmp, "mode": request.param}
    finally:
        if worker is not None:
            worker.stop()
        api.stop()


@pytest.fixture(scope="module")
def small(deployment, pair):
    with httpx.Client(base_url=deployment["url"], headers=ALICE, timeout=120) as c:
        return _run_job(c, pair["source"], pair["target"], ["result", "aligned", "merged"])


def test_a_conversion_is_kept_and_served_like_any_artifact(deployment, small, tmp_path):
    href = small["aligned.ply"]["href"]
    with httpx.Client(base_url=deployment["url"], headers=ALICE, timeout=120) as c:
        first = c.get(href, params={"format": "spz"})
        assert first.status_code == 200, first.text
        etag = first.headers["etag"]
        assert first.headers["accept-ranges"] == "bytes" and first.headers["last-modified"]
        assert first.headers["content-disposition"] == 'attachment; filename="aligned.spz"'
        assert int(first.headers["content-length"]) == len(first.content)
        (tmp_path / "a.spz").write_bytes(first.content)
        assert read_model(tmp_path / "a.spz").metadata["format"] == "spz"
        # Kept in storage beside the job's artifacts, and served from there the next time.
        kept = list((deployment["tmp"] / "data" / "blobs").rglob("conv/*/aligned.spz"))
        assert len(kept) == 1 and kept[0].read_bytes() == first.content
        stamp = kept[0].stat().st_mtime_ns
        again = c.get(href, params={"format": "spz"})
        assert again.content == first.content and again.headers["etag"] == etag
        assert kept[0].stat().st_mtime_ns == stamp  # not converted again
        # Another format is another file with another ETag.
        splat = c.get(href, params={"format": "splat"})
        assert splat.status_code == 200 and splat.headers["etag"] != etag
        # Conditional and partial requests work as for every artifact.
        assert c.get(href, params={"format": "spz"}, headers={"If-None-Match": etag}).status_code == 304
        part = c.get(href, params={"format": "spz"}, headers={"Range": "bytes=10-99"})
        assert part.status_code == 206 and part.content == first.content[10:100]
        assert part.headers["content-range"] == f"bytes 10-99/{len(first.content)}"
        stale = c.get(href, params={"format": "spz"}, headers={"Range": "bytes=10-99", "If-Range": '"0-1"'})
        assert stale.status_code == 200 and stale.content == first.content
        past = c.get(href, params={"format": "spz"}, headers={"Range": f"bytes={len(first.content)}-"})
        assert_problem(past, 416, "range-not-satisfiable")
        head = c.head(href, params={"format": "spz"})
        assert head.status_code == 200 and head.headers["etag"] == etag
        assert int(head.headers["content-length"]) == len(first.content)
        # Still 422 for what cannot convert.
        assert_problem(c.get(href, params={"format": "obj"}), 422, "invalid-input")
        assert_problem(c.get(small["result.json"]["href"], params={"format": "spz"}), 422, "invalid-input")


def test_conversions_past_the_limit_are_503_with_retry_after(deployment, small):
    href = small["merged.ply"]["href"]
    fmts = ["glb", "ksplat", "compressed-ply", "sog"]
    with httpx.Client(base_url=deployment["url"], headers=ALICE, timeout=120) as c:
        answers = _concurrently(lambda f: c.get(href, params={"format": f}), fmts)
        codes = sorted(r.status_code for r in answers)
        # One slot and a 0.3 s wait: a child takes longer than that just to start.
        assert codes.count(200) >= 1 and codes.count(503) >= 1, codes
        for r in answers:
            if r.status_code == 503:
                body = assert_problem(r, 503, "conversions-busy")
                assert int(r.headers["retry-after"]) >= 1 and "1 conversion" in body["detail"]
                assert r.headers["x-request-id"]
        # Concurrent requests for one conversion share it: they need no slot of their own.
        same = _concurrently(lambda _: c.get(href, params={"format": "splat"}), range(4))
        assert [r.status_code for r in same] == [200] * 4, [r.text for r in same]
        assert len({r.content for r in same}) == 1
        # A refused one succeeds when retried once the slot is free.
        for f in fmts:
            assert c.get(href, params={"format": f}).status_code == 200


@pytest.fixture(scope="module")
def large(tmp_path_factory):
    """A 250k-Gaussian SH-3 pair (62 MB a PLY): its merged model is 500k Gaussians, 124 MB."""
    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    d = tmp_path_factory.mktemp("large")
    m = make_object("bus", seed=2, n_gaussians=250_000, sh_degree=3)
    write_ply(m, d / "source.ply")
    write_ply(m.transformed(Sim3(1.2, np.eye(3), np.array([0.3, 0.0, -0.2]))), d / "target.ply")
    return d


def test_the_api_memory_stays_flat_during_conversions(deployment, large):
    """Before: each conversion read the model into the API process (one copy, plus the
    writer's), so three at once of a 124 MB merged model took hundreds of MB more."""
    if deployment["mode"] != "embedded":
        pytest.skip("one mode is enough: the conversion code is the same in both")
    pid = deployment["api"].p.pid
    with httpx.Client(base_url=deployment["url"], headers=ALICE, timeout=300) as c:
        arts = _run_job(c, large / "source.ply", large / "target.ply", ["merged"])
        href = arts["merged.ply"]["href"]
        # The job ran in this process (embedded mode): start the peak afresh.
        Path(f"/proc/{pid}/clear_refs").write_text("5")
        before = rss_bytes(pid, "VmHWM")
        answers = _concurrently(lambda _: c.get(href, params={"format": "splat"}), range(3))
        answers += [c.get(href, params={"format": "spz"})]
        grown = rss_bytes(pid, "VmHWM") - before
    assert [r.status_code for r in answers] == [200] * 4, [r.text[:300] for r in answers]
    assert len(answers[0].content) == 32 * 500_000
    assert grown < 40 * 2**20, f"the API's peak grew by {grown / 2**20:.0f} MB"
