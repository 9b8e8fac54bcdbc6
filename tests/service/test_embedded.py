"""Embedded mode (no Redis): API + in-process worker on SQLite; restarts lose
no queued, running or finished job. Also the CLI verbs against it."""

from __future__ import annotations

import json
import subprocess

import httpx
import pytest

from tests.service.conftest import ALICE, PY, ROOT, service_env, start_api, submit_slow_job, wait_job

pytestmark = pytest.mark.slow  # starts servers and worker processes


def _cli(env, url, *args):
    return subprocess.run(
        [PY, "-m", "service.cli", *args, "--server", url, "--api-key", "key-alice"],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_embedded_restart_keeps_jobs_and_cli(tmp_path, pair):
    env = service_env(tmp_path, GSA_EMBEDDED_WORKERS=1)
    api, url, _ = start_api(tmp_path, env, name="embedded1")
    try:
        # CLI: submit --wait, status, fetch
        r = _cli(
            env,
            url,
            "submit",
            str(pair["source"]),
            "--target",
            str(pair["target"]),
            "--stages",
            "coarse",
            "--options",
            '{"outputs": ["result", "aligned", "merged"]}',
            "--wait",
        )
        assert r.returncode == 0, r.stderr
        first = json.loads(r.stdout)
        assert first["state"] == "succeeded"
        r = _cli(env, url, "status", first["id"])
        assert r.returncode == 0 and json.loads(r.stdout)["id"] == first["id"]
        r = _cli(env, url, "fetch", first["id"], "--out", str(tmp_path / "got"))
        assert r.returncode == 0, r.stderr
        assert (tmp_path / "got" / "aligned.ply").stat().st_size > 0
        assert json.loads((tmp_path / "got" / "result.json").read_text())["job_id"] == first["id"]
        r = _cli(env, url, "status", "job_nope")
        assert r.returncode == 1 and "404" in r.stderr

        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            slow, ids = submit_slow_job(http, pair, copies=3)
            wait_job(http, slow["id"], states=("running",), timeout=60)
            queued = http.post(
                "/v1/jobs",
                json={
                    "source": ids[0],
                    "target": ids[1],
                    "options": {"outputs": ["result"]},
                },
            ).json()
            assert http.get(f"/v1/jobs/{queued['id']}").json()["state"] == "queued"
        api.kill_tree()  # the API process dies mid-job, with a job queued behind it

        api, url, _ = start_api(tmp_path, env, name="embedded2")
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as http:
            old = http.get(f"/v1/jobs/{first['id']}").json()
            assert old["state"] == "succeeded" and old["result"]["transform"] == first["result"]["transform"]
            assert (
                http.get(f"/v1/jobs/{first['id']}/artifacts/aligned.ply").content
                == (tmp_path / "got" / "aligned.ply").read_bytes()
            )
            s = wait_job(http, slow["id"], timeout=120)
            assert s["state"] == "succeeded" and s["attempts"] == 2, s
            q = wait_job(http, queued["id"], timeout=60)
            assert q["state"] == "succeeded" and q["attempts"] == 1
    finally:
        api.stop()
