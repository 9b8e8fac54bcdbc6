"""The `gsa` client verbs as a user runs them (subprocesses): a server that is
down, fetching one named artifact, output into a pipe that closes early."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.service.conftest import PY, ROOT, free_port, submit_pair, submit_slow_job, wait_job

pytestmark = pytest.mark.slow  # starts servers and worker processes


def gsa(*args, server: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [PY, "-m", "gsa.cli", *args, "--server", server, "--api-key", "key-alice"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        **kw,
    )


@pytest.mark.parametrize("verb", [["status", "job_x"], ["wait", "job_x"], ["fetch", "job_x", "--out", "o", "a.json"]])
def test_server_down_is_one_clear_line(verb, tmp_path):
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    r = gsa(*verb, server=url)
    assert r.returncode not in (0, None), r
    assert r.stderr.strip() == f"gsa: cannot reach {url}: connection refused", r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""


@pytest.fixture(scope="module")
def finished_job(stack, http, pair) -> str:
    r = submit_pair(http, pair, {"stages": ["coarse"], "outputs": ["result", "aligned"]})
    assert r.status_code == 202, r.text
    job = wait_job(http, r.json()["id"], timeout=120)
    assert job["state"] == "succeeded", job
    return job["id"]


@pytest.fixture(scope="module")
def http(stack):
    import httpx

    from tests.service.conftest import ALICE

    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        yield c


def test_fetch_one_named_artifact(stack, finished_job, tmp_path):
    out = tmp_path / "out"
    r = gsa("fetch", finished_job, "--out", str(out), "result.json", server=stack["url"])
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["result.json"]
    assert json.loads((out / "result.json").read_text())
    assert r.stdout.strip() == str(out / "result.json")
    # names before the options, and no names (all artifacts), still work
    r = gsa("fetch", finished_job, "result.json", "--out", str(tmp_path / "o2"), server=stack["url"])
    assert r.returncode == 0 and (tmp_path / "o2" / "result.json").is_file(), r.stderr
    r = gsa("fetch", finished_job, "--out", str(tmp_path / "o3"), server=stack["url"])
    assert r.returncode == 0, r.stderr
    assert {p.name for p in (tmp_path / "o3").iterdir()} >= {"result.json", "aligned.ply"}
    # an unknown name is the server's 404 problem, not a traceback
    r = gsa("fetch", finished_job, "--out", str(tmp_path / "o4"), "nope.json", server=stack["url"])
    assert r.returncode == 1 and "Traceback" not in r.stderr and "404" in r.stderr, r.stderr


def test_fetch_of_a_job_without_results_says_so_and_fails(stack, http, pair, tmp_path):
    """It exited 0 having printed and written nothing."""

    slow, _ = submit_slow_job(http, pair, copies=3)  # long enough that the cancel lands mid-run
    job_id = slow["id"]
    wait_job(http, job_id, states=("running",), timeout=60)
    http.post(f"/v1/jobs/{job_id}:cancel")
    job = wait_job(http, job_id, timeout=120)
    assert job["state"] == "cancelled", job
    r = gsa("fetch", job_id, "--out", str(tmp_path / "o"), server=stack["url"])
    assert r.returncode == 1, r
    assert f"job {job_id} is {job['state']}" in r.stderr and "no results" in r.stderr, r.stderr
    assert r.stdout == "" and not (tmp_path / "o").exists()


def test_output_into_a_closed_pipe_is_quiet(stack, finished_job):
    # The reader is gone before we write a byte: every write fails with EPIPE.
    p = subprocess.Popen(
        [PY, "-m", "gsa.cli", "status", finished_job, "--server", stack["url"], "--api-key", "key-alice"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    p.stdout.close()
    err = p.stderr.read().decode()
    p.wait(120)
    assert "Traceback" not in err and "Broken pipe" not in err and "BrokenPipeError" not in err, err
    assert p.returncode == 141, (p.returncode, err)
    # as a user types it
    cmd = f"'{PY}' -m gsa.cli status {finished_job} --server {stack['url']} --api-key key-alice | head -1"
    r = subprocess.run(["bash", "-c", cmd], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.stdout == "{\n" and r.stderr == "", r
