"""The job page's guide against a real API process (uvicorn, embedded worker, SQLite) and
headless Chromium (the guided path): "use this one" on an alternative, clicked point pairs and the
up-axis control each POST the page's refine route, which makes a follow-up job linked to the
parent; the page opens the follow-up's page, which polls its state and shows its result when
it is done. Also the route's own checks: the page's cookie, its origin, and the API's 422s."""

from __future__ import annotations

import time
from contextlib import contextmanager
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from gsa.geometry import axis_rotation
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.viewer.preview import read_splat
from tests.browser import browser_page, click_pairs, errors, spread_points, visible_in_both, wait_ready
from tests.service.conftest import ALICE, BOB, assert_problem, service_env, start_api, wait_job

SECRET = "test-view-secret"
# A confident answer lists its alternatives only when asked: the page steps through them.
ALIGN = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0, "renders": False, "alternatives": "always"}
# The chair's up (-y) onto the target's +z, then 130° about it (tests/test_viewer_guide.py).
TRUTH = Sim3(
    1.7, axis_rotation([0, 0, 1.0], np.radians(130)) @ axis_rotation([1.0, 0, 0], np.radians(-90)), [0.3, -0.2, 0.5]
)


@pytest.fixture(scope="module")
def guide_stack(tmp_path_factory):
    """An API with its embedded worker and one finished job on a chair and its moved copy (PLY:
    file coordinates are the internal ones), with alternatives and previews."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object

    tmp = tmp_path_factory.mktemp("view-guide")
    chair = make_object("chair", seed=5, n_gaussians=3000)
    write_ply(chair, tmp / "source.ply")
    write_ply(chair.transformed(TRUTH), tmp / "target.ply")
    api, url, _ = start_api(tmp, service_env(tmp, GSA_VIEW_SECRET=SECRET), name="view-guide")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = {}
            for k in ("source", "target"):
                with open(tmp / f"{k}.ply", "rb") as fh:
                    ids[k] = c.post("/v1/assets", files={"file": (f"{k}.ply", fh)}).json()["id"]
            job = c.post("/v1/jobs", json={"source": ids["source"], "target": ids["target"], "options": ALIGN}).json()
            parent = wait_job(c, job["id"], timeout=180)
            assert parent["state"] == "succeeded", parent
            assert parent["result"]["metrics"]["alternatives"], parent["result"]["metrics"]
            preview = c.get(f"/v1/jobs/{job['id']}/artifacts/preview/source.splat").content
        (tmp / "source.splat").write_bytes(preview)
        yield {"url": url, "parent": parent, "preview": read_splat(tmp / "source.splat")}
    finally:
        api.stop()


@contextmanager
def page_client(url: str, job_id: str):
    """A browser-like client (no API key) holding the job page's cookie."""
    with httpx.Client(base_url=url, timeout=30) as c:
        link = httpx.post(f"{url}/v1/jobs/{job_id}/view-link", headers=ALICE).json()["url"]
        assert c.get(link).status_code == 303
        yield c


def children(url: str, job_id: str) -> list[str]:
    return httpx.get(f"{url}/v1/jobs/{job_id}", headers=ALICE).json()["children"]


def test_refine_route_wants_the_pages_cookie_and_origin(guide_stack):
    url, parent = guide_stack["url"], guide_stack["parent"]
    route = f"/v1/jobs/{parent['id']}/view/refine"
    before = children(url, parent["id"])
    with page_client(url, parent["id"]) as c:
        assert_problem(c.post(route, json={"alternative": 0}), 403, "cross-origin")  # no Origin
        evil = {"Origin": "http://evil.example"}
        assert_problem(c.post(route, json={"alternative": 0}, headers=evil), 403, "cross-origin")
        same = {"Origin": url}
        # The API's checks and 422s, through the page's route.
        n_alt = len(parent["result"]["metrics"]["alternatives"])
        assert assert_problem(c.post(route, json={"alternative": n_alt}, headers=same), 422)["option"] == "alternative"
        assert assert_problem(c.post(route, json={"up_axes": [[0, 0, 0], [0, 0, 1]]}, headers=same), 422)["option"] == (
            "up_axes"
        )
        front_alone = {"up_axes": [[0, -1, 0], [0, 0, 1]], "front_axes": [[0, -1, 0], [1, 0, 0]]}
        body = assert_problem(c.post(route, json=front_alone, headers=same), 422)
        assert body["option"] == "front_axes" and "within 20 deg" in body["detail"], body
        assert_problem(c.post(route, json={"alternative": 0, "colour": 1}, headers=same), 422)
        # The page's state route: this job only.
        state = c.get(f"/v1/jobs/{parent['id']}/view/state")
        assert state.json() == {
            "id": parent["id"],
            "state": "succeeded",
            "stage": parent["stage"],
            "progress": 1.0,
            "terminal": True,
        }
        assert state.headers["cache-control"] == "no-store"
    assert_problem(httpx.post(url + route, json={"alternative": 0}, headers={"Origin": url}), 401)  # no cookie
    assert_problem(httpx.get(f"{url}/v1/jobs/{parent['id']}/view/state"), 401)
    assert_problem(httpx.post(url + route, json={"alternative": 0}, headers=BOB), 404)  # another owner
    assert children(url, parent["id"]) == before  # none of them made a job


def test_up_and_front_axes_through_the_pages_route(guide_stack):
    """The up-axis control with fronts (what the page sends, web/src/guide.js): the search again
    about the up axes, turning only where the fronts agree; the parent's other options kept."""
    url, parent = guide_stack["url"], guide_stack["parent"]
    # The chair's x across its up (-y); TRUTH turns it 130° about the target's +z, 40° from +y.
    hints = {"up_axes": [[0, -1, 0], [0, 0, 1]], "front_axes": [[1, 0, 0], [0, 1, 0]]}
    with page_client(url, parent["id"]) as c:
        r = c.post(f"/v1/jobs/{parent['id']}/view/refine", json=hints, headers={"Origin": url})
    assert r.status_code == 202, r.text
    child = r.json()["job"]
    assert {k: child["options"][k] for k in hints} == hints
    assert {k: v for k, v in child["options"].items() if k not in hints} == parent["options"]
    assert child["id"] in children(url, parent["id"])
    with httpx.Client(base_url=url, headers=ALICE, timeout=30) as api:
        done = wait_job(api, child["id"], timeout=180)
    assert done["state"] == "succeeded", done
    np.testing.assert_allclose(done["result"]["metrics"]["guidance"]["front_axes"], hints["front_axes"], atol=1e-9)
    assert rre_deg(np.asarray(done["result"]["rotation"]), TRUTH.rotation) < 5.0


def open_page(page, url: str, job_id: str) -> None:
    link = httpx.post(f"{url}/v1/jobs/{job_id}/view-link", headers=ALICE).json()["url"]
    page.goto(url + link)
    assert wait_ready(page)["error"] is None


def follow_up(page, url: str, parent_id: str, timeout: float = 180.0) -> dict:
    """After a guide control: the page opens the follow-up job's page, which polls until the job
    is done and then reloads to show its result. Returns the follow-up job (API)."""
    deadline = time.monotonic() + 30
    while not (path := urlsplit(page.url).path).endswith("/view") or f"/{parent_id}/" in path:
        assert time.monotonic() < deadline, f"the page stayed at {page.url}"
        page.wait_for_timeout(100)  # not time.sleep: the sync API learns of navigations inside its calls
    child_id = path.split("/")[3]
    from playwright.sync_api import Error as PlaywrightError

    deadline = time.monotonic() + timeout
    while True:
        try:  # the page reloads itself once: its context may be gone for a moment
            if page.evaluate("() => document.documentElement.dataset.viewer") == "ready":
                break
        except PlaywrightError:
            pass
        assert time.monotonic() < deadline, "the follow-up's page never showed its result"
        page.wait_for_timeout(250)
    assert f"refines job {parent_id}" in page.locator("header nav").inner_text()
    job = httpx.get(f"{url}/v1/jobs/{child_id}", headers=ALICE).json()
    assert job["state"] == "succeeded" and job["parent_job"] == parent_id, job
    assert child_id in children(url, parent_id)
    return job


@pytest.mark.slow
def test_use_this_one(guide_stack):
    url, parent = guide_stack["url"], guide_stack["parent"]
    alternatives = parent["result"]["metrics"]["alternatives"]
    with browser_page() as (page, messages):
        open_page(page, url, parent["id"])
        assert page.locator("#alt-use").is_disabled()  # the chosen pose is this job's result
        page.click("#alt-next")
        page.click("#alt-use")
        child = follow_up(page, url, parent["id"])
        # The service put the alternative's pose in the files' coordinates, as the result writer states it.
        np.testing.assert_allclose(child["options"]["init_transform"], alternatives[0]["file_transform"], atol=1e-9)
        assert child["result"]["metrics"]["guidance"]["start"]["from"] == "init_transform"
        assert errors(messages) == [], messages


@pytest.mark.slow
def test_point_pairs_and_up_axes(guide_stack):
    url, parent = guide_stack["url"], guide_stack["parent"]
    preview = guide_stack["preview"]
    with browser_page() as (page, messages):
        open_page(page, url, parent["id"])
        # Both models upright (each file's up), picking on (the views unlinked), the target turned
        # on its own to the side the source view shows: TRUTH turns the chair 130° about its up.
        page.select_option("#up-source", "-y")
        page.select_option("#up-target", "+z")
        page.click("#pick-toggle")
        page.locator("#view-target").focus()
        for _ in range(23):
            page.keyboard.press("ArrowLeft")
        pickable = preview["position"][preview["rgba"][:, 3] >= 40]
        candidates = spread_points(visible_in_both(page, pickable, TRUTH.apply), 12)
        moved = TRUTH.apply(pickable.astype(np.float64))
        radius = float(np.sqrt(((moved - moved.mean(0)) ** 2).sum(1).mean()))
        pairs = click_pairs(page, candidates, TRUTH.apply, 4, 0.02 * radius)
        assert page.locator("#pair-list li").count() == 4
        page.click("#pairs-submit")
        child = follow_up(page, url, parent["id"])
        sent = child["options"]["point_pairs"]
        np.testing.assert_allclose(sent["source"], [p["source"] for p in pairs], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(sent["target"], [p["target"] for p in pairs], rtol=1e-5, atol=1e-6)
        assert "init_transform" not in child["options"]
        assert child["result"]["metrics"]["guidance"]["point_pairs"] == 4
        assert rre_deg(np.asarray(child["result"]["rotation"]), TRUTH.rotation) < 2.0

        # Up axes alone: the search again, turning only about them, linked to the same parent.
        open_page(page, url, parent["id"])
        page.select_option("#up-source", "-y")
        page.select_option("#up-target", "+z")
        page.click("#up-submit")
        child = follow_up(page, url, parent["id"])
        assert child["options"]["up_axes"] == [[0, -1, 0], [0, 0, 1]]
        assert "init_transform" not in child["options"] and "point_pairs" not in child["options"]
        assert {k: v for k, v in child["options"].items() if k != "up_axes"} == parent["options"]
        assert rre_deg(np.asarray(child["result"]["rotation"]), TRUTH.rotation) < 5.0
        assert len(children(url, parent["id"])) >= 2
        assert errors(messages) == [], messages


@pytest.mark.slow
def test_known_scale_with_an_alternative(guide_stack):
    """The scale input: a bad value (0, -1, text) shows its message and sends nothing; a good one
    goes with "use this one" as fixed_scale, and the follow-up's result has that scale."""
    url, parent = guide_stack["url"], guide_stack["parent"]
    before = children(url, parent["id"])
    with browser_page() as (page, messages):
        open_page(page, url, parent["id"])
        page.click("#alt-next")
        for bad in ("0", "-1", "text"):
            page.fill("#scale-input", bad)
            page.click("#alt-use")
            assert page.locator("#scale-error").is_visible()
            assert "positive number" in page.locator("#scale-error").inner_text()
        assert page.evaluate("() => gsaViewer.guide.requests.length") == 0
        assert f"/{parent['id']}/view" in page.url
        assert children(url, parent["id"]) == before
        page.fill("#scale-input", "1.7")
        page.click("#alt-use")
        child = follow_up(page, url, parent["id"])
        assert child["options"]["fixed_scale"] == 1.7
        assert child["result"]["scale"] == pytest.approx(1.7, abs=1e-6)
        assert errors(messages) == [], messages
