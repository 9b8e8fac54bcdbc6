"""A many job's results page (N-way registration) against a real API process (embedded worker, SQLite) and
headless Chromium: every model in the reference frame with a toggle each, and the graph of its
edges. The marking of pruned and corrected edges is checked in tests/test_viewer_many.py."""

from __future__ import annotations

import json
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from tests.browser import browser_page, errors, wait_drawn, wait_ready
from tests.service.conftest import ALICE, service_env, start_api, wait_job

pytestmark = pytest.mark.slow  # starts a server and a browser

EDGE_OPTIONS = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0}


@pytest.fixture(scope="module")
def many_stack(tmp_path_factory):
    """An API with its embedded worker and one finished many job over three partial captures
    (1,500 Gaussians each) of one generated car, each under its own Sim(3)."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object, random_sim3
    from gsa.synth.variants import cut_by_plane

    tmp = tmp_path_factory.mktemp("view-many")
    rng = np.random.default_rng([0, 30])
    paths = []
    for k in range(3):
        m = cut_by_plane(make_object("car", seed=0, n_gaussians=1500, sample_seed=k), rng, keep=(0.8, 0.9))
        write_ply(m.transformed(random_sim3(rng, scale_range=(0.5, 2.0))), tmp / f"capture{k}.ply")
        paths.append(tmp / f"capture{k}.ply")
    api, url, _ = start_api(tmp, service_env(tmp, GSA_VIEW_SECRET="test-view-secret"))
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = []
            for p in paths:
                with open(p, "rb") as fh:
                    ids.append(c.post("/v1/assets", files={"file": (p.name, fh)}).json()["id"])
            job = c.post("/v1/many-jobs", json={"assets": ids, "options": EDGE_OPTIONS}).json()
            done = wait_job(c, job["id"], timeout=180)
        assert done["state"] == "succeeded", done
        yield {"url": url, "job": done}
    finally:
        api.stop()


def test_many_page_names_models_previews_and_edges(many_stack):
    job = many_stack["job"]
    names = {a["name"] for a in job["artifacts"]}
    assert names == {"many.json", "preview/model0.splat", "preview/model1.splat", "preview/model2.splat"}
    page = httpx.get(f"{many_stack['url']}/v1/jobs/{job['id']}/view", headers=ALICE).text
    config = json.loads(page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0])
    models = config["many"]["models"]
    assert [m["label"] for m in models] == ["capture0.ply", "capture1.ply", "capture2.ply"]
    assert [m["reference"] for m in models] == [True, False, False]
    assert [m["transform"] for m in models] == [m["transform"] for m in job["result"]["models"]]
    for k, m in enumerate(models):
        assert m["preview"] == f"/v1/jobs/{job['id']}/view/files/preview/model{k}.splat"
        f = httpx.get(many_stack["url"] + m["preview"], headers=ALICE)
        assert f.status_code == 200 and len(f.content) % 32 == 0 and len(f.content) >= 32 * 1000
    assert "capture0.ply (reference)" in page
    # The jobs list gives a many job its least confident model's confidence.
    jobs = httpx.get(f"{many_stack['url']}/v1/view/jobs", headers=ALICE).text
    least = min(m["confidence"] for m in job["result"]["models"])
    assert job["id"] in jobs and f"<td>{least:.3g}</td>" in jobs


def test_browser_shows_every_model_with_toggles_and_the_graph(many_stack, tmp_path):
    job = many_stack["job"]
    link = httpx.post(f"{many_stack['url']}/v1/jobs/{job['id']}/view-link", headers=ALICE).json()["url"]
    with browser_page() as (page, messages):
        page.goto(many_stack["url"] + link)
        assert urlsplit(page.url).path == f"/v1/jobs/{job['id']}/view"
        state = wait_ready(page)
        assert state["ready"] and state["error"] is None, state
        wait_drawn(page, "#view-many")
        boxes = page.locator("input[data-many-model]")
        assert boxes.count() == 3
        meshes = "() => Object.entries(gsaViewer.panes.many.meshes).filter(([k, m]) => m.visible).map(([k]) => k)"
        assert page.evaluate(meshes) == ["model0", "model1", "model2"]
        page.locator('input[data-many-model="1"]').set_checked(False)
        assert page.evaluate("() => gsaViewer.visible") == {
            "model0": True,
            "model1": False,
            "model2": True,
            "tint": True,
        }
        assert page.evaluate(meshes) == ["model0", "model2"]
        assert page.evaluate("() => gsaViewer.many.shown") == 2
        # The graph: three nodes (the reference ringed) and the job's three edges by verdict.
        assert page.locator("#many-graph g.node").count() == 3
        assert page.locator("#many-graph g.node.reference").count() == 1
        statuses = page.locator("#many-graph g.edge").evaluate_all("(gs) => gs.map((g) => g.dataset.status)")
        assert sorted(statuses) == sorted(e["status"] for e in job["result"]["edges"]) and len(statuses) == 3
        page.locator('input[data-many-model="1"]').set_checked(True)
        assert page.evaluate(meshes) == ["model0", "model1", "model2"]
        page.screenshot(path=str(tmp_path / "many-page.png"), full_page=True)
        assert errors(messages) == [], messages
