"""Broken image-set zips against a real deployment (uvicorn API, redis-server, a worker):
every defect (tests/zip_defects.py: entries lying about their sizes, local headers that
disagree with the directory, bad CRCs, symlinks, backslashes, NULs, encryption, ...) is
a 422 problem+json with an X-Request-Id — on POST /v1/assets, on a multipart job and
through `gsa submit` (one line naming the problem, exit 1) — never a 500; and nothing is
left behind. The validator is gsa.ziparchive, shared with the library."""

from __future__ import annotations

import subprocess

import pytest

from tests.service.conftest import PY, ROOT, assert_problem
from tests.zip_defects import cases, good

pytestmark = pytest.mark.slow  # starts servers and worker processes

CASES = cases()


@pytest.fixture(scope="module")
def http(stack):
    import httpx

    from tests.service.conftest import ALICE

    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        yield c


def _blobs(stack) -> set[str]:
    root = stack["tmp"] / "data"
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and "blobs" in p.parts}


@pytest.mark.parametrize("defect", list(CASES))
def test_broken_zip_upload_is_a_422(http, stack, defect):
    before = _blobs(stack)
    r = http.post("/v1/assets", files={"file": (f"{defect}.zip", CASES[defect], "application/zip")})
    body = assert_problem(r, 422, "invalid-input")
    assert r.headers.get("x-request-id"), r.headers
    assert body["detail"].startswith(f"{defect}.zip: "), body
    assert _blobs(stack) == before  # nothing stored


@pytest.mark.parametrize("defect", ["header-name-differs", "size-smaller-than-data", "size-larger-than-data"])
def test_broken_zip_in_a_multipart_job_is_a_422(http, pair, defect):
    with open(pair["target"], "rb") as t:
        r = http.post(
            "/v1/jobs",
            files=[("source", (f"{defect}.zip", CASES[defect], "application/zip")), ("target", ("t.ply", t))],
            data={"options": "{}"},
        )
    body = assert_problem(r, 422, "invalid-input")
    assert r.headers.get("x-request-id") and f"{defect}.zip" in body["detail"], (r.headers, body)


def test_a_good_zip_is_still_accepted(http):
    r = http.post("/v1/assets", files={"file": ("ok.zip", good(), "application/zip")})
    assert r.status_code == 201, r.text
    assert r.json()["kind"] == "images" and r.json()["n_images"] == 3


def test_gsa_submit_prints_the_problem_in_one_line(stack, pair, tmp_path):
    lie = tmp_path / "lie.zip"
    lie.write_bytes(CASES["size-smaller-than-data"])
    r = subprocess.run(
        [PY, "-m", "gsa.cli", "submit", str(lie), "--target", str(pair["target"]), "--server", stack["url"]]
        + ["--api-key", "key-alice"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 1, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith("gsa: error: Invalid input (422): lie.zip: entry 'v0.png'"), lines
    assert "request " in lines[0]  # the X-Request-Id, to find the server's log line
