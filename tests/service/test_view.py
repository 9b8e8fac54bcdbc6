"""Results pages of the service against a real API process (embedded worker, SQLite):
signed links and cookies, 401/403/404, escaping, previews; then headless Chromium on
the page of a finished job (ready, non-blank views, both tints, toggles, no console errors)."""

from __future__ import annotations

import html
import json
import time
from urllib.parse import urlsplit

import httpx
import pytest

from service.api.view_links import sign
from tests.browser import browser_page, errors, wait_colours, wait_drawn, wait_ready
from tests.service.conftest import ALICE, BOB, assert_problem, service_env, start_api, wait_job

SECRET = "test-view-secret"
EVIL = '<img src=x onerror="alert(1)">&.ply'


@pytest.fixture(scope="module")
def view_stack(tmp_path_factory, pair):
    """An API with its embedded worker, one finished single-model job (uploaded under a
    hostile file name) and one finished two-model job."""
    tmp = tmp_path_factory.mktemp("view")
    api, url, _ = start_api(tmp, service_env(tmp, GSA_VIEW_SECRET=SECRET))
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            with open(pair["source"], "rb") as s, open(pair["target"], "rb") as t:
                files = [("source", (EVIL, s)), ("target", ("target.ply", t))]
                single = c.post("/v1/jobs", files=files, data={"options": json.dumps({"renders": False})}).json()
            ids = {}
            for k in ("source", "source2", "target"):
                with open(pair[k], "rb") as fh:
                    ids[k] = c.post("/v1/assets", files={"file": (f"{k}.ply", fh)}).json()["id"]
            multi = c.post(
                "/v1/jobs",
                json={
                    "sources": [ids["source"], ids["source2"]],
                    "target": ids["target"],
                    "options": {"renders": False},
                },
            ).json()
            plain = c.post(
                "/v1/jobs", json={"source": ids["source"], "target": ids["target"], "options": {"outputs": ["result"]}}
            ).json()
            done = [wait_job(c, j["id"], timeout=180) for j in (single, multi, plain)]
        assert [d["state"] for d in done] == ["succeeded"] * 3, done
        yield {"url": url, "single": done[0], "multi": done[1], "plain": done[2]}
    finally:
        api.stop()


def open_link(url: str, job_id: str, headers=ALICE) -> tuple[httpx.Client, str]:
    """A cookie-keeping client (no API key) that has opened the job's signed link."""
    link = httpx.post(f"{url}/v1/jobs/{job_id}/view-link", headers=headers).json()
    c = httpx.Client(base_url=url, timeout=30)
    r = c.get(link["url"])
    assert r.status_code == 303 and r.headers["location"] == f"/v1/jobs/{job_id}/view", r.text
    cookie = r.headers["set-cookie"]
    assert "HttpOnly" in cookie and f"Path=/v1/jobs/{job_id}/view" in cookie and "samesite=lax" in cookie.lower()
    return c, link["url"]


def test_signed_link_cookie_page_and_files(view_stack):
    job = view_stack["single"]
    c, link = open_link(view_stack["url"], job["id"])
    try:
        assert "token=" in link and "key-alice" not in link
        page = c.get(f"/v1/jobs/{job['id']}/view")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "script-src 'self'" in page.headers["content-security-policy"]
        assert page.headers["referrer-policy"] == "no-referrer"
        # Every preview the page names is served to the cookie, and is whole .splat records.
        for kind in ("source", "target", "aligned"):
            f = c.get(f"/v1/jobs/{job['id']}/view/files/preview/{kind}.splat")
            assert f.status_code == 200 and len(f.content) % 32 == 0 and len(f.content) >= 32 * 1000
            assert f"/view/files/preview/{kind}.splat" in page.text
        assert c.get("/v1/view/static/viewer.js").status_code == 200
        # The cookie opens only this job's pages: the API itself still wants a key.
        assert_problem(c.get(f"/v1/jobs/{job['id']}"), 401)
    finally:
        c.close()


def test_hostile_file_name_is_escaped(view_stack):
    job = view_stack["single"]
    page = httpx.get(f"{view_stack['url']}/v1/jobs/{job['id']}/view", headers=ALICE).text
    config = page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0]
    label = json.loads(config)["results"][0]["label"]  # the name as uploaded (httpx quotes '"' as %22)
    assert label.startswith("<img src=x onerror=") and label.endswith(">&.ply") and "<" not in config
    assert "<img src=x" not in page and html.escape(label) in page


def test_wrong_expired_and_foreign_links(view_stack):
    url, job, other = view_stack["url"], view_stack["single"], view_stack["multi"]
    page = f"{url}/v1/jobs/{job['id']}/view"
    assert_problem(httpx.get(page), 401)  # no link, no cookie
    good = httpx.post(f"{page}-link", headers=ALICE).json()["url"]
    token = good.split("token=", 1)[1]
    tampered = token[:-2] + ("AA" if token[-2:] != "AA" else "BB")
    assert_problem(httpx.get(page, params={"token": tampered}), 403, "link-invalid")
    assert_problem(httpx.get(page, params={"token": "garbage"}), 403, "link-invalid")
    # A link for one job does not open another, even of the same owner.
    assert_problem(httpx.get(f"{url}/v1/jobs/{other['id']}/view", params={"token": token}), 403)
    expired, _ = sign(SECRET, f"job:{job['id']}", "alice", -5)
    assert_problem(httpx.get(page, params={"token": expired}), 401, "link-expired")
    assert_problem(httpx.get(page, cookies={"gsa_view": expired}), 401, "link-expired")
    # Another owner: no link for Alice's job, and Bob's own signature does not open it.
    assert_problem(httpx.post(f"{page}-link", headers=BOB), 404)
    bobs, _ = sign(SECRET, f"job:{job['id']}", "bob", 60)
    assert_problem(httpx.get(page, params={"token": bobs}), 404)
    assert_problem(httpx.get(f"{page}/files/preview/source.splat", cookies={"gsa_view": bobs}), 404)
    assert_problem(httpx.get(page, headers={"Authorization": "Bearer nope"}), 401)


def test_jobs_list_for_operators(view_stack):
    url = view_stack["url"]
    link = httpx.post(f"{url}/v1/view-link", headers=ALICE).json()
    assert link["expires_at"] > time.time() + 60
    with httpx.Client(base_url=url, timeout=30, follow_redirects=True) as c:
        page = c.get(link["url"])
        assert page.status_code == 200 and urlsplit(str(page.url)).query == ""
        for job in (view_stack["single"], view_stack["multi"]):
            assert job["id"] in page.text
        assert "succeeded" in page.text and EVIL not in page.text
        # Its links open each job's page.
        first = page.text.split('<a href="', 1)[1].split('"', 1)[0].replace("&amp;", "&")
        assert c.get(first).status_code == 200
    assert_problem(httpx.get(f"{url}/v1/view/jobs"), 401)
    bob = httpx.post(f"{url}/v1/view-link", headers=BOB).json()["url"]
    bob_page = httpx.get(url + bob, follow_redirects=True)
    assert view_stack["single"]["id"] not in bob_page.text


def test_multi_model_page_names_every_source(view_stack):
    job = view_stack["multi"]
    page = httpx.get(f"{view_stack['url']}/v1/jobs/{job['id']}/view", headers=ALICE).text
    config = json.loads(page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0])
    assert [r["label"] for r in config["results"]] == ["source.ply", "source2.ply"]
    assert [r["preview"]["aligned"].rsplit("/files/", 1)[1] for r in config["results"]] == [
        "s0/preview/aligned.splat",
        "s1/preview/aligned.splat",
    ]


def test_job_without_previews_still_shows_its_numbers(view_stack):
    job = view_stack["plain"]
    page = httpx.get(f"{view_stack['url']}/v1/jobs/{job['id']}/view", headers=ALICE).text
    config = json.loads(page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0])
    assert config["results"][0]["preview"] == {}  # the viewer says so instead of loading
    assert "Sim(3)" in page and "confidence" in page and "Confident" in page


@pytest.mark.slow
def test_browser_renders_the_job_page(view_stack, tmp_path):
    job = view_stack["multi"]
    link = httpx.post(f"{view_stack['url']}/v1/jobs/{job['id']}/view-link", headers=ALICE).json()["url"]
    with browser_page() as (page, messages):
        page.goto(view_stack["url"] + link)
        assert urlsplit(page.url).path == f"/v1/jobs/{job['id']}/view" and "token" not in page.url
        state = wait_ready(page)
        assert state["ready"] and state["error"] is None and state["firstFrameMs"] > 0, state
        for pane in ("source", "target", "overlay"):
            wait_drawn(page, f"#view-{pane}")
        # Toggles: each model of the overlay on and off, each in its own tint.
        boxes = {k: page.locator(f'input[data-model="{k}"]') for k in ("target", "source0", "source1")}
        assert len(boxes) == page.locator("input[data-model]").count()
        boxes["source0"].set_checked(False)  # source0 lies exactly on the target (a moved copy)
        both = wait_colours(page, "#view-overlay", lambda c: c["blue"] > 0.003 and c["magenta"] > 0.003)
        page.screenshot(path=str(tmp_path / "job-page.png"))
        boxes["target"].set_checked(False)
        wait_colours(page, "#view-overlay", lambda c: c["blue"] < 0.0005 and c["magenta"] > 0.003)
        boxes["source1"].set_checked(False)
        boxes["source0"].set_checked(True)
        wait_colours(page, "#view-overlay", lambda c: c["orange"] > 0.01 and c["blue"] + c["magenta"] < 0.0005)
        assert both["green"] < 0.0005, both  # tinted: none of the car's own green
        page.locator("#toggle-tint").set_checked(False)
        wait_colours(page, "#view-overlay", lambda c: c["green"] > 0.003)  # the natural colours
        # The source view shows the source picked; the up axis reorients all three views.
        page.select_option("#pick-source", "1")
        shown = "() => Object.entries(gsaViewer.panes.source.meshes).filter(([k, m]) => m.visible).map(([k]) => k)"
        assert page.evaluate(shown) == ["source1"]
        before = page.evaluate("() => gsaViewer.panes.target.camera.position.toArray()")
        page.select_option("#pick-up", "+y")
        wait_drawn(page, "#view-target")
        assert page.evaluate("() => gsaViewer.panes.target.camera.position.toArray()") != before
        # A job made without previews: the page says so, the viewer does not fail.
        plain = view_stack["plain"]["id"]
        page.goto(
            view_stack["url"]
            + httpx.post(f"{view_stack['url']}/v1/jobs/{plain}/view-link", headers=ALICE).json()["url"]
        )
        assert wait_ready(page)["error"] is None
        assert page.evaluate("() => document.documentElement.dataset.viewer") == "no-preview"
        assert "no 3D previews" in page.locator("#viewer-status").inner_text()
        assert errors(messages) == [], messages
