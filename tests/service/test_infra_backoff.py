"""An attempt that fails on the service's infrastructure (here: the storage quota
is full) is requeued after a backoff (GSA_INFRA_RETRY_BASE_S, doubling), so an
outage longer than attempts x an attempt's time does not fail the job."""

from __future__ import annotations

import time

import httpx
import pytest

from tests.service.conftest import ALICE, service_env, start_api, wait_job, wait_until

pytestmark = pytest.mark.slow  # starts a server

QUICK = {"stages": ["coarse"], "coarse_iterations": 30, "seed": 0, "outputs": ["result"]}


def test_a_job_outlives_a_full_storage_quota_and_completes_once_space_frees(tmp_path, pair):
    sizes = sum(pair[k].stat().st_size for k in ("source", "target", "source2"))
    # Room for the two inputs and a filler upload, not for the job's result.json.
    env = service_env(
        tmp_path,
        GSA_STORAGE_QUOTA_BYTES=sizes + 200,
        GSA_MIN_FREE_BYTES=1,
        GSA_INFRA_RETRY_BASE_S=2,
        GSA_INFRA_RETRY_MAX_S=30,
    )
    api, url, _ = start_api(tmp_path, env, name="api-backoff")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            ids = {}
            for k in ("source", "target", "source2"):
                with open(pair[k], "rb") as fh:
                    r = c.post("/v1/assets", files={"file": (k + ".ply", fh)})
                assert r.status_code == 201, r.text
                ids[k] = r.json()["id"]
            r = c.post("/v1/jobs", json={"source": ids["source"], "target": ids["target"], "options": QUICK})
            assert r.status_code == 202, r.text
            jid = r.json()["id"]

            def requeued():
                j = c.get(f"/v1/jobs/{jid}").json()
                assert j["state"] != "failed", j
                return j if j["state"] == "queued" and j["attempts"] >= 1 else None

            first = wait_until(requeued, 60, 0.05, "the first attempt to hit the quota")
            assert first["error"] is None and first["stage"] == "requeued", first
            t_full = time.monotonic()
            # Keep the quota full for 6 s: without a backoff the three attempts (about
            # a second each) are all spent well within it and the job fails.
            while time.monotonic() - t_full < 6:
                j = c.get(f"/v1/jobs/{jid}").json()
                assert j["state"] in ("queued", "running"), j
                time.sleep(0.2)
            assert j["attempts"] < 3, j  # the 2 s + 4 s backoff leaves the last attempt for later
            assert c.delete(f"/v1/assets/{ids['source2']}").status_code == 204  # space frees
            done = wait_job(c, jid, timeout=60)
            assert done["state"] == "succeeded", done
            assert done["attempts"] >= 2 and done["error"] is None, done
            assert [a["name"] for a in done["artifacts"]] == ["result.json"], done
            print(f"quota full {time.monotonic() - t_full:.1f} s, succeeded on attempt {done['attempts']}")
    finally:
        api.stop()
